//! Model-based edge lines: each side of a square is located by fitting a
//! blurred straight step edge to every pixel of a band around it (Gauss–Newton
//! over the line's offset and slope, the two grey levels and the blur width).
//!
//! The gradient-peak profiles of [`super::refine`] find each edge sample by a
//! parabola through the derivative maximum. On a sharply rendered or lightly
//! blurred edge that peak "locks" to the pixel grid: on noise-free frames of
//! the accuracy test (paper §6.2 set-up) every corner is still off by a few
//! hundredths of a pixel in a way that depends on the sub-pixel phase, which
//! is the whole angle error in clear water. The step model integrates the edge over
//! all its pixels instead, so for any symmetric blur (pixel area, forward
//! scatter) the fitted line sits on the edge, and in noisy water it is the
//! least-squares (Gaussian maximum-likelihood) estimate from all ~1000 pixels
//! of a side rather than one peak per profile. Design and measurements:
//! `docs/detector.md`.

use super::geom::{dist, Line, Px};
use crate::mat::GrayView;
use nalgebra::{SMatrix, SVector};

type MatP = SMatrix<f64, NP, NP>;
type VecP = SVector<f64, NP>;

/// Smallest grey-level step accepted as an edge.
const MIN_STEP: f64 = 3.0;

/// `erf(x)` (Abramowitz & Stegun 7.1.26, |error| < 1.5e-7) and `exp(−x²)`.
#[inline]
fn erf_and_gauss(x: f64) -> (f64, f64) {
    let ax = x.abs();
    let t = 1.0 / (1.0 + 0.327_591_1 * ax);
    let poly = t
        * (0.254_829_592
            + t * (-0.284_496_736
                + t * (1.421_413_741 + t * (-1.453_152_027 + t * 1.061_405_429))));
    // Single precision is plenty here (relative 1e-7) and twice as fast.
    let g = f64::from((-(ax * ax) as f32).exp());
    let e = 1.0 - poly * g;
    (if x < 0.0 { -e } else { e }, g)
}

/// One pixel of a band, in the side's frame: along `u` (normalized to
/// −1..1 over the side), across `v` (px, outward positive), grey level.
#[derive(Debug, Clone, Copy)]
struct BandPx {
    u: f64,
    v: f64,
    g: f64,
}

/// The fitted step: edge `v = c0 + c1·u`, grey `a` inside, `b` outside,
/// blur `sigma` (px), and a grey-level ramp `ramp·u` along the side.
///
/// The ramp is the veil's and the illumination's gradient along the edge
/// (turbid water without restoration: the downwelling light makes the top of
/// the marker brighter). Without it the levels are constant and the only
/// parameter that can follow a ramp is the line's slope: the side tilts.
#[derive(Debug, Clone, Copy)]
struct Step {
    c0: f64,
    c1: f64,
    a: f64,
    b: f64,
    sigma: f64,
    ramp: f64,
    /// Grey-level slope across the edge (per px along the outward normal),
    /// with [`Profile::Halo`]; 0 otherwise.
    cross: f64,
}

/// The edge profile fitted across each side.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum Profile {
    /// A Gaussian-blurred step (restored frames: the halo deconvolved, the
    /// contrast stretched).
    Blurred,
    /// The blurred step plus a linear grey-level slope across it: the
    /// camera's raw frame in turbid water, where the edge is a sharp step
    /// (the unscattered light) on the wide, smooth halo of the
    /// forward-scattered light (paper §4.1, the blur of Eq. (14)). Across a band
    /// of a few pixels the halo — the edge's own and its neighbours' — is a
    /// slope; without it the single Gaussian settles between the two
    /// widths and the line is located by the weak, wide part.
    Halo,
}

/// Parameters of [`Step`].
const NP: usize = 7;

