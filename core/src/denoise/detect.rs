//! Is a frame noisy? A cheap, robust estimate of its per-pixel noise,
//! which `denoise auto` compares with [`NOISE_THRESHOLD`] on the first
//! frame of a sequence when the host does not say how many samples it
//! rendered.
//!
//! **The statistic.** On log2 luminance `L = log2(Y + floor)` (`Y` the
//! Rec.709 luminance, `floor` 2 % of the frame's median luminance, so
//! black and near-black pixels do not dominate), the 5-point Laplacian
//! `4 L(p) - L(left) - L(right) - L(up) - L(down)`; its median absolute
//! value over the covered pixels, divided by `0.6745 * sqrt(20)`, is the
//! standard deviation, in stops, of the white noise that would give it.
//! Monte Carlo noise is close to white from pixel to pixel and roughly
//! proportional to the signal (hence the logarithm: the same level in the
//! dark and the bright parts), while a clean render is smooth almost
//! everywhere: its edges and textures cover less than half of the pixels,
//! which the median ignores.
//!
//! Measured (see `ARCHITECTURE.md`, "Denoise stage"): the out-of-domain
//! hall scene (Cycles, 320x180, 24 frames) gives 0.060-0.090 clean (128
//! samples and OIDN), 0.401-0.518 at 4 samples per pixel and 0.037-0.053
//! through Cycles' own denoiser; the courtyard, clean and full of
//! foliage-like texture, 0.081-0.088; the synthetic demo scene 0.13 (its
//! deliberate per-pixel noise, mostly in its dark parts). The threshold,
//! 0.2, sits at the geometric middle of the clean and the 4-sample real
//! frames; by the `1 / sqrt(samples)` law the hall crosses it near 24
//! samples per pixel, so from there to 64 it is the host's `samples` that
//! turns `denoise auto` on.
//!
//! Rows are sampled (at most [`MAX_ROWS`] rows, all their pixels): about
//! 23 ms at 1080p on 2 threads (`denoise_session::noise_level_timing`),
//! once per sequence; the result does not depend on the number of threads
//! (the median of the same values).

use rayon::prelude::*;

use crate::frame::Image;
use crate::ops::inpaint::FULL;
use crate::ops::{fast_log2, median};

/// Above this [`noise_level`] (stops of white noise in log2 luminance),
/// `denoise auto` turns the denoise stage on.
pub const NOISE_THRESHOLD: f32 = 0.2;

/// The luminance floor relative to the frame's median luminance.
const FLOOR: f32 = 0.02;

/// The least absolute floor (a black frame).
const MIN_FLOOR: f32 = 1e-6;

/// The most rows [`noise_level`] looks at.
pub const MAX_ROWS: usize = 256;

/// The fewest pixels [`noise_level`] needs to say anything.
const MIN_PIXELS: usize = 256;

/// `0.6745 * sqrt(20)`: the median absolute value of the 5-point
/// Laplacian of unit white noise.
const LAPLACIAN_MAD: f32 = 3.016_4;

/// The estimated per-pixel noise of the premultiplied RGB in the first 3
/// planes of `color` (see the module's documentation), in stops; pixels
/// where any of the five taps has coverage below 1 are left out. `None`
/// when fewer than 256 pixels could be measured (a tiny frame, or one
/// that is almost all hole). Row-parallel on `pool` when given.
pub fn noise_level(
    color: &Image,
    coverage: Option<&[f32]>,
    pool: Option<&rayon::ThreadPool>,
) -> Option<f32> {
    let (w, h) = (color.width, color.height);
    if w < 3 || h < 3 || color.channels < 3 {
        return None;
    }
    let n = w * h;
    let (r, g, b) = (
        &color.data[..n],
        &color.data[n..2 * n],
        &color.data[2 * n..3 * n],
    );
    let luma = |p: usize| (0.2126 * r[p] + 0.7152 * g[p] + 0.0722 * b[p]).max(0.0);
    let covered = |p: usize| coverage.is_none_or(|c| c[p] >= FULL);
    let step = (h - 2).div_ceil(MAX_ROWS).max(1);
    let rows: Vec<usize> = (1..h - 1).step_by(step).collect();
    let run = |f: &(dyn Fn(&usize) -> Vec<f32> + Sync)| -> Vec<f32> {
        match pool {
            Some(pool) => pool.install(|| rows.par_iter().flat_map_iter(f).collect()),
            None => rows.iter().flat_map(f).collect(),
        }
    };
    // The floor: a share of the median luminance of the sampled rows.
    let mut lum = run(&|&y| {
        (y * w..(y + 1) * w)
            .filter(|&p| covered(p))
            .map(luma)
            .collect()
    });
    if lum.len() < MIN_PIXELS {
        return None;
    }
    let floor = (FLOOR * median(&mut lum)).max(MIN_FLOOR);
    let mut lap = run(&|&y| {
        let log_row = |y: usize| -> Vec<f32> {
            (y * w..(y + 1) * w)
                .map(|p| fast_log2(luma(p) + floor))
                .collect()
        };
        let (up, mid, down) = (log_row(y - 1), log_row(y), log_row(y + 1));
        (1..w - 1)
            .filter(|&x| {
                let p = y * w + x;
                covered(p) && covered(p - 1) && covered(p + 1) && covered(p - w) && covered(p + w)
            })
            .map(|x| (4.0 * mid[x] - mid[x - 1] - mid[x + 1] - up[x] - down[x]).abs())
            .collect()
    });
    if lap.len() < MIN_PIXELS {
        return None;
    }
    Some(median(&mut lap) / LAPLACIAN_MAD)
}

