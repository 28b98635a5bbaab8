//! Insert tone from the albedo AOV: an inserted object's colors corrected
//! by a 3x3 color matrix, estimated from how the scene lights its
//! background.
//!
//! From the frame alone, an insert that is a stop too bright cannot be told
//! from a brighter paint ([`super::harmonize`]): a global tone change keeps
//! every ratio inside the object. The renderer's albedo (Cycles' Denoising
//! Albedo, any renderer's albedo AOV) removes the ambiguity: color divided
//! by albedo is shading, and the insert and its background share one light.
//!
//! 1. **The scene's light**, from the background (not an insert, a surface,
//!    covered, albedo luminance at least [`MIN_ALBEDO`]; sampled on a
//!    lattice of at most [`MAX_BACKGROUND_SAMPLES`]): per channel, the log2
//!    shading `log2((c + eps) / (a + eps))` fitted as an affine function of
//!    the normal, `b0 + b . n`, by robust (Huber) least squares, so the
//!    background's cast shadows and highlights weigh little.
//! 2. **What the insert should look like**: its albedo times that shading at
//!    its normals, `p = a * 2^(b0 + b . n)`, on the insert's pixels whose
//!    normal the background shows too (bins of about 22 degrees,
//!    [`normal_bin`]): a model of the light fitted on a ground plane says
//!    nothing of a face turned away from the sun.
//! 3. **The matrix** `M` with `p ~ M c` over the insert's pixels (at most
//!    [`MAX_INSERT_SAMPLES`]), robust least squares with relative weights:
//!    exposure, white balance and saturation in one linear map.
//! 4. **Confidence**: the fit's own bias on a correctly lit insert (self
//!    occlusion, highlights, a shading model of four terms) is a few tenths
//!    of a stop, so a matrix that changes the insert's brightness by less
//!    than [`EXPOSURE_DEAD_ZONE`] stops and its chroma by less than
//!    [`CHROMA_DEAD_ZONE`] stops (RMS) is left out: the identity. Beyond,
//!    a smooth step over the knees brings in the whole matrix. A fit that
//!    changes the insert by more than [`MAX_CHANGE`] stops is not trusted
//!    (the identity too).
//!
//! Color is unpremultiplied for the fit and the matrix applies to the
//! premultiplied color (linear, so the same), weighted by the mask.

use rayon::prelude::*;

use super::{fast_log2, median, par_bands_mut, solve, Rect, EMPTY_DEPTH, LUMA};
use crate::frame::{Image, ImageView};

/// Albedo luminance below this is too dark for its shading to be read.
pub const MIN_ALBEDO: f32 = 0.03;
/// Brightness changes (stops) up to this are the fit's own bias: ignored.
pub const EXPOSURE_DEAD_ZONE: f32 = 0.5;
/// Width (stops) of the smooth step beyond [`EXPOSURE_DEAD_ZONE`].
pub const EXPOSURE_KNEE: f32 = 0.3;
/// RMS chroma changes (stops) up to this are ignored.
pub const CHROMA_DEAD_ZONE: f32 = 0.15;
/// Width (stops) of the smooth step beyond [`CHROMA_DEAD_ZONE`].
pub const CHROMA_KNEE: f32 = 0.1;
/// [`EXPOSURE_DEAD_ZONE`] under the host's light ([`Light::given`]): its
/// model has no bounce light and no occlusion, and a correctly lit object
/// shows more light than it says (out of domain, the courtyard's object
/// inserted into its reconstruction: 0.47 stops more, chroma 0.13 stops off).
pub const GIVEN_EXPOSURE_DEAD_ZONE: f32 = 0.8;
/// [`CHROMA_DEAD_ZONE`] under the host's light (see
/// [`GIVEN_EXPOSURE_DEAD_ZONE`]).
pub const GIVEN_CHROMA_DEAD_ZONE: f32 = 0.25;
/// A fit that changes brightness or chroma by more stops than this is not trusted.
pub const MAX_CHANGE: f32 = 3.5;
/// Background samples at most (a lattice over the frame).
pub const MAX_BACKGROUND_SAMPLES: usize = 8192;
/// Insert samples at most (a lattice over its bounding box).
pub const MAX_INSERT_SAMPLES: usize = 8192;
/// Fewest samples that make a fit (each of background and insert).
pub const MIN_SAMPLES: usize = 32;

/// Offset inside the logarithms (scene-linear units).
const EPS: f32 = 1e-3;
/// Share of a pixel's luminance added to each channel when measuring the
/// matrix's chroma change.
const CHANNEL_FLOOR: f32 = 0.05;
/// Offset of the relative weights' denominator (luminance).
const REL: f32 = 0.02;
/// Huber threshold in robust standard deviations.
const HUBER: f32 = 1.345;
/// Reweighting rounds of the shading fit and of the matrix fit.
const ROUNDS: usize = 6;
/// Ridge of both fits, relative to the summed weight.
const RIDGE: f64 = 1e-3;
/// A pivot below this share of the summed weight makes a fit singular.
const SINGULAR: f64 = 1e-9;

/// A 3x3 color matrix, rows are output channels: `c'_i = sum_j m[i][j] c_j`.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct ColorMatrix(pub [[f32; 3]; 3]);

impl ColorMatrix {
    /// The matrix that changes nothing.
    pub const IDENTITY: ColorMatrix =
        ColorMatrix([[1.0, 0.0, 0.0], [0.0, 1.0, 0.0], [0.0, 0.0, 1.0]]);

    /// Number of values in [`ColorMatrix::to_vec`].
    pub const LEN: usize = 9;

    /// Row after row (for the backend's carry).
    pub fn to_vec(&self) -> Vec<f32> {
        self.0.iter().flatten().copied().collect()
    }