impl Step {
    /// Model grey level and its gradient w.r.t. `(c0, c1, a, b, sigma, ramp)`.
    ///
    /// The edge profile is a unit step blurred by a Gaussian of `sigma` and
    /// integrated over the pixel's footprint across the edge, a box of width
    /// `box_w` (1 px for an axis-aligned edge): `S(s) = (F(s + w/2) − F(s −
    /// w/2)) / w` with `F(x) = x·Φ(x/σ) + σ·φ(x/σ)`. Without the box, a
    /// near-vertical or near-horizontal edge (all its pixels at the same
    /// sub-pixel phase) would be located with a phase-dependent bias.
    #[inline]
    fn eval(&self, p: &BandPx, box_w: f64) -> (f64, [f64; NP]) {
        let s = p.v - self.c0 - self.c1 * p.u;
        let hw = 0.5 * box_w;
        let inv_s = 1.0 / self.sigma;
        let k = std::f64::consts::FRAC_1_SQRT_2 * inv_s;
        let (e_hi, g_hi) = erf_and_gauss((s + hw) * k);
        let (e_lo, g_lo) = erf_and_gauss((s - hw) * k);
        let cdf_hi = 0.5 * (1.0 + e_hi);
        let cdf_lo = 0.5 * (1.0 + e_lo);
        const INV_SQRT_2PI: f64 = 0.398_942_280_401_432_7;
        let pdf_hi = INV_SQRT_2PI * g_hi;
        let pdf_lo = INV_SQRT_2PI * g_lo;
        let f_hi = (s + hw) * cdf_hi + self.sigma * pdf_hi;
        let f_lo = (s - hw) * cdf_lo + self.sigma * pdf_lo;
        let step = (f_hi - f_lo) / box_w;
        let ds = (cdf_hi - cdf_lo) / box_w;
        let dsigma = (pdf_hi - pdf_lo) / box_w;
        let contrast = self.b - self.a;
        let m = self.a + contrast * step + self.ramp * p.u + self.cross * p.v;
        (
            m,
            [
                -contrast * ds,
                -contrast * ds * p.u,
                1.0 - step,
                step,
                contrast * dsigma,
                p.u,
                p.v,
            ],
        )
    }
}

/// Collect the band pixels of the side `a → b` (clockwise quad, outward
/// normal to the left of travel) within `half` px of the edge `v = c0 + c1·u`,
/// leaving out `skip` px at each end, where the neighbouring sides' edges
/// would enter the band. `sparse`: every other pixel along the edge (every
/// pixel across it). The band is scanned row by row over its exact x-interval.
#[allow(clippy::too_many_arguments)]
fn collect_band(
    view: &GrayView<'_>,
    mid: Px,
    d: Px,
    n: Px,
    half_len: f64,
    skip: f64,
    half: f64,
    prev: &Step,
    sparse: bool,
    out: &mut Vec<BandPx>,
) {
    out.clear();
    let umax = half_len - skip;
    // In pixel offsets (dx, dy) from `mid`: |dx·d0 + dy·d1| ≤ umax (along) and
    // |dx·e0 + dy·e1 − c0| ≤ half (across the current edge), e = n − c1·d / half_len.
    let k = prev.c1 / half_len;
    let e = [n[0] - k * d[0], n[1] - k * d[1]];
    // Rows the band can touch: its four corners' y range.
    let mut ylo = f64::INFINITY;
    let mut yhi = f64::NEG_INFINITY;
    for su in [-umax, umax] {
        for sv in [-half, half] {
            let v = prev.c0 + prev.c1 * su / half_len + sv;
            let y = mid[1] + su * d[1] + v * n[1];
            ylo = ylo.min(y);
            yhi = yhi.max(y);
        }
    }
    let ya = (ylo - 1.0).floor().max(0.0) as usize;
    let yb = ((yhi + 1.0).ceil().min(view.height as f64 - 1.0)).max(0.0) as usize;
    // The interval of dx where |a·dx + b| ≤ r, intersected into [lo, hi].
    let clip = |a: f64, b: f64, r: f64, lo: &mut f64, hi: &mut f64| {
        if a.abs() < 1e-12 {
            if b.abs() > r {
                *lo = f64::INFINITY;
            }
            return;
        }
        let (p, q) = ((-r - b) / a, (r - b) / a);
        *lo = lo.max(p.min(q));
        *hi = hi.min(p.max(q));
    };
    // Sparse: every other pixel along the edge, every pixel across it.
    let along_rows = d[1].abs() > d[0].abs();
    for y in ya..=yb {
        if sparse && along_rows && y % 2 == 1 {
            continue;
        }
        let dy = y as f64 - mid[1];
        let (mut lo, mut hi) = (f64::NEG_INFINITY, f64::INFINITY);
        clip(d[0], dy * d[1], umax, &mut lo, &mut hi);
        clip(e[0], dy * e[1] - prev.c0, half, &mut lo, &mut hi);
        // Empty (or NaN) interval: the band misses this row.
        if lo
            .partial_cmp(&hi)
            .is_none_or(|o| o == std::cmp::Ordering::Greater)
        {
            continue;
        }
        let xa = (mid[0] + lo).ceil().max(0.0) as usize;
        let xb = (mid[0] + hi).floor().min(view.width as f64 - 1.0);
        if xb < 0.0 {
            continue;
        }
        let row = view.row(y);
        for (x, &g) in row.iter().enumerate().take(xb as usize + 1).skip(xa) {
            if sparse && !along_rows && x % 2 == 1 {
                continue;
            }
            let dx = x as f64 - mid[0];
            let u = dx * d[0] + dy * d[1];
            let un = u / half_len;
            let v = dx * n[0] + dy * n[1];
            let p = BandPx {
                u: un,
                v,
                g: f64::from(g),
            };
            out.push(p);
        }
    }
}

