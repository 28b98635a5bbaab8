//! EXR files that claim more than they hold (issue 16, item 1): each is
//! refused before anything is allocated for it, with an error that names the
//! file and frame, and never aborts or panics.

use std::path::Path;
use std::time::Instant;

use exr::prelude::{
    AnyChannel, AnyChannels, Encoding, FlatSamples, Image as ExrImage, Layer, LayerAttributes,
    WritableImage,
};
use harmonizer_core::io::exr::ExrFile;
use harmonizer_core::io::guard::{expansion_bound, ReadLimits};
use harmonizer_core::Error;

use exr::compression::Compression;
use exr::image::Blocks;
use exr::meta::attribute::LineOrder;

/// A single-part scan-line file of `channels` half channels with a
/// deterministic texture (`flat`: all zero, the most compressible content).
fn write(path: &Path, w: usize, h: usize, channels: usize, c: Compression, flat: bool) {
    write_blocks(path, w, h, channels, c, flat, Blocks::ScanLines);
}

fn write_blocks(
    path: &Path,
    w: usize,
    h: usize,
    channels: usize,
    c: Compression,
    flat: bool,
    blocks: Blocks,
) {
    let list = (0..channels)
        .map(|k| {
            let v: Vec<exr::prelude::f16> = (0..w * h)
                .map(|i| {
                    let x = if flat {
                        0.0
                    } else {
                        ((i * 7919 + k * 104_729) % 1009) as f32 / 97.0
                    };
                    exr::prelude::f16::from_f32(x)
                })
                .collect();
            AnyChannel::new(format!("c{k:05}").as_str(), FlatSamples::F16(v))
        })
        .collect();
    let encoding = Encoding {
        compression: c,
        blocks,
        line_order: LineOrder::Increasing,
    };
    let layer = Layer::new(
        (w, h),
        LayerAttributes::default(),
        encoding,
        AnyChannels::sort(list),
    );
    ExrImage::from_layer(layer).write().to_file(path).unwrap();
}

/// Where the header's attributes end (the byte after the terminating 0).
fn header_end(b: &[u8]) -> usize {
    let mut p = 8;
    loop {
        if b[p] == 0 {
            return p + 1;
        }
        let name_end = p + b[p..].iter().position(|&x| x == 0).unwrap();
        let type_end = name_end + 1 + b[name_end + 1..].iter().position(|&x| x == 0).unwrap();
        let size = i32::from_le_bytes(b[type_end + 1..type_end + 5].try_into().unwrap()) as usize;
        p = type_end + 5 + size;
    }
}

/// Rewrites the `dataWindow` box of a single-part file.
fn set_data_window(b: &mut [u8], w: i64, h: i64) {
    let key = b"dataWindow\0box2i\0";
    let at = b.windows(key.len()).position(|x| x == key).unwrap() + key.len() + 4;
    let put = |b: &mut [u8], o: usize, v: i32| b[o..o + 4].copy_from_slice(&v.to_le_bytes());
    put(b, at, 0);
    put(b, at + 4, 0);
    put(b, at + 8, (w - 1) as i32);
    put(b, at + 12, (h - 1) as i32);
}

/// Byte offset of the first chunk's pixel data (after its y and size).
fn first_chunk_data(b: &[u8]) -> usize {
    let table = header_end(b);
    let offset = u64::from_le_bytes(b[table..table + 8].try_into().unwrap()) as usize;
    offset + 8
}

fn open_err(path: &Path) -> Error {
    let t = Instant::now();
    let e = ExrFile::open(path, Some(7)).expect_err("a hostile file must be refused");
    assert!(
        t.elapsed().as_secs_f64() < 5.0,
        "refusing {} took {:?}",
        path.display(),
        t.elapsed()
    );
    let m = e.to_string();
    assert!(
        m.contains("frame 7") && m.contains(&path.display().to_string()),
        "the error names the frame and file: {m}"
    );
    e
}

#[test]
fn a_small_file_claiming_a_huge_data_window_is_refused_before_decoding() {
    let dir = tempfile::tempdir().unwrap();
    let path = dir.path().join("claims.exr");
    write(&path, 8, 8, 3, Compression::Uncompressed, false);
    let good = std::fs::read(&path).unwrap();
    for (w, h) in [(65535, 65535), (1_073_741_821, 1_073_741_821), (70_000, 8)] {
        let mut b = good.clone();
        set_data_window(&mut b, w, h);
        std::fs::write(&path, &b).unwrap();
        let m = open_err(&path).to_string();
        assert!(
            m.contains(&format!("{w}x{h}")) && m.contains("cannot read EXR"),
            "{w}x{h}: {m}"
        );
    }
}

#[test]
fn a_widened_piz_window_is_refused_before_the_huffman_decoder_runs() {
    let dir = tempfile::tempdir().unwrap();
    let path = dir.path().join("piz.exr");
    write(&path, 64, 64, 3, Compression::PIZ, false);
    let mut b = std::fs::read(&path).unwrap();
    set_data_window(&mut b, 300_000, 64);
    std::fs::write(&path, &b).unwrap();
    let m = open_err(&path).to_string();
    assert!(m.contains("cannot hold"), "{m}");
}

