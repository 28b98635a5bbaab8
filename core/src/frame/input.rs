//! One frame's inputs as the host gives them (strided views), and the
//! prepared planar form the pipeline uses (validated, converted to the
//! library's conventions, sanitized).

use rayon::prelude::*;

use super::{Camera, Image, ImageView, Recycler};
use crate::error::{Error, Result};
use crate::ops::inpaint::FULL;
use crate::ops::{Rect, BAND_ROWS};
use crate::temporal::{Lattice, LatticeRows};

/// Reads the first `img.channels` channels of `view` into the planes of
/// `img` (every sample is overwritten), row by row with all channels of a row
/// together (one pass over the host row), in parallel on `pool` when given;
/// applies `fix(channel, sample)` to every sample and returns how many
/// samples it reported as replaced.
fn read_image(
    pool: Option<&rayon::ThreadPool>,
    view: &ImageView<'_>,
    img: &mut Image,
    fix: impl Fn(usize, &mut f32) -> bool + Sync,
) -> usize {
    let channels = img.channels;
    read_image_with(pool, view, img, channels, Vec::new(), fix, |_, _| {
        Found::default()
    })
    .0
}

/// What a row pass ([`read_image_with`]'s `rest`) found besides the samples
/// it replaced: a count, and the bounding box of some pixels with their
/// number. Merging is order-free, so the result does not depend on threads.
#[derive(Debug, Clone, Copy, Default)]
struct Found {
    n: usize,
    bbox: Option<(Rect, usize)>,
}

impl Found {
    fn merge(self, o: Found) -> Found {
        Found {
            n: self.n + o.n,
            bbox: crate::ops::merge_boxes(self.bbox, o.bbox),
        }
    }

    /// Row `y`'s pixels where `pred` holds (after a cheap whole-row test
    /// `row_has`), as [`crate::ops::bbox_above`] finds them.
    fn row(y: usize, row: &[f32], row_has: bool, pred: impl Fn(f32) -> bool) -> Found {
        let bbox = row_has.then(|| crate::ops::row_box(y, row, pred)).flatten();
        Found { n: 0, bbox }
    }
}

/// The most planes [`read_image_with`] fills in one row pass (RGBA and the
/// coverage).
const MAX_PLANES: usize = 5;

/// [`read_image`] of the first `read` channels of `view` into the first
/// `read` planes of `img`; `rest(y, rows)` then gets row `y` of every plane
/// (those of `img`, then those of `extra`, each a frame-sized plane) in the
/// same row task, so work on the row (writing the planes after the read
/// ones, counting, finding) needs no second pass over the frame. Returns the
/// number of replaced samples and what `rest` found, merged.
fn read_image_with(
    pool: Option<&rayon::ThreadPool>,
    view: &ImageView<'_>,
    img: &mut Image,
    read: usize,
    extra: Vec<&mut [f32]>,
    fix: impl Fn(usize, &mut f32) -> bool + Sync,
    rest: impl Fn(usize, &mut [&mut [f32]]) -> Found + Sync,
) -> (usize, Found) {
    let (w, h) = (img.width, img.height);
    if w == 0 || h == 0 {
        return (0, Found::default());
    }
    let mut planes: Vec<_> = img
        .data
        .chunks_mut(w * h)
        .chain(extra)
        .map(|p| p.chunks_mut(w))
        .collect();
    let count = planes.len();
    assert!(count <= MAX_PLANES, "{count} planes read together");
    // Fixed-size rows (the unused entries empty): one allocation, not one per row.
    let rows: Vec<[&mut [f32]; MAX_PLANES]> = (0..h)
        .map(|_| {
            let mut next = planes
                .iter_mut()
                .map(|p| p.next().expect("planes of equal size"));
            std::array::from_fn(|_| next.next().unwrap_or_default())
        })
        .collect();
    let row = |(y, mut outs): (usize, [&mut [f32]; MAX_PLANES])| -> (usize, Found) {
        let outs = &mut outs[..count];
        let mut bad = 0;
        view.read_row_channels(y, &mut outs[..read]);
        for (c, out) in outs[..read].iter_mut().enumerate() {
            // Branch-free `fix` (see the callers) and a narrow counter: the
            // pass vectorizes.
            bad += out.iter_mut().map(|v| u32::from(fix(c, v))).sum::<u32>() as usize;
        }
        (bad, rest(y, outs))
    };
    let add = |a: (usize, Found), b: (usize, Found)| (a.0 + b.0, a.1.merge(b.1));
    match pool {
        Some(pool) => pool.install(|| {
            rows.into_par_iter()
                .enumerate()
                .with_min_len(8)
                .map(row)
                .reduce(|| (0, Found::default()), add)
        }),
        None => rows
            .into_iter()
            .enumerate()
            .map(row)
            .fold((0, Found::default()), add),
    }
}

