//! Open Image Denoise through `denoise::Oidn` and `denoise::Denoiser`, on
//! the real library (the `pyoidn` wheel in the project's `.venv`, which
//! `scripts/setup-venv.sh` installs): PSNR gains on a synthetic noisy HDR
//! frame with and without albedo and normal, filter reuse across sizes and
//! image sets, argument checks, library discovery errors, determinism.
//!
//! PSNR is measured on `x / (1 + x)` of each channel (peak 1), so the HDR
//! highlights count as a display would show them. Thresholds are stated at
//! each assertion; the measured values are printed (`--nocapture`).

use std::path::{Path, PathBuf};
use std::sync::{Arc, OnceLock};

use harmonizer_core::denoise::{self, DenoiseInput, DenoiseOptions, Denoiser, Oidn, Quality};
use harmonizer_core::Error;

/// The library and a 2-thread device shared by the tests; a missing
/// library fails the test (never skips).
fn oidn() -> Arc<Oidn> {
    static OIDN: OnceLock<std::result::Result<Arc<Oidn>, String>> = OnceLock::new();
    OIDN.get_or_init(|| Oidn::new(None, 2).map_err(|e| e.to_string()))
        .clone()
        .unwrap_or_else(|e| {
            panic!(
                "the denoise tests need Open Image Denoise: run scripts/setup-venv.sh in the repository root \
                 (it installs pyoidn into .venv) or set HARMONIZER_OIDN_LIB ({e})"
            )
        })
}

/// splitmix64: a small deterministic generator for the test images.
struct Rng(u64);

impl Rng {
    fn next(&mut self) -> u64 {
        self.0 = self.0.wrapping_add(0x9E37_79B9_7F4A_7C15);
        let mut z = self.0;
        z = (z ^ (z >> 30)).wrapping_mul(0xBF58_476D_1CE4_E5B9);
        z = (z ^ (z >> 27)).wrapping_mul(0x94D0_49BB_1331_11EB);
        z ^ (z >> 31)
    }
    /// Uniform in (0, 1].
    fn uniform(&mut self) -> f32 {
        ((self.next() >> 40) as f32 + 1.0) / (1u64 << 24) as f32
    }
    /// Like the mean of `spp` exponential samples: mean 1, deviation
    /// `1 / sqrt(spp)`, never negative (Monte Carlo noise of `spp` samples).
    fn mc(&mut self, spp: u32) -> f32 {
        (0..spp).map(|_| -self.uniform().ln()).sum::<f32>() / spp as f32
    }
}

/// A synthetic frame: the clean color, its noisy render (4 spp-like
/// multiplicative noise), clean and noisy albedo and normal.
struct Scene {
    w: usize,
    h: usize,
    clean: Vec<f32>,
    noisy: Vec<f32>,
    albedo: Vec<f32>,
    normal: Vec<f32>,
    noisy_albedo: Vec<f32>,
    noisy_normal: Vec<f32>,
}

fn scene(w: usize, h: usize, seed: u64) -> Scene {
    let mut rng = Rng(seed);
    let n = w * h * 3;
    let mut s = Scene {
        w,
        h,
        clean: Vec::with_capacity(n),
        noisy: Vec::with_capacity(n),
        albedo: Vec::with_capacity(n),
        normal: Vec::with_capacity(n),
        noisy_albedo: Vec::with_capacity(n),
        noisy_normal: Vec::with_capacity(n),
    };
    let tau = std::f32::consts::TAU;
    let light = {
        let l = [0.3f32, 0.5, 0.8];
        let len = (l[0] * l[0] + l[1] * l[1] + l[2] * l[2]).sqrt();
        l.map(|c| c / len)
    };
    for y in 0..h {
        for x in 0..w {
            let (u, v) = (x as f32 / w as f32, y as f32 / h as f32);
            // Tiles of two paints with a smooth variation: edges that the
            // albedo explains.
            let tile = ((x / 24) + (y / 24)) % 2 == 0;
            let paint = if tile {
                [0.8, 0.35, 0.2]
            } else {
                [0.2, 0.5, 0.85]
            };
            let vary = 0.8 + 0.2 * (tau * 2.0 * u).sin() * (tau * 1.5 * v).cos();
            let albedo = paint.map(|c| c * vary);
            // A bumpy surface.
            let nx = 0.35 * (tau * 3.0 * u).sin();
            let ny = 0.35 * (tau * 2.0 * v).cos();
            let nz = (1.0 - nx * nx - ny * ny).sqrt();
            let normal = [nx, ny, nz];
            let lambert =
                (normal[0] * light[0] + normal[1] * light[1] + normal[2] * light[2]).max(0.0);
            // HDR: a key light up to about 4 plus a dim fill.
            let shade = 0.15 + 3.0 * lambert * (1.0 + 0.5 * u);
            for c in 0..3 {
                let clean = albedo[c] * shade;
                s.clean.push(clean);
                s.noisy.push(clean * rng.mc(4));
                s.albedo.push(albedo[c]);
                s.normal.push(normal[c]);
                s.noisy_albedo.push((albedo[c] * rng.mc(16)).min(1.0));
                s.noisy_normal
                    .push(normal[c] + 0.15 * (rng.uniform() - 0.5));
            }
        }
    }
    s
}

