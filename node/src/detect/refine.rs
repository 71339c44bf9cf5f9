//! Sub-pixel corner refinement (paper §5: "analysis of the grayscale gradient
//! distribution ... iterative refinement of these coordinates at a subpixel
//! level").
//!
//! The default fits a straight line to the grey-level edge of each whole side
//! of a square and intersects adjacent lines: every pixel along a side votes,
//! so the corner inherits the precision of ~100 edge samples instead of the
//! few pixels of a local corner window, which is what noisy, blurred water
//! images need. The local alternative (`cv::cornerSubPix` with a window
//! scaled to the module size) is kept for comparison.

use super::geom::{dist, Line, Px};
use crate::mat::GrayView;

/// Which way the grey level changes when leaving a square across its sides.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum Polarity {
    /// Dark square on a bright surround (outer edge of a black region).
    DarkInside,
    /// Bright square inside a dark surround (inner edge of a black frame).
    BrightInside,
}

impl Polarity {
    /// +1 for a dark inside, −1 for a bright one: the sign of the grey-level
    /// step when leaving the square (the step model's `sign`).
    pub fn sign(self) -> f64 {
        match self {
            Polarity::DarkInside => 1.0,
            Polarity::BrightInside => -1.0,
        }
    }
}

/// The strongest edge along a profile through `base` in direction `n`,
/// searched over `[-half, half]` px: sub-pixel offset and gradient strength.
fn edge_on_profile(
    view: &GrayView<'_>,
    base: Px,
    n: Px,
    half: f64,
    sign: f64,
) -> Option<(f64, f64)> {
    // Tangent direction: each profile sample averages three points 1 px apart
    // along the edge, which cuts sensor noise by √3 without blurring across it.
    let tg = [-n[1], n[0]];
    const STEP: f64 = 0.5;
    let k = (half / STEP).ceil() as i32;
    // Samples at t = (j - k - 2) * STEP for j in 0..2k+5 (two extra each side for the derivative).
    let len = (2 * k + 5) as usize;
    let mut prof = [0.0f64; 160];
    if len > prof.len() {
        return None;
    }
    for j in 0..len {
        let t = (j as f64 - f64::from(k) - 2.0) * STEP;
        let (x, y) = (base[0] + t * n[0], base[1] + t * n[1]);
        prof[j] = view.sample(x - tg[0], y - tg[1])
            + view.sample(x, y)
            + view.sample(x + tg[0], y + tg[1]);
    }
    // Derivative over ±1 px (two steps), polarity applied.
    let mut best = (f64::MIN, 0usize);
    let mut der = [0.0f64; 160];
    for j in 2..len - 2 {
        der[j] = sign * (prof[j + 2] - prof[j - 2]) / 2.0;
        if der[j] > best.0 {
            best = (der[j], j);
        }
    }
    let (peak, j) = best;
    if peak <= 0.0 || j <= 2 || j >= len - 3 {
        return None;
    }
    let (a, b, c) = (der[j - 1], der[j], der[j + 1]);
    let denom = a - 2.0 * b + c;
    let off = if denom < -1e-12 {
        0.5 * (a - c) / denom
    } else {
        0.0
    };
    let t = (j as f64 - f64::from(k) - 2.0 + off.clamp(-0.5, 0.5)) * STEP;
    Some((t, peak))
}

/// Fit a line to the edge along the side `a → b` (outward normal to the left of
/// travel in a y-down image, i.e. the quad is clockwise on screen).
fn fit_side(
    view: &GrayView<'_>,
    a: Px,
    b: Px,
    half: f64,
    sign: f64,
    spacing_px: f64,
) -> Option<Line> {
    let len = dist(a, b);
    if len < 4.0 {
        return None;
    }
    let d = [(b[0] - a[0]) / len, (b[1] - a[1]) / len];
    let n = [d[1], -d[0]];
    let count = ((len / spacing_px) as usize).clamp(8, 160);
    let mut pts: Vec<(Px, f64)> = Vec::with_capacity(count);
    for i in 0..count {
        // Skip the corners, where the neighbouring side's edge would pull the profile.
        let s = 0.12 + 0.76 * (i as f64 + 0.5) / count as f64;
        let base = [a[0] + s * len * d[0], a[1] + s * len * d[1]];
        if !view.contains(base[0], base[1], half + 2.0) {
            continue;
        }
        if let Some((t, w)) = edge_on_profile(view, base, n, half, sign) {
            pts.push(([base[0] + t * n[0], base[1] + t * n[1]], w));
        }
    }
    if pts.len() < 5 {
        return None;
    }
    // Drop weak responses (occluders, glare) before fitting.
    let mut ws: Vec<f64> = pts.iter().map(|p| p.1).collect();
    ws.sort_by(f64::total_cmp);
    let median_w = ws[ws.len() / 2];
    pts.retain(|p| p.1 >= 0.3 * median_w);
    let mut line = Line::fit(&pts)?;
    // One robust pass: drop residual outliers beyond 3 MAD-sigmas (at least 0.5 px).
    let mut res: Vec<f64> = pts.iter().map(|(p, _)| line.distance(*p).abs()).collect();
    res.sort_by(f64::total_cmp);
    let sigma = 1.4826 * res[res.len() / 2];
    let cut = (3.0 * sigma).max(0.5);
    pts.retain(|(p, _)| line.distance(*p).abs() <= cut);
    if pts.len() >= 5 {
        line = Line::fit(&pts)?;
    }
    Some(line)
}