/// Gives a prepared frame's insert mask back to `recycler`: as a buffer
/// of zeros outside the insert's box when the frame was scanned while
/// prepared (`scan`, see [`Scan::insert`]), else as any buffer.
pub(crate) fn recycle_mask(recycler: &Recycler, mask: Vec<f32>, width: usize, scan: Option<Scan>) {
    match scan {
        Some(scan) => recycler.give_zeroed(mask, width, scan.insert),
        None => recycler.give(mask),
    }
}

/// An insert-mask sample made usable: NaN is 0 (true: counted), the rest
/// clamped to `[0, 1]`, and -0 is +0 (so every pixel outside the box of
/// those above 0 is exactly +0).
#[inline(always)]
fn sanitize_mask(x: &mut f32) -> bool {
    let nan = sanitize(x, 0.0, 1.0, 0.0);
    *x += 0.0;
    nan
}

/// Row `y` of channel 0 of `view`: the host's own samples when they are
/// packed f32, else read into `copy`.
fn host_row<'r>(view: &'r ImageView<'_>, y: usize, copy: &'r mut Vec<f32>) -> &'r [f32] {
    match view.packed_row(y) {
        Some(row) => row,
        None => {
            copy.resize(view.width(), 0.0);
            view.read_row(y, 0, copy);
            copy
        }
    }
}

/// The first pass over an insert mask: the samples [`sanitize_mask`]
/// counts, and the bounding box of those above 0 (after sanitizing), row
/// by row in parallel on `pool` when given; nothing is written.
fn scan_mask(pool: Option<&rayon::ThreadPool>, view: &ImageView<'_>) -> (usize, Option<Rect>) {
    let h = view.height();
    let rows = |ys: std::ops::Range<usize>| -> (usize, Found) {
        let mut copy = Vec::new();
        let mut acc = (0, Found::default());
        for y in ys {
            let row = host_row(view, y, &mut copy);
            // Sanitized, a sample is above 0 exactly when it was (NaN and
            // negatives become 0, the rest is clamped to at most 1): one
            // read-only pass counts the NaN and the samples above 0.
            let (bad, above) = row.iter().fold((0u32, 0u32), |(n, p), &v| {
                (n + u32::from(v.is_nan()), p + u32::from(v > 0.0))
            });
            let found = Found::row(y, row, above > 0, |v| v > 0.0);
            acc = (acc.0 + bad as usize, acc.1.merge(found));
        }
        acc
    };
    let add = |a: (usize, Found), b: (usize, Found)| (a.0 + b.0, a.1.merge(b.1));
    let chunks = h.div_ceil(BAND_ROWS);
    let chunk = |c: usize| rows(c * BAND_ROWS..((c + 1) * BAND_ROWS).min(h));
    let (bad, found) = match pool {
        Some(pool) => pool.install(|| {
            (0..chunks)
                .into_par_iter()
                .map(chunk)
                .reduce(|| (0, Found::default()), add)
        }),
        None => (0..chunks).map(chunk).fold((0, Found::default()), add),
    };
    (bad, found.bbox.map(|(r, _)| r))
}

/// The second pass: the insert mask's samples inside `rect`, sanitized,
/// into `out` (rows of the view's width, zero elsewhere).
fn copy_mask_box(
    pool: Option<&rayon::ThreadPool>,
    view: &ImageView<'_>,
    out: &mut [f32],
    rect: Rect,
) {
    let w = view.width();
    let band = |(i, rows): (usize, &mut [f32])| {
        let mut copy = Vec::new();
        for (k, o) in rows.chunks_mut(w).enumerate() {
            let row = host_row(view, rect.y0 + BAND_ROWS * i + k, &mut copy);
            let (src, dst) = (&row[rect.x0..rect.x1], &mut o[rect.x0..rect.x1]);
            for (&s, d) in src.iter().zip(dst) {
                let mut v = s;
                sanitize_mask(&mut v);
                *d = v;
            }
        }
    };
    let rows = &mut out[rect.y0 * w..rect.y1 * w];
    match pool {
        Some(pool) => pool.install(|| {
            rows.par_chunks_mut(BAND_ROWS * w)
                .enumerate()
                .for_each(band)
        }),
        None => rows.chunks_mut(BAND_ROWS * w).enumerate().for_each(band),
    }
}