fn psnr(a: &[f32], b: &[f32]) -> f64 {
    assert_eq!(a.len(), b.len());
    let tm = |x: f32| {
        let x = x.max(0.0) as f64;
        x / (1.0 + x)
    };
    let mse = a
        .iter()
        .zip(b)
        .map(|(&x, &y)| (tm(x) - tm(y)).powi(2))
        .sum::<f64>()
        / a.len() as f64;
    10.0 * (1.0 / mse).log10()
}

/// How `scene` is denoised: which auxiliary images and options.
#[derive(Clone, Copy, Debug)]
enum Aux {
    None,
    Clean,
    Noisy,
    /// The noisy albedo without a normal.
    NoisyAlbedo,
}

fn input<'a>(s: &'a Scene, aux: Aux) -> DenoiseInput<'a> {
    let (albedo, normal) = match aux {
        Aux::None => (None, None),
        Aux::Clean => (Some(&s.albedo[..]), Some(&s.normal[..])),
        Aux::Noisy => (Some(&s.noisy_albedo[..]), Some(&s.noisy_normal[..])),
        Aux::NoisyAlbedo => (Some(&s.noisy_albedo[..]), None),
    };
    DenoiseInput {
        width: s.w,
        height: s.h,
        color: &s.noisy,
        albedo,
        normal,
    }
}

fn run(d: &mut Denoiser, s: &Scene, aux: Aux, options: DenoiseOptions) -> Vec<f32> {
    let mut out = vec![0.0f32; s.w * s.h * 3];
    d.denoise(&input(s, aux), options, &mut out)
        .unwrap_or_else(|e| panic!("{}x{} {aux:?} {options:?}: {e}", s.w, s.h));
    out
}

fn options(quality: Quality, clean_aux: bool) -> DenoiseOptions {
    DenoiseOptions {
        hdr: true,
        quality,
        clean_aux,
        prefilter: true,
        max_memory_mb: None,
    }
}

/// Denoises `scene(256, 192)` and returns (noisy PSNR, denoised PSNR).
fn gain(aux: Aux, clean_aux: bool) -> (f64, f64) {
    let s = scene(256, 192, 1);
    let mut d = Denoiser::new(&oidn()).unwrap();
    let out = run(&mut d, &s, aux, options(Quality::Default, clean_aux));
    let before = psnr(&s.noisy, &s.clean);
    let after = psnr(&out, &s.clean);
    println!("denoise {aux:?} clean_aux={clean_aux}: PSNR {before:.2} -> {after:.2} dB");
    (before, after)
}

#[test]
fn a_noisy_hdr_frame_gains_at_least_10_db() {
    let (before, after) = gain(Aux::None, false);
    assert!(
        after - before >= 10.0,
        "PSNR {before:.2} -> {after:.2} dB (gain >= 10 dB)"
    );
}

#[test]
fn clean_albedo_and_normal_with_clean_aux_gain_more() {
    let (_, plain) = gain(Aux::None, false);
    let (before, after) = gain(Aux::Clean, true);
    assert!(
        after - before >= 10.0,
        "PSNR {before:.2} -> {after:.2} dB (gain >= 10 dB)"
    );
    // The albedo explains the tiles' edges: at least as good as color alone.
    assert!(
        after >= plain,
        "with clean aux {after:.2} dB, color alone {plain:.2} dB"
    );
}

