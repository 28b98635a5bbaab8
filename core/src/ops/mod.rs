//! Image operations of the classical pipeline: inpainting, insert
//! harmonization, contact and cast shadows, temporal stabilization.
//!
//! Every operation works in place on a 4-plane [`Image`] (RGB premultiplied by
//! A, A the coverage) and runs its parallel loops on the current rayon pool:
//! call them inside `ThreadPool::install` to use a device's pool. Work is split
//! into bands of [`BAND_ROWS`] rows, a constant, and reductions are summed per
//! band and then sequentially, so results do not depend on the thread count.

pub mod albedo_tone;
pub mod cast_shadow;
pub mod harmonize;
pub mod inpaint;
pub mod relight;
pub mod shadow;
pub mod stabilize;

use rayon::prelude::*;

use crate::frame::Image;

/// Runs `op` compiled for the widest vector instructions this CPU has (AVX2
/// and FMA on x86-64 where present, else the baseline), chosen at run time
/// (detected once per process). Code inlined into `op`'s `with_simd` (which
/// must be `#[inline(always)]`, as must the helpers it calls) is vectorized
/// for that width. The arithmetic is the same IEEE operations in the same
/// order on every path (Rust never fuses a multiply and an add), so the
/// results are bit for bit those of the baseline.
#[inline(always)]
pub(crate) fn simd<Op: pulp::WithSimd>(op: Op) -> Op::Output {
    pulp::Arch::new().dispatch(op)
}

/// Asks the CPU to bring the cache line holding `s[i]` into its caches
/// ahead of a read: a hint, with no effect on any value (nothing happens
/// for an index out of range, or on other architectures than x86-64).
/// Through `pulp`'s SSE token (SSE is part of every x86-64), whose
/// prefetch is a safe function: a prefetch neither faults nor writes.
#[inline(always)]
pub(crate) fn prefetch<T>(s: &[T], i: usize) {
    #[cfg(target_arch = "x86_64")]
    if let (Some(v), Some(sse)) = (s.get(i), pulp::core_arch::x86::Sse::try_new()) {
        sse._mm_prefetch::<{ std::arch::x86_64::_MM_HINT_T0 }>(std::ptr::from_ref(v).cast());
    }
    #[cfg(not(target_arch = "x86_64"))]
    let _ = (s, i);
}

/// Rows per parallel work item (fixed, so results never depend on threads).
pub const BAND_ROWS: usize = 16;

/// Rec.709 luminance weights (linear RGB).
pub const LUMA: [f32; 3] = [0.2126, 0.7152, 0.0722];

/// Depth at or above this value means "no surface" (sky, holes).
pub const EMPTY_DEPTH: f32 = 1e9;

/// A half-open pixel rectangle `[x0, x1) x [y0, y1)`.
#[derive(Debug, Clone, Copy, Default, PartialEq, Eq)]
pub struct Rect {
    /// First column.
    pub x0: usize,
    /// First row.
    pub y0: usize,
    /// One past the last column.
    pub x1: usize,
    /// One past the last row.
    pub y1: usize,
}

impl Rect {
    /// The whole `width x height` image.
    pub fn full(width: usize, height: usize) -> Rect {
        Rect {
            x0: 0,
            y0: 0,
            x1: width,
            y1: height,
        }
    }

    /// Width in pixels.
    pub fn width(&self) -> usize {
        self.x1.saturating_sub(self.x0)
    }

    /// Height in pixels.
    pub fn height(&self) -> usize {
        self.y1.saturating_sub(self.y0)
    }

    /// True when the rectangle holds no pixel.
    pub fn is_empty(&self) -> bool {
        self.width() == 0 || self.height() == 0
    }

    /// Grown by `margin` pixels on every side, clipped to `width x height`.
    pub fn expand(&self, margin: usize, width: usize, height: usize) -> Rect {
        Rect {
            x0: self.x0.saturating_sub(margin),
            y0: self.y0.saturating_sub(margin),
            x1: (self.x1 + margin).min(width),
            y1: (self.y1 + margin).min(height),
        }
    }