/// One pixel's terms added to the normal equations (`h`: their upper
/// triangle, row by row, of all [`NP`] parameters; `g`: Jᵀr), for the
/// first `N` parameters only: the rest keep their zeros.
#[inline(always)]
fn accumulate<const N: usize>(
    h: &mut [f64; NP * (NP + 1) / 2],
    g: &mut [f64; NP],
    j: &[f64; NP],
    r: f64,
) {
    let mut k = 0;
    for a in 0..N {
        g[a] += j[a] * r;
        for b in a..N {
            h[k + b - a] += j[a] * j[b];
        }
        k += NP - a;
    }
}

/// Gauss–Newton on the band (a few iterations, damped); `None` when it diverges.
/// Plateau pixels whose residual exceeds `cut` are left out (glare,
/// occluders, a neighbouring edge).
fn fit_step(
    px: &[BandPx],
    init: Step,
    half: f64,
    box_w: f64,
    iters: usize,
    cut: f64,
    profile: Profile,
) -> Option<(Step, StepCovariance)> {
    let mut s = init;
    // The last iteration's factor and residual variance: the covariance
    // is made from them once, when asked for.
    let mut last = StepCovariance(None);
    for _ in 0..iters {
        // Normal equations, upper triangle accumulated by hand (the hot loop).
        let mut h = [0.0f64; NP * (NP + 1) / 2];
        let mut g = [0.0f64; NP];
        let (mut ssr, mut used) = (0.0, 0usize);
        for p in px {
            let (m, j) = s.eval(p, box_w);
            let r = p.g - m;
            // Outliers only on the plateaus: near the edge a residual as
            // large as the contrast just means the line is not there yet.
            if r.abs() > cut && (p.v - s.c0 - s.c1 * p.u).abs() > 2.0 * s.sigma + 1.0 {
                continue;
            }
            ssr += r * r;
            used += 1;
            // The blurred step has no slope across the edge: its row and
            // column of the normal equations stay zero (as the products
            // with a zero derivative left them).
            match profile {
                Profile::Blurred => accumulate::<{ NP - 1 }>(&mut h, &mut g, &j, r),
                Profile::Halo => accumulate::<NP>(&mut h, &mut g, &j, r),
            }
        }
        let mut jtj = MatP::zeros();
        let mut k = 0;
        for a in 0..NP {
            for b in a..NP {
                jtj[(a, b)] = h[k];
                jtj[(b, a)] = h[k];
                k += 1;
            }
        }
        let jtr = VecP::from_column_slice(&g);
        for i in 0..NP {
            jtj[(i, i)] *= 1.0 + 1e-4;
            jtj[(i, i)] += 1e-9;
        }
        // A sharp edge along a pixel row or column leaves the blur nearly
        // unobservable (JᵀJ close to singular): damp more then.
        let chol = match jtj.cholesky() {
            Some(c) => c,
            None => {
                let lambda = 1e-3 * jtj.trace() / NP as f64;
                let mut damped = jtj;
                for i in 0..NP {
                    damped[(i, i)] += lambda;
                }
                damped.cholesky()?
            }
        };
        let step = chol.solve(&jtr);
        if !step.iter().all(|v| v.is_finite()) {
            return None;
        }
        last = StepCovariance(Some((chol, ssr / used.saturating_sub(NP).max(1) as f64)));
        // Trust region: the line moves at most 1 px (offset) per iteration.
        let k = (1.0 / step[0].abs().max(step[1].abs()).max(1e-12)).min(1.0);
        s.c0 += k * step[0];
        s.c1 += k * step[1];
        s.a += k * step[2];
        s.b += k * step[3];
        s.sigma = (s.sigma + k * step[4]).clamp(0.15, half.max(0.5));
        s.ramp += k * step[5];
        s.cross += k * step[6];
        // Converged: the line moves by less than 2e-3 px.
        if (k * step[0]).abs() < 2e-3 && (k * step[1]).abs() < 2e-3 {
            break;
        }
    }
    (s.c0.abs() <= half && s.c1.abs() <= half).then_some((s, last))
}

