//! Session parameters, set by name (the C ABI's `hz_session_set_*`) and
//! validated on commit. Adding a parameter never changes the ABI.

use crate::denoise::Quality;
use crate::error::{Error, Result};
use crate::frame::{DepthKind, FrameShape};
use crate::ops::LUMA;

/// A parameter value as a host passes it.
#[derive(Debug, Clone, PartialEq)]
pub enum ParamValue {
    /// Integer.
    Int(i64),
    /// Float.
    Float(f64),
    /// Boolean.
    Bool(bool),
    /// String.
    Str(String),
}

/// Which backend runs.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum BackendKind {
    /// The neural model when the device has one, else classical.
    Auto,
    /// The ONNX model.
    Neural,
    /// The classical pipeline.
    Classical,
    /// Output equals input (color-management round-trip checks).
    Bypass,
}

impl BackendKind {
    /// Parses `auto|neural|classical|bypass`.
    pub fn parse(s: &str) -> Result<Self> {
        Ok(match s {
            "auto" => BackendKind::Auto,
            "neural" => BackendKind::Neural,
            "classical" => BackendKind::Classical,
            "bypass" => BackendKind::Bypass,
            _ => {
                return Err(Error::invalid(format!(
                    "parameter backend: unknown value {s:?} (expected auto, neural, classical or bypass)"
                )))
            }
        })
    }
    /// The name used in parameters and reports.
    pub fn name(self) -> &'static str {
        match self {
            BackendKind::Auto => "auto",
            BackendKind::Neural => "neural",
            BackendKind::Classical => "classical",
            BackendKind::Bypass => "bypass",
        }
    }
}

/// Whether the session denoises the color before the backend (`denoise`).
#[derive(Debug, Clone, Copy, PartialEq, Eq, Default)]
pub enum DenoiseMode {
    /// On when the host says `samples` is 1..=64, off when it says more;
    /// with `samples` 0 (unknown), on when the first frame after a reset
    /// looks noisy ([`crate::denoise::noise_level`]). Decided once per
    /// sequence; never on with the `bypass` backend. The default.
    #[default]
    Auto,
    /// Always (Open Image Denoise must be found).
    On,
    /// Never.
    Off,
    /// The renderer denoised each frame already (Cycles' own denoiser,
    /// OptiX, a compositor's OIDN): no second spatial pass, only the
    /// temporal accumulation that removes the flicker a per-frame denoiser
    /// leaves.
    Temporal,
}

impl DenoiseMode {
    /// Parses `auto|on|off|temporal`.
    pub fn parse(s: &str) -> Result<Self> {
        Ok(match s {
            "auto" => DenoiseMode::Auto,
            "on" => DenoiseMode::On,
            "off" => DenoiseMode::Off,
            "temporal" => DenoiseMode::Temporal,
            _ => {
                return Err(Error::invalid(format!(
                    "parameter denoise: unknown value {s:?} (expected auto, on, off or temporal)"
                )))
            }
        })
    }

    /// The name used in parameters and reports.
    pub fn name(self) -> &'static str {
        match self {
            DenoiseMode::Auto => "auto",
            DenoiseMode::On => "on",
            DenoiseMode::Off => "off",
            DenoiseMode::Temporal => "temporal",
        }
    }
}

/// Parses the `denoise_quality` values `high|balanced|fast`.
fn parse_quality(s: &str) -> Result<Quality> {
    Ok(match s {
        "high" => Quality::High,
        "balanced" => Quality::Balanced,
        "fast" => Quality::Fast,
        _ => {
            return Err(Error::invalid(format!(
                "parameter denoise_quality: unknown value {s:?} (expected high, balanced or fast)"
            )))
        }
    })
}

/// The `denoise_quality` name of `q` (`Default` is OIDN's default, high).
fn quality_name(q: Quality) -> &'static str {
    match q {
        Quality::High | Quality::Default => "high",
        Quality::Balanced => "balanced",
        Quality::Fast => "fast",
    }
}

/// The most samples per pixel `samples` accepts.
pub const MAX_SAMPLES: i64 = 1 << 30;

/// The space `light_direction` is given in.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum LightSpace {
    /// World space (the camera matrices' world).
    World,
    /// OpenEXR camera space: +x right, +y up, +z forward.
    Camera,
}

