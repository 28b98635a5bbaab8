//! EXR I/O, frame patterns and the sequence runner (issue 2, part 4).

use std::path::Path;

use exr::prelude::{
    AnyChannel, AnyChannels, Encoding, FlatSamples, Image as ExrImage, Layer, LayerAttributes,
    ReadChannels, ReadLayers, WritableImage,
};
use harmonizer_core::io::exr::{write_channels, ExrFile, LoadedFrame, OutChannel, OutputMeta};
use harmonizer_core::io::layout::{LayoutOptions, LayoutPreset};
use harmonizer_core::io::pattern::{select_frames, FramePattern, FrameRange};
use harmonizer_core::io::run::{plan, run_sequence, RunOptions};
use harmonizer_core::synth::{Sequence, SynthConfig};
use harmonizer_core::{Camera, Device, DeviceOptions, Image, ParamValue, Params, Session};

fn ramp(w: usize, h: usize, k: f32) -> Vec<f32> {
    (0..w * h).map(|i| k + i as f32 * 0.001).collect()
}

/// Every part and channel of `path`, read by the `exr` crate directly.
pub fn try_read_all(path: &Path) -> exr::error::Result<exr::image::FlatImage> {
    exr::prelude::read()
        .no_deep_data()
        .largest_resolution_level()
        .all_channels()
        .all_layers()
        .all_attributes()
        .from_file(path)
}

fn read_all(path: &Path) -> exr::image::FlatImage {
    try_read_all(path).unwrap()
}

fn f32s(s: &FlatSamples) -> Vec<f32> {
    match s {
        FlatSamples::F16(v) => v.iter().map(|x| x.to_f32()).collect(),
        FlatSamples::F32(v) => v.clone(),
        FlatSamples::U32(v) => v.iter().map(|&x| x as f32).collect(),
    }
}

/// Writes a Blender-5-style multi-part file: `Composite.Combined` first, then
/// the view layer's passes, half color, float depth, with a camera.
fn write_blender(path: &Path, layer: &str, w: usize, h: usize, cam: &Camera) {
    let n = w * h;
    let part = |name: String, chans: Vec<(&str, FlatSamples)>| {
        let list = chans
            .into_iter()
            .map(|(c, s)| AnyChannel::new(format!("{name}.{c}").as_str(), s))
            .collect();
        let mut attrs = LayerAttributes::named(name.as_str());
        let (a, b) = cam.to_exr_rows();
        let flat = |r: [[f32; 4]; 4]| {
            let mut m = [0.0f32; 16];
            for i in 0..4 {
                m[4 * i..4 * i + 4].copy_from_slice(&r[i]);
            }
            m
        };
        attrs.world_to_camera = Some(flat(a));
        attrs.world_to_normalized_device = Some(flat(b));
        attrs.other.insert(
            "cycles.samples".into(),
            exr::meta::attribute::AttributeValue::I32(64),
        );
        Layer::new(
            (w, h),
            attrs,
            Encoding::SMALL_LOSSLESS,
            AnyChannels::sort(list),
        )
    };
    let half =
        |v: Vec<f32>| FlatSamples::F16(v.into_iter().map(exr::prelude::f16::from_f32).collect());
    let float = FlatSamples::F32;
    let mut depth = ramp(w, h, 2.0);
    depth[0] = 1e10; // background, as Cycles writes it
    let index: Vec<f32> = (0..n).map(|i| if i % 3 == 0 { 2.0 } else { 0.0 }).collect();
    let layers = vec![
        part(
            "Composite.Combined".into(),
            vec![
                ("R", half(ramp(w, h, 0.9))),
                ("G", half(ramp(w, h, 0.9))),
                ("B", half(ramp(w, h, 0.9))),
                ("A", half(vec![1.0; n])),
            ],
        ),
        part(
            format!("{layer}.Combined"),
            vec![
                ("R", half(ramp(w, h, 0.1))),
                ("G", half(ramp(w, h, 0.2))),
                ("B", half(ramp(w, h, 0.3))),
                ("A", half(vec![1.0; n])),
            ],
        ),
        part(format!("{layer}.Depth"), vec![("Z", float(depth))]),
        part(
            format!("{layer}.Vector"),
            vec![
                ("X", float(vec![1.5; n])),
                ("Y", float(vec![2.5; n])),
                ("Z", float(vec![0.0; n])),
                ("W", float(vec![0.0; n])),
            ],
        ),
        part(
            format!("{layer}.Normal"),
            vec![
                ("X", float(vec![0.0; n])),
                ("Y", float(vec![1.0; n])),
                ("Z", float(vec![0.0; n])),
            ],
        ),
        part(format!("{layer}.Object Index"), vec![("X", float(index))]),
    ];
    let img = ExrImage::from_layers(
        exr::prelude::ImageAttributes::new(exr::math::Vec2(0, 0).into_bounds(w, h)),
        layers,
    );
    img.write().to_file(path).unwrap();
}