/// The samples of the first `channels` channels of `view` that are NaN or
/// infinite, counted row by row in parallel on `pool` when given; nothing is
/// written (the normals of a frame whose backend does not read them).
fn count_non_finite(
    pool: Option<&rayon::ThreadPool>,
    view: &ImageView<'_>,
    channels: usize,
) -> usize {
    let (w, h) = (view.width(), view.height());
    let rows = |ys: std::ops::Range<usize>| -> usize {
        // One row buffer per band, read through its channel slices.
        let mut buf = vec![0.0f32; channels * w];
        let mut outs: Vec<&mut [f32]> = buf.chunks_mut(w).collect();
        let mut n = 0;
        for y in ys {
            view.read_row_channels(y, &mut outs);
            n += outs
                .iter()
                .flat_map(|c| c.iter())
                .map(|v| u32::from(!v.is_finite()))
                .sum::<u32>() as usize;
        }
        n
    };
    let chunks = h.div_ceil(BAND_ROWS);
    let chunk = |c: usize| rows(c * BAND_ROWS..((c + 1) * BAND_ROWS).min(h));
    match pool {
        Some(pool) => pool.install(|| (0..chunks).into_par_iter().map(chunk).sum()),
        None => (0..chunks).map(chunk).sum(),
    }
}

/// An AOV sample made usable: NaN becomes `bad`, anything else is clamped
/// to `[lo, hi]`; true when it was NaN (counted). Branch-free, so loops of
/// it vectorize.
#[inline(always)]
fn sanitize(x: &mut f32, lo: f32, hi: f32, bad: f32) -> bool {
    let nan = x.is_nan();
    *x = if nan { bad } else { clamp(*x, lo, hi) };
    nan
}