    /// The smallest rectangle holding both.
    pub fn union(&self, other: &Rect) -> Rect {
        if self.is_empty() {
            return *other;
        }
        if other.is_empty() {
            return *self;
        }
        Rect {
            x0: self.x0.min(other.x0),
            y0: self.y0.min(other.y0),
            x1: self.x1.max(other.x1),
            y1: self.y1.max(other.y1),
        }
    }

    /// True when pixel `(x, y)` is inside.
    pub fn contains(&self, x: usize, y: usize) -> bool {
        x >= self.x0 && x < self.x1 && y >= self.y0 && y < self.y1
    }
}

/// The four planes of an RGBA image, mutable.
///
/// # Panics
/// When the image does not have 4 planes.
pub fn rgba_planes_mut(img: &mut Image) -> [&mut [f32]; 4] {
    assert_eq!(
        img.channels, 4,
        "the classical operations work on 4-plane RGBA images"
    );
    let n = img.len();
    let (r, rest) = img.data.split_at_mut(n);
    let (g, rest) = rest.split_at_mut(n);
    let (b, a) = rest.split_at_mut(n);
    [r, g, b, a]
}

/// Rows `y0..y1` of an RGBA image as parallel bands of [`BAND_ROWS`] rows:
/// `(first row, [r, g, b, a])`, each plane slice holding whole rows.
pub fn par_bands_mut(
    img: &mut Image,
    y0: usize,
    y1: usize,
) -> impl IndexedParallelIterator<Item = (usize, [&mut [f32]; 4])> {
    let w = img.width;
    let [r, g, b, a] = rgba_planes_mut(img);
    let (lo, hi) = (y0 * w, y1 * w);
    let chunk = (BAND_ROWS * w).max(1);
    r[lo..hi]
        .par_chunks_mut(chunk)
        .zip(g[lo..hi].par_chunks_mut(chunk))
        .zip(b[lo..hi].par_chunks_mut(chunk))
        .zip(a[lo..hi].par_chunks_mut(chunk))
        .enumerate()
        .map(move |(i, (((r, g), b), a))| (y0 + i * BAND_ROWS, [r, g, b, a]))
}

/// The bounding box of the pixels where `plane > threshold`, with their count.
pub fn bbox_above(
    plane: &[f32],
    width: usize,
    height: usize,
    threshold: f32,
) -> Option<(Rect, usize)> {
    bbox_where(
        plane,
        width,
        height,
        |v| v > threshold,
        |row| row_max(row) > threshold,
    )
}

/// The bounding box of the pixels where `plane < threshold`, with their count.
pub fn bbox_below(
    plane: &[f32],
    width: usize,
    height: usize,
    threshold: f32,
) -> Option<(Rect, usize)> {
    bbox_where(
        plane,
        width,
        height,
        |v| v < threshold,
        |row| row_min(row) < threshold,
    )
}

fn bbox_where(
    plane: &[f32],
    width: usize,
    height: usize,
    pred: impl Fn(f32) -> bool + Sync,
    row_has: impl Fn(&[f32]) -> bool + Sync,
) -> Option<(Rect, usize)> {
    if width == 0 || height == 0 {
        return None;
    }
    let parts: Vec<Option<(Rect, usize)>> = plane[..width * height]
        .par_chunks(BAND_ROWS * width)
        .enumerate()
        .map(|(i, band)| {
            let mut out: Option<(Rect, usize)> = None;
            for (dy, row) in band.chunks(width).enumerate() {
                // A cheap vectorizable test first: most rows have no match.
                if !row_has(row) {
                    continue;
                }
                out = merge_boxes(out, row_box(i * BAND_ROWS + dy, row, &pred));
            }
            out
        })
        .collect();
    parts.into_iter().fold(None, merge_boxes)
}