/// What to do when a frame number is not the previous one plus one.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum GapPolicy {
    /// Reset the temporal state (the default).
    Reset,
    /// Keep the state and warn.
    Keep,
}

/// All session parameters.
#[derive(Debug, Clone, PartialEq)]
pub struct Params {
    /// Previous enhanced frames used as context, 0..=8 (`context_frames`).
    pub context_frames: usize,
    /// Backend (`backend`).
    pub backend: BackendKind,
    /// Blend of enhanced over input, 0..=1 (`strength`).
    pub strength: f32,
    /// Fill holes where coverage < 1 (`fill_holes`).
    pub fill_holes: bool,
    /// Coverage below which the classical fill drops a hole pixel's own
    /// color and fills the pixel whole, 0..=1 (`coverage_floor`): the faint
    /// edges of a reconstruction's splats are mostly wrong surfaces. The
    /// neural backend's network sees the coverage as rendered (as trained).
    pub coverage_floor: f32,
    /// Harmonize inserted objects with their surroundings (`harmonize`).
    pub harmonize: bool,
    /// With `harmonize`: match each inserted object's color statistics to
    /// the background around it (`match_tone`: exposure, white balance and
    /// saturation, [`crate::ops::harmonize`]). Off by default: on the
    /// project's held-out inserts it cost 0.7 dB in the insert on average
    /// and repainted correctly lit objects (docs/inserts.md); for
    /// composites known to carry a tone or white-balance mismatch.
    pub match_tone: bool,
    /// With `harmonize`, and the frame's albedo and normals: correct each
    /// inserted object's colors by a 3x3 matrix fitted so that its albedo
    /// is shaded as the scene's light shades the background's
    /// (`albedo_tone`, [`crate::ops::albedo_tone`]). A correctly lit object
    /// stays as it is (a dead zone of half a stop). On by default; frames
    /// without an albedo are not touched by it.
    pub albedo_tone: bool,
    /// With `harmonize`, a light direction and a camera: give an inserted
    /// object lit by another light the scene light's shading (`relight`,
    /// [`crate::ops::relight`]).
    pub relight: bool,
    /// Add contact shadows under inserted objects (`contact_shadows`).
    pub contact_shadows: bool,
    /// Shadow darkness, 0..=1 (`shadow_strength`): the share of the light
    /// the shadow takes away (a sun's share of the light on the ground).
    pub shadow_strength: f32,
    /// Direction toward the scene's dominant light (`light_direction`:
    /// "x, y, z", empty when unknown), in world space or the camera's (see
    /// `light_space`). With it (and a camera) inserts cast shadows away
    /// from it; hosts fill it from the scene's sun or brightest light.
    pub light_direction: Option<[f32; 3]>,
    /// The scene's direct-to-ambient light ratio (`light_ratio`, at least
    /// 0; 0, the default: unknown): the dominant light's irradiance on a
    /// surface facing it over the ambient irradiance (sky, dome) on a
    /// surface in its shadow, `k` in `ambient * (1 + k * n.l)`. Hosts fill
    /// it from their lights (a sun's strength against the world's). The
    /// shading correction (`relight`) takes the scene's own ratio from its
    /// shadows on a render, since those include the bounce light the
    /// host's lights do not tell; it takes this one on frames with holes
    /// (a reconstruction's depth is too rough to trace shadows through) and
    /// where the frame shows no shadow of its own.
    pub light_ratio: f32,
    /// The dominant light's color and strength (`light_color`: "r, g, b",
    /// empty when unknown): its irradiance on a surface facing it, in the
    /// frame's scene-linear units (a Blender Sun's strength times its
    /// color; a USD DistantLight's intensity times its color and
    /// `2^exposure`). With `ambient_color`, the light an inserted object
    /// is matched to when its background shows no albedo to read the
    /// scene's light from (`albedo_tone`, a reconstruction: the albedo
    /// only on the object), and the ratio when `light_ratio` is 0.
    pub light_color: Option<[f32; 3]>,
    /// The rest of the scene's light (`ambient_color`: "r, g, b", empty
    /// when unknown): the irradiance (sky, dome, world) on a surface in
    /// the dominant light's shadow, hosts take half of what a surface
    /// facing up gets; see `light_color`.
    pub ambient_color: Option<[f32; 3]>,
    /// Space of `light_direction` (`light_space`: "world", the default, or
    /// "camera": OpenEXR camera space, +x right, +y up, +z forward).
    pub light_space: LightSpace,
    /// Blend with the reprojected history to remove flicker (`stabilize`):
    /// the classical pipeline's last step, also run on the output of neural
    /// models whose manifest asks for it (`stabilize: true`).
    pub stabilize: bool,
    /// Weight of the history in stabilization, 0..=0.98 (`temporal_blend`).
    pub temporal_blend: f32,
    /// Stabilize every pixel of every frame (`stabilize_all`). Off by
    /// default: a frame with holes is stabilized whole, any other only where
    /// the enhancer changed it (the insert, its shadow), so a clean render
    /// comes out as it went in.
    pub stabilize_all: bool,
    /// Frame-number gap policy (`gap_policy`: "reset" or "keep").
    pub gap_policy: GapPolicy,
    /// Reset automatically on a scene cut (`scene_cut_detection`).
    pub scene_cut_detection: bool,
    /// Fraction of mismatching pixels that counts as a cut, 0..=1 (`scene_cut_threshold`).
    pub scene_cut_threshold: f32,
    /// Depth measure of the depth AOV (`depth_kind`: "planar" or "euclidean").
    pub depth_kind: DepthKind,
    /// Run the classical pipeline after the neural model (`classical_post`).
    pub classical_post: bool,
    /// Neural tile edge in pixels, 0 = the manifest's (`tile_size`).
    pub tile_size: usize,
    /// Neural tile overlap in pixels, 0 = the manifest's (`tile_overlap`).
    pub tile_overlap: usize,
    /// Denoise the color with Open Image Denoise before the backend and
    /// accumulate it over time (`denoise`: "auto", "on", "off" or
    /// "temporal").
    pub denoise: DenoiseMode,
    /// Open Image Denoise's quality (`denoise_quality`: "high", "balanced"
    /// or "fast").
    pub denoise_quality: Quality,
    /// The host's samples per pixel, 0 = unknown (`samples`); `denoise
    /// auto` is on for 1..=64 and off above.
    pub samples: u32,
    /// Denoise the albedo and normal before the color
    /// (`denoise_prefilter`), as OIDN recommends for noisy auxiliary
    /// images: three filter runs a frame instead of one. Off by default.
    pub denoise_prefilter: bool,
    /// Run the neural network on frames without holes too
    /// (`neural_clean_frames`); off by default: such frames (clean, or with
    /// an insert alone) get the classical operations.
    pub neural_clean_frames: bool,
    /// Covered pixels far from holes keep their rendered color where the
    /// model's manifest gives a `repair_margin` (`keep_covered`); on by
    /// default. Off: the network's output everywhere.
    pub keep_covered: bool,
}

