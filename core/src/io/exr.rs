//! EXR frames: reading (half, float and uint; single- and multi-part;
//! channels by name), turning them into a [`FrameInput`], and writing the
//! enhanced result back with every input part, channel and attribute kept.

use std::path::{Path, PathBuf};

use exr::prelude::{
    AnyChannel, AnyChannels, AttributeValue, Encoding, FlatSamples, Image as ExrImage, Layer,
    LayerAttributes, ReadChannels, ReadLayers, Text, WritableImage,
};

use super::guard::{self, ReadLimits, Refusal};
use super::layout::{self, ChannelRef, InsertSource, LayoutOptions, LayoutPreset, ResolvedLayout};
use crate::error::{Error, Result};
use crate::frame::{Camera, FrameInput, Image, ImageView};

type FlatImage = exr::image::FlatImage;

/// The message of a caught panic.
fn panic_text(p: &Box<dyn std::any::Any + Send>) -> String {
    p.downcast_ref::<&str>()
        .map(|s| s.to_string())
        .or_else(|| p.downcast_ref::<String>().cloned())
        .unwrap_or_else(|| "internal error".to_string())
}

/// Where a frame came from, for error messages: `frame 12 (path)`.
fn ctx(path: &Path, frame: Option<i64>) -> String {
    match frame {
        Some(n) => format!("frame {n} ({})", path.display()),
        None => path.display().to_string(),
    }
}

/// Sample type of an EXR channel.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum SampleKind {
    /// 16-bit float.
    Half,
    /// 32-bit float.
    Float,
    /// 32-bit unsigned integer.
    Uint,
}

impl SampleKind {
    /// `half`, `float` or `uint`.
    pub fn name(self) -> &'static str {
        match self {
            SampleKind::Half => "half",
            SampleKind::Float => "float",
            SampleKind::Uint => "uint",
        }
    }
}

/// One channel of a file.
#[derive(Debug, Clone, PartialEq, Eq)]
pub struct ChannelInfo {
    /// Part (layer) index in the file.
    pub part: usize,
    /// Index of the channel inside its part.
    pub index: usize,
    /// The name as stored in the part.
    pub name: String,
    /// `part.name` for named parts (unless the name already starts with it).
    pub qualified: String,
    /// Sample type.
    pub kind: SampleKind,
}

/// A whole EXR file in memory (largest resolution level, all parts).
pub struct ExrFile {
    path: PathBuf,
    frame: Option<i64>,
    image: FlatImage,
    channels: Vec<ChannelInfo>,
}

impl std::fmt::Debug for ExrFile {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.debug_struct("ExrFile")
            .field("path", &self.path)
            .field("channels", &self.channels)
            .finish()
    }
}

fn kind_of(s: &FlatSamples) -> SampleKind {
    match s {
        FlatSamples::F16(_) => SampleKind::Half,
        FlatSamples::F32(_) => SampleKind::Float,
        FlatSamples::U32(_) => SampleKind::Uint,
    }
}

fn matrix_rows(m: &[f32; 16]) -> [[f32; 4]; 4] {
    let mut r = [[0.0; 4]; 4];
    for (i, row) in r.iter_mut().enumerate() {
        row.copy_from_slice(&m[4 * i..4 * i + 4]);
    }
    r
}

fn rows_matrix(r: &[[f32; 4]; 4]) -> [f32; 16] {
    let mut m = [0.0; 16];
    for (i, row) in r.iter().enumerate() {
        m[4 * i..4 * i + 4].copy_from_slice(row);
    }
    m
}

/// A channel's name with its part's in front (`part.name`), unless the
/// name already starts with it or the part is unnamed.
fn qualify(part: Option<&str>, name: &str) -> String {
    match part {
        Some(p) if !p.is_empty() && !name.starts_with(&format!("{p}.")) => format!("{p}.{name}"),
        _ => name.to_string(),
    }
}

