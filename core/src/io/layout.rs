//! Channel layouts: which EXR channels hold color, coverage, depth, motion,
//! normals, the insert mask and object ids and the denoise stage's albedo
//! and normals.
//! Channels are always found by name.
//!
//! - `generic` (single part): `R,G,B` (premultiplied), `A` (coverage), `Z`
//!   (planar depth), `motion.X`, `motion.Y`, `N.X`, `N.Y`, `N.Z`,
//!   `mask.insert`, `mask.id` (the insert's object ids, integers held as
//!   floats, 0 where none; see [`crate::frame::FrameInput::insert_id`]),
//!   `albedo.R`, `albedo.G`, `albedo.B`, `denoise_normal.X`,
//!   `denoise_normal.Y`, `denoise_normal.Z`.
//! - `blender`: the multi-part multilayer EXR of Blender 5: `<layer>.Combined`
//!   (.R .G .B .A), `<layer>.Depth` (.Z), `<layer>.Vector` (.X .Y, +y up: the
//!   y component is negated), `<layer>.Normal` (.X .Y .Z), `<layer>.Object
//!   Index` (.X, the insert mask is `Object Index == --insert-index`; with
//!   several indices, `--insert-index 3,5`, the mask is the Object Index
//!   in that set and each index is one object, its value the object's id),
//!   `<layer>.Denoising Albedo` (.R .G .B, the albedo) and `<layer>.Denoising
//!   Normal` (.X .Y .Z, the denoiser's normals: Cycles writes them in camera
//!   space, consistent with its albedo, so they do not replace `Normal`).
//!   The view layer name is detected; a `Composite.Combined` part is left
//!   alone.
//! - a user mapping (`color=beauty.R,beauty.G,beauty.B`, ...) overrides or
//!   completes a preset; `auto` picks `blender` when a view layer's
//!   `Combined` pass is present, else `generic`.

use crate::error::{Error, Result};

/// A layout preset.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Default)]
pub enum LayoutPreset {
    /// `blender` when a Blender view layer is present, else `generic`.
    #[default]
    Auto,
    /// Single-part `R,G,B,A,Z,motion.X,motion.Y,N.*,mask.insert`.
    Generic,
    /// Blender 5 multi-part multilayer.
    Blender,
}

impl LayoutPreset {
    /// Parses `auto|generic|blender`.
    pub fn parse(s: &str) -> Result<LayoutPreset> {
        match s {
            "auto" => Ok(LayoutPreset::Auto),
            "generic" => Ok(LayoutPreset::Generic),
            "blender" => Ok(LayoutPreset::Blender),
            _ => Err(Error::invalid(format!(
                "--layout: unknown layout {s:?} (expected auto, generic or blender)"
            ))),
        }
    }

    /// The name used on the command line.
    pub fn name(self) -> &'static str {
        match self {
            LayoutPreset::Auto => "auto",
            LayoutPreset::Generic => "generic",
            LayoutPreset::Blender => "blender",
        }
    }
}

/// One mapped channel: a (qualified) EXR channel name, possibly negated.
#[derive(Debug, Clone, PartialEq, Eq)]
pub struct ChannelRef {
    /// The channel name, `part.channel` for multi-part files (the bare channel
    /// name is accepted when it is unique).
    pub name: String,
    /// Multiply the samples by -1 (written `-name` in a mapping).
    pub negate: bool,
}

impl ChannelRef {
    /// A plain reference.
    pub fn new(name: impl Into<String>) -> ChannelRef {
        ChannelRef {
            name: name.into(),
            negate: false,
        }
    }

    fn parse(s: &str) -> ChannelRef {
        match s.strip_prefix('-') {
            Some(rest) => ChannelRef {
                name: rest.to_string(),
                negate: true,
            },
            None => ChannelRef::new(s),
        }
    }
}