/// The parameter covariance of a [`fit_step`], made only when asked for:
/// residual variance · (JᵀJ)⁻¹ of its last iteration (zero without one).
struct StepCovariance(Option<(nalgebra::Cholesky<f64, nalgebra::Const<NP>>, f64)>);

impl StepCovariance {
    fn matrix(self) -> MatP {
        self.0
            .map_or_else(MatP::zeros, |(chol, var)| chol.inverse() * var)
    }
}

/// One side's fitted edge in its own frame (`mid`, along `d`, outward `n`).
#[derive(Debug, Clone, Copy)]
struct SideFit {
    step: Step,
    mid: Px,
    d: Px,
    n: Px,
    half_len: f64,
    /// Variance of the fitted blur and the regression of `(c0, c1)` on it.
    var_sigma: f64,
    dc_dsigma: [f64; 2],
}

impl SideFit {
    /// The edge line with the blur fixed at `sigma` instead of this side's own
    /// estimate (the Gaussian conditional of `(c0, c1)` given σ).
    fn line(&self, sigma: f64) -> Option<Line> {
        let ds = sigma - self.step.sigma;
        let c0 = self.step.c0 + self.dc_dsigma[0] * ds;
        let c1 = self.step.c1 + self.dc_dsigma[1] * ds;
        let p = |u: f64| -> Px {
            let v = c0 + c1 * u;
            let along = u * self.half_len;
            [
                self.mid[0] + along * self.d[0] + v * self.n[0],
                self.mid[1] + along * self.d[1] + v * self.n[1],
            ]
        };
        Line::through(p(-1.0), p(1.0))
    }
}

