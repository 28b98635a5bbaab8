//! The neural backend: an ONNX model run through ONNX Runtime (`ort`,
//! loaded dynamically), described by a JSON [`Manifest`].
//!
//! Per frame: one exposure scale for the whole frame ([`encoding`]), the
//! frame cut into tiles ([`tiling`]; one tile when the frame fits a window),
//! each tile's NCHW input built from the frame, its guides and the K
//! reprojected history frames in the manifest's channel order, the model run,
//! its output decoded and (with several tiles) blended into the frame with
//! feathered weights. The per-pixel work (encoding, copies, decoding) runs
//! over rows on the device's thread pool, each pixel computed once per frame
//! and the same way whatever the thread count. Progress is reported per tile
//! and cancellation is honoured between tiles.

pub mod encoding;
pub mod prior;
pub mod runtime;
pub mod tiling;

use std::path::{Path, PathBuf};
use std::sync::{Arc, Mutex};

use rayon::prelude::*;

use super::{Backend, BackendInput, Carry, Progress, Stages};
use crate::device::{DeviceOptions, ModelSource};
use crate::error::{Error, Result};
use crate::frame::Image;
use crate::model::{InputChannel, Manifest, REPAIR_EDGE_SHARE};
use crate::ops::inpaint::{SpatialFill, FULL};
use crate::params::Params;
use crate::temporal::{HistoryView, ReprojectedFrame, RowScratch};
use encoding::ColorCodec;
use tiling::{reflect, TilePlan};

/// A loaded model, shared by the sessions of a device.
pub struct NeuralModel {
    /// Model name from the manifest.
    pub name: String,
    /// Model version from the manifest.
    pub version: String,
    /// The validated manifest.
    pub manifest: Manifest,
    /// Where the model came from (file path, "embedded" or "in-memory model").
    pub origin: String,
    channels: Vec<InputChannel>,
    /// The prior the runtime computes, for a model whose graph reads it.
    prior: Option<prior::PriorChannels>,
    output_order: Vec<usize>,
    /// Static window size of the model input (width, height), if not dynamic.
    fixed: (Option<usize>, Option<usize>),
    memory_limit: usize,
    threads: usize,
    runtime: PathBuf,
    session: Mutex<ort::session::Session>,
    /// Frame-sized work buffers kept between frames (fresh memory costs page
    /// faults on every frame).
    buffers: Mutex<Vec<Vec<f32>>>,
}

/// Work buffers kept for reuse per model: up to three per frame (the
/// tile's input, the prior's scratch, the computed planes of a tiled
/// frame), two frames in flight.
const KEPT_BUFFERS: usize = 6;

/// A work buffer borrowed from a model; returned to it when dropped.
struct Buffer<'a> {
    model: &'a NeuralModel,
    data: Vec<f32>,
}

impl Drop for Buffer<'_> {
    fn drop(&mut self) {
        let mut kept = self.model.buffers.lock().unwrap_or_else(|p| p.into_inner());
        if kept.len() < KEPT_BUFFERS {
            kept.push(std::mem::take(&mut self.data));
        }
    }
}

impl std::fmt::Debug for NeuralModel {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.debug_struct("NeuralModel")
            .field("name", &self.name)
            .field("version", &self.version)
            .field("origin", &self.origin)
            .field("runtime", &self.runtime)
            .finish_non_exhaustive()
    }
}

fn model_err(origin: &str, e: impl std::fmt::Display) -> Error {
    Error::Model(format!("model {origin}: {e}"))
}

/// Reads the manifest beside an `.onnx` file (`<model>.json`).
pub fn manifest_path(onnx: &Path) -> PathBuf {
    onnx.with_extension("json")
}

/// The ONNX bytes, manifest text, and the names of both in messages, of a
/// model given as a file or as bytes (`None` for the embedded model).
type Source<'a> = (
    std::borrow::Cow<'a, [u8]>,
    std::borrow::Cow<'a, str>,
    String,
    String,
);

/// Reads the model `options` name from its file and manifest file, or
/// borrows the bytes given; `Ok(None)` for the embedded model.
fn read_source(options: &DeviceOptions) -> Result<Option<Source<'_>>> {
    Ok(match &options.model {
        ModelSource::Embedded => None,
        ModelSource::File(path) => {
            let json_path = manifest_path(path);
            let onnx = std::fs::read(path).map_err(|e| Error::io(path, e))?;
            let manifest = std::fs::read_to_string(&json_path).map_err(|e| {
                Error::Model(format!(
                    "model {}: cannot read its manifest {}: {e}",
                    path.display(),
                    json_path.display()
                ))
            })?;
            Some((
                onnx.into(),
                manifest.into(),
                path.display().to_string(),
                json_path.display().to_string(),
            ))
        }
        ModelSource::Bytes { onnx, manifest } => Some((
            onnx.as_slice().into(),
            manifest.as_str().into(),
            "in-memory model".to_string(),
            "of in-memory model".to_string(),
        )),
    })
}

/// Checks without ONNX Runtime that `onnx` is an ONNX model whose graph has
/// the manifest's input and output ([`crate::model::onnx::inspect`]).
fn check_graph(onnx: &[u8], manifest: &Manifest, origin: &str) -> Result<()> {
    let names = crate::model::onnx::inspect(onnx)
        .map_err(|e| model_err(origin, format!("not an ONNX model: {e}")))?;
    for (spec, list, what) in [
        (&manifest.input, &names.inputs, "input"),
        (&manifest.output, &names.outputs, "output"),
    ] {
        if !list.contains(&spec.name) {
            let listed: Vec<String> = list.iter().map(|n| format!("{n:?}")).collect();
            return Err(model_err(
                origin,
                format!(
                    "manifest field {what}.name is {:?} but the model's {what}s are {}",
                    spec.name,
                    listed.join(", ")
                ),
            ));
        }
    }
    Ok(())
}

impl NeuralModel {
    /// Loads the model the options name; `Ok(None)` for `Embedded` when this
    /// build embeds no model.
    pub fn load(options: &DeviceOptions) -> Result<Option<Arc<NeuralModel>>> {
        match &options.model {
            ModelSource::Embedded => match crate::model::embedded() {
                Some(m) => Self::from_bytes(m.onnx, m.manifest, "embedded", options).map(Some),
                None => Ok(None),
            },
            _ => {
                let (onnx, manifest, origin, manifest_origin) =
                    read_source(options)?.expect("a file or bytes");
                Self::load_parts(&onnx, &manifest, &origin, &manifest_origin, options).map(Some)
            }
        }
    }

    /// Loads a model from its ONNX bytes and manifest text; `origin` names it in errors.
    pub fn from_bytes(
        onnx: &[u8],
        manifest: &str,
        origin: &str,
        options: &DeviceOptions,
    ) -> Result<Arc<NeuralModel>> {
        Self::load_parts(onnx, manifest, origin, &format!("of {origin}"), options)
    }