/// Where the insert mask comes from.
#[derive(Debug, Clone, PartialEq, Eq)]
pub enum InsertSource {
    /// A channel in `[0,1]`.
    Channel(ChannelRef),
    /// 1 where an object-index channel equals `index`.
    ObjectIndex {
        /// The object-index channel.
        channel: ChannelRef,
        /// The index of the inserted object(s).
        index: i64,
    },
    /// 1 where an object-index channel holds one of `indices`; each index
    /// is one object, its value the object's id.
    ObjectIndices {
        /// The object-index channel.
        channel: ChannelRef,
        /// The indices of the inserted objects (above 0).
        indices: Vec<i64>,
    },
}

/// A user mapping given on the command line: `role=CH[,CH...]`.
#[derive(Debug, Clone, Default, PartialEq, Eq)]
pub struct ChannelMapping {
    /// Color channels (R, G, B).
    pub color: Option<[ChannelRef; 3]>,
    /// Coverage (alpha).
    pub coverage: Option<ChannelRef>,
    /// Planar depth.
    pub depth: Option<ChannelRef>,
    /// Motion vectors (x, y) in the library's convention (negate with `-`).
    pub motion: Option<[ChannelRef; 2]>,
    /// Normals (x, y, z).
    pub normal: Option<[ChannelRef; 3]>,
    /// Insert mask channel.
    pub insert: Option<ChannelRef>,
    /// The insert's object ids channel.
    pub insert_id: Option<ChannelRef>,
    /// Albedo (R, G, B).
    pub albedo: Option<[ChannelRef; 3]>,
    /// The denoise stage's normals (x, y, z).
    pub denoise_normal: Option<[ChannelRef; 3]>,
}

impl ChannelMapping {
    /// Adds one `role=CH[,CH...]` entry (roles: color, coverage, depth,
    /// motion, normal, insert, insert_id, albedo, denoise_normal).
    pub fn add(&mut self, spec: &str) -> Result<()> {
        let bad = |why: String| Error::invalid(format!("--channel {spec:?}: {why}"));
        let (role, list) = spec
            .split_once('=')
            .ok_or_else(|| bad("expected ROLE=CHANNEL[,CHANNEL...], e.g. depth=depth.Z".into()))?;
        let chans: Vec<ChannelRef> = list
            .split(',')
            .map(str::trim)
            .filter(|s| !s.is_empty())
            .map(ChannelRef::parse)
            .collect();
        let want = |n: usize| -> Result<()> {
            if chans.len() != n {
                return Err(bad(format!(
                    "role {role} needs {n} channel(s), got {}",
                    chans.len()
                )));
            }
            Ok(())
        };
        match role.trim() {
            "color" => {
                want(3)?;
                self.color = Some([chans[0].clone(), chans[1].clone(), chans[2].clone()]);
            }
            "coverage" | "alpha" => {
                want(1)?;
                self.coverage = Some(chans[0].clone());
            }
            "depth" => {
                want(1)?;
                self.depth = Some(chans[0].clone());
            }
            "motion" => {
                want(2)?;
                self.motion = Some([chans[0].clone(), chans[1].clone()]);
            }
            "normal" => {
                want(3)?;
                self.normal = Some([chans[0].clone(), chans[1].clone(), chans[2].clone()]);
            }
            "insert" | "mask" => {
                want(1)?;
                self.insert = Some(chans[0].clone());
            }
            "insert_id" | "id" => {
                want(1)?;
                self.insert_id = Some(chans[0].clone());
            }
            "albedo" => {
                want(3)?;
                self.albedo = Some([chans[0].clone(), chans[1].clone(), chans[2].clone()]);
            }
            "denoise_normal" => {
                want(3)?;
                self.denoise_normal = Some([chans[0].clone(), chans[1].clone(), chans[2].clone()]);
            }
            other => {
                return Err(bad(format!(
                    "unknown role {other:?} (expected color, coverage, depth, motion, normal, insert, insert_id, \
                     albedo or denoise_normal)"
                )))
            }
        }
        Ok(())
    }

    /// True when no role is mapped.
    pub fn is_empty(&self) -> bool {
        *self == ChannelMapping::default()
    }
}