    /// Reads [`ColorMatrix::to_vec`]'s layout; `None` for a wrong length or
    /// non-finite values.
    pub fn from_slice(v: &[f32]) -> Option<ColorMatrix> {
        if v.len() != Self::LEN || v.iter().any(|x| !x.is_finite()) {
            return None;
        }
        let mut m = [[0.0; 3]; 3];
        for (i, row) in m.iter_mut().enumerate() {
            row.copy_from_slice(&v[3 * i..3 * i + 3]);
        }
        Some(ColorMatrix(m))
    }

    /// Moves a share `t` of the way to `target`, element by element.
    pub fn toward(&self, target: &ColorMatrix, t: f32) -> ColorMatrix {
        let mut m = self.0;
        for (row, trow) in m.iter_mut().zip(&target.0) {
            for (v, tv) in row.iter_mut().zip(trow) {
                *v += t * (tv - *v);
            }
        }
        ColorMatrix(m)
    }

    /// Whether no element differs from the identity's by more than `tol`.
    pub fn is_near_identity(&self, tol: f32) -> bool {
        self.0.iter().enumerate().all(|(i, row)| {
            row.iter()
                .enumerate()
                .all(|(j, v)| (v - if i == j { 1.0 } else { 0.0 }).abs() <= tol)
        })
    }

    /// Whether this is exactly the identity.
    pub fn is_identity(&self) -> bool {
        *self == Self::IDENTITY
    }

    fn mul(&self, c: [f32; 3]) -> [f32; 3] {
        let m = &self.0;
        [0, 1, 2].map(|i| m[i][0] * c[0] + m[i][1] * c[1] + m[i][2] * c[2])
    }
}

/// What [`estimate`] found for one insert.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct Estimate {
    /// The matrix to apply: the identity moved toward the fitted matrix by
    /// `confidence`.
    pub matrix: ColorMatrix,
    /// The fitted matrix's change of the insert's brightness (median, stops).
    pub exposure: f32,
    /// The fitted matrix's RMS change of the insert's chroma (stops).
    pub chroma: f32,
    /// 0 (left alone) to 1 (the whole fitted matrix).
    pub confidence: f32,
}

/// The albedo and normals [`light`] and [`estimate`] read, taken from the
/// host's images only where they look: the background lattice over the
/// frame ([`MAX_BACKGROUND_SAMPLES`] at most) and every pixel of the
/// inserts' bounding box (each object's lattice lies in it). Read while the
/// frame is prepared: a fraction of the two images at 1080p, where reading
/// them whole cost 4-7 ms on 2 threads.
///
/// Non-finite samples are 0 (counted by [`Samples::read`]), the albedo is
/// clamped to `[0, 1]`.
#[derive(Debug, Clone)]
pub struct Samples {
    width: usize,
    height: usize,
    /// The background lattice: step, and its columns (from `step / 2`).
    step: usize,
    cols: usize,
    /// Per lattice point: albedo RGB, normal XYZ.
    lattice: Vec<[f32; 6]>,
    /// The inserts' bounding box, read whole.
    rect: Rect,
    /// Per row of `rect`: its albedo R, G, B and normal X, Y, Z rows.
    dense: Vec<f32>,
}

impl Samples {
    /// Reads the samples of a `albedo` and `normal` image pair (at least 3
    /// channels each, the same size) for inserts inside `insert`. Returns
    /// the samples and the non-finite albedo and normal samples replaced.
    pub fn read(
        albedo: &ImageView<'_>,
        normal: &ImageView<'_>,
        insert: Rect,
        pool: Option<&rayon::ThreadPool>,
    ) -> (Samples, usize, usize) {
        let (w, h) = (albedo.width(), albedo.height());
        debug_assert!(normal.width() == w && normal.height() == h);
        let s = step(w, h, MAX_BACKGROUND_SAMPLES);
        let cols = (s / 2..w).step_by(s).len();
        // The lattice's rows, side by side on the pool.
        let lattice_row = |(i, row): (usize, &mut [[f32; 6]])| -> [usize; 2] {
            let y = s / 2 + i * s;
            let mut bad = [0, 0];
            for (j, v) in row.iter_mut().enumerate() {
                let x = s / 2 + j * s;
                for k in 0..3 {
                    v[k] = albedo.get(x, y, k);
                    v[3 + k] = normal.get(x, y, k);
                }
                // Counted once: a point in the box is counted there.
                let counted = usize::from(!insert.contains(x, y));
                for (k, x) in v.iter_mut().enumerate() {
                    bad[k / 3] += counted * usize::from(sanitize(x, k < 3));
                }
            }
            bad
        };
        let mut lattice = vec![[0.0f32; 6]; cols * (s / 2..h).step_by(s).len()];
        let lattice_bad = by_rows(&mut lattice, cols, pool, lattice_row);
        let rw = insert.width();
        let mut dense = vec![0.0f32; 6 * rw * insert.height()];
        let read_row = |(dy, row): (usize, &mut [f32])| -> [usize; 2] {
            let y = insert.y0 + dy;
            for (k, out) in row.chunks_mut(rw).enumerate() {
                match k {
                    0..3 => albedo.read_span(y, insert.x0, k, out),
                    _ => normal.read_span(y, insert.x0, k - 3, out),
                }
            }
            let mut bad = [0, 0];
            for (k, out) in row.chunks_mut(rw).enumerate() {
                for x in out {
                    bad[k / 3] += usize::from(sanitize(x, k < 3));
                }
            }
            bad
        };
        let dense_bad = by_rows(&mut dense, 6 * rw, pool, read_row);
        let bad = [0, 1].map(|k| lattice_bad[k] + dense_bad[k]);
        let samples = Samples {
            width: w,
            height: h,
            step: s,
            cols,
            lattice,
            rect: insert,
            dense,
        };
        (samples, bad[0], bad[1])
    }

