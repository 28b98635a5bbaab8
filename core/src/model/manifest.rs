//! The model manifest: a JSON file beside the `.onnx` (`<model>.json`) that
//! says what the network expects: its input and output tensors and their
//! ordered channels, how scene-linear HDR color is encoded into the
//! network's range and back, the temporal context K, and tiling hints.
//!
//! Example (`format_version` 1):
//!
//! ```json
//! {
//!   "format_version": 1,
//!   "name": "harmonizer-small",
//!   "version": "1.0.0",
//!   "context_frames": 4,
//!   "input": { "name": "input", "channels": ["color.r", "color.g", "color.b", "coverage", "insert",
//!                                            "hist0.r", "hist0.g", "hist0.b", "valid0"] },
//!   "output": { "name": "output", "channels": ["color.r", "color.g", "color.b"] },
//!   "residual": true,
//!   "premultiplied": true,
//!   "encoding": { "kind": "log", "key": 0.18, "exposure": "frame", "log_range": 8.0 },
//!   "tile_size": 256,
//!   "tile_overlap": 32,
//!   "spatial_multiple": 16,
//!   "stabilize": true,
//!   "repair_margin": 2
//! }
//! ```

use serde::{Deserialize, Serialize};

use crate::error::{Error, Result};

/// The manifest format this build reads.
pub const MANIFEST_FORMAT_VERSION: u32 = 1;

/// The most context frames a model may ask for (the session's limit).
pub const MAX_CONTEXT_FRAMES: usize = 8;

/// A tensor of the model: its ONNX name and ordered channel names.
#[derive(Debug, Clone, PartialEq, Eq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct TensorSpec {
    /// The ONNX graph input or output name.
    pub name: String,
    /// Channel names in tensor order (the C axis of NCHW).
    pub channels: Vec<String>,
}

/// How exposure is normalized before encoding.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Serialize, Deserialize, Default)]
#[serde(rename_all = "lowercase")]
pub enum Exposure {
    /// Scale so the whole frame's log-average luminance maps to `key`
    /// (computed once per frame over covered pixels, never per tile).
    #[default]
    Frame,
    /// No scaling (scale 1).
    None,
}

/// How scene-linear HDR color maps into the network's range and back.
#[derive(Debug, Clone, Copy, PartialEq, Serialize, Deserialize)]
#[serde(tag = "kind", rename_all = "lowercase", deny_unknown_fields)]
pub enum Encoding {
    /// `y = x * s`; back `x = y / s`.
    Linear {
        /// Target log-average luminance when `exposure` is `frame`.
        #[serde(default = "default_key")]
        key: f32,
        /// Exposure normalization.
        #[serde(default)]
        exposure: Exposure,
    },
    /// `y = log2(1 + x * s) / log_range`; back `x = (2^(y * log_range) - 1) / s`.
    Log {
        /// Target log-average luminance when `exposure` is `frame`.
        #[serde(default = "default_key")]
        key: f32,
        /// Exposure normalization.
        #[serde(default)]
        exposure: Exposure,
        /// Divisor of the log2 (the number of stops above 0 mapped to 1).
        #[serde(default = "default_log_range")]
        log_range: f32,
    },
}

fn default_key() -> f32 {
    0.18
}
fn default_log_range() -> f32 {
    8.0
}
fn default_true() -> bool {
    true
}
fn default_tile_size() -> usize {
    256
}
fn default_tile_overlap() -> usize {
    32
}
fn default_multiple() -> usize {
    1
}

impl Default for Encoding {
    fn default() -> Self {
        Encoding::Log {
            key: default_key(),
            exposure: Exposure::Frame,
            log_range: default_log_range(),
        }
    }
}

/// One input channel of the network, parsed from its manifest name.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum InputChannel {
    /// `color.r|g|b`: the current frame's color, encoded (index 0..3).
    Color(usize),
    /// `coverage`: the frame's coverage in 0..=1 (1 when the host gave none).
    Coverage,
    /// `insert`: the insert mask in 0..=1 (0 when the host gave none).
    Insert,
    /// `disparity`: `1 / (1 + depth)` of the planar depth (0 when absent).
    Disparity,
    /// `normal.x|y|z` (0 when absent).
    Normal(usize),
    /// `motion.x|y`: motion vectors in pixels, library convention (0 when absent).
    Motion(usize),
    /// `hist{k}.r|g|b`: history frame k reprojected, encoded (0 when unavailable).
    History(usize, usize),
    /// `hist{k}.a`: history frame k's coverage (0 when unavailable).
    HistoryAlpha(usize),
    /// `valid{k}`: validity of history frame k's reprojection (0 when unavailable).
    Valid(usize),
    /// `prior.r|g|b`: the manifest's [`PriorSpec`] fill of the encoded
    /// color, computed by the runtime from the other channels of the tile.
    Prior(usize),
}

