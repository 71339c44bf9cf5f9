//! Stage 4 of the detector, **fit corners**: each square's corners to
//! sub-pixel precision, then one choice per marker of which fit gives its
//! corners, recorded with the reason in [`Detection::corner_fit`]
//! ([`CornerChoice`]).
//!
//! Per square (`refine_square`, [`FittedSquare`]), with the default
//! [`Refinement::EdgeModel`]: coarse edge lines ([`super::refine`]), then
//! each side fitted as a blurred, pixel-integrated step to every pixel of a
//! band around it ([`super::edge_model`]). Given the camera's raw frame, the
//! sides are fitted there — one Gaussian when the edge is sharp (blur under
//! [`HALO_MIN_SIGMA_PX`]), else the halo profile — and on the detection
//! image (the restoration) when the raw frame shows no edge.
//!
//! Per marker (`fit_marker`): one blur pooled over the squares fitted to
//! the same image with the same profile, every side's line conditioned on
//! it; then, when [`DetectParams::fit_pattern`] asks for it, one fit of the
//! whole printed pattern to the raw frame ([`super::pattern`]) replaces the
//! side fits' corners. The choice is a [`CornerFit`] and its
//! [`FitReason`] (e.g. `EdgesWeak { step_dn }`).
//!
//! [`Detection::corner_fit`]: super::Detection::corner_fit

use super::assemble::{Marker, SquareSource};
use super::edge_model::{self, Profile, SquareFit};
use super::geom::{apply, Px};
use super::pattern::{self, PatternFitError};
use super::refine::{self, Polarity};
use super::{DetectParams, FitPattern, Images, Refinement};
use crate::mat::GrayView;
use nalgebra::DMatrix;
use opencv::core::ToInputArray;
use opencv::prelude::*;
use shoal_proto::marker::{CodeSet, MarkerId};

/// On the raw frame, sides whose one-Gaussian blur is narrower than this
/// (px) are kept as they are: a sharp edge has no halo worth a slope, and on
/// a side along a pixel column the slope trades off against the edge's
/// sub-pixel position. The one-Gaussian blur of the raw accuracy frames per
/// water, and what the halo profile did to clear water: `docs/detector.md`,
/// "Fitting on the raw frame".
pub const HALO_MIN_SIGMA_PX: f64 = 0.5;

/// How one square's four corners were measured.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Hash, serde::Serialize)]
#[serde(rename_all = "snake_case")]
pub enum SquareCorners {
    /// Step-edge side fits on the raw frame, one Gaussian (a sharp edge).
    RawSharp,
    /// Step-edge side fits on the raw frame, the halo profile.
    RawHalo,
    /// Step-edge side fits on the detection image (the restoration): no
    /// raw frame, or it showed no edge.
    Restored,
    /// No step-edge fit held: the coarse edge lines.
    CoarseLines,
    /// Gradient-peak edge lines ([`Refinement::EdgeLines`]).
    EdgeLines,
    /// `cv::cornerSubPix` ([`Refinement::CornerSubPix`]).
    #[serde(rename = "corner_subpix")]
    CornerSubPix,
    /// The contour's polygon corners: [`Refinement::None`], or a
    /// refinement that found no edge.
    Contour,
}

/// Which fit gave a detection's corners.
#[derive(Debug, Clone, Copy, PartialEq, Eq, PartialOrd, Ord, Hash, serde::Serialize)]
#[serde(rename_all = "snake_case")]
pub enum CornerFit {
    /// One fit of the whole printed pattern to the raw frame.
    Pattern,
    /// Every square's sides fitted on the camera's raw frame.
    RawSides,
    /// Step-edge side fits, at least one square on the detection image.
    RestoredSides,
    /// Some square has no step-edge fit: its corners are the coarse edge lines.
    CoarseLines,
    /// Gradient-peak edge lines ([`Refinement::EdgeLines`]).
    EdgeLines,
    /// `cv::cornerSubPix` ([`Refinement::CornerSubPix`]).
    #[serde(rename = "corner_subpix")]
    CornerSubPix,
    /// Some square's corners are its contour's polygon corners.
    Contour,
    /// Another detector's own corners (OpenCV ArUco, AprilTag 3).
    Baseline,
}

