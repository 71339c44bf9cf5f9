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
//!    `I − B_L` stretched to `stretch_target`) on the whole frame (8-bit);
//!    in the regions of interest `gain·(I − B_L)` is recomputed in f32,
//!    smoothed by a Gaussian when the estimated edge step over noise is low
//!    (our addition, [`water::denoise_sigma_px`]), then CLAHE with a clip
//!    limit growing with `c` (divided by the gain; in denoised regions raised
//!    to bring the edge step to `clahe_contrast_target`) for the local part.
//! 4. De-blurring: Wiener deconvolution with Eq. (14)'s PSF, `p` and σ from
//!    `c`, the noise-to-signal ratio measured in each region (in a denoised
//!    region: that of the region before smoothing, on the 1/2 level).
//!    CLAHE and deconvolution run in the regions of interest ([`super::roi`],
//!    feathered into the globally restored frame) or on the whole frame;
//!    [`StageOrder`] swaps 3b and 4.
//! 5. Pyramid level: the coarser of (a) the finest level at which the PSF's
//!    σ is at most `level_blur_px` and (b) the finest level at which the
//!    marker region's edge step over noise reaches `edge_snr_target`
//!    (measured with `pyrDown` on the region), but no coarser than keeps the
//!    largest region `min_roi_side_at_level_px` wide.

use super::ambient::AmbientLight;
use super::psf::{self, GgPsf, Wiener};
use super::water::{self, WaterEstimate};
use super::{
    check_input, clahe_grid, clahe_tiles, coarse_level, roi, snapshot, Method, RestoreError,
    RestoreParams, Restored, Restorer, StageOrder,
};
use opencv::core::{self, Mat, Rect, Size, CV_32F, CV_8U};
use opencv::imgproc;
use opencv::prelude::*;
use std::sync::{Arc, Mutex, PoisonError};

/// Down-sampling of the level used for the water estimate, ambient light and ROI search.
pub const COARSE_FACTOR: i32 = 8;

/// Width of the ramp over which a restored region is blended into the frame, pixels.
pub const FEATHER_PX: i32 = 16;

/// Coarsest level of 2x2 means on which a region's noise is read for the
/// Wiener NSR. The frame's estimate reads the 4x4 means too
/// ([`water::NOISE_LEVELS`]), but a region is mostly marker, and there the
/// cells' own edges lift the 4x4 level's median: on the ideal simulator it
/// cut HOIRM's CNR lead over a plain low-pass at 8.22 /m from 15 % to 9 %
/// (`restore_synthetic`) and widened the median pose error at 10.13 /m
/// (`eval probe hoirm`, 6 frames: 1.48 → 2.17 mm); through the realistic
/// camera the 2x2 level keeps most of the gain (`docs/results.md`).
const NSR_NOISE_LEVELS: u32 = 1;

/// Side of the patch on which the pyramid level is chosen, pixels.
const LEVEL_PATCH_PX: i32 = 384;

/// HOIRM with its per-camera state.
#[derive(Debug)]
pub struct Hoirm {
    params: RestoreParams,
    ambient: AmbientLight,
    wiener: Wiener,
    /// The filter cache of the frames' [`FineRestoration`]s.
    fine_wiener: Arc<Mutex<Wiener>>,
}

/// How to restore again, keeping detail, the regions where HOIRM gave it
/// up in one frame: there it smoothed the region (denoising, for edges weak
/// against the noise) or deconvolved it with Eq. (14)'s halo alone, whose
/// Wiener filter cuts every frequency the halo does not pass. Both serve a
/// marker whose modules are wider than the halo (turbid water, a marker
/// near) and erase one whose modules are 2–4 px (a marker metres away in
/// clear water), and the image does not tell which is in view. Here the
/// region is restored with neither: no smoothing, and the PSF with its
/// unscattered part (`psf::GgPsf::direct`), whose spectrum keeps the fine
/// detail, deconvolved at full resolution (`docs/restoration.md`, "Fine
/// detail").
#[derive(Debug, Clone)]
pub struct FineRestoration {
    /// The regions that gave up detail (full-resolution pixels).
    pub regions: Vec<Rect>,
    /// The ambient light at the coarse level, scaled by α (f32).
    bl_coarse_f: Mat,
    gain: f64,
    /// CLAHE's clip limit, over the gain (not raised for denoising).
    clip: f64,
    /// Eq. (14)'s PSF with the unscattered part.
    psf: GgPsf,
    deblur: bool,
    params: RestoreParams,
    wiener: Arc<Mutex<Wiener>>,
}

impl FineRestoration {
    /// `image` (the frame's restoration) with `regions` (normally some of
    /// [`Self::regions`]) restored again from `gray`, the frame it was
    /// restored from, keeping their detail.
    pub fn image(&self, image: &Mat, gray: &Mat, regions: &[Rect]) -> Result<Mat, RestoreError> {
        let frame = Rect::new(0, 0, gray.cols(), gray.rows());
        if image.size()? != gray.size()? {
            return Err(RestoreError::FrameMismatch {
                restored: (image.cols(), image.rows()),
                given: (gray.cols(), gray.rows()),
            });
        }
        let mut out = image.try_clone()?;
        let mut wiener = self.wiener.lock().unwrap_or_else(PoisonError::into_inner);
        for &r in regions {
            let r = r & frame;
            if r.width < 1 || r.height < 1 {
                continue;
            }
            let (diff, _) = veil_removed_region(gray, &self.bl_coarse_f, r)?;
            let view = finish_region(diff, self.gain, 0.0)?;
            let deblur = self.deblur.then_some(&self.psf);
            let (_, last) = restore_region_with(
                &mut wiener,
                &self.params,
                &view,
                (self.clip, clahe_tiles(r.size(), self.params.clahe_tile_px)),
                deblur,
                None,
                0,
            )?;
            feather_into(&mut out, &last, r, frame)?;
        }
        Ok(out)
    }
}

