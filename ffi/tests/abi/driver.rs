//! Loads the built cdylib with `libloading` and drives it through the C ABI
//! only (the struct definitions come from the crate, the functions from the
//! shared library).

use std::ffi::{c_char, c_void, CStr};
use std::path::PathBuf;
use std::ptr::{null, null_mut};

use harmonizer::device::{hz_device, hz_device_options};
use harmonizer::hz_status::{self, *};
use harmonizer::image::{hz_format, hz_image};
use harmonizer::run::{hz_run_options, HZ_RUN_HAS_FRAMES, HZ_RUN_HAS_INSERT_INDEX};
use harmonizer::session::{
    hz_frame, hz_report, hz_reset_reason, hz_session, HZ_FRAME_HAS_INDEX, HZ_FRAME_RESET,
};
use libloading::{Library, Symbol};

type Progress = Option<unsafe extern "C" fn(*mut c_void, f64) -> bool>;

/// The shared library cargo built for this test run: in `deps/` beside the
/// test binary (`cargo test`), or one level up after a `cargo build`.
fn lib_path() -> PathBuf {
    let exe = std::env::current_exe().unwrap();
    let deps = exe.parent().unwrap();
    let name = format!(
        "{}harmonizer{}",
        std::env::consts::DLL_PREFIX,
        std::env::consts::DLL_SUFFIX
    );
    let candidates = [deps.join(&name), deps.parent().unwrap().join(&name)];
    candidates
        .iter()
        .find(|p| p.is_file())
        .unwrap_or_else(|| panic!("libharmonizer not built: looked for {candidates:?}"))
        .clone()
}

struct Api {
    lib: Library,
}

macro_rules! sym {
    ($api:expr, $name:literal, $t:ty) => {{
        // SAFETY: the symbol has this signature in harmonizer.h.
        let s: Symbol<'_, $t> =
            unsafe { $api.lib.get(concat!($name, "\0").as_bytes()) }.expect($name);
        *s
    }};
}

impl Api {
    fn load() -> Api {
        // SAFETY: loading our own library runs no foreign initializers of note.
        let lib = unsafe { Library::new(lib_path()) }.expect("load libharmonizer");
        Api { lib }
    }
    fn last_error(&self) -> String {
        let f = sym!(
            self,
            "hz_last_error_message",
            unsafe extern "C" fn() -> *const c_char
        );
        // SAFETY: a NUL-terminated thread-local string.
        unsafe { CStr::from_ptr(f()) }
            .to_string_lossy()
            .into_owned()
    }
    fn device(&self, threads: u32) -> *mut hz_device {
        let new = sym!(
            self,
            "hz_device_new",
            unsafe extern "C" fn(u32, *const hz_device_options, *mut *mut hz_device) -> hz_status
        );
        let mut opts = zeroed_options();
        opts.threads = threads;
        let mut d = null_mut();
        // SAFETY: valid pointers.
        let st = unsafe { new(0, &opts, &mut d) };
        assert_eq!(st, HZ_OK, "{}", self.last_error());
        d
    }
    fn session(&self, d: *mut hz_device, backend: &CStr) -> *mut hz_session {
        self.session_with(d, backend, &[])
    }
    /// [`Api::session`] with boolean parameters set by name.
    fn session_with(
        &self,
        d: *mut hz_device,
        backend: &CStr,
        extra: &[(&CStr, bool)],
    ) -> *mut hz_session {
        let new = sym!(
            self,
            "hz_session_new",
            unsafe extern "C" fn(*const hz_device, *mut *mut hz_session) -> hz_status
        );
        let set = sym!(
            self,
            "hz_session_set_string",
            unsafe extern "C" fn(*mut hz_session, *const c_char, *const c_char) -> hz_status
        );
        let set_bool = sym!(
            self,
            "hz_session_set_bool",
            unsafe extern "C" fn(*mut hz_session, *const c_char, bool) -> hz_status
        );
        let commit = sym!(
            self,
            "hz_session_commit",
            unsafe extern "C" fn(*mut hz_session) -> hz_status
        );
        let mut s = null_mut();
        // SAFETY: valid pointers, NUL-terminated strings.
        unsafe {
            assert_eq!(new(d, &mut s), HZ_OK, "{}", self.last_error());
            assert_eq!(
                set(s, c"backend".as_ptr(), backend.as_ptr()),
                HZ_OK,
                "{}",
                self.last_error()
            );
            for (k, v) in extra {
                assert_eq!(set_bool(s, k.as_ptr(), *v), HZ_OK, "{}", self.last_error());
            }
            assert_eq!(commit(s), HZ_OK, "{}", self.last_error());
        }
        s
    }
    /// `hz_run_sequence`.
    ///
    /// # Safety
    /// `opts`' strings and arrays, and `user` for `on_frame`, are valid
    /// for the call.
    unsafe fn run_sequence(
        &self,
        s: *mut hz_session,
        opts: &hz_run_options,
        on_frame: RunFrameFn,
        user: *mut c_void,
    ) -> hz_status {
        let f = sym!(
            self,
            "hz_run_sequence",
            unsafe extern "C" fn(
                *mut hz_session,
                *const hz_run_options,
                RunFrameFn,
                *mut c_void,
            ) -> hz_status
        );
        // SAFETY: per this function's contract.
        unsafe { f(s, opts, on_frame, user) }
    }
    fn process(&self, s: *mut hz_session, frame: &hz_frame, out: &hz_image) -> hz_status {
        let f = sym!(
            self,
            "hz_session_process",
            unsafe extern "C" fn(*mut hz_session, *const hz_frame, *const hz_image) -> hz_status
        );
        // SAFETY: valid structs whose buffers outlive the call.
        unsafe { f(s, frame, out) }
    }
    /// Stages and commits string parameters.
    fn configure(&self, s: *mut hz_session, params: &[(&CStr, &CStr)]) {
        let set = sym!(
            self,
            "hz_session_set_string",
            unsafe extern "C" fn(*mut hz_session, *const c_char, *const c_char) -> hz_status
        );
        let commit = sym!(
            self,
            "hz_session_commit",
            unsafe extern "C" fn(*mut hz_session) -> hz_status
        );
        // SAFETY: a live session, NUL-terminated strings.
        unsafe {
            for (name, value) in params {
                assert_eq!(
                    set(s, name.as_ptr(), value.as_ptr()),
                    HZ_OK,
                    "{}",
                    self.last_error()
                );
            }
            assert_eq!(commit(s), HZ_OK, "{}", self.last_error());
        }
    }
    /// The last frame's report, asked with `struct_size = size`, into a
    /// buffer of `hz_report`'s size filled with 0xAB first.
    fn report_bytes(&self, s: *mut hz_session, size: usize) -> (hz_status, Vec<u8>) {
        let get = sym!(
            self,
            "hz_session_get_report",
            unsafe extern "C" fn(*const hz_session, *mut hz_report) -> hz_status
        );
        let mut buf = vec![0xABu8; std::mem::size_of::<hz_report>()];
        buf[..std::mem::size_of::<usize>()].copy_from_slice(&size.to_ne_bytes());
        // SAFETY: the buffer has hz_report's size; unaligned writes are
        // what the library does.
        let st = unsafe { get(s, buf.as_mut_ptr().cast()) };
        (st, buf)
    }
    fn report(&self, s: *mut hz_session) -> hz_report {
        let (st, buf) = self.report_bytes(s, std::mem::size_of::<hz_report>());
        assert_eq!(st, HZ_OK, "{}", self.last_error());
        // SAFETY: the library wrote a whole hz_report.
        unsafe { buf.as_ptr().cast::<hz_report>().read_unaligned() }
    }
    fn string(&self, s: *mut hz_session, name: &str) -> String {
        type StrFn =
            unsafe extern "C" fn(*const hz_session, *mut c_char, usize, *mut usize) -> hz_status;
        // SAFETY: every string query has this signature in harmonizer.h.
        let f: Symbol<'_, StrFn> =
            unsafe { self.lib.get(format!("{name}\0").as_bytes()) }.expect(name);
        let mut len = 0usize;
        // SAFETY: NULL buffer asks for the length.
        assert_eq!(
            unsafe { f(s, null_mut(), 0, &mut len) },
            HZ_OK,
            "{}",
            self.last_error()
        );
        let mut buf = vec![0 as c_char; len + 1];
        // SAFETY: a buffer of len + 1 bytes.
        assert_eq!(
            unsafe { f(s, buf.as_mut_ptr(), buf.len(), &mut len) },
            HZ_OK,
            "{}",
            self.last_error()
        );
        // SAFETY: NUL-terminated by the library.
        unsafe { CStr::from_ptr(buf.as_ptr()) }
            .to_str()
            .unwrap()
            .to_string()
    }
    fn set_progress(&self, s: *mut hz_session, cb: Progress, user: *mut c_void) {
        let f = sym!(
            self,
            "hz_session_set_progress_callback",
            unsafe extern "C" fn(*mut hz_session, Progress, *mut c_void) -> hz_status
        );
        // SAFETY: valid session; the callback outlives its use.
        assert_eq!(unsafe { f(s, cb, user) }, HZ_OK);
    }
    fn free(&self, s: *mut hz_session, d: *mut hz_device) {
        let fs = sym!(
            self,
            "hz_session_free",
            unsafe extern "C" fn(*mut hz_session) -> hz_status
        );
        let fd = sym!(
            self,
            "hz_device_free",
            unsafe extern "C" fn(*mut hz_device) -> hz_status
        );
        // SAFETY: live handles, freed once.
        unsafe {
            assert_eq!(fs(s), HZ_OK);
            assert_eq!(fd(d), HZ_OK);
        }
    }
}

