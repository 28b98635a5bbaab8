//! Loads the built cdylib with `libloading` and drives it through the C ABI
//! only (the struct definitions come from the crate, the functions from the
//! shared library).

use std::ffi::{c_char, c_void, CStr};
use std::path::PathBuf;
use std::ptr::{null, null_mut};

use harmonizer::device::{hz_device, hz_device_options};
use harmonizer::hz_status::{self, *};
use harmonizer::image::{hz_format, hz_image};
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
            assert_eq!(commit(s), HZ_OK, "{}", self.last_error());
        }
        s
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
    let mut bad = f;
    bad.struct_size -= 8;
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
