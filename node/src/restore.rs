//! Underwater image restoration: HOIRM (paper §4) and the baselines it is
//! compared with (paper §6.1), all behind one [`Restorer`] interface.
//!
//! | [`Method`] | what it does                                                                  |
//! |------------|-------------------------------------------------------------------------------|
//! | `None`     | passes the frame through                                                      |
//! | `Clahe`    | CLAHE alone (clip 2, 8x8 tiles)                                               |
//! | `Dcp`      | dark channel prior (He et al. 2010), grey version, guided-filter refinement   |
//! | `Udcp`     | underwater DCP (Drews et al. 2013), adapted to one grey channel               |
//! | `Hoirm`    | ambient-light subtraction (Eq. 11–13) → [denoising when the edges are at the noise] → CLAHE → generalized-Gaussian Wiener deconvolution (Eq. 14) → pyramid level |
//!
//! HOIRM estimates the water from the image itself ([`water::WaterEstimate`]:
//! backscatter from the darkest coarse pixels, contrast, noise) so its
//! parameters adapt without being told the attenuation coefficient `c`;
//! [`RestoreParams::c_per_m`] overrides the estimate. To meet 10 ms per
//! 1440x1080 frame on one core it deconvolves only regions of interest found
//! on a 1/8 level ([`roi`]). Choices where the paper is vague are measured
//! and documented in `docs/restoration.md`.

pub mod ambient;
pub mod baselines;
pub(crate) mod dft2;
pub mod hoirm;
pub mod psf;
pub mod roi;
pub mod water;

use opencv::core::{Mat, Rect, Size, CV_8UC1};
use opencv::prelude::*;
use opencv::{imgcodecs, imgproc};
use std::path::Path;

pub use hoirm::Hoirm;
pub use water::WaterEstimate;

/// The restoration methods.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Hash)]
pub enum Method {
    None,
    Clahe,
    Dcp,
    Udcp,
    Hoirm,
}

impl Method {
    /// Every method, in the order of the paper's tables (ours last).
    pub const ALL: [Method; 5] = [
        Method::None,
        Method::Clahe,
        Method::Dcp,
        Method::Udcp,
        Method::Hoirm,
    ];

    /// The lowercase name accepted by [`std::str::FromStr`].
    pub fn name(self) -> &'static str {
        match self {
            Method::None => "none",
            Method::Clahe => "clahe",
            Method::Dcp => "dcp",
            Method::Udcp => "udcp",
            Method::Hoirm => "hoirm",
        }
    }
}

impl std::fmt::Display for Method {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.write_str(self.name())
    }
}

impl std::str::FromStr for Method {
    type Err = RestoreError;
    fn from_str(s: &str) -> Result<Self, Self::Err> {
        Method::ALL
            .into_iter()
            .find(|m| m.name().eq_ignore_ascii_case(s.trim()))
            .ok_or_else(|| RestoreError::UnknownMethod {
                name: s.to_string(),
            })
    }
}

/// The order of HOIRM's de-attenuation and de-blurring stages.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum StageOrder {
    /// The paper's Fig. 7 order: ambient light → CLAHE → deconvolution.
    Paper,
    /// The imaging model's order (Eq. 8 inverted from the outside in):
    /// ambient light → deconvolution → CLAHE. Deconvolving before the
    /// non-linear CLAHE keeps the blur model valid.
    Physical,
}

/// Tunables of all methods. Defaults are documented (and measured) in
/// `docs/restoration.md`.
#[derive(Debug, Clone, PartialEq)]
pub struct RestoreParams {
    /// Attenuation coefficient of the water (1/m); `None` = estimate it from the image.
    pub c_per_m: Option<f64>,
    /// Keep intermediate stages in [`Restored::stages`] (for contact sheets).
    pub keep_stages: bool,

