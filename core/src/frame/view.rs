//! Strided, borrowed views of a host's pixel buffers (f32 or f16), read and
//! written without repacking: an RGBA buffer with a 16-byte pixel stride where
//! only RGB is color is a 3-channel view with `pixel_stride = 16`.

use crate::error::{Error, Result};

/// Sample format of a host buffer.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum PixelFormat {
    /// 32-bit IEEE float.
    F32,
    /// 16-bit IEEE half float.
    F16,
}

impl PixelFormat {
    /// Bytes per sample.
    pub fn size(self) -> usize {
        match self {
            PixelFormat::F32 => 4,
            PixelFormat::F16 => 2,
        }
    }
}

/// Layout of a strided image inside a byte buffer.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
struct Layout {
    format: PixelFormat,
    width: usize,
    height: usize,
    channels: usize,
    offset: usize,
    pixel_stride: usize,
    row_stride: usize,
}

impl Layout {
    /// Validates the layout against a buffer of `len` bytes; 0 strides mean packed.
    #[allow(clippy::too_many_arguments)]
    fn new(
        what: &str,
        len: usize,
        format: PixelFormat,
        width: usize,
        height: usize,
        channels: usize,
        offset: usize,
        pixel_stride: usize,
        row_stride: usize,
    ) -> Result<Layout> {
        if width == 0 || height == 0 {
            return Err(Error::invalid(format!(
                "{what}: image size {width}x{height} is empty"
            )));
        }
        if channels == 0 {
            return Err(Error::invalid(format!("{what}: channel count is 0")));
        }
        let sample = format.size();
        let packed_pixel = channels
            .checked_mul(sample)
            .ok_or_else(|| Error::invalid(format!("{what}: channel count {channels} overflows")))?;
        let pixel_stride = if pixel_stride == 0 {
            packed_pixel
        } else {
            pixel_stride
        };
        if pixel_stride < packed_pixel {
            return Err(Error::invalid(format!(
                "{what}: pixel stride {pixel_stride} bytes is smaller than {channels} channels of {sample} bytes"
            )));
        }
        let packed_row = width.checked_mul(pixel_stride).ok_or_else(|| {
            Error::invalid(format!("{what}: width {width} x pixel stride overflows"))
        })?;
        let row_stride = if row_stride == 0 {
            packed_row
        } else {
            row_stride
        };
        if row_stride < packed_row {
            return Err(Error::invalid(format!(
                "{what}: row stride {row_stride} bytes is smaller than width {width} x pixel stride {pixel_stride}"
            )));
        }
        if !offset.is_multiple_of(sample)
            || !pixel_stride.is_multiple_of(sample)
            || !row_stride.is_multiple_of(sample)
        {
            return Err(Error::invalid(format!(
                "{what}: offset and strides must be multiples of the sample size {sample}"
            )));
        }
        let end = (height - 1)
            .checked_mul(row_stride)
            .and_then(|v| v.checked_add((width - 1).checked_mul(pixel_stride)?))
            .and_then(|v| v.checked_add(packed_pixel))
            .and_then(|v| v.checked_add(offset))
            .ok_or_else(|| {
                Error::invalid(format!("{what}: {width}x{height} image size overflows"))
            })?;
        if end > len {
            return Err(Error::invalid(format!(
                "{what}: {width}x{height}x{channels} image needs {end} bytes, buffer has {len}"
            )));
        }
        Ok(Layout {
            format,
            width,
            height,
            channels,
            offset,
            pixel_stride,
            row_stride,
        })
    }

    #[inline]
    fn index(&self, x: usize, y: usize, c: usize) -> usize {
        self.offset + y * self.row_stride + x * self.pixel_stride + c * self.format.size()
    }
}

/// A read-only strided view of a host image.
#[derive(Debug, Clone, Copy)]
pub struct ImageView<'a> {
    data: &'a [u8],
    layout: Layout,
}

impl<'a> ImageView<'a> {
    /// Describes `data` as an image. `pixel_stride`/`row_stride` of 0 mean packed.
    /// `what` names the image in error messages (for example "depth").
    #[allow(clippy::too_many_arguments)]
    pub fn new(
        what: &str,
        data: &'a [u8],
        format: PixelFormat,
        width: usize,
        height: usize,
        channels: usize,
        offset: usize,
        pixel_stride: usize,
        row_stride: usize,
    ) -> Result<Self> {
        let layout = Layout::new(
            what,
            data.len(),
            format,
            width,
            height,
            channels,
            offset,
            pixel_stride,
            row_stride,
        )?;
        Ok(ImageView { data, layout })
    }

