//! Invertible color encoding between scene-linear HDR and the network's
//! range, with one exposure scale per frame (never per tile, so tiles agree).
//!
//! With exposure scale `s` and `log_range` `c`, the log encoding is
//! `y = log2(1 + s x) / c` and its inverse `x = (2^(c y) - 1) / s`; the linear
//! encoding is `y = s x`, `x = y / s`. The log curve is evaluated with
//! [`log2_1p`] and [`exp2_m1`]: exponent/mantissa splits and short
//! polynomials, branch-free so the row loops vectorize, within a relative
//! error of 1e-6 of the exact formula (checked against `f64` in the tests),
//! including arguments near 0 where `1 + v` would round.

use crate::frame::Image;
use crate::model::{Encoding, Exposure};

/// Coverage below this counts as a hole when color is unpremultiplied.
pub const COVERAGE_EPSILON: f32 = 1e-3;

/// Luminance floor inside the log-average (keeps black frames finite).
const LUMINANCE_FLOOR: f64 = 1e-4;

/// Rec.709 luminance weights.
const LUMA: [f64; 3] = [0.2126, 0.7152, 0.0722];

/// One frame's encoder/decoder.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct ColorCodec {
    /// Exposure scale `s` applied before the curve.
    pub scale: f32,
    /// `log_range` of a log encoding; `None` for linear.
    pub log_range: Option<f32>,
}

/// Pixels per block of [`log_average_luminance`]'s sums (fixed, so the
/// summation order does not depend on the thread count).
const LOG_AVERAGE_BLOCK: usize = 1 << 15;

/// The coverage-weighted log-average luminance of premultiplied color
/// (`exp(sum(w * ln(1e-4 + L)) / sum(w))`, L of the unpremultiplied color),
/// or `None` when nothing is covered. Deterministic: blocks of a fixed
/// number of pixels (32768) are summed in parallel (on the calling pool),
/// their sums added in block order.
pub fn log_average_luminance(color: &Image, coverage: Option<&[f32]>) -> Option<f64> {
    use rayon::prelude::*;
    let n = color.len();
    let (r, g, b) = (color.plane(0), color.plane(1), color.plane(2));
    let blocks: Vec<(f64, f64)> = (0..n.div_ceil(LOG_AVERAGE_BLOCK))
        .into_par_iter()
        .map(|k| {
            let mut sum = 0.0f64;
            let mut weight = 0.0f64;
            for i in k * LOG_AVERAGE_BLOCK..((k + 1) * LOG_AVERAGE_BLOCK).min(n) {
                let a = coverage.map_or(1.0, |c| c[i]);
                if a < COVERAGE_EPSILON {
                    continue;
                }
                let l = (LUMA[0] * r[i] as f64 + LUMA[1] * g[i] as f64 + LUMA[2] * b[i] as f64)
                    / a as f64;
                sum += a as f64 * (LUMINANCE_FLOOR + l).ln();
                weight += a as f64;
            }
            (sum, weight)
        })
        .collect();
    let (sum, weight) = blocks
        .iter()
        .fold((0.0f64, 0.0f64), |(s, w), &(bs, bw)| (s + bs, w + bw));
    (weight > 0.0).then(|| (sum / weight).exp())
}

impl ColorCodec {
    /// The codec for one frame: with `exposure: frame`, `s = key / log-average
    /// luminance` of the whole frame (1 when nothing is covered), clamped to 1e-6..=1e6.
    pub fn for_frame(encoding: &Encoding, color: &Image, coverage: Option<&[f32]>) -> ColorCodec {
        let (key, exposure, log_range) = match *encoding {
            Encoding::Linear { key, exposure } => (key, exposure, None),
            Encoding::Log {
                key,
                exposure,
                log_range,
            } => (key, exposure, Some(log_range)),
        };
        let scale = match exposure {
            Exposure::None => 1.0,
            Exposure::Frame => match log_average_luminance(color, coverage) {
                Some(avg) => (key as f64 / avg).clamp(1e-6, 1e6) as f32,
                None => 1.0,
            },
        };
        ColorCodec { scale, log_range }
    }

    /// Scene-linear (>= 0) to network value.
    #[inline(always)]
    pub fn encode(&self, x: f32) -> f32 {
        let v = x * self.scale;
        match self.log_range {
            None => v,
            Some(c) => log2_1p(v) * (1.0 / c),
        }
    }

    /// Network value back to scene-linear; negative or non-finite results
    /// become 0 (`+inf` becomes `f32::MAX`).
    #[inline(always)]
    pub fn decode(&self, y: f32) -> f32 {
        let v = match self.log_range {
            None => y * (1.0 / self.scale),
            Some(c) => exp2_m1(y * c) * (1.0 / self.scale),
        };
        clean(v)
    }

