//! The planar f32 image the pipeline works on (channel-major, like the
//! network's NCHW tensors).

use crate::error::{Error, Result};

/// `width * height * channels` samples, overflow-checked.
pub fn sample_count(width: usize, height: usize, channels: usize) -> Result<usize> {
    width
        .checked_mul(height)
        .and_then(|n| n.checked_mul(channels))
        .filter(|&n| n <= isize::MAX as usize / std::mem::size_of::<f32>())
        .ok_or_else(|| {
            Error::OutOfMemory(format!(
                "an image of {width}x{height}x{channels} f32 samples is larger than the address space"
            ))
        })
}

/// A buffer of `len` zeros, or [`Error::OutOfMemory`] naming its size when
/// the allocator refuses it (`Vec::try_reserve_exact`: never an abort).
pub fn try_zeros(len: usize) -> Result<Vec<f32>> {
    let mut v = Vec::new();
    v.try_reserve_exact(len).map_err(|e| {
        Error::OutOfMemory(format!(
            "cannot allocate a buffer of {len} f32 samples ({} bytes): {e}",
            len.saturating_mul(std::mem::size_of::<f32>())
        ))
    })?;
    v.resize(len, 0.0);
    Ok(v)
}

/// A planar f32 image: `channels` planes of `width * height` samples.
#[derive(Debug, Clone, PartialEq)]
pub struct Image {
    /// Width in pixels.
    pub width: usize,
    /// Height in pixels.
    pub height: usize,
    /// Number of planes.
    pub channels: usize,
    /// Samples, plane after plane, rows top to bottom.
    pub data: Vec<f32>,
}

impl Image {
    /// A zero-filled image.
    pub fn zeros(width: usize, height: usize, channels: usize) -> Image {
        Image {
            width,
            height,
            channels,
            data: vec![0.0; width * height * channels],
        }
    }

    /// A zero-filled image, or [`Error::OutOfMemory`] when its size
    /// overflows or cannot be allocated (no abort).
    pub fn try_zeros(width: usize, height: usize, channels: usize) -> Result<Image> {
        Ok(Image {
            width,
            height,
            channels,
            data: try_zeros(sample_count(width, height, channels)?)?,
        })
    }

    /// A constant image.
    pub fn filled(width: usize, height: usize, channels: usize, value: f32) -> Image {
        Image {
            width,
            height,
            channels,
            data: vec![value; width * height * channels],
        }
    }

    /// Pixels per plane.
    #[inline]
    pub fn len(&self) -> usize {
        self.width * self.height
    }

    /// True when the image has no pixels.
    pub fn is_empty(&self) -> bool {
        self.len() == 0
    }

    /// One plane.
    #[inline]
    pub fn plane(&self, c: usize) -> &[f32] {
        let n = self.len();
        &self.data[c * n..(c + 1) * n]
    }

    /// One plane, mutable.
    #[inline]
    pub fn plane_mut(&mut self, c: usize) -> &mut [f32] {
        let n = self.len();
        &mut self.data[c * n..(c + 1) * n]
    }

    /// All planes, mutable, split.
    pub fn planes_mut(&mut self) -> Vec<&mut [f32]> {
        let n = self.len();
        self.data.chunks_mut(n.max(1)).collect()
    }

    /// One sample.
    #[inline]
    pub fn at(&self, x: usize, y: usize, c: usize) -> f32 {
        self.data[c * self.len() + y * self.width + x]
    }

    /// Bytes held.
    pub fn bytes(&self) -> usize {
        self.data.len() * std::mem::size_of::<f32>()
    }
}

/// An interleaved RGBA f32 image: R, G, B, A of a pixel side by side, pixels
/// row after row. The history's color is kept so: a bilinear tap of a
/// reprojection reads one 16-byte run instead of one sample from each of four
/// planes.
#[derive(Debug, Clone, PartialEq)]
pub struct RgbaImage {
    /// Width in pixels.
    pub width: usize,
    /// Height in pixels.
    pub height: usize,
    /// `4 * width * height` samples: pixel `p` at `4 * p .. 4 * p + 4`.
    pub data: Vec<f32>,
}

impl RgbaImage {
    /// A zero-filled image.
    pub fn zeros(width: usize, height: usize) -> RgbaImage {
        RgbaImage {
            width,
            height,
            data: vec![0.0; 4 * width * height],
        }
    }

    /// Pixels.
    #[inline]
    pub fn len(&self) -> usize {
        self.width * self.height
    }

    /// True when the image has no pixels.
    pub fn is_empty(&self) -> bool {
        self.len() == 0
    }