    fn load_parts(
        onnx: &[u8],
        manifest_text: &str,
        origin: &str,
        manifest_origin: &str,
        options: &DeviceOptions,
    ) -> Result<Arc<NeuralModel>> {
        let manifest = Manifest::from_json(manifest_text, manifest_origin)?;
        check_graph(onnx, &manifest, origin)?;
        let (env, runtime) = runtime::environment(options.ort_library.as_deref())?;
        let threads = if options.threads == 0 {
            std::thread::available_parallelism()
                .map(|n| n.get())
                .unwrap_or(1)
        } else {
            options.threads
        };
        let session = (|| -> std::result::Result<ort::session::Session, ort::Error> {
            ort::session::Session::builder(&env)?
                .with_intra_threads(threads)?
                .with_inter_threads(1)?
                .with_parallel_execution(false)?
                .with_deterministic_compute(true)?
                .with_intra_op_spinning(false)?
                .with_inter_op_spinning(false)?
                .commit_from_memory(onnx)
        })()
        .map_err(|e| model_err(origin, format!("ONNX Runtime cannot load it: {e}")))?;

        let fixed = check_signature(&session, &manifest, origin)?;
        let channels = manifest.input_channels();
        Ok(Arc::new(NeuralModel {
            name: manifest.name.clone(),
            version: manifest.version.clone(),
            prior: prior::PriorChannels::new(manifest.prior, &channels),
            channels,
            output_order: manifest.output_order(),
            manifest,
            origin: origin.to_string(),
            fixed,
            memory_limit: options.memory_limit,
            threads,
            runtime,
            session: Mutex::new(session),
            buffers: Mutex::new(Vec::new()),
        }))
    }

    /// The ONNX Runtime library this model runs on.
    pub fn runtime_path(&self) -> &Path {
        &self.runtime
    }

    /// ONNX Runtime intra-op threads.
    pub fn threads(&self) -> usize {
        self.threads
    }

    /// Tile size for `params` (`tile_size`, 0 = the manifest's).
    pub fn tile_size(&self, params: &Params) -> usize {
        if params.tile_size > 0 {
            params.tile_size
        } else {
            self.manifest.tile_size
        }
    }

    /// Tile overlap for `params` (`tile_overlap`, 0 = the manifest's).
    pub fn tile_overlap(&self, params: &Params) -> usize {
        if params.tile_overlap > 0 {
            params.tile_overlap
        } else {
            self.manifest.tile_overlap
        }
    }

    /// Estimated working memory in bytes of a frame run with `plan`: the
    /// frame's output (4 planes), with several tiles the frame-sized planes of
    /// the computed input channels (encoded color and history, disparity;
    /// the history channels are now written into each tile's input instead,
    /// an upper bound kept so that tile plans stay as they were), plus one
    /// tile's network working set.
    pub fn working_bytes(&self, plan: &TilePlan) -> usize {
        let computed = if plan.len() > 1 {
            self.channels
                .iter()
                .filter(|ch| {
                    matches!(
                        ch,
                        InputChannel::Color(_)
                            | InputChannel::History(..)
                            | InputChannel::Disparity
                    )
                })
                .count()
        } else {
            0
        };
        4 * (4 + computed) * plan.width * plan.height
            + plan.window_pixels() * self.manifest.tile_bytes_per_pixel()
    }

    /// The tiling of a `width` x `height` frame under `params`: the requested
    /// tile size, shrunk (in steps of `spatial_multiple`) until the working
    /// memory fits the device's `memory_limit` (the whole limit: see
    /// [`NeuralModel::tile_plan_within`] for what a session leaves).
    pub fn tile_plan(&self, width: usize, height: usize, params: &Params) -> Result<TilePlan> {
        let budget = match self.memory_limit {
            0 => usize::MAX,
            n => n,
        };
        self.tile_plan_within(width, height, params, budget)
    }

    /// Checks that the tile settings of `params` (`tile_size`,
    /// `tile_overlap`, 0 = the manifest's) can tile a frame of any size with
    /// this model (its `spatial_multiple` and static size), as
    /// [`tiling::check_settings`] finds; the error names both parameters.
    pub fn check_params(&self, params: &Params) -> Result<()> {
        let m = self.manifest.spatial_multiple;
        let (tile, overlap) = (self.tile_size(params), self.tile_overlap(params));
        let named = |name: &str, set: usize, used: usize| match set {
            0 => format!("{name} 0 (the model's {used})"),
            _ => format!("{name} {used}"),
        };
        for fixed in [self.fixed.0, self.fixed.1] {
            if let Err(why) = tiling::check_settings(tile, overlap, m, fixed) {
                let fix = match fixed {
                    Some(f) => format!(
                        "the model's input is {f} px, so tile_size does not apply; lower tile_overlap"
                    ),
                    None => match tiling::smallest_tile(overlap, m) {
                        Some(t) => format!("use tile_size >= {t} with tile_overlap {overlap}"),
                        None => "lower tile_overlap".to_string(),
                    },
                };
                return Err(Error::invalid(format!(
                    "parameters {} and {} cannot tile frames with model {} (spatial_multiple {m}): {why}; {fix}",
                    named("tile_size", params.tile_size, tile),
                    named("tile_overlap", params.tile_overlap, overlap),
                    self.name,
                )));
            }
        }
        Ok(())
    }

    /// [`NeuralModel::tile_plan`] with the tiles' working memory
    /// ([`NeuralModel::working_bytes`]) kept within `budget` bytes
    /// (`usize::MAX`: no limit).
    pub fn tile_plan_within(
        &self,
        width: usize,
        height: usize,
        params: &Params,
        budget: usize,
    ) -> Result<TilePlan> {
        let m = self.manifest.spatial_multiple;
        let overlap = self.tile_overlap(params);
        let requested = self.tile_size(params);
        let plan = |tile: usize| TilePlan::new(width, height, tile, overlap, m, self.fixed);
        let mut tile = requested;
        let mut p = plan(tile).map_err(|e| Error::invalid(format!("model {}: {e}", self.name)))?;
        if budget == usize::MAX || self.fixed.0.is_some() && self.fixed.1.is_some() {
            return Ok(p);
        }
        while self.working_bytes(&p) > budget {
            let smaller = (p.x.window.max(p.y.window).min(tile) / m).saturating_sub(1) * m;
            if smaller < 4 * overlap + 2 || smaller < m {
                let limit = match self.memory_limit {
                    0 => "the memory of this machine".to_string(),
                    n => format!("memory_limit {n} bytes"),
                };
                return Err(Error::OutOfMemory(format!(
                    "{limit} ({budget} left for the tiles): a {width}x{height} frame needs \
                     at least {} bytes with model {} (tiles of {}x{} px, tile_overlap {overlap})",
                    self.working_bytes(&p),
                    self.name,
                    p.x.window,
                    p.y.window
                )));
            }
            tile = smaller;
            p = plan(tile).map_err(|e| Error::invalid(format!("model {}: {e}", self.name)))?;
        }
        Ok(p)
    }

