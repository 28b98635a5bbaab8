//! Checks what an EXR file claims before anything is decoded.
//!
//! A header is a promise about sizes: the data window, the channels, the
//! compression. The `exr` crate believes it and allocates the decoded image
//! (and, inside DWA chunks, buffers sized by counters in the compressed
//! stream) before it finds out that the file cannot hold that much. A 313-byte
//! file can claim a 65535 x 65535 window; an allocation that cannot succeed
//! aborts the process. So every claim is checked here first, against:
//! - sane limits on channels, sides and pixels ([`ReadLimits`]);
//! - the memory budget (the device's memory limit, else the machine's memory);
//! - the file's own size: each compression has a bound on how many bytes one
//!   stored byte can decompress to ([`expansion_bound`]), so a file of `n`
//!   bytes cannot legitimately hold more than about `n * bound` decoded bytes;
//! - for DWA chunks, the counters of each chunk's leader against the size of
//!   the block they belong to;
//! - one block (a tile, or a chunk of scan lines) against its part and the
//!   budget: the decoder reads a chunk into a buffer of up to the block's
//!   size, and a 2 KB file could claim 8 x 33554625-pixel tiles (a 1.7 GB
//!   buffer; found by the `exr_read` fuzz target).
//!
//! What passes can still be corrupt; the decoder then fails with an error, and
//! the allocations it makes on the way are bounded by the checked claims.

use std::io::Cursor;

use exr::block::chunk::CompressedBlock;
use exr::compression::Compression;
use exr::meta::header::Header;
use exr::meta::BlockDescription;

/// Limits on what one EXR file may claim.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub struct ReadLimits {
    /// Most bytes the decoded pixels of all parts may take; 0 = the memory
    /// of this machine ([`crate::device::machine_memory`], the budget a
    /// device without `memory_limit` uses).
    pub max_bytes: usize,
    /// Most channels in the whole file.
    pub max_channels: usize,
    /// Most pixels of one part's data window.
    pub max_pixels: usize,
    /// Longest side of a data window.
    pub max_side: usize,
}

/// Channels a file may have by default: far above a many-AOV render
/// (a few hundred), far below what exhausts memory on a small frame.
pub const MAX_CHANNELS: usize = 4096;
/// Pixels of one part's data window by default (a 32768 x 32768 frame).
pub const MAX_PIXELS: usize = 1 << 30;
/// Longest side by default.
pub const MAX_SIDE: usize = 1 << 20;

impl Default for ReadLimits {
    fn default() -> ReadLimits {
        ReadLimits {
            max_bytes: 0,
            max_channels: MAX_CHANNELS,
            max_pixels: MAX_PIXELS,
            max_side: MAX_SIDE,
        }
    }
}

impl ReadLimits {
    /// Limits with the byte budget of a device's `memory_limit` (0 = none set:
    /// the memory available).
    pub fn with_memory_limit(memory_limit: usize) -> ReadLimits {
        ReadLimits {
            max_bytes: memory_limit,
            ..ReadLimits::default()
        }
    }

    /// The byte budget in effect now, with where it comes from.
    pub fn budget(&self) -> (usize, &'static str) {
        if self.max_bytes > 0 {
            (self.max_bytes, "the memory limit")
        } else {
            (
                crate::device::machine_memory(),
                "the memory of this machine",
            )
        }
    }
}

/// The most bytes one stored byte of pixel data can decompress to, per
/// compression, with margin:
/// - none: 1;
/// - RLE: a 2-byte run gives at most 128 bytes;
/// - ZIP/ZIPS (deflate, at most ~1032:1), PIZ (Huffman with 8-bit run codes,
///   at most ~453:1 on 16-bit values), PXR24 (deflate of 24-bit floats,
///   ~1376:1 on 32-bit samples): 2048;
/// - B44/B44A: a 4x4 block of halves (32 bytes) from 14 or 3 bytes: 11;
/// - DWAA/DWAB: one DC value per 8x8 block (128 bytes of halves) after
///   deflate, about 66000:1 before the chunk's own overhead: 131072 (the
///   counters of each chunk are checked on their own as well);
/// - anything else (not decodable here anyway): 131072.
pub fn expansion_bound(c: Compression) -> usize {
    match c {
        Compression::Uncompressed => 1,
        Compression::RLE => 64,
        Compression::ZIP1 | Compression::ZIP16 | Compression::PIZ | Compression::PXR24 => 2048,
        Compression::B44 | Compression::B44A => 11,
        _ => 131072,
    }
}