impl InputChannel {
    /// Parses a manifest channel name.
    pub fn parse(name: &str) -> Option<InputChannel> {
        let rgb = |s: &str| match s {
            "r" => Some(0),
            "g" => Some(1),
            "b" => Some(2),
            _ => None,
        };
        let xyz = |s: &str| match s {
            "x" => Some(0),
            "y" => Some(1),
            "z" => Some(2),
            _ => None,
        };
        let index = |s: &str| -> Option<usize> {
            (!s.is_empty() && s.len() <= 2 && s.bytes().all(|b| b.is_ascii_digit()))
                .then(|| s.parse().ok())?
        };
        Some(match name {
            "coverage" => InputChannel::Coverage,
            "insert" => InputChannel::Insert,
            "disparity" => InputChannel::Disparity,
            _ => {
                if let Some(c) = name.strip_prefix("color.") {
                    InputChannel::Color(rgb(c)?)
                } else if let Some(c) = name.strip_prefix("prior.") {
                    InputChannel::Prior(rgb(c)?)
                } else if let Some(c) = name.strip_prefix("normal.") {
                    InputChannel::Normal(xyz(c)?)
                } else if let Some(c) = name.strip_prefix("motion.") {
                    match xyz(c)? {
                        2 => return None,
                        i => InputChannel::Motion(i),
                    }
                } else if let Some(k) = name.strip_prefix("valid") {
                    InputChannel::Valid(index(k)?)
                } else if let Some(rest) = name.strip_prefix("hist") {
                    let (k, c) = rest.split_once('.')?;
                    let k = index(k)?;
                    if c == "a" {
                        InputChannel::HistoryAlpha(k)
                    } else {
                        InputChannel::History(k, rgb(c)?)
                    }
                } else {
                    return None;
                }
            }
        })
    }

    /// The history frame this channel reads, if any.
    pub fn history_index(self) -> Option<usize> {
        match self {
            InputChannel::History(k, _)
            | InputChannel::HistoryAlpha(k)
            | InputChannel::Valid(k) => Some(k),
            _ => None,
        }
    }
}

/// How the runtime computes a model's prior (the `prior.r|g|b` input
/// channels): the encoded color with its holes filled, first from the
/// reprojected history, newest first, then by a push-pull from the
/// background side; the operations of the trainer's `Enhancer.prior`
/// (`training/model.py`) with the "chain" fill, on the tile's input
/// channels (`crate::backend::neural::prior`).
#[derive(Debug, Clone, Copy, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct PriorSpec {
    /// Pixels covered below this count as holes (their color is dropped).
    pub floor: f32,
    /// A history frame fills a hole pixel only where few covered pixels
    /// are near (the classical backend's gate).
    pub gate: bool,
    /// History frames the fill reads (the first ones).
    pub frames: usize,
    /// Halvings of the push-pull pyramid.
    pub levels: usize,
    /// Relative disparity within which two surfaces count as one (0: a
    /// plain push-pull, without depth).
    pub depth_tol: f32,
    /// Share (0..=1) of the edge-continuing fill in what the history left
    /// missing (`crate::ops::inpaint::edge`): the push-pull's fill there
    /// becomes `(1 - edge_fill) * push_pull + edge_fill * edge`. A runtime
    /// stage the trainer's prior does not have (the network does not
    /// correct holes, which keep the prior: `hole_correction` 0); absent
    /// or 0, the trainer's prior exactly.
    #[serde(default, skip_serializing_if = "is_zero")]
    pub edge_fill: f32,
}

fn is_zero(x: &f32) -> bool {
    *x == 0.0
}