impl CornerFit {
    pub const ALL: [CornerFit; 8] = [
        CornerFit::Pattern,
        CornerFit::RawSides,
        CornerFit::RestoredSides,
        CornerFit::CoarseLines,
        CornerFit::EdgeLines,
        CornerFit::CornerSubPix,
        CornerFit::Contour,
        CornerFit::Baseline,
    ];

    /// The name in `shoal detect`'s JSON lines and in status counts.
    pub fn name(self) -> &'static str {
        match self {
            CornerFit::Pattern => "pattern",
            CornerFit::RawSides => "raw_sides",
            CornerFit::RestoredSides => "restored_sides",
            CornerFit::CoarseLines => "coarse_lines",
            CornerFit::EdgeLines => "edge_lines",
            CornerFit::CornerSubPix => "corner_subpix",
            CornerFit::Contour => "contour",
            CornerFit::Baseline => "baseline",
        }
    }

    /// The marker-level fit of a square measured by `m`.
    fn of_square(m: SquareCorners) -> CornerFit {
        match m {
            SquareCorners::RawSharp | SquareCorners::RawHalo => CornerFit::RawSides,
            SquareCorners::Restored => CornerFit::RestoredSides,
            SquareCorners::CoarseLines => CornerFit::CoarseLines,
            SquareCorners::EdgeLines => CornerFit::EdgeLines,
            SquareCorners::CornerSubPix => CornerFit::CornerSubPix,
            SquareCorners::Contour => CornerFit::Contour,
        }
    }
}

impl std::fmt::Display for CornerFit {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.write_str(self.name())
    }
}

/// Why the corner stage chose its [`CornerFit`]: whether the whole-pattern
/// fit was wanted ([`DetectParams::fit_pattern`]) and could run.
#[derive(Debug, Clone, Copy, PartialEq, serde::Serialize)]
#[serde(tag = "why", rename_all = "snake_case")]
pub enum FitReason {
    /// The pattern fit needs the whole marker; `corners` were found (a
    /// frame square clipped, occluded or not found, or a code set whose
    /// marker is the code square alone).
    NotTwelveCorners { corners: u8 },
    /// [`FitPattern::Never`].
    PatternNever,
    /// No raw frame was given ([`super::MarkerDetector::detect`]): the
    /// pattern is fitted to the raw frame only.
    NoRawFrame,
    /// [`FitPattern::WhenEdgesWeak`]: every square fitted on the raw frame,
    /// the weakest side stepping `step_dn` grey levels, at or above the
    /// threshold: the side fits stand.
    EdgesStrong { step_dn: f64 },
    /// [`FitPattern::WhenEdgesWeak`]: the weakest raw side steps `step_dn`
    /// grey levels, under the threshold: the pattern is fitted.
    EdgesWeak { step_dn: f64 },
    /// [`FitPattern::WhenEdgesWeak`]: some square has no step-edge fit on
    /// the raw frame: the pattern is fitted.
    NoRawEdge,
    /// [`FitPattern::Always`].
    PatternAlways,
    /// The pattern fit was wanted and refused; the side fits stand.
    PatternFailed { error: PatternFitError },
    /// Another detector (OpenCV ArUco, AprilTag 3): no choice made here.
    Baseline,
}

/// One square of a detection: how it was found and how its corners were measured.
#[derive(Debug, Clone, Copy, PartialEq, Eq, serde::Serialize)]
pub struct SquareReport {
    /// Its first corner's index into [`CodeSet::corners_3d`] (enhanced
    /// marker: 0 outer frame edge, 4 frame inner edge, 8 code square).
    pub first_corner: u8,
    pub found_by: SquareSource,
    pub corners: SquareCorners,
}