/// How to find a frame's channels: a preset, a user mapping on top, and the
/// object index of the inserted object for Blender files.
#[derive(Debug, Clone, Default, PartialEq, Eq)]
pub struct LayoutOptions {
    /// The preset.
    pub preset: LayoutPreset,
    /// User mapping; each role given here replaces the preset's.
    pub mapping: ChannelMapping,
    /// Blender: pixels whose `Object Index` equals this are the insert mask.
    pub insert_index: Option<i64>,
    /// Blender: the Object Index values of several inserted objects
    /// (`--insert-index 3,5`): the insert mask is the Object Index in this
    /// set and each index is one object (its value the object's id). When
    /// not empty it replaces `insert_index`.
    pub insert_indices: Vec<i64>,
}

/// Checks the Object Index values of several inserted objects
/// ([`LayoutOptions::insert_indices`]): each named once and, when there are
/// several, above 0 (each is an object's id, and 0 is "no object"). `what`
/// names the argument in the error (`--insert-index "3,3"`,
/// `options.insert_indices`).
pub fn check_insert_indices(what: &str, indices: &[i64]) -> Result<()> {
    let bad = |why: String| {
        Error::invalid(format!(
            "{what}: {why} (expected N, or N,N,... with Object Index values above 0)"
        ))
    };
    for (i, n) in indices.iter().enumerate() {
        if indices[..i].contains(n) {
            return Err(bad(format!("{n} is named twice")));
        }
    }
    if indices.len() > 1 {
        if let Some(n) = indices.iter().find(|&&n| n <= 0) {
            return Err(bad(format!("{n} is not above 0")));
        }
    }
    Ok(())
}

/// The channels a frame is read from, after detection.
#[derive(Debug, Clone, PartialEq, Eq)]
pub struct ResolvedLayout {
    /// The preset that applied (`generic` or `blender`, never `auto`).
    pub preset: LayoutPreset,
    /// The Blender view layer, when the preset is `blender`.
    pub view_layer: Option<String>,
    /// Color channels; required.
    pub color: [ChannelRef; 3],
    /// Coverage.
    pub coverage: Option<ChannelRef>,
    /// Depth.
    pub depth: Option<ChannelRef>,
    /// Motion (x, y), converted into the library's convention by `negate`.
    pub motion: Option<[ChannelRef; 2]>,
    /// Normals.
    pub normal: Option<[ChannelRef; 3]>,
    /// Insert mask.
    pub insert: Option<InsertSource>,
    /// The insert's object ids (a channel; [`InsertSource::ObjectIndices`]
    /// gives them too).
    pub insert_id: Option<ChannelRef>,
    /// Albedo, for the denoise stage.
    pub albedo: Option<[ChannelRef; 3]>,
    /// Normals for the denoise stage.
    pub denoise_normal: Option<[ChannelRef; 3]>,
    /// Roles the user mapped explicitly (they must exist).
    pub required: Vec<&'static str>,
}

/// Finds Blender view layers: prefixes `L` with a `L.Combined.R` channel,
/// in file order, `Composite` excluded.
pub fn blender_view_layers<'a>(names: impl IntoIterator<Item = &'a str>) -> Vec<String> {
    let mut out: Vec<String> = Vec::new();
    for n in names {
        if let Some(layer) = n.strip_suffix(".Combined.R") {
            if layer != "Composite" && !out.iter().any(|l| l == layer) {
                out.push(layer.to_string());
            }
        }
    }
    out
}

fn refs<const N: usize>(prefix: &str, names: [&str; N]) -> [ChannelRef; N] {
    names.map(|n| ChannelRef::new(format!("{prefix}{n}")))
}