fn zeroed_options() -> hz_device_options {
    hz_device_options {
        struct_size: std::mem::size_of::<hz_device_options>(),
        threads: 0,
        memory_limit: 0,
        ort_library: null(),
        model_path: null(),
        model_data: null(),
        model_data_size: 0,
        model_manifest: null(),
    }
}

fn image(data: &mut [f32], w: usize, h: usize, channels: u32, pixel_stride: usize) -> hz_image {
    hz_image {
        struct_size: std::mem::size_of::<hz_image>(),
        format: hz_format::HZ_FORMAT_F32 as u32,
        channels,
        width: w,
        height: h,
        offset: 0,
        pixel_stride,
        row_stride: 0,
        data: data.as_mut_ptr().cast(),
    }
}

fn frame(color: &hz_image, coverage: Option<&hz_image>, index: i64) -> hz_frame {
    hz_frame {
        struct_size: std::mem::size_of::<hz_frame>(),
        color,
        depth: null(),
        motion: null(),
        normal: null(),
        coverage: coverage.map_or(null(), |c| c as *const _),
        insert_mask: null(),
        world_to_camera: null(),
        world_to_ndc: null(),
        frame_index: index,
        flags: HZ_FRAME_HAS_INDEX,
        motion_vector_scale: [1.0, 1.0],
        albedo: null(),
        denoise_normal: null(),
        insert_id: null(),
    }
}

/// A deterministic RGBA frame (flickering gradient with a hole) and its coverage.
fn synth(w: usize, h: usize, t: i64) -> (Vec<f32>, Vec<f32>) {
    let mut rgba = vec![0.0f32; w * h * 4];
    let mut cov = vec![1.0f32; w * h];
    let flicker = 1.0 + 0.1 * ((t * 7919) % 5) as f32 / 5.0;
    for y in 0..h {
        for x in 0..w {
            let i = y * w + x;
            let hole = (w / 3..w / 2).contains(&x) && (h / 3..h / 2).contains(&y);
            let c = if hole { 0.0 } else { 1.0 };
            cov[i] = c;
            let base = [
                x as f32 / w as f32,
                y as f32 / h as f32,
                0.5 + 0.25 * ((x + t as usize) % 7) as f32 / 7.0,
            ];
            for k in 0..3 {
                rgba[i * 4 + k] = c * base[k] * flicker;
            }
            rgba[i * 4 + 3] = c;
        }
    }
    (rgba, cov)
}

#[test]
fn version_and_major_mismatch() {
    let api = Api::load();
    let version = sym!(api, "hz_version", unsafe extern "C" fn() -> *const c_char);
    // SAFETY: a static NUL-terminated string.
    assert_eq!(
        unsafe { CStr::from_ptr(version()) }.to_str().unwrap(),
        env!("CARGO_PKG_VERSION")
    );
    let check = sym!(
        api,
        "hz_check_version",
        unsafe extern "C" fn(u32, u32) -> hz_status
    );
    // SAFETY: plain values.
    unsafe {
        assert_eq!(check(0, 1), HZ_OK);
        assert_eq!(check(1, 0), HZ_ERROR_NOT_SUPPORTED);
        assert!(
            api.last_error().contains("major version 1"),
            "{}",
            api.last_error()
        );
        assert_eq!(check(0, 99), HZ_ERROR_NOT_SUPPORTED);
    }
    let new = sym!(
        api,
        "hz_device_new",
        unsafe extern "C" fn(u32, *const hz_device_options, *mut *mut hz_device) -> hz_status
    );
    let mut d: *mut hz_device = std::ptr::dangling_mut();
    // SAFETY: valid out pointer.
    assert_eq!(unsafe { new(7, null(), &mut d) }, HZ_ERROR_NOT_SUPPORTED);
    assert!(d.is_null(), "a failed create sets the handle to NULL");
    assert!(
        api.last_error().starts_with("hz_device_new:"),
        "{}",
        api.last_error()
    );
}