/// `min` for finite values as one instruction (`f32::min` also orders NaN,
/// which costs extra instructions and blocks vectorization).
#[inline(always)]
pub fn fmin(a: f32, b: f32) -> f32 {
    if a < b {
        a
    } else {
        b
    }
}

/// `max` for finite values as one instruction (see [`fmin`]).
#[inline(always)]
pub fn fmax(a: f32, b: f32) -> f32 {
    if a > b {
        a
    } else {
        b
    }
}

/// The pixels of row `y` where `pred` holds: their (one-row) bounding box
/// and number; `None` where it holds nowhere.
#[inline]
pub fn row_box(y: usize, row: &[f32], pred: impl Fn(f32) -> bool) -> Option<(Rect, usize)> {
    // Searched from both ends (a row with some such pixels is often mostly
    // without), counted in a loop that vectorizes.
    let x0 = row.iter().position(|&v| pred(v))?;
    let x1 = row.iter().rposition(|&v| pred(v)).unwrap_or(x0) + 1;
    let count = row[x0..x1].iter().map(|&v| u32::from(pred(v))).sum::<u32>() as usize;
    let r = Rect {
        x0,
        y0: y,
        x1,
        y1: y + 1,
    };
    Some((r, count))
}

/// Two sets of found pixels (bounding box and number) as one: the boxes'
/// union, the numbers added. Order-free, so reductions of it do not depend
/// on the thread count.
pub fn merge_boxes(a: Option<(Rect, usize)>, b: Option<(Rect, usize)>) -> Option<(Rect, usize)> {
    match (a, b) {
        (Some((a, n)), Some((b, m))) => Some((a.union(&b), n + m)),
        (a, b) => a.or(b),
    }
}

/// The smallest value of a row (vectorizable: 8 independent lanes).
pub fn row_min(row: &[f32]) -> f32 {
    let mut acc = [f32::INFINITY; 8];
    let chunks = row.chunks_exact(8);
    let tail = chunks.remainder();
    for c in chunks {
        for k in 0..8 {
            acc[k] = fmin(acc[k], c[k]);
        }
    }
    tail.iter()
        .chain(acc.iter())
        .fold(f32::INFINITY, |m, &v| m.min(v))
}

/// The largest value of a row (vectorizable: 8 independent lanes).
pub fn row_max(row: &[f32]) -> f32 {
    let mut acc = [f32::NEG_INFINITY; 8];
    let chunks = row.chunks_exact(8);
    let tail = chunks.remainder();
    for c in chunks {
        for k in 0..8 {
            acc[k] = fmax(acc[k], c[k]);
        }
    }
    tail.iter()
        .chain(acc.iter())
        .fold(f32::NEG_INFINITY, |m, &v| m.max(v))
}

/// Solves `a x = b` by Gaussian elimination with partial pivoting; `None`
/// when a pivot falls below `tiny` (a singular system).
pub(crate) fn solve<const N: usize>(a: [[f64; N]; N], b: [f64; N], tiny: f64) -> Option<[f64; N]> {
    let (mut m, mut v) = (a, b);
    for c in 0..N {
        let p = (c..N).max_by(|&i, &j| m[i][c].abs().total_cmp(&m[j][c].abs()))?;
        if m[p][c].abs() < tiny {
            return None;
        }
        m.swap(c, p);
        v.swap(c, p);
        let (pivot, vc) = (m[c], v[c]);
        for (row, vr) in m.iter_mut().zip(v.iter_mut()).skip(c + 1) {
            let f = row[c] / pivot[c];
            for (x, p) in row.iter_mut().zip(pivot).skip(c) {
                *x -= f * p;
            }
            *vr -= f * vc;
        }
    }
    let mut x = [0.0f64; N];
    for c in (0..N).rev() {
        let s: f64 = (c + 1..N).map(|k| m[c][k] * x[k]).sum();
        x[c] = (v[c] - s) / m[c][c];
    }
    Some(x)
}