trait Bounds {
    fn into_bounds(self, w: usize, h: usize) -> exr::meta::attribute::IntegerBounds;
}
impl Bounds for exr::math::Vec2<i32> {
    fn into_bounds(self, w: usize, h: usize) -> exr::meta::attribute::IntegerBounds {
        exr::meta::attribute::IntegerBounds::new(self, (w, h))
    }
}

fn camera() -> Camera {
    Camera::look_at(glam::Vec3::new(0.5, 1.5, -3.0), glam::Vec3::ZERO, 0.8, 2.0)
}

fn enhanced(w: usize, h: usize, v: f32) -> Image {
    let mut img = Image::filled(w, h, 4, v);
    img.plane_mut(3).fill(0.75);
    img
}

#[test]
fn patterns_list_frames_in_order() {
    let dir = tempfile::tempdir().unwrap();
    for n in [3, 1, 2, 10] {
        std::fs::write(dir.path().join(format!("f.{n:04}.exr")), b"x").unwrap();
    }
    std::fs::write(dir.path().join("f.7.exr"), b"x").unwrap();
    let p = FramePattern::parse(&dir.path().join("f.####.exr").to_string_lossy()).unwrap();
    let got: Vec<i64> = p.list().unwrap().iter().map(|f| f.0).collect();
    assert_eq!(got, vec![1, 2, 3, 10]);
    let e = select_frames(&p, Some(FrameRange::parse("1-6").unwrap()))
        .unwrap_err()
        .to_string();
    assert!(
        e.contains("4-6") && e.contains("f.0004.exr"),
        "missing frames named: {e}"
    );
    let empty = FramePattern::parse(&dir.path().join("g.%04d.exr").to_string_lossy()).unwrap();
    let e = select_frames(&empty, None).unwrap_err().to_string();
    assert!(e.contains("g.%04d.exr") && e.contains("no files"), "{e}");
}

#[test]
fn generic_round_trip_keeps_every_channel_and_type() {
    let dir = tempfile::tempdir().unwrap();
    let (w, h) = (12, 7);
    let src = dir.path().join("in.exr");
    let extra = ramp(w, h, 5.0);
    let r = ramp(w, h, 0.1);
    let z = ramp(w, h, 3.0);
    let ch = |name, data, half| OutChannel { name, data, half };
    let ones = vec![1.0; w * h];
    write_channels(
        &src,
        w,
        h,
        &[
            ch("R", &r, true),
            ch("G", &r, true),
            ch("B", &r, true),
            ch("A", &ones, true),
            ch("Z", &z, false),
            ch("crypto.extra", &extra, false),
        ],
        Some(&camera()),
    )
    .unwrap();
    let mut f = LoadedFrame::read(&src, Some(1), &LayoutOptions::default()).unwrap();
    assert_eq!((f.width, f.height), (w, h));
    assert_eq!(f.layout.preset, LayoutPreset::Generic);
    assert!(
        (f.color[3] - r[1]).abs() < 1e-3,
        "interleaved RGB from half"
    );
    assert_eq!(f.depth.as_ref().unwrap(), &z);
    assert!(f.motion.is_none() && f.insert_mask.is_none());
    let cam = f.camera.expect("camera read from worldToCamera/worldToNDC");
    assert_eq!(cam, camera(), "camera attributes round trip exactly");

    let out = dir.path().join("out.exr");
    f.write_enhanced(
        &enhanced(w, h, 0.5),
        &out,
        &OutputMeta {
            backend: "classical".into(),
            reset: "first_frame".into(),
            single_threaded: false,
        },
    )
    .unwrap();
    let img = read_all(&out);
    let layer = &img.layer_data[0];
    let get = |n: &str| {
        layer
            .channel_data
            .list
            .iter()
            .find(|c| c.name.to_string() == n)
            .unwrap()
    };
    assert!(
        matches!(get("R").sample_data, FlatSamples::F16(_)),
        "half stays half"
    );
    assert!(
        matches!(get("Z").sample_data, FlatSamples::F32(_)),
        "float stays float"
    );
    assert!(f32s(&get("G").sample_data).iter().all(|&v| v == 0.5));
    assert!(
        f32s(&get("A").sample_data).iter().all(|&v| v == 0.75),
        "alpha is the output coverage"
    );
    assert_eq!(
        f32s(&get("crypto.extra").sample_data),
        extra,
        "other channels kept"
    );
    assert_eq!(f32s(&get("Z").sample_data), z);
    let attr = |k: &str| {
        format!(
            "{:?}",
            layer
                .attributes
                .other
                .get(&exr::prelude::Text::from(k))
                .unwrap()
        )
    };
    assert!(attr("harmonizer:backend").contains("classical"));
    assert!(attr("harmonizer:frame").contains('1'));
    assert!(attr("harmonizer:reset").contains("first_frame"));
    assert!(attr("harmonizer:version").contains(harmonizer_core::VERSION));
    assert!(
        layer.attributes.world_to_camera.is_some(),
        "camera kept in the output"
    );
    // Atomic: no temporary file is left behind.
    let names: Vec<String> = std::fs::read_dir(dir.path())
        .unwrap()
        .map(|e| e.unwrap().file_name().to_string_lossy().into())
        .collect();
    assert!(names.iter().all(|n| !n.contains(".tmp-")), "{names:?}");
}

