//! Stage 3 of the detector, **assemble the marker**: the enhanced marker's
//! frame squares around each decoded code square (paper §3.2, the 10x10
//! grid). The frame's inner and outer edges are predicted from the code
//! square's homography (one and two modules outside it) and matched against
//! the quads found ([`SquareSource::Contour`]). We pair by geometry rather
//! than by the contour hierarchy: the hierarchy breaks whenever blur or a
//! threshold glitch joins the code border to the frame, while the prediction
//! does not.
//!
//! A frame square that no quad matches is refined from the prediction itself
//! ([`SquareSource::Prediction`], `frame_from_prediction`): a small
//! marker's frame is often never a contour (on the half-resolution level the
//! one-module ring does not separate the code square from the frame). A
//! frame that is clipped by the image border or occluded is not found, and
//! the marker keeps the squares it has ([`super::Detection::corner_ids`]).
//!
//! Input: a [`CodeSquare`] and the quads. Output: a [`Marker`], its squares
//! refined by the corner stage ([`super::corners`]) and in corner order.

use super::codes::CodeSquare;
use super::corners::{self, FittedSquare};
use super::edge_model::{self, Profile};
use super::geom::{apply, dist, homography_4, Px};
use super::quads::Quad;
use super::refine::{self, Polarity};
use super::{DetectParams, Images, Refinement};
use crate::mat::GrayView;
use opencv::core::ToInputArray;
use opencv::prelude::*;
use shoal_proto::marker::{CodeSet, MarkerId};

/// How a square of a marker was found.
#[derive(Debug, Clone, Copy, PartialEq, Eq, serde::Serialize)]
#[serde(rename_all = "snake_case")]
pub enum SquareSource {
    /// A quad of the contours (the code square always is one).
    Contour,
    /// No quad matched: the square predicted from the code square's
    /// homography, refined and accepted by `frame_from_prediction`.
    Prediction,
}

/// One square of a marker.
#[derive(Debug, Clone, Copy)]
pub struct MarkerSquare {
    /// Index of its first corner into [`CodeSet::corners_3d`].
    pub first: u8,
    pub source: SquareSource,
    pub square: FittedSquare,
}

/// A decoded marker with its squares, outer first (enhanced marker: outer
/// frame edge, frame inner edge, code square; others: the code square).
#[derive(Debug, Clone)]
pub struct Marker {
    pub id: MarkerId,
    pub hamming: u32,
    pub module_px: f64,
    pub squares: Vec<MarkerSquare>,
}

/// The frame squares of the enhanced marker: modules outside the code
/// square, polarity, first corner (paper §3.2: outer frame edge 0..4, frame
/// inner edge 4..8).
const FRAME_SQUARES: [(f64, Polarity, u8); 2] = [
    (2.0, Polarity::DarkInside, 0),
    (1.0, Polarity::BrightInside, 4),
];

/// The marker around `code`: for [`CodeSet::Shoal`] its frame squares
/// (matched among `quads`, or from the prediction), then the code square.
/// `None` when the enhanced marker's outer frame edge should be in the
/// image and is not there ([`DetectParams::require_frame`]).
pub(crate) fn assemble<G: MatTraitConst + ToInputArray>(
    params: &DetectParams,
    codes: CodeSet,
    images: &Images<'_, G>,
    code: CodeSquare,
    quads: &[Quad],
) -> Option<Marker> {
    let mut squares = Vec::with_capacity(3);
    let code_corners = code.square.corners;
    let module_px = code.module_px;
    if codes == CodeSet::Shoal {
        for (off, polarity, first) in FRAME_SQUARES {
            let found = if let Some(q) = find_frame(codes, &code_corners, module_px, off, quads) {
                let square = corners::refine_square(params, images, &q, module_px, polarity);
                Some((SquareSource::Contour, square))
            } else {
                let frame = PredictedFrame {
                    code: &code.square,
                    module_px,
                    off,
                    polarity,
                };
                frame_from_prediction(params, codes, images, &frame)
                    .map(|s| (SquareSource::Prediction, s))
            };
            if let Some((source, square)) = found {
                squares.push(MarkerSquare {
                    first,
                    source,
                    square,
                });
            }
        }
        let outer_found = squares.iter().any(|s| s.first == 0);
        if params.require_frame
            && !outer_found
            && !frame_in_pixels(&images.view, codes, &code_corners, module_px)
        {
            return None;
        }
    }
    squares.push(MarkerSquare {
        first: if codes == CodeSet::Shoal { 8 } else { 0 },
        source: SquareSource::Contour,
        square: code.square,
    });
    Some(Marker {
        id: code.id,
        hamming: code.hamming,
        module_px,
        squares,
    })
}