#[test]
fn sequence_in_place_and_strided_rgba() {
    let api = Api::load();
    let d = api.device(2);
    let (a, b) = (api.session(d, c"classical"), api.session(d, c"classical"));
    let (w, h) = (48, 32);
    for t in 0..6 {
        let (mut rgba, mut cov) = synth(w, h, t);
        let mut copy = rgba.clone();
        // Session a: RGBA buffer, color = first 3 channels at stride 16, output a new RGBA buffer.
        let color = image(&mut rgba, w, h, 3, 16);
        let coverage = image(&mut cov, w, h, 1, 0);
        let mut out = vec![-1.0f32; w * h * 4];
        let oimg = image(&mut out, w, h, 4, 0);
        assert_eq!(
            api.process(a, &frame(&color, Some(&coverage), t), &oimg),
            HZ_OK,
            "{}",
            api.last_error()
        );
        // Session b: the same frame enhanced in place (RGB of the same buffer).
        let color_b = image(&mut copy, w, h, 3, 16);
        assert_eq!(
            api.process(b, &frame(&color_b, Some(&coverage), t), &color_b),
            HZ_OK,
            "{}",
            api.last_error()
        );
        for i in 0..w * h {
            for k in 0..3 {
                assert_eq!(
                    out[i * 4 + k].to_bits(),
                    copy[i * 4 + k].to_bits(),
                    "pixel {i} channel {k}, frame {t}"
                );
            }
            // In place with 3 output channels leaves the 4th untouched.
            assert_eq!(copy[i * 4 + 3], rgba[i * 4 + 3]);
            assert!(out[i * 4 + 3] >= 0.0 && out[i * 4 + 3] <= 1.0);
        }
        // Holes are filled (coverage 1 in the output where the input had 0).
        let hole = (h / 3 + 1) * w + w / 3 + 1;
        assert_eq!(cov[hole], 0.0);
        assert!(out[hole * 4 + 3] > 0.99, "hole alpha {}", out[hole * 4 + 3]);
    }
    let get_report = sym!(
        api,
        "hz_session_get_report",
        unsafe extern "C" fn(*const hz_session, *mut hz_report) -> hz_status
    );
    // SAFETY: hz_report is plain data.
    let mut r: hz_report = unsafe { std::mem::zeroed() };
    r.struct_size = std::mem::size_of::<hz_report>();
    // SAFETY: valid pointers.
    assert_eq!(
        unsafe { get_report(a, &mut r) },
        HZ_OK,
        "{}",
        api.last_error()
    );
    assert_eq!((r.frame_index, r.has_frame_index), (5, true));
    assert_eq!(r.reset_reason, hz_reset_reason::HZ_RESET_NONE);
    assert!(r.history_used >= 1);
    let hist = sym!(
        api,
        "hz_session_get_history_length",
        unsafe extern "C" fn(*const hz_session, *mut usize) -> hz_status
    );
    let mut n = 0usize;
    // SAFETY: valid pointers.
    assert_eq!(unsafe { hist(a, &mut n) }, HZ_OK);
    assert_eq!(n, 4, "history holds context_frames = 4 frames");
    let json = sym!(
        api,
        "hz_session_get_report_json",
        unsafe extern "C" fn(*const hz_session, *mut c_char, usize, *mut usize) -> hz_status
    );
    let mut len = 0usize;
    // SAFETY: NULL buffer asks for the length.
    assert_eq!(unsafe { json(a, null_mut(), 0, &mut len) }, HZ_OK);
    let mut buf = vec![0 as c_char; len + 1];
    // SAFETY: a buffer of len + 1 bytes.
    assert_eq!(
        unsafe { json(a, buf.as_mut_ptr(), buf.len(), &mut len) },
        HZ_OK
    );
    // SAFETY: NUL-terminated by the library.
    let text = unsafe { CStr::from_ptr(buf.as_ptr()) }.to_str().unwrap();
    let v: serde_json::Value = serde_json::from_str(text).unwrap();
    assert_eq!(v["backend"], "classical");
    assert_eq!(v["frame_index"], 5);
    // Too small a buffer is refused and says how much is needed.
    // SAFETY: a 4-byte buffer.
    assert_eq!(
        unsafe { json(a, buf.as_mut_ptr(), 4, &mut len) },
        HZ_ERROR_INVALID_ARGUMENT
    );
    assert!(
        api.last_error().contains("too small"),
        "{}",
        api.last_error()
    );
    let fs = sym!(
        api,
        "hz_session_free",
        unsafe extern "C" fn(*mut hz_session) -> hz_status
    );
    // SAFETY: live handle.
    assert_eq!(unsafe { fs(b) }, HZ_OK);
    api.free(a, d);
}

struct CancelAt {
    calls: usize,
    cancel_at: usize,
}

unsafe extern "C" fn cancel_cb(user: *mut c_void, p: f64) -> bool {
    // SAFETY: `user` is the `CancelAt` the test registered.
    let c = unsafe { &mut *user.cast::<CancelAt>() };
    assert!((0.0..=1.0).contains(&p));
    c.calls += 1;
    c.calls < c.cancel_at
}

#[test]
fn cancel_leaves_state_unchanged() {
    let api = Api::load();
    let d = api.device(2);
    let (w, h) = (40, 24);
    // Find how many progress calls one frame makes.
    let probe = api.session(d, c"classical");
    let mut count = CancelAt {
        calls: 0,
        cancel_at: usize::MAX,
    };
    api.set_progress(probe, Some(cancel_cb), (&mut count as *mut CancelAt).cast());
    let (mut rgba, mut cov) = synth(w, h, 0);
    let mut out = vec![0.0f32; w * h * 4];
    {
        let (c, cv, o) = (
            image(&mut rgba, w, h, 4, 0),
            image(&mut cov, w, h, 1, 0),
            image(&mut out, w, h, 4, 0),
        );
        assert_eq!(api.process(probe, &frame(&c, Some(&cv), 0), &o), HZ_OK);
    }
    let total = count.calls;
    assert!(total >= 2, "progress called {total} times");
    for cancel_at in [1, total.div_ceil(2), total] {
        let reference = api.session(d, c"classical");
        let tested = api.session(d, c"classical");
        let mut outs = [vec![0.0f32; w * h * 4], vec![0.0f32; w * h * 4]];
        for t in 0..5 {
            let (mut rgba, mut cov) = synth(w, h, t);
            let (c, cv) = (image(&mut rgba, w, h, 4, 0), image(&mut cov, w, h, 1, 0));
            let f = frame(&c, Some(&cv), t);
            if t == 2 {
                // The cancelled call: its output buffer must stay untouched.
                let mut cancel = CancelAt {
                    calls: 0,
                    cancel_at,
                };
                api.set_progress(
                    tested,
                    Some(cancel_cb),
                    (&mut cancel as *mut CancelAt).cast(),
                );
                let mut sentinel = vec![7.0f32; w * h * 4];
                let o = image(&mut sentinel, w, h, 4, 0);
                assert_eq!(
                    api.process(tested, &f, &o),
                    HZ_ERROR_CANCELLED,
                    "cancel at call {cancel_at}"
                );
                assert!(
                    api.last_error().contains("cancelled"),
                    "{}",
                    api.last_error()
                );
                assert!(
                    sentinel.iter().all(|v| *v == 7.0),
                    "a cancelled call wrote its output"
                );
                api.set_progress(tested, None, null_mut());
            }
            for (k, s) in [reference, tested].into_iter().enumerate() {
                let o = image(&mut outs[k], w, h, 4, 0);
                assert_eq!(api.process(s, &f, &o), HZ_OK, "{}", api.last_error());
            }
            let same = outs[0]
                .iter()
                .zip(&outs[1])
                .all(|(a, b)| a.to_bits() == b.to_bits());
            assert!(
                same,
                "frame {t}: output differs after a cancel at progress call {cancel_at}"
            );
        }
        let fs = sym!(
            api,
            "hz_session_free",
            unsafe extern "C" fn(*mut hz_session) -> hz_status
        );
        // SAFETY: live handles.
        unsafe {
            fs(reference);
            fs(tested);
        }
    }
    api.free(probe, d);
}