#[test]
fn channels_are_found_by_name_not_position() {
    let dir = tempfile::tempdir().unwrap();
    let (w, h) = (5, 4);
    let path = dir.path().join("shuffled.exr");
    let vals: Vec<Vec<f32>> = (0..8).map(|k| vec![k as f32 + 0.25; w * h]).collect();
    let names = [
        "motion.Y",
        "Z",
        "B",
        "mask.insert",
        "R",
        "A",
        "motion.X",
        "G",
    ];
    let chans: Vec<OutChannel> = names
        .iter()
        .zip(&vals)
        .map(|(n, v)| OutChannel {
            name: n,
            data: v,
            half: false,
        })
        .collect();
    write_channels(&path, w, h, &chans, None).unwrap();
    let f = LoadedFrame::read(&path, None, &LayoutOptions::default()).unwrap();
    assert_eq!(&f.color[..3], &[4.25, 7.25, 2.25]);
    assert_eq!(f.depth.as_ref().unwrap()[0], 1.25);
    assert_eq!(&f.motion.as_ref().unwrap()[..2], &[6.25, 0.25]);
    assert_eq!(f.insert_mask.as_ref().unwrap()[0], 3.25);
    assert!(f.camera.is_none());

    // A user mapping on other names.
    let path2 = dir.path().join("mapped.exr");
    let chans2: Vec<OutChannel> = [
        "beauty.R", "beauty.G", "beauty.B", "depth.Z", "mv.X", "mv.Y",
    ]
    .iter()
    .zip(&vals)
    .map(|(n, v)| OutChannel {
        name: n,
        data: v,
        half: false,
    })
    .collect();
    write_channels(&path2, w, h, &chans2, None).unwrap();
    let mut opts = LayoutOptions::default();
    for m in [
        "color=beauty.R,beauty.G,beauty.B",
        "depth=depth.Z",
        "motion=mv.X,-mv.Y",
    ] {
        opts.mapping.add(m).unwrap();
    }
    let f = LoadedFrame::read(&path2, None, &opts).unwrap();
    assert_eq!(&f.color[..3], &[0.25, 1.25, 2.25]);
    assert_eq!(f.depth.as_ref().unwrap()[0], 3.25);
    assert_eq!(&f.motion.as_ref().unwrap()[..2], &[4.25, -5.25]);
}