/// What every region of one frame is restored with
/// ([`Hoirm::restore_one_region`]).
struct RegionInputs<'a> {
    gray: &'a Mat,
    /// The ambient light at the coarse level, scaled by α (f32).
    bl_coarse_f: &'a Mat,
    water: &'a WaterEstimate,
    /// Eq. (14)'s PSF for the water.
    psf: GgPsf,
    c: f64,
    /// The global de-attenuation gain.
    gain: f64,
    /// CLAHE's clip limit over the gain.
    clip: f64,
    denoise_sigma: f64,
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
    /// σ of the Gaussian smoothing before the local stretch (0: none), full-resolution pixels.
    pub denoise_sigma_px: f64,
    /// PSF σ measured on the first region's edges (before clamping), when it could be.
    pub measured_psf_sigma_px: Option<f64>,
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
            fine_wiener: Arc::new(Mutex::new(Wiener::new())),
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
        let direct = if self.params.psf_unscattered {
            water::direct_share(c_per_m, &self.params)
        } else {
            0.0
        };
        (
            water::clahe_clip(c_per_m, &self.params),
            GgPsf {
                p,
                sigma_px,
                direct,
            },
        )
    }

    /// Choose the pyramid level for edge detection on a patch of `img`
    /// around the largest region of interest (the centre when there is none).
    fn choose_level(&self, img: &Mat, rois: &[Rect], psf: &GgPsf) -> Result<u32, RestoreError> {
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
        // The largest region is normally the marker; small ones are often
        // specks of veil texture and must not hold the level down.
        let focus_side = focus.width.min(focus.height);
        // Blur rule: the finest level at which the forward-scatter PSF's σ is
        // at most `level_blur_px` — edges a few pixels wide, what a contour
        // detector expects.
        let mut blur_level = 0u32;
        while blur_level < self.params.max_pyramid_level
            && psf.sigma_px / f64::from(1u32 << blur_level) > self.params.level_blur_px
        {
            blur_level += 1;
        }
        let fits = |level: u32| (focus_side >> level) >= self.params.min_roi_side_at_level_px;
        let mut patch = Mat::roi(img, patch_rect)?.try_clone()?;
        let mut best = (0u32, 0.0f64);
        for level in 0..=self.params.max_pyramid_level {
            if level > 0 {
                if (focus_side >> level) < self.params.min_roi_side_at_level_px
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
                best = (level, f64::INFINITY);
                break;
            }
            if snr > best.1 {
                best = (level, snr);
            }
        }
        // Noise rule: the finest level whose edge step / noise reaches the
        // target. The coarser of the two, as far as the regions still fit.
        let mut level = best.0.max(blur_level);
        while level > 0 && !fits(level) {
            level -= 1;
        }
        Ok(level)
    }

    /// The regions of interest of `gray` (`coarse` its coarse level), or
    /// the whole frame without [`RestoreParams::roi_only`].
    fn regions(
        &self,
        gray: &Mat,
        coarse: &Mat,
        water: &WaterEstimate,
        psf: &GgPsf,
    ) -> Result<Vec<Rect>, RestoreError> {
        let full = gray.size()?;
        if !self.params.roi_only {
            return Ok(vec![Rect::new(0, 0, full.width, full.height)]);
        }
        let margin = FEATHER_PX + 8 + psf.radius_px() / 4;
        let coarse_f = roi::coarse_level_f32(gray, coarse.size()?)?;
        roi::find_rois(
            &coarse_f,
            COARSE_FACTOR,
            full,
            water.noise_sigma,
            margin,
            &self.params,
        )
    }

    /// The names of the two local stages, in the order they run.
    fn local_stage_names(&self) -> [&'static str; 2] {
        match self.params.order {
            StageOrder::Paper => ["de-attenuated (CLAHE)", "deblurred (Wiener)"],
            StageOrder::Physical => ["deblurred (Wiener)", "de-attenuated (CLAHE)"],
        }
    }

    /// Steps 3b./4. in one region `r` of the frame: the veil removed, the
    /// PSF's width measured when the region's edges tell (pushed to
    /// `measured_sigma`), denoised, de-attenuated and deblurred. Returns
    /// the region after the first local stage (when `want_first`) and
    /// after both, and whether it gave up detail (smoothed, or deconvolved
    /// with the halo alone or on a coarser level: [`FineRestoration`]).
    fn restore_one_region(
        &mut self,
        g: &RegionInputs<'_>,
        r: Rect,
        measured_sigma: &mut Vec<f64>,
        want_first: bool,
    ) -> Result<(Option<Mat>, Mat, bool), RestoreError> {
        let (diff, diff_std) = veil_removed_region(g.gray, g.bl_coarse_f, r)?;
        // The PSF's width from the region's own edges when they tell
        // (else Eq. (14)'s σ from c), see `psf::edge_blur_sigma_px`.
        let region_psf = if self.params.psf_sigma_from_image && g.denoise_sigma == 0.0 {
            let est = psf::edge_blur_sigma_px(&diff, g.water.noise_sigma)?;
            if let Some(s) = est {
                measured_sigma.push(s);
            }
            // The estimate reads the sharpest component of the blur (a
            // sharp unscattered core under a wide halo reads narrow), so
            // it only overrides Eq. (14) when it finds the edges much
            // sharper than Eq. (14)'s σ.
            let trusted = est.filter(|s| *s < self.params.psf_trust_ratio * g.psf.sigma_px);
            GgPsf {
                sigma_px: trusted.map_or(g.psf.sigma_px, |s| s.max(self.params.psf_min_sigma_px)),
                ..g.psf
            }
        } else {
            g.psf
        };
        // In a denoised region the NSR is the white-noise one of the
        // region before smoothing (measured after it, the noise looks
        // small and the filter would sharpen it back).
        let nsr = if g.denoise_sigma > 0.0 {
            let k = self.params.nsr_gain * g.water.noise_sigma.powi(2)
                / (diff_std * diff_std).max(1e-6);
            Some(k.clamp(self.params.nsr_min, self.params.nsr_max))
        } else {
            None
        };
        // Denoised regions are deconvolved too, with the NSR of the
        // region before smoothing (`deconv_when_denoised`); measured on the
        // smoothed region the NSR is small and the filter sharpens the
        // noise back (calibrated water, 12.20 /m: detection 0.20).
        let deblur = (g.c >= self.params.deconv_min_c_per_m
            && (g.denoise_sigma == 0.0 || self.params.deconv_when_denoised))
            .then_some(&region_psf);
        // A region smoothed by σ ≥ 2 px has nothing left above the half
        // level's Nyquist frequency (a Gaussian of σ 2 passes 0.7 % at
        // 1/4 cycle/px): deconvolve it there, on 4x smaller DFTs.
        let level = if g.denoise_sigma >= 2.0 {
            self.params
                .deconv_level
                .max(self.params.denoised_deconv_level)
        } else {
            self.params.deconv_level
        };
        let lost =
            g.denoise_sigma > 0.0 || deblur.is_some_and(|psf| psf.direct <= 0.0 || level > 0);
        // The tiles of the region at full resolution, whatever level it is
        // stretched on (OpenCV's clip limit is per tile area, so the
        // stretch is nearly the same).
        let tiles = clahe_tiles(r.size(), self.params.clahe_tile_px);
        let (first, last) = if level > 0 && g.denoise_sigma >= 2.0 {
            // …and then it is smoothed and stretched there too: the half
            // level's pyramid kernel (σ 1 px) with σ/2 on top smooths as σ
            // at full resolution before the stretch and the kernel did,
            // on a quarter of the pixels.
            let small = finish_region(pyr_down(&diff)?, g.gain, 0.5 * g.denoise_sigma)?;
            let half_psf = deblur.map(|p| GgPsf {
                sigma_px: 0.5 * p.sigma_px,
                ..*p
            });
            let (first, last) = restore_region_with(
                &mut self.wiener,
                &self.params,
                &small,
                (g.clip, tiles),
                half_psf.as_ref(),
                nsr,
                level - 1,
            )?;
            let first = if want_first {
                Some(upsample_pyramid_level(&first, 1, r.size())?)
            } else {
                None
            };
            (first, upsample_pyramid_level(&last, 1, r.size())?)
        } else {
            let view = finish_region(diff, g.gain, g.denoise_sigma)?;
            let (first, last) = restore_region_with(
                &mut self.wiener,
                &self.params,
                &view,
                (g.clip, tiles),
                deblur,
                nsr,
                level,
            )?;
            (want_first.then_some(first), last)
        };
        Ok((first, last, lost))
    }

    /// Steps 3b./4. in every region of `rois`, each feathered into `image`
    /// (and its first local stage into `first_stage`); returns the PSF
    /// widths measured on the regions and the regions that gave up detail.
    fn restore_regions(
        &mut self,
        g: &RegionInputs<'_>,
        rois: &[Rect],
        image: &mut Mat,
        mut first_stage: Option<&mut Mat>,
    ) -> Result<(Vec<f64>, Vec<Rect>), RestoreError> {
        let frame = Rect::new(0, 0, image.cols(), image.rows());
        let mut measured_sigma = Vec::new();
        let mut detail_lost = Vec::new();
        for &r in rois {
            let want_first = first_stage.is_some();
            let (first, last, lost) =
                self.restore_one_region(g, r, &mut measured_sigma, want_first)?;
            if lost {
                detail_lost.push(r);
            }
            feather_into(image, &last, r, frame)?;
            if let (Some(st), Some(first)) = (first_stage.as_deref_mut(), first) {
                feather_into(st, &first, r, frame)?;
            }
        }
        Ok((measured_sigma, detail_lost))
    }

    /// Whether the regions that gave up detail, `detail_lost`, are to be
    /// searched again ([`RestoreParams::fine_pass`]). A frame restored whole
    /// because nothing in it stood out from the noise (`roi::find_rois`'
    /// fallback) is searched once, as restored for the water, unless
    /// [`RestoreParams::fine_pass_whole_frame`].
    fn fine_pass_wanted(&self, rois: &[Rect], detail_lost: &[Rect], full: Size) -> bool {
        let whole_fallback = self.params.roi_only
            && rois.len() == 1
            && (rois[0].width, rois[0].height) == (full.width, full.height);
        self.params.fine_pass
            && !detail_lost.is_empty()
            && (self.params.fine_pass_whole_frame || !whole_fallback)
    }

    /// The [`FineRestoration`] of `regions` in water of attenuation `c`:
    /// the frame's ambient light, gain and undenoised clip limit (over the
    /// gain), `psf` with its unscattered part.
    fn fine_restoration(
        &self,
        regions: Vec<Rect>,
        bl_coarse_f: Mat,
        gain: f64,
        clip: f64,
        psf: GgPsf,
        c: f64,
    ) -> FineRestoration {
        FineRestoration {
            regions,
            bl_coarse_f,
            gain,
            clip,
            psf: GgPsf {
                direct: water::direct_share(c, &self.params),
                ..psf
            },
            deblur: c >= self.params.deconv_min_c_per_m,
            params: self.params.clone(),
            wiener: Arc::clone(&self.fine_wiener),
        }
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
        if c < self.params.passthrough_below_c_per_m {
            // Clear water: nothing to restore (the ambient state above is
            // still updated, so it is current when the water turns).
            let frame_params = HoirmFrameParams {
                water,
                c_per_m: c,
                alpha,
                gain: 1.0,
                clahe_clip: clip,
                psf,
                denoise_sigma_px: 0.0,
                measured_psf_sigma_px: None,
            };
            return Ok((passed_through(gray, keep, &frame_params)?, frame_params));
        }
        let mut bl = Mat::default();
        imgproc::resize(&bl_coarse, &mut bl, full, 0.0, 0.0, imgproc::INTER_LINEAR)?;

        // 3a. Global part of de-attenuation: I − B_L ≈ J·t, so scale by 1/t̂,
        // with t̂ read off the coarse level (its 99.5th percentile of I − B_L
        // brought to `stretch_target`), capped at `stretch_max_gain`.
        let mut residual = Mat::default();
        core::subtract(&coarse, &bl_coarse, &mut residual, &core::no_array(), -1)?;
        let top = water::percentile(&water::histogram(&residual)?, 0.995).max(1.0);
        let gain = (self.params.stretch_target / top).clamp(1.0, self.params.stretch_max_gain);
        // gain·(I − B_L) in one saturating pass (Eq. (13) and the 1/t̂ gain).
        let mut global = Mat::default();
        core::add_weighted(gray, gain, &bl, -gain, 0.0, &mut global, CV_8U)?;
        if keep {
            let mut denoised = Mat::default();
            core::subtract(gray, &bl, &mut denoised, &core::no_array(), -1)?;
            stages.push(("input".to_string(), snapshot(gray)?));
            stages.push(("ambient light B_L".to_string(), bl));
            stages.push(("denoised (I - B_L)".to_string(), denoised));
        }

        // 3b./4. Local de-attenuation (CLAHE) and de-blurring (Wiener), in
        // the regions of interest (feathered into the globally restored
        // frame) or on the whole frame.
        let rois = self.regions(gray, &coarse, &water, &psf)?;
        let mut image = global.try_clone()?;
        let mut first_stage = keep.then(|| global.try_clone()).transpose()?;
        // Denoising before the local stretch when the edges are weak
        // against the noise, and the stretch it allows.
        let denoise_sigma = water::denoise_sigma_px(&water, &self.params);
        let clip_undenoised = clip;
        let clip = if denoise_sigma > 0.0 {
            clip.max(self.params.clahe_contrast_target / water.local_contrast.max(0.5))
        } else {
            clip
        } / gain;
        let mut bl_coarse_f = Mat::default();
        set_mean.convert_to(&mut bl_coarse_f, CV_32F, alpha, 0.0)?;
        let region = RegionInputs {
            gray,
            bl_coarse_f: &bl_coarse_f,
            water: &water,
            psf,
            c,
            gain,
            clip,
            denoise_sigma,
        };
        let (measured_sigma, detail_lost) =
            self.restore_regions(&region, &rois, &mut image, first_stage.as_mut())?;
        if let Some(st) = first_stage {
            let [first, second] = self.local_stage_names();
            stages.push((first.to_string(), st));
            stages.push((second.to_string(), snapshot(&image)?));
        }

        // 5. Pyramid level for the detector.
        let pyramid_level = self.choose_level(&image, &rois, &psf)?;
        let level_image = level_image(&image, pyramid_level)?;
        if keep {
            if let Some(l) = &level_image {
                let mut up = Mat::default();
                imgproc::resize(l, &mut up, full, 0.0, 0.0, imgproc::INTER_NEAREST)?;
                stages.push((format!("pyramid level {pyramid_level}"), up));
            }
        }
        let fine = self.fine_pass_wanted(&rois, &detail_lost, full).then(|| {
            self.fine_restoration(
                detail_lost,
                bl_coarse_f,
                gain,
                clip_undenoised / gain,
                psf,
                c,
            )
        });
        let restored = Restored {
            image,
            pyramid_level,
            level_image,
            estimated_c_per_m: c,
            backscatter: water.backscatter,
            rois,
            stages: keep.then_some(stages),
            fine,
        };
        let frame_params = HoirmFrameParams {
            water,
            c_per_m: c,
            alpha,
            gain,
            clahe_clip: clip,
            psf,
            denoise_sigma_px: denoise_sigma,
            measured_psf_sigma_px: measured_sigma.first().copied(),
        };
        Ok((restored, frame_params))
    }
}