/// The corner stage's choice for one marker.
#[derive(Debug, Clone, PartialEq, serde::Serialize)]
pub struct CornerChoice {
    /// Which fit gave the corners.
    pub fit: CornerFit,
    /// Why.
    pub reason: FitReason,
    /// The marker's squares, in the order of its corners.
    pub squares: Vec<SquareReport>,
}

impl CornerChoice {
    /// The choice recorded for another detector's corners.
    pub fn baseline() -> CornerChoice {
        CornerChoice {
            fit: CornerFit::Baseline,
            reason: FitReason::Baseline,
            squares: Vec::new(),
        }
    }
}

/// Detections per [`CornerFit`] (the node pipeline's status counts).
#[derive(Debug, Clone, Copy, Default, PartialEq, Eq)]
pub struct CornerFitCounts {
    counts: [u64; CornerFit::ALL.len()],
}

impl CornerFitCounts {
    pub fn add(&mut self, fit: CornerFit) {
        self.counts[fit as usize] += 1;
    }

    /// Adds `other`'s counts to these.
    pub fn merge(&mut self, other: &CornerFitCounts) {
        for (a, b) in self.counts.iter_mut().zip(other.counts) {
            *a += b;
        }
    }

    pub fn get(&self, fit: CornerFit) -> u64 {
        self.counts[fit as usize]
    }

    pub fn total(&self) -> u64 {
        self.counts.iter().sum()
    }

    /// `(fit, count)` for every fit that ran at least once.
    pub fn nonzero(&self) -> impl Iterator<Item = (CornerFit, u64)> + '_ {
        CornerFit::ALL
            .into_iter()
            .map(|f| (f, self.get(f)))
            .filter(|(_, n)| *n > 0)
    }
}

impl<'a> FromIterator<&'a super::Detection> for CornerFitCounts {
    fn from_iter<I: IntoIterator<Item = &'a super::Detection>>(iter: I) -> Self {
        let mut c = CornerFitCounts::default();
        for d in iter {
            c.add(d.corner_fit.fit);
        }
        c
    }
}

/// One square's refined corners.
#[derive(Debug, Clone, Copy)]
pub struct FittedSquare {
    /// Corners in the order the square was given (clockwise on screen).
    pub corners: [Px; 4],
    /// The step-edge side fits, with [`Refinement::EdgeModel`]: their blur
    /// is pooled over the marker in `fit_marker`.
    pub fit: Option<SquareFit>,
    pub method: SquareCorners,
}

impl FittedSquare {
    /// Corners from a step-edge fit, the method read from the fit.
    pub(crate) fn from_fit(corners: [Px; 4], fit: SquareFit) -> FittedSquare {
        let method = match (fit.is_raw(), fit.profile()) {
            (true, Profile::Blurred) => SquareCorners::RawSharp,
            (true, Profile::Halo) => SquareCorners::RawHalo,
            (false, _) => SquareCorners::Restored,
        };
        FittedSquare {
            corners,
            fit: Some(fit),
            method,
        }
    }

    pub(crate) fn without_fit(corners: [Px; 4], method: SquareCorners) -> FittedSquare {
        FittedSquare {
            corners,
            fit: None,
            method,
        }
    }
}