/// What a rendered file says about its noise, for `denoise auto`, from its
/// headers alone (no pixel is decoded): Blender's `cycles.<view layer>.samples`
/// attribute (for the view layer `options` resolve to, or the only one),
/// and whether the file has Cycles' `Noisy Image` pass (written when its
/// denoiser ran: the color was denoised per frame). A file whose headers
/// cannot be read says nothing (`RenderHints::default()`): reading it for
/// real reports why.
pub fn read_render_hints(path: &Path, options: &LayoutOptions) -> RenderHints {
    let meta = std::panic::catch_unwind(|| exr::meta::MetaData::read_from_file(path, false));
    let Ok(Ok(meta)) = meta else {
        return RenderHints::default();
    };
    let mut names = Vec::new();
    let mut found: Vec<(String, u32)> = Vec::new();
    for h in meta.headers.iter() {
        let part = h.own_attributes.layer_name.as_ref().map(|t| t.to_string());
        names.extend(
            h.channels
                .list
                .iter()
                .map(|c| qualify(part.as_deref(), &c.name.to_string())),
        );
        for (k, v) in &h.own_attributes.other {
            let key = k.to_string();
            let Some(layer) = key
                .strip_prefix("cycles.")
                .and_then(|r| r.strip_suffix(".samples"))
            else {
                continue;
            };
            let n = match v {
                AttributeValue::Text(t) => t.to_string().trim().parse::<u32>().ok(),
                AttributeValue::I32(i) => u32::try_from(*i).ok(),
                _ => None,
            };
            if let Some(n) = n.filter(|&n| n > 0) {
                if !found.iter().any(|(l, _)| l == layer) {
                    found.push((layer.to_string(), n));
                }
            }
        }
    }
    let view_layer = layout::resolve(options, &names, &|n| names.iter().any(|x| x == n))
        .ok()
        .and_then(|r| r.view_layer);
    let samples = match view_layer.as_deref() {
        Some(vl) => found.iter().find(|(l, _)| l == vl).map(|f| f.1),
        None if found.len() == 1 => Some(found[0].1),
        None => None,
    };
    let noisy_pass = |name: &str| match view_layer.as_deref() {
        Some(vl) => name.starts_with(&format!("{vl}.Noisy Image.")),
        None => name.contains("Noisy Image."),
    };
    RenderHints {
        samples,
        denoised_by_renderer: names.iter().any(|n| noisy_pass(n)),
    }
}

/// What a rendered file says about its noise ([`read_render_hints`]).
#[derive(Debug, Clone, Copy, PartialEq, Eq, Default)]
pub struct RenderHints {
    /// Samples per pixel the renderer recorded (Blender/Cycles:
    /// `cycles.<view layer>.samples`).
    pub samples: Option<u32>,
    /// The renderer denoised the color itself (Cycles wrote its `Noisy
    /// Image` pass beside the denoised `Combined`).
    pub denoised_by_renderer: bool,
}

impl RenderHints {
    /// The session parameters a host would pass for such frames when the
    /// user set neither `denoise` nor `samples`: `denoise temporal` for
    /// frames the renderer denoised, else `samples`; and why, for the user.
    pub fn params(&self) -> Option<(&'static str, crate::params::ParamValue, String)> {
        use crate::params::ParamValue;
        if self.denoised_by_renderer {
            return Some((
                "denoise",
                ParamValue::Str("temporal".into()),
                "the renderer denoised the frames (Cycles' Noisy Image pass is there): denoise temporal"
                    .to_string(),
            ));
        }
        self.samples.map(|n| {
            (
                "samples",
                ParamValue::Int(i64::from(n)),
                format!("the file says the renderer took {n} samples per pixel: samples {n}"),
            )
        })
    }
}

impl ExrFile {
    /// Reads every part and channel of `path`; `frame` only names the frame in
    /// errors. The header's claims are checked first with the default
    /// [`ReadLimits`] (the memory available as the budget).
    pub fn open(path: &Path, frame: Option<i64>) -> Result<ExrFile> {
        ExrFile::open_with(path, frame, &ReadLimits::default())
    }

    /// [`ExrFile::open`] with explicit limits (a device's memory limit, ...).
    /// A file whose header claims more than the limits, the memory budget or
    /// its own size can hold is refused before anything is decoded
    /// ([`super::guard`]); a decoder failure, even a panic inside the `exr`
    /// crate, is an error naming the file and frame.
    pub fn open_with(path: &Path, frame: Option<i64>, limits: &ReadLimits) -> Result<ExrFile> {
        if !path.is_file() {
            return Err(Error::Io(format!("{}: file not found", ctx(path, frame))));
        }
        let size = std::fs::metadata(path)
            .map_err(|e| Error::Io(format!("{}: {e}", ctx(path, frame))))?
            .len();
        let (budget, budget_name) = limits.budget();
        if size > budget as u64 {
            return Err(Error::OutOfMemory(format!(
                "{}: the file is {size} bytes, more than {budget_name} ({budget} bytes)",
                ctx(path, frame)
            )));
        }
        let bytes =
            std::fs::read(path).map_err(|e| Error::Io(format!("{}: {e}", ctx(path, frame))))?;
        ExrFile::from_bytes(bytes, path, frame, limits)
    }

