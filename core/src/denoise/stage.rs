//! The session's denoise stage: Open Image Denoise on a prepared frame's
//! color, before the backend, so the history and the temporal
//! stabilization work on denoised frames; and the `denoise auto` decision.
//!
//! The temporal accumulation that follows it, once the session knows
//! whether the frame continues the sequence, is [`crate::denoise::accumulate`].

use std::sync::Arc;

use rayon::prelude::*;

use super::{DenoiseInput, DenoiseOptions, Denoiser, Oidn, Quality};
use crate::error::Result;
use crate::frame::{try_zeros, Image, PreparedFrame};

/// What `denoise` came to for a sequence: decided on its first frame
/// after a reset (other than a scene cut) and kept until the next one.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub struct Decision {
    /// Whether Open Image Denoise runs on the frames (the spatial pass).
    pub on: bool,
    /// Whether the frames are accumulated over time
    /// ([`crate::denoise::accumulate`]): after the spatial pass, or alone
    /// for frames the renderer denoised (`denoise temporal`).
    pub temporal: bool,
}

impl Decision {
    /// Neither pass.
    pub const OFF: Decision = Decision {
        on: false,
        temporal: false,
    };
    /// Both passes.
    pub const ON: Decision = Decision {
        on: true,
        temporal: true,
    };
    /// The temporal accumulation alone.
    pub const TEMPORAL: Decision = Decision {
        on: false,
        temporal: true,
    };
}

/// The denoiser of one session (created on its first denoised frame) and
/// its interleaved buffers, reused from frame to frame.
#[derive(Debug, Default)]
pub struct Stage {
    denoiser: Option<Denoiser>,
    color: Vec<f32>,
    out: Vec<f32>,
    albedo: Vec<f32>,
    normal: Vec<f32>,
}

impl Stage {
    /// A stage with no denoiser yet.
    pub fn new() -> Stage {
        Stage::default()
    }

    /// Frame-sized f32 planes the stage holds while it denoises a frame
    /// with (`albedo`) an albedo and (`normal`) a normal: the interleaved
    /// color, the output, and each auxiliary image with its prefiltered
    /// copy (counted whether or not `denoise_prefilter` is on; Open Image
    /// Denoise's own working memory, bounded by its tiling, is not
    /// counted).
    pub fn working_planes(albedo: bool, normal: bool) -> usize {
        6 + 6 * usize::from(albedo) + 6 * usize::from(albedo && normal)
    }