#[test]
fn bad_input_is_refused_with_a_message() {
    let api = Api::load();
    let d = api.device(1);
    let s = api.session(d, c"bypass");
    let (w, h) = (8, 4);
    let (mut rgba, _) = synth(w, h, 0);
    let mut out = vec![0.0f32; w * h * 4];
    let c = image(&mut rgba, w, h, 4, 0);
    let o = image(&mut out, w, h, 4, 0);
    let f = frame(&c, None, 0);
    let expect = |st: hz_status, want: hz_status, text: &str| {
        assert_eq!(st, want, "{}", api.last_error());
        assert!(
            api.last_error().contains(text),
            "{:?} lacks {text:?}",
            api.last_error()
        );
    };
    let process = sym!(
        api,
        "hz_session_process",
        unsafe extern "C" fn(*mut hz_session, *const hz_frame, *const hz_image) -> hz_status
    );
    // SAFETY: NULL pointers are checked by the library.
    unsafe {
        expect(
            process(null_mut(), &f, &o),
            HZ_ERROR_INVALID_ARGUMENT,
            "session is NULL",
        );
        expect(
            process(s, null(), &o),
            HZ_ERROR_INVALID_ARGUMENT,
            "frame is NULL",
        );
        expect(
            process(s, &f, null()),
            HZ_ERROR_INVALID_ARGUMENT,
            "output is NULL",
        );
    }
    // Not a size any header gave (8 less is the size before `insert_id`).
    let mut bad = f;
    bad.struct_size -= 4;
    expect(
        api.process(s, &bad, &o),
        HZ_ERROR_INVALID_ARGUMENT,
        "hz_frame.struct_size",
    );
    let mut bad_img = c;
    bad_img.struct_size = 3;
    expect(
        api.process(s, &frame(&bad_img, None, 0), &o),
        HZ_ERROR_INVALID_ARGUMENT,
        "hz_image.struct_size is 3",
    );
    let mut zero = c;
    zero.width = 0;
    expect(
        api.process(s, &frame(&zero, None, 0), &o),
        HZ_ERROR_INVALID_ARGUMENT,
        "is empty",
    );
    let mut huge = c;
    huge.width = usize::MAX / 2;
    huge.height = 3;
    expect(
        api.process(s, &frame(&huge, None, 0), &o),
        HZ_ERROR_INVALID_ARGUMENT,
        "overflows",
    );
    let mut fmt = c;
    fmt.format = 9;
    expect(
        api.process(s, &frame(&fmt, None, 0), &o),
        HZ_ERROR_INVALID_ARGUMENT,
        "format 9",
    );
    let mut flags = f;
    flags.flags |= 0x100;
    expect(
        api.process(s, &flags, &o),
        HZ_ERROR_INVALID_ARGUMENT,
        "unknown bits",
    );
    let mut small_out = o;
    small_out.width = w - 1;
    expect(
        api.process(s, &f, &small_out),
        HZ_ERROR_INVALID_ARGUMENT,
        "differs from color",
    );
    let mut reset = f;
    reset.flags |= HZ_FRAME_RESET;
    assert_eq!(api.process(s, &reset, &o), HZ_OK, "{}", api.last_error());

    let set_int = sym!(
        api,
        "hz_session_set_int",
        unsafe extern "C" fn(*mut hz_session, *const c_char, i64) -> hz_status
    );
    // SAFETY: valid session, NUL-terminated names.
    unsafe {
        expect(
            set_int(s, c"context_frames".as_ptr(), 99),
            HZ_ERROR_INVALID_ARGUMENT,
            "99",
        );
        expect(
            set_int(s, c"no_such".as_ptr(), 1),
            HZ_ERROR_INVALID_ARGUMENT,
            "no_such",
        );
        expect(
            set_int(s, null(), 1),
            HZ_ERROR_INVALID_ARGUMENT,
            "name is NULL",
        );
        assert_eq!(set_int(s, c"context_frames".as_ptr(), 2), HZ_OK);
    }
    expect(
        api.process(s, &f, &o),
        HZ_ERROR_INVALID_OPERATION,
        "hz_session_commit",
    );
    api.free(s, d);
}

/// `hz_frame` as the headers before `albedo` and `denoise_normal` declared
/// it: what a host built against them passes.
#[repr(C)]
#[allow(non_camel_case_types, dead_code)]
struct hz_frame_0_1_0 {
    struct_size: usize,
    color: *const hz_image,
    depth: *const hz_image,
    motion: *const hz_image,
    normal: *const hz_image,
    coverage: *const hz_image,
    insert_mask: *const hz_image,
    world_to_camera: *const f32,
    world_to_ndc: *const f32,
    frame_index: i64,
    flags: u32,
    motion_vector_scale: [f32; 2],
}

/// `hz_frame` as the headers before `insert_id` declared it.
#[repr(C)]
#[allow(non_camel_case_types, dead_code)]
struct hz_frame_0_2_0 {
    old: hz_frame_0_1_0,
    albedo: *const hz_image,
    denoise_normal: *const hz_image,
}

/// `hz_report` as the headers before `denoised`, `has_noise_level` and
/// `noise_level` declared it.
#[repr(C)]
#[allow(non_camel_case_types, dead_code)]
struct hz_report_0_1_0 {
    struct_size: usize,
    frame_index: i64,
    has_frame_index: bool,
    reset_reason: hz_reset_reason,
    history_used: usize,
    sanitized: usize,
    warning_count: usize,
    total_ms: f64,
}

fn expect_error(api: &Api, st: hz_status, text: &str) {
    assert_eq!(st, HZ_ERROR_INVALID_ARGUMENT, "{}", api.last_error());
    assert!(
        api.last_error().contains(text),
        "{:?} lacks {text:?}",
        api.last_error()
    );
}