    /// A packed interleaved f32 view of a slice.
    pub fn from_f32(
        what: &str,
        data: &'a [f32],
        width: usize,
        height: usize,
        channels: usize,
    ) -> Result<Self> {
        Self::new(
            what,
            f32_bytes(data),
            PixelFormat::F32,
            width,
            height,
            channels,
            0,
            0,
            0,
        )
    }

    /// Width in pixels.
    pub fn width(&self) -> usize {
        self.layout.width
    }
    /// Height in pixels.
    pub fn height(&self) -> usize {
        self.layout.height
    }
    /// Channels described by this view.
    pub fn channels(&self) -> usize {
        self.layout.channels
    }
    /// Sample format.
    pub fn format(&self) -> PixelFormat {
        self.layout.format
    }

    /// One sample as f32.
    #[inline]
    pub fn get(&self, x: usize, y: usize, c: usize) -> f32 {
        let i = self.layout.index(x, y, c);
        match self.layout.format {
            PixelFormat::F32 => f32::from_ne_bytes([
                self.data[i],
                self.data[i + 1],
                self.data[i + 2],
                self.data[i + 3],
            ]),
            PixelFormat::F16 => {
                half::f16::from_bits(u16::from_ne_bytes([self.data[i], self.data[i + 1]])).to_f32()
            }
        }
    }

    /// Copies channels `0..outs.len()` of row `y` into `outs` (one slice
    /// of width samples per channel): the same values as [`ImageView::read_row`]
    /// channel by channel, in one pass over the row for interleaved f32 RGB
    /// in RGBA pixels and 2-channel pixels (the usual color and motion).
    pub fn read_row_channels(&self, y: usize, outs: &mut [&mut [f32]]) {
        let l = &self.layout;
        let n = l.width;
        if l.format == PixelFormat::F32 {
            if let Some(samples) = aligned::<f32>(self.data) {
                let start = l.index(0, y, 0) / 4;
                match (l.pixel_stride, &mut *outs) {
                    (16, [r, g, b]) => {
                        if let Some(row) = samples.get(start..start + 4 * n) {
                            let px = row.chunks_exact(4).zip(r.iter_mut());
                            for ((q, r), (g, b)) in px.zip(g.iter_mut().zip(b.iter_mut())) {
                                (*r, *g, *b) = (q[0], q[1], q[2]);
                            }
                            return;
                        }
                    }
                    (8, [u, v]) => {
                        if let Some(row) = samples.get(start..start + 2 * n) {
                            let px = row.chunks_exact(2).zip(u.iter_mut());
                            for ((q, u), v) in px.zip(v.iter_mut()) {
                                (*u, *v) = (q[0], q[1]);
                            }
                            return;
                        }
                    }
                    _ => {}
                }
            }
        }
        for (c, out) in outs.iter_mut().enumerate() {
            self.read_row(y, c, out);
        }
    }