    /// A whole EXR file already in memory; `path` and `frame` name it in
    /// errors. The same checks as [`ExrFile::open_with`].
    pub fn from_bytes(
        bytes: Vec<u8>,
        path: &Path,
        frame: Option<i64>,
        limits: &ReadLimits,
    ) -> Result<ExrFile> {
        let checked =
            std::panic::catch_unwind(|| guard::check(&bytes, limits)).unwrap_or_else(|p| {
                Err(Refusal::Invalid(format!(
                    "the header could not be read ({})",
                    panic_text(&p)
                )))
            });
        checked.map_err(|r| match r {
            Refusal::Memory(m) => Error::OutOfMemory(format!("{}: {m}", ctx(path, frame))),
            Refusal::Invalid(m) => Error::Io(format!(
                "{}: cannot read EXR (unreadable or truncated file): {m}",
                ctx(path, frame)
            )),
        })?;
        let decoded = std::panic::catch_unwind(|| {
            exr::prelude::read()
                .no_deep_data()
                .largest_resolution_level()
                .all_channels()
                .all_layers()
                .all_attributes()
                .pedantic()
                // On this thread: a panic in the crate's worker threads
                // aborts the process, here it is caught.
                .non_parallel()
                .from_buffered(std::io::Cursor::new(&bytes[..]))
                .map_err(|e| e.to_string())
        })
        .unwrap_or_else(|p| Err(format!("the decoder failed ({})", panic_text(&p))));
        drop(bytes);
        let image = decoded.map_err(|e| {
            Error::Io(format!(
                "{}: cannot read EXR (unreadable or truncated file): {e}",
                ctx(path, frame)
            ))
        })?;
        let mut channels = Vec::new();
        for (part, layer) in image.layer_data.iter().enumerate() {
            let part_name = layer.attributes.layer_name.as_ref().map(|t| t.to_string());
            for (index, ch) in layer.channel_data.list.iter().enumerate() {
                let name = ch.name.to_string();
                let qualified = qualify(part_name.as_deref(), &name);
                channels.push(ChannelInfo {
                    part,
                    index,
                    name,
                    qualified,
                    kind: kind_of(&ch.sample_data),
                });
            }
        }
        Ok(ExrFile {
            path: path.to_path_buf(),
            frame,
            image,
            channels,
        })
    }

    /// The file's path.
    pub fn path(&self) -> &Path {
        &self.path
    }

    /// Every channel, part after part.
    pub fn channels(&self) -> &[ChannelInfo] {
        &self.channels
    }

    /// Part names (empty string for an unnamed part) and their data-window sizes.
    pub fn parts(&self) -> Vec<(String, usize, usize)> {
        self.image
            .layer_data
            .iter()
            .map(|l| {
                (
                    l.attributes
                        .layer_name
                        .as_ref()
                        .map(|t| t.to_string())
                        .unwrap_or_default(),
                    l.size.0,
                    l.size.1,
                )
            })
            .collect()
    }

    /// Display-window size.
    pub fn display_size(&self) -> (usize, usize) {
        let s = self.image.attributes.display_window.size;
        (s.0, s.1)
    }

    /// Finds a channel by qualified name, else by bare name when that is unique.
    pub fn find(&self, name: &str) -> Option<&ChannelInfo> {
        if let Some(c) = self.channels.iter().find(|c| c.qualified == name) {
            return Some(c);
        }
        let mut bare = self.channels.iter().filter(|c| c.name == name);
        match (bare.next(), bare.next()) {
            (Some(c), None) => Some(c),
            _ => None,
        }
    }

    /// The qualified channel names.
    pub fn names(&self) -> Vec<String> {
        self.channels.iter().map(|c| c.qualified.clone()).collect()
    }

    /// The layout `options` resolves to for this file.
    pub fn resolve(&self, options: &LayoutOptions) -> Result<ResolvedLayout> {
        layout::resolve(options, &self.names(), &|n| self.find(n).is_some())
            .map_err(|e| Error::invalid(format!("{}: {}", ctx(&self.path, self.frame), strip(&e))))
    }

    /// The camera from the `worldToCamera` and `worldToNDC` attributes of
    /// part `part` (or of any part holding both).
    pub fn camera(&self, part: usize) -> Option<Camera> {
        let of = |a: &LayerAttributes| match (&a.world_to_camera, &a.world_to_normalized_device) {
            (Some(c), Some(n)) => Some(Camera::from_exr_rows(matrix_rows(c), matrix_rows(n))),
            _ => None,
        };
        self.image
            .layer_data
            .get(part)
            .and_then(|l| of(&l.attributes))
            .or_else(|| self.image.layer_data.iter().find_map(|l| of(&l.attributes)))
    }

    fn samples(&self, c: &ChannelInfo) -> &FlatSamples {
        &self.image.layer_data[c.part].channel_data.list[c.index].sample_data
    }

    fn lookup(&self, r: &ChannelRef, role: &str) -> Result<&ChannelInfo> {
        self.find(&r.name).ok_or_else(|| {
            let found: Vec<String> = self.channels.iter().map(|c| c.qualified.clone()).collect();
            Error::invalid(format!(
                "{}: missing channel {:?} ({role}); channels found: {}",
                ctx(&self.path, self.frame),
                r.name,
                found.join(", ")
            ))
        })
    }
}

/// The message of an error without its category prefix.
fn strip(e: &Error) -> String {
    match e {
        Error::Invalid(m)
        | Error::InvalidOperation(m)
        | Error::NotSupported(m)
        | Error::Io(m)
        | Error::OutOfMemory(m)
        | Error::Model(m)
        | Error::RuntimeMissing(m)
        | Error::Cancelled(m) => m.clone(),
    }
}

fn to_f32(s: &FlatSamples) -> Vec<f32> {
    match s {
        FlatSamples::F16(v) => v.iter().map(|x| x.to_f32()).collect(),
        FlatSamples::F32(v) => v.clone(),
        FlatSamples::U32(v) => v.iter().map(|&x| x as f32).collect(),
    }
}

