//! One frame's inputs as the host gives them (strided views), and the
//! prepared planar form the pipeline uses (validated, converted to the
//! library's conventions, sanitized).

use rayon::prelude::*;

use super::{Camera, Image, ImageView};
use crate::error::{Error, Result};

/// Reads channel `c` of `view` into `plane` row by row (in parallel on `pool`
/// when given) and applies `fix` to every sample; returns how many samples
/// `fix` reported as replaced.
fn read_plane(
    pool: Option<&rayon::ThreadPool>,
    view: &ImageView<'_>,
    c: usize,
    plane: &mut [f32],
    fix: impl Fn(&mut f32) -> bool + Sync,
) -> usize {
    let w = view.width();
    let row = |(y, row): (usize, &mut [f32])| -> usize {
        view.read_row(y, c, row);
        row.iter_mut().map(|v| usize::from(fix(v))).sum()
    };
    match pool {
        Some(pool) => pool.install(|| plane.par_chunks_mut(w).enumerate().map(row).sum()),
        None => plane.chunks_mut(w).enumerate().map(row).sum(),
    }
}

/// How the depth AOV measures distance.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Default)]
pub enum DepthKind {
    /// Distance along the camera's view axis (Cycles' Depth pass). The default.
    #[default]
    Planar,
    /// Distance along the ray from the camera centre; needs the camera to convert.
    Euclidean,
}

/// One rendered frame as the host hands it over. Only `color` is required.
#[derive(Debug, Clone, Copy)]
pub struct FrameInput<'a> {
    /// Scene-linear Linear Rec.709 color, premultiplied by coverage; the first
    /// 3 channels are RGB (a 4th channel, if described, is ignored).
    pub color: ImageView<'a>,
    /// Depth (1 channel), see [`DepthKind`]; empty pixels carry a very large value.
    pub depth: Option<ImageView<'a>>,
    /// Motion vectors (2 channels): pixels from the current pixel to where the
    /// same surface point was in the previous frame, x right, y down, after
    /// multiplying by `motion_vector_scale`.
    pub motion: Option<ImageView<'a>>,
    /// Normals (3 channels), any space.
    pub normal: Option<ImageView<'a>>,
    /// Coverage in [0,1] (1 channel): 0 where the renderer had no data (a hole).
    pub coverage: Option<ImageView<'a>>,
    /// Insert mask in [0,1] (1 channel): where an inserted object is.
    pub insert_mask: Option<ImageView<'a>>,
    /// The camera of this frame.
    pub camera: Option<Camera>,
    /// The host's frame number; a gap triggers the session's gap policy.
    pub frame_index: Option<i64>,
    /// Drop the temporal state before this frame.
    pub reset: bool,
    /// Multiplies the motion AOV into the library's convention (for example
    /// `[1, -1]` for +y-up vectors).
    pub motion_vector_scale: [f32; 2],
}

impl<'a> FrameInput<'a> {
    /// A frame with color only.
    pub fn new(color: ImageView<'a>) -> Self {
        FrameInput {
            color,
            depth: None,
            motion: None,
            normal: None,
            coverage: None,
            insert_mask: None,
            camera: None,
            frame_index: None,
            reset: false,
            motion_vector_scale: [1.0, 1.0],
        }
    }

    /// Width of the frame (the color image's).
    pub fn width(&self) -> usize {
        self.color.width()
    }

    /// Height of the frame (the color image's).
    pub fn height(&self) -> usize {
        self.color.height()
    }
}

/// A frame in the pipeline's planar form, in the library's conventions.
#[derive(Debug, Clone)]
pub struct PreparedFrame {
    /// Premultiplied RGB, sanitized (no NaN, Inf or negative values).
    pub color: Image,
    /// Coverage in [0,1]; `None` means fully covered.
    pub coverage: Option<Vec<f32>>,
    /// Planar depth; `None` when the host gave none.
    pub depth: Option<Vec<f32>>,
    /// Motion vectors (2 planes) in the library's convention.
    pub motion: Option<Image>,
    /// Normals (3 planes).
    pub normal: Option<Image>,
    /// Insert mask in [0,1].
    pub insert_mask: Option<Vec<f32>>,
    /// The frame's camera.
    pub camera: Option<Camera>,
    /// The host's frame number.
    pub frame_index: Option<i64>,
    /// Color samples that were NaN, infinite or negative and were replaced.
    pub sanitized: usize,
    /// Samples of the other AOVs that were NaN or infinite and were replaced.
    pub sanitized_aovs: usize,
}

impl PreparedFrame {
    /// Width in pixels.
    pub fn width(&self) -> usize {
        self.color.width
    }
    /// Height in pixels.
    pub fn height(&self) -> usize {
        self.color.height
    }

    /// Validates `input` and converts it to the planar form (on the calling thread).
    pub fn from_input(input: &FrameInput<'_>, depth_kind: DepthKind) -> Result<PreparedFrame> {
        Self::prepare(input, depth_kind, None)
    }