#[test]
fn noisy_albedo_and_normal_are_prefiltered_without_clean_aux() {
    let (before, after) = gain(Aux::Noisy, false);
    assert!(
        after - before >= 10.0,
        "PSNR {before:.2} -> {after:.2} dB (gain >= 10 dB)"
    );
    // Taken as clean (`clean_aux` true), the same noisy images leave
    // residual noise: the prefilters are worth at least 2 dB here.
    let (_, unfiltered) = gain(Aux::Noisy, true);
    assert!(
        after >= unfiltered + 2.0,
        "noisy aux prefiltered {after:.2} dB, taken as clean {unfiltered:.2} dB (at least 2 dB better)"
    );
    // Clean images through the prefilters lose little against using them
    // as they are.
    let (_, direct) = gain(Aux::Clean, true);
    let (_, prefiltered) = gain(Aux::Clean, false);
    assert!(
        prefiltered >= direct - 1.0,
        "clean aux prefiltered {prefiltered:.2} dB, used as they are {direct:.2} dB (within 1 dB)"
    );
}

#[test]
fn a_denoiser_is_reused_across_sizes_image_sets_and_options() {
    // Each frame through one denoiser equals the same frame through a new
    // one, bit for bit: the kept filters are set up again when the size,
    // the images or the options change.
    let big = scene(256, 192, 2);
    let small = scene(160, 96, 3);
    let odd = scene(201, 77, 4);
    let steps: [(&Scene, Aux, DenoiseOptions); 8] = [
        (&big, Aux::None, options(Quality::Default, false)),
        (&small, Aux::None, options(Quality::Default, false)),
        (&small, Aux::Clean, options(Quality::Default, true)),
        (&small, Aux::Noisy, options(Quality::Default, false)),
        (&small, Aux::NoisyAlbedo, options(Quality::Default, false)),
        (&odd, Aux::Noisy, options(Quality::Balanced, false)),
        (&odd, Aux::Clean, options(Quality::Balanced, true)),
        (&big, Aux::None, options(Quality::High, false)),
    ];
    let mut reused = Denoiser::new(&oidn()).unwrap();
    for (i, (s, aux, opts)) in steps.into_iter().enumerate() {
        let kept = run(&mut reused, s, aux, opts);
        let fresh = run(&mut Denoiser::new(&oidn()).unwrap(), s, aux, opts);
        assert!(
            kept == fresh,
            "step {i}: {}x{} {aux:?} {opts:?}: the reused denoiser differs from a new one",
            s.w,
            s.h
        );
        let (before, after) = (psnr(&s.noisy, &s.clean), psnr(&kept, &s.clean));
        assert!(
            after - before >= 8.0,
            "step {i}: PSNR {before:.2} -> {after:.2} dB (gain >= 8 dB)"
        );
    }
}

#[test]
fn the_same_input_twice_gives_the_same_bytes() {
    let s = scene(192, 128, 5);
    for (aux, clean_aux) in [(Aux::None, false), (Aux::Noisy, false), (Aux::Clean, true)] {
        let mut d = Denoiser::new(&oidn()).unwrap();
        let opts = options(Quality::High, clean_aux);
        let a = run(&mut d, &s, aux, opts);
        let b = run(&mut d, &s, aux, opts);
        let bits = |v: &[f32]| v.iter().map(|x| x.to_bits()).collect::<Vec<_>>();
        assert_eq!(bits(&a), bits(&b), "{aux:?} clean_aux={clean_aux}");
    }
}