impl Default for Params {
    fn default() -> Self {
        Params {
            context_frames: 4,
            backend: BackendKind::Auto,
            strength: 1.0,
            fill_holes: true,
            coverage_floor: 0.95,
            harmonize: true,
            match_tone: false,
            albedo_tone: true,
            relight: true,
            contact_shadows: true,
            shadow_strength: 0.6,
            light_direction: None,
            light_ratio: 0.0,
            light_color: None,
            ambient_color: None,
            light_space: LightSpace::World,
            stabilize: true,
            temporal_blend: 0.6,
            stabilize_all: false,
            gap_policy: GapPolicy::Reset,
            scene_cut_detection: true,
            scene_cut_threshold: 0.6,
            depth_kind: DepthKind::Planar,
            classical_post: false,
            tile_size: 0,
            tile_overlap: 0,
            denoise: DenoiseMode::Auto,
            denoise_quality: Quality::High,
            samples: 0,
            denoise_prefilter: false,
            neural_clean_frames: false,
            keep_covered: true,
        }
    }
}

/// Reads three numbers separated by commas or spaces ("x, y, z"); empty is
/// none. The error names what is not a number or how many there were.
pub(crate) fn parse_three(s: &str) -> std::result::Result<Option<[f32; 3]>, String> {
    let s = s.trim();
    if s.is_empty() {
        return Ok(None);
    }
    let v: Vec<f32> = s
        .split(|c: char| c == ',' || c.is_whitespace())
        .filter(|t| !t.is_empty())
        .map(|t| {
            t.parse::<f32>()
                .map_err(|_| format!("{t:?} is not a number"))
        })
        .collect::<std::result::Result<_, _>>()?;
    match v[..] {
        [x, y, z] => Ok(Some([x, y, z])),
        _ => Err(format!("expected three numbers, got {} in {s:?}", v.len())),
    }
}