    /// The albedo and normal at `(x, y)`, when read (inside the inserts'
    /// box or on the background lattice).
    fn at(&self, x: usize, y: usize) -> Option<([f32; 3], [f32; 3])> {
        if self.rect.contains(x, y) {
            let rw = self.rect.width();
            let row = &self.dense[6 * rw * (y - self.rect.y0)..];
            let i = x - self.rect.x0;
            let v = |k: usize| row[k * rw + i];
            return Some(([v(0), v(1), v(2)], [v(3), v(4), v(5)]));
        }
        let h = self.step / 2;
        if x < h
            || y < h
            || !(x - h).is_multiple_of(self.step)
            || !(y - h).is_multiple_of(self.step)
        {
            return None;
        }
        let v = self
            .lattice
            .get((y - h) / self.step * self.cols + (x - h) / self.step)?;
        Some(([v[0], v[1], v[2]], [v[3], v[4], v[5]]))
    }
}

/// `f` on each row (`len` items) of `buf`, on `pool` when given; the
/// counts it returns, summed (empty rows: none).
fn by_rows<T: Send>(
    buf: &mut [T],
    len: usize,
    pool: Option<&rayon::ThreadPool>,
    f: impl Fn((usize, &mut [T])) -> [usize; 2] + Sync + Send,
) -> [usize; 2] {
    let add = |a: [usize; 2], b: [usize; 2]| [a[0] + b[0], a[1] + b[1]];
    match (len, pool) {
        (0, _) => [0, 0],
        (_, Some(pool)) => pool.install(|| {
            buf.par_chunks_mut(len)
                .enumerate()
                .map(&f)
                .reduce(|| [0, 0], add)
        }),
        (_, None) => buf.chunks_mut(len).enumerate().map(&f).fold([0, 0], add),
    }
}

/// A sample of [`Samples`] made readable: non-finite is 0 (returns whether
/// it was), an albedo sample is clamped to `[0, 1]`.
fn sanitize(x: &mut f32, albedo: bool) -> bool {
    let bad = !x.is_finite();
    *x = match (bad, albedo) {
        (true, _) => 0.0,
        (false, true) => x.clamp(0.0, 1.0),
        (false, false) => *x,
    };
    bad
}

/// The AOVs [`estimate`] reads besides the color.
pub struct Aovs<'a> {
    /// Albedo and normals (world or camera space: one frame's are
    /// consistent) where they are read.
    pub samples: &'a Samples,
    /// Coverage (pixels under 0.95 are holes and not sampled).
    pub coverage: Option<&'a [f32]>,
    /// Planar depth (empty pixels, the sky, are not background).
    pub depth: Option<&'a [f32]>,
}

fn smoothstep(x: f32, edge: f32, knee: f32) -> f32 {
    let u = ((x - edge) / knee).clamp(0.0, 1.0);
    u * u * (3.0 - 2.0 * u)
}

/// Huber weights for residuals `r`: `base / max(1, r / (HUBER * scale))`,
/// the scale the residuals' median absolute value (`scratch`: a buffer for
/// the median).
fn huber_weights(r: &[f32], base: impl Fn(usize) -> f32, w: &mut [f32], scratch: &mut Vec<f32>) {
    scratch.clear();
    scratch.extend_from_slice(r);
    let scale = 1.4826 * median(scratch) + 1e-6;
    for (i, (wi, &ri)) in w.iter_mut().zip(r).enumerate() {
        *wi = base(i) / (ri / (HUBER * scale)).max(1.0);
    }
}

/// Least squares of `y ~ x . beta` with Huber reweighting ([`ROUNDS`]
/// rounds) and a light ridge on every coefficient but the first.
fn robust_fit<const N: usize>(x: &[[f64; N]], y: &[f64]) -> Option<[f64; N]> {
    let mut w = vec![1.0f32; y.len()];
    let mut beta = None;
    let (mut r, mut scratch) = (vec![0.0f32; y.len()], Vec::with_capacity(y.len()));
    for _ in 0..ROUNDS {
        let mut a = [[0.0f64; N]; N];
        let mut b = [0.0f64; N];
        // The upper triangle, mirrored after.
        for ((xi, &yi), &wi) in x.iter().zip(y).zip(&w) {
            let wi = wi as f64;
            for i in 0..N {
                let wx = wi * xi[i];
                b[i] += wx * yi;
                for j in i..N {
                    a[i][j] += wx * xi[j];
                }
            }
        }
        let upper = a;
        for (i, row) in a.iter_mut().enumerate() {
            for (j, v) in row.iter_mut().enumerate().take(i) {
                *v = upper[j][i];
            }
        }
        // A light ridge on the normal's terms: a background of one or two
        // planes leaves some directions unseen, and those stay at 0.
        let ridge = RIDGE * a[0][0];
        for (i, row) in a.iter_mut().enumerate().skip(1) {
            row[i] += ridge;
        }
        let bt = solve(a, b, SINGULAR * (1.0 + a[0][0]))?;
        for ((ri, xi), &yi) in r.iter_mut().zip(x).zip(y) {
            let p: f64 = (0..N).map(|i| bt[i] * xi[i]).sum();
            *ri = (yi - p).abs() as f32;
        }
        huber_weights(&r, |_| 1.0, &mut w, &mut scratch);
        beta = Some(bt);
    }
    beta
}

fn lum(c: [f32; 3]) -> f32 {
    LUMA[0] * c[0] + LUMA[1] * c[1] + LUMA[2] * c[2]
}

/// A pixel's color, albedo and normal.
type Pixel = ([f32; 3], [f32; 3], [f32; 3]);