/// A host built against an older header passes the smaller `hz_frame`
/// and `hz_report`: the frame's appended fields read as NULL (here they
/// hold an albedo that would be refused, so reading it would fail the
/// call) and nothing of the report is written past the old size.
#[test]
fn older_struct_sizes_still_work() {
    let old_frame = std::mem::size_of::<hz_frame_0_1_0>();
    let old_report = std::mem::size_of::<hz_report_0_1_0>();
    assert!(old_frame < std::mem::size_of::<hz_frame>());
    assert!(old_report < std::mem::size_of::<hz_report>());
    let api = Api::load();
    let d = api.device(1);
    let s = api.session(d, c"bypass");
    let (w, h) = (16, 8);
    let (mut rgba, _) = synth(w, h, 0);
    let mut one = vec![0.5f32; w * h];
    let mut out = vec![0.0f32; w * h * 4];
    let c = image(&mut rgba, w, h, 4, 0);
    let bad_albedo = image(&mut one, w, h, 1, 0);
    let o = image(&mut out, w, h, 4, 0);
    let mut f = frame(&c, None, 3);
    f.albedo = &bad_albedo;
    f.denoise_normal = &bad_albedo;
    // This library's size reads the albedo and refuses it.
    expect_error(
        &api,
        api.process(s, &f, &o),
        "albedo: needs 3 channel(s), got 1",
    );
    f.struct_size = old_frame;
    assert_eq!(api.process(s, &f, &o), HZ_OK, "{}", api.last_error());
    f.struct_size = old_frame;
    for (i, (a, b)) in out
        .iter()
        .zip(&rgba)
        .enumerate()
        .filter(|(i, _)| i % 4 != 3)
    {
        assert_eq!(a.to_bits(), b.to_bits(), "bypass output sample {i}");
    }
    // Sizes between the two are refused, naming both.
    f.struct_size = old_frame + 8;
    expect_error(&api, api.process(s, &f, &o), "hz_frame.struct_size");
    assert!(
        api.last_error().contains(&old_frame.to_string())
            && api
                .last_error()
                .contains(&std::mem::size_of::<hz_frame>().to_string()),
        "{}",
        api.last_error()
    );

    let (st, bytes) = api.report_bytes(s, old_report);
    assert_eq!(st, HZ_OK, "{}", api.last_error());
    assert!(
        bytes[old_report..].iter().all(|b| *b == 0xAB),
        "written past the old hz_report: {:?}",
        &bytes[old_report..]
    );
    // SAFETY: the first old_report bytes hold an old hz_report.
    let r = unsafe { bytes.as_ptr().cast::<hz_report_0_1_0>().read_unaligned() };
    assert_eq!(
        (r.struct_size, r.frame_index, r.has_frame_index),
        (old_report, 3, true)
    );
    assert_eq!(r.reset_reason, hz_reset_reason::HZ_RESET_FIRST_FRAME);
    let (st, _) = api.report_bytes(s, old_report + 1);
    expect_error(&api, st, "hz_report.struct_size");
    let r = api.report(s);
    assert!(!r.denoised && !r.has_noise_level && r.noise_level == 0.0);
    // The sequence's first frame: the bypass backend decided no denoising.
    let decision = api.string(s, "hz_session_get_report_denoise_decision");
    assert!(
        decision.starts_with("denoise auto: off (backend bypass"),
        "{decision}"
    );
    // The header before `insert_id`: its fields are read, `insert_id` not
    // (here an id image that would be refused).
    let before_ids = std::mem::size_of::<hz_frame_0_2_0>();
    assert!(old_frame < before_ids && before_ids < std::mem::size_of::<hz_frame>());
    let mut small = vec![1.0f32; w * h];
    let bad_ids = image(&mut small, w / 2, h, 1, 0);
    f.insert_id = &bad_ids;
    f.frame_index = 4;
    f.struct_size = before_ids;
    expect_error(
        &api,
        api.process(s, &f, &o),
        "albedo: needs 3 channel(s), got 1",
    );
    f.albedo = null();
    f.denoise_normal = null();
    f.struct_size = std::mem::size_of::<hz_frame>();
    expect_error(
        &api,
        api.process(s, &f, &o),
        "insert_id: size 8x8 differs from color 16x8",
    );
    f.struct_size = before_ids;
    assert_eq!(api.process(s, &f, &o), HZ_OK, "{}", api.last_error());
    api.free(s, d);
}

/// `albedo` and `denoise_normal` are validated like the other images, and
/// the errors name the field.
#[test]
fn albedo_and_denoise_normal_are_validated() {
    let api = Api::load();
    let d = api.device(1);
    let s = api.session(d, c"bypass");
    let (w, h) = (16, 8);
    let (mut rgba, _) = synth(w, h, 0);
    let mut aux = vec![0.5f32; w * h * 3];
    let mut out = vec![0.0f32; w * h * 4];
    let c = image(&mut rgba, w, h, 4, 0);
    let o = image(&mut out, w, h, 4, 0);
    let good = image(&mut aux, w, h, 3, 0);
    let mut two = good;
    two.channels = 2;
    let mut small = good;
    small.width = w / 2;
    let mut no_data = good;
    no_data.data = null_mut();
    for field in ["albedo", "denoise_normal"] {
        let with = |img: &hz_image| {
            let mut f = frame(&c, None, 0);
            match field {
                "albedo" => f.albedo = img,
                _ => f.denoise_normal = img,
            }
            f
        };
        expect_error(
            &api,
            api.process(s, &with(&two), &o),
            &format!("{field}: needs 3 channel(s), got 2"),
        );
        expect_error(
            &api,
            api.process(s, &with(&small), &o),
            &format!("{field}: size 8x8 differs from color 16x8"),
        );
        expect_error(
            &api,
            api.process(s, &with(&no_data), &o),
            &format!("{field}: data is NULL"),
        );
        assert_eq!(
            api.process(s, &with(&good), &o),
            HZ_OK,
            "{}",
            api.last_error()
        );
    }
    api.free(s, d);
}