    /// Encodes a row: `dst[i] = encode(src[i])`.
    pub fn encode_row(&self, src: &[f32], dst: &mut [f32]) {
        crate::ops::simd(RowJob {
            codec: self,
            op: RowOp::Encode(src),
            dst,
        });
    }

    /// Encodes a row of premultiplied color as straight color:
    /// `dst[i] = encode(src[i] / alpha[i])`, 0 where `alpha < COVERAGE_EPSILON`.
    pub fn encode_straight_row(&self, src: &[f32], alpha: &[f32], dst: &mut [f32]) {
        crate::ops::simd(RowJob {
            codec: self,
            op: RowOp::EncodeStraight(src, alpha),
            dst,
        });
    }

    /// Decodes a row: `dst[i] = decode(src[i])`.
    pub fn decode_row(&self, src: &[f32], dst: &mut [f32]) {
        crate::ops::simd(RowJob {
            codec: self,
            op: RowOp::Decode(src),
            dst,
        });
    }

    /// [`ColorCodec::decode_row`] of `net + inp` (a residual model's
    /// output plus its encoded input), element by element.
    pub fn decode_sum_row(&self, net: &[f32], inp: &[f32], dst: &mut [f32]) {
        crate::ops::simd(RowJob {
            codec: self,
            op: RowOp::DecodeSum(net, inp),
            dst,
        });
    }

    #[inline(always)]
    fn encode_row_in(&self, src: &[f32], dst: &mut [f32]) {
        let s = self.scale;
        match self.log_range {
            None => dst.iter_mut().zip(src).for_each(|(d, &x)| *d = x * s),
            Some(c) => {
                let inv_c = 1.0 / c;
                dst.iter_mut()
                    .zip(src)
                    .for_each(|(d, &x)| *d = log2_1p(x * s) * inv_c);
            }
        }
    }

    #[inline(always)]
    fn encode_straight_row_in(&self, src: &[f32], alpha: &[f32], dst: &mut [f32]) {
        for ((d, &x), &a) in dst.iter_mut().zip(src).zip(alpha) {
            let v = if a >= COVERAGE_EPSILON { x / a } else { 0.0 };
            *d = v;
        }
        // Second pass in place keeps the first loop a plain select and this one the curve.
        let s = self.scale;
        match self.log_range {
            None => dst.iter_mut().for_each(|d| *d *= s),
            Some(c) => {
                let inv_c = 1.0 / c;
                dst.iter_mut().for_each(|d| *d = log2_1p(*d * s) * inv_c);
            }
        }
    }

    #[inline(always)]
    fn decode_row_in(&self, src: &[f32], dst: &mut [f32]) {
        let inv_s = 1.0 / self.scale;
        match self.log_range {
            None => dst
                .iter_mut()
                .zip(src)
                .for_each(|(d, &y)| *d = clean(y * inv_s)),
            Some(c) => dst
                .iter_mut()
                .zip(src)
                .for_each(|(d, &y)| *d = clean(exp2_m1(y * c) * inv_s)),
        }
    }
}

/// What a [`RowJob`] computes into its `dst`.
enum RowOp<'a> {
    Encode(&'a [f32]),
    EncodeStraight(&'a [f32], &'a [f32]),
    Decode(&'a [f32]),
    DecodeSum(&'a [f32], &'a [f32]),
}

/// One row of the codec compiled for the CPU's widest vectors
/// ([`crate::ops::simd`]): the same operations in the same order as the
/// baseline (no fused multiply-add), so the same bits.
struct RowJob<'a> {
    codec: &'a ColorCodec,
    op: RowOp<'a>,
    dst: &'a mut [f32],
}

impl pulp::WithSimd for RowJob<'_> {
    type Output = ();

    #[inline(always)]
    fn with_simd<S: pulp::Simd>(self, _: S) {
        let RowJob { codec, op, dst } = self;
        match op {
            RowOp::Encode(src) => codec.encode_row_in(src, dst),
            RowOp::EncodeStraight(src, alpha) => codec.encode_straight_row_in(src, alpha, dst),
            RowOp::Decode(src) => codec.decode_row_in(src, dst),
            RowOp::DecodeSum(net, inp) => {
                dst.iter_mut()
                    .zip(net.iter().zip(inp))
                    .for_each(|(d, (&r, &i))| *d = r + i);
                // Decode in place.
                for d in dst.iter_mut() {
                    *d = codec.decode(*d);
                }
            }
        }
    }
}

/// Negative and NaN to 0, `+inf` to `f32::MAX` (branch-free).
#[inline(always)]
fn clean(v: f32) -> f32 {
    let v = v.min(f32::MAX);
    if v >= 0.0 {
        v
    } else {
        0.0
    }
}

/// Largest argument [`log2_1p`] takes; larger ones are clamped (2^123).
const LOG_INPUT_MAX: f32 = 1.0633824e37;