    /// A work buffer of `len` values with unspecified contents (the caller
    /// writes every value before reading it).
    fn buffer(&self, len: usize) -> Buffer<'_> {
        let mut data = {
            let mut kept = self.buffers.lock().unwrap_or_else(|p| p.into_inner());
            // The largest kept buffer (frames of one session have one size).
            let best = (0..kept.len()).max_by_key(|&i| kept[i].capacity());
            best.map(|i| kept.swap_remove(i)).unwrap_or_default()
        };
        data.resize(len, 0.0);
        Buffer { model: self, data }
    }

    /// Runs the network on one NCHW input and hands the output tensor data to
    /// `use_output` (read in place, before ONNX Runtime releases it).
    fn run<T>(
        &self,
        input: &[f32],
        w: usize,
        h: usize,
        use_output: impl FnOnce(&[f32]) -> T,
    ) -> Result<T> {
        let cin = self.channels.len();
        let tensor = ort::value::TensorRef::from_array_view(([1usize, cin, h, w], input))
            .map_err(|e| model_err(&self.origin, format!("cannot make the input tensor: {e}")))?;
        let mut session = self.session.lock().unwrap_or_else(|p| p.into_inner());
        let outputs = session
            .run(ort::inputs![self.manifest.input.name.as_str() => tensor])
            .map_err(|e| {
                model_err(
                    &self.origin,
                    format!("inference failed on a {w}x{h} tile: {e}"),
                )
            })?;
        let name = &self.manifest.output.name;
        let value = outputs.get(name).ok_or_else(|| {
            model_err(
                &self.origin,
                format!("the model produced no output {name:?}"),
            )
        })?;
        let (shape, data) = value.try_extract_tensor::<f32>().map_err(|e| {
            model_err(
                &self.origin,
                format!("output {name:?} is not a float tensor: {e}"),
            )
        })?;
        let want = [1, self.output_order.len() as i64, h as i64, w as i64];
        if **shape != want {
            return Err(model_err(
                &self.origin,
                format!(
                    "output {name:?} has shape {:?}, expected {want:?}",
                    &**shape
                ),
            ));
        }
        Ok(use_output(data))
    }
}

/// Checks the model's input and output against the manifest; returns the
/// static (width, height) of the input, if fixed.
fn check_signature(
    session: &ort::session::Session,
    manifest: &Manifest,
    origin: &str,
) -> Result<(Option<usize>, Option<usize>)> {
    let names = |outlets: &[ort::value::Outlet]| {
        outlets
            .iter()
            .map(|o| format!("{:?}", o.name()))
            .collect::<Vec<_>>()
            .join(", ")
    };
    let check = |outlets: &[ort::value::Outlet],
                 spec: &crate::model::TensorSpec,
                 what: &str|
     -> Result<Vec<i64>> {
        let Some(o) = outlets.iter().find(|o| o.name() == spec.name) else {
            return Err(model_err(
                origin,
                format!(
                    "manifest field {what}.name is {:?} but the model's {what}s are {}",
                    spec.name,
                    names(outlets)
                ),
            ));
        };
        let ort::value::ValueType::Tensor { ty, shape, .. } = o.dtype() else {
            return Err(model_err(
                origin,
                format!("{what} {:?} is not a tensor", spec.name),
            ));
        };
        if *ty != ort::value::TensorElementType::Float32 {
            return Err(model_err(
                origin,
                format!(
                    "{what} {:?} has element type {ty:?}, expected f32",
                    spec.name
                ),
            ));
        }
        if shape.len() != 4 {
            return Err(model_err(
                origin,
                format!(
                    "{what} {:?} has {} dimensions {:?}, expected 4 (NCHW)",
                    spec.name,
                    shape.len(),
                    &**shape
                ),
            ));
        }
        let c = shape[1];
        if c > 0 && c as usize != spec.channels.len() {
            return Err(model_err(
                origin,
                format!(
                    "{what} {:?} has {c} channels but manifest field {what}.channels lists {}",
                    spec.name,
                    spec.channels.len()
                ),
            ));
        }
        if shape[0] > 1 {
            return Err(model_err(
                origin,
                format!(
                    "{what} {:?} has batch size {}, expected 1",
                    spec.name, shape[0]
                ),
            ));
        }
        Ok(shape.to_vec())
    };
    let input = check(session.inputs(), &manifest.input, "input")?;
    check(session.outputs(), &manifest.output, "output")?;
    if session.inputs().len() != 1 {
        return Err(model_err(
            origin,
            format!(
                "the model has {} inputs ({}), expected 1",
                session.inputs().len(),
                names(session.inputs())
            ),
        ));
    }
    let dim = |d: i64| (d > 0).then_some(d as usize);
    let fixed = (dim(input[3]), dim(input[2]));
    for (d, name) in [(fixed.0, "width"), (fixed.1, "height")] {
        if let Some(d) = d {
            if !d.is_multiple_of(manifest.spatial_multiple) || d < 2 * manifest.tile_overlap + 2 {
                return Err(model_err(
                    origin,
                    format!(
                        "static input {name} {d} is not a multiple of spatial_multiple {} or leaves no room \
                         inside tile_overlap {}",
                        manifest.spatial_multiple, manifest.tile_overlap
                    ),
                ));
            }
        }
    }
    Ok(fixed)
}

/// The neural backend over a loaded model.
#[derive(Debug)]
pub struct Neural {
    /// The model.
    pub model: Arc<NeuralModel>,
}

/// Where one input channel's rows come from.
#[derive(Clone, Copy)]
enum Src<'a> {
    /// The same value everywhere (absent inputs).
    Const(f32),
    /// A frame-sized plane, copied as is.
    Copy(&'a [f32]),
    /// Color encoded with the frame's codec (premultiplied as stored).
    Encode(&'a [f32]),
    /// Premultiplied color divided by `alpha` (0 in holes), then encoded.
    EncodeStraight(&'a [f32], &'a [f32]),
    /// Planar depth as `1 / (1 + max(d, 0))`.
    Disparity(&'a [f32]),
    /// A channel of a reprojected history frame, computed row by row with
    /// the others by [`history_window`] (never through [`Src::row`]).
    History,
    /// Already written into the tile's input (by [`history_window`]).
    Filled,
}

impl Src<'_> {
    /// True for sources computed per pixel (worth computing once per frame).
    fn computed(&self) -> bool {
        matches!(
            self,
            Src::Encode(_) | Src::EncodeStraight(..) | Src::Disparity(_)
        )
    }

    /// Writes frame row `y`, columns `x0..x0 + dst.len()`, into `dst`.
    #[inline]
    fn row(&self, codec: &ColorCodec, width: usize, y: usize, x0: usize, dst: &mut [f32]) {
        let r = y * width + x0..y * width + x0 + dst.len();
        match *self {
            Src::Const(v) => dst.fill(v),
            Src::Copy(p) => dst.copy_from_slice(&p[r]),
            Src::Encode(p) => codec.encode_row(&p[r], dst),
            Src::EncodeStraight(p, a) => codec.encode_straight_row(&p[r.clone()], &a[r], dst),
            Src::Disparity(p) => dst
                .iter_mut()
                .zip(&p[r])
                .for_each(|(o, &d)| *o = 1.0 / (1.0 + d.max(0.0))),
            Src::History | Src::Filled => {
                unreachable!("history channels are written by history_window")
            }
        }
    }
}

/// The sources of the model's input channels, in the manifest's order.
fn channel_sources<'a>(
    channels: &[InputChannel],
    frame: &'a crate::frame::PreparedFrame,
    used: usize,
    premultiplied: bool,
) -> Vec<Src<'a>> {
    let coverage = frame.coverage.as_deref();
    channels
        .iter()
        .map(|&ch| match ch {
            InputChannel::Color(c) => {
                let p = frame.color.plane(c);
                match (premultiplied, coverage) {
                    (false, Some(a)) => Src::EncodeStraight(p, a),
                    _ => Src::Encode(p),
                }
            }
            InputChannel::Coverage => coverage.map_or(Src::Const(1.0), Src::Copy),
            InputChannel::Insert => frame
                .insert_mask
                .as_deref()
                .map_or(Src::Const(0.0), Src::Copy),
            InputChannel::Disparity => frame
                .depth
                .as_deref()
                .map_or(Src::Const(0.0), Src::Disparity),
            InputChannel::Normal(c) => frame
                .normal
                .as_ref()
                .map_or(Src::Const(0.0), |n| Src::Copy(n.plane(c))),
            InputChannel::Motion(c) => frame
                .motion
                .as_ref()
                .map_or(Src::Const(0.0), |m| Src::Copy(m.plane(c))),
            InputChannel::History(k, _)
            | InputChannel::HistoryAlpha(k)
            | InputChannel::Valid(k) => match k < used {
                true => Src::History,
                false => Src::Const(0.0),
            },
            // Computed into each tile's input from its other channels.
            InputChannel::Prior(_) => Src::Filled,
        })
        .collect()
}

