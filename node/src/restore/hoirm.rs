//! HOIRM, the hydro-optic image restoration model (paper §4.2), for 8-bit
//! grey frames.
//!
//! Per frame:
//! 1. 1/8 area-averaged level; water estimate from it ([`WaterEstimate`]);
//!    `c` = the override or the estimate.
//! 2. Ambient light (Eq. 11–12) from the running state ([`AmbientLight`]) on
//!    the 1/8 level, scaled by `α = min(α_max, backscatter / mean(Set))` so
//!    that what is taken away matches the veil the image shows; up-sampled
//!    and subtracted (Eq. 13).
//! 3. De-attenuation: a global gain `1/t̂` (the 99.5th percentile of
//!    `I − B_L` stretched to `stretch_target`), then CLAHE with a clip limit
//!    growing with `c` for the local part.
//! 4. De-blurring: Wiener deconvolution with Eq. (14)'s PSF, `p` and σ from
//!    `c`, the noise-to-signal ratio measured in each region — in the regions
//!    of interest ([`super::roi`]) or the whole frame.
//!    ([`StageOrder`] swaps 3 and 4.)
//! 5. Pyramid level: the finest level at which the marker region's edge
//!    step over noise reaches `edge_snr_target` (measured with `pyrDown` on
//!    the region), no coarser than keeps the region `min_roi_side_at_level_px`.

use super::ambient::AmbientLight;
use super::psf::{GgPsf, Wiener};
use super::water::{self, WaterEstimate};
use super::{
    check_input, clahe, coarse_level, roi, snapshot, Method, RestoreError, RestoreParams,
    Restored, Restorer, StageOrder,
};
use opencv::core::{self, Mat, Rect, CV_8U};
use opencv::imgproc;
use opencv::prelude::*;

/// Down-sampling of the level used for the water estimate, ambient light and ROI search.
pub const COARSE_FACTOR: i32 = 8;

/// Side of the patch on which the pyramid level is chosen, pixels.
const LEVEL_PATCH_PX: i32 = 384;

/// HOIRM with its per-camera state.
#[derive(Debug)]
pub struct Hoirm {
    params: RestoreParams,
    ambient: AmbientLight,
    wiener: Wiener,
}

/// What HOIRM derived for one frame (for logs, tests and the docs).
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct HoirmFrameParams {
    pub water: WaterEstimate,
    pub c_per_m: f64,
    pub alpha: f64,
    /// Global de-attenuation gain applied to `I − B_L`.
    pub gain: f64,
    pub clahe_clip: f64,
    pub psf: GgPsf,
}

impl Hoirm {
    pub fn new(params: RestoreParams) -> Self {
        let ambient = AmbientLight::new(
            params.ambient_tau_s,
            params.ambient_sigma_px / COARSE_FACTOR as f64,
        );
        Self {
            params,
            ambient,
            wiener: Wiener::new(),
        }
    }

    pub fn params(&self) -> &RestoreParams {
        &self.params
    }

    /// Forget the ambient-light history (e.g. after a camera restart).
    pub fn reset(&mut self) {
        self.ambient.reset();
    }

    /// Parameters HOIRM uses for water of attenuation `c_per_m`.
    pub fn parameters_for(&self, c_per_m: f64) -> (f64, GgPsf) {
        let p = water::psf_p(c_per_m, &self.params);
        let sigma_px = water::psf_sigma_px(p, &self.params);
        (
            water::clahe_clip(c_per_m, &self.params),
            GgPsf { p, sigma_px },
        )
    }

    /// Deconvolve `src` inside `rois` (all of it when `rois` covers the frame).
    fn deblur(&mut self, src: &Mat, rois: &[Rect], psf: &GgPsf) -> Result<Mat, RestoreError> {
        let mut out = src.try_clone()?;
        let frame = Rect::new(0, 0, src.cols(), src.rows());
        let margin = psf.radius_px();
        for &r in rois {
            // Deconvolve with a margin of real pixels so the region's own
            // border is not reflected into it, then keep the region.
            let tile = Rect::new(
                r.x - margin,
                r.y - margin,
                r.width + 2 * margin,
                r.height + 2 * margin,
            ) & frame;
            let view = Mat::roi(src, tile)?;
            let nsr = self.nsr(&view)?;
            let restored = self.wiener.deconvolve(&view, psf, nsr)?;
            let inner = Mat::roi(
                &restored,
                Rect::new(r.x - tile.x, r.y - tile.y, r.width, r.height),
            )?;
            let mut dst = Mat::roi_mut(&mut out, r)?;
            inner.copy_to(&mut dst)?;
        }
        Ok(out)
    }