/// One frame read from an EXR file: the planar AOVs the session needs (in the
/// library's conventions) and the whole file, to write the result back.
pub struct LoadedFrame {
    /// The file.
    pub path: PathBuf,
    /// The frame number.
    pub frame: Option<i64>,
    /// Width in pixels.
    pub width: usize,
    /// Height in pixels.
    pub height: usize,
    /// The channels used.
    pub layout: ResolvedLayout,
    /// RGB, interleaved (premultiplied as stored).
    pub color: Vec<f32>,
    /// Coverage.
    pub coverage: Option<Vec<f32>>,
    /// Planar depth.
    pub depth: Option<Vec<f32>>,
    /// Motion vectors (x, y interleaved) in the library's convention.
    pub motion: Option<Vec<f32>>,
    /// Normals (x, y, z interleaved).
    pub normal: Option<Vec<f32>>,
    /// Albedo (RGB interleaved).
    pub albedo: Option<Vec<f32>>,
    /// The denoise stage's normals (x, y, z interleaved).
    pub denoise_normal: Option<Vec<f32>>,
    /// Insert mask in `[0,1]`.
    pub insert_mask: Option<Vec<f32>>,
    /// The insert's object ids (0 where none): the layout's `mask.id`
    /// channel, or the Object Index values of several inserted objects.
    pub insert_id: Option<Vec<f32>>,
    /// The camera, from the header.
    pub camera: Option<Camera>,
    /// Things worth telling the user (camera dropped, ...).
    pub warnings: Vec<String>,
    file: ExrFile,
    color_ids: [ChannelInfo; 3],
    coverage_id: Option<ChannelInfo>,
}

impl std::fmt::Debug for LoadedFrame {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.debug_struct("LoadedFrame")
            .field("path", &self.path)
            .field("frame", &self.frame)
            .field("size", &(self.width, self.height))
            .field("layout", &self.layout)
            .finish_non_exhaustive()
    }
}

/// What the output header records.
#[derive(Debug, Clone, Default)]
pub struct OutputMeta {
    /// The backend that ran.
    pub backend: String,
    /// Why the temporal state was reset before this frame (`""` when it was not).
    pub reset: String,
    /// Compress on the calling thread alone. Otherwise the exr crate makes
    /// a pool of one thread per core for each file it writes, whatever the
    /// device's thread count: a run on one thread (one farm worker of
    /// several on a machine) would compress on every core.
    pub single_threaded: bool,
}

impl LoadedFrame {
    /// Reads frame `frame` from `path` with `options`.
    pub fn read(path: &Path, frame: Option<i64>, options: &LayoutOptions) -> Result<LoadedFrame> {
        Self::read_with(path, frame, options, &ReadLimits::default())
    }

    /// [`LoadedFrame::read`] within `limits` (see [`ExrFile::open_with`]).
    pub fn read_with(
        path: &Path,
        frame: Option<i64>,
        options: &LayoutOptions,
        limits: &ReadLimits,
    ) -> Result<LoadedFrame> {
        let file = ExrFile::open_with(path, frame, limits)?;
        Self::from_file(file, options)
    }