    /// Pixel `p` (row-major index) as R, G, B, A.
    #[inline(always)]
    pub fn pixel(&self, p: usize) -> [f32; 4] {
        let q = &self.data[4 * p..4 * p + 4];
        [q[0], q[1], q[2], q[3]]
    }

    /// Row `y` of channel `c` into `out` (one row long).
    pub fn read_row(&self, y: usize, c: usize, out: &mut [f32]) {
        let w = self.width;
        let row = &self.data[4 * y * w..4 * (y + 1) * w];
        for (o, q) in out[..w].iter_mut().zip(row.chunks_exact(4)) {
            *o = q[c];
        }
    }

    /// The image of a 4-plane [`Image`], in parallel on `pool` when given.
    pub fn from_planes(img: &Image, pool: Option<&rayon::ThreadPool>) -> RgbaImage {
        let mut out = RgbaImage::zeros(img.width, img.height);
        out.set_planes(img, pool);
        out
    }

    /// Writes the samples of the planes `[r, g, b, a]` (each at least
    /// `out.len()` long) interleaved into `out`: pixel `p` gets `[r[p],
    /// g[p], b[p], a[p]]`. Any run of pixels: whole images, rows, chunks.
    #[inline]
    pub fn interleave(planes: [&[f32]; 4], out: &mut [[f32; 4]]) {
        let n = out.len();
        let [r, g, b, a] = planes.map(|p| &p[..n]);
        for (p, q) in out.iter_mut().enumerate() {
            *q = [r[p], g[p], b[p], a[p]];
        }
    }

    /// Overwrites every sample with the 4-plane `img` of the same size, in
    /// parallel on `pool` when given.
    pub fn set_planes(&mut self, img: &Image, pool: Option<&rayon::ThreadPool>) {
        use rayon::prelude::*;
        assert_eq!(
            (img.width, img.height, img.channels),
            (self.width, self.height, 4),
            "an RGBA image is made of 4 planes of its size"
        );
        let n = img.len();
        if n == 0 {
            return;
        }
        let [r, g, b, a] = [0, 1, 2, 3].map(|c| img.plane(c));
        const CHUNK: usize = 1 << 14;
        let part = |(k, out): (usize, &mut [f32])| {
            let s = k * CHUNK..;
            let planes = [&r[s.clone()], &g[s.clone()], &b[s.clone()], &a[s]];
            RgbaImage::interleave(planes, out.as_chunks_mut::<4>().0);
        };
        match pool {
            Some(pool) => pool.install(|| {
                self.data
                    .par_chunks_mut(4 * CHUNK)
                    .enumerate()
                    .for_each(part)
            }),
            None => self.data.chunks_mut(4 * CHUNK).enumerate().for_each(part),
        }
    }

    /// The 4-plane [`Image`] of this one.
    pub fn to_planes(&self) -> Image {
        let mut img = Image::zeros(self.width, self.height, 4);
        let n = self.len();
        for (p, q) in self.data.chunks_exact(4).enumerate() {
            for (c, v) in q.iter().enumerate() {
                img.data[c * n + p] = *v;
            }
        }
        img
    }

    /// Bytes held.
    pub fn bytes(&self) -> usize {
        self.data.len() * std::mem::size_of::<f32>()
    }
}

/// Sample buffers kept for reuse from one frame to the next.
///
/// Frame-sized buffers are tens of megabytes; allocating them fresh every
/// frame costs a page fault and a page clear per 4 KiB, more than the work
/// done on them. A session gives its spent buffers back here and takes them
/// again for the next frame. A buffer taken has the requested length and
/// *arbitrary* contents: the taker overwrites every sample.
///
/// One more buffer is kept apart, known to be zero outside a rectangle
/// ([`Recycler::take_zeroed`], [`Recycler::give_zeroed`]): a sparse plane
/// (the insert mask) is then prepared by clearing and writing only where
/// it is not zero, not the whole frame.
#[derive(Debug, Default)]
pub struct Recycler {
    free: std::sync::Mutex<Vec<Vec<f32>>>,
    zeroed: std::sync::Mutex<Option<Zeroed>>,
}

/// A buffer of rows of `width` samples, zero outside `dirty`.
#[derive(Debug)]
struct Zeroed {
    data: Vec<f32>,
    width: usize,
    dirty: Option<crate::ops::Rect>,
}

impl Recycler {
    /// Buffers kept at most; more given back are freed.
    pub const MAX_BUFFERS: usize = 48;

    /// An empty recycler.
    pub fn new() -> Recycler {
        Recycler::default()
    }