/// `image` reduced `level` times by the Gaussian pyramid; `None` at level 0.
fn level_image(image: &Mat, level: u32) -> Result<Option<Mat>, RestoreError> {
    if level == 0 {
        return Ok(None);
    }
    let mut cur = image.try_clone()?;
    for _ in 0..level {
        let mut down = Mat::default();
        imgproc::pyr_down_def(&cur, &mut down)?;
        cur = down;
    }
    Ok(Some(cur))
}

/// CLAHE (clip limit and tile grid `(clip, tiles)`) and Wiener
/// deconvolution of one region of the globally de-attenuated frame, in the
/// configured order; returns `(after the first stage, after both)`.
fn restore_region_with(
    wiener: &mut Wiener,
    params: &RestoreParams,
    src: &(impl MatTraitConst + core::ToInputArray),
    (clip, tiles): (f64, Size),
    psf: Option<&GgPsf>,
    nsr: Option<f64>,
    level: u32,
) -> Result<(Mat, Mat), RestoreError> {
    Ok(match (params.order, psf) {
        (StageOrder::Paper, Some(psf)) => {
            let deatt = clahe_grid(src, clip, tiles)?;
            let deblurred = deconvolve_with(wiener, params, &deatt, psf, nsr, level)?;
            (deatt, deblurred)
        }
        (StageOrder::Physical, Some(psf)) => {
            let deblurred = deconvolve_with(wiener, params, src, psf, nsr, level)?;
            let deatt = clahe_grid(&deblurred, clip, tiles)?;
            (deblurred, deatt)
        }
        (_, None) => {
            let deatt = clahe_grid(src, clip, tiles)?;
            (deatt.try_clone()?, deatt)
        }
    })
}

