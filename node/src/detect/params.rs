//! The detector's tuning ([`DetectParams`]) and the choices it offers:
//! how corners are refined ([`Refinement`]) and when the whole printed
//! pattern is fitted instead of the squares' sides ([`FitPattern`]).

/// How corners are refined to sub-pixel precision.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum Refinement {
    /// Straight lines fitted to each side's grey-level edge (gradient peaks), intersected.
    EdgeLines,
    /// [`Refinement::EdgeLines`], then each side's line re-fitted as a blurred
    /// step edge to every pixel of a band around it ([`super::edge_model`]; default).
    EdgeModel,
    /// `cv::cornerSubPix` with a window of 0.35 module.
    CornerSubPix,
    /// The polygon corners of the contour (integer pixels).
    None,
}

/// Tuning of [`super::ShoalDetector`].
#[derive(Debug, Clone, PartialEq)]
pub struct DetectParams {
    /// Adaptive-threshold window sizes (odd, pixels at the detection level);
    /// more windows find more marker sizes at more cost.
    pub threshold_windows: Vec<i32>,
    /// Offset subtracted from the local mean (grey levels): a pixel is dark
    /// when it is at least this far below the mean of its window. With
    /// [`DetectParams::contrast_offset`] this is the offset where the local
    /// contrast is high (and where there is none).
    pub threshold_offset: f64,
    /// The offset follows the local contrast where that is low
    /// ([`ContrastOffset`]); `None`: [`DetectParams::threshold_offset`]
    /// everywhere.
    pub contrast_offset: Option<ContrastOffset>,
    /// Frames wider than this are searched for quads at half resolution.
    pub full_res_max_width: i32,
    /// Smallest accepted code-square side in full-resolution pixels.
    pub min_code_side_px: f64,
    /// On a downsampled frame, undecoded quads up to this mean side
    /// (full-resolution px) are searched again at full resolution around
    /// them (the per-marker pyramid level)…
    pub full_res_region_max_side_px: f64,
    /// …in at most this many windows per frame (0: never).
    pub max_full_res_regions: usize,
    /// Quads with a corner closer than this to the image border (px) are
    /// dropped (and always those whose dark region reaches the outermost
    /// row or column: cut by the border). A tag whose quiet zone the frame
    /// cuts can lie a pixel from the edge and still be whole.
    pub border_margin_px: f64,
    /// Polygon approximation tolerance as a fraction of the contour perimeter.
    pub approx_epsilon: f64,
    /// Smallest black/white contrast (grey levels) for a readable code.
    pub min_contrast: f64,
    /// Fraction of border (and ring) modules allowed to read wrong.
    pub max_border_error_rate: f64,
    /// Bits corrected at most; `None` = the larger of the code table's
    /// `max_correction_bits` and the unique-decoding radius `(d_min − 1) / 2`
    /// of the IDs in use (1 bit for the enhanced marker's 50 codes, as OpenCV's
    /// `DICT_4X4_50`; the 1000-code table's own figure is 0), at most
    /// [`super::codes::DEFAULT_CORRECTION_CAP_BITS`] (AprilTag 3's default).
    pub max_correction_bits: Option<u32>,
    pub refinement: Refinement,
    /// Given the raw frame beside the restored one
    /// ([`super::MarkerDetector::detect_restored`]), fit the step-edge model
    /// to the raw frame's pixels (`docs/detector.md`, "Fitting on the raw frame").
    pub fit_on_raw: bool,
    /// When the enhanced marker's corners come from one fit of its whole
    /// pattern to the raw frame ([`super::pattern`]; needs the raw frame and
    /// all twelve corners; the per-side corners stand when the fit fails).
    pub fit_pattern: FitPattern,
    /// The camera, when known: its lens distortion is taken out of the
    /// pattern fit (a planar marker is a homography only without it).
    pub lens: Option<shoal_proto::camera::CameraModel>,
    /// An enhanced marker whose outer frame edge lies wholly inside the
    /// image must show it (as a contour or from the prediction): a code
    /// square alone, or with only the white ring around it, is another
    /// fiducial's black square — an ArUco 4x4 marker (in a ChArUco board, its
    /// white square is the ring) or an AprilTag reads as a shoal code from
    /// it. A marker clipped by the image border keeps the squares it has.
    /// Default true.
    pub require_frame: bool,
}