/// `log2(1 + v)` for `v >= 0` (clamped to 2^123), within a relative error of
/// 1e-6 everywhere, small `v` included.
///
/// `1 + v = 2^k m` with `m` in `[sqrt(1/2), sqrt(2))` (from the bits of the
/// rounded `1 + v`); `m - 1` is recomputed from `v` itself so no precision is
/// lost to the rounding of `1 + v`; then `ln m = 2 atanh(t)`,
/// `t = (m - 1) / (m + 1)`, `|t| <= 0.1716`, by its odd series to `t^9`
/// (truncation below 1e-8 relative).
#[inline(always)]
pub fn log2_1p(v: f32) -> f32 {
    const SQRT_HALF_BITS: u32 = 0x3f35_04f3;
    let v = v.clamp(0.0, LOG_INPUT_MAX);
    let u = 1.0 + v;
    let k = (u.to_bits().wrapping_sub(SQRT_HALF_BITS) as i32) >> 23;
    let two_k = f32::from_bits(((127 + k) as u32) << 23);
    let two_neg_k = f32::from_bits(((127 - k) as u32) << 23);
    let m1 = (v + (1.0 - two_k)) * two_neg_k;
    let t = m1 / (m1 + 2.0);
    let t2 = t * t;
    const C3: f32 = 1.0 / 3.0;
    const C5: f32 = 1.0 / 5.0;
    const C7: f32 = 1.0 / 7.0;
    const C9: f32 = 1.0 / 9.0;
    let series = 1.0 + t2 * (C3 + t2 * (C5 + t2 * (C7 + t2 * C9)));
    const TWO_OVER_LN2: f32 = 2.0 / std::f32::consts::LN_2;
    k as f32 + (t * TWO_OVER_LN2) * series
}

/// Arguments of [`exp2_m1`] are clamped to this range (the upper end is the
/// decoder's historic `e^80` cap).
const EXP_INPUT_RANGE: (f32, f32) = (-64.0, 80.0 / std::f32::consts::LN_2);