/// Resolves `options` against the (qualified) channel names of a file.
/// `has` tells whether a channel name exists (exactly or as a unique bare name).
pub fn resolve(
    options: &LayoutOptions,
    names: &[String],
    has: &dyn Fn(&str) -> bool,
) -> Result<ResolvedLayout> {
    let layers = blender_view_layers(names.iter().map(String::as_str));
    let preset = match options.preset {
        LayoutPreset::Auto if !layers.is_empty() => LayoutPreset::Blender,
        LayoutPreset::Auto => LayoutPreset::Generic,
        p => p,
    };
    let all = |r: &[ChannelRef]| r.iter().all(|c| has(&c.name));
    let mut out = match preset {
        LayoutPreset::Blender => {
            let layer = layers
                .first()
                .cloned()
                .unwrap_or_else(|| "ViewLayer".to_string());
            let p = |pass: &str| format!("{layer}.{pass}.");
            let color = refs(&p("Combined"), ["R", "G", "B"]);
            let coverage =
                Some(ChannelRef::new(format!("{}A", p("Combined")))).filter(|c| has(&c.name));
            let depth = Some(ChannelRef::new(format!("{}Z", p("Depth")))).filter(|c| has(&c.name));
            let mut mv = refs(&p("Vector"), ["X", "Y"]);
            mv[1].negate = true;
            let motion = Some(mv).filter(|m| all(m));
            let normal = Some(refs(&p("Normal"), ["X", "Y", "Z"])).filter(|m| all(m));
            let albedo = Some(refs(&p("Denoising Albedo"), ["R", "G", "B"])).filter(|m| all(m));
            let denoise_normal =
                Some(refs(&p("Denoising Normal"), ["X", "Y", "Z"])).filter(|m| all(m));
            let index_channel = [
                format!("{}X", p("Object Index")),
                format!("{}X", p("IndexOB")),
            ]
            .into_iter()
            .find(|n| has(n));
            let wanted = match options.insert_indices.as_slice() {
                [] => options.insert_index.map(|i| vec![i]),
                many => Some(many.to_vec()),
            };
            let insert = match (wanted, index_channel) {
                (Some(indices), Some(ch)) => Some(match indices.as_slice() {
                    [index] => InsertSource::ObjectIndex {
                        channel: ChannelRef::new(ch),
                        index: *index,
                    },
                    _ => InsertSource::ObjectIndices {
                        channel: ChannelRef::new(ch),
                        indices,
                    },
                }),
                (Some(indices), None) if options.mapping.insert.is_none() => {
                    let list: Vec<String> = indices.iter().map(i64::to_string).collect();
                    return Err(Error::invalid(format!(
                        "--insert-index {}: view layer {layer:?} has no Object Index pass \
                         (channel {layer}.Object Index.X); enable the Object Index pass in Blender",
                        list.join(",")
                    )));
                }
                _ => None,
            };
            ResolvedLayout {
                preset,
                view_layer: Some(layer),
                color,
                coverage,
                depth,
                motion,
                normal,
                insert,
                insert_id: None,
                albedo,
                denoise_normal,
                required: vec![],
            }
        }
        _ => {
            let opt1 = |n: &str| Some(ChannelRef::new(n)).filter(|c| has(&c.name));
            ResolvedLayout {
                preset: LayoutPreset::Generic,
                view_layer: None,
                color: refs("", ["R", "G", "B"]),
                coverage: opt1("A"),
                depth: opt1("Z"),
                motion: Some(refs("", ["motion.X", "motion.Y"])).filter(|m| all(m)),
                normal: Some(refs("", ["N.X", "N.Y", "N.Z"])).filter(|m| all(m)),
                insert: opt1("mask.insert").map(InsertSource::Channel),
                insert_id: opt1("mask.id"),
                albedo: Some(refs("", ["albedo.R", "albedo.G", "albedo.B"])).filter(|m| all(m)),
                denoise_normal: Some(refs(
                    "",
                    ["denoise_normal.X", "denoise_normal.Y", "denoise_normal.Z"],
                ))
                .filter(|m| all(m)),
                required: vec![],
            }
        }
    };
    let m = &options.mapping;
    if let Some(c) = &m.color {
        out.color = c.clone();
        out.required.push("color");
    }
    if let Some(c) = &m.coverage {
        out.coverage = Some(c.clone());
        out.required.push("coverage");
    }
    if let Some(c) = &m.depth {
        out.depth = Some(c.clone());
        out.required.push("depth");
    }
    if let Some(c) = &m.motion {
        out.motion = Some(c.clone());
        out.required.push("motion");
    }
    if let Some(c) = &m.normal {
        out.normal = Some(c.clone());
        out.required.push("normal");
    }
    if let Some(c) = &m.insert {
        out.insert = Some(InsertSource::Channel(c.clone()));
        out.required.push("insert");
    }
    if let Some(c) = &m.insert_id {
        out.insert_id = Some(c.clone());
        out.required.push("insert_id");
    }
    if let Some(c) = &m.albedo {
        out.albedo = Some(c.clone());
        out.required.push("albedo");
    }
    if let Some(c) = &m.denoise_normal {
        out.denoise_normal = Some(c.clone());
        out.required.push("denoise_normal");
    }
    Ok(out)
}

