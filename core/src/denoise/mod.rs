//! Denoising with Intel Open Image Denoise (OIDN), loaded at run time.
//!
//! [`Oidn`] is the library and one CPU device; a [`Denoiser`] owns OIDN
//! `RT` filters and denoises interleaved RGB f32 frames, with optional
//! albedo and normal images, reusing its filters from frame to frame
//! (creating and committing a filter is expensive; OIDN re-initializes a
//! committed filter only when the frame size, the set of images or an
//! option changes).
//!
//! **Finding the library** ([`locate`]), as for ONNX Runtime: the explicit
//! path, else `HARMONIZER_OIDN_LIB`, else the `pyoidn` wheel in a virtual
//! environment `.venv*` found walking up from the current directory and
//! from the executable's directory
//! (`.venv*/lib/python3*/site-packages/pyoidn/oidn/lib/libOpenImageDenoise.so*`;
//! `scripts/setup-venv.sh` installs it into `.venv`), else the system's
//! `libOpenImageDenoise.so.2`. The library finds its CPU device module
//! (`libOpenImageDenoise_device_cpu.so.*`) in its own directory, so loading
//! the wheel's copy by absolute path works. A library is loaded once per
//! process and never unloaded.
//!
//! The C calls live in `oidn.rs`, the crate's only `unsafe` code. The
//! session's denoise stage (`stage.rs`) and the noise estimate that
//! `denoise auto` decides on ([`noise_level`], `detect.rs`) build on them.

pub mod accumulate;
mod detect;
#[allow(unsafe_code)]
mod oidn;
pub(crate) mod stage;

pub use detect::{noise_level, NOISE_THRESHOLD};

use std::path::{Path, PathBuf};
use std::sync::Arc;

pub use oidn::Oidn;
use oidn::{Filter, Slot};

use crate::error::{Error, Result};

/// The `pyoidn` release whose library this build is made for (OIDN 2.x).
pub const OIDN_REQUIREMENT: &str = "pyoidn==2.*";

/// The environment variable naming the library's path.
pub const LIBRARY_ENV: &str = "HARMONIZER_OIDN_LIB";

/// The library's name for the system's loader (the last place searched).
pub const SYSTEM_LIBRARY: &str = "libOpenImageDenoise.so.2";

/// The install hint every missing-library error carries.
pub fn install_hint() -> String {
    format!(
        "install it with `.venv/bin/python -m pip install {OIDN_REQUIREMENT}` (or run scripts/setup-venv.sh \
         in the harmonizer checkout) or set {LIBRARY_ENV}=<site-packages>/pyoidn/oidn/lib/libOpenImageDenoise.so.2 \
         (or pass the library path)"
    )
}

/// A library to load and where its path came from.
struct Candidate {
    path: PathBuf,
    from: String,
}

/// Finds `libOpenImageDenoise.so*` of the `pyoidn` wheel in a virtual
/// environment `.venv*` in `start` or any of its ancestors: `.venv` first,
/// then the others by name.
pub fn find_in_venv(start: &Path) -> Option<PathBuf> {
    for dir in start.ancestors() {
        let Ok(entries) = std::fs::read_dir(dir) else {
            continue;
        };
        let mut venvs: Vec<PathBuf> = entries
            .flatten()
            .filter(|e| e.file_name().to_string_lossy().starts_with(".venv"))
            .map(|e| e.path())
            .collect();
        // `.venv` sorts before `.venv-*`.
        venvs.sort();
        for venv in venvs {
            if let Some(p) = find_in_one_venv(&venv) {
                return Some(p);
            }
        }
    }
    None
}

fn find_in_one_venv(venv: &Path) -> Option<PathBuf> {
    crate::device::wheel_library(venv, "pyoidn/oidn/lib", "libOpenImageDenoise.so")
}