/// Wiener deconvolution of a region at pyramid level `level`: the region
/// is `pyrDown`-ed, deconvolved with the PSF scaled to that level, and
/// up-sampled; the DFTs are 4x smaller per level. Forward scatter is a
/// low-frequency degradation (a halo of σ ≈ 5 px at working range), so
/// what it needs undone lies well below the 1/2 level's Nyquist
/// frequency; the band above it (mostly CLAHE-amplified noise in a
/// denoised region) is dropped, not kept: docs/restoration.md,
/// "Deconvolution level".
fn deconvolve_with(
    wiener: &mut Wiener,
    params: &RestoreParams,
    src: &(impl MatTraitConst + core::ToInputArray),
    psf: &GgPsf,
    nsr_given: Option<f64>,
    level: u32,
) -> Result<Mat, RestoreError> {
    if level == 0 {
        let nsr = match nsr_given {
            Some(k) => k,
            None => nsr_of(params, src)?,
        };
        return wiener.deconvolve(src, psf, nsr);
    }
    let mut small = Mat::default();
    imgproc::pyr_down_def(src, &mut small)?;
    for _ in 1..level {
        let mut next = Mat::default();
        imgproc::pyr_down_def(&small, &mut next)?;
        small = next;
    }
    let psf_l = GgPsf {
        sigma_px: psf.sigma_px / f64::from(1u32 << level),
        ..*psf
    };
    let nsr = match nsr_given {
        Some(k) => k,
        None => nsr_of(params, &small)?,
    };
    let restored = wiener.deconvolve(&small, &psf_l, nsr)?;
    // The restored level, up-sampled: the band above its Nyquist
    // frequency — mostly CLAHE-amplified noise, which the full-resolution
    // Wiener filter would suppress anyway — is dropped.
    upsample_pyramid_level(&restored, level, src.size()?)
}