    /// A buffer of exactly `len` samples, reused when one of that length is
    /// held (contents arbitrary), else newly allocated (zeros).
    ///
    /// # Panics
    /// When a new buffer cannot be allocated (a panic, not an abort: the C
    /// ABI turns it into an error). The frame-sized buffers of a frame are
    /// taken with [`Recycler::try_take`] after the session checked the
    /// frame's working set against the memory limit.
    pub fn take(&self, len: usize) -> Vec<f32> {
        self.try_take(len).unwrap_or_else(|e| panic!("{e}"))
    }

    /// [`Recycler::take`], or [`Error::OutOfMemory`] when a new buffer cannot
    /// be allocated (`Vec::try_reserve_exact`: never an abort).
    pub fn try_take(&self, len: usize) -> Result<Vec<f32>> {
        let reused = {
            let mut free = self.free.lock().unwrap_or_else(|e| e.into_inner());
            free.iter()
                .rposition(|b| b.len() == len)
                .map(|i| free.swap_remove(i))
        };
        match reused {
            Some(b) => Ok(b),
            None => try_zeros(len),
        }
    }

    /// An image whose samples are all to be overwritten by the caller.
    ///
    /// # Panics
    /// As [`Recycler::take`].
    pub fn image(&self, width: usize, height: usize, channels: usize) -> Image {
        self.try_image(width, height, channels)
            .unwrap_or_else(|e| panic!("{e}"))
    }

    /// [`Recycler::image`], or [`Error::OutOfMemory`] when the size
    /// overflows or the buffer cannot be allocated.
    pub fn try_image(&self, width: usize, height: usize, channels: usize) -> Result<Image> {
        Ok(Image {
            width,
            height,
            channels,
            data: self.try_take(sample_count(width, height, channels)?)?,
        })
    }

    /// Keeps `buf` for a later [`Recycler::take`] of its length.
    pub fn give(&self, buf: Vec<f32>) {
        if buf.is_empty() {
            return;
        }
        let mut free = self.free.lock().unwrap_or_else(|e| e.into_inner());
        if free.len() < Self::MAX_BUFFERS {
            free.push(buf);
        }
    }

    /// Drops every buffer held whose length is not `len`, `2 * len`, ... up
    /// to `4 * len` (after a change of frame size).
    pub fn keep_frame_size(&self, len: usize) {
        let mut free = self.free.lock().unwrap_or_else(|e| e.into_inner());
        free.retain(|b| len > 0 && b.len() % len == 0 && b.len() / len <= 5);
        let mut zeroed = self.zeroed.lock().unwrap_or_else(|e| e.into_inner());
        if zeroed.as_ref().is_some_and(|z| z.data.len() != len) {
            *zeroed = None;
        }
    }

    /// A buffer of `width * height` zeros: the one kept by
    /// [`Recycler::give_zeroed`] when it has that shape (cleared where it
    /// was not zero), else newly allocated; [`Error::OutOfMemory`] when the
    /// size overflows or a new buffer cannot be allocated.
    pub fn take_zeroed(&self, width: usize, height: usize) -> Result<Vec<f32>> {
        let len = sample_count(width, height, 1)?;
        let kept = self
            .zeroed
            .lock()
            .unwrap_or_else(|e| e.into_inner())
            .take()
            .filter(|z| z.width == width && z.data.len() == len);
        match kept {
            Some(Zeroed {
                mut data, dirty, ..
            }) => {
                if let Some(r) = dirty {
                    for y in r.y0..r.y1 {
                        data[y * width + r.x0..y * width + r.x1].fill(0.0);
                    }
                }
                Ok(data)
            }
            None => try_zeros(len),
        }
    }

    /// Keeps `buf` (rows of `width` samples, every sample outside `dirty`
    /// exactly +0.0; `None`: all of them) for [`Recycler::take_zeroed`],
    /// in place of the one kept before.
    ///
    /// # Panics
    /// When `dirty` is not inside the buffer.
    pub fn give_zeroed(&self, buf: Vec<f32>, width: usize, dirty: Option<crate::ops::Rect>) {
        if buf.is_empty() || width == 0 {
            return;
        }
        if let Some(r) = dirty {
            assert!(
                r.x1 <= width && r.y1 * width <= buf.len(),
                "dirty {r:?} outside a buffer of {} rows of {width}",
                buf.len() / width
            );
        }
        *self.zeroed.lock().unwrap_or_else(|e| e.into_inner()) = Some(Zeroed {
            data: buf,
            width,
            dirty,
        });
    }

    /// Bytes held.
    pub fn bytes(&self) -> usize {
        let free = self.free.lock().unwrap_or_else(|e| e.into_inner());
        let zeroed = self.zeroed.lock().unwrap_or_else(|e| e.into_inner());
        free.iter().map(|b| b.len() * 4).sum::<usize>()
            + zeroed.as_ref().map_or(0, |z| z.data.len() * 4)
    }
}