/// One pixel's unpremultiplied color, albedo and normal, when it can be
/// sampled: finite, covered, albedo luminance at least [`MIN_ALBEDO`], a
/// normal of length above 0.5.
fn sample(img: &Image, aovs: &Aovs<'_>, p: usize) -> Option<Pixel> {
    let n = img.width * img.height;
    let alpha = img.data[3 * n + p];
    if aovs.coverage.is_some_and(|c| c[p] < 0.95) || alpha < 0.95 {
        return None;
    }
    let (a, nr) = aovs.samples.at(p % img.width, p / img.width)?;
    let c = [0, 1, 2].map(|k| img.data[k * n + p] / alpha);
    let ok = c.iter().chain(&a).chain(&nr).all(|v| v.is_finite())
        && c.iter().all(|&v| v >= 0.0)
        && lum(a) >= MIN_ALBEDO
        && nr.iter().map(|v| v * v).sum::<f32>() > 0.25;
    ok.then_some((c, a.map(|v| v.max(0.0)), nr))
}

/// Bins per side of the octahedral map of normals ([`normal_bin`]).
pub const NORMAL_BINS: usize = 8;
/// A normal bin counts as seen in the background with at least this many
/// samples and at least [`MIN_BIN_SHARE`] of them.
pub const MIN_BIN_SAMPLES: usize = 8;
/// See [`MIN_BIN_SAMPLES`].
pub const MIN_BIN_SHARE: f32 = 0.002;

/// The bin of a normal (any length) on an octahedral map of the sphere,
/// [`NORMAL_BINS`] x [`NORMAL_BINS`] bins of about 22 degrees.
pub fn normal_bin(n: [f32; 3]) -> usize {
    let l1 = n[0].abs() + n[1].abs() + n[2].abs();
    if l1.partial_cmp(&0.0) != Some(std::cmp::Ordering::Greater) {
        return 0;
    }
    let (mut u, mut v) = (n[0] / l1, n[1] / l1);
    if n[2] < 0.0 {
        let (au, av) = (u.abs(), v.abs());
        u = (1.0 - av).copysign(u);
        v = (1.0 - au).copysign(v);
    }
    let cell = |t: f32| (((t + 1.0) * 0.5 * NORMAL_BINS as f32) as usize).min(NORMAL_BINS - 1);
    cell(v) * NORMAL_BINS + cell(u)
}

/// Lattice step so that a `w x h` area gives at most `max` samples.
fn step(w: usize, h: usize, max: usize) -> usize {
    let mut s = 1;
    while w.div_ceil(s) * h.div_ceil(s) > max {
        s += 1;
    }
    s
}

/// The scene's light as the background shows it (step 1 of the module
/// documentation): per channel, log2 shading as an affine function of the
/// normal, and which normals the background shows; or as the host gives it
/// ([`Light::given`]).
#[derive(Debug, Clone)]
pub struct Light {
    shading: Shading,
    /// Background samples per normal bin ([`normal_bin`]).
    seen: [usize; NORMAL_BINS * NORMAL_BINS],
    /// Samples a bin needs to count as seen.
    enough: usize,
}

#[derive(Debug, Clone)]
enum Shading {
    /// Fitted on the background: per channel `[b0, bx, by, bz]`.
    Fitted([[f64; 4]; 3]),
    /// The host's lights: irradiance of the ambient light (on a surface in
    /// the direct light's shadow) and of the direct light (on a surface
    /// facing it), and the unit direction toward it.
    Given {
        ambient: [f32; 3],
        direct: [f32; 3],
        toward: [f32; 3],
    },
}

impl Light {
    /// The scene's light as the host gives it (`ambient_color`,
    /// `light_color`, `light_direction` in the normals' space): a white
    /// diffuse surface of normal `n` shows `(ambient + direct * max(0,
    /// n.l)) / pi`, whatever normals the background shows. For frames whose
    /// background has no albedo ([`light`] gives none): a reconstruction
    /// with an object inserted. `None` for a direction of no length or no
    /// light at all.
    pub fn given(ambient: [f32; 3], direct: [f32; 3], toward: [f32; 3]) -> Option<Light> {
        let len = toward.iter().map(|v| v * v).sum::<f32>().sqrt();
        let finite = ambient
            .iter()
            .chain(&direct)
            .chain(&toward)
            .all(|v| v.is_finite());
        if !finite || len <= 1e-6 || (lum(ambient) <= 0.0 && lum(direct) <= 0.0) {
            return None;
        }
        Some(Light {
            shading: Shading::Given {
                ambient: ambient.map(|v| v.max(0.0)),
                direct: direct.map(|v| v.max(0.0)),
                toward: toward.map(|v| v / len),
            },
            seen: [0; NORMAL_BINS * NORMAL_BINS],
            enough: 0,
        })
    }

    /// The dead zones of brightness and chroma (stops) a matrix under this
    /// light must exceed to apply.
    fn dead_zones(&self) -> (f32, f32) {
        match self.shading {
            Shading::Fitted(_) => (EXPOSURE_DEAD_ZONE, CHROMA_DEAD_ZONE),
            Shading::Given { .. } => (GIVEN_EXPOSURE_DEAD_ZONE, GIVEN_CHROMA_DEAD_ZONE),
        }
    }

    /// Whether the background shows normals like `n` (every normal, for
    /// the host's light).
    fn sees(&self, n: [f32; 3]) -> bool {
        self.seen[normal_bin(n)] >= self.enough
    }

    /// The log2 shading of channel `k` at normal `n`.
    fn log_shading(&self, k: usize, n: [f32; 3]) -> f32 {
        match &self.shading {
            Shading::Fitted(s) => {
                let b = &s[k];
                let l = b[0] + b[1] * n[0] as f64 + b[2] * n[1] as f64 + b[3] * n[2] as f64;
                l.clamp(-60.0, 60.0) as f32
            }
            Shading::Given {
                ambient,
                direct,
                toward,
            } => {
                let len = n.iter().map(|v| v * v).sum::<f32>().sqrt().max(1e-6);
                let facing = (0..3).map(|i| n[i] * toward[i]).sum::<f32>() / len;
                let e = ambient[k] + direct[k] * facing.max(0.0);
                (e / std::f32::consts::PI)
                    .max(1e-12)
                    .log2()
                    .clamp(-60.0, 60.0)
            }
        }
    }
}

