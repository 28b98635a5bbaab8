//! `hz_image`: a host's strided pixel buffer, validated with checked size
//! math before any byte of it is touched.

use std::ffi::c_void;

use harmonizer_core::{Error, Image, ImageView, PixelFormat};

use crate::check_struct_size;

/// Sample format of an `hz_image` (the value of its `format` field).
#[repr(u32)]
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum hz_format {
    /// 32-bit IEEE float samples.
    HZ_FORMAT_F32 = 1,
    /// 16-bit IEEE half-float samples.
    HZ_FORMAT_F16 = 2,
}

/// A strided image in host memory. Pixel `(x, y)` channel `c` is at byte
/// `offset + y * row_stride + x * pixel_stride + c * sample_size` from `data`,
/// where `sample_size` is 4 (F32) or 2 (F16). A stride of 0 means packed.
/// An RGBA buffer where only RGB is color is `channels = 3, pixel_stride = 16`.
/// Samples need no particular alignment; strides and offset are multiples of
/// the sample size.
#[repr(C)]
#[derive(Debug, Clone, Copy)]
pub struct hz_image {
    /// `sizeof(hz_image)`.
    pub struct_size: usize,
    /// One of `hz_format` (`HZ_FORMAT_F32`, `HZ_FORMAT_F16`).
    pub format: u32,
    /// Channels described (the first `channels` samples of each pixel).
    pub channels: u32,
    /// Width in pixels (> 0).
    pub width: usize,
    /// Height in pixels (> 0).
    pub height: usize,
    /// Bytes from `data` to the first sample.
    pub offset: usize,
    /// Bytes from one pixel to the next in a row; 0 = `channels * sample_size`.
    pub pixel_stride: usize,
    /// Bytes from one row to the next; 0 = `width * pixel_stride`.
    pub row_stride: usize,
    /// The buffer. Read-only for inputs; written for the output.
    pub data: *mut c_void,
}

/// A validated image description: strides resolved, byte extent computed.
#[derive(Debug, Clone, Copy)]
pub(crate) struct Described {
    pub format: PixelFormat,
    pub channels: usize,
    pub width: usize,
    pub height: usize,
    pub offset: usize,
    pub pixel_stride: usize,
    pub row_stride: usize,
    pub data: *mut u8,
    /// Bytes from `data` up to and including the last sample.
    pub len: usize,
}

impl Described {
    /// Reads and validates an `hz_image`. `what` names it in messages ("color").
    ///
    /// # Safety
    /// `img` is NULL or points to a readable `hz_image`.
    pub unsafe fn read(what: &str, img: *const hz_image) -> Result<Described, Error> {
        if img.is_null() {
            return Err(Error::invalid(format!("{what} is NULL")));
        }
        // SAFETY: non-NULL; the caller promises a readable struct. The first
        // field is read alone so a struct of another size is refused before
        // any other field is read.
        let size = unsafe { std::ptr::addr_of!((*img).struct_size).read_unaligned() };
        check_struct_size("hz_image", size, std::mem::size_of::<hz_image>())
            .map_err(|e| Error::invalid(format!("{what}: {}", message(&e))))?;
        // SAFETY: the struct has this library's size, so every field is readable.
        let i = unsafe { img.read_unaligned() };
        let format = match i.format {
            x if x == hz_format::HZ_FORMAT_F32 as u32 => PixelFormat::F32,
            x if x == hz_format::HZ_FORMAT_F16 as u32 => PixelFormat::F16,
            x => {
                return Err(Error::invalid(format!(
                    "{what}: format {x} is not HZ_FORMAT_F32 (1) or HZ_FORMAT_F16 (2)"
                )))
            }
        };
        let channels = i.channels as usize;
        let (width, height) = (i.width, i.height);
        if width == 0 || height == 0 {
            return Err(Error::invalid(format!(
                "{what}: image size {width}x{height} is empty"
            )));
        }
        if channels == 0 {
            return Err(Error::invalid(format!("{what}: channel count is 0")));
        }
        if i.data.is_null() {
            return Err(Error::invalid(format!("{what}: data is NULL")));
        }
        let sample = format.size();
        let overflow = || {
            Error::invalid(format!(
                "{what}: {width}x{height}x{channels} image size overflows"
            ))
        };
        let packed_pixel = channels.checked_mul(sample).ok_or_else(overflow)?;
        let pixel_stride = if i.pixel_stride == 0 {
            packed_pixel
        } else {
            i.pixel_stride
        };
        if pixel_stride < packed_pixel {
            return Err(Error::invalid(format!(
                "{what}: pixel stride {pixel_stride} bytes is smaller than {channels} channels of {sample} bytes"
            )));
        }
        let packed_row = width.checked_mul(pixel_stride).ok_or_else(overflow)?;
        let row_stride = if i.row_stride == 0 {
            packed_row
        } else {
            i.row_stride
        };
        if row_stride < packed_row {
            return Err(Error::invalid(format!(
                "{what}: row stride {row_stride} bytes is smaller than width {width} x pixel stride {pixel_stride}"
            )));
        }
        if i.offset % sample != 0 || pixel_stride % sample != 0 || row_stride % sample != 0 {
            return Err(Error::invalid(format!(
                "{what}: offset {} and strides {pixel_stride}, {row_stride} must be multiples of the sample size {sample}",
                i.offset
            )));
        }
        let len = (height - 1)
            .checked_mul(row_stride)
            .and_then(|v| v.checked_add((width - 1).checked_mul(pixel_stride)?))
            .and_then(|v| v.checked_add(packed_pixel))
            .and_then(|v| v.checked_add(i.offset))
            .filter(|&v| v <= isize::MAX as usize)
            .ok_or_else(overflow)?;
        if (i.data as usize).checked_add(len).is_none() {
            return Err(Error::invalid(format!(
                "{what}: the buffer wraps around the address space"
            )));
        }
        Ok(Described {
            format,
            channels,
            width,
            height,
            offset: i.offset,
            pixel_stride,
            row_stride,
            data: i.data.cast::<u8>(),
            len,
        })
    }