#[test]
fn dwa_chunk_counters_larger_than_their_block_are_refused() {
    let dir = tempfile::tempdir().unwrap();
    let path = dir.path().join("dwa.exr");
    for c in [Compression::DWAA(None), Compression::DWAB(None)] {
        write(&path, 40, 40, 3, c, false);
        let good = std::fs::read(&path).unwrap();
        ExrFile::open(&path, Some(7)).expect("the unmodified file reads");
        let data = first_chunk_data(&good);
        // unknown uncompressed size, RLE sizes, AC and DC counts: each alone
        // set to an impossible value (a 36 PB request in the decoder).
        for counter in [1usize, 6, 7, 8, 9] {
            let mut b = good.clone();
            let at = data + 8 * counter;
            b[at..at + 8].copy_from_slice(&(1u64 << 52).to_le_bytes());
            std::fs::write(&path, &b).unwrap();
            let m = open_err(&path).to_string();
            assert!(m.contains("DWA chunk"), "{c:?} counter {counter}: {m}");
        }
    }
}

#[test]
fn too_many_channels_are_refused() {
    let dir = tempfile::tempdir().unwrap();
    let path = dir.path().join("channels.exr");
    write(&path, 4, 4, 5000, Compression::ZIP16, true);
    let m = open_err(&path).to_string();
    assert!(m.contains("5000 channels"), "{m}");
}

#[test]
fn a_frame_larger_than_the_memory_limit_is_out_of_memory() {
    let dir = tempfile::tempdir().unwrap();
    let path = dir.path().join("big.exr");
    write(&path, 512, 512, 4, Compression::ZIP16, true);
    let limits = ReadLimits::with_memory_limit(1 << 20);
    let e = ExrFile::open_with(&path, Some(3), &limits).unwrap_err();
    assert!(matches!(e, Error::OutOfMemory(_)), "{e}");
    assert!(e.to_string().contains("memory limit"), "{e}");
    ExrFile::open_with(&path, Some(3), &ReadLimits::with_memory_limit(4 << 20))
        .expect("the same file fits 4 MiB");
}

#[test]
fn legitimate_files_of_every_compression_read_even_when_flat() {
    let dir = tempfile::tempdir().unwrap();
    let path = dir.path().join("ok.exr");
    for c in [
        Compression::Uncompressed,
        Compression::RLE,
        Compression::ZIP1,
        Compression::ZIP16,
        Compression::PIZ,
        Compression::PXR24,
        Compression::B44,
        Compression::B44A,
        Compression::DWAA(None),
        Compression::DWAB(None),
    ] {
        for (w, h, flat, tiles) in [
            (37, 21, false, false),
            (1024, 300, true, false),
            (100, 70, false, true),
            (1024, 300, true, true),
        ] {
            let blocks = if tiles {
                Blocks::Tiles(exr::math::Vec2(64, 32))
            } else {
                Blocks::ScanLines
            };
            write_blocks(&path, w, h, 3, c, flat, blocks);
            let size = std::fs::metadata(&path).unwrap().len() as usize;
            let f = ExrFile::open(&path, Some(1)).unwrap_or_else(|e| {
                panic!(
                    "{c:?} {w}x{h} flat {flat} tiles {tiles}, {size} bytes (bound {}x): {e}",
                    expansion_bound(c)
                )
            });
            assert_eq!(f.parts()[0].1, w);
        }
    }
}

/// B44 blocks whose deltas wrap below zero: OpenEXR's decoder wraps (C
/// unsigned arithmetic), and so must the `exr` crate in debug builds, where
/// it used to panic with `attempt to subtract with overflow`.
/// A tiled file whose tile claims 8 x 33554625 pixels (the `exr_read` fuzz
/// target's find: the decoder sized a 1.7 GB read buffer for one tile of a
/// 12 x 10 image) is refused from its header.
#[test]
fn a_tile_larger_than_its_image_and_the_budget_is_refused() {
    let dir = tempfile::tempdir().unwrap();
    let path = dir.path().join("tile.exr");
    write_blocks(
        &path,
        12,
        10,
        3,
        Compression::Uncompressed,
        false,
        Blocks::Tiles(exr::math::Vec2(8, 8)),
    );
    let good = std::fs::read(&path).unwrap();
    assert!(
        ExrFile::open(&path, Some(7)).is_ok(),
        "the file as written reads"
    );
    let key = b"tiles\0tiledesc\0";
    let at = good.windows(key.len()).position(|x| x == key).unwrap() + key.len() + 4;
    let mut b = good.clone();
    b[at + 4..at + 8].copy_from_slice(&0x0200_00c1u32.to_le_bytes());
    std::fs::write(&path, &b).unwrap();
    let e = open_err(&path);
    let m = e.to_string();
    assert!(
        m.contains("tiles of 8x33554625 pixels") && m.contains("12x10 data window"),
        "{m}"
    );
}

#[test]
fn b44_blocks_that_wrap_decode_without_a_panic() {
    let dir = tempfile::tempdir().unwrap();
    let path = dir.path().join("b44.exr");
    write(&path, 8, 8, 1, Compression::B44, false);
    let mut b = std::fs::read(&path).unwrap();
    let data = first_chunk_data(&b);
    let len = i32::from_le_bytes(b[data - 4..data].try_into().unwrap()) as usize;
    assert!(
        len > 14 && len < 8 * 8 * 2,
        "a compressed chunk ({len} bytes)"
    );
    // s[0] = 0, shift 1, zero deltas: s[4] = 0 + 0 - bias wraps.
    for blk in b[data..data + len].chunks_mut(14) {
        blk.fill(0);
        if blk.len() > 2 {
            blk[2] = 4;
        }
    }
    std::fs::write(&path, &b).unwrap();
    let decoded = std::panic::catch_unwind(|| crate::io::try_read_all(&path).map(|_| ()));
    assert!(
        decoded.is_ok(),
        "the exr crate panicked on wrapping B44 data"
    );
    let _ = ExrFile::open(&path, Some(1));
}