/// Wiener `K = gain·σ_noise²/σ_signal²`, measured on the region, clamped.
/// The noise is read across scales ([`NSR_NOISE_LEVELS`]): noise a codec
/// or demosaicing has low-passed hides from a 3x3 mask at full
/// resolution, and a filter told the region is clean sharpens it into
/// blotches (`docs/restoration.md`, "Water estimate").
fn nsr_of(
    params: &RestoreParams,
    view: &(impl MatTraitConst + core::ToInputArray),
) -> Result<f64, RestoreError> {
    let noise = water::noise_sigma_across_scales(view, 2, NSR_NOISE_LEVELS)?;
    let (mut mean, mut std) = (core::Scalar::default(), core::Scalar::default());
    core::mean_std_dev(view, &mut mean, &mut std, &core::no_array())?;
    let signal_var = (std[0] * std[0]).max(1e-6);
    Ok((params.nsr_gain * noise * noise / signal_var).clamp(params.nsr_min, params.nsr_max))
}

/// The frame itself as its restoration (clear water), with the input as
/// its one stage when `keep`.
fn passed_through(
    gray: &Mat,
    keep: bool,
    frame: &HoirmFrameParams,
) -> Result<Restored, RestoreError> {
    let stages = if keep {
        vec![(
            "input (clear water: passed through)".to_string(),
            snapshot(gray)?,
        )]
    } else {
        Vec::new()
    };
    Ok(Restored {
        image: gray.try_clone()?,
        pyramid_level: 0,
        level_image: None,
        estimated_c_per_m: frame.c_per_m,
        backscatter: frame.water.backscatter,
        rois: Vec::new(),
        stages: keep.then_some(stages),
        fine: None,
    })
}

impl Restorer for Hoirm {
    fn method(&self) -> Method {
        Method::Hoirm
    }

    fn restore(&mut self, gray: &Mat, stamp_ns: u64) -> Result<Restored, RestoreError> {
        Ok(self.restore_with_params(gray, stamp_ns)?.0)
    }
}

/// Bilinear up-sampling of pyramid level `level` (made by `level` ×
/// `pyrDown`) to `size`, on the pyramid's own pixel grid.
///
/// `pyrDown` centres level pixel `i` on full-resolution pixel `2i` (its
/// 5-tap kernel is centred there), not on `2i + 0.5` as `resize` assumes for a
/// 2x scale: `resize(…, INTER_LINEAR)` of a `pyrDown`-ed image shifts it by
/// half a full-resolution pixel right and down per level. That shift (+0.5 px
/// on every corner of a turbid-water marker, whose denoised regions are
/// deconvolved on the half level) was the largest error of the accuracy test
/// at 8.22 /m. Here full-resolution `x` samples the level at `x / 2^level`.
fn upsample_pyramid_level(
    level_img: &Mat,
    level: u32,
    size: core::Size,
) -> Result<Mat, RestoreError> {
    let s = 1.0 / f64::from(1u32 << level);
    let m = Mat::from_slice_2d(&[[s, 0.0, 0.0], [0.0, s, 0.0]])?;
    let mut out = Mat::default();
    imgproc::warp_affine(
        level_img,
        &mut out,
        &m,
        size,
        imgproc::INTER_LINEAR | imgproc::WARP_INVERSE_MAP,
        core::BORDER_REPLICATE,
        core::Scalar::default(),
    )?;
    Ok(out)
}