#[test]
fn blender_multipart_round_trip() {
    let dir = tempfile::tempdir().unwrap();
    let (w, h) = (8, 6);
    let src = dir.path().join("shot.0001.exr");
    write_blender(&src, "Shot Layer", w, h, &camera());
    let opts = LayoutOptions {
        insert_index: Some(2),
        ..Default::default()
    };
    let mut f = LoadedFrame::read(&src, Some(1), &opts).unwrap();
    assert_eq!(
        f.layout.preset,
        LayoutPreset::Blender,
        "auto detects Blender"
    );
    assert_eq!(f.layout.view_layer.as_deref(), Some("Shot Layer"));
    assert!(
        (f.color[0] - 0.1).abs() < 1e-3 && (f.color[1] - 0.2).abs() < 1e-3,
        "color from the view layer, not Composite"
    );
    assert_eq!(
        f.depth.as_ref().unwrap()[0],
        1e10,
        "background depth stays very large"
    );
    assert_eq!(
        &f.motion.as_ref().unwrap()[..2],
        &[1.5, -2.5],
        "mv.y = -Vector.Y"
    );
    assert_eq!(&f.normal.as_ref().unwrap()[..3], &[0.0, 1.0, 0.0]);
    let mask = f.insert_mask.as_ref().unwrap();
    assert_eq!(
        (mask[0], mask[1], mask[3]),
        (1.0, 0.0, 1.0),
        "Object Index == 2"
    );
    assert_eq!(f.camera, Some(camera()));

    let out = dir.path().join("out.0001.exr");
    f.write_enhanced(&enhanced(w, h, 0.5), &out, &OutputMeta::default())
        .unwrap();
    let a = read_all(&src);
    let b = read_all(&out);
    assert_eq!(a.layer_data.len(), b.layer_data.len(), "every part kept");
    for (la, lb) in a.layer_data.iter().zip(&b.layer_data) {
        assert_eq!(la.attributes.layer_name, lb.attributes.layer_name);
        assert!(
            lb.attributes
                .other
                .contains_key(&exr::prelude::Text::from("cycles.samples")),
            "attributes kept"
        );
        let name = la.attributes.layer_name.as_ref().unwrap().to_string();
        for (ca, cb) in la.channel_data.list.iter().zip(&lb.channel_data.list) {
            assert_eq!(ca.name, cb.name);
            assert_eq!(
                std::mem::discriminant(&ca.sample_data),
                std::mem::discriminant(&cb.sample_data)
            );
            let replaced = name == "Shot Layer.Combined";
            let (va, vb) = (f32s(&ca.sample_data), f32s(&cb.sample_data));
            if replaced {
                let want = if cb.name.to_string().ends_with(".A") {
                    0.75
                } else {
                    0.5
                };
                assert!(vb.iter().all(|&v| v == want), "{} replaced", cb.name);
            } else {
                assert_eq!(va, vb, "{} unchanged", cb.name);
            }
        }
    }
    // An explicit --insert-index without an Object Index pass is an error naming the pass.
    let plain = dir.path().join("plain.exr");
    let ones = vec![1.0; w * h];
    write_channels(
        &plain,
        w,
        h,
        &[OutChannel {
            name: "R",
            data: &ones,
            half: false,
        }],
        None,
    )
    .unwrap();
    let e = LoadedFrame::read(
        &plain,
        Some(4),
        &LayoutOptions {
            preset: LayoutPreset::Blender,
            insert_index: Some(1),
            ..Default::default()
        },
    )
    .unwrap_err()
    .to_string();
    assert!(
        e.contains("plain.exr") && e.contains("frame 4") && e.contains("Object Index"),
        "{e}"
    );
}

/// Writing the same enhanced frame twice gives the same bytes (the exr
/// crate would write the attributes it does not know in hash-map order,
/// which changes between runs), compressed on one thread or on many, with
/// every header's attributes sorted by name, and the file still reads back
/// whole.
#[test]
fn enhanced_files_are_byte_identical_with_sorted_attributes() {
    let dir = tempfile::tempdir().unwrap();
    // Tall enough for several compressed blocks per part.
    let (w, h) = (8, 70);
    let src = dir.path().join("shot.0001.exr");
    write_blender(&src, "Shot Layer", w, h, &camera());
    let mut files = Vec::new();
    for k in 0..4 {
        let meta = OutputMeta {
            backend: "classical".into(),
            reset: "first_frame".into(),
            single_threaded: k % 2 == 1,
        };
        // A new read each time: new hash maps of attributes.
        let mut f = LoadedFrame::read(&src, Some(1), &LayoutOptions::default()).unwrap();
        let out = dir.path().join(format!("out{k}.0001.exr"));
        f.write_enhanced(&enhanced(w, h, 0.5), &out, &meta).unwrap();
        files.push(std::fs::read(&out).unwrap());
    }
    assert!(
        files.windows(2).all(|p| p[0] == p[1]),
        "same bytes every time"
    );
    // In each part's header the four attributes come in name order.
    let find = |from: usize, name: &str| {
        files[0][from..]
            .windows(name.len() + 1)
            .position(|w| w[..name.len()] == *name.as_bytes() && w[name.len()] == 0)
            .map(|i| from + i)
    };
    let names = [
        "harmonizer:backend",
        "harmonizer:frame",
        "harmonizer:reset",
        "harmonizer:version",
    ];
    let parts = read_all(&src).layer_data.len();
    assert!(parts > 1, "a multi-part file");
    let mut from = 0;
    for _ in 0..parts {
        let at: Vec<usize> = names.iter().map(|n| find(from, n).unwrap()).collect();
        assert!(at.windows(2).all(|p| p[0] < p[1]), "sorted: {at:?}");
        from = at[3] + 1;
    }
    assert_eq!(find(from, names[0]), None, "one set per part");
    let (a, b) = (read_all(&src), read_all(&dir.path().join("out0.0001.exr")));
    assert_eq!(a.layer_data.len(), b.layer_data.len());
    for (la, lb) in a.layer_data.iter().zip(&b.layer_data) {
        assert_eq!(la.attributes.layer_name, lb.attributes.layer_name);
        assert_eq!(la.channel_data.list.len(), lb.channel_data.list.len());
    }
    let mut junk = b"not an exr".to_vec();
    assert!(harmonizer_core::io::exr::sort_header_attributes(&mut junk).is_err());
    let mut cut = files[0][..40].to_vec();
    assert!(harmonizer_core::io::exr::sort_header_attributes(&mut cut).is_err());
}