    /// Row `y` of a single-channel f32 image whose samples are packed
    /// (pixel stride 4 bytes) and aligned, borrowed; `None` for any other
    /// layout (read it with [`ImageView::read_row`]).
    pub fn packed_row(&self, y: usize) -> Option<&'a [f32]> {
        let l = &self.layout;
        if l.format != PixelFormat::F32 || l.pixel_stride != 4 || y >= l.height {
            return None;
        }
        let start = l.index(0, y, 0) / 4;
        aligned::<f32>(self.data)?.get(start..start + l.width)
    }

    /// Copies channel `c` of row `y` into `out` (length = width).
    pub fn read_row(&self, y: usize, c: usize, out: &mut [f32]) {
        debug_assert_eq!(out.len(), self.layout.width);
        self.read_span(y, 0, c, out);
    }

    /// Copies channel `c` of row `y` from column `x0` on into `out` (its
    /// length columns, at most to the end of the row).
    pub fn read_span(&self, y: usize, x0: usize, c: usize, out: &mut [f32]) {
        let l = &self.layout;
        debug_assert!(x0 + out.len() <= l.width);
        let n = out.len();
        if n == 0 {
            return;
        }
        let base = l.index(x0, y, c);
        match l.format {
            PixelFormat::F32 => {
                let (step, start) = (l.pixel_stride / 4, base / 4);
                if let Some(samples) = aligned::<f32>(self.data) {
                    let row = &samples[start..start + (n - 1) * step + 1];
                    // Constant strides for the usual layouts (1 to 4
                    // interleaved channels), so the copy vectorizes.
                    match step {
                        1 => out.copy_from_slice(row),
                        2 => gather_every::<2>(row, out),
                        3 => gather_every::<3>(row, out),
                        4 => gather_every::<4>(row, out),
                        _ => out
                            .iter_mut()
                            .zip(row.iter().step_by(step))
                            .for_each(|(o, v)| *o = *v),
                    }
                } else {
                    let row = &self.data[base..base + (n - 1) * l.pixel_stride + 4];
                    for (o, b) in out.iter_mut().zip(row.chunks(l.pixel_stride)) {
                        *o = f32::from_ne_bytes([b[0], b[1], b[2], b[3]]);
                    }
                }
            }
            PixelFormat::F16 => {
                let (step, start) = (l.pixel_stride / 2, base / 2);
                if let Some(samples) = aligned::<u16>(self.data) {
                    let row = &samples[start..start + (n - 1) * step + 1];
                    out.iter_mut()
                        .zip(row.iter().step_by(step))
                        .for_each(|(o, v)| *o = half::f16::from_bits(*v).to_f32());
                } else {
                    let row = &self.data[base..base + (n - 1) * l.pixel_stride + 2];
                    for (o, b) in out.iter_mut().zip(row.chunks(l.pixel_stride)) {
                        *o = half::f16::from_bits(u16::from_ne_bytes([b[0], b[1]])).to_f32();
                    }
                }
            }
        }
    }
}

/// A writable strided view of a host image.
#[derive(Debug)]
pub struct ImageViewMut<'a> {
    data: &'a mut [u8],
    layout: Layout,
}

impl<'a> ImageViewMut<'a> {
    /// Describes `data` as a writable image; see [`ImageView::new`].
    #[allow(clippy::too_many_arguments)]
    pub fn new(
        what: &str,
        data: &'a mut [u8],
        format: PixelFormat,
        width: usize,
        height: usize,
        channels: usize,
        offset: usize,
        pixel_stride: usize,
        row_stride: usize,
    ) -> Result<Self> {
        let layout = Layout::new(
            what,
            data.len(),
            format,
            width,
            height,
            channels,
            offset,
            pixel_stride,
            row_stride,
        )?;
        Ok(ImageViewMut { data, layout })
    }

    /// A packed interleaved f32 view of a mutable slice.
    pub fn from_f32(
        what: &str,
        data: &'a mut [f32],
        width: usize,
        height: usize,
        channels: usize,
    ) -> Result<Self> {
        Self::new(
            what,
            f32_bytes_mut(data),
            PixelFormat::F32,
            width,
            height,
            channels,
            0,
            0,
            0,
        )
    }

    /// Width in pixels.
    pub fn width(&self) -> usize {
        self.layout.width
    }
    /// Height in pixels.
    pub fn height(&self) -> usize {
        self.layout.height
    }
    /// Channels described by this view.
    pub fn channels(&self) -> usize {
        self.layout.channels
    }