/// `insert_id` is validated like the other images (the errors name it),
/// its NaN samples are counted as AOV samples, and alone it makes the
/// insert mask (1 where the id is above 0): the classical backend then
/// harmonizes the objects it names.
#[test]
fn insert_id_is_validated_and_makes_the_mask() {
    let api = Api::load();
    let d = api.device(1);
    // The box's own filter (`match_tone`) is what its id changes.
    let s = api.session_with(d, c"classical", &[(c"match_tone", true)]);
    let (w, h) = (48, 32);
    let mut rgba = vec![0.0f32; w * h * 4];
    let mut ids = vec![0.0f32; w * h];
    let mut mask = vec![0.0f32; w * h];
    for y in 0..h {
        for x in 0..w {
            let i = y * w + x;
            // A grey ground, a box 8 times too bright on it (id 3).
            let inside = (16..32).contains(&x) && (8..24).contains(&y);
            let v = if inside { 4.0 } else { 0.5 };
            rgba[4 * i..4 * i + 4].copy_from_slice(&[v, v, v, 1.0]);
            ids[i] = if inside { 3.0 } else { 0.0 };
            mask[i] = if inside { 1.0 } else { 0.0 };
        }
    }
    ids[0] = f32::NAN;
    let mut out = vec![0.0f32; w * h * 4];
    let c = image(&mut rgba, w, h, 4, 0);
    let o = image(&mut out, w, h, 4, 0);
    let id_img = image(&mut ids, w, h, 1, 0);
    let mut no_channels = id_img;
    no_channels.channels = 0;
    let mut small = id_img;
    small.width = w / 2;
    let mut no_data = id_img;
    no_data.data = null_mut();
    let with = |img: &hz_image| {
        let mut f = frame(&c, None, 0);
        f.flags |= HZ_FRAME_RESET;
        f.insert_id = img;
        f
    };
    for (img, text) in [
        (&no_channels, "insert_id"),
        (&small, "insert_id: size 24x32 differs from color 48x32"),
        (&no_data, "insert_id: data is NULL"),
    ] {
        let st = api.process(s, &with(img), &o);
        assert_ne!(st, HZ_OK, "{text}");
        expect_error(&api, st, text);
    }
    assert_eq!(
        api.process(s, &with(&id_img), &o),
        HZ_OK,
        "{}",
        api.last_error()
    );
    let from_ids = out.clone();
    let warnings = api.report(s).warning_count;
    assert!(warnings >= 1, "the NaN id was not reported");
    // The box was darkened, as with the same mask given.
    let box_px = 4 * (16 * w + 24);
    assert!(from_ids[box_px] < 3.5, "{}", from_ids[box_px]);
    let m = image(&mut mask, w, h, 1, 0);
    let mut f = frame(&c, None, 0);
    f.flags |= HZ_FRAME_RESET;
    f.insert_mask = &m;
    assert_eq!(api.process(s, &f, &o), HZ_OK, "{}", api.last_error());
    assert_eq!(out, from_ids);
    api.free(s, d);
}

/// splitmix64, for the noisy frame.
struct Rng(u64);

impl Rng {
    fn uniform(&mut self) -> f32 {
        self.0 = self.0.wrapping_add(0x9E37_79B9_7F4A_7C15);
        let mut z = self.0;
        z = (z ^ (z >> 30)).wrapping_mul(0xBF58_476D_1CE4_E5B9);
        z = (z ^ (z >> 27)).wrapping_mul(0x94D0_49BB_1331_11EB);
        z ^= z >> 31;
        ((z >> 40) as f32 + 1.0) / (1u64 << 24) as f32
    }
}

/// A noisy render and what it should be: the clean RGB, the noisy RGB
/// (each pixel times the mean of 4 exponential samples: the Monte Carlo
/// noise of 4 samples per pixel, deviation 0.5 of the signal) and the
/// albedo (RGB in [0, 1]), all packed.
fn noisy_frame(w: usize, h: usize) -> (Vec<f32>, Vec<f32>, Vec<f32>) {
    let mut rng = Rng(7);
    let (mut clean, mut noisy, mut albedo) = (
        vec![0.0; w * h * 3],
        vec![0.0; w * h * 3],
        vec![0.0; w * h * 3],
    );
    for y in 0..h {
        for x in 0..w {
            let i = (y * w + x) * 3;
            let tile = ((x / 12 + y / 12) % 2) as f32;
            let a = [0.2 + 0.6 * tile, 0.5, 0.8 - 0.5 * tile];
            let light = 0.4 + 1.2 * x as f32 / w as f32;
            let n = (0..4).map(|_| -rng.uniform().ln()).sum::<f32>() / 4.0;
            for k in 0..3 {
                albedo[i + k] = a[k];
                clean[i + k] = a[k] * light;
                noisy[i + k] = a[k] * light * n;
            }
        }
    }
    (clean, noisy, albedo)
}

fn mse(a: &[f32], rgba: &[f32]) -> f64 {
    let n = a.len() / 3;
    (0..n)
        .flat_map(|i| (0..3).map(move |k| (i, k)))
        .map(|(i, k)| (a[i * 3 + k] as f64 - rgba[i * 4 + k] as f64).powi(2))
        .sum::<f64>()
        / (3 * n) as f64
}

/// With `denoise on` and an albedo, Open Image Denoise (the real library:
/// the `pyoidn` wheel in the repository's `.venv`, or
/// `HARMONIZER_OIDN_LIB`; missing, the test fails) denoises a noisy frame
/// through the C ABI, and the report says so; `denoise auto` measures the
/// noise (`noise_level`) and turns itself on.
#[test]
fn denoise_on_with_albedo() {
    let api = Api::load();
    let d = api.device(2);
    let (w, h) = (96, 64);
    let (clean, mut noisy, mut albedo) = noisy_frame(w, h);
    let c = image(&mut noisy, w, h, 3, 0);
    let a = image(&mut albedo, w, h, 3, 0);
    let mut out = vec![0.0f32; w * h * 4];
    let o = image(&mut out, w, h, 4, 0);
    let mut f = frame(&c, None, 1);
    f.albedo = &a;
    // Bypass with denoise on: the output is the denoised frame alone.
    let s = api.session(d, c"bypass");
    api.configure(s, &[(c"denoise", c"on")]);
    let st = api.process(s, &f, &o);
    assert_eq!(
        st,
        HZ_OK,
        "denoise on needs Open Image Denoise: run scripts/setup-venv.sh in the repository root \
         (it installs pyoidn into .venv) or set HARMONIZER_OIDN_LIB: {}",
        api.last_error()
    );
    let noisy_rgba: Vec<f32> = noisy
        .chunks(3)
        .flat_map(|p| [p[0], p[1], p[2], 1.0])
        .collect();
    let (before, after) = (mse(&clean, &noisy_rgba), mse(&clean, &out));
    println!("denoise on, albedo: MSE {before:.5} noisy, {after:.5} denoised");
    assert!(
        after < 0.1 * before,
        "denoising should cut the error at least tenfold: MSE {before} -> {after}"
    );
    let r = api.report(s);
    assert!(r.denoised, "the report says denoised");
    assert!(!r.has_noise_level, "denoise on measures no noise");
    assert_eq!(
        api.string(s, "hz_session_get_report_denoise_decision"),
        "denoise on"
    );
    let json: serde_json::Value =
        serde_json::from_str(&api.string(s, "hz_session_get_report_json")).unwrap();
    assert_eq!(json["denoised"], true);
    assert_eq!(json["denoise_decision"], "denoise on");
    assert!(json["noise_level"].is_null());
    // The next frame keeps the decision and reports none.
    f.frame_index = 2;
    assert_eq!(api.process(s, &f, &o), HZ_OK, "{}", api.last_error());
    let r = api.report(s);
    assert!(r.denoised);
    assert_eq!(api.string(s, "hz_session_get_report_denoise_decision"), "");

    // auto (samples 0) on the classical backend measures the noise.
    let auto = api.session(d, c"classical");
    f.frame_index = 1;
    assert_eq!(api.process(auto, &f, &o), HZ_OK, "{}", api.last_error());
    let r = api.report(auto);
    let decision = api.string(auto, "hz_session_get_report_denoise_decision");
    println!("denoise auto: {decision}");
    assert!(r.denoised && r.has_noise_level, "{decision}");
    assert!(r.noise_level > 0.2, "noise level {}", r.noise_level);
    assert!(
        decision.starts_with("denoise auto: on (noise level"),
        "{decision}"
    );
    let json: serde_json::Value =
        serde_json::from_str(&api.string(auto, "hz_session_get_report_json")).unwrap();
    assert_eq!(json["noise_level"].as_f64().unwrap() as f32, r.noise_level);
    let fs = sym!(
        api,
        "hz_session_free",
        unsafe extern "C" fn(*mut hz_session) -> hz_status
    );
    // SAFETY: a live handle.
    assert_eq!(unsafe { fs(auto) }, HZ_OK);
    api.free(s, d);
}