/// What a history input channel holds of its reprojected frame.
#[derive(Clone, Copy)]
enum HistPart {
    /// Color channel `c`, encoded (straight or premultiplied as the model reads it).
    Color(usize),
    /// The reprojected alpha, as is.
    Alpha,
    /// The validity, as is.
    Valid,
}

/// The history input channels that read one of the first `used` history
/// frames: (input channel, history frame, part), in channel order.
fn history_slots(channels: &[InputChannel], used: usize) -> Vec<(usize, usize, HistPart)> {
    channels
        .iter()
        .enumerate()
        .filter_map(|(slot, &ch)| match ch {
            InputChannel::History(k, c) => Some((slot, k, HistPart::Color(c))),
            InputChannel::HistoryAlpha(k) => Some((slot, k, HistPart::Alpha)),
            InputChannel::Valid(k) => Some((slot, k, HistPart::Valid)),
            _ => None,
        })
        .filter(|&(_, k, _)| k < used)
        .collect()
}

/// Writes the history input channels `slots` of one tile's input, their
/// planes (window-sized) in `planes`, in the slots' order: each window row
/// is reprojected over the frame columns the window covers
/// ([`HistoryView::reproject_rows`], the same bits as whole reprojected
/// frames) and encoded while it is in cache, so no frame-sized
/// reprojection is written and read back; rows and columns outside the
/// frame are mirror reflections, as [`fill_window`] writes them. Window
/// rows in parallel on `pool` (each written by one task: the same bits on
/// any thread count). With `keep`, history frame 0's runs over the tile's
/// core are also copied into `keep`'s frame-sized planes.
#[allow(clippy::too_many_arguments)]
fn history_window(
    view: &HistoryView<'_>,
    slots: &[(usize, usize, HistPart)],
    codec: &ColorCodec,
    premultiplied: bool,
    planes: Vec<&mut [f32]>,
    (width, height): (usize, usize),
    tile: tiling::Tile,
    keep: Option<Keep<'_>>,
    pool: &rayon::ThreadPool,
    fresh: Option<&Refresh<'_>>,
) {
    let Some(n) = slots.iter().map(|&(_, k, _)| k + 1).max() else {
        return;
    };
    let (ww, wh) = tile.size;
    let (ox, oy) = tile.origin;
    // Window columns [c0, c1) lie inside the frame, at frame columns [c0 + ox, c1 + ox).
    let c0 = (-ox).max(0) as usize;
    let c1 = ((width as isize - ox).min(ww as isize)).max(c0 as isize) as usize;
    let fx0 = (c0 as isize + ox) as usize;
    let mut rows: Vec<_> = planes.into_iter().map(|p| p.chunks_exact_mut(ww)).collect();
    let rows: Vec<Vec<&mut [f32]>> = (0..wh)
        .map(|_| {
            rows.iter_mut()
                .map(|p| p.next().expect("wh rows"))
                .collect()
        })
        .collect();
    // Per window row, the runs of `keep`'s planes it writes (frame row
    // `oy + wy` inside the core's rows, the core's columns), else none.
    let mut kept: Vec<Vec<&mut [f32]>> = (0..wh).map(|_| Vec::new()).collect();
    let mut kept_cols = 0..0;
    if let Some(Keep {
        planes,
        cols,
        rows: (r0, r1),
    }) = keep
    {
        debug_assert!(fx0 <= cols.0 && cols.1 <= fx0 + (c1 - c0));
        kept_cols = cols.0 - fx0..cols.1 - fx0;
        for p in planes {
            for (fy, row) in p.chunks_exact_mut(width).enumerate().take(r1).skip(r0) {
                kept[(fy as isize - oy) as usize].push(&mut row[cols.0..cols.1]);
            }
        }
    }
    // Frame row `fy`, frame columns `fx..fx + len`, into window columns
    // `at..at + len` of `dst`; history frame 0's `kept_cols` of the run into
    // `keep` (the five planes, or none), as reprojected (before the pull
    // toward the frame's own fill).
    let write = |(scratch, mixed): &mut (RowScratch, [Vec<f32>; 4]),
                 dst: &mut [&mut [f32]],
                 keep: &mut [&mut [f32]],
                 fy,
                 fx: usize,
                 at: usize,
                 len| {
        view.reproject_rows(n, fy, fx..fx + len, scratch, |k, run| {
            if k == 0 {
                for (kp, src) in keep.iter_mut().zip(run) {
                    kp.copy_from_slice(&src[kept_cols.clone()]);
                }
            }
            let [r, g, b, a, v] = run;
            // Where the current frame has a hole, the history is first
            // pulled toward the frame's own fill (the prior fills holes
            // from it; `Refresh`).
            let holes = fresh.filter(|f| {
                f.coverage[fy * width + fx..fy * width + fx + len]
                    .iter()
                    .any(|&c| c < FULL)
            });
            let (r, g, b, a) = match holes {
                Some(f) => {
                    for (m, src) in mixed.iter_mut().zip([r, g, b, a]) {
                        m.clear();
                        m.extend_from_slice(src);
                    }
                    let [mr, mg, mb, ma] = mixed;
                    for t in 0..len {
                        if f.coverage[fy * width + fx + t] < FULL {
                            let c = f
                                .fill
                                .pull(fy, fx + t, [mr[t], mg[t], mb[t], ma[t]], f.share);
                            (mr[t], mg[t], mb[t], ma[t]) = (c[0], c[1], c[2], c[3]);
                        }
                    }
                    (&mr[..], &mg[..], &mb[..], &ma[..])
                }
                None => (r, g, b, a),
            };
            let rgb = [r, g, b];
            for (d, &(_, sk, part)) in dst.iter_mut().zip(slots) {
                if sk != k {
                    continue;
                }
                let d = &mut d[at..at + len];
                match part {
                    HistPart::Color(c) if premultiplied => codec.encode_row(rgb[c], d),
                    HistPart::Color(c) => codec.encode_straight_row(rgb[c], a, d),
                    HistPart::Alpha => d.copy_from_slice(a),
                    HistPart::Valid => d.copy_from_slice(v),
                }
            }
        });
    };
    pool.install(|| {
        rows.into_par_iter()
            .zip(kept)
            .enumerate()
            .with_min_len(4)
            .for_each_init(
                || (RowScratch::new(c1 - c0, n), Default::default()),
                |scratch, (wy, (mut dst, mut keep))| {
                    let fy = reflect(oy + wy as isize, height);
                    write(scratch, &mut dst, &mut keep, fy, fx0, c0, c1 - c0);
                    for wx in (0..c0).chain(c1..ww) {
                        let fx = reflect(ox + wx as isize, width);
                        let inside = fx as isize - ox;
                        if inside >= c0 as isize && inside < c1 as isize {
                            for d in dst.iter_mut() {
                                d[wx] = d[inside as usize];
                            }
                        } else {
                            write(scratch, &mut dst, &mut [], fy, fx, wx, 1);
                        }
                    }
                },
            );
    });
}