    /// Extracts the frame from an opened file.
    pub fn from_file(file: ExrFile, options: &LayoutOptions) -> Result<LoadedFrame> {
        let where_ = ctx(&file.path, file.frame);
        let layout = file.resolve(options)?;
        let color_ids = [
            file.lookup(&layout.color[0], "color")?.clone(),
            file.lookup(&layout.color[1], "color")?.clone(),
            file.lookup(&layout.color[2], "color")?.clone(),
        ];
        let base = &file.image.layer_data[color_ids[0].part];
        let (width, height) = (base.size.0, base.size.1);
        let origin = base.attributes.layer_position;
        let mut warnings = Vec::new();
        let check = |c: &ChannelInfo, role: &str| -> Result<()> {
            let l = &file.image.layer_data[c.part];
            if l.size.0 != width || l.size.1 != height || l.attributes.layer_position != origin {
                return Err(Error::invalid(format!(
                    "{where_}: channel {:?} ({role}) has data window {}x{} at ({}, {}), color has {width}x{height} at ({}, {})",
                    c.qualified, l.size.0, l.size.1, l.attributes.layer_position.0, l.attributes.layer_position.1,
                    origin.0, origin.1
                )));
            }
            let ch = &l.channel_data.list[c.index];
            if ch.sampling.0 != 1 || ch.sampling.1 != 1 {
                return Err(Error::NotSupported(format!(
                    "{where_}: channel {:?} ({role}) is subsampled ({}x{})",
                    c.qualified, ch.sampling.0, ch.sampling.1
                )));
            }
            Ok(())
        };
        let read1 = |r: &ChannelRef, role: &str| -> Result<(ChannelInfo, Vec<f32>)> {
            let c = file.lookup(r, role)?;
            check(c, role)?;
            let mut v = to_f32(file.samples(c));
            if r.negate {
                v.iter_mut().for_each(|x| *x = -*x);
            }
            Ok((c.clone(), v))
        };
        let interleave = |planes: Vec<Vec<f32>>| -> Vec<f32> {
            let k = planes.len();
            let mut out = vec![0.0; width * height * k];
            for (c, p) in planes.iter().enumerate() {
                for (i, v) in p.iter().enumerate() {
                    out[i * k + c] = *v;
                }
            }
            out
        };
        let optional = |r: &Option<ChannelRef>,
                        role: &'static str|
         -> Result<Option<(ChannelInfo, Vec<f32>)>> {
            match r {
                Some(r) => read1(r, role).map(Some),
                None => Ok(None),
            }
        };
        let many = |rs: &[ChannelRef], role: &str| -> Result<Vec<f32>> {
            let planes = rs
                .iter()
                .map(|r| read1(r, role).map(|x| x.1))
                .collect::<Result<Vec<_>>>()?;
            Ok(interleave(planes))
        };

        let color = many(&layout.color, "color")?;
        let coverage = optional(&layout.coverage, "coverage")?;
        let coverage_id = coverage.as_ref().map(|c| c.0.clone());
        let coverage = coverage.map(|c| c.1);
        let depth = optional(&layout.depth, "depth")?.map(|d| d.1);
        let motion = layout
            .motion
            .as_ref()
            .map(|m| many(m, "motion"))
            .transpose()?;
        let normal = layout
            .normal
            .as_ref()
            .map(|m| many(m, "normal"))
            .transpose()?;
        let albedo = layout
            .albedo
            .as_ref()
            .map(|m| many(m, "albedo"))
            .transpose()?;
        let denoise_normal = layout
            .denoise_normal
            .as_ref()
            .map(|m| many(m, "denoise_normal"))
            .transpose()?;
        let mut index_ids = None;
        let insert_mask = match &layout.insert {
            None => None,
            Some(InsertSource::Channel(r)) => Some(read1(r, "insert")?.1),
            Some(InsertSource::ObjectIndex { channel, index }) => {
                let v = read1(channel, "insert (object index)")?.1;
                Some(
                    v.iter()
                        .map(|&x| {
                            if (x - *index as f32).abs() < 0.5 {
                                1.0
                            } else {
                                0.0
                            }
                        })
                        .collect(),
                )
            }
            Some(InsertSource::ObjectIndices { channel, indices }) => {
                // Each index one object, its value the object's id.
                let v = read1(channel, "insert (object index)")?.1;
                let ids: Vec<f32> = v
                    .iter()
                    .map(|&x| {
                        indices
                            .iter()
                            .find(|&&i| (x - i as f32).abs() < 0.5)
                            .map_or(0.0, |&i| i as f32)
                    })
                    .collect();
                let mask = ids
                    .iter()
                    .map(|&id| f32::from(u8::from(id > 0.0)))
                    .collect();
                index_ids = Some(ids);
                Some(mask)
            }
        };
        // The object ids: the layout's channel, else the Object Index
        // values of several inserted objects.
        let insert_id = match &layout.insert_id {
            Some(r) => Some(read1(r, "insert_id")?.1),
            None => index_ids,
        };
        let mut camera = file.camera(color_ids[0].part);
        if camera.is_some() {
            let dw = file.image.attributes.display_window;
            if dw.size.0 != width || dw.size.1 != height || dw.position != origin {
                warnings.push(format!(
                    "{where_}: the data window {width}x{height} differs from the display window {}x{}; \
                     the camera matrices are not used",
                    dw.size.0, dw.size.1
                ));
                camera = None;
            }
        }
        Ok(LoadedFrame {
            path: file.path.clone(),
            frame: file.frame,
            width,
            height,
            layout,
            color,
            coverage,
            depth,
            motion,
            normal,
            albedo,
            denoise_normal,
            insert_mask,
            insert_id,
            camera,
            warnings,
            color_ids,
            coverage_id,
            file,
        })
    }