/// Whether the pixels around a code square show the enhanced marker's
/// frame when its outer edge was not found as a square: sampled along the
/// four sides (corners left out), the frame band (1–2 modules outside the
/// code square) must be darker than both the white ring inside it and what
/// lies outside it, each by at least [`FRAME_CONTRAST`] of the code square's
/// own contrast (ring against its black border). A ratio, so turbid water,
/// which lowers every contrast alike, does not fail it; another fiducial's
/// black square does: around an AprilTag or a lone ArUco marker the band is
/// background, and in a ChArUco board the band falls on the black squares,
/// which go on outside it. Where too little of the band is in the image (a
/// marker cut by the border) there is nothing to judge: true.
fn frame_in_pixels(view: &GrayView<'_>, codes: CodeSet, code: &[Px; 4], module_px: f64) -> bool {
    let ms = codes.data_side() as f64 + 2.0;
    let cells = [[0.0, 0.0], [ms, 0.0], [ms, ms], [0.0, ms]];
    let Some(h) = homography_4(&cells, code) else {
        return true;
    };
    // Mean grey level at `depth` modules outside the code square's edges
    // (negative: inside), over the points in view; and how many were.
    let ring_mean = |depth: f64| {
        let (mut sum, mut n, mut total) = (0.0, 0usize, 0usize);
        let steps = ((ms - 2.0) * 2.0) as usize;
        for side in 0..4 {
            for k in 0..=steps {
                let u = 1.0 + k as f64 * 0.5;
                let p = match side {
                    0 => [u, -depth],
                    1 => [ms + depth, u],
                    2 => [ms - u, ms + depth],
                    _ => [-depth, ms - u],
                };
                let q = apply(&h, p);
                total += 1;
                if view.contains(q[0], q[1], 1.0) {
                    sum += view.sample(q[0], q[1]);
                    n += 1;
                }
            }
        }
        (sum / n.max(1) as f64, n, total)
    };
    let (border, _, _) = ring_mean(-0.5);
    let (ring, _, _) = ring_mean(0.5);
    let (band, n_band, total) = ring_mean(1.5);
    let (outside, n_out, _) = ring_mean(2.5);
    if n_band * 2 < total || n_out * 2 < total || module_px < 1.0 {
        return true;
    }
    let contrast = ring - border;
    contrast > 0.0
        && ring - band >= FRAME_CONTRAST * contrast
        && outside - band >= FRAME_CONTRAST * contrast
}

/// Least darkening of the frame band, as a share of the code square's
/// contrast, that [`frame_in_pixels`] accepts (chosen before measuring).
const FRAME_CONTRAST: f64 = 0.25;

/// The square `off` modules outside the code square, mapped by the code
/// square's homography (the paper's 10x10 module grid).
fn predict_frame(codes: CodeSet, code: &[Px; 4], off: f64) -> Option<[Px; 4]> {
    let ms = codes.data_side() as f64 + 2.0;
    let cells = [[0.0, 0.0], [ms, 0.0], [ms, ms], [0.0, ms]];
    let hmat = homography_4(&cells, code)?;
    Some([
        apply(&hmat, [-off, -off]),
        apply(&hmat, [ms + off, -off]),
        apply(&hmat, [ms + off, ms + off]),
        apply(&hmat, [-off, ms + off]),
    ])
}

