//! Conversions between [`GrayImage`] (the simulator's plain pixels) and
//! OpenCV's `cv::Mat`, plus a borrowed row-major view of an 8-bit grey `Mat`
//! that the detector samples without per-pixel FFI calls.

use opencv::boxed_ref::BoxedRef;
use opencv::core::{Mat, CV_8UC1};
use opencv::prelude::*;
use shoal_proto::image::GrayImage;

/// Errors of this module.
#[derive(Debug, thiserror::Error)]
pub enum MatError {
    #[error(
        "expected an 8-bit single-channel image, got OpenCV type {typ} with {channels} channel(s)"
    )]
    NotGray8 { typ: i32, channels: i32 },
    #[error("image is empty ({width}x{height})")]
    Empty { width: i32, height: i32 },
    #[error("image of {width}x{height} has {len} bytes, expected {expected}")]
    SizeMismatch {
        width: u32,
        height: u32,
        len: usize,
        expected: usize,
    },
    #[error("OpenCV: {0}")]
    OpenCv(#[from] opencv::Error),
}

/// Wrap a [`GrayImage`] as a `Mat` without copying (the `Mat` borrows the pixels).
pub fn gray_as_mat(img: &GrayImage) -> Result<BoxedRef<'_, Mat>, MatError> {
    let expected = img.width as usize * img.height as usize;
    if img.data.len() != expected || expected == 0 {
        return Err(MatError::SizeMismatch {
            width: img.width,
            height: img.height,
            len: img.data.len(),
            expected,
        });
    }
    Ok(Mat::new_rows_cols_with_data(
        img.height as i32,
        img.width as i32,
        &img.data,
    )?)
}

/// Copy a [`GrayImage`] into an owned `Mat` (when the `Mat` must outlive the image).
pub fn gray_to_mat(img: &GrayImage) -> Result<Mat, MatError> {
    Ok(gray_as_mat(img)?.clone_pointee())
}

/// Copy an 8-bit grey `Mat` into a [`GrayImage`].
pub fn mat_to_gray(mat: &impl MatTraitConst) -> Result<GrayImage, MatError> {
    let view = GrayView::new(mat)?;
    let mut data = Vec::with_capacity(view.width * view.height);
    for y in 0..view.height {
        data.extend_from_slice(view.row(y));
    }
    Ok(GrayImage {
        width: view.width as u32,
        height: view.height as u32,
        data,
    })
}

/// A borrowed view of an 8-bit grey image: `height` rows of `width` pixels, `stride` bytes apart.
#[derive(Debug, Clone, Copy)]
pub struct GrayView<'a> {
    pub data: &'a [u8],
    pub width: usize,
    pub height: usize,
    pub stride: usize,
}

impl<'a> GrayView<'a> {
    /// View a `CV_8UC1` `Mat` (continuous or not) without copying.
    pub fn new(mat: &'a impl MatTraitConst) -> Result<Self, MatError> {
        if mat.typ() != CV_8UC1 {
            return Err(MatError::NotGray8 {
                typ: mat.typ(),
                channels: mat.channels(),
            });
        }
        let (width, height) = (mat.cols(), mat.rows());
        if width <= 0 || height <= 0 {
            return Err(MatError::Empty { width, height });
        }
        let stride = mat.step1(0)?;
        let len = stride * (height as usize - 1) + width as usize;
        if !mat.is_continuous() {
            return Self::from_roi(mat, width as usize, height as usize, stride, len);
        }
        let data = mat.data_bytes()?;
        Ok(Self {
            data,
            width: width as usize,
            height: height as usize,
            stride,
        })
    }