    /// Views over the frame's buffers for [`crate::Session::process`].
    pub fn frame_input(&self) -> Result<FrameInput<'_>> {
        let (w, h) = (self.width, self.height);
        fn mk<'b>(what: &str, d: &'b [f32], w: usize, h: usize, c: usize) -> Result<ImageView<'b>> {
            ImageView::from_f32(what, d, w, h, c)
        }
        let view = |what: &str, d, c| mk(what, d, w, h, c);
        let mut f = FrameInput::new(view("color", &self.color, 3)?);
        f.coverage = self
            .coverage
            .as_deref()
            .map(|d| view("coverage", d, 1))
            .transpose()?;
        f.depth = self
            .depth
            .as_deref()
            .map(|d| view("depth", d, 1))
            .transpose()?;
        f.motion = self
            .motion
            .as_deref()
            .map(|d| view("motion", d, 2))
            .transpose()?;
        f.normal = self
            .normal
            .as_deref()
            .map(|d| view("normal", d, 3))
            .transpose()?;
        f.albedo = self
            .albedo
            .as_deref()
            .map(|d| view("albedo", d, 3))
            .transpose()?;
        f.denoise_normal = self
            .denoise_normal
            .as_deref()
            .map(|d| view("denoise_normal", d, 3))
            .transpose()?;
        f.insert_mask = self
            .insert_mask
            .as_deref()
            .map(|d| view("insert_mask", d, 1))
            .transpose()?;
        f.insert_id = self
            .insert_id
            .as_deref()
            .map(|d| view("insert_id", d, 1))
            .transpose()?;
        f.camera = self.camera;
        f.frame_index = self.frame;
        Ok(f)
    }

    /// The whole file as read.
    pub fn file(&self) -> &ExrFile {
        &self.file
    }

    /// Writes the enhanced frame `out` (4 planes: RGB premultiplied, A
    /// coverage) to `path`: every part, channel and attribute of the input is
    /// kept, the color channels (and coverage) are replaced in their own
    /// sample types, and `harmonizer:*` attributes are added. Atomic; refuses
    /// to write over the input file.
    pub fn write_enhanced(&mut self, out: &Image, path: &Path, meta: &OutputMeta) -> Result<()> {
        let where_ = ctx(&self.path, self.frame);
        if out.width != self.width || out.height != self.height || out.channels < 4 {
            return Err(Error::invalid(format!(
                "{where_}: enhanced image is {}x{}x{}, expected {}x{}x4",
                out.width, out.height, out.channels, self.width, self.height
            )));
        }
        refuse_input(path, &self.path, self.frame)?;
        let mut targets: Vec<(ChannelInfo, usize)> =
            self.color_ids.iter().cloned().zip(0..3).collect();
        if let Some(c) = &self.coverage_id {
            targets.push((c.clone(), 3));
        }
        for (c, plane) in targets {
            let src = out.plane(plane);
            let dst =
                &mut self.file.image.layer_data[c.part].channel_data.list[c.index].sample_data;
            match dst {
                FlatSamples::F16(v) => v
                    .iter_mut()
                    .zip(src)
                    .for_each(|(d, s)| *d = exr::prelude::f16::from_f32(*s)),
                FlatSamples::F32(v) => v.copy_from_slice(src),
                FlatSamples::U32(v) => v
                    .iter_mut()
                    .zip(src)
                    .for_each(|(d, s)| *d = s.max(0.0).round() as u32),
            }
        }
        let frame = self.frame.map(|f| f.to_string()).unwrap_or_default();
        for l in self.file.image.layer_data.iter_mut() {
            for (k, v) in [
                ("harmonizer:version", crate::VERSION),
                ("harmonizer:backend", meta.backend.as_str()),
                ("harmonizer:frame", frame.as_str()),
                ("harmonizer:reset", meta.reset.as_str()),
            ] {
                l.attributes
                    .other
                    .insert(Text::from(k), AttributeValue::Text(Text::from(v)));
            }
        }
        let image = &self.file.image;
        write_atomic(path, |tmp| -> std::result::Result<(), String> {
            // In memory first: the exr crate writes the attributes it does
            // not know (the input's own and `harmonizer:*`) in hash-map
            // order, which changes from run to run; sorted, equal images
            // give equal files.
            let mut buf = std::io::Cursor::new(Vec::new());
            let writer = image.write();
            let writer = if meta.single_threaded {
                writer.non_parallel()
            } else {
                writer
            };
            writer.to_buffered(&mut buf).map_err(|e| e.to_string())?;
            let mut bytes = buf.into_inner();
            sort_header_attributes(&mut bytes)?;
            std::fs::write(tmp, bytes).map_err(|e| e.to_string())
        })
        .map_err(|e| {
            Error::Io(format!(
                "{where_}: cannot write output {}: {}",
                path.display(),
                strip(&e)
            ))
        })
    }
}