/// A threshold offset relative to the local contrast (stage 1,
/// `docs/detector.md`, *A threshold offset that follows the contrast*).
///
/// The local contrast is the grey-level range (maximum − minimum) around
/// each pixel, over 4 x 4 px tiles covering about the threshold window. A
/// marker whose black and white differ by 15 grey levels (a far tag in
/// green water) is lost under a fixed offset of 3: its black border's
/// region leaks into the dark surround. Where the range is at least
/// `flat_below_dn`, the offset is `fraction` × range, at least `min_dn`
/// and at most [`DetectParams::threshold_offset`]; so the offset is the
/// fixed one wherever the contrast is high (range ≥ offset / fraction) and
/// in flat regions, where a smaller one would only trace sensor noise.
/// AprilTag 3 thresholds at the middle of the local extremes for the same
/// reason.
///
/// A region is also flat *against the noise* when its range over a
/// neighbourhood two tiles wider than the window's (36 x 36 px for the
/// window of 19) is under `flat_below_sigmas` times the image's noise σ
/// (estimated from the image, [`super::quads::noise_sigma_dn`]; noise alone
/// spans about 6.5σ over those ~1 300 pixels): there the offset is at least
/// `flat_floor_sigmas`·σ. Without that, an empty frame's noise of σ ≥ 1
/// grey level passes for contrast and is thresholded at about one σ: a
/// third of its pixels dark, in clusters that `findContours` traces by the
/// ten thousand (`docs/detector.md`, *Flat is relative to the noise*).
/// Where a marker lifts the range above the noise's, nothing changes.
/// `flat_below_sigmas = 0` turns the test off.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct ContrastOffset {
    pub fraction: f64,
    pub min_dn: f64,
    pub flat_below_dn: f64,
    pub flat_below_sigmas: f64,
    pub flat_floor_sigmas: f64,
}

/// When [`super::pattern::fit_pattern`] replaces the per-side corner fits.
#[derive(Debug, Clone, Copy, PartialEq)]
pub enum FitPattern {
    Never,
    /// When some square's step-edge fit found no edge on the raw frame, or
    /// its weakest side's step is under `below_dn` grey levels: turbid
    /// water, where the sharp part of an edge sinks into the noise and the
    /// halo carries the position. Where edges are strong the side fits are
    /// as good and much cheaper (raw steps per water and the costs:
    /// `docs/detector.md`, "Fitting the whole pattern").
    WhenEdgesWeak {
        below_dn: f64,
    },
    Always,
}

impl Default for DetectParams {
    fn default() -> Self {
        Self {
            threshold_windows: vec![19],
            threshold_offset: 3.0,
            contrast_offset: Some(ContrastOffset {
                fraction: 0.1,
                min_dn: 1.0,
                flat_below_dn: 6.0,
                flat_below_sigmas: 8.0,
                flat_floor_sigmas: 2.0,
            }),
            full_res_max_width: 1000,
            // 36h11's 8-module black square at ~1.1 px per module: AprilTag 3
            // reads tags this small on real photos (docs/real-data.md).
            min_code_side_px: 9.0,
            // A 10-module enhanced frame whose 2-module ring is ≤ ~4 px at half size.
            full_res_region_max_side_px: 90.0,
            max_full_res_regions: 24,
            border_margin_px: 1.0,
            approx_epsilon: 0.04,
            min_contrast: 6.0,
            max_border_error_rate: 0.2,
            max_correction_bits: None,
            refinement: Refinement::EdgeModel,
            fit_on_raw: true,
            fit_pattern: FitPattern::WhenEdgesWeak { below_dn: 16.0 },
            lens: None,
            require_frame: true,
        }
    }
}