/// `x.clamp(lo, hi)` (the same results, NaN passes through) without its
/// argument check, so loops using it vectorize; needs `lo <= hi`.
#[inline(always)]
fn clamp(x: f32, lo: f32, hi: f32) -> f32 {
    let x = if x < lo { lo } else { x };
    if x > hi {
        hi
    } else {
        x
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
    /// Albedo (3 channels, linear, in `[0, 1]`): the surface reflectance
    /// the renderer saw, what Cycles' Denoising Albedo pass holds; read by
    /// the denoise stage (`denoise` parameter) only.
    pub albedo: Option<ImageView<'a>>,
    /// Normals for the denoise stage (3 channels, any space), for example
    /// Cycles' Denoising Normal pass (camera space, consistent with its
    /// Denoising Albedo); when absent the denoiser reads `normal`.
    pub denoise_normal: Option<ImageView<'a>>,
    /// Coverage in `[0,1]` (1 channel): 0 where the renderer had no data (a hole).
    pub coverage: Option<ImageView<'a>>,
    /// Insert mask in `[0,1]` (1 channel): where an inserted object is.
    pub insert_mask: Option<ImageView<'a>>,
    /// Insert object ids (1 channel, integer ids held as floats; 0: not an
    /// inserted object): which inserted object each pixel belongs to, for
    /// example Blender's Object Index pass or a USD prim id. Each distinct
    /// id above 0 among the insert's pixels is one object, whether or not
    /// its pixels touch another's; insert pixels with id 0 are grouped by
    /// connected parts as without ids. Without `insert_mask` the mask is 1
    /// where the id is above 0.
    pub insert_id: Option<ImageView<'a>>,
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
            albedo: None,
            denoise_normal: None,
            coverage: None,
            insert_mask: None,
            insert_id: None,
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
    /// Premultiplied RGB, sanitized (no NaN, Inf or negative values): 3
    /// planes, or 4 when prepared as RGBA ([`PreparedFrame::from_input_recycled`]
    /// with `rgba`), plane 3 then a copy of the coverage (1 where it is
    /// absent). No planes (the size kept) once [`PreparedFrame::take_color`]
    /// handed it to a backend.
    pub color: Image,
    /// Coverage in `[0,1]`; `None` means fully covered.
    pub coverage: Option<Vec<f32>>,
    /// Planar depth; `None` when the host gave none.
    pub depth: Option<Vec<f32>>,
    /// Motion vectors (2 planes) in the library's convention.
    pub motion: Option<Image>,
    /// Normals (3 planes).
    pub normal: Option<Image>,
    /// Albedo (3 planes): non-finite samples 0, the rest clamped to
    /// `[0, 1]`. Prepared only for the denoise stage
    /// ([`PrepareOptions::denoise_aux`]).
    pub albedo: Option<Image>,
    /// The albedo and normals where the insert color matrix reads them
    /// ([`PrepareOptions::albedo`], a frame with an insert, its albedo and
    /// its normals).
    pub insert_aovs: Option<crate::ops::albedo_tone::Samples>,
    /// The denoise stage's normals (3 planes, non-finite samples 0), from
    /// [`FrameInput::denoise_normal`]; prepared as `albedo` is.
    pub denoise_normal: Option<Image>,
    /// Insert mask in `[0,1]` (from [`FrameInput::insert_id`], 1 where the
    /// id is above 0, when only the ids were given).
    pub insert_mask: Option<Vec<f32>>,
    /// Insert object ids ([`FrameInput::insert_id`]): NaN, infinite and
    /// negative samples are 0 (the non-finite ones counted in
    /// `sanitized_aovs`).
    pub insert_id: Option<Vec<f32>>,
    /// The frame's camera.
    pub camera: Option<Camera>,
    /// The host's frame number.
    pub frame_index: Option<i64>,
    /// Color samples that were NaN or infinite and were replaced by 0.
    pub sanitized: usize,
    /// The negative parts of finite color samples, pixel by pixel in row
    /// order: `(y * width + x, [min(r, 0), min(g, 0), min(b, 0)])`. Colors
    /// outside the Rec.709 gamut (from an ACEScg or Rec.2020 host) have
    /// negative components in Linear Rec.709; the planes of `color` hold
    /// `max(c, 0)`, what every backend works on, and the session adds these
    /// parts back to the result, so they pass through untouched.
    pub out_of_gamut: Vec<(usize, [f32; 3])>,
    /// Samples of the other AOVs that were NaN or infinite and were replaced.
    pub sanitized_aovs: usize,
    /// Normal samples that were NaN or infinite (replaced by 0 when the
    /// normals are prepared, counted either way), those of
    /// `denoise_normal` included.
    pub sanitized_normals: usize,
    /// Albedo samples that were NaN or infinite (replaced by 0 when the
    /// albedo is prepared, counted either way; for the insert color matrix
    /// alone, among the samples it reads).
    pub sanitized_albedo: usize,
    /// Motion vectors longer than the image in either axis (a wrong scale
    /// or AOV), counted after scaling.
    pub huge_motion: usize,
    /// What preparing found while the rows were in cache (`None`: not
    /// scanned, for a frame made another way; the pipeline then looks
    /// itself).
    pub scan: Option<Scan>,
    /// The frame at the scene-cut detector's lattice
    /// ([`crate::temporal::Lattice`] of its size): premultiplied RGB and
    /// the coverage (1 where absent), row-major, kept while the rows were
    /// in cache; the detector needs them after the backend changed the
    /// color in place. `None` for a frame made another way (the detector
    /// then reads the planes).
    pub scene_samples: Option<Vec<[f32; 4]>>,
}

/// Where the holes and the insert are, found by [`PreparedFrame`]'s
/// preparation.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub struct Scan {
    /// The bounding box and number of the pixels whose coverage is below
    /// [`FULL`] (what [`crate::ops::inpaint::find_holes`] finds in the
    /// coverage); `None` when there are none or no coverage.
    pub holes: Option<(Rect, usize)>,
    /// The bounding box of the insert mask's pixels above 0 (what
    /// [`crate::ops::harmonize::insert_rect`] finds); `None` when there are
    /// none or no mask.
    pub insert: Option<Rect>,
}

