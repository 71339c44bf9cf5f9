//! The camera effects done with OpenCV or block transforms: a heavy-tailed
//! PSF drawn per frame (Moffat or generalized Gaussian, applied by
//! `cv::filter2D`), JPEG through `cv::imencode`/`cv::imdecode`, and an
//! H.264-like intra coder (4x4 DCT, H.264's quantizer step; see
//! `docs/water-model.md` for what it leaves out).

use crate::error::SimError;
use crate::profile::PsfMix;
use opencv::core::{Mat, Point, Vector, BORDER_REFLECT, CV_32F};
use opencv::prelude::*;
use opencv::{imgcodecs, imgproc};
use rand::Rng;
use rand_chacha::ChaCha8Rng;

fn cv(stage: &'static str) -> impl Fn(opencv::Error) -> SimError {
    move |e| SimError::Effect {
        stage,
        message: e.to_string(),
    }
}

/// A radially symmetric PSF drawn for one frame.
#[derive(Debug, Clone, Copy, PartialEq)]
pub enum PsfShape {
    /// `(1 + (r/α)²)^−β`.
    Moffat { alpha_px: f64, beta: f64 },
    /// `exp(−(r/s)^p)`.
    GeneralizedGaussian { scale_px: f64, p: f64 },
}

/// Largest kernel radius (px): the farthest tail is cut there and the rest renormalized.
pub const PSF_MAX_RADIUS_PX: usize = 30;

impl PsfShape {
    /// Draw a family, a shape and a width from `mix`.
    pub fn draw(mix: &PsfMix, rng: &mut ChaCha8Rng) -> PsfShape {
        let uniform = |r: &mut ChaCha8Rng, [lo, hi]: [f64; 2]| {
            if hi > lo {
                r.gen_range(lo..=hi)
            } else {
                lo
            }
        };
        let fwhm = uniform(rng, mix.fwhm_px);
        if rng.gen::<f64>() < mix.moffat_share {
            let beta = uniform(rng, mix.moffat_beta);
            PsfShape::Moffat {
                alpha_px: 0.5 * fwhm / (2f64.powf(1.0 / beta) - 1.0).sqrt(),
                beta,
            }
        } else {
            let p = uniform(rng, mix.gg_shape);
            PsfShape::GeneralizedGaussian {
                scale_px: 0.5 * fwhm / 2f64.ln().powf(1.0 / p),
                p,
            }
        }
    }

    pub fn value(&self, r: f64) -> f64 {
        match *self {
            PsfShape::Moffat { alpha_px, beta } => (1.0 + (r / alpha_px).powi(2)).powf(-beta),
            PsfShape::GeneralizedGaussian { scale_px, p } => (-(r / scale_px).powf(p)).exp(),
        }
    }

    /// Full width at half maximum (px).
    pub fn fwhm_px(&self) -> f64 {
        match *self {
            PsfShape::Moffat { alpha_px, beta } => {
                2.0 * alpha_px * (2f64.powf(1.0 / beta) - 1.0).sqrt()
            }
            PsfShape::GeneralizedGaussian { scale_px, p } => {
                2.0 * scale_px * 2f64.ln().powf(1.0 / p)
            }
        }
    }

    /// Kernel radius: 8 FWHM, at most [`PSF_MAX_RADIUS_PX`].
    pub fn radius_px(&self) -> usize {
        ((8.0 * self.fwhm_px()).ceil() as usize).clamp(1, PSF_MAX_RADIUS_PX)
    }

    /// The normalized kernel, each pixel the mean of 4x4 samples over its area.
    pub fn kernel(&self) -> Vec<f32> {
        let r = self.radius_px() as i64;
        let n = (2 * r + 1) as usize;
        let mut k = vec![0.0f64; n * n];
        for y in -r..=r {
            for x in -r..=r {
                let mut s = 0.0;
                for sy in 0..4 {
                    for sx in 0..4 {
                        let (dx, dy) = (
                            x as f64 + (sx as f64 + 0.5) / 4.0 - 0.5,
                            y as f64 + (sy as f64 + 0.5) / 4.0 - 0.5,
                        );
                        s += self.value((dx * dx + dy * dy).sqrt());
                    }
                }
                k[((y + r) as usize) * n + (x + r) as usize] = s;
            }
        }
        let total: f64 = k.iter().sum();
        k.iter().map(|v| (v / total) as f32).collect()
    }

    pub fn describe(&self) -> String {
        match *self {
            PsfShape::Moffat { beta, .. } => {
                format!("Moffat β {beta:.2}, FWHM {:.2} px", self.fwhm_px())
            }
            PsfShape::GeneralizedGaussian { p, .. } => {
                format!(
                    "generalized Gaussian p {p:.2}, FWHM {:.2} px",
                    self.fwhm_px()
                )
            }
        }
    }
}

/// Convolve a float frame with `psf` (reflecting borders).
pub fn blur(dn: &[f32], w: usize, h: usize, psf: &PsfShape) -> Result<Vec<f32>, SimError> {
    let err = cv("psf");
    let src = Mat::new_rows_cols_with_data(h as i32, w as i32, dn).map_err(&err)?;
    let r = psf.radius_px();
    let n = 2 * r + 1;
    let k = psf.kernel();
    let kernel = Mat::new_rows_cols_with_data(n as i32, n as i32, &k).map_err(&err)?;
    let mut dst = Mat::default();
    imgproc::filter_2d(
        &src,
        &mut dst,
        CV_32F,
        &kernel,
        Point::new(-1, -1),
        0.0,
        BORDER_REFLECT,
    )
    .map_err(&err)?;
    Ok(dst.data_typed::<f32>().map_err(&err)?.to_vec())
}