    /// A read-only core view of the buffer.
    ///
    /// # Safety
    /// The host's buffer is readable for `self.len` bytes and not written by
    /// anyone while the view lives.
    pub unsafe fn view<'a>(&self, what: &str) -> Result<ImageView<'a>, Error> {
        // SAFETY: `data` is non-NULL, `len <= isize::MAX` and the range does not
        // wrap (checked in `read`); readability is the caller's contract.
        let bytes = unsafe { std::slice::from_raw_parts(self.data.cast_const(), self.len) };
        ImageView::new(
            what,
            bytes,
            self.format,
            self.width,
            self.height,
            self.channels,
            self.offset,
            self.pixel_stride,
            self.row_stride,
        )
    }

    /// Checks that this image can receive a result of `width` x `height`.
    pub fn check_output(&self, width: usize, height: usize) -> Result<(), Error> {
        if self.width != width || self.height != height {
            return Err(Error::invalid(format!(
                "output: size {}x{} differs from color {width}x{height}",
                self.width, self.height
            )));
        }
        if !(3..=4).contains(&self.channels) {
            return Err(Error::invalid(format!(
                "output: needs 3 (RGB) or 4 (RGBA) channels, got {}",
                self.channels
            )));
        }
        Ok(())
    }

    /// Writes a 4-plane result (RGB, plus A when the output has 4 channels).
    /// Uses raw writes only, so the buffer may alias any input (whose views
    /// are gone by now) and need not be initialized.
    ///
    /// # Safety
    /// The host's buffer is writable for `self.len` bytes and no reference to
    /// it is alive.
    pub unsafe fn write(&self, img: &Image) {
        debug_assert_eq!((img.width, img.height), (self.width, self.height));
        let ch = self.channels.min(img.channels);
        let w = self.width;
        for y in 0..self.height {
            for c in 0..ch {
                let src = &img.plane(c)[y * w..(y + 1) * w];
                let base = self.offset + y * self.row_stride + c * self.format.size();
                match self.format {
                    PixelFormat::F32 => {
                        for (x, v) in src.iter().enumerate() {
                            // SAFETY: `base + x * pixel_stride + 4 <= len` for every
                            // sample of a validated layout; the caller promises the
                            // buffer is writable and unaliased by references.
                            unsafe {
                                self.data
                                    .add(base + x * self.pixel_stride)
                                    .cast::<f32>()
                                    .write_unaligned(*v)
                            };
                        }
                    }
                    PixelFormat::F16 => {
                        for (x, v) in src.iter().enumerate() {
                            let bits = half::f16::from_f32(*v).to_bits();
                            // SAFETY: as above, with 2-byte samples.
                            unsafe {
                                self.data
                                    .add(base + x * self.pixel_stride)
                                    .cast::<u16>()
                                    .write_unaligned(bits)
                            };
                        }
                    }
                }
            }
        }
    }
}

/// The text of an error without its cause prefix.
fn message(e: &Error) -> String {
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