    /// Writes channel `c` of row `y` from `src` (length = width).
    pub fn write_row(&mut self, y: usize, c: usize, src: &[f32]) {
        let l = self.layout;
        debug_assert_eq!(src.len(), l.width);
        let base = l.index(0, y, c);
        let n = l.width;
        match l.format {
            PixelFormat::F32 => {
                let (step, start) = (l.pixel_stride / 4, base / 4);
                if let Some(samples) = aligned_mut::<f32>(self.data) {
                    let row = &mut samples[start..start + (n - 1) * step + 1];
                    if step == 1 {
                        row.copy_from_slice(src);
                    } else {
                        row.iter_mut()
                            .step_by(step)
                            .zip(src)
                            .for_each(|(o, v)| *o = *v);
                    }
                } else {
                    let row = &mut self.data[base..base + (n - 1) * l.pixel_stride + 4];
                    for (b, v) in row.chunks_mut(l.pixel_stride).zip(src) {
                        b[..4].copy_from_slice(&v.to_ne_bytes());
                    }
                }
            }
            PixelFormat::F16 => {
                let (step, start) = (l.pixel_stride / 2, base / 2);
                if let Some(samples) = aligned_mut::<u16>(self.data) {
                    let row = &mut samples[start..start + (n - 1) * step + 1];
                    row.iter_mut()
                        .step_by(step)
                        .zip(src)
                        .for_each(|(o, v)| *o = half::f16::from_f32(*v).to_bits());
                } else {
                    let row = &mut self.data[base..base + (n - 1) * l.pixel_stride + 2];
                    for (b, v) in row.chunks_mut(l.pixel_stride).zip(src) {
                        b[..2].copy_from_slice(&half::f16::from_f32(*v).to_bits().to_ne_bytes());
                    }
                }
            }
        }
    }
}

/// The buffer as samples of `T` when its start is aligned for `T` (the tail
/// that does not fill a whole sample is dropped; layouts never reach it).
/// `out[x] = row[S * x]` (`row` holds `(out.len() - 1) * S + 1` samples).
#[inline]
fn gather_every<const S: usize>(row: &[f32], out: &mut [f32]) {
    let Some((last, head)) = out.split_last_mut() else {
        return;
    };
    let n = head.len();
    for (o, c) in head.iter_mut().zip(row[..n * S].chunks_exact(S)) {
        *o = c[0];
    }
    *last = row[n * S];
}

fn aligned<T: bytemuck::Pod>(data: &[u8]) -> Option<&[T]> {
    let whole = data.len() / std::mem::size_of::<T>() * std::mem::size_of::<T>();
    bytemuck::try_cast_slice(&data[..whole]).ok()
}

/// Mutable form of [`aligned`].
fn aligned_mut<T: bytemuck::Pod>(data: &mut [u8]) -> Option<&mut [T]> {
    let whole = data.len() / std::mem::size_of::<T>() * std::mem::size_of::<T>();
    bytemuck::try_cast_slice_mut(&mut data[..whole]).ok()
}

/// The bytes of an f32 slice (native endianness).
pub(crate) fn f32_bytes(data: &[f32]) -> &[u8] {
    bytemuck::cast_slice(data)
}