    // --- HOIRM -------------------------------------------------------------
    /// Deconvolve only regions of interest found on a coarse level (else the full frame).
    pub roi_only: bool,
    /// Stage order, see [`StageOrder`].
    pub order: StageOrder,
    /// σ of Eq. (11)'s Gaussian blur, full-resolution pixels.
    pub ambient_sigma_px: f64,
    /// Time constant of the ambient-light weights `w_n ∝ exp(−age/τ)` (Eq. 12), seconds.
    pub ambient_tau_s: f64,
    /// Upper bound of `α = Σ w_n` (paper: α < 1).
    pub ambient_alpha_max: f64,
    /// CLAHE tile side, pixels (the grid is `ceil(size / tile)`).
    pub clahe_tile_px: i32,
    /// CLAHE clip limit in clear water and its growth per 1/m of `c`.
    pub clahe_clip_base: f64,
    pub clahe_clip_per_c: f64,
    /// Shape of Eq. (14): `p(c) = p_clear / (1 + c / psf_c_half)`.
    pub psf_p_clear: f64,
    pub psf_c_half_per_m: f64,
    /// Pixels per unit of Eq. (14)'s σ = 1/(2√p) (the paper states no unit).
    pub psf_px_per_unit: f64,
    /// Measure the PSF's σ on each region's edges (`psf::edge_blur_sigma_px`)
    /// and use it (at least `psf_min_sigma_px`) instead of Eq. (14)'s σ,
    /// which is fitted to one water's blur. Off by default: the estimate reads
    /// a sharp core under a wide halo as a narrow PSF (docs/restoration.md,
    /// "Turbid water").
    pub psf_sigma_from_image: bool,
    pub psf_min_sigma_px: f64,
    /// …but only when it is below this fraction of Eq. (14)'s σ (the
    /// estimate reads a sharp core under a wide halo as narrow).
    pub psf_trust_ratio: f64,
    /// Below this attenuation (1/m) HOIRM does not deconvolve: forward-scatter
    /// blur grows with optical depth and is negligible in clear water, where
    /// deconvolving a sharp image with Eq. (14)'s PSF only rings edges (it cut
    /// detection at 0.126 /m from 1.00 to 0.81; see docs/restoration.md).
    pub deconv_min_c_per_m: f64,
    /// Below this `c` (as HOIRM estimates it from the image, or the override)
    /// the frame is passed through unrestored: in clear water every stage
    /// only costs precision (shoal's median error at 0.126 /m: 0.11 mm raw,
    /// 0.51 mm through HOIRM; docs/results.md). HOIRM's estimate reads 0 up
    /// to 1.38 /m, 0.76 at 2 /m and 2.75 at 3.92 /m on simulated frames.
    pub passthrough_below_c_per_m: f64,
    /// Deconvolve denoised regions too (with the NSR of the region before smoothing)…
    pub deconv_when_denoised: bool,
    /// …at this pyramid level when smoothed by σ ≥ 2 px (at least `deconv_level`).
    pub denoised_deconv_level: u32,
    /// Pyramid level at which the Wiener deconvolution runs (0 = full
    /// resolution; 1 = half, its correction up-sampled), see `docs/restoration.md`.
    pub deconv_level: u32,
    /// Wiener noise-to-signal ratio = gain · σ_noise² / σ_signal², clamped.
    pub nsr_gain: f64,
    pub nsr_min: f64,
    pub nsr_max: f64,
    /// Range at which `c` is inferred from the image (the paper's test range, 600 mm).
    pub reference_range_m: f64,
    /// Veil at infinity over a white object's radiance, `B∞/W`, for the `c` estimate.
    pub white_over_veil: f64,
    /// Part of `c` that is small-angle forward scatter (still reaches the camera), for the `c` estimate.
    pub forward_scatter_fraction: f64,
    /// The `c` estimate's strongest contrast is taken less the noise's own
    /// share, at least this many times the coarse gradient's median (2: the
    /// 99.9th percentile of Gaussian noise's 3x3 range; 0: the white-noise
    /// prediction alone, as before session 41). See docs/restoration.md.
    pub contrast_noise_k: f64,
    /// Deconvolve the PSF mixed with the unscattered light, `e^{−s·c·d_ref}`
    /// of it sharp (`psf::GgPsf::direct`), in the frame's restoration too;
    /// `false` (default): Eq. (14)'s PSF alone, as the paper writes it, whose
    /// filter also suppresses noise finer than the halo (what turbid water
    /// needs) and erases detail as fine (what a far marker needs; the
    /// detail-keeping restoration, `fine_pass`, always keeps the unscattered
    /// part). See docs/restoration.md, "Fine detail".
    pub psf_unscattered: bool,
    /// Where the restoration smoothed or deconvolved a region and no marker
    /// was read in it, search the region's detail-keeping restoration
    /// (no smoothing, the unscattered part kept) too.
    pub fine_pass: bool,
    /// …also when no region stood out from the noise and the frame was
    /// restored whole (`roi_max_fraction`). Off by default: through the
    /// realistic camera that second whole-frame search was half the node's
    /// CPU at 8.22 /m for one read in 76 such frames (docs/restoration.md,
    /// "Fine detail").
    pub fine_pass_whole_frame: bool,
    /// Grey level the 99.5th percentile of `I − B_L` is stretched to (global de-attenuation, 1/t).
    pub stretch_target: f64,
    /// Largest global de-attenuation gain.
    pub stretch_max_gain: f64,
    /// Coarsest pyramid level handed to the detector.
    pub max_pyramid_level: u32,
    /// Edge step / noise ratio the detector wants at the chosen level.
    pub edge_snr_target: f64,
    /// Largest PSF σ (pixels at the chosen level) the detector should see.
    pub level_blur_px: f64,
    /// The largest region of interest (pixels) must keep this side at the chosen level.
    pub min_roi_side_at_level_px: i32,
    /// Denoising before the local stretch: the detector wants edge step /
    /// noise ≥ this at full resolution; when the frame's (estimated local
    /// contrast / noise σ) is lower, the regions are smoothed with a Gaussian
    /// of σ = `denoise_edge_snr / (2√π · contrast/noise)` (a Gaussian of σ
    /// divides white noise by 2√π·σ), from `denoise_min_sigma_px` up to
    /// `denoise_max_sigma_px` (0 disables). See docs/restoration.md.
    pub denoise_edge_snr: f64,
    pub denoise_min_sigma_px: f64,
    pub denoise_max_sigma_px: f64,
    /// In denoised regions CLAHE may stretch the estimated edge step ΔI to
    /// this many grey levels: its clip limit (a bound on the total slope,
    /// global gain × CLAHE) is raised to `clahe_contrast_target / ΔI`.
    pub clahe_contrast_target: f64,
    /// Region of interest search (`roi::find_rois`): local contrast threshold
    /// in units of the noise σ of the smoothed 1/8 level, and as a fraction of
    /// the strongest local contrast…
    pub roi_noise_k: f64,
    pub roi_rel_threshold: f64,
    /// …and at least this many grey levels of the (smoothed, local-mean-free)
    /// 1/8 level's 3x3 gradient, and this many times its median over the frame.
    pub roi_min_gradient: f64,
    pub roi_background_k: f64,
    /// Hysteresis: a region grows over neighbours above this fraction of the threshold.
    pub roi_hysteresis: f64,
    /// Beyond this fraction of the frame, ROIs are dropped for the full frame.
    pub roi_max_fraction: f64,