/// A model manifest (see the module documentation for the JSON form).
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct Manifest {
    /// Manifest format; must be [`MANIFEST_FORMAT_VERSION`].
    pub format_version: u32,
    /// Model name (reported by the library).
    pub name: String,
    /// Model version (reported by the library).
    pub version: String,
    /// K: previous enhanced frames the model expects (0..=8).
    pub context_frames: usize,
    /// How many of its `context_frames` history slots the runtime fills
    /// (the newest frames first); the later slots get no frame (zeros,
    /// validity 0), as at a sequence's start. For a model measured to gain
    /// nothing from its older frames: their reprojection is skipped.
    /// Absent: all of them.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub history_read: Option<usize>,
    /// The input tensor (NCHW f32).
    pub input: TensorSpec,
    /// The output tensor (NCHW f32); channels are a permutation of `color.r`, `color.g`, `color.b`.
    pub output: TensorSpec,
    /// The output is added to the encoded input color (a residual) instead of replacing it.
    #[serde(default)]
    pub residual: bool,
    /// The network sees color premultiplied by coverage (`true`, holes are 0)
    /// or straight color (`false`, color divided by coverage where coverage
    /// is at least 1e-3, else 0). Either way it predicts the complete frame
    /// (alpha 1) in the same form as its input.
    #[serde(default = "default_true")]
    pub premultiplied: bool,
    /// Color encoding.
    #[serde(default)]
    pub encoding: Encoding,
    /// Tile edge in pixels (the network input's size, including overlap).
    #[serde(default = "default_tile_size")]
    pub tile_size: usize,
    /// Overlap between neighbouring tiles in pixels. Tiled output equals the
    /// untiled output when `tile_overlap / 2` is at least the receptive radius.
    #[serde(default = "default_tile_overlap")]
    pub tile_overlap: usize,
    /// Tile width and height must be multiples of this (e.g. 16 for a UNet with 4 downsamplings).
    #[serde(default = "default_multiple")]
    pub spatial_multiple: usize,
    /// Peak working memory of the network per tile pixel in bytes, if
    /// measured at export; otherwise estimated from the channel counts.
    #[serde(default)]
    pub bytes_per_pixel: Option<usize>,
    /// The network's output is meant to be stabilized over time: the neural
    /// backend blends it with the reprojected previous result, clamped to
    /// the local color range (the classical stabilization,
    /// `crate::ops::stabilize`), whenever the session's `stabilize` parameter
    /// is on (the default) and `temporal_blend` is above 0.
    #[serde(default, skip_serializing_if = "std::ops::Not::not")]
    pub stabilize: bool,
    /// Covered pixels (coverage at least the session's `coverage_floor`)
    /// farther than this many pixels (Chebyshev distance) from a hole keep
    /// their rendered color; at this distance they take
    /// [`REPAIR_EDGE_SHARE`] of the network's output, nearer all of it. For
    /// a model measured to repair holes and their edges but to repaint the
    /// rest of the frame worse than it came. Absent: the network's output
    /// everywhere. The session's `keep_covered` parameter turns it off.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub repair_margin: Option<usize>,
    /// How the runtime computes the `prior.r|g|b` channels; required by,
    /// and only with, those channels.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub prior: Option<PriorSpec>,
}

/// Share of the network's output a covered pixel takes at `repair_margin`
/// pixels from a hole (a one-pixel fade to the rendered color beyond).
pub const REPAIR_EDGE_SHARE: f32 = 0.4;

/// The largest `repair_margin` a manifest may give.
pub const MAX_REPAIR_MARGIN: usize = 64;

impl Manifest {
    /// The history slots the runtime fills: `history_read`, else
    /// `context_frames`.
    pub fn history_slots(&self) -> usize {
        self.history_read
            .unwrap_or(self.context_frames)
            .min(self.context_frames)
    }

    /// Parses and validates manifest JSON; `origin` names the source in errors
    /// (a file path or "in-memory manifest").
    pub fn from_json(text: &str, origin: &str) -> Result<Manifest> {
        let m: Manifest = serde_json::from_str(text)
            .map_err(|e| Error::Model(format!("manifest {origin}: {e}")))?;
        m.validate(origin)?;
        Ok(m)
    }

    /// The manifest as pretty JSON.
    pub fn to_json(&self) -> String {
        serde_json::to_string_pretty(self).expect("a manifest always serializes")
    }

    /// The parsed input channels, in tensor order.
    pub fn input_channels(&self) -> Vec<InputChannel> {
        self.input
            .channels
            .iter()
            .map(|c| InputChannel::parse(c).expect("validated manifest"))
            .collect()
    }