/// Reads a color parameter: "r, g, b" (commas or spaces), three finite
/// numbers at least 0, not all 0; empty is none.
pub fn parse_color(s: &str) -> std::result::Result<Option<[f32; 3]>, String> {
    match parse_three(s)? {
        Some(c) if c.iter().all(|v| v.is_finite() && *v >= 0.0) && c.iter().any(|v| *v > 0.0) => {
            Ok(Some(c))
        }
        None => Ok(None),
        Some(_) => Err(format!(
            "expected three finite numbers at least 0, not all 0 (\"r, g, b\"), got {:?}",
            s.trim()
        )),
    }
}

fn color_text(c: Option<[f32; 3]>) -> String {
    c.map(|[r, g, b]| format!("{r}, {g}, {b}"))
        .unwrap_or_default()
}

/// The names of all parameters, for help texts and bindings.
pub const PARAM_NAMES: &[&str] = &[
    "context_frames",
    "backend",
    "strength",
    "fill_holes",
    "coverage_floor",
    "harmonize",
    "match_tone",
    "albedo_tone",
    "relight",
    "contact_shadows",
    "shadow_strength",
    "light_direction",
    "light_ratio",
    "light_color",
    "ambient_color",
    "light_space",
    "stabilize",
    "temporal_blend",
    "stabilize_all",
    "gap_policy",
    "scene_cut_detection",
    "scene_cut_threshold",
    "depth_kind",
    "classical_post",
    "tile_size",
    "tile_overlap",
    "denoise",
    "denoise_quality",
    "samples",
    "denoise_prefilter",
    "neural_clean_frames",
    "keep_covered",
];

fn want_int(name: &str, v: &ParamValue, lo: i64, hi: i64) -> Result<i64> {
    let i = match v {
        ParamValue::Int(i) => *i,
        other => {
            return Err(Error::invalid(format!(
                "parameter {name}: expected an integer, got {other:?}"
            )))
        }
    };
    if i < lo || i > hi {
        return Err(Error::invalid(format!(
            "parameter {name}: {i} is out of range {lo}..={hi}"
        )));
    }
    Ok(i)
}

fn want_float(name: &str, v: &ParamValue, lo: f64, hi: f64) -> Result<f32> {
    let f = match v {
        ParamValue::Float(f) => *f,
        ParamValue::Int(i) => *i as f64,
        other => {
            return Err(Error::invalid(format!(
                "parameter {name}: expected a number, got {other:?}"
            )))
        }
    };
    if !f.is_finite() || f < lo || f > hi {
        return Err(Error::invalid(format!(
            "parameter {name}: {f} is out of range {lo}..={hi}"
        )));
    }
    Ok(f as f32)
}

fn want_bool(name: &str, v: &ParamValue) -> Result<bool> {
    match v {
        ParamValue::Bool(b) => Ok(*b),
        ParamValue::Int(0) => Ok(false),
        ParamValue::Int(1) => Ok(true),
        other => Err(Error::invalid(format!(
            "parameter {name}: expected a boolean, got {other:?}"
        ))),
    }
}

fn want_str<'a>(name: &str, v: &'a ParamValue) -> Result<&'a str> {
    match v {
        ParamValue::Str(s) => Ok(s),
        other => Err(Error::invalid(format!(
            "parameter {name}: expected a string, got {other:?}"
        ))),
    }
}

impl Params {
    /// Whether frames of `shape` get the insert color matrix
    /// (`albedo_tone`): the session then prepares their albedo and normals.
    pub fn insert_albedo(&self, shape: &FrameShape) -> bool {
        self.harmonize
            && self.albedo_tone
            && shape.albedo
            && shape.normal
            && (shape.insert_mask || shape.insert_id)
    }

    /// `light_direction` in world space for a frame seen by `camera`
    /// (`None` without a direction, or in camera space without a camera).
    pub fn light_direction_world(
        &self,
        camera: Option<&crate::frame::Camera>,
    ) -> Option<glam::DVec3> {
        let d = glam::DVec3::from(self.light_direction?.map(f64::from));
        match self.light_space {
            LightSpace::World => Some(d),
            LightSpace::Camera => {
                let c2w = camera?.world_to_camera.as_dmat4().inverse();
                Some(c2w.transform_vector3(d))
            }
        }
    }