    /// Wiener `K = gain·σ_noise²/σ_signal²`, measured on the region, clamped.
    fn nsr(&self, view: &(impl MatTraitConst + core::ToInputArray)) -> Result<f64, RestoreError> {
        let noise = water::noise_sigma(view, 2)?;
        let (mut mean, mut std) = (core::Scalar::default(), core::Scalar::default());
        core::mean_std_dev(view, &mut mean, &mut std, &core::no_array())?;
        let signal_var = (std[0] * std[0]).max(1e-6);
        Ok((self.params.nsr_gain * noise * noise / signal_var)
            .clamp(self.params.nsr_min, self.params.nsr_max))
    }

    /// Choose the pyramid level for edge detection on a patch of `img`
    /// around the largest region of interest (the centre when there is none).
    fn choose_level(&self, img: &Mat, rois: &[Rect]) -> Result<u32, RestoreError> {
        let frame = Rect::new(0, 0, img.cols(), img.rows());
        let focus = rois
            .iter()
            .copied()
            .max_by_key(|r| r.area())
            .unwrap_or(frame);
        let side_w = focus.width.min(LEVEL_PATCH_PX);
        let side_h = focus.height.min(LEVEL_PATCH_PX);
        let patch_rect = Rect::new(
            focus.x + (focus.width - side_w) / 2,
            focus.y + (focus.height - side_h) / 2,
            side_w,
            side_h,
        ) & frame;
        let smallest = rois
            .iter()
            .map(|r| r.width.min(r.height))
            .min()
            .unwrap_or(frame.width.min(frame.height));
        let mut patch = Mat::roi(img, patch_rect)?.try_clone()?;
        let mut best = (0u32, 0.0f64);
        for level in 0..=self.params.max_pyramid_level {
            if level > 0 {
                if (smallest >> level) < self.params.min_roi_side_at_level_px
                    || patch.cols() < 8
                    || patch.rows() < 8
                {
                    break;
                }
                let mut down = Mat::default();
                imgproc::pyr_down_def(&patch, &mut down)?;
                patch = down;
            }
            let hist = water::histogram(&patch)?;
            let step = water::percentile(&hist, 0.98) - water::percentile(&hist, 0.02);
            let noise = water::noise_sigma(&patch, 1)?;
            let snr = step / noise;
            if snr >= self.params.edge_snr_target {
                return Ok(level);
            }
            if snr > best.1 {
                best = (level, snr);
            }
        }
        Ok(best.0)
    }