/// The quad of `quads` whose corners are each within 0.45 module of the
/// square predicted `off` modules outside the code square (enhanced marker:
/// 1 = frame inner edge, 2 = outer edge), its corners in the prediction's
/// order; the closest in total when several match.
fn find_frame(
    codes: CodeSet,
    code: &[Px; 4],
    module_px: f64,
    off: f64,
    quads: &[Quad],
) -> Option<[Px; 4]> {
    let pred = predict_frame(codes, code, off)?;
    let tol = 0.45 * module_px;
    let mut best: Option<(f64, [Px; 4])> = None;
    for q in quads {
        let mut out = [[0.0; 2]; 4];
        let mut total = 0.0;
        let mut ok = true;
        for i in 0..4 {
            let (j, d) = (0..4)
                .map(|j| (j, dist(q.pts[j], pred[i])))
                .min_by(|a, b| a.1.total_cmp(&b.1))
                .unwrap_or((0, f64::INFINITY));
            if d > tol {
                ok = false;
                break;
            }
            out[i] = q.pts[j];
            total += d;
        }
        if ok && best.as_ref().is_none_or(|b| total < b.0) {
            best = Some((total, out));
        }
    }
    best.map(|b| b.1)
}

/// A frame square to find from the prediction: `off` modules outside the
/// refined code square `code`.
struct PredictedFrame<'a> {
    code: &'a FittedSquare,
    module_px: f64,
    off: f64,
    polarity: Polarity,
}

/// A frame square without a contour: when no quad matches the predicted
/// frame square, the prediction itself is refined by the step-edge model
/// (with [`Refinement::EdgeModel`] only). Accepted only when all four sides
/// are edges of the right polarity with at least half the code square's
/// contrast and the corners stay within 0.35 module of the prediction; a
/// clipped frame (prediction near the image border) is not tried, an
/// occluded side fails the contrast test.
fn frame_from_prediction<G: MatTraitConst + ToInputArray>(
    params: &DetectParams,
    codes: CodeSet,
    images: &Images<'_, G>,
    frame: &PredictedFrame<'_>,
) -> Option<FittedSquare> {
    if params.refinement != Refinement::EdgeModel {
        return None;
    }
    let view: &GrayView<'_> = &images.view;
    let (module_px, polarity) = (frame.module_px, frame.polarity);
    let code_fit = frame.code.fit.as_ref()?;
    let pred = predict_frame(codes, &frame.code.corners, frame.off)?;
    let margin = module_px + 4.0;
    if !pred.iter().all(|p| view.contains(p[0], p[1], margin)) {
        return None;
    }
    let coarse = refine::refine_by_edge_lines_coarse(view, &pred, module_px, polarity)?;
    // The frame is accepted on the detection image (the restored frame),
    // where its contrast compares with the code square's.
    let blurred = Profile::Blurred;
    let code_contrast = if code_fit.profile() == blurred {
        code_fit.min_contrast()
    } else {
        let dark = Polarity::DarkInside.sign();
        edge_model::fit_square(view, &frame.code.corners, module_px, dark, blurred)?.min_contrast()
    };
    let check = edge_model::fit_square(view, &coarse, module_px, polarity.sign(), blurred)?;
    if check.min_contrast() < 0.5 * code_contrast {
        return None;
    }
    // The restored-frame fall-back is `check` itself, not fitted again.
    let square = images
        .raw
        .as_ref()
        .and_then(|r| corners::fit_on_raw(r, &coarse, module_px, polarity))
        .or_else(|| Some(FittedSquare::from_fit(check.corners(None)?, check)))?;
    (0..4)
        .all(|i| dist(square.corners[i], pred[i]) < 0.35 * module_px)
        .then_some(square)
}