/// The frame's [`Light`], from its background: the pixels outside every
/// insert (`inserts`, the whole insert mask). Once per frame, shared by its
/// objects. `None` when the albedo or normals do not match the frame's
/// size or too few background pixels can be read.
pub fn light(img: &Image, aovs: &Aovs<'_>, inserts: &[f32]) -> Option<Light> {
    let (w, h) = (img.width, img.height);
    let sized = (aovs.samples.width, aovs.samples.height) == (w, h);
    if !sized || inserts.len() != w * h || img.channels < 4 {
        return None;
    }
    // The lattice's rows on the caller's pool, gathered in order.
    let s = aovs.samples.step;
    let rows: Vec<Vec<Pixel>> = (s / 2..h)
        .into_par_iter()
        .step_by(s)
        .map(|y| {
            (s / 2..w)
                .step_by(s)
                .map(|x| y * w + x)
                .filter(|&p| {
                    inserts[p] < 0.01
                        && !aovs
                            .depth
                            .is_some_and(|d| d[p].is_nan() || d[p] >= EMPTY_DEPTH)
                })
                .filter_map(|p| sample(img, aovs, p))
                .collect()
        })
        .collect();
    let count = rows.iter().map(Vec::len).sum();
    let mut xs: Vec<[f64; 4]> = Vec::with_capacity(count);
    let mut ys: [Vec<f64>; 3] = std::array::from_fn(|_| Vec::with_capacity(count));
    for (c, a, nr) in rows.into_iter().flatten() {
        xs.push([1.0, nr[0] as f64, nr[1] as f64, nr[2] as f64]);
        for k in 0..3 {
            ys[k].push(fast_log2((c[k] + EPS) / (a[k] + EPS)) as f64);
        }
    }
    if xs.len() < MIN_SAMPLES {
        return None;
    }
    // Which normals the background shows: the fit is a model of the light
    // only there (a ground plane says nothing of the light on a face
    // turned away from the sun).
    let mut seen = [0usize; NORMAL_BINS * NORMAL_BINS];
    for x in &xs {
        seen[normal_bin([x[1] as f32, x[2] as f32, x[3] as f32])] += 1;
    }
    // The three channels' fits on the caller's pool, side by side.
    let [y0, y1, y2] = &ys;
    let (r0, (r1, r2)) = rayon::join(
        || robust_fit(&xs, y0),
        || rayon::join(|| robust_fit(&xs, y1), || robust_fit(&xs, y2)),
    );
    Some(Light {
        shading: Shading::Fitted([r0?, r1?, r2?]),
        seen,
        enough: MIN_BIN_SAMPLES.max((MIN_BIN_SHARE * xs.len() as f32) as usize),
    })
}

/// The insert's color matrix (see the module documentation) under the
/// frame's `light`: `mask` is this object's mask, `insert` its bounding
/// box. `None` when too few of its pixels can be read.
pub fn estimate(
    img: &Image,
    aovs: &Aovs<'_>,
    light: &Light,
    mask: &[f32],
    insert: Rect,
) -> Option<Estimate> {
    let w = img.width;
    let sized = (aovs.samples.width, aovs.samples.height) == (w, img.height);
    if !sized || mask.len() != w * img.height || insert.is_empty() {
        return None;
    }
    // 2. The insert's colors and what the light makes of its albedo.
    let si = step(insert.width(), insert.height(), MAX_INSERT_SAMPLES);
    let mut cs: Vec<[f32; 3]> = Vec::new();
    let mut ps: Vec<[f32; 3]> = Vec::new();
    for y in (insert.y0 + si / 2..insert.y1).step_by(si) {
        for x in (insert.x0 + si / 2..insert.x1).step_by(si) {
            let p = y * w + x;
            if mask[p] < 0.99 {
                continue;
            }
            if let Some((c, a, nr)) = sample(img, aovs, p).filter(|s| light.sees(s.2)) {
                cs.push(c);
                ps.push([0, 1, 2].map(|k| a[k] * light.log_shading(k, nr).exp2()));
            }
        }
    }
    if cs.len() < MIN_SAMPLES {
        return None;
    }
    // 3. The matrix: one weighted system per output channel, same weights.
    let base: Vec<f32> = ps.iter().map(|&p| 1.0 / (lum(p) + REL).powi(2)).collect();
    let mut wts = base.clone();
    let mut m = ColorMatrix::IDENTITY;
    let (mut r, mut scratch) = (vec![0.0f32; cs.len()], Vec::with_capacity(cs.len()));
    for _ in 0..ROUNDS {
        let mut a = [[0.0f64; 3]; 3];
        let mut b = [[0.0f64; 3]; 3];
        for ((c, p), &wi) in cs.iter().zip(&ps).zip(&wts) {
            for i in 0..3 {
                let wc = (wi * c[i]) as f64;
                for j in 0..3 {
                    a[i][j] += wc * c[j] as f64;
                    b[j][i] += wc * p[j] as f64;
                }
            }
        }
        // A light ridge toward the identity: a grey insert (its channels
        // proportional) does not tell the channels apart.
        let ridge = RIDGE * (a[0][0] + a[1][1] + a[2][2]) / 3.0;
        for (i, row) in a.iter_mut().enumerate() {
            row[i] += ridge;
            b[i][i] += ridge;
        }
        let tiny = SINGULAR * (1.0 + a[0][0]);
        let mut next = [[0.0f32; 3]; 3];
        for (row, bk) in next.iter_mut().zip(b) {
            *row = solve(a, bk, tiny)?.map(|v| v as f32);
        }
        m = ColorMatrix(next);
        for ((ri, c), p) in r.iter_mut().zip(&cs).zip(&ps) {
            let q = m.mul(*c);
            *ri = (0..3).map(|k| (p[k] - q[k]).abs()).sum::<f32>() / (lum(*p) + REL);
        }
        huber_weights(&r, |i| base[i], &mut wts, &mut scratch);
    }
    // 4. How much the matrix changes the insert, and the confidence.
    let mut dl = Vec::with_capacity(cs.len());
    let mut dk: [Vec<f32>; 3] = Default::default();
    for c in &cs {
        let q = m.mul(*c).map(|v| v.max(0.0));
        dl.push((lum(q) + EPS).log2() - (lum(*c) + EPS).log2());
        // A channel near black changes by few stops in this measure, not by
        // the ratio of two tiny values.
        let off = CHANNEL_FLOOR * lum(*c) + EPS;
        for k in 0..3 {
            dk[k].push((q[k] + off).log2() - (c[k] + off).log2());
        }
    }
    let exposure = median(&mut dl);
    let d = [0, 1, 2].map(|k| median(&mut dk[k]));
    let mean = (d[0] + d[1] + d[2]) / 3.0;
    let chroma = (d.iter().map(|v| (v - mean).powi(2)).sum::<f32>() / 3.0).sqrt();
    let trusted = exposure.abs() <= MAX_CHANGE
        && chroma <= MAX_CHANGE
        && m.to_vec().iter().all(|v| v.is_finite());
    let (exposure_zone, chroma_zone) = light.dead_zones();
    let confidence = if trusted {
        smoothstep(exposure.abs(), exposure_zone, EXPOSURE_KNEE).max(smoothstep(
            chroma,
            chroma_zone,
            CHROMA_KNEE,
        ))
    } else {
        0.0
    };
    let matrix = if confidence > 0.0 {
        ColorMatrix::IDENTITY.toward(&m, confidence)
    } else {
        ColorMatrix::IDENTITY
    };
    Some(Estimate {
        matrix,
        exposure,
        chroma,
        confidence,
    })
}