/// The edge of side `a → b` fitted as a blurred step. `sign` is +1 when the
/// outside is brighter (dark square), −1 when darker. `half` is the first
/// round's band half-width (px), `max_half` the second's upper bound.
fn fit_side_model(
    view: &GrayView<'_>,
    a: Px,
    b: Px,
    half: f64,
    max_half: f64,
    sign: f64,
    profile: Profile,
    buf: &mut Vec<BandPx>,
) -> Option<SideFit> {
    let len = dist(a, b);
    if len < 8.0 {
        return None;
    }
    let d = [(b[0] - a[0]) / len, (b[1] - a[1]) / len];
    let n = [d[1], -d[0]];
    let mid = [0.5 * (a[0] + b[0]), 0.5 * (a[1] + b[1])];
    // The pixel's footprint across the edge: its longer projection on the normal.
    let box_w = n[0].abs().max(n[1].abs());
    let half_len = 0.5 * len;
    // Leave out the ends: the adjacent side's edge is `t` px away at `t` px from the corner.
    let skip = (max_half + 2.0).max(0.1 * len);
    if half_len - skip < 3.0 {
        return None;
    }
    let mut step = Step {
        c0: 0.0,
        c1: 0.0,
        a: 0.0,
        b: 0.0,
        sigma: 0.7,
        ramp: 0.0,
        cross: 0.0,
    };
    collect_band(view, mid, d, n, half_len, skip, half, &step, true, buf);
    if buf.len() < 10 {
        return None;
    }
    // Initial grey levels: the band's means on either side of the line.
    let (mut sa, mut na, mut sb, mut nb) = (0.0, 0, 0.0, 0);
    for p in buf.iter() {
        if p.v < -0.5 * half {
            sa += p.g;
            na += 1;
        } else if p.v > 0.5 * half {
            sb += p.g;
            nb += 1;
        }
    }
    if na == 0 || nb == 0 {
        return None;
    }
    step.a = sa / f64::from(na);
    step.b = sb / f64::from(nb);
    if sign * (step.b - step.a) < MIN_STEP {
        return None;
    }
    step = fit_step(buf, step, half, box_w, 1, f64::INFINITY, profile)?.0;
    // Second round: the band re-centred on the fitted edge, outliers dropped.
    let mut res: Vec<f64> = buf
        .iter()
        .map(|p| (p.g - step.eval(p, box_w).0).abs())
        .collect();
    let mid_res = res.len() / 2;
    let robust_sigma = 1.4826 * *res.select_nth_unstable_by(mid_res, f64::total_cmp).1;
    let cut = (4.0 * robust_sigma).max(2.0 * MIN_STEP);
    // Pixels farther than ~3σ from the edge only see the plateaus: a
    // narrower band keeps the cost down where the edge is sharp.
    // Not for the halo profile: its σ is the sharp part's, but its levels
    // and slope need the band's full width — at ±2 px they are poorly
    // pinned and their noise moves the edge.
    let half2 = match profile {
        Profile::Halo => max_half,
        Profile::Blurred => (3.0 * step.sigma + 1.5).clamp(2.0, max_half),
    };
    // With the blur known, the band can run closer to the corners: the
    // adjacent side's edge is ~t px away at t px from the corner, so 4σ plus
    // the band's lean (corners of 80–100° under perspective) is clear of it.
    // The longer lever matters most for the corners, which are the lines
    // extrapolated to the ends.
    let skip2 = (4.0 * step.sigma + 0.25 * half2 + 1.0).clamp(2.0, skip);
    collect_band(view, mid, d, n, half_len, skip2, half2, &step, false, buf);
    if buf.len() < 20 {
        return None;
    }
    let (step, cov) = fit_step(buf, step, half2, box_w, 3, cut, profile)?;
    if sign * (step.b - step.a) < MIN_STEP {
        return None;
    }
    let cov = cov.matrix();
    let var_sigma = cov[(4, 4)];
    let dc_dsigma = if var_sigma > 0.0 && var_sigma.is_finite() {
        [cov[(0, 4)] / var_sigma, cov[(1, 4)] / var_sigma]
    } else {
        [0.0, 0.0]
    };
    Some(SideFit {
        step,
        mid,
        d,
        n,
        half_len,
        var_sigma,
        dc_dsigma,
    })
}

/// The four fitted sides of one square, before their lines are intersected.
#[derive(Debug, Clone, Copy)]
pub struct SquareFit {
    sides: [SideFit; 4],
    start: [Px; 4],
    half: f64,
    profile: Profile,
    raw: bool,
}

