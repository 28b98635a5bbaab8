//! Invertible color encoding between scene-linear HDR and the network's
//! range, with one exposure scale per frame (never per tile, so tiles agree).

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

/// The coverage-weighted log-average luminance of premultiplied color
/// (`exp(sum(w * ln(1e-4 + L)) / sum(w))`, L of the unpremultiplied color),
/// or `None` when nothing is covered. Deterministic (fixed summation order).
pub fn log_average_luminance(color: &Image, coverage: Option<&[f32]>) -> Option<f64> {
    let n = color.len();
    let (r, g, b) = (color.plane(0), color.plane(1), color.plane(2));
    let mut sum = 0.0f64;
    let mut weight = 0.0f64;
    for i in 0..n {
        let a = coverage.map_or(1.0, |c| c[i]);
        if a < COVERAGE_EPSILON {
            continue;
        }
        let l = (LUMA[0] * r[i] as f64 + LUMA[1] * g[i] as f64 + LUMA[2] * b[i] as f64) / a as f64;
        sum += a as f64 * (LUMINANCE_FLOOR + l).ln();
        weight += a as f64;
    }
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
    #[inline]
    pub fn encode(&self, x: f32) -> f32 {
        let v = x * self.scale;
        match self.log_range {
            None => v,
            Some(c) => v.ln_1p() / (std::f32::consts::LN_2 * c),
        }
    }

    /// Network value back to scene-linear; negative or non-finite results become 0.
    #[inline]
    pub fn decode(&self, y: f32) -> f32 {
        let v = match self.log_range {
            None => y / self.scale,
            Some(c) => (y * c * std::f32::consts::LN_2).min(80.0).exp_m1() / self.scale,
        };
        if v >= 0.0 && v.is_finite() {
            v
        } else if v == f32::INFINITY {
            f32::MAX
        } else {
            0.0
        }
    }
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
}