type RunFrameFn = Option<unsafe extern "C" fn(*mut c_void, *const c_char) -> bool>;

/// The frames' JSON the run callback received; stops the run (returns
/// false) once `stop_after` frames were seen.
struct Seen {
    frames: Vec<serde_json::Value>,
    stop_after: usize,
}

unsafe extern "C" fn on_run_frame(user: *mut c_void, json: *const c_char) -> bool {
    // SAFETY: `user` is the `Seen` the test passed; `json` a NUL-terminated string.
    let seen = unsafe { &mut *user.cast::<Seen>() };
    let text = unsafe { CStr::from_ptr(json) }.to_str().unwrap();
    seen.frames.push(serde_json::from_str(text).unwrap());
    seen.frames.len() < seen.stop_after
}

/// A fresh directory under the system's temporary one (removed at the end
/// of the test that made it).
struct TempDir(PathBuf);

impl TempDir {
    fn new(name: &str) -> TempDir {
        let d = std::env::temp_dir().join(format!("hz-abi-{name}-{}", std::process::id()));
        let _ = std::fs::remove_dir_all(&d);
        std::fs::create_dir_all(&d).unwrap();
        TempDir(d)
    }
}

impl Drop for TempDir {
    fn drop(&mut self) {
        let _ = std::fs::remove_dir_all(&self.0);
    }
}

/// The library's own runner (what `harmonize run` calls) with a classical
/// session of 2 threads: the bytes `hz_run_sequence` must match.
fn run_classical_directly(
    options: &harmonizer_core::io::run::RunOptions,
    extra: &[(&str, harmonizer_core::ParamValue)],
) {
    use harmonizer_core::io::run::{plan, run_sequence};
    let device = harmonizer_core::Device::new(harmonizer_core::DeviceOptions {
        threads: 2,
        ..Default::default()
    })
    .unwrap();
    let mut params = harmonizer_core::Params::default();
    params
        .set(
            "backend",
            &harmonizer_core::ParamValue::Str("classical".into()),
        )
        .unwrap();
    for (k, v) in extra {
        params.set(k, v).unwrap();
    }
    let mut session = harmonizer_core::Session::new(device, params).unwrap();
    let planned = plan(options).unwrap();
    run_sequence(&mut session, options, &planned, false, &mut |_| Ok(())).unwrap();
}

/// Issue 22: `hz_run_sequence` runs a chunk with its pre-roll from files,
/// writes only the chunk's frames, the same bytes as the library's own
/// runner (what `harmonize run --frames A-B --preroll N` calls) gives, and
/// reports each frame; the callback can stop it; a pre-roll without a
/// frame range is refused.
#[test]
fn run_sequence_writes_a_chunk_with_its_preroll() {
    use harmonizer_core::io::pattern::FramePattern;
    use harmonizer_core::io::run::RunOptions;
    use harmonizer_core::synth::{Sequence, SynthConfig};

    let dir = TempDir::new("run");
    let seq = Sequence::generate(SynthConfig {
        width: 48,
        height: 32,
        frames: 12,
        ..Default::default()
    })
    .unwrap();
    let (input, _) = seq.write_generic(&dir.0, "shot.####.exr").unwrap();
    let out = dir.0.join("abi").join("o.####.exr");
    let report = dir.0.join("report.json");
    let cstr = |s: &str| std::ffi::CString::new(s).unwrap();
    let (c_in, c_out, c_report) = (
        cstr(&input),
        cstr(out.to_str().unwrap()),
        cstr(report.to_str().unwrap()),
    );

    let api = Api::load();
    let d = api.device(2);
    let s = api.session(d, c"classical");
    let mut opts = hz_run_options {
        struct_size: std::mem::size_of::<hz_run_options>(),
        input: c_in.as_ptr(),
        output: c_out.as_ptr(),
        layout: null(),
        channels: null(),
        flags: HZ_RUN_HAS_FRAMES,
        frame_first: 8,
        frame_last: 12,
        preroll: 4,
        insert_index: 0,
        report: c_report.as_ptr(),
        insert_indices: null(),
        insert_index_count: 0,
    };
    let mut seen = Seen {
        frames: Vec::new(),
        stop_after: usize::MAX,
    };
    // SAFETY: valid options and callback; `seen` outlives the call.
    let st = unsafe {
        api.run_sequence(
            s,
            &opts,
            Some(on_run_frame),
            (&mut seen as *mut Seen).cast(),
        )
    };
    assert_eq!(st, HZ_OK, "{}", api.last_error());
    let pre: Vec<i64> = seen
        .frames
        .iter()
        .filter(|f| f["preroll"] == true)
        .map(|f| f["frame"].as_i64().unwrap())
        .collect();
    let written: Vec<i64> = seen
        .frames
        .iter()
        .filter(|f| f["preroll"] == false)
        .map(|f| f["frame"].as_i64().unwrap())
        .collect();
    assert_eq!(pre, [4, 5, 6, 7]);
    assert_eq!(written, [8, 9, 10, 11, 12]);
    let op = FramePattern::parse(out.to_str().unwrap()).unwrap();
    assert!(
        (1..=7).all(|n| !op.path(n).exists()),
        "pre-roll frames written"
    );
    let r: serde_json::Value =
        serde_json::from_str(&std::fs::read_to_string(&report).unwrap()).unwrap();
    assert_eq!(r["summary"]["frames"], 5);
    assert_eq!(r["summary"]["preroll_frames"], 4);
    // The session's report is the last frame's.
    assert_eq!(api.report(s).frame_index, 12);

    // The same chunk through the library's runner directly: the same bytes.
    let direct = dir.0.join("direct").join("o.####.exr");
    let options = RunOptions {
        input: input.clone(),
        output: direct.to_string_lossy().to_string(),
        layout: Default::default(),
        frames: Some(harmonizer_core::io::pattern::FrameRange::parse("8-12").unwrap()),
        preroll: 4,
    };
    run_classical_directly(&options, &[]);
    let dp = FramePattern::parse(&options.output).unwrap();
    for n in 8..=12 {
        assert_eq!(
            std::fs::read(op.path(n)).unwrap(),
            std::fs::read(dp.path(n)).unwrap(),
            "frame {n}"
        );
    }

    // The callback stops the run after the 2nd frame: cancelled, the
    // frames after it not written.
    let stopped = dir.0.join("stopped").join("o.####.exr");
    let c_stopped = cstr(stopped.to_str().unwrap());
    opts.output = c_stopped.as_ptr();
    opts.report = null();
    opts.preroll = 0;
    let mut seen = Seen {
        frames: Vec::new(),
        stop_after: 2,
    };
    // SAFETY: as above.
    let st = unsafe {
        api.run_sequence(
            s,
            &opts,
            Some(on_run_frame),
            (&mut seen as *mut Seen).cast(),
        )
    };
    assert_eq!(st, HZ_ERROR_CANCELLED, "{}", api.last_error());
    assert!(
        api.last_error().contains("after frame 9"),
        "{}",
        api.last_error()
    );
    let sp = FramePattern::parse(stopped.to_str().unwrap()).unwrap();
    assert!(sp.path(9).exists() && !sp.path(10).exists());

    // A pre-roll needs a frame range; a NULL input is named.
    opts.flags = 0;
    opts.preroll = 2;
    // SAFETY: as above, no callback.
    let st = unsafe { api.run_sequence(s, &opts, None, null_mut()) };
    expect_error(&api, st, "--preroll needs --frames");
    opts.input = null();
    // SAFETY: as above.
    let st = unsafe { api.run_sequence(s, &opts, None, null_mut()) };
    expect_error(&api, st, "options.input is NULL");
    api.free(s, d);
}