/// Fit the four sides of a square (clockwise on screen) whose corners are
/// already within a pixel or so (the coarse edge-line pass). `module_px` sets
/// the bands; `sign` is +1 for a dark square on a bright surround, −1 for the
/// reverse. `None` when a side has no edge.
pub fn fit_square(
    view: &GrayView<'_>,
    quad: &[Px; 4],
    module_px: f64,
    sign: f64,
    profile: Profile,
) -> Option<SquareFit> {
    // The first round needs only the blur's size (±5 px at most); the second
    // reaches ~3σ either side, up to 0.4 module (the next edge is a module away).
    let max_half = (0.4 * module_px).max(2.0);
    let half = max_half.min(5.0);
    let mut buf: Vec<BandPx> = Vec::with_capacity(4096);
    let mut sides = [None; 4];
    for i in 0..4 {
        sides[i] = fit_side_model(
            view,
            quad[i],
            quad[(i + 1) % 4],
            half,
            max_half,
            sign,
            profile,
            &mut buf,
        );
    }
    Some(SquareFit {
        sides: [sides[0]?, sides[1]?, sides[2]?, sides[3]?],
        start: *quad,
        half,
        profile,
        raw: false,
    })
}

/// The blur shared by the sides of `squares`: the inverse-variance weighted
/// mean of their estimates.
///
/// The blur is the water's and the range's, the same on every side; but a
/// side that runs along a pixel row or column samples its edge at one
/// sub-pixel phase only, where blur and position trade off and noise in the
/// fitted blur becomes noise in the line. Pooled, the tilted sides (all
/// phases, a well-determined blur) dominate, and every line is then
/// conditioned on the pooled value ([`SquareFit::corners`]).
pub fn pooled_sigma(squares: &[&SquareFit]) -> Option<f64> {
    let (mut sw, mut swx) = (0.0, 0.0);
    for f in squares.iter().flat_map(|q| q.sides.iter()) {
        if f.var_sigma > 0.0 && f.var_sigma.is_finite() {
            sw += 1.0 / f.var_sigma;
            swx += f.step.sigma / f.var_sigma;
        }
    }
    (sw > 0.0).then(|| swx / sw)
}

impl SquareFit {
    /// The profile the sides were fitted with.
    pub fn profile(&self) -> Profile {
        self.profile
    }

    /// Marks the fit as made on the camera's raw frame (not the detection
    /// image): its blur is pooled only with fits of the same image.
    #[must_use]
    pub fn from_raw(mut self) -> Self {
        self.raw = true;
        self
    }

    /// Fitted on the camera's raw frame ([`SquareFit::from_raw`]).
    pub fn is_raw(&self) -> bool {
        self.raw
    }

    /// Fitted to the same image with the same profile: blurs comparable.
    pub fn same_model(&self, other: &SquareFit) -> bool {
        self.raw == other.raw && self.profile == other.profile
    }

    /// The smallest fitted grey-level step of the four sides.
    pub fn min_contrast(&self) -> f64 {
        self.sides
            .iter()
            .map(|f| (f.step.b - f.step.a).abs())
            .fold(f64::INFINITY, f64::min)
    }

    /// The corners: adjacent sides' lines intersected, each line conditioned
    /// on the blur `sigma` (this square's pooled estimate when `None`).
    /// `None` when the lines do not meet near the starting corners.
    pub fn corners(&self, sigma: Option<f64>) -> Option<[Px; 4]> {
        let sigma = sigma.or_else(|| pooled_sigma(&[self]));
        let mut lines = [None; 4];
        for (l, f) in lines.iter_mut().zip(&self.sides) {
            *l = f.line(sigma.unwrap_or(f.step.sigma));
        }
        let mut out = self.start;
        for i in 0..4 {
            let (prev, this) = (lines[(i + 3) % 4]?, lines[i]?);
            out[i] = prev.intersect(&this)?;
        }
        // The start is already close: a fit that moves a corner by more than the band is not the same edge.
        if (0..4).any(|i| dist(out[i], self.start[i]) > self.half) {
            return None;
        }
        Some(out)
    }
}

/// Refine the corners of one square by the step-edge model: [`fit_square`],
/// then [`SquareFit::corners`] with the square's own pooled blur.
pub fn refine_by_edge_model(
    view: &GrayView<'_>,
    quad: &[Px; 4],
    module_px: f64,
    sign: f64,
) -> Option<[Px; 4]> {
    fit_square(view, quad, module_px, sign, Profile::Blurred)?.corners(None)
}

#[cfg(test)]
mod tests;