/// Which of a frame's inputs [`PreparedFrame::from_input_with`] reads into
/// planes. An input not read is still checked (size, channels) and its
/// NaN and infinite samples counted.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub struct PrepareOptions {
    /// Read the normals (a backend that uses them, or the denoise stage
    /// without [`FrameInput::denoise_normal`]).
    pub normals: bool,
    /// Prepare the color as 4 planes, the 4th the coverage (1 where it is
    /// absent), written in the same pass: the working image of a backend
    /// that works in place ([`crate::backend::Backend::works_in_place`]).
    pub rgba: bool,
    /// Read the albedo and the denoise stage's normals.
    pub denoise_aux: bool,
    /// Read the albedo and the normals where the insert color matrix fits
    /// with them ([`crate::ops::albedo_tone::Samples`]).
    pub albedo: bool,
}

impl Default for PrepareOptions {
    /// Everything read, the color as 3 planes.
    fn default() -> Self {
        PrepareOptions {
            normals: true,
            rgba: false,
            denoise_aux: true,
            albedo: true,
        }
    }
}

impl PreparedFrame {
    /// A frame of `color` (premultiplied RGB planes, taken as they are)
    /// and nothing else: no AOVs, no camera, nothing sanitized or scanned.
    /// For tools and tests that build a frame's planes themselves.
    pub fn from_color(color: Image) -> PreparedFrame {
        PreparedFrame {
            color,
            coverage: None,
            depth: None,
            motion: None,
            normal: None,
            albedo: None,
            insert_aovs: None,
            denoise_normal: None,
            insert_mask: None,
            insert_id: None,
            camera: None,
            frame_index: None,
            sanitized: 0,
            out_of_gamut: Vec::new(),
            sanitized_aovs: 0,
            sanitized_normals: 0,
            sanitized_albedo: 0,
            huge_motion: 0,
            scan: None,
            scene_samples: None,
        }
    }

    /// Whether the frame has a hole (coverage below
    /// [`crate::ops::inpaint::FULL`]), from the scan made while preparing it
    /// when there is one.
    pub fn has_holes(&self) -> bool {
        match self.scan {
            Some(s) => s.holes.is_some(),
            None => {
                let full = crate::ops::inpaint::FULL;
                self.coverage
                    .as_ref()
                    .is_some_and(|c| c.iter().any(|&v| v < full))
            }
        }
    }