    /// The host's direct-to-ambient ratio: `light_ratio`, or where it is 0
    /// the luminance of `light_color` over `ambient_color`'s (at most
    /// [`crate::ops::relight::MAX_RATIO`]); 0 when neither says.
    pub fn host_light_ratio(&self) -> f32 {
        if self.light_ratio > 0.0 {
            return self.light_ratio;
        }
        let lum = |c: [f32; 3]| c[0] * LUMA[0] + c[1] * LUMA[1] + c[2] * LUMA[2];
        match (self.light_color, self.ambient_color) {
            (Some(d), Some(a)) if lum(a) > 0.0 && lum(d) > 0.0 => {
                (lum(d) / lum(a)).min(crate::ops::relight::MAX_RATIO)
            }
            _ => 0.0,
        }
    }

    /// Sets one parameter by name; unknown names and out-of-range values are errors.
    pub fn set(&mut self, name: &str, v: &ParamValue) -> Result<()> {
        match name {
            "context_frames" => self.context_frames = want_int(name, v, 0, 8)? as usize,
            "backend" => self.backend = BackendKind::parse(want_str(name, v)?)?,
            "strength" => self.strength = want_float(name, v, 0.0, 1.0)?,
            "fill_holes" => self.fill_holes = want_bool(name, v)?,
            "coverage_floor" => self.coverage_floor = want_float(name, v, 0.0, 1.0)?,
            "harmonize" => self.harmonize = want_bool(name, v)?,
            "match_tone" => self.match_tone = want_bool(name, v)?,
            "albedo_tone" => self.albedo_tone = want_bool(name, v)?,
            "relight" => self.relight = want_bool(name, v)?,
            "contact_shadows" => self.contact_shadows = want_bool(name, v)?,
            "shadow_strength" => self.shadow_strength = want_float(name, v, 0.0, 1.0)?,
            "light_direction" => {
                self.light_direction = crate::ops::cast_shadow::parse_direction(want_str(name, v)?)
                    .map_err(|e| Error::invalid(format!("parameter light_direction: {e}")))?
            }
            "light_ratio" => {
                self.light_ratio = want_float(name, v, 0.0, crate::ops::relight::MAX_RATIO as f64)?
            }
            "light_color" | "ambient_color" => {
                let c = parse_color(want_str(name, v)?)
                    .map_err(|e| Error::invalid(format!("parameter {name}: {e}")))?;
                match name {
                    "light_color" => self.light_color = c,
                    _ => self.ambient_color = c,
                }
            }
            "light_space" => {
                self.light_space = match want_str(name, v)? {
                    "world" => LightSpace::World,
                    "camera" => LightSpace::Camera,
                    s => {
                        return Err(Error::invalid(format!(
                            "parameter light_space: unknown value {s:?} (expected world or camera)"
                        )))
                    }
                }
            }
            "stabilize" => self.stabilize = want_bool(name, v)?,
            "temporal_blend" => self.temporal_blend = want_float(name, v, 0.0, 0.98)?,
            "stabilize_all" => self.stabilize_all = want_bool(name, v)?,
            "gap_policy" => {
                self.gap_policy = match want_str(name, v)? {
                    "reset" => GapPolicy::Reset,
                    "keep" => GapPolicy::Keep,
                    s => {
                        return Err(Error::invalid(format!(
                            "parameter gap_policy: unknown value {s:?} (expected reset or keep)"
                        )))
                    }
                }
            }
            "scene_cut_detection" => self.scene_cut_detection = want_bool(name, v)?,
            "scene_cut_threshold" => self.scene_cut_threshold = want_float(name, v, 0.0, 1.0)?,
            "depth_kind" => {
                self.depth_kind = match want_str(name, v)? {
                    "planar" => DepthKind::Planar,
                    "euclidean" => DepthKind::Euclidean,
                    s => {
                        return Err(Error::invalid(format!(
                        "parameter depth_kind: unknown value {s:?} (expected planar or euclidean)"
                    )))
                    }
                }
            }
            "classical_post" => self.classical_post = want_bool(name, v)?,
            "tile_size" => self.tile_size = want_int(name, v, 0, 8192)? as usize,
            "tile_overlap" => self.tile_overlap = want_int(name, v, 0, 1024)? as usize,
            "denoise" => self.denoise = DenoiseMode::parse(want_str(name, v)?)?,
            "denoise_quality" => self.denoise_quality = parse_quality(want_str(name, v)?)?,
            "samples" => self.samples = want_int(name, v, 0, MAX_SAMPLES)? as u32,
            "denoise_prefilter" => self.denoise_prefilter = want_bool(name, v)?,
            "neural_clean_frames" => self.neural_clean_frames = want_bool(name, v)?,
            "keep_covered" => self.keep_covered = want_bool(name, v)?,
            _ => {
                return Err(Error::invalid(format!(
                    "unknown parameter {name:?} (known: {})",
                    PARAM_NAMES.join(", ")
                )))
            }
        }
        Ok(())
    }