    #[allow(unsafe_code)] // A non-continuous Mat (a ROI) has no safe slice accessor in the opencv crate.
    fn from_roi(
        mat: &'a impl MatTraitConst,
        width: usize,
        height: usize,
        stride: usize,
        len: usize,
    ) -> Result<Self, MatError> {
        let first = mat.ptr(0)?;
        // SAFETY: `ptr(0)` points at row 0 of a live Mat borrowed for 'a; rows are
        // `stride` bytes apart in one allocation, so `len` bytes from it are readable.
        let data = unsafe { std::slice::from_raw_parts(first, len) };
        Ok(Self {
            data,
            width,
            height,
            stride,
        })
    }

    /// Row `y` (`y < height`).
    pub fn row(&self, y: usize) -> &'a [u8] {
        &self.data[y * self.stride..y * self.stride + self.width]
    }

    /// Pixel at integer coordinates (clamped to the image).
    #[inline]
    pub fn px(&self, x: isize, y: isize) -> f64 {
        let x = x.clamp(0, self.width as isize - 1) as usize;
        let y = y.clamp(0, self.height as isize - 1) as usize;
        f64::from(self.data[y * self.stride + x])
    }

    /// Bilinear sample at `(x, y)` (pixel centres at integers, OpenCV convention); clamped at the borders.
    #[inline]
    pub fn sample(&self, x: f64, y: f64) -> f64 {
        let x0 = x.floor();
        let y0 = y.floor();
        let (fx, fy) = (x - x0, y - y0);
        let (xi, yi) = (x0 as isize, y0 as isize);
        if xi >= 0 && yi >= 0 && (xi as usize) + 1 < self.width && (yi as usize) + 1 < self.height {
            let o = yi as usize * self.stride + xi as usize;
            let d = self.data;
            let a = f64::from(d[o]);
            let b = f64::from(d[o + 1]);
            let c = f64::from(d[o + self.stride]);
            let e = f64::from(d[o + self.stride + 1]);
            return (a * (1.0 - fx) + b * fx) * (1.0 - fy) + (c * (1.0 - fx) + e * fx) * fy;
        }
        let a = self.px(xi, yi);
        let b = self.px(xi + 1, yi);
        let c = self.px(xi, yi + 1);
        let e = self.px(xi + 1, yi + 1);
        (a * (1.0 - fx) + b * fx) * (1.0 - fy) + (c * (1.0 - fx) + e * fx) * fy
    }

    /// True when `(x, y)` lies inside the image with `margin` pixels to spare.
    pub fn contains(&self, x: f64, y: f64, margin: f64) -> bool {
        x >= margin
            && y >= margin
            && x <= self.width as f64 - 1.0 - margin
            && y <= self.height as f64 - 1.0 - margin
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn gray_image_round_trips_through_mat() {
        let data: Vec<u8> = (0..12u8).collect();
        let img = GrayImage::from_vec(4, 3, data).unwrap();
        let mat = gray_as_mat(&img).unwrap();
        assert_eq!((mat.rows(), mat.cols()), (3, 4));
        assert_eq!(*mat.at_2d::<u8>(2, 1).unwrap(), 9);
        let back = mat_to_gray(&mat).unwrap();
        assert_eq!(back, img);
    }

    #[test]
    fn rejects_size_mismatch_and_colour() {
        let bad = GrayImage {
            width: 4,
            height: 3,
            data: vec![0; 5],
        };
        assert!(matches!(
            gray_as_mat(&bad),
            Err(MatError::SizeMismatch { .. })
        ));
        let colour =
            Mat::new_rows_cols_with_default(2, 2, opencv::core::CV_8UC3, 0.into()).unwrap();
        assert!(matches!(
            GrayView::new(&colour),
            Err(MatError::NotGray8 { .. })
        ));
    }

    #[test]
    fn bilinear_sample_interpolates_between_pixels() {
        let img = GrayImage::from_vec(2, 2, vec![0, 100, 100, 200]).unwrap();
        let mat = gray_as_mat(&img).unwrap();
        let v = GrayView::new(&mat).unwrap();
        assert!((v.sample(0.5, 0.5) - 100.0).abs() < 1e-9);
        assert!((v.sample(0.5, 0.0) - 50.0).abs() < 1e-9);
    }
}