/// JPEG-compress an 8-bit grey frame at `quality` and decode it again (libjpeg through OpenCV).
pub fn jpeg_roundtrip(data: &[u8], w: usize, h: usize, quality: u8) -> Result<Vec<u8>, SimError> {
    let err = cv("jpeg");
    let src = Mat::new_rows_cols_with_data(h as i32, w as i32, data).map_err(&err)?;
    let mut buf = Vector::<u8>::new();
    let params = Vector::<i32>::from_slice(&[imgcodecs::IMWRITE_JPEG_QUALITY, i32::from(quality)]);
    if !imgcodecs::imencode(".jpg", &src, &mut buf, &params).map_err(&err)? {
        return Err(SimError::Effect {
            stage: "jpeg",
            message: "the encoder refused the frame".into(),
        });
    }
    let out = imgcodecs::imdecode(&buf, imgcodecs::IMREAD_GRAYSCALE).map_err(&err)?;
    if out.rows() != h as i32 || out.cols() != w as i32 {
        return Err(SimError::Effect {
            stage: "jpeg",
            message: format!("decoded {}x{}, expected {w}x{h}", out.cols(), out.rows()),
        });
    }
    Ok(out.data_bytes().map_err(&err)?.to_vec())
}

/// H.264's quantizer step for quantization parameter `qp`: 0.625 at QP 0, doubling every 6.
pub fn h264_qstep(qp: u8) -> f64 {
    0.625 * 2f64.powf(f64::from(qp) / 6.0)
}

/// H.264-like intra coding: every 4x4 block's orthonormal DCT (to which
/// H.264's integer transform with its post-scaling is equivalent) is
/// quantized with step [`h264_qstep`] and the encoder's intra dead zone
/// (rounding offset 1/3), then inverted. No intra prediction, no
/// deblocking filter, no rate control: see `docs/water-model.md`.
pub fn h264_like(data: &[u8], w: usize, h: usize, qp: u8) -> Vec<u8> {
    let q = h264_qstep(qp);
    // Orthonormal 4-point DCT-II.
    let mut c = [[0.0f64; 4]; 4];
    for (k, row) in c.iter_mut().enumerate() {
        let s = if k == 0 { 0.5 } else { (0.5f64).sqrt() };
        for (n, v) in row.iter_mut().enumerate() {
            *v = s * (std::f64::consts::PI * (2.0 * n as f64 + 1.0) * k as f64 / 8.0).cos();
        }
    }
    let mut out = data.to_vec();
    for by in (0..h).step_by(4) {
        for bx in (0..w).step_by(4) {
            let mut x = [[0.0f64; 4]; 4];
            for (i, row) in x.iter_mut().enumerate() {
                for (j, v) in row.iter_mut().enumerate() {
                    // Edge blocks repeat the last row/column.
                    let (yy, xx) = ((by + i).min(h - 1), (bx + j).min(w - 1));
                    *v = f64::from(data[yy * w + xx]);
                }
            }
            // Y = C X Cᵀ, quantized, X' = Cᵀ Y' C.
            let mut y = [[0.0f64; 4]; 4];
            for k in 0..4 {
                for l in 0..4 {
                    let mut s = 0.0;
                    for i in 0..4 {
                        for j in 0..4 {
                            s += c[k][i] * x[i][j] * c[l][j];
                        }
                    }
                    let level = (s.abs() / q + 1.0 / 3.0).floor();
                    y[k][l] = s.signum() * level * q;
                }
            }
            for i in 0..4 {
                for j in 0..4 {
                    if by + i >= h || bx + j >= w {
                        continue;
                    }
                    let mut s = 0.0;
                    for k in 0..4 {
                        for l in 0..4 {
                            s += c[k][i] * y[k][l] * c[l][j];
                        }
                    }
                    out[(by + i) * w + bx + j] = s.round().clamp(0.0, 255.0) as u8;
                }
            }
        }
    }
    out
}

#[cfg(test)]
mod tests {
    use super::*;
    use rand::SeedableRng;

    #[test]
    fn drawn_psfs_have_the_drawn_width() {
        let mut rng = ChaCha8Rng::seed_from_u64(5);
        for _ in 0..20 {
            let psf = PsfShape::draw(&PsfMix::default(), &mut rng);
            let f = psf.fwhm_px();
            assert!((1.0..=2.5).contains(&f), "{f}");
            // Half maximum at half the FWHM.
            assert!(
                (psf.value(0.5 * f) - 0.5).abs() < 1e-9,
                "{}",
                psf.describe()
            );
            let k = psf.kernel();
            assert!((k.iter().map(|v| f64::from(*v)).sum::<f64>() - 1.0).abs() < 1e-5);
        }
    }

    #[test]
    fn the_h264_like_coder_keeps_flat_blocks_and_loses_detail_with_qp() {
        let (w, h) = (16, 16);
        let flat = vec![120u8; w * h];
        assert_eq!(h264_like(&flat, w, h, 20), flat);
        let noise: Vec<u8> = (0..w * h)
            .map(|i| ((i * 37 + i / 7 * 11) % 200) as u8)
            .collect();
        let err = |qp| {
            let out = h264_like(&noise, w, h, qp);
            out.iter()
                .zip(&noise)
                .map(|(a, b)| (f64::from(*a) - f64::from(*b)).powi(2))
                .sum::<f64>()
        };
        assert!(
            err(36) > err(24) && err(24) > err(12) && err(12) > err(0),
            "{} {} {} {}",
            err(0),
            err(12),
            err(24),
            err(36)
        );
    }
}