/// Decoded bytes of a part's largest level (what the reader allocates), or
/// `None` when the arithmetic overflows.
fn decoded_bytes(h: &Header) -> Option<usize> {
    let (w, ht) = (h.layer_size.0, h.layer_size.1);
    let mut total = 0usize;
    for c in &h.channels.list {
        let sx = c.sampling.0.max(1);
        let sy = c.sampling.1.max(1);
        let n = w.div_ceil(sx).checked_mul(ht.div_ceil(sy))?;
        total = total.checked_add(n.checked_mul(c.sample_type.bytes_per_sample())?)?;
    }
    Some(total)
}

fn mib(n: usize) -> String {
    format!("{:.1} MiB", n as f64 / (1024.0 * 1024.0))
}

/// Why a file was refused.
#[derive(Debug, Clone, PartialEq, Eq)]
pub enum Refusal {
    /// The claims exceed the memory budget (an out-of-memory error).
    Memory(String),
    /// The file is malformed or claims more than it can hold.
    Invalid(String),
}

impl From<String> for Refusal {
    fn from(m: String) -> Refusal {
        Refusal::Invalid(m)
    }
}

/// Bytes one block may take whatever its part's size (a 1024 x 1024 tile
/// of four 32-bit channels is 16 MiB).
const BLOCK_FLOOR: usize = 64 << 20;

/// Checks the headers of `bytes` (a whole EXR file) against `limits` and the
/// file's size, then the chunk leaders of DWA parts. The message names the
/// part and the claim; the caller adds file and frame.
pub fn check(bytes: &[u8], limits: &ReadLimits) -> Result<(), Refusal> {
    let reader = exr::block::read(Cursor::new(bytes), true).map_err(|e| format!("{e}"))?;
    let headers = reader.headers().to_vec();
    let (budget, budget_name) = limits.budget();
    if bytes.len() > budget {
        return Err(Refusal::Memory(format!(
            "the file is {} but {budget_name} is {}",
            mib(bytes.len()),
            mib(budget)
        )));
    }
    let channels: usize = headers.iter().map(|h| h.channels.list.len()).sum();
    if channels > limits.max_channels {
        return Err(Refusal::Invalid(format!(
            "{channels} channels, more than the {} this reader accepts",
            limits.max_channels
        )));
    }
    let mut total = 0usize;
    let mut stored_need = 0usize;
    for (i, h) in headers.iter().enumerate() {
        let part = part_name(h, i);
        if h.deep {
            return Err(format!("{part}: deep data is not supported").into());
        }
        let (w, ht) = (h.layer_size.0, h.layer_size.1);
        let pixels = w.saturating_mul(ht);
        if w > limits.max_side || ht > limits.max_side || pixels > limits.max_pixels {
            return Err(Refusal::Invalid(format!(
                "{part}: data window {w}x{ht} is larger than the {}x{} / {} pixels this reader accepts",
                limits.max_side, limits.max_side, limits.max_pixels
            )));
        }
        let part_bytes = decoded_bytes(h).ok_or_else(|| {
            format!("{part}: data window {w}x{ht} with these channels overflows the address space")
        })?;
        // One block, as the decoder sizes its read buffer for it: a tile
        // may be larger than a small image, but not by more than
        // `BLOCK_FLOOR`; a chunk of scan lines (up to 256 for DWAB) of a
        // short wide image only within the budget.
        let (bw, bh, tiles) = match h.blocks {
            BlockDescription::Tiles(t) => (t.tile_size.0, t.tile_size.1, true),
            BlockDescription::ScanLines => (w, h.compression.scan_lines_per_block(), false),
        };
        let block = bw
            .saturating_mul(bh)
            .saturating_mul(h.channels.bytes_per_pixel);
        if block > budget || (tiles && block > part_bytes.max(BLOCK_FLOOR)) {
            return Err(Refusal::Invalid(format!(
                "{part}: {} of {bw}x{bh} pixels ({} a block) for a {w}x{ht} data window \
                 (corrupt header)",
                if tiles { "tiles" } else { "scan-line blocks" },
                mib(block)
            )));
        }
        total = total.saturating_add(part_bytes);
        stored_need = stored_need.saturating_add(part_bytes / expansion_bound(h.compression));
    }
    if total > budget {
        return Err(Refusal::Memory(format!(
            "the header claims {} of pixels, more than {budget_name} ({})",
            mib(total),
            mib(budget)
        )));
    }
    if stored_need > bytes.len() {
        return Err(Refusal::Invalid(format!(
            "the header claims {} of pixels ({}), which a file of {} bytes cannot hold \
             (truncated file or corrupt header)",
            mib(total),
            headers
                .iter()
                .enumerate()
                .map(|(i, h)| format!(
                    "{}: {}x{}, {} channels, {}",
                    part_name(h, i),
                    h.layer_size.0,
                    h.layer_size.1,
                    h.channels.list.len(),
                    h.compression
                ))
                .collect::<Vec<_>>()
                .join("; "),
            bytes.len()
        )));
    }
    if headers
        .iter()
        .any(|h| matches!(h.compression, Compression::DWAA(_) | Compression::DWAB(_)))
    {
        check_dwa_chunks(bytes, &headers).map_err(Refusal::Invalid)?;
    }
    Ok(())
}