    // --- baselines -----------------------------------------------------------
    pub baseline_clahe_clip: f64,
    pub baseline_clahe_grid: i32,
    /// DCP/UDCP: dark-channel patch side (He: 15), haze kept (ω), transmission floor (t0).
    pub dcp_patch: i32,
    pub dcp_omega: f64,
    pub dcp_t0: f64,
    /// Guided-filter refinement of the transmission (radius 0 = off).
    pub dcp_guided_radius: i32,
    pub dcp_guided_eps: f64,
}

impl Default for RestoreParams {
    fn default() -> Self {
        Self {
            c_per_m: None,
            keep_stages: false,
            roi_only: true,
            order: StageOrder::Paper,
            ambient_sigma_px: 32.0,
            ambient_tau_s: 0.5,
            ambient_alpha_max: 0.9,
            clahe_tile_px: 128,
            clahe_clip_base: 2.0,
            clahe_clip_per_c: 0.15,
            psf_p_clear: 2.0,
            psf_c_half_per_m: 6.0,
            psf_px_per_unit: 10.0,
            psf_sigma_from_image: false,
            psf_min_sigma_px: 0.5,
            psf_trust_ratio: 0.5,
            deconv_min_c_per_m: 3.0,
            passthrough_below_c_per_m: 1.0,
            deconv_when_denoised: true,
            denoised_deconv_level: 1,
            deconv_level: 0,
            nsr_gain: 1.0,
            nsr_min: 2e-3,
            nsr_max: 0.5,
            reference_range_m: 0.6,
            white_over_veil: 0.5,
            forward_scatter_fraction: 0.3,
            contrast_noise_k: 2.0,
            psf_unscattered: false,
            fine_pass: true,
            fine_pass_whole_frame: false,
            stretch_target: 235.0,
            stretch_max_gain: 6.0,
            max_pyramid_level: 3,
            edge_snr_target: 12.0,
            level_blur_px: 1.5,
            min_roi_side_at_level_px: 48,
            denoise_edge_snr: 35.0,
            // 1 px, not 2 (session 21): through the realistic camera the
            // frames at 3.92-5.16 /m asked for 1.5-2 px, went unsmoothed,
            // and the stretch's speckle cost AprilTag 3 its reads there
            // (docs/results.md, "accuracy", the restoration check).
            denoise_min_sigma_px: 1.0,
            denoise_max_sigma_px: 3.0,
            clahe_contrast_target: 60.0,
            roi_noise_k: 8.0,
            roi_rel_threshold: 0.2,
            roi_min_gradient: 0.25,
            roi_background_k: 1.8,
            roi_hysteresis: 0.7,
            roi_max_fraction: 0.5,
            baseline_clahe_clip: 2.0,
            baseline_clahe_grid: 8,
            dcp_patch: 15,
            dcp_omega: 0.95,
            dcp_t0: 0.1,
            dcp_guided_radius: 40,
            dcp_guided_eps: 1e-3,
        }
    }
}