/// Sorts the attributes of every header of the OpenEXR file in `bytes` by
/// name, in place, as OpenEXR itself writes them. Each header keeps its
/// length, so the offset tables after the headers stay valid. An error names
/// what is malformed (nothing is changed then).
pub fn sort_header_attributes(bytes: &mut [u8]) -> std::result::Result<(), String> {
    const MAGIC: [u8; 4] = [0x76, 0x2f, 0x31, 0x01];
    const MULTIPART: u32 = 0x1000;
    if bytes.len() < 8 || bytes[..4] != MAGIC {
        return Err("not an OpenEXR file".into());
    }
    let flags = u32::from_le_bytes([bytes[4], bytes[5], bytes[6], bytes[7]]);
    let multipart = flags & MULTIPART != 0;
    // Every header as (start, end, attributes as (name, byte range)).
    let mut headers = Vec::new();
    let mut pos = 8;
    loop {
        let start = pos;
        let mut attrs: Vec<(&[u8], std::ops::Range<usize>)> = Vec::new();
        loop {
            let at = |p: usize| -> std::result::Result<u8, String> {
                bytes
                    .get(p)
                    .copied()
                    .ok_or_else(|| format!("header truncated at byte {p}"))
            };
            if at(pos)? == 0 {
                break;
            }
            let nul = |from: usize| {
                bytes[from..]
                    .iter()
                    .position(|&b| b == 0)
                    .map(|i| from + i)
                    .ok_or_else(|| format!("unterminated attribute name or type at byte {from}"))
            };
            let name_end = nul(pos)?;
            let type_end = nul(name_end + 1)?;
            let size_at = type_end + 1;
            let size = bytes
                .get(size_at..size_at + 4)
                .map(|b| i32::from_le_bytes([b[0], b[1], b[2], b[3]]))
                .ok_or_else(|| format!("attribute size truncated at byte {size_at}"))?;
            let end = usize::try_from(size)
                .ok()
                .and_then(|n| (size_at + 4).checked_add(n))
                .filter(|&e| e <= bytes.len())
                .ok_or_else(|| format!("attribute at byte {pos} has a bad size {size}"))?;
            attrs.push((&bytes[pos..name_end], pos..end));
            pos = end;
        }
        // `pos` is at the header's terminating null byte.
        let empty = attrs.is_empty();
        if !empty {
            headers.push((start, pos, attrs));
        }
        pos += 1;
        if !multipart || empty {
            break;
        }
    }
    let sorted: Vec<(usize, usize, Vec<u8>)> = headers
        .into_iter()
        .map(|(start, end, mut attrs)| {
            attrs.sort_by(|a, b| a.0.cmp(b.0));
            let out: Vec<u8> = attrs
                .iter()
                .flat_map(|(_, r)| bytes[r.clone()].iter().copied())
                .collect();
            (start, end, out)
        })
        .collect();
    for (start, end, out) in sorted {
        bytes[start..end].copy_from_slice(&out);
    }
    Ok(())
}

/// Refuses an output path that names the input file.
pub fn refuse_input(output: &Path, input: &Path, frame: Option<i64>) -> Result<()> {
    let same = match (std::fs::canonicalize(output), std::fs::canonicalize(input)) {
        (Ok(a), Ok(b)) => a == b,
        _ => output == input,
    };
    if same {
        return Err(Error::invalid(format!(
            "{}: output {} is the input file; inputs are never overwritten",
            ctx(input, frame),
            output.display()
        )));
    }
    Ok(())
}

/// Writes a file atomically: `write` fills `name.tmp-<pid>` in the same
/// directory, which is then renamed over `path`.
pub fn write_atomic<E: std::fmt::Display>(
    path: &Path,
    write: impl FnOnce(&Path) -> std::result::Result<(), E>,
) -> Result<()> {
    let name = path
        .file_name()
        .ok_or_else(|| Error::invalid(format!("output {}: has no file name", path.display())))?;
    let dir = path
        .parent()
        .filter(|d| !d.as_os_str().is_empty())
        .unwrap_or(Path::new("."));
    if !dir.is_dir() {
        std::fs::create_dir_all(dir).map_err(|e| Error::io(dir, e))?;
    }
    let tmp = dir.join(format!(
        "{}.tmp-{}",
        name.to_string_lossy(),
        std::process::id()
    ));
    if let Err(e) = write(&tmp) {
        let _ = std::fs::remove_file(&tmp);
        return Err(Error::io(&tmp, e));
    }
    std::fs::rename(&tmp, path).map_err(|e| {
        let _ = std::fs::remove_file(&tmp);
        Error::io(path, e)
    })
}

/// One channel to write with [`write_channels`].
#[derive(Debug, Clone, Copy)]
pub struct OutChannel<'a> {
    /// The channel name.
    pub name: &'a str,
    /// Samples, row after row (`width * height`).
    pub data: &'a [f32],
    /// Store as half float instead of float.
    pub half: bool,
}

impl<'a> OutChannel<'a> {
    /// Full-float channels from `(name, samples)` pairs.
    pub fn floats(channels: &[(&'a str, &'a [f32])]) -> Vec<OutChannel<'a>> {
        channels
            .iter()
            .map(|&(name, data)| OutChannel {
                name,
                data,
                half: false,
            })
            .collect()
    }
}