/// `I − B_L` on region `r` of the frame `gray`, in f32: `B_L` is
/// interpolated bilinearly from its coarse level `bl_coarse` (f32, the frame
/// divided into `bl_coarse`'s grid) exactly as a full-resolution
/// `INTER_LINEAR` resize would, without rounding it to whole grey levels
/// first (after a gain of up to 6 and CLAHE, 1-DN steps of the veil become
/// contour bands as strong as a turbid marker's edges). One pass: per row
/// the two coarse rows blended, then each pixel's two taps (`warpAffine`
/// and a subtraction took ~3x as long: 3.4 against 1.2 ms for the ~0.76 Mpx
/// of regions in a murky realistic frame). Also returns the difference's
/// standard deviation (over its pixels, as `cv::meanStdDev` gives it).
fn veil_removed_region(gray: &Mat, bl_coarse: &Mat, r: Rect) -> Result<(Mat, f64), RestoreError> {
    // (The region's view fails, as an OpenCV error, when `r` leaves the frame.)
    let region = Mat::roi(gray, r)?;
    let (cw, ch) = (bl_coarse.cols(), bl_coarse.rows());
    let sx = f64::from(gray.cols()) / f64::from(cw);
    let sy = f64::from(gray.rows()) / f64::from(ch);
    // Bilinear taps of full-resolution pixel `p` on a coarse axis of `n`
    // samples, as `INTER_LINEAR` takes them (source `(p + ½)/s − ½`,
    // the edge sample beyond either end).
    let taps = |p: i32, s: f64, n: i32| -> (usize, usize, f32) {
        let u = ((f64::from(p) + 0.5) / s - 0.5).clamp(0.0, f64::from(n - 1));
        let i0 = u.floor();
        let i1 = (i0 + 1.0).min(f64::from(n - 1));
        (i0 as usize, i1 as usize, (u - i0) as f32)
    };
    let cols: Vec<(usize, usize, f32)> = (r.x..r.x + r.width).map(|x| taps(x, sx, cw)).collect();
    let mut diff =
        Mat::new_rows_cols_with_default(r.height, r.width, CV_32F, core::Scalar::all(0.0))?;
    let mut veil_row = vec![0f32; cw as usize];
    let (mut sum, mut sum_sq) = (0f64, 0f64);
    for y in 0..r.height {
        let (j0, j1, fy) = taps(r.y + y, sy, ch);
        let (a, b) = (
            bl_coarse.at_row::<f32>(j0 as i32)?,
            bl_coarse.at_row::<f32>(j1 as i32)?,
        );
        for ((v, &a), &b) in veil_row.iter_mut().zip(a).zip(b) {
            *v = a + fy * (b - a);
        }
        let src = region.at_row::<u8>(y)?;
        for ((d, &g), &(i0, i1, fx)) in diff.at_row_mut::<f32>(y)?.iter_mut().zip(src).zip(&cols) {
            let (a, b) = (veil_row[i0], veil_row[i1]);
            *d = f32::from(g) - (a + fx * (b - a));
            let v = f64::from(*d);
            sum += v;
            sum_sq += v * v;
        }
    }
    let n = f64::from(r.width) * f64::from(r.height);
    let mean = sum / n.max(1.0);
    let std = (sum_sq / n.max(1.0) - mean * mean).max(0.0).sqrt();
    Ok((diff, std))
}

/// `img` reduced once by the Gaussian pyramid (same depth).
fn pyr_down(img: &Mat) -> Result<Mat, RestoreError> {
    let mut small = Mat::default();
    imgproc::pyr_down_def(img, &mut small)?;
    Ok(small)
}

/// `gain·diff` (f32) smoothed with a Gaussian of `denoise_sigma` px when
/// > 0, rounded to 8 bits.
fn finish_region(mut diff: Mat, gain: f64, denoise_sigma: f64) -> Result<Mat, RestoreError> {
    if denoise_sigma > 0.0 {
        let mut smooth = Mat::default();
        imgproc::gaussian_blur(
            &diff,
            &mut smooth,
            core::Size::new(0, 0),
            denoise_sigma,
            denoise_sigma,
            core::BORDER_REFLECT_101,
        )?;
        diff = smooth;
    }
    let mut out = Mat::default();
    diff.convert_to(&mut out, CV_8U, gain, 0.0)?;
    Ok(out)
}

/// Paste `region` (the size of `r`) into `dst` at `r`, blending linearly
/// from `dst`'s own pixels at the region's edges to `region`'s over
/// [`FEATHER_PX`] (sides on the frame border are not blended), so a region's
/// border never becomes an edge the detector could take for a marker side.
fn feather_into(dst: &mut Mat, region: &Mat, r: Rect, frame: Rect) -> Result<(), RestoreError> {
    let f = FEATHER_PX as f32;
    let left = r.x > frame.x;
    let top = r.y > frame.y;
    let right = r.x + r.width < frame.x + frame.width;
    let bottom = r.y + r.height < frame.y + frame.height;
    let width = r.width.max(0) as usize;
    // Columns this far from both sides are the region's own in every row
    // the vertical ramp leaves alone: (x + 0.5) and (width − x − 0.5) ≥
    // FEATHER_PX + 0.5 > FEATHER_PX.
    let band = (FEATHER_PX as usize + 1).min(width);
    let middle = band..width.saturating_sub(band).max(band);
    for y in 0..r.height {
        let dy_top = if top { y as f32 + 0.5 } else { f32::INFINITY };
        let dy_bot = if bottom {
            (r.height - y) as f32 - 0.5
        } else {
            f32::INFINITY
        };
        let wy = (dy_top.min(dy_bot) / f).min(1.0);
        let src = region.at_row::<u8>(y)?;
        let out = &mut dst.at_row_mut::<u8>(r.y + y)?[r.x as usize..(r.x + r.width) as usize];
        let blend = |x: usize, o: &mut u8| {
            let dx_l = if left { x as f32 + 0.5 } else { f32::INFINITY };
            let dx_r = if right {
                (width - x) as f32 - 0.5
            } else {
                f32::INFINITY
            };
            let w = wy.min((dx_l.min(dx_r) / f).min(1.0));
            *o = if w >= 1.0 {
                src[x]
            } else {
                (w * src[x] as f32 + (1.0 - w) * *o as f32).round() as u8
            };
        };
        if wy >= 1.0 {
            out[middle.clone()].copy_from_slice(&src[middle.clone()]);
            for x in (0..middle.start).chain(middle.end..width) {
                blend(x, &mut out[x]);
            }
        } else {
            for (x, o) in out.iter_mut().enumerate() {
                blend(x, o);
            }
        }
    }
    Ok(())
}