    /// For each output tensor channel, the color index (0 r, 1 g, 2 b) it holds.
    pub fn output_order(&self) -> Vec<usize> {
        self.output
            .channels
            .iter()
            .map(|c| match c.as_str() {
                "color.r" => 0,
                "color.g" => 1,
                _ => 2,
            })
            .collect()
    }

    /// Working memory per tile pixel in bytes (`bytes_per_pixel`, else
    /// 4 bytes x (input + output channels) x 4 for the network's activations).
    pub fn tile_bytes_per_pixel(&self) -> usize {
        self.bytes_per_pixel
            .unwrap_or(4 * (self.input.channels.len() + self.output.channels.len()) * 4)
    }

    /// The `prior` field against the channels: the spec comes with the
    /// three `prior` channels, and the channels it reads are there.
    fn validate_prior(&self, origin: &str) -> Result<()> {
        let bad = |field: &str, msg: String| {
            Err(Error::Model(format!(
                "manifest {origin}: field {field}: {msg}"
            )))
        };
        let has = |name: &str| self.input.channels.iter().any(|c| c == name);
        let wants = ["prior.r", "prior.g", "prior.b"].map(has);
        let Some(p) = self.prior else {
            if wants.iter().any(|&w| w) {
                return bad(
                    "prior",
                    "is missing: the input has prior channels, which the runtime computes as this field says"
                        .into(),
                );
            }
            return Ok(());
        };
        if wants != [true; 3] {
            return bad(
                "prior",
                "is given but the input lacks prior.r, prior.g or prior.b".into(),
            );
        }
        if !(p.floor.is_finite() && (0.0..=1.0).contains(&p.floor)) {
            return bad("prior.floor", format!("{} is out of range 0..=1", p.floor));
        }
        if !(p.depth_tol.is_finite() && (0.0..=1.0).contains(&p.depth_tol)) {
            return bad(
                "prior.depth_tol",
                format!("{} is out of range 0..=1", p.depth_tol),
            );
        }
        if !(p.edge_fill.is_finite() && (0.0..=1.0).contains(&p.edge_fill)) {
            return bad(
                "prior.edge_fill",
                format!("{} is out of range 0..=1", p.edge_fill),
            );
        }
        if !(1..=16).contains(&p.levels) {
            return bad(
                "prior.levels",
                format!("{} is out of range 1..=16", p.levels),
            );
        }
        if p.frames > self.history_slots() {
            return bad(
                "prior.frames",
                format!(
                    "{} is above the history slots the runtime fills ({})",
                    p.frames,
                    self.history_slots()
                ),
            );
        }
        let mut needed: Vec<String> = ["color.r", "color.g", "color.b", "coverage"]
            .map(String::from)
            .into();
        for k in 0..p.frames {
            needed.extend(["r", "g", "b"].map(|c| format!("hist{k}.{c}")));
            needed.push(format!("valid{k}"));
        }
        if p.depth_tol > 0.0 {
            needed.push("disparity".into());
        }
        if let Some(missing) = needed.iter().find(|n| !has(n)) {
            return bad(
                "prior",
                format!("reads channel {missing:?}, which the input lacks"),
            );
        }
        Ok(())
    }