/// The mutable bytes of an f32 slice (native endianness).
pub(crate) fn f32_bytes_mut(data: &mut [f32]) -> &mut [u8] {
    bytemuck::cast_slice_mut(data)
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn rgba_buffer_read_as_rgb_with_16_byte_stride() {
        let data: Vec<f32> = (0..2 * 3 * 4).map(|i| i as f32).collect();
        let v = ImageView::new(
            "color",
            f32_bytes(&data),
            PixelFormat::F32,
            3,
            2,
            3,
            0,
            16,
            0,
        )
        .unwrap();
        let mut row = [0.0; 3];
        v.read_row(1, 2, &mut row);
        assert_eq!(row, [14.0, 18.0, 22.0]);
        assert_eq!(v.get(2, 1, 1), 21.0);
    }

    #[test]
    fn row_channels_equal_channel_by_channel_reads() {
        let data: Vec<f32> = (0..5 * 3 * 4 + 1).map(|i| i as f32 * 0.5).collect();
        // (channels, pixel stride, offset in samples): the one-pass cases
        // (the last pixel of an RGB view of RGBA ends the buffer early), and
        // others that read channel by channel.
        for (ch, stride, off) in [
            (3, 16, 0),
            (3, 16, 1),
            (4, 16, 0),
            (2, 8, 0),
            (2, 12, 0),
            (3, 12, 0),
        ] {
            let end = off + (5 * 3 - 1) * stride / 4 + ch;
            let v = ImageView::new(
                "x",
                f32_bytes(&data[..end]),
                PixelFormat::F32,
                5,
                3,
                ch,
                4 * off,
                stride,
                0,
            )
            .unwrap();
            let read = ch.min(3);
            for y in 0..3 {
                let mut want = vec![vec![0.0; 5]; read];
                for (c, o) in want.iter_mut().enumerate() {
                    v.read_row(y, c, o);
                }
                let mut got = vec![vec![0.0; 5]; read];
                let mut outs: Vec<&mut [f32]> = got.iter_mut().map(|o| &mut o[..]).collect();
                v.read_row_channels(y, &mut outs);
                assert_eq!(
                    got, want,
                    "{ch} channels, stride {stride}, offset {off}, row {y}"
                );
            }
        }
    }

    #[test]
    fn unaligned_and_f16_buffers_read_and_write() {
        // f32 samples starting one byte into the buffer: the byte path.
        let vals = [1.5f32, -2.0, 3.25, 4.0];
        let mut bytes = [0u8; 1 + 16];
        for (i, v) in vals.iter().enumerate() {
            bytes[1 + 4 * i..5 + 4 * i].copy_from_slice(&v.to_ne_bytes());
        }
        let v = ImageView::new("x", &bytes[1..], PixelFormat::F32, 4, 1, 1, 0, 0, 0).unwrap();
        let mut row = [0.0; 4];
        v.read_row(0, 0, &mut row);
        assert_eq!(row, vals);
        let mut out = [0u8; 1 + 16];
        let mut w =
            ImageViewMut::new("y", &mut out[1..], PixelFormat::F32, 4, 1, 1, 0, 0, 0).unwrap();
        w.write_row(0, 0, &vals);
        assert_eq!(&out[1..], &bytes[1..]);

        let halfs: Vec<u16> = [0.5f32, 1.0, 2.0]
            .iter()
            .map(|v| half::f16::from_f32(*v).to_bits())
            .collect();
        let hb: Vec<u8> = halfs.iter().flat_map(|h| h.to_ne_bytes()).collect();
        let v = ImageView::new("h", &hb, PixelFormat::F16, 3, 1, 1, 0, 0, 0).unwrap();
        let mut row = [0.0; 3];
        v.read_row(0, 0, &mut row);
        assert_eq!(row, [0.5, 1.0, 2.0]);
    }

    #[test]
    fn spans_equal_sample_by_sample_reads() {
        // f32 and f16, packed and strided, aligned and one byte in; every
        // span of every row.
        let (w, h) = (7, 3);
        let vals: Vec<f32> = (0..w * h * 4).map(|i| i as f32 * 0.25 - 3.0).collect();
        let f32b: Vec<u8> = vals.iter().flat_map(|v| v.to_ne_bytes()).collect();
        let f16b: Vec<u8> = vals
            .iter()
            .flat_map(|v| half::f16::from_f32(*v).to_bits().to_ne_bytes())
            .collect();
        let mut shifted = vec![0u8];
        shifted.extend_from_slice(&f32b);
        for (bytes, format, ch, stride) in [
            (&f32b[..], PixelFormat::F32, 3, 16),
            (&f32b[..], PixelFormat::F32, 4, 0),
            (&shifted[1..], PixelFormat::F32, 3, 16),
            (&f16b[..], PixelFormat::F16, 3, 8),
            (&f16b[..], PixelFormat::F16, 1, 0),
        ] {
            let v = ImageView::new("x", bytes, format, w, h, ch, 0, stride, 0).unwrap();
            for y in 0..h {
                for c in 0..ch {
                    for x0 in 0..w {
                        for n in 0..=w - x0 {
                            let mut got = vec![f32::NAN; n];
                            v.read_span(y, x0, c, &mut got);
                            let want: Vec<f32> = (x0..x0 + n).map(|x| v.get(x, y, c)).collect();
                            assert_eq!(got, want, "{format:?} {ch} ch, stride {stride}");
                        }
                    }
                }
            }
        }
    }

    #[test]
    fn short_buffers_and_overflow_are_refused() {
        let data = vec![0.0f32; 11];
        let e = ImageView::from_f32("depth", &data, 4, 3, 1)
            .unwrap_err()
            .to_string();
        assert!(
            e.contains("depth") && e.contains("48") && e.contains("44"),
            "{e}"
        );
        let e = ImageView::new("c", &[0u8; 4], PixelFormat::F32, usize::MAX, 2, 1, 0, 0, 0)
            .unwrap_err()
            .to_string();
        assert!(e.contains("overflow"), "{e}");
    }
}