#[cfg(test)]
mod tests {
    use super::*;

    fn names(list: &[&str]) -> Vec<String> {
        list.iter().map(|s| s.to_string()).collect()
    }

    #[test]
    fn auto_detects_blender_and_its_view_layer() {
        let n = names(&[
            "Composite.Combined.R",
            "Composite.Combined.G",
            "Composite.Combined.B",
            "Shot.Combined.R",
            "Shot.Combined.G",
            "Shot.Combined.B",
            "Shot.Combined.A",
            "Shot.Vector.X",
            "Shot.Vector.Y",
            "Shot.Object Index.X",
        ]);
        let has = |s: &str| n.iter().any(|x| x == s);
        let opts = LayoutOptions {
            insert_index: Some(3),
            ..Default::default()
        };
        let r = resolve(&opts, &n, &has).unwrap();
        assert_eq!(r.preset, LayoutPreset::Blender);
        assert_eq!(r.view_layer.as_deref(), Some("Shot"));
        assert_eq!(r.color[0].name, "Shot.Combined.R");
        let mv = r.motion.unwrap();
        assert!(
            !mv[0].negate && mv[1].negate,
            "Blender's +y-up vector is flipped"
        );
        assert!(r.depth.is_none());
        assert!(matches!(
            r.insert,
            Some(InsertSource::ObjectIndex { index: 3, .. })
        ));
        // Several indices: each one object.
        let opts = LayoutOptions {
            insert_indices: vec![3, 5],
            ..Default::default()
        };
        let r = resolve(&opts, &n, &has).unwrap();
        match r.insert {
            Some(InsertSource::ObjectIndices { channel, indices }) => {
                assert_eq!(channel.name, "Shot.Object Index.X");
                assert_eq!(indices, vec![3, 5]);
            }
            other => panic!("{other:?}"),
        }
        let plain = names(&["Shot.Combined.R", "Shot.Combined.G", "Shot.Combined.B"]);
        let e = resolve(&opts, &plain, &|s: &str| plain.iter().any(|x| x == s))
            .unwrap_err()
            .to_string();
        assert!(
            e.contains("--insert-index 3,5") && e.contains("Object Index"),
            "{e}"
        );
    }

    #[test]
    fn generic_object_ids() {
        let n = names(&["R", "G", "B", "mask.insert", "mask.id", "objid.X"]);
        let has = |s: &str| n.iter().any(|x| x == s);
        let r = resolve(&LayoutOptions::default(), &n, &has).unwrap();
        assert_eq!(r.insert_id.map(|c| c.name), Some("mask.id".to_string()));
        let mut opts = LayoutOptions::default();
        opts.mapping.add("insert_id=objid.X").unwrap();
        let r = resolve(&opts, &n, &has).unwrap();
        assert_eq!(r.insert_id.map(|c| c.name), Some("objid.X".to_string()));
        assert!(r.required.contains(&"insert_id"));
    }