#[test]
fn bad_inputs_name_file_frame_and_channel() {
    let dir = tempfile::tempdir().unwrap();
    let (w, h) = (6, 5);
    let ones = vec![1.0; w * h];
    // Missing channel: names the file, the frame, the channel and what was found.
    let p = dir.path().join("f.0003.exr");
    write_channels(
        &p,
        w,
        h,
        &[
            OutChannel {
                name: "R",
                data: &ones,
                half: false,
            },
            OutChannel {
                name: "G",
                data: &ones,
                half: false,
            },
        ],
        None,
    )
    .unwrap();
    let e = LoadedFrame::read(&p, Some(3), &LayoutOptions::default())
        .unwrap_err()
        .to_string();
    assert!(
        e.contains("frame 3")
            && e.contains("f.0003.exr")
            && e.contains("\"B\"")
            && e.contains("found: G, R"),
        "{e}"
    );
    // A mapped channel that does not exist.
    let mut opts = LayoutOptions::default();
    opts.mapping.add("depth=depth.Z").unwrap();
    let rgb = dir.path().join("rgb.0006.exr");
    let c = |name| OutChannel {
        name,
        data: &ones,
        half: false,
    };
    write_channels(&rgb, w, h, &[c("R"), c("G"), c("B")], None).unwrap();
    let e = LoadedFrame::read(&rgb, Some(6), &opts)
        .unwrap_err()
        .to_string();
    assert!(
        e.contains("frame 6") && e.contains("\"depth.Z\" (depth)") && e.contains("found: B, G, R"),
        "{e}"
    );
    // Truncated file.
    let t = dir.path().join("f.0004.exr");
    let mut bytes = std::fs::read(&p).unwrap();
    bytes.truncate(bytes.len() / 2);
    std::fs::write(&t, &bytes).unwrap();
    let e = LoadedFrame::read(&t, Some(4), &LayoutOptions::default())
        .unwrap_err()
        .to_string();
    assert!(
        e.contains("frame 4") && e.contains("f.0004.exr") && e.contains("truncated"),
        "{e}"
    );
    // Not an EXR at all.
    let g = dir.path().join("f.0005.exr");
    std::fs::write(&g, b"not an exr").unwrap();
    let e = LoadedFrame::read(&g, Some(5), &LayoutOptions::default())
        .unwrap_err()
        .to_string();
    assert!(
        e.contains("f.0005.exr") && e.contains("cannot read EXR"),
        "{e}"
    );
    // Missing file.
    let e = LoadedFrame::read(
        &dir.path().join("nope.exr"),
        Some(9),
        &LayoutOptions::default(),
    )
    .unwrap_err()
    .to_string();
    assert!(e.contains("frame 9") && e.contains("not found"), "{e}");
    // Bad pattern and bad range.
    let e = FramePattern::parse("shot.exr").unwrap_err().to_string();
    assert!(e.contains("shot.exr") && e.contains("frame token"), "{e}");
    let e = FrameRange::parse("9-2").unwrap_err().to_string();
    assert!(e.contains("9-2"), "{e}");
}