    /// Denoises the premultiplied RGB (the first 3 planes) of `frame` in
    /// place with OIDN's RT filter on `oidn`: HDR, `quality`, with
    /// `frame.albedo` when present and then the normal
    /// (`frame.denoise_normal`, else `frame.normal`), both prefiltered when
    /// `prefilter` (`denoise_prefilter`; else one filter run with OIDN's
    /// `cleanAux` off), within `max_memory` bytes of OIDN working memory
    /// when given (OIDN's `maxMemoryMB`: smaller tiles; best effort):
    /// a renderer's albedo and normal are noisy too, with
    /// depth of field, motion blur and glossy surfaces. The frame's
    /// scene-cut samples are taken again from the denoised color.
    ///
    /// Coverage: the color is denoised premultiplied, as the renderer
    /// wrote it (holes black; their albedo and normal are 0 too, so OIDN
    /// sees an edge and keeps it), and the result is taken wherever the
    /// coverage is above 0. A soft border pixel is an anti-aliased edge
    /// between the surface and the black hole, which is what a denoiser is
    /// trained on, so its denoised value is the premultiplied color
    /// without the noise. Denoising un-premultiplied color instead would
    /// divide the noise of a thinly covered pixel by its coverage and hand
    /// OIDN outliers. Where the coverage is 0 the input is kept (holes are
    /// the backend's business, and OIDN would spread the border into them).
    ///
    /// Errors: OIDN's, naming the step; [`crate::Error::OutOfMemory`]
    /// when a buffer cannot be allocated. The frame's color is unchanged
    /// on error.
    pub fn run(
        &mut self,
        oidn: &Arc<Oidn>,
        frame: &mut PreparedFrame,
        quality: Quality,
        prefilter: bool,
        max_memory: Option<usize>,
        pool: &rayon::ThreadPool,
    ) -> Result<()> {
        let (w, h) = (frame.width(), frame.height());
        let values = crate::frame::sample_count(w, h, 3)?;
        if self.denoiser.is_none() {
            self.denoiser = Some(Denoiser::new(oidn)?);
        }
        let normal = frame.denoise_normal.as_ref().or(frame.normal.as_ref());
        let aux = frame.albedo.as_ref().map(|a| (a, normal));
        ensure(&mut self.color, values)?;
        ensure(&mut self.out, values)?;
        interleave(&frame.color, &mut self.color, pool);
        if let Some((albedo, normal)) = aux {
            ensure(&mut self.albedo, values)?;
            interleave(albedo, &mut self.albedo, pool);
            if let Some(n) = normal {
                ensure(&mut self.normal, values)?;
                interleave(n, &mut self.normal, pool);
            }
        }
        let input = DenoiseInput {
            width: w,
            height: h,
            color: &self.color,
            albedo: aux.map(|_| &self.albedo[..]),
            normal: aux.and_then(|(_, n)| n).map(|_| &self.normal[..]),
        };
        let options = DenoiseOptions {
            hdr: true,
            quality,
            clean_aux: false,
            prefilter,
            // At least 1 MiB: 0 would ask OIDN for the impossible.
            max_memory_mb: max_memory.map(|b| u32::try_from((b >> 20).max(1)).unwrap_or(u32::MAX)),
        };
        let denoiser = self.denoiser.as_mut().expect("created above");
        denoiser.denoise(&input, options, &mut self.out)?;
        write_back(&self.out, frame, pool);
        let lattice = crate::temporal::Lattice::new(w, h);
        frame.scene_samples = None;
        frame.scene_samples =
            Some(crate::temporal::scene_cut::current_samples(&lattice, frame).into_owned());
        Ok(())
    }
}

/// Makes `buf` hold `len` samples (contents arbitrary), fallibly.
fn ensure(buf: &mut Vec<f32>, len: usize) -> Result<()> {
    if buf.len() != len {
        *buf = Vec::new();
        *buf = try_zeros(len)?;
    }
    Ok(())
}

/// The first 3 planes of `img`, interleaved into `out`, row-parallel.
fn interleave(img: &Image, out: &mut [f32], pool: &rayon::ThreadPool) {
    let (w, n) = (img.width, img.width * img.height);
    let planes = [&img.data[..n], &img.data[n..2 * n], &img.data[2 * n..3 * n]];
    pool.install(|| {
        out.par_chunks_mut(3 * w).enumerate().for_each(|(y, row)| {
            for (x, px) in row.chunks_exact_mut(3).enumerate() {
                let p = y * w + x;
                px.copy_from_slice(&[planes[0][p], planes[1][p], planes[2][p]]);
            }
        })
    });
}

/// The denoised interleaved RGB `out` into the first 3 planes of
/// `frame.color` where the coverage is above 0 (see [`Stage::run`]);
/// negative or non-finite results (OIDN's HDR output should have none)
/// keep the input, so the planes stay what the backends expect.
fn write_back(out: &[f32], frame: &mut PreparedFrame, pool: &rayon::ThreadPool) {
    let w = frame.width();
    let n = w * frame.height();
    let coverage = frame.coverage.as_deref();
    let (rgb, _) = frame.color.data.split_at_mut(3 * n);
    let (r, gb) = rgb.split_at_mut(n);
    let (g, b) = gb.split_at_mut(n);
    pool.install(|| {
        r.par_chunks_mut(w)
            .zip(g.par_chunks_mut(w))
            .zip(b.par_chunks_mut(w))
            .enumerate()
            .for_each(|(y, ((r, g), b))| {
                let src = &out[3 * w * y..3 * w * (y + 1)];
                for x in 0..w {
                    let keep = coverage.is_some_and(|c| c[y * w + x] <= 0.0);
                    for (c, plane) in [&mut *r, &mut *g, &mut *b].into_iter().enumerate() {
                        let v = src[3 * x + c];
                        let good = !keep && (0.0..f32::INFINITY).contains(&v);
                        plane[x] = if good { v } else { plane[x] };
                    }
                }
            })
    });
}