#[test]
fn wrong_sizes_and_lengths_are_refused_before_oidn_runs() {
    let s = scene(64, 32, 6);
    let mut d = Denoiser::new(&oidn()).unwrap();
    let n = 64 * 32 * 3;
    let mut out = vec![0.0f32; n];
    let opts = DenoiseOptions::default();
    let refused = |d: &mut Denoiser, input: DenoiseInput<'_>, out: &mut [f32], needles: &[&str]| {
        let e = d.denoise(&input, opts, out).unwrap_err();
        assert!(matches!(e, Error::Invalid(_)), "{e}");
        for needle in needles {
            assert!(
                e.to_string().contains(needle),
                "{needle:?} missing from: {e}"
            );
        }
    };
    let good = input(&s, Aux::Clean);
    refused(
        &mut d,
        DenoiseInput {
            color: &s.noisy[..n - 3],
            ..good
        },
        &mut out,
        &["color has 6141 values", "64x32", "6144"],
    );
    refused(&mut d, good, &mut out[..n - 1], &["output has 6143 values"]);
    refused(
        &mut d,
        good,
        &mut vec![0.0; n + 3],
        &["output has 6147 values"],
    );
    refused(
        &mut d,
        DenoiseInput {
            albedo: Some(&s.albedo[..3]),
            ..good
        },
        &mut out,
        &["albedo has 3 values"],
    );
    refused(
        &mut d,
        DenoiseInput {
            normal: Some(&s.normal[6..]),
            ..good
        },
        &mut out,
        &["normal has 6138 values"],
    );
    refused(
        &mut d,
        DenoiseInput {
            albedo: None,
            ..good
        },
        &mut out,
        &["normal image needs an albedo"],
    );
    for (w, h) in [(0, 0), (0, 32), (64, 0)] {
        refused(
            &mut d,
            DenoiseInput {
                width: w,
                height: h,
                ..good
            },
            &mut [],
            &["is empty", &format!("{w}x{h}")],
        );
    }
    for (w, h) in [(usize::MAX, 2), (1 << 40, 1 << 40), (usize::MAX / 3 + 1, 1)] {
        refused(
            &mut d,
            DenoiseInput {
                width: w,
                height: h,
                ..good
            },
            &mut out,
            &["too large", &format!("{w}x{h}")],
        );
    }
    // After the refusals the denoiser still works.
    let after = run(&mut d, &s, Aux::Clean, opts);
    assert!(psnr(&after, &s.clean) > psnr(&s.noisy, &s.clean) + 5.0);
    // Threads out of range are refused before any library is looked for.
    let e = Oidn::new(
        Some(Path::new("/nonexistent/libOpenImageDenoise.so.2")),
        1025,
    )
    .unwrap_err();
    assert!(
        matches!(e, Error::Invalid(_)) && e.to_string().contains("1025"),
        "{e}"
    );
}

#[test]
fn a_bad_library_path_is_an_error_naming_it() {
    let missing = PathBuf::from("/nonexistent/oidn/libOpenImageDenoise.so.2");
    let e = Oidn::new(Some(&missing), 2).unwrap_err();
    let msg = e.to_string();
    assert!(matches!(e, Error::RuntimeMissing(_)), "{msg}");
    for needle in [
        "/nonexistent/oidn/libOpenImageDenoise.so.2",
        "does not exist",
        "pip install pyoidn",
        "scripts/setup-venv.sh",
        "HARMONIZER_OIDN_LIB",
    ] {
        assert!(msg.contains(needle), "{needle:?} missing from: {msg}");
    }
    assert_eq!(denoise::locate(Some(&missing)).unwrap_err(), e);
    // A file that is not a shared library: the loader's refusal, with the path.
    let dir = tempfile::tempdir().unwrap();
    let junk = dir.path().join("libOpenImageDenoise.so.2");
    std::fs::write(&junk, b"not a shared library").unwrap();
    let e = Oidn::new(Some(&junk), 2).unwrap_err();
    let msg = e.to_string();
    assert!(matches!(e, Error::RuntimeMissing(_)), "{msg}");
    for needle in [
        &junk.display().to_string()[..],
        "cannot load",
        "HARMONIZER_OIDN_LIB",
    ] {
        assert!(msg.contains(needle), "{needle:?} missing from: {msg}");
    }
}