    #[test]
    fn generic_and_user_mapping() {
        let n = names(&["R", "G", "B", "A", "Z", "beauty.R", "mv.X", "mv.Y"]);
        let has = |s: &str| n.iter().any(|x| x == s);
        let mut opts = LayoutOptions::default();
        opts.mapping.add("motion=mv.X,-mv.Y").unwrap();
        let r = resolve(&opts, &n, &has).unwrap();
        assert_eq!(r.preset, LayoutPreset::Generic);
        assert_eq!(r.depth, Some(ChannelRef::new("Z")));
        assert_eq!(
            r.motion.as_ref().unwrap()[1],
            ChannelRef {
                name: "mv.Y".into(),
                negate: true
            }
        );
        assert_eq!(r.required, vec!["motion"]);
        let e = opts.mapping.add("color=a,b").unwrap_err().to_string();
        assert!(e.contains("color") && e.contains("3"), "{e}");
        let e = opts.mapping.add("albedo=x").unwrap_err().to_string();
        assert!(e.contains("albedo") && e.contains('3'), "{e}");
        let e = opts.mapping.add("sheen=x").unwrap_err().to_string();
        assert!(e.contains("sheen") && e.contains("albedo"), "{e}");
    }

    #[test]
    fn albedo_and_the_denoisers_normals() {
        // Generic: `albedo.R/G/B` and `denoise_normal.X/Y/Z` when all three are there.
        let n = names(&[
            "R", "G", "B", "albedo.R", "albedo.G", "albedo.B", "N.X", "N.Y", "N.Z",
        ]);
        let has = |s: &str| n.iter().any(|x| x == s);
        let r = resolve(&LayoutOptions::default(), &n, &has).unwrap();
        assert_eq!(
            r.albedo,
            Some(refs("", ["albedo.R", "albedo.G", "albedo.B"]))
        );
        assert_eq!(r.denoise_normal, None);
        let partial = names(&["R", "G", "B", "albedo.R", "albedo.G"]);
        let has_partial = |s: &str| partial.iter().any(|x| x == s);
        let r = resolve(&LayoutOptions::default(), &partial, &has_partial).unwrap();
        assert_eq!(r.albedo, None);
        // Blender: the Denoising Albedo and Denoising Normal passes; the
        // Normal pass stays the normal.
        let b = names(&[
            "View Layer.Combined.R",
            "View Layer.Combined.G",
            "View Layer.Combined.B",
            "View Layer.Normal.X",
            "View Layer.Normal.Y",
            "View Layer.Normal.Z",
            "View Layer.Denoising Albedo.R",
            "View Layer.Denoising Albedo.G",
            "View Layer.Denoising Albedo.B",
            "View Layer.Denoising Normal.X",
            "View Layer.Denoising Normal.Y",
            "View Layer.Denoising Normal.Z",
        ]);
        let has_b = |s: &str| b.iter().any(|x| x == s);
        let r = resolve(&LayoutOptions::default(), &b, &has_b).unwrap();
        assert_eq!(r.preset, LayoutPreset::Blender);
        assert_eq!(
            r.albedo.as_ref().unwrap()[0].name,
            "View Layer.Denoising Albedo.R"
        );
        assert_eq!(
            r.albedo.as_ref().unwrap()[2].name,
            "View Layer.Denoising Albedo.B"
        );
        assert_eq!(
            r.denoise_normal.as_ref().unwrap()[1].name,
            "View Layer.Denoising Normal.Y"
        );
        assert_eq!(r.normal.as_ref().unwrap()[0].name, "View Layer.Normal.X");
        // The user mapping.
        let mut opts = LayoutOptions::default();
        opts.mapping.add("albedo=alb.r,alb.g,alb.b").unwrap();
        opts.mapping.add("denoise_normal=dn.x,dn.y,dn.z").unwrap();
        let r = resolve(&opts, &n, &has).unwrap();
        assert_eq!(r.albedo.as_ref().unwrap()[1].name, "alb.g");
        assert_eq!(r.denoise_normal.as_ref().unwrap()[2].name, "dn.z");
        assert_eq!(r.required, vec!["albedo", "denoise_normal"]);
    }
}