    /// Like [`PreparedFrame::from_input`], row-parallel on `pool`; the result
    /// is the same for any number of threads.
    pub fn from_input_on(
        input: &FrameInput<'_>,
        depth_kind: DepthKind,
        pool: &rayon::ThreadPool,
    ) -> Result<PreparedFrame> {
        Self::prepare(input, depth_kind, Some(pool))
    }

    fn prepare(
        input: &FrameInput<'_>,
        depth_kind: DepthKind,
        pool: Option<&rayon::ThreadPool>,
    ) -> Result<PreparedFrame> {
        let (w, h) = (input.width(), input.height());
        if input.color.channels() < 3 {
            return Err(Error::invalid(format!(
                "color: needs at least 3 channels (RGB), got {}",
                input.color.channels()
            )));
        }
        let check = |name: &str, v: &Option<ImageView<'_>>, ch: usize| -> Result<()> {
            if let Some(v) = v {
                if v.width() != w || v.height() != h {
                    return Err(Error::invalid(format!(
                        "{name}: size {}x{} differs from color {w}x{h}",
                        v.width(),
                        v.height()
                    )));
                }
                if v.channels() < ch {
                    return Err(Error::invalid(format!(
                        "{name}: needs {ch} channel(s), got {}",
                        v.channels()
                    )));
                }
            }
            Ok(())
        };
        check("depth", &input.depth, 1)?;
        check("motion", &input.motion, 2)?;
        check("normal", &input.normal, 3)?;
        check("coverage", &input.coverage, 1)?;
        check("insert_mask", &input.insert_mask, 1)?;
        let s = input.motion_vector_scale;
        if !s[0].is_finite() || !s[1].is_finite() {
            return Err(Error::invalid(format!(
                "motion_vector_scale: {s:?} is not finite"
            )));
        }
        if depth_kind == DepthKind::Euclidean && input.depth.is_some() && input.camera.is_none() {
            return Err(Error::invalid(
                "depth: Euclidean depth needs the camera to convert to planar depth",
            ));
        }

        let n = w * h;
        let mut color = Image::zeros(w, h, 3);
        let mut sanitized = 0usize;
        for c in 0..3 {
            sanitized += read_plane(
                pool,
                &input.color,
                c,
                &mut color.data[c * n..(c + 1) * n],
                |v| {
                    if v.is_finite() && *v >= 0.0 {
                        false
                    } else {
                        *v = 0.0;
                        true
                    }
                },
            );
        }
        let mut sanitized_aovs = 0usize;
        // NaN becomes `bad` (counted), everything else is clamped to [lo, hi].
        let mut read_planes = |v: &Option<ImageView<'_>>, ch: usize, lo: f32, hi: f32, bad: f32| {
            v.as_ref().map(|v| {
                let mut img = Image::zeros(w, h, ch);
                for c in 0..ch {
                    sanitized_aovs +=
                        read_plane(pool, v, c, &mut img.data[c * n..(c + 1) * n], |x| {
                            if x.is_nan() {
                                *x = bad;
                                true
                            } else {
                                *x = x.clamp(lo, hi);
                                false
                            }
                        });
                }
                img
            })
        };
        let coverage = read_planes(&input.coverage, 1, 0.0, 1.0, 0.0).map(|i| i.data);
        let insert_mask = read_planes(&input.insert_mask, 1, 0.0, 1.0, 0.0).map(|i| i.data);
        let mut depth = read_planes(&input.depth, 1, 0.0, f32::MAX, f32::MAX).map(|i| i.data);
        let normal = read_planes(&input.normal, 3, -f32::MAX, f32::MAX, 0.0);
        let limit = 4.0 * (w.max(h) as f32);
        let motion = input.motion.as_ref().map(|v| {
            let mut img = Image::zeros(w, h, 2);
            for (c, scale) in s.iter().copied().enumerate() {
                sanitized_aovs += read_plane(pool, v, c, &mut img.data[c * n..(c + 1) * n], |x| {
                    if x.is_nan() {
                        *x = 0.0;
                        true
                    } else {
                        *x = (x.clamp(-f32::MAX, f32::MAX) * scale).clamp(-limit, limit);
                        false
                    }
                });
            }
            img
        });
        if depth_kind == DepthKind::Euclidean {
            if let (Some(d), Some(cam)) = (depth.as_mut(), input.camera.as_ref()) {
                let un = cam.unprojector(w, h);
                let convert = |(y, row): (usize, &mut [f32])| {
                    for (x, v) in row.iter_mut().enumerate() {
                        if *v < f32::MAX {
                            let f = un.euclidean_to_planar(glam::DVec2::new(
                                x as f64 + 0.5,
                                y as f64 + 0.5,
                            ));
                            *v = (*v as f64 * f) as f32;
                        }
                    }
                };
                match pool {
                    Some(pool) => {
                        pool.install(|| d.par_chunks_mut(w).enumerate().for_each(convert))
                    }
                    None => d.chunks_mut(w).enumerate().for_each(convert),
                }
            }
        }
        Ok(PreparedFrame {
            color,
            coverage,
            depth,
            motion,
            normal,
            insert_mask,
            camera: input.camera,
            frame_index: input.frame_index,
            sanitized,
            sanitized_aovs,
        })
    }
}