#[test]
fn the_wheel_library_loads_by_absolute_path_with_its_cpu_device() {
    // The library the tests use is the wheel's, found in a `.venv*` above
    // the working directory; loading it by that absolute path finds its CPU
    // device module beside it (`Oidn::new` fails without one).
    let path = denoise::locate(None).unwrap();
    assert!(path.is_absolute(), "{}", path.display());
    let text = path.display().to_string();
    assert!(
        text.contains("/.venv") && text.contains("/pyoidn/oidn/lib/libOpenImageDenoise.so"),
        "{text}"
    );
    let real = path.canonicalize().unwrap();
    let one = Oidn::new(Some(&path), 1).unwrap();
    assert_eq!(one.library(), real);
    assert_eq!(one.threads(), 1);
    assert!(one.version().starts_with("2."), "{}", one.version());
    // The shared device: the same library (loaded once per process).
    assert_eq!(oidn().library(), real);
    // And it denoises.
    let s = scene(96, 64, 7);
    let out = run(
        &mut Denoiser::new(&one).unwrap(),
        &s,
        Aux::None,
        options(Quality::Default, false),
    );
    assert!(psnr(&out, &s.clean) > psnr(&s.noisy, &s.clean) + 5.0);
    // A symbolic link elsewhere is loaded as the file it points to: the
    // loader's `$ORIGIN` and OIDN's search for its device modules start
    // from the directory a library was opened in. (Here the library is
    // already loaded; `Oidn::library` shows the resolved path.)
    let dir = tempfile::tempdir().unwrap();
    let link = dir.path().join("libOpenImageDenoise.so.2");
    std::os::unix::fs::symlink(&path, &link).unwrap();
    let linked = Oidn::new(Some(&link), 1).unwrap();
    assert_eq!(linked.library(), real);
}

/// This process's CPU time (user + system) from `/proc/self/stat`, in
/// seconds (clock ticks of 1/100 s).
fn cpu_seconds() -> f64 {
    let stat = std::fs::read_to_string("/proc/self/stat").unwrap();
    // The fields after the command name (which is in parentheses).
    let rest = &stat[stat.rfind(')').unwrap() + 2..];
    let f: Vec<&str> = rest.split(' ').collect();
    // utime and stime are fields 14 and 15 of the line, 12 and 13 here.
    (f[11].parse::<f64>().unwrap() + f[12].parse::<f64>().unwrap()) / 100.0
}

/// The time of one 1024x576 denoise (HDR; color alone, with clean
/// albedo and normal, with noisy ones prefiltered) at `High` and
/// `Balanced` on 2 threads: the first call (with the filters' setup) and
/// the mean of the next three, wall clock and the process's CPU time.
/// Prints, asserts nothing about time. Run alone: `cargo test -p
/// harmonizer-core --test core denoise::timing -- --ignored --nocapture
/// --test-threads=1`.
#[test]
#[ignore = "a measurement: run it alone, see the doc comment"]
fn timing_1024x576_high_and_balanced_on_2_threads() {
    let oidn = Oidn::new(None, 2).unwrap();
    let s = scene(1024, 576, 8);
    println!(
        "Open Image Denoise {} from {}",
        oidn.version(),
        oidn.library().display()
    );
    for (aux, clean_aux) in [(Aux::None, false), (Aux::Clean, true), (Aux::Noisy, false)] {
        for quality in [Quality::High, Quality::Balanced] {
            let mut d = Denoiser::new(&oidn).unwrap();
            let opts = options(quality, clean_aux);
            let (t, c) = (std::time::Instant::now(), cpu_seconds());
            let out = run(&mut d, &s, aux, opts);
            let (first, first_cpu) = (t.elapsed().as_secs_f64(), cpu_seconds() - c);
            let (t, c) = (std::time::Instant::now(), cpu_seconds());
            for _ in 0..3 {
                run(&mut d, &s, aux, opts);
            }
            let (next, next_cpu) = (t.elapsed().as_secs_f64() / 3.0, (cpu_seconds() - c) / 3.0);
            println!(
                "1024x576 {quality:?} {aux:?} clean_aux={clean_aux}: first {:.0} ms (cpu {:.0} ms), then {:.0} ms \
                 (cpu {:.0} ms); PSNR {:.2} -> {:.2} dB",
                first * 1e3,
                first_cpu * 1e3,
                next * 1e3,
                next_cpu * 1e3,
                psnr(&s.noisy, &s.clean),
                psnr(&out, &s.clean)
            );
        }
    }
}