#[cfg(test)]
mod tests {
    use super::*;
    use opencv::core::{Scalar, CV_32FC1, CV_8UC1};

    /// The veil removed from a region is the full-frame bilinear up-sampling
    /// of the coarse ambient light, in f32: no whole-level steps, which a
    /// gain of 6 would turn into 6-level contour bands.
    #[test]
    fn veil_removal_in_a_region_matches_the_full_frame_and_has_no_steps() {
        let mut bl = Mat::new_rows_cols_with_default(30, 40, CV_32FC1, Scalar::all(0.0)).unwrap();
        for y in 0..30 {
            for (x, v) in bl.at_row_mut::<f32>(y).unwrap().iter_mut().enumerate() {
                *v = 100.3 + 0.37 * x as f32 + 0.21 * y as f32;
            }
        }
        let gray = Mat::new_rows_cols_with_default(240, 320, CV_8UC1, Scalar::all(150.0)).unwrap();
        // `frame − veil` on region `r`, and its spread, against the veil
        // resized to the whole frame by OpenCV and `cv::meanStdDev`.
        let check = |frame: &Mat, veil: &Mat, r: Rect| -> Mat {
            let mut full = Mat::default();
            imgproc::resize(
                veil,
                &mut full,
                frame.size().unwrap(),
                0.0,
                0.0,
                imgproc::INTER_LINEAR,
            )
            .unwrap();
            let (diff, std) = veil_removed_region(frame, veil, r).unwrap();
            let (mut m, mut want_std) = (Scalar::default(), Scalar::default());
            core::mean_std_dev(&diff, &mut m, &mut want_std, &core::no_array()).unwrap();
            assert!(
                (std - want_std[0]).abs() < 1e-9 * want_std[0],
                "{std} vs {want_std:?}"
            );
            for y in 0..r.height {
                for x in 0..r.width {
                    let (fx, fy) = (r.x + x, r.y + y);
                    let g = f32::from(*frame.at_2d::<u8>(fy, fx).unwrap());
                    let want = g - *full.at_2d::<f32>(fy, fx).unwrap();
                    let got = *diff.at_2d::<f32>(y, x).unwrap();
                    assert!(
                        (want - got).abs() < 1e-3,
                        "{r:?} ({x}, {y}): {got} vs {want}"
                    );
                }
            }
            diff
        };
        let r = Rect::new(37, 53, 101, 77);
        let diff = check(&gray, &bl, r);
        // A veil that is not linear, on a frame that is not flat, and
        // regions at the frame's corners (the edge samples beyond it).
        let mut bumpy = bl.clone();
        for y in 0..30 {
            for (x, v) in bumpy.at_row_mut::<f32>(y).unwrap().iter_mut().enumerate() {
                *v = 80.0 + 40.0 * ((x * 7 + y as usize * 13) % 11) as f32 / 11.0;
            }
        }
        let mut textured = gray.clone();
        for y in 0..240 {
            for (x, v) in textured.at_row_mut::<u8>(y).unwrap().iter_mut().enumerate() {
                *v = ((x * 31 + y as usize * 17) % 256) as u8;
            }
        }
        for r in [
            Rect::new(0, 0, 45, 33),
            Rect::new(270, 200, 50, 40),
            Rect::new(0, 0, 320, 240),
        ] {
            check(&textured, &bumpy, r);
        }
        assert!(veil_removed_region(&gray, &bl, Rect::new(300, 0, 40, 10)).is_err());
        let out = finish_region(diff, 6.0, 0.0).unwrap();
        for y in 0..r.height {
            let row = out.at_row::<u8>(y).unwrap();
            for w in row.windows(2) {
                assert!(
                    (i32::from(w[1]) - i32::from(w[0])).abs() <= 1,
                    "row {y}: {w:?}"
                );
            }
        }
    }

    /// Sub-pixel position of the rising 50 % crossing along row `y`.
    fn crossing_x(img: &Mat, y: i32, lo: f64, hi: f64) -> f64 {
        let row: Vec<f64> = (0..img.cols())
            .map(|x| f64::from(*img.at_2d::<f32>(y, x).unwrap()))
            .collect();
        let half = 0.5 * (lo + hi);
        let i = row
            .windows(2)
            .position(|w| w[0] < half && w[1] >= half)
            .unwrap();
        i as f64 + (half - row[i]) / (row[i + 1] - row[i])
    }