fn candidate(explicit: Option<&Path>) -> Result<Candidate> {
    let given = [
        (explicit.map(Path::to_path_buf), "the library path given"),
        (crate::device::env_path(LIBRARY_ENV), LIBRARY_ENV),
    ];
    for (path, from) in given {
        if let Some(path) = path {
            if !path.is_file() {
                return Err(Error::RuntimeMissing(format!(
                    "Open Image Denoise: {} (from {from}) does not exist; {}",
                    path.display(),
                    install_hint()
                )));
            }
            return Ok(Candidate {
                path,
                from: from.into(),
            });
        }
    }
    let starts = crate::device::search_starts();
    for s in &starts {
        if let Some(path) = find_in_venv(s) {
            return Ok(Candidate {
                path,
                from: format!("the pyoidn wheel in a .venv above {}", s.display()),
            });
        }
    }
    Ok(Candidate {
        path: PathBuf::from(SYSTEM_LIBRARY),
        from: format!(
            "the system's library path, after no library path given, no {LIBRARY_ENV} and no .venv* with \
             pyoidn above {}",
            starts
                .iter()
                .map(|p| p.display().to_string())
                .collect::<Vec<_>>()
                .join(" or ")
        ),
    })
}

/// The library [`Oidn::new`] would load, without loading it: the explicit
/// path, `HARMONIZER_OIDN_LIB`, the `pyoidn` wheel in a `.venv*`, else the
/// bare name [`SYSTEM_LIBRARY`] for the system's loader. An explicit path
/// or `HARMONIZER_OIDN_LIB` naming no file is [`Error::RuntimeMissing`].
pub fn locate(explicit: Option<&Path>) -> Result<PathBuf> {
    candidate(explicit).map(|c| c.path)
}

impl Oidn {
    /// Loads Open Image Denoise (found as [`locate`] says) and creates a
    /// committed CPU device with `threads` worker threads (0: one per
    /// core; threads are not pinned).
    ///
    /// Errors: [`Error::RuntimeMissing`] when the library cannot be found
    /// or loaded, or has no CPU device module, naming the path and where
    /// it came from, with the install hint; [`Error::NotSupported`] for a
    /// library other than 2.x or a CPU OIDN does not support;
    /// [`Error::Invalid`] for `threads` over 1024.
    pub fn new(library: Option<&Path>, threads: usize) -> Result<Arc<Oidn>> {
        if threads > 1024 {
            return Err(Error::invalid(format!(
                "threads: {threads} is out of range 0..=1024"
            )));
        }
        let threads = if threads == 0 {
            std::thread::available_parallelism()
                .map(|n| n.get())
                .unwrap_or(1)
        } else {
            threads
        };
        let c = candidate(library)?;
        Oidn::open(&c.path, &c.from, threads, &install_hint()).map(Arc::new)
    }
}

/// OIDN's `quality` setting.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Hash, Default)]
pub enum Quality {
    /// The library's default (high for the RT filter).
    #[default]
    Default,
    /// Fastest, for interactive previews.
    Fast,
    /// Balanced quality and speed, for interactive rendering.
    Balanced,
    /// Highest quality, for final frames.
    High,
}

impl Quality {
    /// `OIDN_QUALITY_*`.
    fn value(self) -> i32 {
        match self {
            Quality::Default => 0,
            Quality::Fast => 4,
            Quality::Balanced => 5,
            Quality::High => 6,
        }
    }
}

/// How to denoise.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Hash)]
pub struct DenoiseOptions {
    /// The color is high dynamic range (scene-linear radiance, the
    /// project's convention); false for display values in [0, 1].
    pub hdr: bool,
    /// OIDN's quality setting.
    pub quality: Quality,
    /// The albedo and normal are noise-free (OIDN's `cleanAux`).
    pub clean_aux: bool,
    /// Read with `clean_aux` false. True: denoise the albedo and normal
    /// first (each by its own RT filter into a scratch buffer) and filter
    /// the color with the clean images, as OIDN's documentation recommends
    /// for noisy auxiliary images (three filter runs). False: one run with
    /// `cleanAux` off (OIDN's filter then allows for the noise of the
    /// auxiliary images itself, a little less sharply).
    pub prefilter: bool,
    /// OIDN's `maxMemoryMB` for each filter: it keeps its working memory
    /// under this many MiB by processing smaller tiles (slower, and not
    /// guaranteed); `None`: no limit (OIDN's default).
    pub max_memory_mb: Option<u32>,
}