fn session(backend: &str) -> Session {
    let mut p = Params::default();
    p.set("backend", &ParamValue::Str(backend.into())).unwrap();
    Session::new(
        Device::new(DeviceOptions {
            threads: 2,
            ..Default::default()
        })
        .unwrap(),
        p,
    )
    .unwrap()
}

#[test]
fn runner_refuses_to_overwrite_inputs_and_names_size_changes() {
    let dir = tempfile::tempdir().unwrap();
    let seq = Sequence::generate(SynthConfig {
        width: 32,
        height: 18,
        frames: 3,
        seed: 3,
        first_frame: 1,
    })
    .unwrap();
    let (input, _truth) = seq.write_generic(dir.path(), "f.####.exr").unwrap();
    // Output equal to input (spelled differently) is refused before anything runs.
    let same = input.replace("####", "%04d");
    let opts = RunOptions {
        input: input.clone(),
        output: same,
        layout: LayoutOptions::default(),
        frames: None,
        preroll: 0,
    };
    let e = plan(&opts).unwrap_err().to_string();
    assert!(e.contains("frame 1") && e.contains("input file"), "{e}");
    let before = std::fs::read(FramePattern::parse(&input).unwrap().path(1)).unwrap();

    // A frame of another size stops the run at that frame; earlier outputs stay.
    let small = Sequence::generate(SynthConfig {
        width: 16,
        height: 9,
        frames: 1,
        seed: 3,
        first_frame: 3,
    })
    .unwrap();
    let p3 = FramePattern::parse(&input).unwrap().path(3);
    harmonizer_core::io::exr::write_generic(&p3, &small.frames[0].input).unwrap();
    let out = dir
        .path()
        .join("out")
        .join("o.####.exr")
        .to_string_lossy()
        .to_string();
    let opts = RunOptions {
        input: input.clone(),
        output: out.clone(),
        layout: LayoutOptions::default(),
        frames: None,
        preroll: 0,
    };
    let planned = plan(&opts).unwrap();
    let mut s = session("bypass");
    let mut seen = 0;
    let e = run_sequence(&mut s, &opts, &planned, false, &mut |_| {
        seen += 1;
        Ok(())
    })
    .unwrap_err()
    .to_string();
    assert!(
        e.contains("frame 3")
            && e.contains("16x9")
            && e.contains("32x18")
            && e.contains("f.0001.exr"),
        "{e}"
    );
    assert_eq!(seen, 2);
    let op = FramePattern::parse(&out).unwrap();
    assert!(op.path(1).is_file() && op.path(2).is_file() && !op.path(3).exists());
    assert_eq!(
        std::fs::read(FramePattern::parse(&input).unwrap().path(1)).unwrap(),
        before,
        "input untouched"
    );
}

#[test]
fn bypass_run_reproduces_the_input_color() {
    let dir = tempfile::tempdir().unwrap();
    let seq = Sequence::generate(SynthConfig {
        width: 40,
        height: 24,
        frames: 2,
        seed: 5,
        first_frame: 7,
    })
    .unwrap();
    let (input, _) = seq.write_generic(dir.path(), "f.####.exr").unwrap();
    let out = dir.path().join("o.####.exr").to_string_lossy().to_string();
    let opts = RunOptions {
        input,
        output: out.clone(),
        layout: LayoutOptions::default(),
        frames: Some(FrameRange::parse("7-8").unwrap()),
        preroll: 0,
    };
    let planned = plan(&opts).unwrap();
    let res = run_sequence(&mut session("bypass"), &opts, &planned, false, &mut |_| {
        Ok(())
    })
    .unwrap();
    assert_eq!(res.len(), 2);
    let f = ExrFile::open(&FramePattern::parse(&out).unwrap().path(8), Some(8)).unwrap();
    assert!(
        f.find("motion.X").is_some() && f.find("N.Z").is_some(),
        "AOV channels kept"
    );
    let back = LoadedFrame::read(
        &FramePattern::parse(&out).unwrap().path(8),
        Some(8),
        &LayoutOptions::default(),
    )
    .unwrap();
    let want: Vec<f32> = seq.frames[1]
        .input
        .color
        .chunks(4)
        .flat_map(|p| [p[0], p[1], p[2]])
        .collect();
    assert_eq!(
        back.color, want,
        "bypass output equals the input color, bit for bit"
    );
    assert_eq!(
        back.coverage.as_ref().unwrap(),
        &seq.frames[1].input.coverage
    );
}