/// The median of `v` (the upper one of an even count; 0 when empty);
/// reorders `v`.
pub(crate) fn median(v: &mut [f32]) -> f32 {
    if v.is_empty() {
        return 0.0;
    }
    let k = v.len() / 2;
    *v.select_nth_unstable_by(k, f32::total_cmp).1
}

/// Fast base-2 logarithm of a positive finite value (absolute error below
/// 1e-4), exactly reproducible: bit manipulation plus a fixed polynomial.
#[inline]
pub fn fast_log2(x: f32) -> f32 {
    let bits = x.to_bits();
    let e = ((bits >> 23) & 0xff) as i32 - 127;
    // Mantissa in [1, 2); log2(m) from the series of log2((1+t)/(1-t)),
    // t = (m-1)/(m+1) in [0, 1/3).
    let m = f32::from_bits((bits & 0x007f_ffff) | 0x3f80_0000);
    let t = (m - 1.0) / (m + 1.0);
    let t2 = t * t;
    let p = t * (2.885_39 + t2 * (0.961_797 + t2 * (0.577_078 + t2 * 0.412_198)));
    e as f32 + p
}

/// Fast base-2 exponential (relative error below 1e-4), exactly
/// reproducible; saturates to 0 below -126 and to a large value above 127.
#[inline]
pub fn fast_exp2(x: f32) -> f32 {
    let x = x.clamp(-126.0, 127.0);
    // floor without a libm call: truncate, then step down for negative fractions.
    let t = x as i32;
    let fl = if (t as f32) > x { t - 1 } else { t };
    let f = x - fl as f32;
    // 2^f on [0,1): Taylor polynomial of degree 6 of exp(f ln 2).
    let p = 1.0
        + f * (std::f32::consts::LN_2
            + f * (0.240_226_5
                + f * (0.055_504_1 + f * (0.009_618_1 + f * (0.001_333_6 + f * 0.000_154_0)))));
    f32::from_bits(((fl + 127) as u32) << 23) * p
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn fast_log_exp_match_std() {
        let mut worst_log: f32 = 0.0;
        let mut worst_exp: f32 = 0.0;
        let mut x = 1e-6f32;
        while x < 1e6 {
            worst_log = worst_log.max((fast_log2(x) - x.log2()).abs());
            x *= 1.013;
        }
        let mut y = -20.0f32;
        while y < 20.0 {
            worst_exp = worst_exp.max((fast_exp2(y) / y.exp2() - 1.0).abs());
            y += 0.0137;
        }
        assert!(worst_log < 1e-4, "fast_log2 error {worst_log}");
        assert!(worst_exp < 1e-4, "fast_exp2 relative error {worst_exp}");
    }

    #[test]
    fn bbox_finds_the_marked_pixels() {
        let (w, h) = (40, 37);
        let mut p = vec![0.0; w * h];
        p[5 * w + 7] = 1.0;
        p[30 * w + 20] = 0.7;
        let (r, n) = bbox_above(&p, w, h, 0.5).unwrap();
        assert_eq!(
            (r, n),
            (
                Rect {
                    x0: 7,
                    y0: 5,
                    x1: 21,
                    y1: 31
                },
                2
            )
        );
        assert!(bbox_above(&p, w, h, 1.0).is_none());
        let (r, n) = bbox_below(&p, w, h, 0.5).unwrap();
        assert_eq!((r, n), (Rect::full(w, h), w * h - 2));
    }

    #[test]
    fn bands_cover_the_rows() {
        let mut img = Image::zeros(5, 40, 4);
        let rows: Vec<(usize, usize)> = par_bands_mut(&mut img, 3, 38)
            .map(|(y, p)| (y, p[0].len() / 5))
            .collect();
        assert_eq!(rows, vec![(3, 16), (19, 16), (35, 3)]);
    }
}