impl Default for DenoiseOptions {
    /// HDR, default quality, auxiliary images taken as noisy.
    fn default() -> Self {
        DenoiseOptions {
            hdr: true,
            quality: Quality::Default,
            clean_aux: false,
            prefilter: true,
            max_memory_mb: None,
        }
    }
}

/// One frame to denoise: interleaved RGB f32 images of `width` x `height`
/// pixels, rows top to bottom, `width * height * 3` values each.
#[derive(Debug, Clone, Copy)]
pub struct DenoiseInput<'a> {
    /// Width in pixels.
    pub width: usize,
    /// Height in pixels.
    pub height: usize,
    /// The noisy color.
    pub color: &'a [f32],
    /// The albedo (reflectance, [0, 1]), optional.
    pub albedo: Option<&'a [f32]>,
    /// The shading normal ([-1, 1], any space), optional; needs `albedo`.
    pub normal: Option<&'a [f32]>,
}

/// What the filters were last set up for.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
struct Setup {
    width: usize,
    height: usize,
    albedo: bool,
    normal: bool,
    options: DenoiseOptions,
}

/// Denoises frames with OIDN's `RT` filter, keeping its filters (and their
/// committed state) from one frame to the next.
///
/// `Send` and `Sync` (through its parts): filters may move between
/// threads, and every call into OIDN takes `&mut self`.
pub struct Denoiser {
    oidn: Arc<Oidn>,
    main: Filter,
    /// Prefilters of the albedo and the normal (`clean_aux` false).
    prefilters: [Option<Filter>; 2],
    /// The prefiltered albedo and normal.
    scratch: [Vec<f32>; 2],
    setup: Option<Setup>,
}

impl std::fmt::Debug for Denoiser {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.debug_struct("Denoiser")
            .field("oidn", &self.oidn)
            .field("setup", &self.setup)
            .finish_non_exhaustive()
    }
}

impl Denoiser {
    /// A denoiser on `oidn`'s device.
    pub fn new(oidn: &Arc<Oidn>) -> Result<Denoiser> {
        Ok(Denoiser {
            oidn: oidn.clone(),
            main: Filter::new(oidn)?,
            prefilters: [None, None],
            scratch: [Vec::new(), Vec::new()],
            setup: None,
        })
    }

    /// The library and device this denoiser runs on.
    pub fn oidn(&self) -> &Arc<Oidn> {
        &self.oidn
    }