/// Applies `m` to the insert in place, weighted by the mask:
/// `c' = c + mask * (max(M c, 0) - c)` on premultiplied color. Only pixels
/// inside `insert` are touched; the identity touches none.
pub fn apply(img: &mut Image, mask: &[f32], insert: Rect, m: &ColorMatrix) {
    if m.is_identity() || insert.is_empty() {
        return;
    }
    let (w, m) = (img.width, *m);
    par_bands_mut(img, insert.y0, insert.y1).for_each(|(y0, [r, g, b, _])| {
        let rows = r.len() / w;
        for dy in 0..rows {
            let row = dy * w;
            let mrow = &mask[(y0 + dy) * w..(y0 + dy + 1) * w];
            for (x, &t) in mrow.iter().enumerate().take(insert.x1).skip(insert.x0) {
                if t <= 0.0 {
                    continue;
                }
                let p = row + x;
                let c = [r[p], g[p], b[p]];
                let q = m.mul(c);
                r[p] = c[0] + t * (q[0].max(0.0) - c[0]);
                g[p] = c[1] + t * (q[1].max(0.0) - c[1]);
                b[p] = c[2] + t * (q[2].max(0.0) - c[2]);
            }
        }
    });
}

#[cfg(test)]
mod tests {
    use super::*;

    const W: usize = 160;
    const H: usize = 120;

    /// A lit scene: ground (normal up) and a wall (normal toward the camera)
    /// of textured albedo, and a sphere-like insert (normals over a hemisphere)
    /// of orange albedo; sun from above-front plus sky. `grade` maps the
    /// insert's correct color to what the frame shows.
    fn scene(grade: impl Fn([f32; 3]) -> [f32; 3]) -> (Image, Image, Image, Vec<f32>) {
        let n = W * H;
        let mut img = Image::filled(W, H, 4, 1.0);
        let mut albedo = Image::zeros(W, H, 3);
        let mut normal = Image::zeros(W, H, 3);
        let mut mask = vec![0.0; n];
        let sun = [0.3f32, -0.5, 0.81];
        let light = |nr: [f32; 3]| {
            let d = (nr[0] * sun[0] + nr[1] * sun[1] + nr[2] * sun[2]).max(0.0);
            [0.25 + 1.6 * d, 0.3 + 1.5 * d, 0.4 + 1.3 * d]
        };
        let (cx, cy, r) = (80.0f32, 60.0f32, 26.0f32);
        for y in 0..H {
            for x in 0..W {
                let p = y * W + x;
                let t = 0.5 + 0.35 * ((x as f32 * 0.37).sin() * (y as f32 * 0.23).cos());
                let (dx, dy) = ((x as f32 + 0.5 - cx) / r, (y as f32 + 0.5 - cy) / r);
                let inside = dx * dx + dy * dy < 1.0;
                let (a, nr) = if inside {
                    let nz = (1.0 - dx * dx - dy * dy).max(0.0).sqrt();
                    // Camera looks along +y; image up is world +z.
                    ([0.75, 0.32, 0.08], [dx, -nz, -dy])
                } else if y < H / 2 {
                    ([0.5 * t, 0.45 * t, 0.4 * t], [0.0, -1.0, 0.0])
                } else {
                    (
                        [0.3 + 0.3 * t, 0.35 + 0.2 * t, 0.2 * t + 0.1],
                        [0.0, 0.0, 1.0],
                    )
                };
                let lit = light(nr);
                let mut c = [0, 1, 2].map(|k| a[k] * lit[k]);
                if inside {
                    c = grade(c);
                    mask[p] = 1.0;
                }
                for k in 0..3 {
                    img.data[k * n + p] = c[k];
                    albedo.data[k * n + p] = a[k];
                    normal.data[k * n + p] = nr[k];
                }
            }
        }
        (img, albedo, normal, mask)
    }