/// Refine one square (`quad`, corners within a pixel or two) with
/// [`DetectParams::refinement`]; the step-edge fits use the raw frame when
/// there is one ([`fit_model`]).
pub(crate) fn refine_square<G: MatTraitConst + ToInputArray>(
    params: &DetectParams,
    images: &Images<'_, G>,
    quad: &[Px; 4],
    module_px: f64,
    polarity: Polarity,
) -> FittedSquare {
    let view = &images.view;
    let or_contour = |c: Option<[Px; 4]>, method| match c {
        Some(c) => FittedSquare::without_fit(c, method),
        None => FittedSquare::without_fit(*quad, SquareCorners::Contour),
    };
    match params.refinement {
        Refinement::EdgeLines => or_contour(
            refine::refine_by_edge_lines(view, quad, module_px, polarity),
            SquareCorners::EdgeLines,
        ),
        Refinement::EdgeModel => {
            let raw = images.raw.as_ref();
            let coarse = refine::refine_by_edge_lines_coarse(view, quad, module_px, polarity);
            if let Some(fit) = coarse.and_then(|c| fit_model(view, raw, &c, module_px, polarity)) {
                return fit;
            }
            // No fit from there: a corner of `quad` may be a module or more
            // off (a dark region joined to the square at that corner pulled
            // the contour's polygon out), which the coarse search cannot
            // reach. Its edges searched for wider, the fit once more.
            let wide = refine::refine_by_edge_lines_wide(view, quad, module_px, polarity);
            if let Some(fit) = wide.and_then(|w| fit_model(view, raw, &w, module_px, polarity)) {
                return fit;
            }
            match coarse {
                Some(c) => FittedSquare::without_fit(c, SquareCorners::CoarseLines),
                None => FittedSquare::without_fit(*quad, SquareCorners::Contour),
            }
        }
        Refinement::CornerSubPix => or_contour(
            refine::refine_by_corner_subpix(images.gray, quad, module_px).ok(),
            SquareCorners::CornerSubPix,
        ),
        Refinement::None => FittedSquare::without_fit(*quad, SquareCorners::Contour),
    }
}

/// The step-edge fit of one square from its `coarse` corners: on the raw
/// frame when there is one ([`fit_on_raw`]), and when that finds no edge
/// (the sharp part of a side a few grey levels) on the detection image
/// `view` with [`Profile::Blurred`].
fn fit_model(
    view: &GrayView<'_>,
    raw: Option<&GrayView<'_>>,
    coarse: &[Px; 4],
    module_px: f64,
    polarity: Polarity,
) -> Option<FittedSquare> {
    raw.and_then(|r| fit_on_raw(r, coarse, module_px, polarity))
        .or_else(|| {
            let fit =
                edge_model::fit_square(view, coarse, module_px, polarity.sign(), Profile::Blurred)?;
            Some(FittedSquare::from_fit(fit.corners(None)?, fit))
        })
}

/// The raw-frame part of [`fit_model`]: [`Profile::Blurred`] when that
/// finds a sharp edge (one Gaussian narrower than [`HALO_MIN_SIGMA_PX`]:
/// no halo to model), else [`Profile::Halo`]; `None` when neither fits.
pub(crate) fn fit_on_raw(
    raw: &GrayView<'_>,
    coarse: &[Px; 4],
    module_px: f64,
    polarity: Polarity,
) -> Option<FittedSquare> {
    let sign = polarity.sign();
    let with_corners = |f: SquareFit| Some(FittedSquare::from_fit(f.corners(None)?, f));
    let one = edge_model::fit_square(raw, coarse, module_px, sign, Profile::Blurred)?.from_raw();
    if edge_model::pooled_sigma(&[&one]).is_some_and(|s| s < HALO_MIN_SIGMA_PX) {
        return with_corners(one);
    }
    with_corners(edge_model::fit_square(raw, coarse, module_px, sign, Profile::Halo)?.from_raw())
}

/// The corner stage's output for one marker.
#[derive(Debug, Clone)]
pub(crate) struct MarkerCorners {
    pub corners_px: Vec<Px>,
    /// Index of each corner into [`CodeSet::corners_3d`].
    pub corner_ids: Vec<u8>,
    /// Covariance (px²) of `corners_px` when the fit that gave them states
    /// one (the whole-pattern fit).
    pub covariance: Option<DMatrix<f64>>,
    pub choice: CornerChoice,
}