/// Writes a single-part EXR with the given channels and optional camera
/// attributes (`worldToCamera`, `worldToNDC`), atomically.
pub fn write_channels(
    path: &Path,
    width: usize,
    height: usize,
    channels: &[OutChannel<'_>],
    camera: Option<&Camera>,
) -> Result<()> {
    for c in channels {
        if c.data.len() != width * height {
            return Err(Error::invalid(format!(
                "{}: channel {} has {} samples, expected {width}x{height}",
                path.display(),
                c.name,
                c.data.len()
            )));
        }
    }
    let list = channels
        .iter()
        .map(|c| {
            let s = if c.half {
                FlatSamples::F16(
                    c.data
                        .iter()
                        .map(|v| exr::prelude::f16::from_f32(*v))
                        .collect(),
                )
            } else {
                FlatSamples::F32(c.data.to_vec())
            };
            AnyChannel::new(c.name, s)
        })
        .collect();
    let mut attrs = LayerAttributes::default();
    if let Some(cam) = camera {
        let (w2c, w2n) = cam.to_exr_rows();
        attrs.world_to_camera = Some(rows_matrix(&w2c));
        attrs.world_to_normalized_device = Some(rows_matrix(&w2n));
    }
    let layer = Layer::new(
        (width, height),
        attrs,
        Encoding::SMALL_LOSSLESS,
        AnyChannels::sort(list),
    );
    let image = ExrImage::from_layer(layer);
    write_atomic(path, |tmp| image.write().to_file(tmp))
}

fn plane(data: &[f32], channels: usize, c: usize) -> Vec<f32> {
    data.iter().skip(c).step_by(channels).copied().collect()
}

/// Writes a synthetic input frame in the `generic` layout (float).
pub fn write_generic(path: &Path, f: &crate::synth::SynthInput) -> Result<()> {
    let p: Vec<Vec<f32>> = (0..4).map(|c| plane(&f.color, 4, c)).collect();
    let m: Vec<Vec<f32>> = (0..2).map(|c| plane(&f.motion, 2, c)).collect();
    let n: Vec<Vec<f32>> = (0..3).map(|c| plane(&f.normal, 3, c)).collect();
    let ch = |name, data| OutChannel {
        name,
        data,
        half: false,
    };
    write_channels(
        path,
        f.width,
        f.height,
        &[
            ch("R", &p[0]),
            ch("G", &p[1]),
            ch("B", &p[2]),
            ch("A", &p[3]),
            ch("Z", &f.depth),
            ch("motion.X", &m[0]),
            ch("motion.Y", &m[1]),
            ch("N.X", &n[0]),
            ch("N.Y", &n[1]),
            ch("N.Z", &n[2]),
            ch("mask.insert", &f.insert_mask),
        ],
        Some(&f.camera),
    )
}

/// Writes a synthetic frame's ground truth: `R,G,B`, `A` = 1, exact
/// `motion.X/Y`, and region masks `mask.hole`, `mask.insert`, `mask.shadow`,
/// `mask.temporal` (0/1).
pub fn write_truth(path: &Path, f: &crate::synth::SynthFrame) -> Result<()> {
    let (w, h) = (f.input.width, f.input.height);
    let rgb: Vec<Vec<f32>> = (0..3).map(|c| plane(&f.truth, 3, c)).collect();
    let m: Vec<Vec<f32>> = (0..2).map(|c| plane(&f.truth_motion, 2, c)).collect();
    let ones = vec![1.0; w * h];
    let mask = |m: &[bool]| {
        m.iter()
            .map(|&b| if b { 1.0 } else { 0.0 })
            .collect::<Vec<f32>>()
    };
    let (hole, ins, sh, tm) = (
        mask(&f.hole_mask),
        mask(&f.insert_mask),
        mask(&f.shadow_mask),
        mask(&f.temporal_mask),
    );
    let ch = |name, data| OutChannel {
        name,
        data,
        half: false,
    };
    write_channels(
        path,
        w,
        h,
        &[
            ch("R", &rgb[0]),
            ch("G", &rgb[1]),
            ch("B", &rgb[2]),
            ch("A", &ones),
            ch("motion.X", &m[0]),
            ch("motion.Y", &m[1]),
            ch("mask.hole", &hole),
            ch("mask.insert", &ins),
            ch("mask.shadow", &sh),
            ch("mask.temporal", &tm),
        ],
        Some(&f.input.camera),
    )
}

/// What `harmonize info` prints about a file.
#[derive(Debug, Clone)]
pub struct FileInfo {
    /// Parts: name, width, height.
    pub parts: Vec<(String, usize, usize)>,
    /// Channels: qualified name and sample type.
    pub channels: Vec<(String, SampleKind)>,
    /// Display window size.
    pub display: (usize, usize),
    /// The layout `auto` detects.
    pub layout: LayoutPreset,
    /// The Blender view layer, if any.
    pub view_layer: Option<String>,
    /// Roles found with the detected layout.
    pub roles: Vec<&'static str>,
    /// Whether `worldToCamera` and `worldToNDC` are present.
    pub camera: bool,
}

/// Describes a file (parts, channels, detected layout, camera).
pub fn info(path: &Path) -> Result<FileInfo> {
    let f = ExrFile::open(path, None)?;
    let l = f.resolve(&LayoutOptions::default())?;
    let mut roles = Vec::new();
    if l.color.iter().all(|c| f.find(&c.name).is_some()) {
        roles.push("color");
    }
    for (r, present) in [
        ("coverage", l.coverage.is_some()),
        ("depth", l.depth.is_some()),
        ("motion", l.motion.is_some()),
        ("normal", l.normal.is_some()),
        ("insert", l.insert.is_some()),
        ("insert_id", l.insert_id.is_some()),
        ("albedo", l.albedo.is_some()),
        ("denoise_normal", l.denoise_normal.is_some()),
    ] {
        if present {
            roles.push(r);
        }
    }
    Ok(FileInfo {
        parts: f.parts(),
        channels: f
            .channels
            .iter()
            .map(|c| (c.qualified.clone(), c.kind))
            .collect(),
        display: f.display_size(),
        layout: l.preset,
        view_layer: l.view_layer,
        roles,
        camera: f.camera(0).is_some(),
    })
}