#[cfg(test)]
mod tests {
    use super::*;

    fn splitmix(mut x: u64) -> u64 {
        x = x.wrapping_add(0x9E37_79B9_7F4A_7C15);
        x = (x ^ (x >> 30)).wrapping_mul(0xBF58_476D_1CE4_E5B9);
        x = (x ^ (x >> 27)).wrapping_mul(0x94D0_49BB_1331_11EB);
        x ^ (x >> 31)
    }

    /// A smooth HDR gradient with hard-edged 32-pixel tiles (their edges
    /// touch an eighth of the pixels, which moves the median a little), times `1 + sigma * n`
    /// per pixel (`n` of unit variance, nearly Gaussian: a sum of 4
    /// uniform variables).
    fn image(w: usize, h: usize, sigma: f32) -> Image {
        let mut img = Image::zeros(w, h, 3);
        let n = w * h;
        for y in 0..h {
            for x in 0..w {
                let p = y * w + x;
                let tile = if (x / 32 + y / 32) % 2 == 0 { 1.0 } else { 0.3 };
                let base = tile * (0.2 + 2.0 * x as f32 / w as f32);
                let u: f32 = (0..4u64)
                    .map(|k| (splitmix((p as u64) << 2 | k) >> 40) as f32 / (1u64 << 24) as f32)
                    .sum();
                let noise = 1.0 + sigma * (u - 2.0) * 3f32.sqrt();
                for c in 0..3 {
                    img.data[c * n + p] = base * noise * [1.0, 0.8, 0.6][c];
                }
            }
        }
        img
    }

    #[test]
    fn clean_is_low_noisy_is_high_and_scales_with_the_noise() {
        let clean = noise_level(&image(320, 180, 0.0), None, None).unwrap();
        assert!(clean < 0.02, "clean {clean}");
        let mut last = clean;
        for sigma in [0.05f32, 0.2, 0.5] {
            let level = noise_level(&image(320, 180, sigma), None, None).unwrap();
            // Relative noise sigma is about sigma / ln 2 stops.
            let stops = sigma / std::f32::consts::LN_2;
            assert!(
                level > 0.75 * stops && level < 1.33 * stops,
                "sigma {sigma}: {level} (about {stops})"
            );
            assert!(level > last);
            last = level;
        }
    }

    #[test]
    fn holes_are_left_out_and_tiny_frames_say_nothing() {
        let mut img = image(64, 64, 0.0);
        // A black hole over a third of the frame: its edges would count
        // as noise if the pixels around it were measured.
        let mut cov = vec![1.0f32; 64 * 64];
        for y in 0..64 {
            for x in 0..64 {
                if (x / 4 + y / 4) % 3 == 0 {
                    cov[y * 64 + x] = 0.0;
                    for c in 0..3 {
                        img.data[c * 64 * 64 + y * 64 + x] = 0.0;
                    }
                }
            }
        }
        let level = noise_level(&img, Some(&cov), None).unwrap();
        assert!(level < 0.02, "{level}");
        assert!(noise_level(&image(8, 8, 0.5), None, None).is_none());
        assert!(noise_level(&img, Some(&vec![0.0; 64 * 64]), None).is_none());
    }
}