/// The current frame's own fill of its holes ([`SpatialFill`]), toward which
/// the history input is pulled by `share` at the frame's hole pixels
/// (those with coverage below [`FULL`]).
struct Refresh<'a> {
    fill: SpatialFill,
    coverage: &'a [f32],
    share: f32,
}

/// Where [`history_window`] copies history frame 0's reprojection: the
/// frame-sized planes (R, G, B, A, validity) and the frame columns and rows
/// of the tile's core (the cores of a plan cover every pixel once).
struct Keep<'k> {
    planes: [&'k mut [f32]; 5],
    cols: (usize, usize),
    rows: (usize, usize),
}

/// Fills a tile's NCHW input tensor, one window row per task: frame rows and
/// columns outside the frame are mirror reflections; each window row is
/// written once from its frame row (plain copies for precomputed planes), and
/// its reflected columns are copied from the row itself.
fn fill_window(
    tensor: &mut [f32],
    sources: &[Src<'_>],
    codec: &ColorCodec,
    (width, height): (usize, usize),
    tile: tiling::Tile,
    pool: &rayon::ThreadPool,
) {
    let (ww, wh) = tile.size;
    let (ox, oy) = tile.origin;
    // Window columns [c0, c1) lie inside the frame, at frame columns [c0 + ox, c1 + ox).
    let c0 = (-ox).max(0) as usize;
    let c1 = ((width as isize - ox).min(ww as isize)).max(c0 as isize) as usize;
    let fx0 = (c0 as isize + ox) as usize;
    pool.install(|| {
        tensor
            .par_chunks_mut(ww)
            .with_min_len(4)
            .enumerate()
            .for_each(|(r, row)| {
                let (ch, wy) = (r / wh, r % wh);
                let src = &sources[ch];
                if matches!(src, Src::Filled) {
                    return;
                }
                let fy = reflect(oy + wy as isize, height);
                src.row(codec, width, fy, fx0, &mut row[c0..c1]);
                for wx in (0..c0).chain(c1..ww) {
                    let fx = reflect(ox + wx as isize, width);
                    let inside = fx as isize - ox;
                    if inside >= c0 as isize && inside < c1 as isize {
                        row[wx] = row[inside as usize];
                    } else {
                        src.row(codec, width, fy, fx, &mut row[wx..wx + 1]);
                    }
                }
            });
    });
}

impl Neural {
    /// Enhances one frame: tiles, runs the model, blends. See the module docs.
    fn run_frame(
        &self,
        input: &BackendInput<'_>,
        progress: &mut Progress<'_>,
        stages: &mut Stages,
    ) -> Result<Image> {
        let model = &self.model;
        let m = &model.manifest;
        let frame = input.frame;
        let pool = input.pool;
        let (w, h) = (frame.width(), frame.height());
        let plan = model.tile_plan_within(w, h, input.params, input.memory_budget)?;
        let codec = stages.time("encode_stats", || {
            pool.install(|| {
                ColorCodec::for_frame(&m.encoding, &frame.color, frame.coverage.as_deref())
            })
        });
        let used = m.history_slots().min(input.history.len());
        let mut sources = channel_sources(&model.channels, frame, used, m.premultiplied);
        let slots = history_slots(&model.channels, used);

        // The history channels are written into each tile's input by
        // `history_window`.
        for &(slot, ..) in &slots {
            sources[slot] = Src::Filled;
        }
        // With several tiles, the other computed channels are computed once
        // for the whole frame, so the tiles' overlaps only copy.
        let computed: Buffer<'_>;
        if plan.len() > 1 {
            computed = stages.time("encode", || {
                let wanted: Vec<Src<'_>> = sources.iter().copied().filter(Src::computed).collect();
                let mut planes = model.buffer(wanted.len() * w * h);
                pool.install(|| {
                    planes
                        .data
                        .par_chunks_mut(w)
                        .with_min_len(4)
                        .enumerate()
                        .for_each(|(r, row)| wanted[r / h].row(&codec, w, r % h, 0, row));
                });
                planes
            });
            let mut next = computed.data.chunks_exact(w * h);
            for s in sources.iter_mut().filter(|s| s.computed()) {
                *s = Src::Copy(next.next().expect("one plane per computed channel"));
            }
        }

        // The frame's own fill of its holes, which the history the model
        // reads is pulled toward there (the in-graph prior fills holes
        // from it), as the classical backend pulls its history:
        // `classical::HISTORY_REFRESH`.
        let share = crate::backend::classical::HISTORY_REFRESH;
        let fresh = match (&frame.coverage, used > 0 && share > 0.0) {
            (Some(coverage), true) if frame.color.channels >= 3 => {
                let holes = match frame.scan {
                    Some(scan) => scan.holes,
                    None => crate::ops::bbox_below(coverage, w, h, FULL),
                };
                holes
                    .and_then(|(rect, _)| {
                        stages.time("inpaint", || {
                            pool.install(|| {
                                SpatialFill::new(
                                    [
                                        frame.color.plane(0),
                                        frame.color.plane(1),
                                        frame.color.plane(2),
                                        coverage,
                                    ],
                                    w,
                                    rect,
                                    input.params.coverage_floor,
                                    frame.depth.as_deref(),
                                )
                            })
                        })
                    })
                    .map(|fill| Refresh {
                        fill,
                        coverage,
                        share,
                    })
            }
            _ => None,
        };
        let n_tiles = plan.len();
        let cin = model.channels.len();
        let (ww, wh) = (plan.x.window, plan.y.window);
        let np = ww * wh;
        let color_slots: [Option<usize>; 3] = std::array::from_fn(|c| {
            model
                .channels
                .iter()
                .position(|&ch| ch == InputChannel::Color(c))
        });
        // Per output color channel: its plane in the model's output and, for
        // residual models, the input plane holding the encoded color.
        let planes: [(usize, Option<usize>); 3] = std::array::from_fn(|c| {
            let o = model
                .output_order
                .iter()
                .position(|&oc| oc == c)
                .expect("validated output channels");
            let slot = m
                .residual
                .then(|| color_slots[c].expect("validated: residual models read color"));
            (o, slot)
        });
        let coverage = if input.params.fill_holes {
            None
        } else {
            frame.coverage.as_deref()
        };
        let repair = stages.time("keep_covered", || Repair::for_frame(model, input));
        let mut tensor = model.buffer(cin * np);
        // The output comes from the session's recycled frame buffers (fresh
        // memory costs a page fault per 4 KiB on every frame): one tile
        // writes every sample, several add into zeros.
        let mut out = match input.history.recycler() {
            Some(r) => {
                let mut img = r.try_image(w, h, 4)?;
                if n_tiles > 1 {
                    pool.install(|| img.data.par_chunks_mut(w).for_each(|row| row.fill(0.0)));
                }
                img
            }
            None => Image::try_zeros(w, h, 4)?,
        };
        // When the manifest's stabilization follows, its pass reads history
        // frame 0 reprojected again: the tiles keep the runs they compute
        // of it (each pixel once, from its tile's core), and the view
        // caches that frame for the pass to copy.
        let stabilized = input.params.stabilize
            && input.params.temporal_blend > 0.0
            && m.stabilize
            && !input.params.classical_post;
        let mut first = match (!slots.is_empty() && stabilized, input.history.recycler()) {
            (true, Some(r)) => Some(ReprojectedFrame {
                color: r.try_image(w, h, 4)?,
                valid: r.try_image(w, h, 1)?.data,
            }),
            (true, None) => Some(ReprojectedFrame {
                color: Image::try_zeros(w, h, 4)?,
                valid: Image::try_zeros(w, h, 1)?.data,
            }),
            (false, _) => None,
        };
        for (t, tile) in plan.tiles().enumerate() {
            if !slots.is_empty() {
                stages.time("reproject", || {
                    let mut planes: Vec<Option<&mut [f32]>> =
                        tensor.data.chunks_exact_mut(np).map(Some).collect();
                    let mine: Vec<&mut [f32]> = slots
                        .iter()
                        .map(|&(slot, ..)| planes[slot].take().expect("one slot per channel"))
                        .collect();
                    let keep = first.as_mut().map(|f| {
                        let [r, g, b, a] = f.color.planes_mut().try_into().expect("4 planes");
                        Keep {
                            planes: [r, g, b, a, &mut f.valid[..]],
                            cols: plan.x.cores[tile.ix],
                            rows: plan.y.cores[tile.iy],
                        }
                    });
                    history_window(
                        input.history,
                        &slots,
                        &codec,
                        m.premultiplied,
                        mine,
                        (w, h),
                        tile,
                        keep,
                        pool,
                        fresh.as_ref(),
                    );
                });
            }
            stages.time("tile_input", || {
                fill_window(&mut tensor.data, &sources, &codec, (w, h), tile, pool)
            });
            if let Some(prior) = &model.prior {
                stages.time("prior", || {
                    let mut scratch = model.buffer(2 * np);
                    prior.compute(&mut tensor.data, (ww, wh), &mut scratch.data, pool)
                });
            }
            let started = std::time::Instant::now();
            let mut decoding = 0.0;
            model.run(&tensor.data, ww, wh, |result| {
                let t = std::time::Instant::now();
                let view = TileOutput {
                    result,
                    tensor: &tensor.data,
                    planes,
                    size: tile.size,
                    origin: tile.origin,
                };
                if n_tiles == 1 {
                    write_single(&mut out, &view, &codec, coverage, repair.as_ref(), pool);
                } else {
                    blend_tile(&mut out, &plan, tile, &view, &codec, pool);
                }
                decoding = t.elapsed().as_secs_f64() * 1e3;
            })?;
            let total = started.elapsed().as_secs_f64() * 1e3;
            record(stages, "inference", total - decoding);
            record(stages, "tile_blend", decoding);
            progress.report((t + 1) as f64 / n_tiles as f64)?;
        }
        if n_tiles > 1 {
            stages.time("finish", || {
                finish(&mut out, frame.coverage.as_deref(), input.params.fill_holes)
            });
            if let Some(r) = &repair {
                stages.time("keep_covered", || r.apply(&mut out, pool));
            }
        }
        if let Some(f) = first {
            input.history.keep_reprojected(0, f);
        }
        Ok(out)
    }
}

/// The manifest's `repair_margin` for one frame: pixels covered at least
/// `floor` get their rendered color (`color`, premultiplied by `coverage`)
/// back where no hole (coverage below `floor`) lies within `margin` pixels
/// (Chebyshev distance); at exactly `margin` they keep
/// [`REPAIR_EDGE_SHARE`] of the network's output, nearer all of it.
struct Repair<'a> {
    color: &'a Image,
    coverage: &'a [f32],
    margin: usize,
    /// Per pixel, the distance to the nearest hole in its row, capped at
    /// `margin + 1`.
    row_dist: Vec<u16>,
}