fn part_name(h: &Header, i: usize) -> String {
    match &h.own_attributes.layer_name {
        Some(n) => format!("part {i} ({n})"),
        None => format!("part {i}"),
    }
}

/// Size of a DWA chunk leader: eleven little-endian u64 counters.
const DWA_LEADER: usize = 11 * 8;

/// Every DWA chunk's counters against the size of its block: the decoder
/// sizes its buffers by them before it inflates anything.
fn check_dwa_chunks(bytes: &[u8], headers: &[Header]) -> Result<(), String> {
    let reader = exr::block::read(Cursor::new(bytes), true).map_err(|e| format!("{e}"))?;
    let chunks = reader.all_chunks(true).map_err(|e| format!("{e}"))?;
    for chunk in chunks {
        let chunk = chunk.map_err(|e| format!("{e}"))?;
        let Some(h) = headers.get(chunk.layer_index) else {
            return Err(format!(
                "a chunk names part {} of {}",
                chunk.layer_index,
                headers.len()
            ));
        };
        if !matches!(h.compression, Compression::DWAA(_) | Compression::DWAB(_)) {
            continue;
        }
        let data = match &chunk.compressed_block {
            CompressedBlock::ScanLine(b) => &b.compressed_pixels_le,
            CompressedBlock::Tile(b) => &b.compressed_pixels_le,
            _ => continue,
        };
        let tile = h
            .get_block_data_indices(&chunk.compressed_block)
            .map_err(|e| format!("{e}"))?;
        let bounds = h
            .get_absolute_block_pixel_coordinates(tile)
            .map_err(|e| format!("{e}"))?;
        let (bw, bh) = (bounds.size.0, bounds.size.1);
        let expected = bw
            .saturating_mul(bh)
            .saturating_mul(h.channels.bytes_per_pixel);
        // Stored raw (or empty): the decoder copies it.
        if data.is_empty() || data.len() == expected {
            continue;
        }
        if data.len() < DWA_LEADER {
            return Err(format!(
                "{}: a DWA chunk of {} bytes is shorter than its leader",
                part_name(h, chunk.layer_index),
                data.len()
            ));
        }
        let counter = |i: usize| {
            let mut b = [0u8; 8];
            b.copy_from_slice(&data[8 * i..8 * i + 8]);
            u64::from_le_bytes(b)
        };
        // Blocks of 8x8 per channel, one DC and at most 63 AC values each.
        let blocks = (bw.div_ceil(8) as u64)
            .saturating_mul(bh.div_ceil(8) as u64)
            .saturating_mul(h.channels.list.len() as u64);
        let exp = expected as u64;
        let claims = [
            ("unknown uncompressed size", counter(1), exp),
            (
                "RLE uncompressed size",
                counter(6),
                exp.saturating_mul(2) + 64,
            ),
            ("RLE raw size", counter(7), exp),
            ("AC count", counter(8), blocks.saturating_mul(63)),
            ("DC count", counter(9), blocks),
        ];
        for (what, value, most) in claims {
            if value > most {
                return Err(format!(
                    "{}: a DWA chunk of the {bw}x{bh} block at y {} claims {what} {value}, \
                     more than such a block can hold ({most})",
                    part_name(h, chunk.layer_index),
                    bounds.position.1
                ));
            }
        }
        let sections = [2usize, 3, 4, 5]
            .iter()
            .map(|&i| counter(i))
            .fold(0u64, |a, b| a.saturating_add(b));
        if sections > data.len() as u64 {
            return Err(format!(
                "{}: a DWA chunk of {} bytes claims {sections} bytes of sections",
                part_name(h, chunk.layer_index),
                data.len()
            ));
        }
    }
    Ok(())
}