    /// Planar 3-channel `img` interleaved, as a host passes it.
    fn interleaved(img: &Image) -> Vec<f32> {
        let n = img.width * img.height;
        (0..n)
            .flat_map(|p| [0, 1, 2].map(|k| img.data[k * n + p]))
            .collect()
    }

    fn samples_of(albedo: &Image, normal: &Image, rect: Rect) -> (Samples, usize, usize) {
        let (a, nr) = (interleaved(albedo), interleaved(normal));
        let (w, h) = (albedo.width, albedo.height);
        let av = ImageView::from_f32("albedo", &a, w, h, 3).unwrap();
        let nv = ImageView::from_f32("normal", &nr, w, h, 3).unwrap();
        Samples::read(&av, &nv, rect, None)
    }

    fn run(img: &Image, albedo: &Image, normal: &Image, mask: &[f32]) -> Option<Estimate> {
        let rect = super::super::harmonize::insert_rect(mask, W, H).unwrap();
        let samples = samples_of(albedo, normal, rect).0;
        let aovs = Aovs {
            samples: &samples,
            coverage: None,
            depth: None,
        };
        estimate(img, &aovs, &light(img, &aovs, mask)?, mask, rect)
    }

    fn region_error(a: &Image, b: &Image, mask: &[f32]) -> f32 {
        let n = W * H;
        let mut s = 0.0;
        let mut k = 0;
        for (p, _) in mask.iter().enumerate().filter(|(_, &m)| m > 0.5) {
            for c in 0..3 {
                s += (a.data[c * n + p] - b.data[c * n + p]).abs();
                k += 1;
            }
        }
        s / k as f32
    }

    #[test]
    fn a_correctly_lit_insert_is_left_alone() {
        let (img, albedo, normal, mask) = scene(|c| c);
        let e = run(&img, &albedo, &normal, &mask).unwrap();
        assert!(e.matrix.is_identity(), "{e:?}");
        // The fit's own bias (a clamped cosine fitted by an affine map).
        assert!(e.exposure.abs() < 0.3 && e.chroma < 0.05, "{e:?}");
    }

    #[test]
    fn a_graded_insert_is_brought_back() {
        let (truth, ..) = scene(|c| c);
        // A stop brighter, warm, more saturated (linear, around luminance).
        let grade = |c: [f32; 3]| {
            let g = [2.4 * c[0], 1.9 * c[1], 1.3 * c[2]];
            let y = lum(g);
            g.map(|v| (y + 1.25 * (v - y)).max(0.0))
        };
        let (mut img, albedo, normal, mask) = scene(grade);
        let before = region_error(&img, &truth, &mask);
        let e = run(&img, &albedo, &normal, &mask).unwrap();
        assert!(e.confidence == 1.0 && e.exposure < -0.8, "{e:?}");
        let rect = super::super::harmonize::insert_rect(&mask, W, H).unwrap();
        apply(&mut img, &mask, rect, &e.matrix);
        let after = region_error(&img, &truth, &mask);
        assert!(after < 0.1 * before, "error {before} -> {after}");
        // The background is untouched.
        let n = W * H;
        for p in (0..n).filter(|&p| mask[p] == 0.0) {
            assert_eq!(img.data[p], truth.data[p]);
        }
    }

    #[test]
    fn small_differences_are_the_fits_own_bias() {
        // A fifth of a stop darker: inside the dead zone.
        let (img, albedo, normal, mask) = scene(|c| c.map(|v| v * 0.87));
        let e = run(&img, &albedo, &normal, &mask).unwrap();
        assert!(e.matrix.is_identity() && e.exposure > 0.1, "{e:?}");
    }

    #[test]
    fn no_estimate_without_albedo_to_read() {
        let (img, mut albedo, normal, mask) = scene(|c| c);
        // A black albedo everywhere (a host that wrote an empty pass).
        albedo.data.iter_mut().for_each(|v| *v = 0.0);
        assert!(run(&img, &albedo, &normal, &mask).is_none());
        // Wrong size.
        let small = Image::zeros(8, 8, 3);
        let samples = samples_of(&small, &small, Rect::default()).0;
        let aovs = Aovs {
            samples: &samples,
            coverage: None,
            depth: None,
        };
        assert!(light(&img, &aovs, &mask).is_none());
        let _ = normal;
    }

    /// The fixture's light as a host gives it (irradiance: pi times the
    /// shading), and the scene with the albedo only on the insert.
    fn host_light() -> Light {
        let pi = std::f32::consts::PI;
        let [a, d] = [[0.25, 0.3, 0.4], [1.6, 1.5, 1.3]].map(|c: [f32; 3]| c.map(|v| v * pi));
        Light::given(a, d, [0.6, -1.0, 1.62]).unwrap()
    }

    fn run_given(img: &Image, albedo: &Image, normal: &Image, mask: &[f32]) -> Option<Estimate> {
        let rect = super::super::harmonize::insert_rect(mask, W, H).unwrap();
        let n = W * H;
        // A reconstruction's background: no albedo but the object's.
        let mut albedo = albedo.clone();
        for (p, _) in mask.iter().enumerate().filter(|(_, &m)| m == 0.0) {
            (0..3).for_each(|k| albedo.data[k * n + p] = 0.0);
        }
        let samples = samples_of(&albedo, normal, rect).0;
        let aovs = Aovs {
            samples: &samples,
            coverage: None,
            depth: None,
        };
        assert!(
            light(img, &aovs, mask).is_none(),
            "the background has no albedo"
        );
        estimate(img, &aovs, &host_light(), mask, rect)
    }