impl<'a> Repair<'a> {
    /// `None` without a margin, without coverage or with `keep_covered` off.
    fn for_frame(model: &NeuralModel, input: &BackendInput<'a>) -> Option<Repair<'a>> {
        let margin = model.manifest.repair_margin?;
        let coverage = input.frame.coverage.as_deref()?;
        if !input.params.keep_covered {
            return None;
        }
        let (w, floor) = (input.frame.width(), input.params.coverage_floor);
        let cap = margin + 1;
        let mut row_dist = vec![0u16; coverage.len()];
        input.pool.install(|| {
            row_dist
                .par_chunks_mut(w)
                .with_min_len(8)
                .zip(coverage.par_chunks(w))
                .for_each(|(d, cov)| {
                    let mut last = cap;
                    for (d, &c) in d.iter_mut().zip(cov) {
                        last = if c < floor { 0 } else { (last + 1).min(cap) };
                        *d = last as u16;
                    }
                    let mut next = cap;
                    for (d, &c) in d.iter_mut().zip(cov).rev() {
                        next = if c < floor { 0 } else { (next + 1).min(cap) };
                        *d = (*d).min(next as u16);
                    }
                })
        });
        Some(Repair {
            color: &input.frame.color,
            coverage,
            margin,
            row_dist,
        })
    }

    /// The network's share of each pixel of row `y` (holes are at distance
    /// 0, so every pixel with a share below 1 is covered); `false` when it
    /// is all of every pixel.
    fn shares(&self, y: usize, (dist, share): &mut (Vec<u16>, Vec<f32>)) -> bool {
        let (w, margin) = (self.color.width, self.margin);
        let h = self.color.height;
        dist.clear();
        dist.resize(w, (margin + 1) as u16);
        for yy in y.saturating_sub(margin)..(y + margin + 1).min(h) {
            let dy = yy.abs_diff(y) as u16;
            for (d, &s) in dist.iter_mut().zip(&self.row_dist[yy * w..(yy + 1) * w]) {
                *d = (*d).min(s.max(dy));
            }
        }
        share.clear();
        share.extend(dist.iter().map(|&d| match (d as usize).cmp(&margin) {
            std::cmp::Ordering::Less => 1.0,
            std::cmp::Ordering::Equal => REPAIR_EDGE_SHARE,
            std::cmp::Ordering::Greater => 0.0,
        }));
        share.iter().any(|&s| s < 1.0)
    }

    /// Blends plane `c` of row `y` of the output (`row`, premultiplied by
    /// `alpha`) toward the rendered color by `share`.
    fn blend(&self, c: usize, y: usize, row: &mut [f32], alpha: Option<&[f32]>, share: &[f32]) {
        let (w, n) = (self.color.width, self.color.width * self.color.height);
        let src = &self.color.data[c * n + y * w..c * n + (y + 1) * w];
        let cov = &self.coverage[y * w..(y + 1) * w];
        for (x, (v, &s)) in row.iter_mut().zip(share).enumerate() {
            if s >= 1.0 {
                continue;
            }
            let a = alpha.map_or(1.0, |a| a[x]);
            let rendered = if cov[x] > 0.0 {
                src[x] * (a / cov[x])
            } else {
                0.0
            };
            *v = rendered + s * (*v - rendered);
        }
    }

    /// The whole image (premultiplied by its plane 3), after the tiles.
    fn apply(&self, out: &mut Image, pool: &rayon::ThreadPool) {
        let (w, n) = (out.width, out.width * out.height);
        let (rgb, alpha) = out.data.split_at_mut(3 * n);
        let alpha = &alpha[..n];
        pool.install(|| {
            rgb.par_chunks_mut(w)
                .with_min_len(4)
                .enumerate()
                .for_each_init(Default::default, |scratch, (r, row)| {
                    let (c, y) = (r / out.height.max(1), r % out.height.max(1));
                    if self.shares(y, scratch) {
                        self.blend(c, y, row, Some(&alpha[y * w..(y + 1) * w]), &scratch.1);
                    }
                })
        });
    }
}

/// Gives the covered pixels of inserted objects (coverage at least
/// `coverage_floor`) their rendered color back, by twice the insert mask
/// (a pixel at least half insert keeps all of it; the soft edge's outer
/// half takes part of the network's repair of the background): an
/// object composited into a reconstruction is the host's render, not a
/// reconstruction to repair, and the network, trained on reconstructions,
/// repaints it (out of domain, insert_recon's object came out 0.14 dB under
/// the classical backend's in its region, 0.02 with this; by the mask alone
/// 0.03, wholly wherever the mask is above 0 0.01 but 0.04 dB lower over
/// the frame). An object's pixel covered less than the floor (its soft
/// edge over a hole: no splat behind it) keeps the share it covers as
/// rendered and takes the network's fill for the rest (the correctly lit
/// object in the reconstruction, insert_recon_control: 35.35 dB in its
/// region against 33.04 when those pixels were the network's; its input
/// 35.03). The insert operations then harmonize it as over a render; one
/// they leave as it came is not stabilized either, as over a render (the
/// control: 32.66 dB against 31.98 when its box was stabilized). Off with
/// `keep_covered`.
fn keep_inserts(img: &mut Image, input: &BackendInput<'_>) {
    let frame = input.frame;
    let (Some(mask), Some(coverage)) = (frame.insert_mask.as_deref(), frame.coverage.as_deref())
    else {
        return;
    };
    if !input.params.keep_covered || img.channels < 4 {
        return;
    }
    let (w, h, floor) = (img.width, img.height, input.params.coverage_floor);
    let n = w * h;
    // Only the rows and columns of the insert's bounding box (found while
    // the mask was prepared, when it was).
    let rect = match frame.scan {
        Some(scan) => scan.insert,
        None => input
            .pool
            .install(|| crate::ops::harmonize::insert_rect(mask, w, h)),
    };
    let Some(rect) = rect else {
        return;
    };
    let color = &frame.color;
    let (rgb, alpha) = img.data.split_at_mut(3 * n);
    let alpha = &alpha[..n];
    input.pool.install(|| {
        rgb.par_chunks_mut(w)
            .with_min_len(4)
            .enumerate()
            .filter(|(r, _)| (rect.y0..rect.y1).contains(&(r % h)))
            .for_each(|(r, row)| {
                let (c, y) = (r / h, r % h);
                let s = y * w..(y + 1) * w;
                let src = &color.data[c * n + s.start..c * n + s.end];
                for x in rect.x0..rect.x1 {
                    let (m, cov) = (mask[s.start + x], coverage[s.start + x]);
                    if m > 0.0 && cov > 0.0 {
                        // The covered share as rendered, the rest the
                        // network's fill (`a`: the output's alpha).
                        let a = alpha[s.start + x];
                        let rendered = if cov >= floor {
                            src[x] * (a / cov)
                        } else {
                            crate::ops::inpaint::over_fill(src[x], cov, row[x], a)
                        };
                        row[x] += (2.0 * m).min(1.0) * (rendered - row[x]);
                    }
                }
            })
    });
}

/// Adds `ms` to stage `name` (as [`Stages::time`] does).
fn record(stages: &mut Stages, name: &str, ms: f64) {
    match stages.0.iter_mut().find(|(n, _)| n == name) {
        Some(e) => e.1 += ms,
        None => stages.0.push((name.to_string(), ms)),
    }
}

/// One tile's network output and the input it was computed from.
struct TileOutput<'a> {
    result: &'a [f32],
    tensor: &'a [f32],
    /// Per color channel: output plane, residual input plane.
    planes: [(usize, Option<usize>); 3],
    size: (usize, usize),
    origin: (isize, isize),
}