/// The corners of `marker` in the published order, and which fit gave them.
///
/// The side fits' lines are conditioned on one blur per image and profile,
/// pooled over the marker's squares ([`edge_model::pooled_sigma`]). When
/// [`pattern_wanted`] says so and a raw frame is given, one fit of the whole
/// pattern ([`pattern_corners`]) replaces them unless it fails.
pub(crate) fn fit_marker(
    params: &DetectParams,
    codes: CodeSet,
    raw: Option<&GrayView<'_>>,
    marker: &Marker,
) -> MarkerCorners {
    let squares = &marker.squares;
    // One blur for the whole marker (per image fitted): every side's line
    // conditioned on it.
    let pooled = |like: &SquareFit| {
        let fits: Vec<&SquareFit> = squares
            .iter()
            .filter_map(|s| s.square.fit.as_ref())
            .filter(|f| f.same_model(like))
            .collect();
        edge_model::pooled_sigma(&fits)
    };
    let mut corners_px = Vec::with_capacity(4 * squares.len());
    let mut corner_ids = Vec::with_capacity(4 * squares.len());
    for s in squares {
        let c = s
            .square
            .fit
            .as_ref()
            .and_then(|f| f.corners(pooled(f)))
            .unwrap_or(s.square.corners);
        corners_px.extend_from_slice(&c);
        corner_ids.extend(s.first..s.first + 4);
    }
    let sides = squares
        .iter()
        .map(|s| CornerFit::of_square(s.square.method))
        .max()
        .unwrap_or(CornerFit::Contour);
    let (wanted, mut reason) = pattern_wanted(params.fit_pattern, raw.is_some(), marker);
    let mut fit = sides;
    let mut covariance = None;
    if let (true, Some(raw)) = (wanted, raw) {
        match pattern_corners(params, codes, raw, marker.id, &corners_px, &corner_ids) {
            Ok((c, cov)) => {
                corners_px = c;
                covariance = cov;
                fit = CornerFit::Pattern;
            }
            Err(error) => reason = FitReason::PatternFailed { error },
        }
    }
    let squares = squares
        .iter()
        .map(|s| SquareReport {
            first_corner: s.first,
            found_by: s.source,
            corners: s.square.method,
        })
        .collect();
    MarkerCorners {
        corners_px,
        corner_ids,
        covariance,
        choice: CornerChoice {
            fit,
            reason,
            squares,
        },
    }
}

/// Whether the whole pattern is fitted to `marker` under `mode`, and why.
/// The pattern model needs the whole marker (all twelve corners: no side
/// hidden, clipped or occluded) and the raw frame.
fn pattern_wanted(mode: FitPattern, has_raw: bool, marker: &Marker) -> (bool, FitReason) {
    let corners = 4 * marker.squares.len();
    if corners != 12 {
        return (
            false,
            FitReason::NotTwelveCorners {
                corners: corners as u8,
            },
        );
    }
    match mode {
        FitPattern::Never => (false, FitReason::PatternNever),
        _ if !has_raw => (false, FitReason::NoRawFrame),
        FitPattern::Always => (true, FitReason::PatternAlways),
        FitPattern::WhenEdgesWeak { below_dn } => {
            let mut raw_fits = marker.squares.iter().map(|s| s.square.fit);
            if raw_fits.any(|f| f.is_none_or(|f| !f.is_raw())) {
                return (true, FitReason::NoRawEdge);
            }
            let step_dn = marker
                .squares
                .iter()
                .filter_map(|s| s.square.fit.map(|f| f.min_contrast()))
                .fold(f64::INFINITY, f64::min);
            if step_dn < below_dn {
                (true, FitReason::EdgesWeak { step_dn })
            } else {
                (false, FitReason::EdgesStrong { step_dn })
            }
        }
    }
}

