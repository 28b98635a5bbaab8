//! Frame descriptions (sizes, strides, offsets, formats, which AOVs, the
//! denoiser's albedo and normals and the insert's object ids included;
//! `hz_frame` of this header's size or an older one without them) through
//! the C ABI's validation and a classical session, on buffers exactly as
//! large as the description says. AddressSanitizer flags any read or write
//! outside them.
#![no_main]

use std::ffi::{c_void, CString};
use std::ptr;

use harmonizer::device::{hz_device, hz_device_free, hz_device_new, hz_device_options};
use harmonizer::image::hz_image;
use harmonizer::session::{
    hz_frame, hz_session, hz_session_commit, hz_session_new, hz_session_process,
    hz_session_set_int, hz_session_set_string,
};
use libfuzzer_sys::fuzz_target;

/// Most bytes one described buffer may span here.
const MAX_SPAN: u128 = 1 << 22;

struct Bytes<'a>(&'a [u8]);

impl Bytes<'_> {
    fn u8(&mut self) -> u8 {
        match self.0.split_first() {
            Some((&b, rest)) => {
                self.0 = rest;
                b
            }
            None => 0,
        }
    }
    fn u16(&mut self) -> u16 {
        u16::from(self.u8()) | (u16::from(self.u8()) << 8)
    }
    fn u64(&mut self) -> u64 {
        (0..4).fold(0, |a, i| a | (u64::from(self.u16()) << (16 * i)))
    }
}

/// One described buffer: the description and the memory behind it.
struct Buffer {
    image: hz_image,
    _memory: Vec<u8>,
}

/// Reads a description; `None` when its span is too large to back here
/// (a huge stride on one row is valid and would be read).
fn describe(b: &mut Bytes, fill: u8) -> Option<Buffer> {
    let format = match b.u8() % 4 {
        0 => 1,
        1 => 2,
        2 => 0,
        _ => u32::from(b.u8()),
    };
    let channels = u32::from(b.u8() % 6);
    let width = usize::from(b.u8() % 24);
    let height = usize::from(b.u8() % 24);
    let wide = b.u8();
    let (width, height) = match wide % 16 {
        0 => (width << 16, height),
        1 => (width, height << 16),
        2 => (1 << 40, 1 << 40),
        _ => (width, height),
    };
    let offset = usize::from(b.u16() % 64);
    let pixel_stride = usize::from(b.u16() % 96);
    let row_stride = match b.u8() % 8 {
        0 => b.u64() as usize,
        _ => usize::from(b.u16()),
    };
    let sample = if format == 2 { 2u128 } else { 4 };
    let ps = if pixel_stride == 0 {
        u128::from(channels) * sample
    } else {
        pixel_stride as u128
    };
    let rs = if row_stride == 0 {
        width as u128 * ps
    } else {
        row_stride as u128
    };
    let span = if width == 0 || height == 0 || channels == 0 {
        1
    } else {
        offset as u128
            + (height as u128 - 1) * rs
            + (width as u128 - 1) * ps
            + u128::from(channels) * sample
    };
    if span > MAX_SPAN {
        return None;
    }
    let mut memory = vec![fill; span as usize];
    for (i, m) in memory.iter_mut().enumerate() {
        *m = m.wrapping_add((i as u8).wrapping_mul(31));
    }
    Some(Buffer {
        image: hz_image {
            struct_size: std::mem::size_of::<hz_image>(),
            format,
            channels,
            width,
            height,
            offset,
            pixel_stride,
            row_stride,
            data: memory.as_mut_ptr() as *mut c_void,
        },
        _memory: memory,
    })
}

thread_local! {
    static SESSION: *mut hz_session = unsafe {
        let options = hz_device_options {
            struct_size: std::mem::size_of::<hz_device_options>(),
            threads: 1,
            memory_limit: 64 << 20,
            ort_library: ptr::null(),
            model_path: ptr::null(),
            model_data: ptr::null(),
            model_data_size: 0,
            model_manifest: ptr::null(),
        };
        let mut device: *mut hz_device = ptr::null_mut();
        hz_device_new(harmonizer::version_numbers().0, &options, &mut device);
        let mut session: *mut hz_session = ptr::null_mut();
        hz_session_new(device, &mut session);
        // The session keeps its own reference.
        hz_device_free(device);
        let backend = CString::new("backend").unwrap();
        let classical = CString::new("classical").unwrap();
        hz_session_set_string(session, backend.as_ptr(), classical.as_ptr());
        let k = CString::new("context_frames").unwrap();
        hz_session_set_int(session, k.as_ptr(), 2);
        hz_session_commit(session);
        session
    };
}

fuzz_target!(|data: &[u8]| {
    let mut b = Bytes(data);
    let present = b.u8();
    let fill = b.u8();
    let Some(color) = describe(&mut b, fill) else {
        return;
    };
    let mut aovs = Vec::new();
    for bit in 0..8 {
        if present & (1 << bit) != 0 {
            match describe(&mut b, fill.wrapping_add(bit)) {
                Some(buf) => aovs.push((bit, buf)),
                None => return,
            }
        } else {
            aovs.push((
                bit,
                Buffer {
                    image: color.image,
                    _memory: Vec::new(),
                },
            ));
        }
    }
    let pick = |bit: u8| -> *const hz_image {
        if present & (1 << bit) != 0 {
            &aovs[bit as usize].1.image
        } else {
            ptr::null()
        }
    };
    let matrix: Vec<f32> = (0..16)
        .map(|i| f32::from(b.u8()) / 16.0 - (i % 3) as f32)
        .collect();
    let cameras = b.u8();
    let frame = hz_frame {
        // Also the size of the headers before `albedo`, which must not be read then.
        // And the size of the headers before `insert_id`.
        struct_size: if cameras & 8 != 0 {
            std::mem::offset_of!(hz_frame, albedo)
                .next_multiple_of(std::mem::align_of::<hz_frame>())
        } else if cameras & 32 != 0 {
            std::mem::offset_of!(hz_frame, insert_id)
                .next_multiple_of(std::mem::align_of::<hz_frame>())
        } else {
            std::mem::size_of::<hz_frame>()
        },
        color: &color.image,
        depth: pick(0),
        motion: pick(1),
        normal: pick(2),
        coverage: pick(3),
        insert_mask: pick(4),
        world_to_camera: if cameras & 1 != 0 {
            matrix.as_ptr()
        } else {
            ptr::null()
        },
        world_to_ndc: if cameras & 2 != 0 {
            matrix.as_ptr()
        } else {
            ptr::null()
        },
        frame_index: b.u64() as i64 % 4,
        flags: u32::from(b.u8() % 4),
        motion_vector_scale: [1.0, if cameras & 4 != 0 { -1.0 } else { 1.0 }],
        albedo: pick(6),
        denoise_normal: pick(7),
        // The insert's object ids: the insert mask's description.
        insert_id: if cameras & 16 != 0 {
            pick(4)
        } else {
            ptr::null()
        },
    };
    // The output: the sixth description when given, else the color's.
    let output: *const hz_image = if present & (1 << 5) != 0 {
        &aovs[5].1.image
    } else {
        &color.image
    };
    SESSION.with(|s| unsafe {
        hz_session_process(*s, &frame, output);
    });
});