impl TileOutput<'_> {
    /// Decodes window row `wy`, columns `wx0..wx0 + dst.len()`, of color channel `c`.
    #[inline]
    fn decode_row(&self, codec: &ColorCodec, c: usize, wy: usize, wx0: usize, dst: &mut [f32]) {
        let np = self.size.0 * self.size.1;
        let at = wy * self.size.0 + wx0;
        let (o, slot) = self.planes[c];
        let net = &self.result[o * np + at..o * np + at + dst.len()];
        match slot {
            Some(s) => {
                let inp = &self.tensor[s * np + at..s * np + at + dst.len()];
                codec.decode_sum_row(net, inp, dst);
            }
            None => codec.decode_row(net, dst),
        }
    }
}

/// The whole frame in one tile: decode straight into the output, RGB
/// premultiplied by the output coverage (`coverage`, 1 where `None`).
fn write_single(
    out: &mut Image,
    view: &TileOutput<'_>,
    codec: &ColorCodec,
    coverage: Option<&[f32]>,
    repair: Option<&Repair<'_>>,
    pool: &rayon::ThreadPool,
) {
    let (w, h) = (out.width, out.height);
    debug_assert_eq!(view.origin, (0, 0));
    pool.install(|| {
        out.data
            .par_chunks_mut(w)
            .with_min_len(4)
            .enumerate()
            .for_each_init(Default::default, |scratch, (r, row)| {
                let (c, y) = (r / h, r % h);
                let alpha = coverage.map(|a| &a[y * w..(y + 1) * w]);
                if c == 3 {
                    match alpha {
                        Some(a) => row.copy_from_slice(a),
                        None => row.fill(1.0),
                    }
                    return;
                }
                view.decode_row(codec, c, y, 0, row);
                if let Some(a) = alpha {
                    row.iter_mut().zip(a).for_each(|(v, &a)| *v *= a);
                }
                if let Some(rp) = repair {
                    if rp.shares(y, scratch) {
                        rp.blend(c, y, row, alpha, &scratch.1);
                    }
                }
            });
    });
}