/// `2^x - 1`, within a relative error of 1e-6, `x` near 0 included; `x` is
/// clamped to `[-64, 80 / ln 2]` and NaN gives `2^-64 - 1` (negative).
///
/// `x = n + f`, `n` the nearest integer, `|f| <= 1/2`; `2^f - 1` by its
/// Taylor series in `z = f ln 2` to `z^7` (truncation below 2e-8 relative);
/// then `2^x - 1 = (2^n - 1) + 2^n (2^f - 1)`, exact in its first term.
#[inline(always)]
pub fn exp2_m1(x: f32) -> f32 {
    // Round to nearest by the 1.5 * 2^23 trick (valid for |x| < 2^22).
    const ROUND: f32 = 12_582_912.0;
    let x = x.max(EXP_INPUT_RANGE.0).min(EXP_INPUT_RANGE.1);
    let r = x + ROUND;
    let n = r - ROUND;
    let ni = r.to_bits() as i32 - ROUND.to_bits() as i32;
    let z = (x - n) * std::f32::consts::LN_2;
    let p = z
        * (1.0
            + z * (1.0 / 2.0
                + z * (1.0 / 6.0
                    + z * (1.0 / 24.0
                        + z * (1.0 / 120.0 + z * (1.0 / 720.0 + z * (1.0 / 5040.0)))))));
    let two_n = f32::from_bits(((ni + 127) as u32) << 23);
    (two_n - 1.0) + two_n * p
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn log_average_of_constant_is_the_constant() {
        let img = Image::filled(4, 3, 3, 0.5);
        let avg = log_average_luminance(&img, None).unwrap();
        assert!((avg - (0.5 + 1e-4)).abs() < 1e-9, "{avg}");
        let cov = vec![0.0; 12];
        assert_eq!(log_average_luminance(&img, Some(&cov)), None);
    }

    /// Over several blocks, the log-average is the same bits on 1 and 3
    /// threads and within 1e-12 of one sequential sum.
    #[test]
    fn log_average_is_independent_of_the_thread_count() {
        let (w, h) = (500, 200);
        let mut img = Image::filled(w, h, 3, 0.0);
        for (i, v) in img.data.iter_mut().enumerate() {
            *v = 0.01 + ((i * 7919) % 1000) as f32 * 0.01;
        }
        let cov: Vec<f32> = (0..w * h).map(|i| ((i * 31) % 17) as f32 / 16.0).collect();
        let on = |threads: usize| {
            rayon::ThreadPoolBuilder::new()
                .num_threads(threads)
                .build()
                .unwrap()
                .install(|| log_average_luminance(&img, Some(&cov)).unwrap())
        };
        let one = on(1);
        assert_eq!(one.to_bits(), on(3).to_bits());
        let (mut sum, mut weight) = (0.0f64, 0.0f64);
        for (i, &c) in cov.iter().enumerate() {
            let a = c as f64;
            if c < COVERAGE_EPSILON {
                continue;
            }
            let p = |c: usize| img.data[c * w * h + i] as f64;
            let l = (LUMA[0] * p(0) + LUMA[1] * p(1) + LUMA[2] * p(2)) / a;
            sum += a * (LUMINANCE_FLOOR + l).ln();
            weight += a;
        }
        assert!(((sum / weight).exp() - one).abs() < 1e-12 * one, "{one}");
    }

    /// f32 values from `lo` to `hi` in geometric steps of about `ratio`, plus every
    /// value near the exponent/mantissa split points.
    fn sweep(lo: f32, hi: f32, ratio: f32) -> Vec<f32> {
        let mut v = vec![0.0f32];
        let mut x = lo;
        while x < hi {
            v.push(x);
            x = (x * ratio).max(f32::from_bits(x.to_bits() + 1));
        }
        for s in [0.5f32.sqrt(), 2f32.sqrt(), 1.0, 2.0, 4.0] {
            for d in -200i32..=200 {
                v.push(f32::from_bits((s.to_bits() as i32 + d) as u32) - 1.0);
            }
        }
        v.retain(|&x| x >= 0.0);
        v
    }

    /// Relative error of `got` against the f64 reference `want` over `xs`
    /// is at most 1e-6 (absolute where the reference is 0).
    fn assert_accurate(xs: Vec<f32>, got: fn(f32) -> f32, want: fn(f64) -> f64) {
        let mut worst = (0.0f64, 0.0f32);
        for x in xs {
            let (g, w) = (got(x) as f64, want(x as f64));
            let rel = if w == 0.0 {
                g.abs()
            } else {
                ((g - w) / w).abs()
            };
            if rel > worst.0 {
                worst = (rel, x);
            }
        }
        assert!(
            worst.0 <= 1e-6,
            "worst relative error {} at {}",
            worst.0,
            worst.1
        );
    }

    #[test]
    fn fast_log2_1p_is_accurate() {
        assert_accurate(sweep(1e-30, 1e37, 1.0001), log2_1p, |x| {
            x.ln_1p() / std::f64::consts::LN_2
        });
        assert_eq!(log2_1p(0.0), 0.0);
        assert_eq!(log2_1p(f32::INFINITY), log2_1p(LOG_INPUT_MAX));
    }

    #[test]
    fn fast_exp2_m1_is_accurate() {
        let mut xs = sweep(1e-30, 115.0, 1.0001);
        xs.extend(xs.clone().iter().map(|x| -x).filter(|&x| x >= -64.0));
        for x in [0.5f32, -0.5, 1.5, -1.5] {
            for d in -100i32..=100 {
                xs.push(f32::from_bits((x.to_bits() as i32 + d) as u32));
            }
        }
        assert_accurate(xs, exp2_m1, |x| (x * std::f64::consts::LN_2).exp_m1());
        assert_eq!(exp2_m1(0.0), 0.0);
        assert!(exp2_m1(f32::NAN) < 0.0);
        assert!(exp2_m1(1e9).is_finite());
    }

    #[test]
    fn rows_match_the_scalar_codec() {
        let codec = ColorCodec {
            scale: 3.7,
            log_range: Some(8.0),
        };
        let src: Vec<f32> = (0..1000)
            .map(|i| (i as f32 * 0.37).powi(3) * 1e-3)
            .collect();
        let alpha: Vec<f32> = (0..1000).map(|i| (i % 7) as f32 / 6.0).collect();
        let mut enc = vec![0.0; src.len()];
        codec.encode_row(&src, &mut enc);
        let mut straight = vec![0.0; src.len()];
        codec.encode_straight_row(&src, &alpha, &mut straight);
        let mut dec = vec![0.0; src.len()];
        codec.decode_row(&enc, &mut dec);
        for i in 0..src.len() {
            assert_eq!(enc[i], codec.encode(src[i]));
            let a = alpha[i];
            let s = if a >= COVERAGE_EPSILON {
                codec.encode(src[i] / a)
            } else {
                0.0
            };
            assert_eq!(straight[i], s);
            assert_eq!(dec[i], codec.decode(enc[i]));
            assert!(
                (dec[i] - src[i]).abs() <= 2e-6 * src[i],
                "{} -> {}",
                src[i],
                dec[i]
            );
        }
        let bad = [f32::NAN, -5.0, f32::INFINITY, 1e30];
        let mut out = [0.0; 4];
        codec.decode_row(&bad, &mut out);
        assert_eq!(out[..2], [0.0, 0.0]);
        assert!(
            out[2..].iter().all(|v| v.is_finite() && *v > 0.0),
            "{out:?}"
        );
    }
}