impl RestoreParams {
    /// A short description of the first unusable parameter, or `None`.
    pub fn problem(&self) -> Option<RestoreError> {
        let bad = |name: &'static str, value: f64, reason: &'static str| {
            Some(RestoreError::BadParam {
                name,
                value,
                reason,
            })
        };
        if let Some(c) = self.c_per_m {
            if !(c.is_finite() && c >= 0.0) {
                return bad("c_per_m", c, "must be finite and >= 0");
            }
        }
        let non_negative = |params: &[(&'static str, f64)]| {
            params
                .iter()
                .find(|(_, v)| !(v.is_finite() && *v >= 0.0))
                .and_then(|&(name, v)| bad(name, v, "must be finite and >= 0"))
        };
        let first = non_negative(&[
            ("passthrough_below_c_per_m", self.passthrough_below_c_per_m),
            ("deconv_min_c_per_m", self.deconv_min_c_per_m),
        ]);
        if first.is_some() {
            return first;
        }
        let positive = [
            ("ambient_sigma_px", self.ambient_sigma_px),
            ("psf_p_clear", self.psf_p_clear),
            ("psf_c_half_per_m", self.psf_c_half_per_m),
            ("psf_px_per_unit", self.psf_px_per_unit),
            ("nsr_min", self.nsr_min),
            ("reference_range_m", self.reference_range_m),
            ("white_over_veil", self.white_over_veil),
            ("stretch_target", self.stretch_target),
            ("stretch_max_gain", self.stretch_max_gain),
            ("edge_snr_target", self.edge_snr_target),
            ("level_blur_px", self.level_blur_px),
            ("baseline_clahe_clip", self.baseline_clahe_clip),
            ("clahe_clip_base", self.clahe_clip_base),
            ("dcp_t0", self.dcp_t0),
        ];
        for (name, v) in positive {
            if !(v.is_finite() && v > 0.0) {
                return bad(name, v, "must be finite and > 0");
            }
        }
        let more = non_negative(&[
            ("denoise_edge_snr", self.denoise_edge_snr),
            ("denoise_min_sigma_px", self.denoise_min_sigma_px),
            ("denoise_max_sigma_px", self.denoise_max_sigma_px),
            ("clahe_contrast_target", self.clahe_contrast_target),
            ("roi_min_gradient", self.roi_min_gradient),
            ("roi_background_k", self.roi_background_k),
            ("roi_hysteresis", self.roi_hysteresis),
            ("psf_min_sigma_px", self.psf_min_sigma_px),
            ("psf_trust_ratio", self.psf_trust_ratio),
            ("ambient_tau_s", self.ambient_tau_s),
            ("contrast_noise_k", self.contrast_noise_k),
        ]);
        if more.is_some() {
            return more;
        }
        if !(self.ambient_alpha_max >= 0.0 && self.ambient_alpha_max < 1.0) {
            return bad(
                "ambient_alpha_max",
                self.ambient_alpha_max,
                "paper: 0 <= α < 1",
            );
        }
        if !(self.nsr_max >= self.nsr_min && self.nsr_max.is_finite()) {
            return bad("nsr_max", self.nsr_max, "must be finite and >= nsr_min");
        }
        if !(self.forward_scatter_fraction >= 0.0 && self.forward_scatter_fraction < 1.0) {
            return bad(
                "forward_scatter_fraction",
                self.forward_scatter_fraction,
                "must be in [0, 1)",
            );
        }
        if !(self.dcp_omega > 0.0 && self.dcp_omega <= 1.0) {
            return bad("dcp_omega", self.dcp_omega, "must be in (0, 1]");
        }
        if self.deconv_level > 3 {
            return bad("deconv_level", self.deconv_level as f64, "must be <= 3");
        }
        if self.denoised_deconv_level > 3 {
            return bad(
                "denoised_deconv_level",
                self.denoised_deconv_level as f64,
                "must be <= 3",
            );
        }
        if self.clahe_tile_px < 8 {
            return bad("clahe_tile_px", self.clahe_tile_px as f64, "must be >= 8");
        }
        if self.baseline_clahe_grid < 1 {
            return bad(
                "baseline_clahe_grid",
                self.baseline_clahe_grid as f64,
                "must be >= 1",
            );
        }
        if self.dcp_patch < 1 || self.dcp_guided_radius < 0 {
            return bad(
                "dcp_patch",
                self.dcp_patch as f64,
                "patch >= 1, radius >= 0",
            );
        }
        if !(self.roi_max_fraction > 0.0 && self.roi_max_fraction <= 1.0) {
            return bad(
                "roi_max_fraction",
                self.roi_max_fraction,
                "must be in (0, 1]",
            );
        }
        None
    }
}

/// The result of restoring one frame.
#[derive(Debug)]
pub struct Restored {
    /// Full-resolution 8-bit grey, same size as the input.
    pub image: Mat,
    /// Pyramid level chosen for edge detection (0 = full resolution).
    pub pyramid_level: u32,
    /// `image` down-sampled `pyramid_level` times with `pyrDown`
    /// (`None` when the level is 0: use `image`).
    pub level_image: Option<Mat>,
    /// Attenuation coefficient used (the override, else the estimate), 1/m.
    pub estimated_c_per_m: f64,
    /// Estimated backscatter (veiling light) level, grey levels 0–255.
    pub backscatter: f64,
    /// Regions that were deconvolved (full-resolution pixels); the whole frame when not ROI-limited.
    pub rois: Vec<Rect>,
    /// Intermediate stages `(name, full-res 8-bit image)` when `keep_stages`.
    pub stages: Option<Vec<(String, Mat)>>,
    /// HOIRM: the regions where this restoration gave up detail (smoothed
    /// them, or deconvolved them with the scatter halo alone), and how to
    /// restore them again keeping it; searched where nothing was read there
    /// ([`crate::pipeline::detect_restoration`]). `None` elsewhere.
    pub fine: Option<hoirm::FineRestoration>,
}

/// Errors of restoration.
#[derive(Debug, thiserror::Error)]
pub enum RestoreError {
    #[error("unknown restoration method {name:?}; known: none, clahe, dcp, udcp, hoirm")]
    UnknownMethod { name: String },
    #[error("input image is empty")]
    EmptyImage,
    #[error("input image is not single-channel 8-bit (OpenCV type {typ})")]
    NotGray8 { typ: i32 },
    #[error("input image {width}x{height} is smaller than the {min}x{min} minimum")]
    TooSmall { width: i32, height: i32, min: i32 },
    #[error("parameter {name} = {value}: {reason}")]
    BadParam {
        name: &'static str,
        value: f64,
        reason: &'static str,
    },
    #[error("input image {width}x{height} ({} Mpx) is more than the {} Mpx restoration limit (peak memory grows ~55 bytes per pixel with dcp)", (*width as f64 * *height as f64 / 1e6), MAX_RESTORE_PIXELS as f64 / 1e6)]
    TooLarge { width: i32, height: i32 },
    #[error(transparent)]
    File(#[from] crate::image_file::ImageError),
    #[error("cannot write image {path}: {reason}")]
    Write { path: String, reason: String },
    #[error("the fine restoration needs the frame it was made from: {restored:?} restored, {given:?} given")]
    FrameMismatch {
        restored: (i32, i32),
        given: (i32, i32),
    },
    #[error("DFT of a {rows}x{cols} grid: {reason}")]
    Dft {
        rows: usize,
        cols: usize,
        reason: String,
    },
    #[error("OpenCV")]
    OpenCv(#[from] opencv::Error),
}

/// One restoration method with its per-camera state (HOIRM keeps the
/// ambient-light running sum; the baselines are stateless).
pub trait Restorer: Send {
    fn method(&self) -> Method;
    /// Restore one 8-bit grey frame taken at `stamp_ns` (camera clock).
    fn restore(&mut self, gray: &Mat, stamp_ns: u64) -> Result<Restored, RestoreError>;
}

/// A restorer of `method` with `params`.
pub fn restorer(method: Method, params: &RestoreParams) -> Box<dyn Restorer> {
    match method {
        Method::None => Box::new(baselines::Passthrough::new(params)),
        Method::Clahe => Box::new(baselines::ClaheOnly::new(params)),
        Method::Dcp => Box::new(baselines::DarkChannel::new(params, false)),
        Method::Udcp => Box::new(baselines::DarkChannel::new(params, true)),
        Method::Hoirm => Box::new(Hoirm::new(params.clone())),
    }
}

/// Restore one image file (PNG, ...) into another: `shoal restore --water 12.20 in.png out.png`.
pub fn restore_file(
    input: &Path,
    output: &Path,
    method: Method,
    c_per_m: Option<f64>,
) -> Result<(), RestoreError> {
    let img = crate::image_file::read_gray_for(input, MAX_RESTORE_PIXELS, " for restoration")?.gray;
    let params = RestoreParams {
        c_per_m,
        ..RestoreParams::default()
    };
    if let Some(e) = params.problem() {
        return Err(e);
    }
    let out = restorer(method, &params).restore(&img, 0)?;
    let out_name = output.display().to_string();
    let write = |reason: String| RestoreError::Write {
        path: out_name.clone(),
        reason,
    };
    let ext = output
        .extension()
        .and_then(|e| e.to_str())
        .map(|e| format!(".{e}"))
        .ok_or_else(|| {
            write("no extension to choose the format by (.png, .jpg, .bmp, .tif)".into())
        })?;
    let mut encoded = opencv::core::Vector::<u8>::new();
    let ok = imgcodecs::imencode(&ext, &out.image, &mut encoded, &opencv::core::Vector::new())
        .map_err(|e| write(e.to_string()))?;
    if !ok {
        return Err(write(format!("cannot encode as {ext}")));
    }
    shoal_proto::files::OutputFile::write_whole(output, &[input], encoded.as_slice())
        .map_err(|e| write(error_chain(&e)))?;
    Ok(())
}

/// An error and its sources, `: `-separated.
fn error_chain(e: &dyn std::error::Error) -> String {
    let mut s = e.to_string();
    let mut src = e.source();
    while let Some(inner) = src {
        s += &format!(": {inner}");
        src = inner.source();
    }
    s
}

/// The most pixels a frame may have to be restored: 16 Mpx. The dark-channel
/// baselines peak at ~55 bytes per pixel (864 MB on a 16 Mpx frame,
/// `docs/results.md`, "Hostile files"), so any method stays under 1 GB.
pub const MAX_RESTORE_PIXELS: u64 = 16_000_000;

/// The smallest frame any method accepts (the 1/8 level must be at least 2x2... and
/// the SSIM window fit).
pub const MIN_SIDE_PX: i32 = 16;

/// Check that `gray` is a usable 8-bit single-channel image.
pub(crate) fn check_input(gray: &Mat) -> Result<(), RestoreError> {
    if gray.empty() {
        return Err(RestoreError::EmptyImage);
    }
    if gray.typ() != CV_8UC1 {
        return Err(RestoreError::NotGray8 { typ: gray.typ() });
    }
    if gray.cols() as u64 * gray.rows() as u64 > MAX_RESTORE_PIXELS {
        return Err(RestoreError::TooLarge {
            width: gray.cols(),
            height: gray.rows(),
        });
    }
    if gray.cols() < MIN_SIDE_PX || gray.rows() < MIN_SIDE_PX {
        return Err(RestoreError::TooSmall {
            width: gray.cols(),
            height: gray.rows(),
            min: MIN_SIDE_PX,
        });
    }
    Ok(())
}

/// An area-averaged `1/factor` copy (each coarse pixel the mean of a factor x factor block).
pub(crate) fn coarse_level(gray: &Mat, factor: i32) -> Result<Mat, RestoreError> {
    let size = Size::new((gray.cols() / factor).max(1), (gray.rows() / factor).max(1));
    let mut out = Mat::default();
    imgproc::resize(gray, &mut out, size, 0.0, 0.0, imgproc::INTER_AREA)?;
    Ok(out)
}

/// The CLAHE tile grid of about `tile_px` pixels per tile over an image of
/// `size`: `ceil(size / tile)` tiles each way.
pub(crate) fn clahe_tiles(size: Size, tile_px: i32) -> Size {
    Size::new(
        ((size.width + tile_px - 1) / tile_px).max(1),
        ((size.height + tile_px - 1) / tile_px).max(1),
    )
}

/// A CLAHE with `clip` and a `grid` of tiles, applied to `src`.
pub(crate) fn clahe_grid(
    src: &impl opencv::core::ToInputArray,
    clip: f64,
    grid: Size,
) -> Result<Mat, RestoreError> {
    let mut c = imgproc::create_clahe(clip, grid)?;
    let mut out = Mat::default();
    c.apply(src, &mut out)?;
    Ok(out)
}

/// A deep copy of a `Mat` (for stages).
pub(crate) fn snapshot(m: &Mat) -> Result<Mat, RestoreError> {
    Ok(m.try_clone()?)
}
