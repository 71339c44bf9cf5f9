//! Marker detection (paper §5): contours → geometric filtering → grid code
//! reading → 12 (or 4) corners → sub-pixel refinement.
//!
//! [`ShoalDetector`] runs four stages, a module each, each with its own
//! input and output types (design and measurements: `docs/detector.md`):
//!
//! 1. **Find quads** ([`quads`]): adaptive thresholds, contours, convex
//!    quadrilaterals of sufficient size clear of the border → [`quads::Quad`]s.
//!    Frames wider than [`DetectParams::full_res_max_width`] are searched at
//!    half size, and small quads that read no code there again at full
//!    resolution around them (the per-marker pyramid level).
//! 2. **Read codes** ([`codes`]): every quad tried as the code square, its
//!    module grid sampled through a homography and matched to the code table
//!    under all four rotations → [`codes::CodeSquare`]s (ID, bits corrected,
//!    the code square refined by stage 4's square fit).
//! 3. **Assemble the marker** ([`assemble`]): for the enhanced marker, its
//!    frame's inner and outer edges predicted from the code square and
//!    matched against the quads, or refined from the prediction when no quad
//!    matches → an [`assemble::Marker`] with up to three squares, each
//!    recording how it was found ([`SquareSource`]).
//! 4. **Fit corners** ([`corners`]): each square's sides fitted as a
//!    blurred step edge ([`edge_model`]) on the camera's raw frame when given
//!    ([`MarkerDetector::detect_restored`]), else on the detection image; one
//!    blur pooled over the marker; in murky water one fit of the whole printed
//!    pattern ([`pattern`], [`FitPattern::WhenEdgesWeak`]) → the corners and
//!    a [`CornerChoice`]: which [`CornerFit`] gave them and the
//!    [`FitReason`], recorded in [`Detection::corner_fit`].
//!
//! The pose (IPPE + LM PnP with covariance) is [`crate::pose`]'s, from
//! [`Detection::object_points`] and [`Detection::corners_px`]. Tuning:
//! [`params`].

pub mod assemble;
pub mod codes;
pub mod contours;
pub mod corners;
pub mod edge_model;
pub mod geom;
pub mod params;
pub mod paths;
pub mod pattern;
pub mod polygon;
pub mod quads;
pub mod refine;

use crate::mat::{GrayView, MatError};
use codes::{CodeReader, CodeSquare};
use geom::{centre, dist};
use opencv::core::{Mat, ToInputArray};
use opencv::prelude::*;
use quads::Quad;
use refine::Polarity;
use shoal_proto::marker::{CodeSet, MarkerId};

pub use assemble::SquareSource;
pub use corners::{
    CornerChoice, CornerFit, CornerFitCounts, FitReason, SquareCorners, SquareReport,
    HALO_MIN_SIGMA_PX,
};
pub use params::{ContrastOffset, DetectParams, FitPattern, Refinement};
pub use paths::{detect_paths, DetectSummary};