    #[test]
    fn a_pyramid_level_comes_back_where_it_was() {
        // A blurred vertical edge at x = 60.3; down two levels and back.
        let (w, h) = (128, 64);
        let mut img = Mat::new_rows_cols_with_default(h, w, CV_32FC1, Scalar::all(0.0)).unwrap();
        for y in 0..h {
            for (x, v) in img.at_row_mut::<f32>(y).unwrap().iter_mut().enumerate() {
                let t = (x as f64 - 60.3) / 3.0;
                *v = (50.0 + 100.0 / (1.0 + (-1.7 * t).exp())) as f32;
            }
        }
        let before = crossing_x(&img, 30, 50.0, 150.0);
        for level in 1..=2u32 {
            let mut small = img.try_clone().unwrap();
            for _ in 0..level {
                let mut down = Mat::default();
                imgproc::pyr_down_def(&small, &mut down).unwrap();
                small = down;
            }
            let up = upsample_pyramid_level(&small, level, img.size().unwrap()).unwrap();
            let after = crossing_x(&up, 30, 50.0, 150.0);
            assert!(
                (after - before).abs() < 0.05,
                "level {level}: edge at {after:.3}, was {before:.3}"
            );
        }
    }

    #[test]
    fn feathered_region_has_no_step_at_its_border_but_keeps_frame_sides() {
        let frame = Rect::new(0, 0, 200, 100);
        let mut dst =
            Mat::new_rows_cols_with_default(100, 200, CV_8UC1, Scalar::all(100.0)).unwrap();
        let region = Mat::new_rows_cols_with_default(60, 80, CV_8UC1, Scalar::all(200.0)).unwrap();
        // Touches the top of the frame, inside on the other three sides.
        let r = Rect::new(50, 0, 80, 60);
        feather_into(&mut dst, &region, r, frame).unwrap();
        let at = |x: i32, y: i32| *dst.at_2d::<u8>(y, x).unwrap() as i32;
        // Interior: the region; outside: untouched.
        assert_eq!(at(90, 30), 200);
        assert_eq!(at(49, 30), 100);
        // Left edge: within 100/16·0.5 ≈ 3 grey levels of the outside, then a ramp.
        assert!(at(50, 30) - 100 <= 4, "{}", at(50, 30));
        for x in 50..50 + FEATHER_PX {
            assert!(at(x + 1, 30) - at(x, 30) <= 8, "step at x = {x}");
        }
        // Top side lies on the frame border: not blended.
        assert_eq!(at(90, 0), 200);
    }

    /// [`feather_into`] as sessions 1–43 ran it, pixel by pixel: the
    /// reference the copied middle must equal.
    #[allow(clippy::needless_range_loop)]
    fn feather_into_per_pixel(
        dst: &mut Mat,
        region: &Mat,
        r: Rect,
        frame: Rect,
    ) -> Result<(), RestoreError> {
        let f = FEATHER_PX as f32;
        let left = r.x > frame.x;
        let top = r.y > frame.y;
        let right = r.x + r.width < frame.x + frame.width;
        let bottom = r.y + r.height < frame.y + frame.height;
        for y in 0..r.height {
            let dy_top = if top { y as f32 + 0.5 } else { f32::INFINITY };
            let dy_bot = if bottom {
                (r.height - y) as f32 - 0.5
            } else {
                f32::INFINITY
            };
            let wy = (dy_top.min(dy_bot) / f).min(1.0);
            let src = region.at_row::<u8>(y)?;
            let out = &mut dst.at_row_mut::<u8>(r.y + y)?[r.x as usize..(r.x + r.width) as usize];
            for x in 0..r.width as usize {
                let dx_l = if left { x as f32 + 0.5 } else { f32::INFINITY };
                let dx_r = if right {
                    (r.width as usize - x) as f32 - 0.5
                } else {
                    f32::INFINITY
                };
                let w = wy.min((dx_l.min(dx_r) / f).min(1.0));
                out[x] = if w >= 1.0 {
                    src[x]
                } else {
                    (w * src[x] as f32 + (1.0 - w) * out[x] as f32).round() as u8
                };
            }
        }
        Ok(())
    }

    #[test]
    fn feathering_is_the_pixel_by_pixel_blend() {
        use rand::{Rng, SeedableRng};
        let mut rng = rand_chacha::ChaCha8Rng::seed_from_u64(5);
        let frame = Rect::new(0, 0, 120, 90);
        let mut base = Mat::new_rows_cols_with_default(90, 120, CV_8UC1, Scalar::all(0.0)).unwrap();
        for y in 0..90 {
            for v in base.at_row_mut::<u8>(y).unwrap() {
                *v = rng.gen();
            }
        }
        let mut blended = 0usize;
        for case in 0..300 {
            // Regions narrower and wider than two ramps, on and off each side.
            let (w, h) = (rng.gen_range(1..=120), rng.gen_range(1..=90));
            let r = Rect::new(rng.gen_range(0..=120 - w), rng.gen_range(0..=90 - h), w, h);
            let mut region =
                Mat::new_rows_cols_with_default(h, w, CV_8UC1, Scalar::all(0.0)).unwrap();
            for y in 0..h {
                for v in region.at_row_mut::<u8>(y).unwrap() {
                    *v = rng.gen();
                }
            }
            let (mut ours, mut theirs) = (base.try_clone().unwrap(), base.try_clone().unwrap());
            feather_into(&mut ours, &region, r, frame).unwrap();
            feather_into_per_pixel(&mut theirs, &region, r, frame).unwrap();
            let mut diff = Mat::default();
            core::absdiff(&ours, &theirs, &mut diff).unwrap();
            assert_eq!(
                core::count_non_zero(&diff).unwrap(),
                0,
                "case {case}, {r:?}"
            );
            let mut changed = Mat::default();
            core::absdiff(&ours, &base, &mut changed).unwrap();
            blended += core::count_non_zero(&changed).unwrap() as usize;
        }
        assert!(blended > 100_000, "{blended} pixels changed");
    }
}