    /// Whether the frame has an insert (mask above 0), from the scan made
    /// while preparing it when there is one.
    pub fn has_insert(&self) -> bool {
        match self.scan {
            Some(s) => s.insert.is_some(),
            None => self
                .insert_mask
                .as_ref()
                .is_some_and(|m| m.iter().any(|&v| v > 0.0)),
        }
    }

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
        Self::prepare(input, depth_kind, None, None, PrepareOptions::default())
    }

    /// Like [`PreparedFrame::from_input`], row-parallel on `pool`; the result
    /// is the same for any number of threads.
    pub fn from_input_on(
        input: &FrameInput<'_>,
        depth_kind: DepthKind,
        pool: &rayon::ThreadPool,
    ) -> Result<PreparedFrame> {
        Self::prepare(
            input,
            depth_kind,
            Some(pool),
            None,
            PrepareOptions::default(),
        )
    }

    /// Like [`PreparedFrame::from_input_on`], with its buffers taken from
    /// `recycler` (give them back with [`PreparedFrame::recycle`]); the
    /// normals are prepared only when `normals` is true (else `normal` is
    /// `None`; their size and channels are still checked and their NaN and
    /// infinite samples counted in `sanitized_normals`); with `rgba` the color gets a
    /// 4th plane, the coverage (1 where absent), written in the same pass:
    /// the working image of a backend that works in place
    /// ([`crate::backend::Backend::works_in_place`]), no copy needed.
    pub fn from_input_recycled(
        input: &FrameInput<'_>,
        depth_kind: DepthKind,
        pool: &rayon::ThreadPool,
        recycler: &Recycler,
        normals: bool,
        rgba: bool,
    ) -> Result<PreparedFrame> {
        let options = PrepareOptions {
            normals,
            rgba,
            denoise_aux: false,
            albedo: false,
        };
        Self::from_input_with(input, depth_kind, pool, recycler, options)
    }

    /// Like [`PreparedFrame::from_input_recycled`], reading what `options`
    /// says (the albedo and the denoise stage's normals are counted only
    /// unless [`PrepareOptions::denoise_aux`]).
    pub fn from_input_with(
        input: &FrameInput<'_>,
        depth_kind: DepthKind,
        pool: &rayon::ThreadPool,
        recycler: &Recycler,
        options: PrepareOptions,
    ) -> Result<PreparedFrame> {
        Self::prepare(input, depth_kind, Some(pool), Some(recycler), options)
    }

    /// Takes the color out (for a backend that works on it in place),
    /// leaving an image of the frame's size with no planes, so
    /// [`PreparedFrame::width`] and [`PreparedFrame::height`] still hold.
    pub fn take_color(&mut self) -> Image {
        let (width, height) = (self.color.width, self.color.height);
        std::mem::replace(
            &mut self.color,
            Image {
                width,
                height,
                channels: 0,
                data: Vec::new(),
            },
        )
    }

    /// Gives the frame's buffers to `recycler`.
    pub fn recycle(self, recycler: &Recycler) {
        let width = self.color.width;
        recycler.give(self.color.data);
        if let Some(mask) = self.insert_mask {
            recycle_mask(recycler, mask, width, self.scan);
        }
        for b in [self.coverage, self.depth, self.insert_id]
            .into_iter()
            .flatten()
        {
            recycler.give(b);
        }
        for img in [self.motion, self.normal, self.albedo, self.denoise_normal]
            .into_iter()
            .flatten()
        {
            recycler.give(img.data);
        }
    }

    fn prepare(
        input: &FrameInput<'_>,
        depth_kind: DepthKind,
        pool: Option<&rayon::ThreadPool>,
        recycler: Option<&Recycler>,
        options: PrepareOptions,
    ) -> Result<PreparedFrame> {
        let PrepareOptions {
            normals,
            rgba,
            denoise_aux,
            albedo: albedo_wanted,
        } = options;
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
        check("albedo", &input.albedo, 3)?;
        check("denoise_normal", &input.denoise_normal, 3)?;
        check("coverage", &input.coverage, 1)?;
        check("insert_mask", &input.insert_mask, 1)?;
        check("insert_id", &input.insert_id, 1)?;
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

        // Fallible: a buffer the allocator refuses is an error, not an abort.
        let take = |ch: usize| match recycler {
            Some(r) => r.try_image(w, h, ch),
            None => Image::try_zeros(w, h, ch),
        };
        let mut sanitized_aovs = 0usize;
        // The insert mask, clamped to [0, 1] (NaN is 0, counted; zeros are
        // +0), and the bounding box of its pixels above 0
        // (`ops::harmonize::insert_rect`): found in a first pass that only
        // reads, then only the box is written into a buffer of zeros (an
        // insert usually covers a small part of the frame).
        let mut insert = None;
        let insert_mask = input
            .insert_mask
            .as_ref()
            .map(|v| -> Result<Vec<f32>> {
                let (bad, found) = scan_mask(pool, v);
                sanitized_aovs += bad;
                insert = found;
                let mut data = match recycler {
                    Some(r) => r.take_zeroed(w, h)?,
                    None => super::try_zeros(super::sample_count(w, h, 1)?)?,
                };
                if let Some(r) = found {
                    copy_mask_box(pool, v, &mut data, r);
                }
                Ok(data)
            })
            .transpose()?;
        // The insert's object ids: non-finite samples are 0 (counted),
        // negative ones 0. Without a mask, the mask is 1 where an id is
        // above 0, written only inside their box as above.
        let insert_id = input
            .insert_id
            .as_ref()
            .map(|v| -> Result<Vec<f32>> {
                let mut img = take(1)?;
                sanitized_aovs += read_image(pool, v, &mut img, |_, x| {
                    let bad = !x.is_finite();
                    *x = if bad { 0.0 } else { x.max(0.0) + 0.0 };
                    bad
                });
                Ok(img.data)
            })
            .transpose()?;
        let insert_mask = match (insert_mask, &insert_id) {
            (None, Some(ids)) => {
                insert = crate::ops::bbox_above(ids, w, h, 0.0).map(|(r, _)| r);
                let mut data = match recycler {
                    Some(r) => r.take_zeroed(w, h)?,
                    None => super::try_zeros(super::sample_count(w, h, 1)?)?,
                };
                if let Some(r) = insert {
                    for y in r.y0..r.y1 {
                        let s = y * w + r.x0..y * w + r.x1;
                        for (m, &id) in data[s.clone()].iter_mut().zip(&ids[s]) {
                            *m = if id > 0.0 { 1.0 } else { 0.0 };
                        }
                    }
                }
                Some(data)
            }
            (mask, _) => mask,
        };
        // NaN becomes `bad` (counted), everything else is clamped to [lo, hi].
        let mut read_planes = |v: &Option<ImageView<'_>>, ch: usize, lo: f32, hi: f32, bad: f32| {
            v.as_ref()
                .map(|v| -> Result<Image> {
                    let mut img = take(ch)?;
                    // By value (`move`): with the bounds behind references the
                    // loop does not vectorize (three times slower).
                    sanitized_aovs +=
                        read_image(pool, v, &mut img, move |_, x| sanitize(x, lo, hi, bad));
                    Ok(img)
                })
                .transpose()
        };
        // Coverage: NaN becomes 0 (counted), the rest is clamped to [0, 1].
        // It is read in the color pass, row by row beside the color, so
        // the alpha plane is its copy while the row is still in cache.
        let cov_fix = |x: &mut f32| sanitize(x, 0.0, 1.0, 0.0);
        let cov_view = input.coverage.as_ref();
        let mut coverage = cov_view.map(|_| take(1)).transpose()?.map(|i| i.data);
        let color_planes = if rgba { 4 } else { 3 };
        let mut color = take(color_planes)?;
        let lattice = Lattice::new(w, h);
        let scene_rows = LatticeRows::new(&lattice);
        // Negative parts of finite colors, split off row by row (see
        // `PreparedFrame::out_of_gamut`); sorted after the parallel pass.
        let gamut_rows = std::sync::Mutex::new(Vec::new());
        // The `fix` functions are written without branches (selects), so
        // their loops vectorize.
        let (sanitized, cov_found) = read_image_with(
            pool,
            &input.color,
            &mut color,
            3,
            coverage.as_deref_mut().into_iter().collect(),
            |_, v| {
                // Finite, as one plain compare (NaN fails it); negative
                // finite samples are split off below.
                let good = v.abs() < f32::INFINITY;
                *v = if good { *v } else { 0.0 };
                !good
            },
            |y, rows| {
                // Rows: R, G, B, then A when `rgba`, then the coverage when given.
                let lowest = crate::ops::row_min(rows[0])
                    .min(crate::ops::row_min(rows[1]))
                    .min(crate::ops::row_min(rows[2]));
                if lowest < 0.0 {
                    let mut parts = Vec::new();
                    for x in 0..rows[0].len() {
                        let neg = [rows[0][x], rows[1][x], rows[2][x]].map(|v| v.min(0.0));
                        if neg.iter().any(|&v| v < 0.0) {
                            parts.push((y * w + x, neg));
                            for row in rows[..3].iter_mut() {
                                row[x] = row[x].max(0.0);
                            }
                        }
                    }
                    gamut_rows
                        .lock()
                        .unwrap_or_else(|e| e.into_inner())
                        .extend(parts);
                }
                let mut found = Found::default();
                if let Some(v) = cov_view {
                    let c = &mut *rows[color_planes];
                    v.read_row(y, 0, c);
                    let bad = c.iter_mut().map(|x| u32::from(cov_fix(x))).sum::<u32>() as usize;
                    // The holes (what `ops::inpaint::find_holes` finds),
                    // while the row is in cache.
                    found = Found::row(y, c, crate::ops::row_min(c) < FULL, |v| v < FULL);
                    found.n = bad;
                }
                if rgba {
                    // The coverage, or 1 where there is none.
                    let (head, tail) = rows.split_at_mut(4);
                    match tail.first() {
                        Some(c) => head[3].copy_from_slice(c),
                        None => head[3].fill(1.0),
                    }
                }
                let cov_row = cov_view.map(|_| &*rows[color_planes]);
                scene_rows.set(y, |x| {
                    let c = cov_row.map_or(1.0, |c| c[x]);
                    [rows[0][x], rows[1][x], rows[2][x], c]
                });
                found
            },
        );
        let (cov_bad, holes) = (cov_found.n, cov_found.bbox);

        let mut depth = read_planes(&input.depth, 1, 0.0, f32::MAX, f32::MAX)?.map(|i| i.data);
        // Normals: NaN and infinite samples are 0 (counted apart, see
        // `sanitized_normals`); read into planes only for a backend that
        // reads them, else only counted (one read-only pass).
        let mut sanitized_normals = 0;
        let normal = match input.normal.as_ref() {
            Some(v) if normals => {
                let mut img = take(3)?;
                sanitized_normals = read_image(pool, v, &mut img, |_, x| {
                    let bad = !x.is_finite();
                    *x = if bad { 0.0 } else { *x };
                    bad
                });
                Some(img)
            }
            Some(v) => {
                sanitized_normals = count_non_finite(pool, v, 3);
                None
            }
            None => None,
        };
        // The insert color matrix's albedo and normals, where it reads them
        // (the normals are counted whole above).
        let (insert_aovs, bad_sampled) = match (&input.albedo, &input.normal, insert) {
            (Some(a), Some(n), Some(rect)) if albedo_wanted => {
                let (samples, bad_albedo, _) =
                    crate::ops::albedo_tone::Samples::read(a, n, rect, pool);
                (Some(samples), bad_albedo)
            }
            _ => (None, 0),
        };
        // The denoise stage's albedo and normals, validated as the normals
        // are: non-finite samples are 0 (counted); the albedo is clamped
        // to [0, 1] (Open Image Denoise's range for it).
        let aux = |v: Option<&ImageView<'_>>, albedo: bool| -> Result<(Option<Image>, usize)> {
            let Some(v) = v else {
                return Ok((None, 0));
            };
            if !denoise_aux {
                // The insert color matrix counted what it read.
                let counted = match albedo && insert_aovs.is_some() {
                    true => bad_sampled,
                    false => count_non_finite(pool, v, 3),
                };
                return Ok((None, counted));
            }
            let hi = if albedo { 1.0 } else { f32::MAX };
            let lo = if albedo { 0.0 } else { -f32::MAX };
            let mut img = take(3)?;
            let bad = read_image(pool, v, &mut img, move |_, x| {
                let bad = !x.is_finite();
                *x = if bad { 0.0 } else { clamp(*x, lo, hi) };
                bad
            });
            Ok((Some(img), bad))
        };
        let (albedo, sanitized_albedo) = aux(input.albedo.as_ref(), true)?;
        let (denoise_normal, bad_denoise_normals) = aux(input.denoise_normal.as_ref(), false)?;
        sanitized_normals += bad_denoise_normals;
        let limit = 4.0 * (w.max(h) as f32);
        let (wf, hf) = (w as f32, h as f32);
        let mut huge_motion = 0;
        let motion = input.motion.as_ref().map(|v| -> Result<Image> {
            let mut img = take(2)?;
            let (bad, huge) = read_image_with(
                pool,
                v,
                &mut img,
                2,
                Vec::new(),
                move |c, x| {
                    let nan = x.is_nan();
                    let scaled = clamp(clamp(*x, -f32::MAX, f32::MAX) * s[c], -limit, limit);
                    *x = if nan { 0.0 } else { scaled };
                    nan
                },
                // Vectors longer than the image, counted on the row just read.
                |_, rows| Found {
                    n: rows[0]
                        .iter()
                        .zip(rows[1].iter())
                        .map(|(x, y)| u32::from((x.abs() > wf) | (y.abs() > hf)))
                        .sum::<u32>() as usize,
                    bbox: None,
                },
            );
            sanitized_aovs += bad;
            huge_motion = huge.n;
            Ok(img)
        });
        let motion = motion.transpose()?;
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
            albedo,
            insert_aovs,
            denoise_normal,
            insert_mask,
            insert_id,
            scan: Some(Scan { holes, insert }),
            scene_samples: scene_rows.finish(),
            camera: input.camera,
            frame_index: input.frame_index,
            sanitized,
            out_of_gamut: {
                let mut g = gamut_rows.into_inner().unwrap_or_else(|e| e.into_inner());
                g.sort_unstable_by_key(|p| p.0);
                g
            },
            sanitized_aovs: sanitized_aovs + cov_bad,
            sanitized_normals,
            sanitized_albedo,
            huge_motion,
        })
    }
}