    /// Reads one parameter by name.
    pub fn get(&self, name: &str) -> Result<ParamValue> {
        Ok(match name {
            "context_frames" => ParamValue::Int(self.context_frames as i64),
            "backend" => ParamValue::Str(self.backend.name().into()),
            "strength" => ParamValue::Float(self.strength as f64),
            "fill_holes" => ParamValue::Bool(self.fill_holes),
            "coverage_floor" => ParamValue::Float(self.coverage_floor as f64),
            "harmonize" => ParamValue::Bool(self.harmonize),
            "match_tone" => ParamValue::Bool(self.match_tone),
            "albedo_tone" => ParamValue::Bool(self.albedo_tone),
            "relight" => ParamValue::Bool(self.relight),
            "contact_shadows" => ParamValue::Bool(self.contact_shadows),
            "shadow_strength" => ParamValue::Float(self.shadow_strength as f64),
            "light_direction" => ParamValue::Str(
                self.light_direction
                    .map(|[x, y, z]| format!("{x}, {y}, {z}"))
                    .unwrap_or_default(),
            ),
            "light_ratio" => ParamValue::Float(self.light_ratio as f64),
            "light_color" => ParamValue::Str(color_text(self.light_color)),
            "ambient_color" => ParamValue::Str(color_text(self.ambient_color)),
            "light_space" => ParamValue::Str(
                match self.light_space {
                    LightSpace::World => "world",
                    LightSpace::Camera => "camera",
                }
                .into(),
            ),
            "stabilize" => ParamValue::Bool(self.stabilize),
            "temporal_blend" => ParamValue::Float(self.temporal_blend as f64),
            "stabilize_all" => ParamValue::Bool(self.stabilize_all),
            "gap_policy" => ParamValue::Str(
                match self.gap_policy {
                    GapPolicy::Reset => "reset",
                    GapPolicy::Keep => "keep",
                }
                .into(),
            ),
            "scene_cut_detection" => ParamValue::Bool(self.scene_cut_detection),
            "scene_cut_threshold" => ParamValue::Float(self.scene_cut_threshold as f64),
            "depth_kind" => ParamValue::Str(
                match self.depth_kind {
                    DepthKind::Planar => "planar",
                    DepthKind::Euclidean => "euclidean",
                }
                .into(),
            ),
            "classical_post" => ParamValue::Bool(self.classical_post),
            "tile_size" => ParamValue::Int(self.tile_size as i64),
            "tile_overlap" => ParamValue::Int(self.tile_overlap as i64),
            "denoise" => ParamValue::Str(self.denoise.name().into()),
            "denoise_quality" => ParamValue::Str(quality_name(self.denoise_quality).into()),
            "samples" => ParamValue::Int(self.samples as i64),
            "denoise_prefilter" => ParamValue::Bool(self.denoise_prefilter),
            "neural_clean_frames" => ParamValue::Bool(self.neural_clean_frames),
            "keep_covered" => ParamValue::Bool(self.keep_covered),
            _ => {
                return Err(Error::invalid(format!(
                    "unknown parameter {name:?} (known: {})",
                    PARAM_NAMES.join(", ")
                )))
            }
        })
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn every_name_round_trips() {
        let mut p = Params::default();
        for name in PARAM_NAMES {
            let v = p.get(name).unwrap();
            p.set(name, &v).unwrap();
        }
        assert_eq!(p, Params::default());
    }

    #[test]
    fn errors_name_the_parameter_and_value() {
        let mut p = Params::default();
        let e = p
            .set("context_frames", &ParamValue::Int(9))
            .unwrap_err()
            .to_string();
        assert!(e.contains("context_frames") && e.contains('9'), "{e}");
        let e = p.set("nope", &ParamValue::Int(1)).unwrap_err().to_string();
        assert!(e.contains("nope"), "{e}");
        let e = p
            .set("backend", &ParamValue::Str("gpu".into()))
            .unwrap_err()
            .to_string();
        assert!(e.contains("gpu"), "{e}");
        for (name, v, needle) in [
            ("denoise", ParamValue::Str("maybe".into()), "maybe"),
            ("denoise_quality", ParamValue::Str("best".into()), "best"),
            ("samples", ParamValue::Int(-1), "-1"),
            ("samples", ParamValue::Str("4".into()), "integer"),
        ] {
            let e = p.set(name, &v).unwrap_err().to_string();
            assert!(e.contains(name) && e.contains(needle), "{e}");
        }
    }

    #[test]
    fn light_colors_parse_and_give_the_ratio() {
        let mut p = Params::default();
        assert_eq!(p.host_light_ratio(), 0.0);
        p.set("light_color", &ParamValue::Str("4.5, 4.32 4.05".into()))
            .unwrap();
        assert_eq!(p.light_color, Some([4.5, 4.32, 4.05]));
        // One of the two says nothing of the ratio.
        assert_eq!(p.host_light_ratio(), 0.0);
        p.set("ambient_color", &ParamValue::Str("1.3, 2.2, 3.9".into()))
            .unwrap();
        let lum = |c: [f32; 3]| c[0] * LUMA[0] + c[1] * LUMA[1] + c[2] * LUMA[2];
        let want = lum([4.5, 4.32, 4.05]) / lum([1.3, 2.2, 3.9]);
        assert!((p.host_light_ratio() - want).abs() < 1e-6);
        // The host's ratio wins.
        p.set("light_ratio", &ParamValue::Float(3.0)).unwrap();
        assert_eq!(p.host_light_ratio(), 3.0);
        // A faint ambient gives at most the largest ratio.
        p.set("light_ratio", &ParamValue::Float(0.0)).unwrap();
        p.set("ambient_color", &ParamValue::Str("0.001, 0, 0".into()))
            .unwrap();
        assert_eq!(p.host_light_ratio(), crate::ops::relight::MAX_RATIO);
        // Round trip, and empty is none.
        let v = p.get("light_color").unwrap();
        p.set("light_color", &v).unwrap();
        assert_eq!(p.light_color, Some([4.5, 4.32, 4.05]));
        p.set("light_color", &ParamValue::Str(" ".into())).unwrap();
        assert_eq!(p.light_color, None);
        for bad in [
            "1, 2",
            "1, -2, 3",
            "0, 0, 0",
            "1, nan, 2",
            "a, b, c",
            "1, 2, 3, 4",
        ] {
            let e = p
                .set("ambient_color", &ParamValue::Str(bad.into()))
                .unwrap_err()
                .to_string();
            assert!(e.contains("ambient_color"), "{e}");
        }
        let e = p
            .set("light_color", &ParamValue::Float(2.0))
            .unwrap_err()
            .to_string();
        assert!(e.contains("light_color"), "{e}");
    }

    #[test]
    fn denoise_parameters_parse() {
        let mut p = Params::default();
        assert_eq!(
            (p.denoise, p.denoise_quality, p.samples),
            (DenoiseMode::Auto, Quality::High, 0)
        );
        p.set("denoise", &ParamValue::Str("on".into())).unwrap();
        p.set("denoise_quality", &ParamValue::Str("fast".into()))
            .unwrap();
        p.set("samples", &ParamValue::Int(4)).unwrap();
        assert_eq!(
            (p.denoise, p.denoise_quality, p.samples),
            (DenoiseMode::On, Quality::Fast, 4)
        );
        assert_eq!(p.get("denoise").unwrap(), ParamValue::Str("on".into()));
        assert_eq!(
            p.get("denoise_quality").unwrap(),
            ParamValue::Str("fast".into())
        );
        assert_eq!(p.get("samples").unwrap(), ParamValue::Int(4));
    }
}