/// The corners `ids` of marker `id` from one fit of its whole pattern to
/// `raw`, started from the per-side corners `found`, and their covariance
/// (`None` if it is degenerate).
fn pattern_corners(
    params: &DetectParams,
    codes: CodeSet,
    raw: &GrayView<'_>,
    id: MarkerId,
    found: &[Px],
    ids: &[u8],
) -> Result<(Vec<Px>, Option<DMatrix<f64>>), PatternFitError> {
    let m = codes.modules();
    let grid = codes
        .module_grid(id)
        .map_err(|_| PatternFitError::UnknownCode)?;
    let module_xy: Vec<Px> = ids.iter().map(|&c| corner_module_xy(m, c)).collect();
    let h = pattern::homography_ls(&module_xy, found).ok_or(PatternFitError::Singular)?;
    let mf = m as f64;
    let outer = [[0.0, 0.0], [mf, 0.0], [mf, mf], [0.0, mf]].map(|p| apply(&h, p));
    let lens = pattern::Lens(params.lens);
    let fit = pattern::fit_pattern(raw, &grid, m, &outer, lens)?;
    Ok((
        module_xy.iter().map(|&p| fit.project(p)).collect(),
        fit.points_covariance(m, &module_xy),
    ))
}

/// Module coordinates (column, row from the outer frame's top-left corner,
/// upright) of the enhanced marker's corner `id` ([`CodeSet::corners_3d`]
/// order: outer frame edge, frame inner edge, code border; each TL, TR, BR, BL).
fn corner_module_xy(m: usize, id: u8) -> Px {
    let c = 0.5 * m as f64;
    let half = c - (id / 4) as f64;
    let (sx, sy) = [(-1.0, -1.0), (1.0, -1.0), (1.0, 1.0), (-1.0, 1.0)][(id % 4) as usize];
    [c + sx * half, c + sy * half]
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn corner_names_are_the_json_names() {
        for f in CornerFit::ALL {
            assert_eq!(serde_json::to_value(f).unwrap(), f.name());
        }
        assert_eq!(
            serde_json::to_value(SquareCorners::CornerSubPix).unwrap(),
            "corner_subpix"
        );
        let why = serde_json::to_value(FitReason::EdgesWeak { step_dn: 7.5 }).unwrap();
        assert_eq!(
            why,
            serde_json::json!({"why": "edges_weak", "step_dn": 7.5})
        );
        let failed = FitReason::PatternFailed {
            error: PatternFitError::Diverged,
        };
        assert_eq!(
            serde_json::to_value(failed).unwrap(),
            serde_json::json!({"why": "pattern_failed", "error": "diverged"})
        );
    }

    #[test]
    fn counts_add_up_per_fit() {
        let mut a = CornerFitCounts::default();
        a.add(CornerFit::Pattern);
        a.add(CornerFit::Pattern);
        a.add(CornerFit::RawSides);
        let mut b = CornerFitCounts::default();
        b.add(CornerFit::RawSides);
        b.merge(&a);
        assert_eq!(b.get(CornerFit::Pattern), 2);
        assert_eq!(b.get(CornerFit::RawSides), 2);
        assert_eq!(b.total(), 4);
        let names: Vec<(&str, u64)> = b.nonzero().map(|(f, n)| (f.name(), n)).collect();
        assert_eq!(names, [("pattern", 2), ("raw_sides", 2)]);
    }

    #[test]
    fn the_enhanced_markers_corners_sit_on_its_module_grid() {
        // 10 modules: outer frame at 0/10, its inner edge at 1/9, the code
        // border at 2/8 (paper §3.2).
        assert_eq!(corner_module_xy(10, 0), [0.0, 0.0]);
        assert_eq!(corner_module_xy(10, 2), [10.0, 10.0]);
        assert_eq!(corner_module_xy(10, 5), [9.0, 1.0]);
        assert_eq!(corner_module_xy(10, 11), [2.0, 8.0]);
    }
}