/// Errors of detection.
#[derive(Debug, thiserror::Error)]
pub enum DetectError {
    #[error("bad input image: {0}")]
    Image(#[from] MatError),
    #[error("OpenCV: {0}")]
    OpenCv(#[from] opencv::Error),
    #[error("code set {set} has no code table; run `shoal eval probe code-tables`")]
    NoCodes { set: &'static str },
    #[error("AprilTag: {0}")]
    AprilTag(String),
    #[error("code set {set} is not supported by detector {detector}")]
    Unsupported {
        detector: &'static str,
        set: &'static str,
    },
    #[error("{path}: {reason}")]
    Input { path: String, reason: String },
    #[error("writing output: {0}")]
    Io(#[from] std::io::Error),
    #[error("restored frame is {}x{} but the raw frame is {}x{}", restored.0, restored.1, raw.0, raw.1)]
    FrameSizes {
        restored: (usize, usize),
        raw: (usize, usize),
    },
}

/// One detected marker.
#[derive(Debug, Clone, PartialEq)]
pub struct Detection {
    pub codes: CodeSet,
    pub id: MarkerId,
    /// Corner pixels, in the order of [`Detection::corner_ids`].
    pub corners_px: Vec<[f64; 2]>,
    /// Index of each corner into [`CodeSet::corners_3d`].
    pub corner_ids: Vec<u8>,
    /// Covariance (px², x then y of each corner of `corners_px`) when the
    /// fit that gave the corners states one: the whole-pattern fit, whose
    /// corners all follow the same four outer corners, so their errors are
    /// correlated and the pose's residuals cannot show them
    /// ([`crate::pose::corner_covariance`]). `None`: independent corner
    /// errors, estimated from the residuals.
    pub corner_covariance: Option<nalgebra::DMatrix<f64>>,
    /// Bits corrected when decoding.
    pub hamming: u32,
    /// Mean module size in pixels.
    pub module_px: f64,
    /// Which fit gave `corners_px`, and why.
    pub corner_fit: CornerChoice,
}

impl Detection {
    /// The 3-D corners matching `corners_px`, for a marker of footprint `side_m`.
    pub fn object_points(&self, side_m: f64) -> Vec<nalgebra::Point3<f64>> {
        let all = self.codes.corners_3d(side_m);
        self.corner_ids.iter().map(|&i| all[i as usize]).collect()
    }
}

/// A detector of markers in 8-bit grey images.
pub trait MarkerDetector: Send {
    fn name(&self) -> &str;
    fn detect(&mut self, gray: &Mat) -> Result<Vec<Detection>, DetectError>;
    /// Detect in `restored`, the restoration of `raw` (same size). A
    /// detector may take its sub-pixel measurements from the raw frame
    /// ([`DetectParams::fit_on_raw`]); by default only `restored` is used.
    fn detect_restored(
        &mut self,
        restored: &Mat,
        raw: &Mat,
    ) -> Result<Vec<Detection>, DetectError> {
        let _ = raw;
        self.detect(restored)
    }
    /// [`MarkerDetector::detect_restored`] for markers inside `windows`
    /// (full-resolution rectangles): a detector may skip what lies wholly
    /// outside them, and may return more; by default it searches everything.
    fn detect_restored_within(
        &mut self,
        restored: &Mat,
        raw: &Mat,
        windows: &[opencv::core::Rect],
    ) -> Result<Vec<Detection>, DetectError> {
        let _ = windows;
        self.detect_restored(restored, raw)
    }
}

/// The images one detection works on.
pub(crate) struct Images<'a, G> {
    /// The detection image (the restoration, when there is one).
    pub gray: &'a G,
    /// The same, as pixels.
    pub view: GrayView<'a>,
    /// The camera's raw frame, for the step-edge and pattern fits.
    pub raw: Option<GrayView<'a>>,
}

/// The detector of paper §5, for any [`CodeSet`].
#[derive(Debug, Clone)]
pub struct ShoalDetector {
    codes: CodeSet,
    params: DetectParams,
    name: String,
    reader: CodeReader,
}

impl ShoalDetector {
    pub fn new(codes: CodeSet, params: DetectParams) -> Self {
        Self {
            codes,
            name: format!("shoal-{}", codes.name()),
            reader: CodeReader::new(codes, &params),
            params,
        }
    }

    pub fn codes(&self) -> CodeSet {
        self.codes
    }

    pub fn params(&self) -> &DetectParams {
        &self.params
    }

    /// Use `lens` for the frames that follow (a calibration fitted to their size).
    pub fn set_lens(&mut self, lens: Option<shoal_proto::camera::CameraModel>) {
        self.params.lens = lens;
    }

    /// Detect in a [`shoal_proto::image::GrayImage`] (wrapped without copying).
    pub fn detect_gray(
        &mut self,
        img: &shoal_proto::image::GrayImage,
    ) -> Result<Vec<Detection>, DetectError> {
        let mat = crate::mat::gray_as_mat(img)?;
        self.detect_in(&mat)
    }

    /// [`MarkerDetector::detect`] for any grey `Mat`-like input (a borrowed `BoxedRef<Mat>` too).
    pub fn detect_in(
        &mut self,
        gray: &(impl MatTraitConst + ToInputArray),
    ) -> Result<Vec<Detection>, DetectError> {
        let images = Images {
            gray,
            view: GrayView::new(gray)?,
            raw: None,
        };
        self.detect_images(&images, None)
    }

    /// Detect in `restored` and fit the corners' step-edge model
    /// ([`Refinement::EdgeModel`]) to `raw`, the same frame before
    /// restoration: quads, codes and the coarse edge lines come from the
    /// restored frame, where the marker stands out, while the sub-pixel
    /// fit uses the camera's own pixels: their noise is white and their
    /// edge profile is the optics' blur, neither reshaped by a local
    /// contrast stretch nor smoothed by denoising (`docs/detector.md`,
    /// "Fitting on the raw frame"). Other refinements use `restored` only.
    pub fn detect_with_raw_fit(
        &mut self,
        restored: &(impl MatTraitConst + ToInputArray),
        raw: &(impl MatTraitConst + ToInputArray),
    ) -> Result<Vec<Detection>, DetectError> {
        self.detect_with_raw_fit_within(restored, raw, None)
    }

    /// [`Self::detect_with_raw_fit`], with `windows` only the markers whose
    /// dark regions lie wholly inside one of them
    /// ([`quads::find_quads_and_blobs_within`]): the rest of the frame is
    /// thresholded but not traced, read or fitted.
    pub fn detect_with_raw_fit_within(
        &mut self,
        restored: &(impl MatTraitConst + ToInputArray),
        raw: &(impl MatTraitConst + ToInputArray),
        windows: Option<&[opencv::core::Rect]>,
    ) -> Result<Vec<Detection>, DetectError> {
        let view = GrayView::new(restored)?;
        let fit_view = GrayView::new(raw)?;
        if (fit_view.width, fit_view.height) != (view.width, view.height) {
            return Err(DetectError::FrameSizes {
                restored: (view.width, view.height),
                raw: (fit_view.width, fit_view.height),
            });
        }
        let images = Images {
            gray: restored,
            view,
            raw: Some(fit_view),
        };
        self.detect_images(&images, windows)
    }

    /// The four stages on `images`.
    fn detect_images<G: MatTraitConst + ToInputArray>(
        &self,
        images: &Images<'_, G>,
        windows: Option<&[opencv::core::Rect]>,
    ) -> Result<Vec<Detection>, DetectError> {
        if !self.reader.has_codes() {
            return Err(DetectError::NoCodes {
                set: self.codes.name(),
            });
        }
        let p = &self.params;
        // A frame narrower or lower than the smallest readable marker holds
        // none (and its half-resolution level would be empty).
        let (w, h) = (images.view.width as f64, images.view.height as f64);
        if w < p.min_code_side_px.max(2.0) || h < p.min_code_side_px.max(2.0) {
            return Ok(Vec::new());
        }
        let (mut quads, blobs) = quads::find_quads_and_blobs_within(p, images.gray, windows)?;
        let mut found: Vec<CodeSquare> = Vec::new();
        let mut undecoded = self.read_codes(images, &quads, &mut found);
        undecoded.extend(blobs);
        if images.gray.cols() > p.full_res_max_width && p.max_full_res_regions > 0 {
            // Quads inside a marker already read are its frame: nothing more to find there.
            let inside_found = |q: &Quad| {
                let c = centre(&q.pts);
                found
                    .iter()
                    .any(|f| dist(centre(&f.square.corners), c) < 4.0 * f.module_px)
            };
            let candidates: Vec<Quad> =
                undecoded.into_iter().filter(|q| !inside_found(q)).collect();
            if !candidates.is_empty() {
                let extra = quads::full_res_quads(p, &images.view, &candidates, &quads)?;
                self.read_codes(images, &extra, &mut found);
                quads.extend(extra);
            }
        }
        let raw = images.raw.as_ref();
        Ok(found
            .into_iter()
            .filter_map(|code| assemble::assemble(p, self.codes, images, code, &quads))
            .map(|marker| {
                let fitted = corners::fit_marker(p, self.codes, raw, &marker);
                Detection {
                    codes: self.codes,
                    id: marker.id,
                    corners_px: fitted.corners_px,
                    corner_ids: fitted.corner_ids,
                    corner_covariance: fitted.covariance,
                    hamming: marker.hamming,
                    module_px: marker.module_px,
                    corner_fit: fitted.choice,
                }
            })
            .collect())
    }

    /// Stage 2 over `quads`, the code squares refined by stage 4's square
    /// fit, merged into `found`; returns the quads that read no code.
    fn read_codes<G: MatTraitConst + ToInputArray>(
        &self,
        images: &Images<'_, G>,
        quads: &[Quad],
        found: &mut Vec<CodeSquare>,
    ) -> Vec<Quad> {
        let refine = |code: &[geom::Px; 4], module_px: f64| {
            corners::refine_square(&self.params, images, code, module_px, Polarity::DarkInside)
        };
        self.reader
            .decode((&images.view, images.raw.as_ref()), quads, refine, found)
    }
}

impl MarkerDetector for ShoalDetector {
    fn name(&self) -> &str {
        &self.name
    }

    fn detect(&mut self, gray: &Mat) -> Result<Vec<Detection>, DetectError> {
        self.detect_in(gray)
    }

    fn detect_restored(
        &mut self,
        restored: &Mat,
        raw: &Mat,
    ) -> Result<Vec<Detection>, DetectError> {
        if self.params.fit_on_raw {
            self.detect_with_raw_fit(restored, raw)
        } else {
            self.detect_in(restored)
        }
    }

    fn detect_restored_within(
        &mut self,
        restored: &Mat,
        raw: &Mat,
        windows: &[opencv::core::Rect],
    ) -> Result<Vec<Detection>, DetectError> {
        if self.params.fit_on_raw {
            self.detect_with_raw_fit_within(restored, raw, Some(windows))
        } else {
            let images = Images {
                gray: restored,
                view: GrayView::new(restored)?,
                raw: None,
            };
            self.detect_images(&images, Some(windows))
        }
    }
}