    /// Denoises `input.color` into `output` (`width * height * 3` values).
    ///
    /// Sizes and slice lengths are checked before anything runs
    /// ([`Error::Invalid`] naming the image, the length seen and the one
    /// expected; a normal without an albedo is refused, as OIDN does). An
    /// error from OIDN names its step; after one, `output` may be partly
    /// written. The same input with the same options gives the same bits.
    pub fn denoise(
        &mut self,
        input: &DenoiseInput<'_>,
        options: DenoiseOptions,
        output: &mut [f32],
    ) -> Result<()> {
        let (width, height) = (input.width, input.height);
        let values = check_size(width, height)?;
        check_len("color", input.color.len(), values, width, height)?;
        check_len("output", output.len(), values, width, height)?;
        if let Some(a) = input.albedo {
            check_len("albedo", a.len(), values, width, height)?;
        }
        if let Some(n) = input.normal {
            check_len("normal", n.len(), values, width, height)?;
            if input.albedo.is_none() {
                return Err(Error::invalid(
                    "denoise: a normal image needs an albedo image too (OIDN's RT filter takes color, \
                     color + albedo, or color + albedo + normal)",
                ));
            }
        }

        let aux = [input.albedo, input.normal];
        let prefilter = !options.clean_aux && options.prefilter && input.albedo.is_some();
        let setup = Setup {
            width,
            height,
            albedo: input.albedo.is_some(),
            normal: input.normal.is_some(),
            options,
        };
        if self.setup != Some(setup) {
            // Parameters are set only when they change: OIDN re-initializes
            // a filter at commit when a parameter's value, the image size or
            // the set of images changed, never for new image pointers.
            self.setup = None;
            self.main.set_bool(c"hdr", options.hdr);
            self.main.set_int(c"quality", options.quality.value());
            let max_mb = options
                .max_memory_mb
                .map_or(-1, |m| i32::try_from(m).unwrap_or(i32::MAX));
            self.main.set_int(c"maxMemoryMB", max_mb);
            self.main.set_bool(
                c"cleanAux",
                setup.albedo && (options.clean_aux || prefilter),
            );
            for (i, data) in aux.iter().enumerate() {
                if prefilter && data.is_some() {
                    if self.prefilters[i].is_none() {
                        self.prefilters[i] = Some(Filter::new(&self.oidn)?);
                    }
                    if let Some(f) = self.prefilters[i].as_mut() {
                        f.set_int(c"quality", options.quality.value());
                        f.set_int(c"maxMemoryMB", max_mb);
                    }
                    self.scratch[i].resize(values, 0.0);
                } else {
                    self.prefilters[i] = None;
                    self.scratch[i] = Vec::new();
                }
            }
        }

        // With prefiltering, the main filter reads the cleaned images
        // (`cleanAux` is on whenever auxiliary images are given).
        let mut clean: [Option<&[f32]>; 2] = aux;
        if prefilter {
            let slots = [Slot::Albedo, Slot::Normal];
            for (i, data) in aux.iter().enumerate() {
                let (Some(data), Some(f)) = (data, self.prefilters[i].as_mut()) else {
                    continue;
                };
                let during = match slots[i] {
                    Slot::Albedo => "prefiltering the albedo",
                    _ => "prefiltering the normal",
                };
                f.run(
                    width,
                    height,
                    &[(slots[i], data)],
                    &mut self.scratch[i],
                    during,
                )?;
            }
            for (i, c) in clean.iter_mut().enumerate() {
                if c.is_some() {
                    *c = Some(&self.scratch[i]);
                }
            }
        }
        let mut images: Vec<(Slot, &[f32])> = vec![(Slot::Color, input.color)];
        if let Some(a) = clean[0] {
            images.push((Slot::Albedo, a));
        }
        if let Some(n) = clean[1] {
            images.push((Slot::Normal, n));
        }
        let result = self
            .main
            .run(width, height, &images, output, "denoising the color");
        // A failed frame sets everything up again next time.
        self.setup = result.as_ref().ok().map(|_| setup);
        result
    }
}

fn check_size(width: usize, height: usize) -> Result<usize> {
    if width == 0 || height == 0 {
        return Err(Error::invalid(format!(
            "denoise: frame size {width}x{height} is empty"
        )));
    }
    width
        .checked_mul(height)
        .and_then(|p| p.checked_mul(3))
        .filter(|&v| {
            v.checked_mul(std::mem::size_of::<f32>())
                .is_some_and(|b| b <= isize::MAX as usize)
        })
        .ok_or_else(|| Error::invalid(format!("denoise: frame size {width}x{height} is too large")))
}

fn check_len(name: &str, len: usize, values: usize, width: usize, height: usize) -> Result<()> {
    if len == values {
        return Ok(());
    }
    Err(Error::invalid(format!(
        "denoise: {name} has {len} values; a {width}x{height} RGB image needs {values}"
    )))
}