    #[test]
    fn the_host_s_light_brings_back_an_insert_over_a_background_without_albedo() {
        let (truth, ..) = scene(|c| c);
        // Lit by another, weaker and bluer light: two stops darker, cool.
        let grade = |c: [f32; 3]| [0.2 * c[0], 0.25 * c[1], 0.4 * c[2]];
        let (mut img, albedo, normal, mask) = scene(grade);
        let before = region_error(&img, &truth, &mask);
        let e = run_given(&img, &albedo, &normal, &mask).unwrap();
        assert!(e.confidence == 1.0 && e.exposure > 1.5, "{e:?}");
        let rect = super::super::harmonize::insert_rect(&mask, W, H).unwrap();
        apply(&mut img, &mask, rect, &e.matrix);
        let after = region_error(&img, &truth, &mask);
        assert!(after < 0.1 * before, "error {before} -> {after}");
    }

    #[test]
    fn the_host_s_light_leaves_a_correctly_lit_insert_alone() {
        let (img, albedo, normal, mask) = scene(|c| c);
        let e = run_given(&img, &albedo, &normal, &mask).unwrap();
        assert!(e.matrix.is_identity() && e.exposure.abs() < 0.05, "{e:?}");
        // Off by less than the host light's wider dead zone (its model has
        // no bounce light): left alone, where the fitted light's would not.
        let (img, albedo, normal, mask) = scene(|c| c.map(|v| v * 0.65));
        let e = run_given(&img, &albedo, &normal, &mask).unwrap();
        assert!(e.matrix.is_identity() && e.exposure > 0.55, "{e:?}");
        assert!(run(&img, &albedo, &normal, &mask).unwrap().confidence > 0.0);
    }

    #[test]
    fn the_host_s_light_needs_a_direction_and_some_light() {
        assert!(Light::given([1.0; 3], [1.0; 3], [0.0; 3]).is_none());
        assert!(Light::given([0.0; 3], [0.0; 3], [0.0, 0.0, 1.0]).is_none());
        assert!(Light::given([1.0; 3], [f32::NAN; 3], [0.0, 0.0, 1.0]).is_none());
        // Only a sky: the shading is the same for every normal.
        let sky = Light::given([2.0, 1.0, 0.5], [0.0; 3], [0.0, 0.0, 1.0]).unwrap();
        let up = sky.log_shading(0, [0.0, 0.0, 1.0]);
        assert_eq!(up, sky.log_shading(0, [0.0, 0.0, -1.0]));
        assert!((up.exp2() - 2.0 / std::f32::consts::PI).abs() < 1e-5);
        // A normal of any length; facing away gets the ambient only.
        let sun = Light::given([1.0; 3], [3.0; 3], [0.0, 0.0, 2.0]).unwrap();
        let pi = std::f32::consts::PI;
        assert!((sun.log_shading(1, [0.0, 0.0, 5.0]).exp2() - 4.0 / pi).abs() < 1e-5);
        assert!((sun.log_shading(1, [0.0, 3.0, -3.0]).exp2() - 1.0 / pi).abs() < 1e-5);
    }

    #[test]
    fn samples_are_read_where_the_fits_look_and_sanitized() {
        let (_, mut albedo, mut normal, mask) = scene(|c| c);
        let rect = super::super::harmonize::insert_rect(&mask, W, H).unwrap();
        let n = W * H;
        // Bad samples inside the box, on the lattice and elsewhere.
        let s = step(W, H, MAX_BACKGROUND_SAMPLES);
        let (inside, on, off) = (
            rect.y0 * W + rect.x0,
            (s / 2) * W + s / 2,
            (s / 2 + 1) * W + s / 2 + 1,
        );
        assert!(!rect.contains(s / 2, s / 2) && !rect.contains(s / 2 + 1, s / 2 + 1));
        albedo.data[inside] = f32::NAN;
        albedo.data[n + on] = 7.0;
        albedo.data[off] = f32::INFINITY;
        normal.data[2 * n + on] = f32::NAN;
        let (samples, bad_albedo, bad_normal) = samples_of(&albedo, &normal, rect);
        // The sample off the lattice and outside the box is not read.
        assert_eq!((bad_albedo, bad_normal), (1, 1));
        let at = |p: usize| samples.at(p % W, p / W);
        assert_eq!(at(inside).unwrap().0[0], 0.0);
        assert_eq!(at(on).unwrap().0[1], 1.0);
        assert_eq!(at(on).unwrap().1[2], 0.0);
        assert!(at(off).is_none());
        // Every read sample is the image's, everywhere it is read.
        for y in 0..H {
            for x in 0..W {
                let p = y * W + x;
                if let Some((a, nr)) = samples.at(x, y).filter(|_| ![inside, on].contains(&p)) {
                    for k in 0..3 {
                        assert_eq!(a[k], albedo.data[k * n + p]);
                        assert_eq!(nr[k], normal.data[k * n + p]);
                    }
                }
            }
        }
    }

    #[test]
    fn matrix_round_trips_and_blends() {
        let m = ColorMatrix([[1.2, 0.1, 0.0], [0.0, 0.9, 0.05], [0.0, 0.0, 1.4]]);
        assert_eq!(ColorMatrix::from_slice(&m.to_vec()), Some(m));
        assert!(ColorMatrix::from_slice(&[1.0; 8]).is_none());
        assert!(ColorMatrix::from_slice(&[f32::NAN; 9]).is_none());
        assert_eq!(ColorMatrix::IDENTITY.toward(&m, 1.0), m);
        assert_eq!(m.toward(&ColorMatrix::IDENTITY, 1.0), ColorMatrix::IDENTITY);
        assert!(ColorMatrix::IDENTITY
            .toward(&m, 0.01)
            .is_near_identity(0.01));
    }
}