/// Refine the corners of a square (clockwise on screen) by edge-line fitting.
/// `module_px` sets the search range; returns `None` when a side has no edge.
pub fn refine_by_edge_lines(
    view: &GrayView<'_>,
    quad: &[Px; 4],
    module_px: f64,
    polarity: Polarity,
) -> Option<[Px; 4]> {
    edge_line_passes(view, quad, module_px, polarity, &PASSES, 1.0)
}

/// Pass 1 searches ±0.45 module around the contour estimate, pass 2 ±0.3
/// module around pass 1. The contour corners are within a few pixels
/// (half-resolution contours, polygon approximation), so the first search is
/// capped at 6 px; the second only needs to cover the first fit's error.
/// Pass 1 samples every 3rd pixel along the side (it only has to get close);
/// pass 2 uses every pixel, which is where the precision comes from.
/// `(fraction of a module, cap px, spacing px)`.
const PASSES: [(f64, f64, f64); 2] = [(0.45, 6.0, 3.0), (0.3, 2.5, 1.0)];

/// Only the coarse pass of [`refine_by_edge_lines`]: the start of the
/// step-edge model fit ([`super::edge_model`]), which replaces the fine pass.
/// Where it finds no edge within ±0.45 module (at least 1.5 px) of a side,
/// once more within ±0.9 module: a far marker's polygon from the
/// half-resolution level can be 2–2.5 px off at a module of 2.8 px. Edges of
/// the same polarity are two modules apart, so the wider search cannot
/// take a neighbour's.
pub fn refine_by_edge_lines_coarse(
    view: &GrayView<'_>,
    quad: &[Px; 4],
    module_px: f64,
    polarity: Polarity,
) -> Option<[Px; 4]> {
    // The fine fit starts from this: every 8th pixel along a side is enough.
    edge_line_passes(view, quad, module_px, polarity, &[(0.45, 6.0, 8.0)], 1.0)
        .or_else(|| edge_line_passes(view, quad, module_px, polarity, &[(0.9, 6.0, 4.0)], 1.0))
}

/// The square's edges searched for within ±1.5 modules of each side, then
/// once more within ±0.45 module of what that found: for a polygon with a
/// corner pulled a module or more out (a shadow or the card's edge joined
/// to the black region at that corner, so the contour runs out to it, and
/// the polygon's approximation skews the sides next to it). Each side's
/// edge points are fitted robustly, so the part of a side that runs along
/// the true edge decides where it lies; a corner may move two modules at
/// most. Only for modules over 6.7 px: below that the coarse search
/// ([`refine_by_edge_lines_coarse`]) already reaches ±0.9 module, above it
/// its cap of 6 px stops short of one.
pub fn refine_by_edge_lines_wide(
    view: &GrayView<'_>,
    quad: &[Px; 4],
    module_px: f64,
    polarity: Polarity,
) -> Option<[Px; 4]> {
    if 0.9 * module_px <= COARSE_CAP_PX {
        return None;
    }
    edge_line_passes(
        view,
        quad,
        module_px,
        polarity,
        &[(1.5, f64::INFINITY, 8.0), (0.45, COARSE_CAP_PX, 8.0)],
        2.0,
    )
}

/// The coarse edge search's half-width at most (px).
const COARSE_CAP_PX: f64 = 6.0;

fn edge_line_passes(
    view: &GrayView<'_>,
    quad: &[Px; 4],
    module_px: f64,
    polarity: Polarity,
    passes: &[(f64, f64, f64)],
    max_move_modules: f64,
) -> Option<[Px; 4]> {
    let sign = polarity.sign();
    let mut cur = *quad;
    for &(frac, cap, spacing) in passes {
        let half = (frac * module_px).min(cap).max(1.5);
        let mut lines = [None; 4];
        for i in 0..4 {
            lines[i] = fit_side(view, cur[i], cur[(i + 1) % 4], half, sign, spacing);
        }
        let mut next = cur;
        for i in 0..4 {
            // Corner i is where side i-1 (ending at i) meets side i (starting at i).
            let (prev, this) = (lines[(i + 3) % 4]?, lines[i]?);
            next[i] = prev.intersect(&this)?;
        }
        // A refinement that moves a corner farther than `max_move_modules` is not the same edge.
        if (0..4).any(|i| dist(next[i], quad[i]) > (max_move_modules * module_px).max(2.0)) {
            return None;
        }
        cur = next;
    }
    Some(cur)
}

/// OpenCV's `cornerSubPix` with a window scaled to the module size (`0.35 ·
/// module_px`, clamped to 2..=15 px half-width), the alternative to edge lines.
pub fn refine_by_corner_subpix(
    gray: &impl opencv::core::ToInputArray,
    quad: &[Px; 4],
    module_px: f64,
) -> opencv::Result<[Px; 4]> {
    use opencv::core::{Point2f, Size, TermCriteria, TermCriteria_Type, Vector};
    let mut pts: Vector<Point2f> = quad
        .iter()
        .map(|p| Point2f::new(p[0] as f32, p[1] as f32))
        .collect();
    let win = (0.35 * module_px).round().clamp(2.0, 15.0) as i32;
    let crit = TermCriteria::new(
        TermCriteria_Type::COUNT as i32 + TermCriteria_Type::EPS as i32,
        30,
        0.01,
    )?;
    opencv::imgproc::corner_sub_pix(gray, &mut pts, Size::new(win, win), Size::new(-1, -1), crit)?;
    let mut out = *quad;
    for (i, p) in pts.iter().enumerate() {
        out[i] = [f64::from(p.x), f64::from(p.y)];
    }
    Ok(out)
}