    /// Restore one frame and also return the parameters derived for it.
    pub fn restore_with_params(
        &mut self,
        gray: &Mat,
        stamp_ns: u64,
    ) -> Result<(Restored, HoirmFrameParams), RestoreError> {
        check_input(gray)?;
        if let Some(e) = self.params.problem() {
            return Err(e);
        }
        let keep = self.params.keep_stages;
        let mut stages = Vec::new();
        let full = gray.size()?;

        // 1. Water from the image (or the override).
        let coarse = coarse_level(gray, COARSE_FACTOR)?;
        let water = WaterEstimate::from_image(gray, &coarse, &self.params)?;
        let c = self.params.c_per_m.unwrap_or(water.c_per_m);
        let (clip, psf) = self.parameters_for(c);

        // 2. Ambient light, Eq. (11)–(13).
        let set_mean = self.ambient.update(&coarse, stamp_ns)?;
        let set_level = core::mean(&set_mean, &core::no_array())?[0];
        let alpha = if set_level > 0.0 {
            (water.backscatter / set_level).min(self.params.ambient_alpha_max)
        } else {
            0.0
        };
        let mut bl_coarse = Mat::default();
        set_mean.convert_to(&mut bl_coarse, CV_8U, alpha, 0.0)?;
        let mut bl = Mat::default();
        imgproc::resize(&bl_coarse, &mut bl, full, 0.0, 0.0, imgproc::INTER_LINEAR)?;
        let mut denoised = Mat::default();
        core::subtract(gray, &bl, &mut denoised, &core::no_array(), -1)?;
        if keep {
            stages.push(("input".to_string(), snapshot(gray)?));
            stages.push(("ambient light B_L".to_string(), bl));
            stages.push(("denoised (I - B_L)".to_string(), snapshot(&denoised)?));
        }
        // Global part of de-attenuation: I − B_L ≈ J·t, so scale by 1/t̂,
        // with t̂ read off the coarse level (its 99.5th percentile of I − B_L
        // brought to `stretch_target`), capped at `stretch_max_gain`.
        let mut residual = Mat::default();
        core::subtract(&coarse, &bl_coarse, &mut residual, &core::no_array(), -1)?;
        let top = water::percentile(&water::histogram(&residual)?, 0.995).max(1.0);
        let gain = (self.params.stretch_target / top).clamp(1.0, self.params.stretch_max_gain);
        if gain > 1.0 {
            let mut scaled = Mat::default();
            denoised.convert_to(&mut scaled, CV_8U, gain, 0.0)?;
            denoised = scaled;
        }

        // 3./4. De-attenuation and de-blurring.
        let margin = 16 + psf.radius_px();
        let frame = Rect::new(0, 0, full.width, full.height);
        let rois = if self.params.roi_only {
            roi::find_rois(
                &coarse,
                COARSE_FACTOR,
                full,
                water.noise_sigma,
                margin,
                &self.params,
            )?
        } else {
            vec![frame]
        };
        let tile = self.params.clahe_tile_px;
        let image = match self.params.order {
            StageOrder::Paper => {
                let deatt = clahe(&denoised, clip, tile)?;
                if keep {
                    stages.push(("de-attenuated (CLAHE)".to_string(), snapshot(&deatt)?));
                }
                let deblurred = self.deblur(&deatt, &rois, &psf)?;
                if keep {
                    stages.push(("deblurred (Wiener)".to_string(), snapshot(&deblurred)?));
                }
                deblurred
            }
            StageOrder::Physical => {
                let deblurred = self.deblur(&denoised, &rois, &psf)?;
                if keep {
                    stages.push(("deblurred (Wiener)".to_string(), snapshot(&deblurred)?));
                }
                let deatt = clahe(&deblurred, clip, tile)?;
                if keep {
                    stages.push(("de-attenuated (CLAHE)".to_string(), snapshot(&deatt)?));
                }
                deatt
            }
        };

        // 5. Pyramid level for the detector.
        let pyramid_level = self.choose_level(&image, &rois)?;
        let level_image = if pyramid_level > 0 {
            let mut cur = image.try_clone()?;
            for _ in 0..pyramid_level {
                let mut down = Mat::default();
                imgproc::pyr_down_def(&cur, &mut down)?;
                cur = down;
            }
            Some(cur)
        } else {
            None
        };
        if keep {
            if let Some(l) = &level_image {
                let mut up = Mat::default();
                imgproc::resize(l, &mut up, full, 0.0, 0.0, imgproc::INTER_NEAREST)?;
                stages.push((format!("pyramid level {pyramid_level}"), up));
            }
        }
        let restored = Restored {
            image,
            pyramid_level,
            level_image,
            estimated_c_per_m: c,
            backscatter: water.backscatter,
            rois,
            stages: keep.then_some(stages),
        };
        let frame_params = HoirmFrameParams {
            water,
            c_per_m: c,
            alpha,
            gain,
            clahe_clip: clip,
            psf,
        };
        Ok((restored, frame_params))
    }
}

impl Restorer for Hoirm {
    fn method(&self) -> Method {
        Method::Hoirm
    }

    fn restore(&mut self, gray: &Mat, stamp_ns: u64) -> Result<Restored, RestoreError> {
        Ok(self.restore_with_params(gray, stamp_ns)?.0)
    }
}
