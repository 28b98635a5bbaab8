//! The neural backend: an ONNX model run through ONNX Runtime (`ort`,
//! loaded dynamically), described by a JSON [`Manifest`].
//!
//! Per frame: one exposure scale for the whole frame ([`encoding`]), the
//! frame cut into overlapping tiles ([`tiling`]), each tile's NCHW input built
//! from the frame, its guides and the K reprojected history frames in the
//! manifest's channel order, the model run, its output decoded and blended
//! into the frame with feathered weights. Progress is reported per tile and
//! cancellation is honoured between tiles.

pub mod encoding;
pub mod runtime;
pub mod tiling;

use std::path::{Path, PathBuf};
use std::sync::{Arc, Mutex};

use rayon::prelude::*;

use super::{Backend, BackendInput, Carry, Progress, Stages};
use crate::device::{DeviceOptions, ModelSource};
use crate::error::{Error, Result};
use crate::frame::Image;
use crate::model::{InputChannel, Manifest};
use crate::params::Params;
use crate::temporal::ReprojectedFrame;
use encoding::{ColorCodec, COVERAGE_EPSILON};
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
    output_order: Vec<usize>,
    /// Static window size of the model input (width, height), if not dynamic.
    fixed: (Option<usize>, Option<usize>),
    memory_limit: usize,
    threads: usize,
    runtime: PathBuf,
    session: Mutex<ort::session::Session>,
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