/// Decodes one tile's kept region and adds it, weighted, into the
/// accumulators (weighted RGB in planes 0..3, weight sum in plane 3).
fn blend_tile(
    out: &mut Image,
    plan: &TilePlan,
    tile: tiling::Tile,
    view: &TileOutput<'_>,
    codec: &ColorCodec,
    pool: &rayon::ThreadPool,
) {
    let (w, h) = (plan.width, plan.height);
    let o = plan.overlap;
    let (x0, x1) = plan.x.kept(tile.ix, o, w);
    let (y0, y1) = plan.y.kept(tile.iy, o, h);
    let wx: Vec<f32> = (x0..x1).map(|x| plan.x.weight(tile.ix, x, o)).collect();
    let (ox, oy) = tile.origin;
    let wx0 = (x0 as isize - ox) as usize;
    pool.install(|| {
        out.data
            .par_chunks_mut(w)
            .with_min_len(4)
            .enumerate()
            .filter(|(r, _)| (y0..y1).contains(&(r % h)))
            .for_each_init(
                || vec![0.0f32; x1 - x0],
                |dec, (r, row)| {
                    let (c, y) = (r / h, r % h);
                    let wy = plan.y.weight(tile.iy, y, o);
                    if wy == 0.0 {
                        return;
                    }
                    let acc = &mut row[x0..x1];
                    if c == 3 {
                        acc.iter_mut().zip(&wx).for_each(|(a, &wxv)| *a += wxv * wy);
                        return;
                    }
                    let wyi = (y as isize - oy) as usize;
                    view.decode_row(codec, c, wyi, wx0, dec);
                    acc.iter_mut()
                        .zip(&wx)
                        .zip(dec.iter())
                        .for_each(|((a, &wxv), &d)| *a += wxv * wy * d);
                },
            );
    });
}

/// Normalizes the accumulators and sets the output coverage: 1 when
/// `fill_holes`, else the input coverage (RGB premultiplied by it).
fn finish(out: &mut Image, coverage: Option<&[f32]>, fill_holes: bool) {
    let n = out.len();
    let (rgb, a) = out.data.split_at_mut(3 * n);
    for i in 0..n {
        let wsum = a[i];
        let alpha = match (fill_holes, coverage) {
            (false, Some(c)) => c[i],
            _ => 1.0,
        };
        let k = if wsum > 0.0 { alpha / wsum } else { 0.0 };
        for c in 0..3 {
            rgb[c * n + i] *= k;
        }
        a[i] = alpha;
    }
}

impl Backend for Neural {
    fn name(&self) -> &str {
        "neural"
    }

    fn uses_normals(&self) -> bool {
        self.model
            .channels
            .iter()
            .any(|ch| matches!(ch, InputChannel::Normal(_)))
    }

    fn check_params(&self, params: &Params) -> Result<()> {
        self.model.check_params(params)
    }

    fn working_planes(&self, params: &Params) -> usize {
        // The reprojected history frames the model reads (RGBA and validity,
        // frame-sized); the tiles fit what is left of the limit. The history
        // channels are now reprojected row by row into each tile's input
        // (`history_window`), so this is an upper bound, kept so that the
        // tile plans under a memory limit stay as they were.
        5 * self
            .model
            .manifest
            .history_slots()
            .min(params.context_frames)
    }

    fn process(
        &self,
        input: &BackendInput<'_>,
        carry: &mut Carry,
        progress: &mut Progress<'_>,
        stages: &mut Stages,
    ) -> Result<Image> {
        if !input.params.neural_clean_frames && !input.frame.has_holes() {
            // No hole: nothing the network repairs better than the
            // classical operations. Run by the network, a clean frame is
            // repainted, not repaired (out of domain a clean render came
            // back at 32 dB, a denoised 4-spp one 2 dB below its input), and
            // so is a frame whose only change is an insert (a correctly lit
            // insert came back at 28.0 dB overall, 17.1 in its region; a
            // mistoned one 3 dB below its input). Such frames get the
            // classical insert harmonization and shadows, and nothing else
            // (`neural_clean_frames` runs the network anyway).
            return crate::backend::classical::Classical.process(input, carry, progress, stages);
        }
        if !input.params.classical_post {
            // A frame with holes: the network, then the insert operations
            // on its output (an object inserted into a reconstruction is
            // harmonized and casts its shadow as over a render).
            let (lo, hi) = progress.span();
            let mid = lo + 0.9 * (hi - lo);
            progress.set_span(lo, mid);
            let mut img = self.run_frame(input, progress, stages)?;
            stages.time("keep_inserts", || keep_inserts(&mut img, input));
            progress.set_span(mid, hi);
            let done = crate::backend::classical::insert_ops(
                &mut img,
                Some(&input.frame.color),
                input,
                carry,
                progress,
                stages,
            );
            progress.set_span(lo, hi);
            let changed = done?;
            if self.model.manifest.stabilize {
                // The model asks for temporal stabilization of its output.
                crate::backend::classical::stabilize_with_history(&mut img, input, stages, None);
            } else if let Some(area) = changed {
                // A recolored insert is stabilized, as over a render (the
                // rest is the network's, already blended with its history).
                // One kept as rendered is the host's render, as it came.
                crate::backend::classical::stabilize_with_history(
                    &mut img,
                    input,
                    stages,
                    Some(area),
                );
            }
            return Ok(img);
        }
        // `classical_post`: the classical operations (hole fill, insert
        // harmonization, contact shadow, stabilization) run on the network's
        // output, with the same history and carried state.
        let (lo, hi) = progress.span();
        let mid = lo + 0.8 * (hi - lo);
        progress.set_span(lo, mid);
        let mut img = self.run_frame(input, progress, stages)?;
        progress.set_span(mid, hi);
        let done = crate::backend::classical::run_ops(&mut img, input, carry, progress, stages);
        progress.set_span(lo, hi);
        done?;
        Ok(img)
    }
}