    /// Checks every field; errors name the field and the value seen.
    pub fn validate(&self, origin: &str) -> Result<()> {
        let bad = |field: &str, msg: String| {
            Err(Error::Model(format!(
                "manifest {origin}: field {field}: {msg}"
            )))
        };
        if self.format_version != MANIFEST_FORMAT_VERSION {
            return bad(
                "format_version",
                format!(
                    "{} is not supported (this build reads {MANIFEST_FORMAT_VERSION})",
                    self.format_version
                ),
            );
        }
        if self.name.trim().is_empty() {
            return bad("name", format!("{:?} is empty", self.name));
        }
        if self.version.trim().is_empty() {
            return bad("version", format!("{:?} is empty", self.version));
        }
        if self.context_frames > MAX_CONTEXT_FRAMES {
            return bad(
                "context_frames",
                format!(
                    "{} is out of range 0..={MAX_CONTEXT_FRAMES}",
                    self.context_frames
                ),
            );
        }
        if let Some(n) = self.history_read {
            if n > self.context_frames {
                return bad(
                    "history_read",
                    format!("{n} is above context_frames {}", self.context_frames),
                );
            }
        }
        if let Some(m) = self.repair_margin {
            if !(1..=MAX_REPAIR_MARGIN).contains(&m) {
                return bad(
                    "repair_margin",
                    format!("{m} is out of range 1..={MAX_REPAIR_MARGIN}"),
                );
            }
        }
        if self.input.name.is_empty() {
            return bad("input.name", "is empty".into());
        }
        if self.input.channels.is_empty() {
            return bad("input.channels", "is empty".into());
        }
        let mut has_color = [false; 3];
        for (i, name) in self.input.channels.iter().enumerate() {
            let field = format!("input.channels[{i}]");
            let Some(ch) = InputChannel::parse(name) else {
                return bad(
                    &field,
                    format!(
                        "unknown channel {name:?} (known: color.r|g|b, coverage, insert, disparity, normal.x|y|z, \
                         motion.x|y, hist<k>.r|g|b|a, valid<k>, prior.r|g|b)"
                    ),
                );
            };
            if let Some(k) = ch.history_index() {
                if k >= self.context_frames {
                    return bad(
                        &field,
                        format!(
                            "{name:?} reads history frame {k} but context_frames is {}",
                            self.context_frames
                        ),
                    );
                }
            }
            if self.input.channels[..i].contains(name) {
                return bad(&field, format!("channel {name:?} is listed twice"));
            }
            if let InputChannel::Color(c) = ch {
                has_color[c] = true;
            }
        }
        self.validate_prior(origin)?;
        if self.residual && has_color != [true; 3] {
            return bad(
                "input.channels",
                "a residual model needs color.r, color.g and color.b in its input".into(),
            );
        }
        if self.output.name.is_empty() {
            return bad("output.name", "is empty".into());
        }
        let mut out = self.output.channels.clone();
        out.sort();
        if out != ["color.b", "color.g", "color.r"] {
            return bad(
                "output.channels",
                format!(
                    "{:?} must be color.r, color.g and color.b in some order",
                    self.output.channels
                ),
            );
        }
        match self.encoding {
            Encoding::Linear { key, .. } => {
                if !(key.is_finite() && key > 0.0) {
                    return bad("encoding.key", format!("{key} must be a positive number"));
                }
            }
            Encoding::Log { key, log_range, .. } => {
                if !(key.is_finite() && key > 0.0) {
                    return bad("encoding.key", format!("{key} must be a positive number"));
                }
                if !(log_range.is_finite() && log_range > 0.0 && log_range <= 64.0) {
                    return bad(
                        "encoding.log_range",
                        format!("{log_range} is out of range (0, 64]"),
                    );
                }
            }
        }
        if self.spatial_multiple == 0 || self.spatial_multiple > 256 {
            return bad(
                "spatial_multiple",
                format!("{} is out of range 1..=256", self.spatial_multiple),
            );
        }
        if self.tile_size < 8 || self.tile_size > 8192 {
            return bad(
                "tile_size",
                format!("{} is out of range 8..=8192", self.tile_size),
            );
        }
        if self.tile_overlap > 1024 {
            return bad(
                "tile_overlap",
                format!("{} is out of range 0..=1024", self.tile_overlap),
            );
        }
        if self.tile_size < 4 * self.tile_overlap + 2 {
            return bad(
                "tile_size",
                format!(
                    "{} is too small for tile_overlap {} (needs at least 4 * tile_overlap + 2 = {})",
                    self.tile_size,
                    self.tile_overlap,
                    4 * self.tile_overlap + 2
                ),
            );
        }
        if let Some(b) = self.bytes_per_pixel {
            if b == 0 {
                return bad("bytes_per_pixel", "0 must be positive".into());
            }
        }
        Ok(())
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    fn sample() -> Manifest {
        Manifest {
            format_version: 1,
            name: "m".into(),
            version: "1".into(),
            context_frames: 2,
            history_read: None,
            prior: None,
            input: TensorSpec {
                name: "input".into(),
                channels: ["color.r", "color.g", "color.b", "hist1.a", "valid0"]
                    .map(String::from)
                    .to_vec(),
            },
            output: TensorSpec {
                name: "output".into(),
                channels: ["color.b", "color.g", "color.r"].map(String::from).to_vec(),
            },
            residual: true,
            premultiplied: true,
            encoding: Encoding::default(),
            tile_size: 64,
            tile_overlap: 8,
            spatial_multiple: 16,
            bytes_per_pixel: None,
            stabilize: false,
            repair_margin: None,
        }
    }

    #[test]
    fn round_trips_and_parses_channels() {
        let m = sample();
        let back = Manifest::from_json(&m.to_json(), "test").unwrap();
        assert_eq!(back, m);
        assert_eq!(back.output_order(), vec![2, 1, 0]);
        assert_eq!(back.input_channels()[3], InputChannel::HistoryAlpha(1));
        assert_eq!(
            InputChannel::parse("hist3.g"),
            Some(InputChannel::History(3, 1))
        );
        assert_eq!(InputChannel::parse("motion.z"), None);
        assert_eq!(InputChannel::parse("valid"), None);
    }

    #[test]
    fn errors_name_field_and_value() {
        let mut m = sample();
        m.input.channels[4] = "valid2".into();
        let e = m.validate("x.json").unwrap_err().to_string();
        assert!(
            e.contains("input.channels[4]") && e.contains("valid2") && e.contains("x.json"),
            "{e}"
        );
        let mut m = sample();
        m.encoding = Encoding::Log {
            key: -1.0,
            exposure: Exposure::Frame,
            log_range: 8.0,
        };
        let e = m.validate("x").unwrap_err().to_string();
        assert!(e.contains("encoding.key") && e.contains("-1"), "{e}");
        let e = Manifest::from_json(r#"{"format_version": 1, "nme": 3}"#, "y.json")
            .unwrap_err()
            .to_string();
        assert!(e.contains("nme") && e.contains("y.json"), "{e}");
    }

    /// A model whose prior the runtime computes: its channels and `prior`.
    fn with_prior() -> Manifest {
        let mut m = sample();
        m.residual = false;
        m.input.channels = [
            "color.r",
            "color.g",
            "color.b",
            "coverage",
            "hist0.r",
            "hist0.g",
            "hist0.b",
            "valid0",
            "disparity",
            "prior.r",
            "prior.g",
            "prior.b",
        ]
        .map(String::from)
        .to_vec();
        m.prior = Some(PriorSpec {
            floor: 0.95,
            gate: true,
            frames: 1,
            levels: 8,
            depth_tol: 0.05,
            edge_fill: 0.0,
        });
        m
    }

    #[test]
    fn the_prior_comes_with_its_channels_and_what_it_reads() {
        let m = with_prior();
        let back = Manifest::from_json(&m.to_json(), "test").unwrap();
        assert_eq!(back, m);
        assert_eq!(back.input_channels()[10], InputChannel::Prior(1));
        let err = |m: &Manifest| m.validate("p.json").unwrap_err().to_string();
        let mut m = with_prior();
        m.prior = None;
        let e = err(&m);
        assert!(e.contains("field prior") && e.contains("missing"), "{e}");
        let mut m = sample();
        m.prior = with_prior().prior;
        let e = err(&m);
        assert!(
            e.contains("field prior") && e.contains("lacks prior"),
            "{e}"
        );
        // Two history frames read, one given.
        let mut m = with_prior();
        m.prior.as_mut().unwrap().frames = 2;
        let e = err(&m);
        assert!(e.contains("hist1.r"), "{e}");
        // The depth tolerance reads the disparity.
        let mut m = with_prior();
        m.input.channels[8] = "insert".into();
        let e = err(&m);
        assert!(e.contains("\"disparity\""), "{e}");
        m.prior.as_mut().unwrap().depth_tol = 0.0;
        m.validate("p.json").unwrap();
        let mut m = with_prior();
        m.prior.as_mut().unwrap().levels = 0;
        let e = err(&m);
        assert!(e.contains("prior.levels") && e.contains('0'), "{e}");
        let mut m = with_prior();
        m.history_read = Some(0);
        let e = err(&m);
        assert!(e.contains("prior.frames"), "{e}");
        // The edge fill's share: a round trip, and its range.
        let mut m = with_prior();
        m.prior.as_mut().unwrap().edge_fill = 0.5;
        assert!(m.to_json().contains("\"edge_fill\""));
        assert_eq!(Manifest::from_json(&m.to_json(), "test").unwrap(), m);
        assert!(!with_prior().to_json().contains("edge_fill"));
        m.prior.as_mut().unwrap().edge_fill = 1.5;
        let e = err(&m);
        assert!(e.contains("prior.edge_fill") && e.contains("1.5"), "{e}");
    }
}