impl NeuralModel {
    /// Loads the model the options name; `Ok(None)` for `Embedded` when this
    /// build embeds no model.
    pub fn load(options: &DeviceOptions) -> Result<Option<Arc<NeuralModel>>> {
        match &options.model {
            ModelSource::Embedded => match crate::model::embedded() {
                Some(m) => Self::from_bytes(m.onnx, m.manifest, "embedded", options).map(Some),
                None => Ok(None),
            },
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
                Self::load_parts(
                    &onnx,
                    &manifest,
                    &path.display().to_string(),
                    &json_path.display().to_string(),
                    options,
                )
                .map(Some)
            }
            ModelSource::Bytes { onnx, manifest } => {
                Self::from_bytes(onnx, manifest, "in-memory model", options).map(Some)
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
        Ok(Arc::new(NeuralModel {
            name: manifest.name.clone(),
            version: manifest.version.clone(),
            channels: manifest.input_channels(),
            output_order: manifest.output_order(),
            manifest,
            origin: origin.to_string(),
            fixed,
            memory_limit: options.memory_limit,
            threads,
            runtime,
            session: Mutex::new(session),
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
    /// frame's output (4 planes) plus one tile's network working set.
    pub fn working_bytes(&self, plan: &TilePlan) -> usize {
        4 * 4 * plan.width * plan.height
            + plan.window_pixels() * self.manifest.tile_bytes_per_pixel()
    }

    /// The tiling of a `width` x `height` frame under `params`: the requested
    /// tile size, shrunk (in steps of `spatial_multiple`) until the working
    /// memory fits the device's `memory_limit`.
    pub fn tile_plan(&self, width: usize, height: usize, params: &Params) -> Result<TilePlan> {
        let m = self.manifest.spatial_multiple;
        let overlap = self.tile_overlap(params);
        let requested = self.tile_size(params);
        let plan = |tile: usize| TilePlan::new(width, height, tile, overlap, m, self.fixed);
        let mut tile = requested;
        let mut p = plan(tile).map_err(|e| Error::invalid(format!("model {}: {e}", self.name)))?;
        if self.memory_limit == 0 || self.fixed.0.is_some() && self.fixed.1.is_some() {
            return Ok(p);
        }
        while self.working_bytes(&p) > self.memory_limit {
            let smaller = (p.x.window.max(p.y.window).min(tile) / m).saturating_sub(1) * m;
            if smaller < 4 * overlap + 2 || smaller < m {
                return Err(Error::OutOfMemory(format!(
                    "memory_limit {} bytes: a {width}x{height} frame needs at least {} bytes with model {} \
                     (tiles of {}x{} px, tile_overlap {overlap})",
                    self.memory_limit,
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

    /// Runs the network on one NCHW input; returns the output tensor data.
    fn run(&self, input: &[f32], w: usize, h: usize) -> Result<Vec<f32>> {
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
        Ok(data.to_vec())
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

/// Per-frame sources the tile builder reads.
struct Sources<'a> {
    width: usize,
    color: &'a Image,
    coverage: Option<&'a [f32]>,
    insert: Option<&'a [f32]>,
    depth: Option<&'a [f32]>,
    normal: Option<&'a Image>,
    motion: Option<&'a Image>,
    history: Vec<&'a ReprojectedFrame>,
    codec: ColorCodec,
    premultiplied: bool,
}

/// Writes `f(frame index)` for every window pixel (`xs`, `ys`: frame columns and rows).
#[inline]
fn each(out: &mut [f32], xs: &[usize], ys: &[usize], w: usize, f: impl Fn(usize) -> f32) {
    for (row, &sy) in out.chunks_mut(xs.len()).zip(ys) {
        let base = sy * w;
        for (o, &sx) in row.iter_mut().zip(xs) {
            *o = f(base + sx);
        }
    }
}

impl Sources<'_> {
    /// Fills one input channel of a tile window.
    fn fill(&self, ch: InputChannel, xs: &[usize], ys: &[usize], out: &mut [f32]) {
        let w = self.width;
        let straight = |v: f32, a: f32| -> f32 {
            if a >= COVERAGE_EPSILON {
                v / a
            } else {
                0.0
            }
        };
        match ch {
            InputChannel::Color(c) => {
                let p = self.color.plane(c);
                match (self.premultiplied, self.coverage) {
                    (false, Some(cov)) => each(out, xs, ys, w, |i| {
                        self.codec.encode(straight(p[i], cov[i]))
                    }),
                    _ => each(out, xs, ys, w, |i| self.codec.encode(p[i])),
                }
            }
            InputChannel::Coverage => match self.coverage {
                Some(cov) => each(out, xs, ys, w, |i| cov[i]),
                None => out.fill(1.0),
            },
            InputChannel::Insert => match self.insert {
                Some(m) => each(out, xs, ys, w, |i| m[i]),
                None => out.fill(0.0),
            },
            InputChannel::Disparity => match self.depth {
                Some(d) => each(out, xs, ys, w, |i| 1.0 / (1.0 + d[i].max(0.0))),
                None => out.fill(0.0),
            },
            InputChannel::Normal(c) => match self.normal {
                Some(n) => {
                    let p = n.plane(c);
                    each(out, xs, ys, w, |i| p[i])
                }
                None => out.fill(0.0),
            },
            InputChannel::Motion(c) => match self.motion {
                Some(m) => {
                    let p = m.plane(c);
                    each(out, xs, ys, w, |i| p[i])
                }
                None => out.fill(0.0),
            },
            InputChannel::History(k, c) => match self.history.get(k) {
                Some(h) => {
                    let (p, a) = (h.color.plane(c), h.color.plane(3));
                    if self.premultiplied {
                        each(out, xs, ys, w, |i| self.codec.encode(p[i]))
                    } else {
                        each(out, xs, ys, w, |i| self.codec.encode(straight(p[i], a[i])))
                    }
                }
                None => out.fill(0.0),
            },
            InputChannel::HistoryAlpha(k) => match self.history.get(k) {
                Some(h) => {
                    let a = h.color.plane(3);
                    each(out, xs, ys, w, |i| a[i])
                }
                None => out.fill(0.0),
            },
            InputChannel::Valid(k) => match self.history.get(k) {
                Some(h) => each(out, xs, ys, w, |i| h.valid[i]),
                None => out.fill(0.0),
            },
        }
    }
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
        let (w, h) = (frame.width(), frame.height());
        let plan = model.tile_plan(w, h, input.params)?;
        let codec = stages.time("encode_stats", || {
            ColorCodec::for_frame(&m.encoding, &frame.color, frame.coverage.as_deref())
        });
        let used = m.context_frames.min(input.history.len());
        let history: Vec<&ReprojectedFrame> = stages.time("reproject", || {
            (0..used).map(|k| input.history.reproject(k)).collect()
        });
        let src = Sources {
            width: w,
            color: &frame.color,
            coverage: frame.coverage.as_deref(),
            insert: frame.insert_mask.as_deref(),
            depth: frame.depth.as_deref(),
            normal: frame.normal.as_ref(),
            motion: frame.motion.as_ref(),
            history,
            codec,
            premultiplied: m.premultiplied,
        };

        // Accumulators: weighted RGB in planes 0..3, weight sum in plane 3.
        let mut out = Image::zeros(w, h, 4);
        let n_tiles = plan.len();
        let cin = model.channels.len();
        let color_slots: [Option<usize>; 3] = std::array::from_fn(|c| {
            model
                .channels
                .iter()
                .position(|&ch| ch == InputChannel::Color(c))
        });
        for (t, tile) in plan.tiles().enumerate() {
            let (ww, wh) = tile.size;
            let xs: Vec<usize> = (0..ww)
                .map(|x| reflect(tile.origin.0 + x as isize, w))
                .collect();
            let ys: Vec<usize> = (0..wh)
                .map(|y| reflect(tile.origin.1 + y as isize, h))
                .collect();
            let mut tensor = vec![0.0f32; cin * ww * wh];
            stages.time("tile_input", || {
                input.pool.install(|| {
                    tensor
                        .par_chunks_mut(ww * wh)
                        .zip(model.channels.par_iter())
                        .for_each(|(plane, &ch)| src.fill(ch, &xs, &ys, plane));
                })
            });
            let mut result = stages.time("inference", || model.run(&tensor, ww, wh))?;
            stages.time("tile_blend", || {
                let np = ww * wh;
                if m.residual {
                    for (o, &c) in model.output_order.iter().enumerate() {
                        let slot = color_slots[c].expect("validated: residual models read color");
                        let (res, inp) = (
                            &mut result[o * np..(o + 1) * np],
                            &tensor[slot * np..(slot + 1) * np],
                        );
                        res.iter_mut().zip(inp).for_each(|(r, i)| *r += i);
                    }
                }
                blend_tile(
                    &mut out,
                    &plan,
                    tile,
                    &result,
                    &model.output_order,
                    &codec,
                    input.pool,
                );
            });
            progress.report((t + 1) as f64 / n_tiles as f64)?;
        }
        stages.time("finish", || {
            finish(&mut out, frame.coverage.as_deref(), input.params.fill_holes)
        });
        Ok(out)
    }
}

/// Decodes one tile's output and adds it, weighted, into the accumulators.
fn blend_tile(
    out: &mut Image,
    plan: &TilePlan,
    tile: tiling::Tile,
    result: &[f32],
    order: &[usize],
    codec: &ColorCodec,
    pool: &rayon::ThreadPool,
) {
    let (w, h) = (plan.width, plan.height);
    let o = plan.overlap;
    let (x0, x1) = plan.x.kept(tile.ix, o, w);
    let (y0, y1) = plan.y.kept(tile.iy, o, h);
    let wx: Vec<f32> = (x0..x1).map(|x| plan.x.weight(tile.ix, x, o)).collect();
    let (ww, wh) = tile.size;
    let np = ww * wh;
    // Window coordinates of frame pixel (x, y).
    let (ox, oy) = tile.origin;
    let mut planes = out.planes_mut();
    pool.install(|| {
        planes.par_iter_mut().enumerate().for_each(|(c, plane)| {
            let src = (c < 3).then(|| {
                let slot = order
                    .iter()
                    .position(|&oc| oc == c)
                    .expect("validated output channels");
                &result[slot * np..(slot + 1) * np]
            });
            for y in y0..y1 {
                let wy = plan.y.weight(tile.iy, y, o);
                if wy == 0.0 {
                    continue;
                }
                let row = &mut plane[y * w + x0..y * w + x1];
                let wyi = (y as isize - oy) as usize;
                debug_assert!(wyi < wh);
                match src {
                    Some(s) => {
                        let srow = &s[wyi * ww..(wyi + 1) * ww];
                        for (i, (acc, &wxv)) in row.iter_mut().zip(&wx).enumerate() {
                            let wt = wxv * wy;
                            if wt > 0.0 {
                                let wxi = ((x0 + i) as isize - ox) as usize;
                                *acc += wt * codec.decode(srow[wxi]);
                            }
                        }
                    }
                    None => {
                        for (acc, &wxv) in row.iter_mut().zip(&wx) {
                            *acc += wxv * wy;
                        }
                    }
                }
            }
        });
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

    fn process(
        &self,
        input: &BackendInput<'_>,
        _carry: &mut Carry,
        progress: &mut Progress<'_>,
        stages: &mut Stages,
    ) -> Result<Image> {
        self.run_frame(input, progress, stages)
    }
}