/// Issue 19: `hz_run_options.insert_indices` names several inserted
/// objects by their Object Index (`harmonize run --insert-index 3,5`): the
/// bytes the library's runner writes with those indices, which differ from
/// a run without them; a NULL array with a count, an index named twice and
/// 0 among several are refused by name; an older header's size (without the
/// array) still runs, as a single index.
#[test]
fn run_sequence_takes_several_insert_indices() {
    use harmonizer_core::io::exr::{write_channels, OutChannel};
    use harmonizer_core::io::layout::LayoutOptions;
    use harmonizer_core::io::pattern::FramePattern;
    use harmonizer_core::io::run::RunOptions;

    let (w, h) = (96usize, 64usize);
    // Two touching boxes on a textured ground: the left one too bright and
    // blue (Object Index 3), the right one the ground's color (5).
    let (rgb, _, index) = harmonizer_core::synth::touching_boxes(w, h);
    let ones = vec![1.0f32; w * h];
    let dir = TempDir::new("run-ids");
    let named: [(&str, &[f32]); 5] = [
        ("ViewLayer.Combined.R", &rgb[0]),
        ("ViewLayer.Combined.G", &rgb[1]),
        ("ViewLayer.Combined.B", &rgb[2]),
        ("ViewLayer.Combined.A", &ones),
        ("ViewLayer.Object Index.X", &index),
    ];
    let list = OutChannel::floats(&named);
    write_channels(&dir.0.join("layer.0001.exr"), w, h, &list, None).unwrap();
    let input = dir.0.join("layer.####.exr").to_string_lossy().to_string();
    let cstr = |s: &str| std::ffi::CString::new(s).unwrap();
    let c_in = cstr(&input);

    let api = Api::load();
    let d = api.device(2);
    let s = api.session_with(d, c"classical", &[(c"match_tone", true)]);
    let abi_out = dir.0.join("abi").join("o.####.exr");
    let c_out = cstr(abi_out.to_str().unwrap());
    let indices = [3i64, 5];
    let mut opts = hz_run_options {
        struct_size: std::mem::size_of::<hz_run_options>(),
        input: c_in.as_ptr(),
        output: c_out.as_ptr(),
        layout: c"blender".as_ptr(),
        channels: null(),
        flags: 0,
        frame_first: 0,
        frame_last: 0,
        preroll: 0,
        insert_index: 0,
        report: null(),
        insert_indices: indices.as_ptr(),
        insert_index_count: indices.len(),
    };
    // SAFETY: valid options; `indices` outlives the call.
    let st = unsafe { api.run_sequence(s, &opts, None, null_mut()) };
    assert_eq!(st, HZ_OK, "{}", api.last_error());

    // The library's runner directly, with and without the indices.
    let direct = |name: &str, insert_indices: Vec<i64>| -> Vec<u8> {
        let out = dir.0.join(name).join("o.####.exr");
        let options = RunOptions {
            input: input.clone(),
            output: out.to_string_lossy().to_string(),
            layout: LayoutOptions {
                preset: harmonizer_core::io::layout::LayoutPreset::parse("blender").unwrap(),
                insert_indices,
                ..Default::default()
            },
            frames: None,
            preroll: 0,
        };
        // The boxes' own filters (`match_tone`) are what the ids change.
        run_classical_directly(
            &options,
            &[("match_tone", harmonizer_core::ParamValue::Bool(true))],
        );
        std::fs::read(FramePattern::parse(&options.output).unwrap().path(1)).unwrap()
    };
    let got = std::fs::read(
        FramePattern::parse(abi_out.to_str().unwrap())
            .unwrap()
            .path(1),
    )
    .unwrap();
    assert!(
        got == direct("ids", vec![3, 5]),
        "not the runner's bytes with indices 3,5"
    );
    assert!(
        got != direct("none", Vec::new()),
        "the indices changed nothing (the test could not fail)"
    );

    // Refused by name, nothing written.
    let refused = dir.0.join("refused").join("o.####.exr");
    let c_refused = cstr(refused.to_str().unwrap());
    opts.output = c_refused.as_ptr();
    opts.insert_indices = null();
    // SAFETY: as above (the NULL array is what is tested).
    let st = unsafe { api.run_sequence(s, &opts, None, null_mut()) };
    expect_error(
        &api,
        st,
        "options.insert_indices is NULL with insert_index_count 2",
    );
    for (bad, want) in [
        ([3i64, 3], "3 is named twice"),
        ([3, 0], "0 is not above 0"),
    ] {
        opts.insert_indices = bad.as_ptr();
        // SAFETY: as above; `bad` outlives the call.
        let st = unsafe { api.run_sequence(s, &opts, None, null_mut()) };
        expect_error(&api, st, want);
        assert!(
            api.last_error().contains("options.insert_indices"),
            "{}",
            api.last_error()
        );
    }
    assert!(!refused.parent().unwrap().join("o.0001.exr").exists());

    // An older header's size: the array is not read (garbage there is
    // ignored), the single index is.
    let older = dir.0.join("older").join("o.####.exr");
    let c_older = cstr(older.to_str().unwrap());
    opts.output = c_older.as_ptr();
    opts.struct_size = std::mem::offset_of!(hz_run_options, insert_indices);
    opts.insert_indices = std::ptr::dangling::<i64>();
    opts.insert_index_count = 7;
    opts.insert_index = 3;
    opts.flags = HZ_RUN_HAS_INSERT_INDEX;
    // SAFETY: the library reads only the older header's fields.
    let st = unsafe { api.run_sequence(s, &opts, None, null_mut()) };
    assert_eq!(st, HZ_OK, "{}", api.last_error());
    assert!(FramePattern::parse(older.to_str().unwrap())
        .unwrap()
        .path(1)
        .exists());
    api.free(s, d);
}
