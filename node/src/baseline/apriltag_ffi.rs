//! Minimal FFI to Debian's libapriltag 3 (`libapriltag-dev`, linked as
//! `-lapriltag`, see its pkg-config file). Only what shoal uses: the two
//! classic families, their code tables and rendering, and the detector.
//!
//! The struct layouts mirror `/usr/include/apriltag/apriltag.h` (3.3.0).
//! `apriltag_detector` is only declared up to the fields we set: we never
//! construct or move it, we only write its leading fields through the
//! pointer the library returned.
#![allow(unsafe_code)] // FFI to a C library: there is no safe way to call it.
#![allow(non_camel_case_types)]

use std::os::raw::{c_char, c_double, c_float, c_int, c_void};

/// `apriltag_family_t`.
#[repr(C)]
pub struct apriltag_family_t {
    pub ncodes: u32,
    pub codes: *mut u64,
    pub width_at_border: c_int,
    pub total_width: c_int,
    pub reversed_border: bool,
    pub nbits: u32,
    pub bit_x: *mut u32,
    pub bit_y: *mut u32,
    pub h: u32,
    pub name: *mut c_char,
    pub impl_: *mut c_void,
}

/// The leading, public tuning fields of `apriltag_detector_t`.
#[repr(C)]
pub struct apriltag_detector_t {
    pub nthreads: c_int,
    pub quad_decimate: c_float,
    pub quad_sigma: c_float,
    pub refine_edges: bool,
    pub decode_sharpening: c_double,
    pub debug: bool,
    // ... more fields that we never touch.
}

/// `image_u8_t`.
#[repr(C)]
pub struct image_u8_t {
    pub width: i32,
    pub height: i32,
    pub stride: i32,
    pub buf: *mut u8,
}

/// `zarray_t`.
#[repr(C)]
pub struct zarray_t {
    pub el_sz: usize,
    pub size: c_int,
    pub alloc: c_int,
    pub data: *mut c_char,
}

/// `apriltag_detection_t`.
#[repr(C)]
pub struct apriltag_detection_t {
    pub family: *mut apriltag_family_t,
    pub id: c_int,
    pub hamming: c_int,
    pub decision_margin: c_float,
    pub h: *mut c_void,
    pub c: [c_double; 2],
    pub p: [[c_double; 2]; 4],
}

extern "C" {
    /// libc's `free`: libapriltag 3.3 does not export `image_u8_destroy`, which
    /// is `free(im->buf); free(im);` (both allocated with `calloc`).
    fn free(p: *mut c_void);
}

/// Free an `image_u8_t` made by libapriltag.
///
/// # Safety
/// `im` must come from libapriltag (`apriltag_to_image`, `image_u8_create`) and not be used afterwards.
pub unsafe fn image_u8_destroy(im: *mut image_u8_t) {
    if !im.is_null() {
        free((*im).buf.cast());
        free(im.cast());
    }
}

#[link(name = "apriltag")]
extern "C" {
    pub fn tag36h11_create() -> *mut apriltag_family_t;
    pub fn tag36h11_destroy(tf: *mut apriltag_family_t);
    pub fn tag16h5_create() -> *mut apriltag_family_t;
    pub fn tag16h5_destroy(tf: *mut apriltag_family_t);
    pub fn apriltag_to_image(fam: *mut apriltag_family_t, idx: c_int) -> *mut image_u8_t;
    pub fn apriltag_detector_create() -> *mut apriltag_detector_t;
    pub fn apriltag_detector_add_family_bits(
        td: *mut apriltag_detector_t,
        fam: *mut apriltag_family_t,
        bits_corrected: c_int,
    );
    pub fn apriltag_detector_destroy(td: *mut apriltag_detector_t);
    pub fn apriltag_detector_detect(
        td: *mut apriltag_detector_t,
        im: *mut image_u8_t,
    ) -> *mut zarray_t;
    pub fn apriltag_detections_destroy(detections: *mut zarray_t);
}

/// libapriltag's default number of corrected bits: `apriltag_detector_add_family`
/// (a static inline in `apriltag.h`) calls `add_family_bits(td, fam, 2)`.
pub const DEFAULT_BITS_CORRECTED: u32 = 2;

/// The two classic families shoal supports.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum Family {
    Tag16h5,
    Tag36h11,
}

/// An owned family object.
pub struct FamilyHandle {
    pub(crate) ptr: *mut apriltag_family_t,
    family: Family,
}

// SAFETY: the family is immutable after creation except through the detector that owns it,
// and we only hand it to one detector at a time.
unsafe impl Send for FamilyHandle {}

impl FamilyHandle {
    pub fn new(family: Family) -> Option<Self> {
        // SAFETY: plain constructors of the C library; null is checked.
        let ptr = unsafe {
            match family {
                Family::Tag16h5 => tag16h5_create(),
                Family::Tag36h11 => tag36h11_create(),
            }
        };
        (!ptr.is_null()).then_some(Self { ptr, family })
    }

    pub fn ncodes(&self) -> usize {
        // SAFETY: ptr is a valid family for the life of self.
        unsafe { (*self.ptr).ncodes as usize }
    }

    /// The tag rendered by libapriltag, 1 pixel per module: `(total_width, pixels)`,
    /// 255 = white, including the white quiet zone outside the black border.
    pub fn render(&self, idx: usize) -> Option<(usize, Vec<u8>)> {
        if idx >= self.ncodes() {
            return None;
        }
        // SAFETY: idx is in range; the image is copied then destroyed.
        unsafe {
            let im = apriltag_to_image(self.ptr, idx as c_int);
            if im.is_null() {
                return None;
            }
            let (w, h, s) = (
                (*im).width as usize,
                (*im).height as usize,
                (*im).stride as usize,
            );
            let mut out = Vec::with_capacity(w * h);
            for y in 0..h {
                out.extend_from_slice(std::slice::from_raw_parts((*im).buf.add(y * s), w));
            }
            image_u8_destroy(im);
            Some((w, out))
        }
    }

    /// Modules across the black border (`width_at_border`).
    pub fn width_at_border(&self) -> usize {
        // SAFETY: ptr is valid.
        unsafe { (*self.ptr).width_at_border as usize }
    }
}

impl Drop for FamilyHandle {
    fn drop(&mut self) {
        // SAFETY: created by the matching constructor, destroyed once.
        unsafe {
            match self.family {
                Family::Tag16h5 => tag16h5_destroy(self.ptr),
                Family::Tag36h11 => tag36h11_destroy(self.ptr),
            }
        }
    }
}
