//! Water quality estimated from the image itself, and HOIRM's parameters as
//! functions of the attenuation coefficient `c`.
//!
//! The estimate uses the 1/8 area-averaged level (noise averaged away):
//! - **backscatter** `B`: the 2nd percentile of the coarse level — the veiling
//!   light over the darkest things in view (the marker's black cells, shadows),
//!   the grey analogue of the dark channel prior's haze level;
//! - **bright** level: the 99.5th percentile;
//! - **veil fraction** `v = B / bright`: 0 in clear water (black stays black),
//!   → 1 as backscatter swamps the signal;
//! - **contrast** `(bright − B) / (bright + B)` (Michelson);
//! - **noise** σ: Immerkær's Laplacian-difference estimator with a median
//!   (robust to edges) on every 16th row of the full-resolution frame and of
//!   its 2x2 and 4x4 area means, scaled to full resolution, over all pixels
//!   and over the darkest 5 %; the largest ([`noise_sigma_across_scales`]:
//!   demosaiced or compressed noise is low-passed and hides from the finest
//!   level; a gamma-encoded frame's noise is largest in its dark levels).
//!
//! - **local contrast** `ΔI`: the 99.9th percentile of the 3x3 morphological
//!   gradient of the coarse level (less 3 coarse noise σ): the black/white
//!   step of the most contrasted object, normally the marker.
//!
//! With the single-scattering model (paper Eq. 6) an object at range `d`
//! shows its reflectance contrast times `t = e^{−c·d}` while the veil is
//! `B∞(1 − t) ≈ B`; with a white-to-veil radiance ratio `W/B∞` (parameter
//! `white_over_veil` = `B∞/W`, 0.5 by default, the simulator's value)
//! `t ≈ (B∞/W)·ΔI/B`. The part `s` of `c` that is small-angle forward
//! scatter still reaches the camera (blurred), so `t = e^{−(1−s)·c·d}` and
//! `c ≈ −ln t / ((1−s)·d_ref)` (`forward_scatter_fraction` s = 0.3), `d_ref` the reference range
//! ([`super::RestoreParams::reference_range_m`], the paper's 600 mm). This
//! is an index of the water rather than a measurement (range and
//! reflectances are unknown, and with no object in view it reads "very
//! turbid"); it only drives the parameters below, and its agreement with the
//! simulator's `c` is reported in `docs/restoration.md`.

use super::{RestoreError, RestoreParams};
use opencv::core::{self, Mat, Point, Size};
use opencv::imgproc;
use opencv::prelude::*;

/// The coarse level averages 8x8 pixels: noise σ divided by 8.
const COARSE_FACTOR_FOR_NOISE: f64 = 8.0;

/// What the image says about the water.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct WaterEstimate {
    /// Veiling light over the darkest objects, grey levels.
    pub backscatter: f64,
    /// 99.5th percentile of the coarse level, grey levels.
    pub bright: f64,
    /// Mean of the coarse level, grey levels.
    pub mean: f64,
    /// `backscatter / bright`.
    pub veil_fraction: f64,
    /// Michelson contrast of the coarse level.
    pub contrast: f64,
    /// Full-resolution noise standard deviation, grey levels.
    pub noise_sigma: f64,
    /// Strongest local (3x3 coarse) contrast above the noise floor, grey levels.
    pub local_contrast: f64,
    /// Attenuation coefficient inferred at the reference range, 1/m.
    pub c_per_m: f64,
}

/// Largest `c` the estimate reports (a fully veiled image), 1/m.
pub const C_MAX_PER_M: f64 = 20.0;

impl WaterEstimate {
    /// Estimate from the full-resolution frame and its 1/8 level.
    pub fn from_image(
        full: &Mat,
        coarse: &Mat,
        params: &RestoreParams,
    ) -> Result<WaterEstimate, RestoreError> {
        let hist = histogram(coarse)?;
        let backscatter = percentile(&hist, 0.02);
        let bright = percentile(&hist, 0.995).max(1.0);
        let mean = hist_mean(&hist);
        let veil_fraction = (backscatter / bright).clamp(0.0, 1.0);
        let contrast = (bright - backscatter) / (bright + backscatter).max(1.0);
        let noise_sigma = noise_sigma_across_scales(full, 16, NOISE_LEVELS)?;
        // Strongest local contrast: 99.9th percentile of the 3x3
        // morphological gradient of the coarse level, less its noise floor.
        let kernel = imgproc::get_structuring_element(
            imgproc::MORPH_RECT,
            Size::new(3, 3),
            Point::new(-1, -1),
        )?;
        let mut grad = Mat::default();
        imgproc::morphology_ex(
            coarse,
            &mut grad,
            imgproc::MORPH_GRADIENT,
            &kernel,
            Point::new(-1, -1),
            1,
            core::BORDER_REPLICATE,
            imgproc::morphology_default_border_value()?,
        )?;
        // The noise's own part of that percentile: 3σ of the coarse level's
        // noise as predicted for white noise, or, where the noise does not
        // average down so (a camera's demosaicing, codec and gamma correlate
        // it), what the gradient itself shows: its median is the water's
        // noise in a frame mostly of water, and the 99.9th percentile of a
        // 3x3 range of Gaussian noise is 2.0x its median.
        let noise_coarse = noise_sigma / COARSE_FACTOR_FOR_NOISE;
        let grad_hist = histogram(&grad)?;
        let noise_floor =
            (3.0 * noise_coarse).max(params.contrast_noise_k * percentile(&grad_hist, 0.5));
        let local_contrast = (percentile(&grad_hist, 0.999) - noise_floor).max(0.0);
        let t = (params.white_over_veil * local_contrast / backscatter.max(1.0)).clamp(1e-4, 1.0);
        let c_per_m = (-t.ln()
            / ((1.0 - params.forward_scatter_fraction) * params.reference_range_m))
            .clamp(0.0, C_MAX_PER_M);
        Ok(WaterEstimate {
            backscatter,
            bright,
            mean,
            veil_fraction,
            contrast,
            noise_sigma,
            local_contrast,
            c_per_m,
        })
    }
}

/// Generalized-Gaussian shape `p` for water of attenuation `c` (Eq. 14's "p is
/// related to water quality"): `p_clear / (1 + c / c_half)`. Clear water keeps
/// a Gaussian (p = 2) core; turbid water's forward scatter has heavier tails
/// (smaller p), as in the paper's Fig. 6 family.
pub fn psf_p(c_per_m: f64, params: &RestoreParams) -> f64 {
    (params.psf_p_clear / (1.0 + c_per_m.max(0.0) / params.psf_c_half_per_m)).clamp(0.3, 4.0)
}

/// Share of the transmitted light that arrives unscattered, for water of
/// attenuation `c` at the reference range: `e^{−s·c·d_ref}` of the
/// `e^{−(1−s)·c·d_ref}` that is transmitted [Jaffe 1990]. With `c` from the
/// image it is `t^{s/(1−s)}`, `t` the transmission read off the strongest
/// contrast in view, so it does not depend on the reference range: a
/// marker at 4.5 m in 0.5 /m water reads as one at 0.6 m in ~4 /m, and
/// both carry the same unscattered share (0.5).
pub fn direct_share(c_per_m: f64, params: &RestoreParams) -> f64 {
    (-params.forward_scatter_fraction * c_per_m.max(0.0) * params.reference_range_m)
        .exp()
        .clamp(0.0, 1.0)
}

/// Eq. (14)'s σ = 1/(2√p), converted to pixels with `psf_px_per_unit`.
pub fn psf_sigma_px(p: f64, params: &RestoreParams) -> f64 {
    params.psf_px_per_unit / (2.0 * p.sqrt())
}

/// σ (full-resolution pixels) of the Gaussian that smooths the regions
/// before the local stretch, 0 for none: the estimated edge step over noise
/// `ΔI/σ_n` must reach `denoise_edge_snr` after smoothing, and a Gaussian of
/// σ divides white noise by `2√π·σ` (its noise-equivalent area is `4πσ²`)
/// while leaving a step of modules much wider than σ intact.
pub fn denoise_sigma_px(water: &WaterEstimate, params: &RestoreParams) -> f64 {
    if params.denoise_edge_snr <= 0.0 || params.denoise_max_sigma_px <= 0.0 {
        return 0.0;
    }
    let snr = water.local_contrast / water.noise_sigma.max(QUANTIZATION_SIGMA);
    let sigma = params.denoise_edge_snr / (2.0 * std::f64::consts::PI.sqrt() * snr.max(1e-6));
    if sigma < params.denoise_min_sigma_px {
        0.0
    } else {
        sigma.min(params.denoise_max_sigma_px)
    }
}

/// The factor by which a Gaussian of `sigma_px` divides white noise (≥ 1).
pub fn noise_reduction(sigma_px: f64) -> f64 {
    (2.0 * std::f64::consts::PI.sqrt() * sigma_px).max(1.0)
}

/// HOIRM's CLAHE clip limit for water of attenuation `c`: more veil, more
/// stretch allowed.
pub fn clahe_clip(c_per_m: f64, params: &RestoreParams) -> f64 {
    params.clahe_clip_base + params.clahe_clip_per_c * c_per_m.max(0.0)
}

/// A 256-bin histogram of an 8-bit Mat.
pub(crate) fn histogram(m: &impl MatTraitConst) -> Result<[u64; 256], RestoreError> {
    let mut h = [0u64; 256];
    for y in 0..m.rows() {
        for &v in m.at_row::<u8>(y)? {
            h[v as usize] += 1;
        }
    }
    Ok(h)
}

/// The grey level below which a fraction `q` of the pixels lie.
pub(crate) fn percentile(hist: &[u64; 256], q: f64) -> f64 {
    let total: u64 = hist.iter().sum();
    if total == 0 {
        return 0.0;
    }
    let target = (q.clamp(0.0, 1.0) * total as f64).ceil().max(1.0) as u64;
    let mut acc = 0;
    for (v, &n) in hist.iter().enumerate() {
        acc += n;
        if acc >= target {
            return v as f64;
        }
    }
    255.0
}

fn hist_mean(hist: &[u64; 256]) -> f64 {
    let total: u64 = hist.iter().sum();
    if total == 0 {
        return 0.0;
    }
    hist.iter()
        .enumerate()
        .map(|(v, &n)| v as f64 * n as f64)
        .sum::<f64>()
        / total as f64
}

/// The noise floor reported for noiseless (or 8-bit-quantized only) images:
/// the standard deviation of uniform quantization error, 1/√12.
pub const QUANTIZATION_SIGMA: f64 = 0.288_675_134_594_812_9;

/// Noise standard deviation of an 8-bit image (Immerkær 1996, "Fast noise
/// variance estimation", with a median instead of a mean so edges do not
/// count): the 3x3 mask `[1 −2 1; −2 4 −2; 1 −2 1]` annihilates smooth
/// content, its output on white noise σ has standard deviation 6σ, and the
/// median of a half-normal is 0.6745 times its scale. Every `row_step`-th row.
pub fn noise_sigma(m: &impl MatTraitConst, row_step: usize) -> Result<f64, RestoreError> {
    let (rows, cols) = (m.rows(), m.cols());
    if rows < 3 || cols < 3 {
        return Ok(QUANTIZATION_SIGMA);
    }
    let mut hist = vec![0u64; 16 * 255 + 1];
    let mut y = 1;
    while y < rows - 1 {
        let r0 = m.at_row::<u8>(y - 1)?;
        let r1 = m.at_row::<u8>(y)?;
        let r2 = m.at_row::<u8>(y + 1)?;
        for x in 1..cols as usize - 1 {
            let v = r0[x - 1] as i32 - 2 * r0[x] as i32 + r0[x + 1] as i32 - 2 * r1[x - 1] as i32
                + 4 * r1[x] as i32
                - 2 * r1[x + 1] as i32
                + r2[x - 1] as i32
                - 2 * r2[x] as i32
                + r2[x + 1] as i32;
            hist[v.unsigned_abs() as usize] += 1;
        }
        y += row_step.max(1) as i32;
    }
    let total: u64 = hist.iter().sum();
    let half = total.div_ceil(2);
    let mut acc = 0;
    let mut median = 0.0;
    for (v, &n) in hist.iter().enumerate() {
        acc += n;
        if acc >= half {
            // Interpolate inside the bin: the mask output is integer-valued.
            let below = acc - n;
            median = v as f64 - 0.5 + (half - below) as f64 / n.max(1) as f64;
            break;
        }
    }
    Ok((median.max(0.0) / (0.6745 * 6.0)).max(QUANTIZATION_SIGMA))
}

/// Coarsest level of 2x2 area means [`noise_sigma_across_scales`] reads.
pub const NOISE_LEVELS: u32 = 2;

/// The darkest part of the frame whose noise [`noise_sigma_across_scales`]
/// also reads on its own: pixels at or below this quantile of the grey levels.
pub const DARK_QUANTILE: f64 = 0.05;

/// Fewest dark mask outputs for their median to count.
const MIN_DARK_SAMPLES: usize = 200;

/// The noise at the scales and grey levels the detector needs: Immerkær's
/// estimate ([`noise_sigma`]) on the frame and on its 2x2, 4x4, … area means
/// up to level `levels` (f32, no rounding; [`NOISE_LEVELS`] for the frame's
/// estimate), each times the side of its blocks, over all pixels and
/// over the darkest ones ([`DARK_QUANTILE`], where a marker's black cells
/// are); the largest. White noise reads alike on every level (the mean of n×n
/// independent pixels has σ/n); noise that demosaicing or a codec has
/// low-passed hides from the finest level's 3x3 mask (JPEG at quality 75
/// takes a σ 2.7 sensor noise to the quantization floor there) but not from
/// the coarser ones. A gamma-encoded frame stretches the noise of its dark
/// levels and squeezes that of its bright veil, which most pixels show (its
/// slope `(v/255)^(1/γ−1)/γ` for γ 2.2: 1.1 at a fifth of full scale, 0.6 at
/// three fifths).
/// Every `row_step`-th row of the frame (every `row_step/2^k`-th of level `k`).
pub fn noise_sigma_across_scales(
    m: &impl MatTraitConst,
    row_step: usize,
    levels: u32,
) -> Result<f64, RestoreError> {
    let mut sigma = noise_sigma(m, row_step)?;
    let (rows, cols) = (m.rows().max(0) as usize, m.cols().max(0) as usize);
    if rows < 3 || cols < 3 {
        return Ok(sigma);
    }
    // Level 0 is read in place (its mask outputs over all pixels are
    // `noise_sigma`'s); only its dark pixels are read here.
    let frame: Vec<&[u8]> = (0..rows as i32)
        .map(|y| m.at_row::<u8>(y).map(|r| &r[..cols]))
        .collect::<Result<_, _>>()?;
    if let (_, Some(d)) = sample_level(&frame, cols, row_step.max(1), false) {
        sigma = sigma.max(d);
    }
    // Coarser levels: 2x2 block means (a trailing odd row or column is
    // dropped), kept only as long as the next one needs them.
    let mut level = Plane::block_means_u8(&frame, cols);
    for k in 1..=levels {
        if k > 1 {
            level = level.block_means();
        }
        if level.rows < 3 || level.cols < 3 {
            break;
        }
        let rows: Vec<&[f32]> = level.data.chunks_exact(level.cols).collect();
        let (all, dark) = sample_level(&rows, level.cols, (row_step >> k).max(1), true);
        let scale = f64::from(1u32 << k);
        sigma = sigma.max(scale * all);
        if let Some(d) = dark {
            sigma = sigma.max(scale * d);
        }
    }
    Ok(sigma)
}

/// One level of 2x2 block means, row-major f32.
struct Plane {
    rows: usize,
    cols: usize,
    data: Vec<f32>,
}

impl Plane {
    fn block_means_u8(src: &[&[u8]], cols: usize) -> Plane {
        let (h, w) = (src.len() / 2, cols / 2);
        let mut data = Vec::with_capacity(h * w);
        for y in 0..h {
            let (a, b) = (src[2 * y], src[2 * y + 1]);
            data.extend(
                a.chunks_exact(2)
                    .zip(b.chunks_exact(2))
                    .take(w)
                    .map(|(p, q)| {
                        let s =
                            u16::from(p[0]) + u16::from(p[1]) + u16::from(q[0]) + u16::from(q[1]);
                        f32::from(s) * 0.25
                    }),
            );
        }
        Plane {
            rows: h,
            cols: w,
            data,
        }
    }

    fn block_means(&self) -> Plane {
        let (h, w) = (self.rows / 2, self.cols / 2);
        let mut data = Vec::with_capacity(h * w);
        for y in 0..h {
            let a = &self.data[2 * y * self.cols..][..self.cols];
            let b = &self.data[(2 * y + 1) * self.cols..][..self.cols];
            data.extend(
                (0..w).map(|x| ((a[2 * x] + a[2 * x + 1]) + (b[2 * x] + b[2 * x + 1])) * 0.25),
            );
        }
        Plane {
            rows: h,
            cols: w,
            data,
        }
    }
}

/// Index `i` reflected into `0..n` without repeating the edge (OpenCV's
/// `BORDER_REFLECT_101`); 0 when `n < 2`.
fn reflect_101(mut i: isize, n: usize) -> usize {
    if n < 2 {
        return 0;
    }
    let n = n as isize;
    while i < 0 || i >= n {
        i = if i < 0 { -i } else { 2 * (n - 1) - i };
    }
    i as usize
}

/// [`noise_sigma`] on one level (no quantization floor) of at least 3x3,
/// every `row_step`-th row: the median mask output over all pixels (when
/// `want_all`; 0 otherwise), and over the darkest [`DARK_QUANTILE`] of them
/// by their 7x7 mean (a pixel's own value would pick those the noise pulled
/// down, whose mask output is large by selection) when there are enough.
/// Only the sampled rows' means are computed.
fn sample_level<T: Copy + Into<f32>>(
    rows: &[&[T]],
    cols: usize,
    row_step: usize,
    want_all: bool,
) -> (f64, Option<f64>) {
    const R: usize = 3;
    let n_rows = rows.len();
    let capacity = (n_rows / row_step + 1) * cols.saturating_sub(2);
    let (mut levels, mut values) = (Vec::with_capacity(capacity), Vec::with_capacity(capacity));
    // The 7-row sums of the sampled row, reflected 3 columns past each edge,
    // and its vertical second difference (the 3x3 mask is separable).
    let mut padded = vec![0f32; cols + 2 * R];
    let mut second = vec![0f32; cols];
    let mut window = vec![0f32; cols - 2];
    let mut y = 1;
    while y + 1 < n_rows {
        let column_sums = &mut padded[R..][..cols];
        column_sums.fill(0.0);
        for dy in 0..=2 * R {
            let r = rows[reflect_101(y as isize + dy as isize - R as isize, n_rows)];
            for (s, &v) in column_sums.iter_mut().zip(r.iter()) {
                *s += v.into();
            }
        }
        for d in 1..=R {
            padded[R - d] = padded[R + reflect_101(-(d as isize), cols)];
            padded[R + cols - 1 + d] = padded[R + reflect_101((cols - 1 + d) as isize, cols)];
        }
        for (((s, &a), &b), &c) in second
            .iter_mut()
            .zip(rows[y - 1])
            .zip(rows[y])
            .zip(rows[y + 1])
        {
            *s = a.into() - 2.0 * b.into() + c.into();
        }
        values.extend(second.windows(3).map(|w| (w[0] - 2.0 * w[1] + w[2]).abs()));
        // Each 7-wide window's sum as seven shifted adds over the row (the
        // compiler vectorises them): the sums are of whole multiples of
        // 4^−level grey levels, exact in f32 in any order for the levels read.
        window.fill(0.0);
        for k in 0..=2 * R {
            for (s, &v) in window.iter_mut().zip(&padded[1 + k..]) {
                *s += v;
            }
        }
        levels.extend(window.iter().map(|s| s / 49.0));
        y += row_step;
    }
    if values.is_empty() {
        return (0.0, None);
    }
    let scale = |median: f32| f64::from(median) / (0.6745 * 6.0);
    let n_dark = (DARK_QUANTILE * values.len() as f64) as usize;
    let dark = (n_dark >= MIN_DARK_SAMPLES).then(|| {
        // The darkest `n_dark` by level, ties at the threshold in row order.
        let threshold = {
            let mut l = levels.clone();
            *l.select_nth_unstable_by(n_dark, f32::total_cmp).1
        };
        let mut dark: Vec<f32> = Vec::with_capacity(n_dark + 1);
        dark.extend(
            levels
                .iter()
                .zip(&values)
                .filter(|(l, _)| **l < threshold)
                .map(|(_, v)| *v),
        );
        let ties = levels
            .iter()
            .zip(&values)
            .filter(|(l, _)| **l == threshold)
            .map(|(_, v)| *v);
        let missing = n_dark.saturating_sub(dark.len());
        dark.extend(ties.take(missing));
        scale(median_of(&mut dark))
    });
    let all = if want_all {
        scale(median_of(&mut values))
    } else {
        0.0
    };
    (all, dark)
}

fn median_of(v: &mut [f32]) -> f32 {
    let mid = v.len() / 2;
    *v.select_nth_unstable_by(mid, f32::total_cmp).1
}

#[cfg(test)]
mod tests {
    use super::*;
    use opencv::core::{Mat, Scalar, CV_8UC1};
    use rand::SeedableRng;
    use rand_chacha::ChaCha8Rng;
    use rand_distr::{Distribution, Normal};

    fn noisy_flat(mean: f64, sigma: f64, seed: u64) -> Mat {
        let mut rng = ChaCha8Rng::seed_from_u64(seed);
        let n = Normal::new(mean, sigma).unwrap();
        let mut m = Mat::new_rows_cols_with_default(200, 300, CV_8UC1, Scalar::all(0.0)).unwrap();
        for y in 0..200 {
            for v in m.at_row_mut::<u8>(y).unwrap() {
                *v = n.sample(&mut rng).round().clamp(0.0, 255.0) as u8;
            }
        }
        m
    }

    /// `m` blurred by a Gaussian of `sigma` px.
    fn gaussian(m: &Mat, sigma: f64) -> Mat {
        let mut out = Mat::default();
        imgproc::gaussian_blur(
            m,
            &mut out,
            Size::new(0, 0),
            sigma,
            sigma,
            core::BORDER_REFLECT_101,
        )
        .unwrap();
        out
    }

    /// Coarse-level noise several times what the frame's own noise predicts
    /// for white noise (σ 3 against 2/8: what a camera's demosaicing, codec
    /// and gamma leave): without the gradient's own noise floor its 99.9th
    /// percentile passes for an object's contrast and the water reads
    /// clearer than it is; with it, noise alone is no contrast, and a dark
    /// square's 40-level step still is.
    #[test]
    fn correlated_noise_is_not_read_as_contrast() {
        let full = noisy_flat(120.0, 2.0, 1);
        let mut coarse = noisy_flat(120.0, 3.0, 2);
        let params = RestoreParams::default();
        let white_only = RestoreParams {
            contrast_noise_k: 0.0,
            ..RestoreParams::default()
        };
        let noise = WaterEstimate::from_image(&full, &coarse, &params).unwrap();
        let noise_white = WaterEstimate::from_image(&full, &coarse, &white_only).unwrap();
        assert!(noise.local_contrast < 3.0, "{noise:?}");
        assert!(noise_white.local_contrast > 12.0, "{noise_white:?}");
        assert!(noise.c_per_m > noise_white.c_per_m + 2.0);
        for y in 70..130 {
            for v in &mut coarse.at_row_mut::<u8>(y).unwrap()[120..180] {
                *v = v.saturating_sub(40);
            }
        }
        let square = WaterEstimate::from_image(&full, &coarse, &params).unwrap();
        assert!(
            square.local_contrast > 24.0 && square.local_contrast < 45.0,
            "{square:?}"
        );
        assert!(square.c_per_m < noise.c_per_m - 2.0, "{square:?} {noise:?}");
    }

    #[test]
    fn noise_estimate_recovers_gaussian_noise_sigma() {
        for sigma in [2.0, 5.0, 12.0] {
            let m = noisy_flat(120.0, sigma, 3);
            let est = noise_sigma(&m, 1).unwrap();
            assert!(
                (est - sigma).abs() < 0.12 * sigma + 0.3,
                "σ {sigma}: estimated {est}"
            );
        }
    }

    /// The first implementation (OpenCV's f32 conversion, INTER_AREA and
    /// 7x7 box filter over whole levels): the one in use must read the same
    /// on levels of even sides, where INTER_AREA's weights are 2x2 means.
    fn reference_across_scales(
        m: &impl MatTraitConst,
        row_step: usize,
        levels: u32,
    ) -> Result<f64, RestoreError> {
        let mut sigma = noise_sigma(m, row_step)?;
        let mut level = Mat::default();
        m.convert_to(&mut level, core::CV_32F, 1.0, 0.0)?;
        for k in 0..=levels {
            if k > 0 {
                let size = Size::new(level.cols() / 2, level.rows() / 2);
                if size.width < 3 || size.height < 3 {
                    break;
                }
                let mut down = Mat::default();
                imgproc::resize(&level, &mut down, size, 0.0, 0.0, imgproc::INTER_AREA)?;
                level = down;
            }
            let (all, dark) = reference_level(&level, (row_step >> k).max(1))?;
            let scale = f64::from(1u32 << k);
            if k > 0 {
                sigma = sigma.max(scale * all);
            }
            if let Some(d) = dark {
                sigma = sigma.max(scale * d);
            }
        }
        Ok(sigma)
    }

    fn reference_level(m: &Mat, row_step: usize) -> Result<(f64, Option<f64>), RestoreError> {
        let (rows, cols) = (m.rows(), m.cols());
        let mut mean = Mat::default();
        imgproc::box_filter(
            m,
            &mut mean,
            -1,
            Size::new(7, 7),
            Point::new(-1, -1),
            true,
            core::BORDER_REFLECT_101,
        )?;
        let mut samples: Vec<(f32, f32)> = Vec::new();
        let mut y = 1;
        while y < rows - 1 {
            let r0 = m.at_row::<f32>(y - 1)?;
            let r1 = m.at_row::<f32>(y)?;
            let r2 = m.at_row::<f32>(y + 1)?;
            let level = mean.at_row::<f32>(y)?;
            for x in 1..cols as usize - 1 {
                let v = (r0[x - 1] - 2.0 * r0[x] + r0[x + 1] - 2.0 * r1[x - 1] + 4.0 * r1[x]
                    - 2.0 * r1[x + 1]
                    + r2[x - 1]
                    - 2.0 * r2[x]
                    + r2[x + 1])
                    .abs();
                samples.push((level[x], v));
            }
            y += row_step.max(1) as i32;
        }
        if samples.is_empty() {
            return Ok((0.0, None));
        }
        let scale = |median: f32| f64::from(median) / (0.6745 * 6.0);
        let mut all: Vec<f32> = samples.iter().map(|s| s.1).collect();
        let all_sigma = scale(median_of(&mut all));
        let n_dark = (DARK_QUANTILE * samples.len() as f64) as usize;
        if n_dark < MIN_DARK_SAMPLES {
            return Ok((all_sigma, None));
        }
        samples.select_nth_unstable_by(n_dark, |a, b| a.0.total_cmp(&b.0));
        let mut dark: Vec<f32> = samples[..n_dark].iter().map(|s| s.1).collect();
        Ok((all_sigma, Some(scale(median_of(&mut dark)))))
    }

    #[test]
    fn sampled_levels_read_what_whole_level_filters_read() {
        let raw = noisy_flat(90.0, 3.0, 8);
        let mut blurred = gaussian(&raw, 0.8);
        // A dark band, and a view into a larger frame (row stride ≠ width).
        Mat::roi(&noisy_flat(30.0, 5.0, 9), core::Rect::new(0, 0, 300, 24))
            .unwrap()
            .copy_to(&mut Mat::roi_mut(&mut blurred, core::Rect::new(0, 100, 300, 24)).unwrap())
            .unwrap();
        let view = Mat::roi(&blurred, core::Rect::new(4, 8, 256, 184)).unwrap();
        for (name, m) in [
            ("whole", blurred.clone()),
            ("view", view.try_clone().unwrap()),
        ] {
            for (row_step, levels) in [(1, 2), (2, 1), (4, 2)] {
                let now = noise_sigma_across_scales(&m, row_step, levels).unwrap();
                let reference = reference_across_scales(&m, row_step, levels).unwrap();
                assert!(
                    (now - reference).abs() <= 1e-4 * reference,
                    "{name}, row step {row_step}, {levels} levels: {now} vs {reference}"
                );
            }
        }
    }

    #[test]
    fn white_noise_reads_alike_across_scales_and_in_the_dark() {
        // 200x300 px: the darkest 5 % by their 7x7 mean are picked by the
        // noise itself here; the mean keeps that from inflating the estimate.
        for sigma in [2.0, 5.0] {
            let m = noisy_flat(120.0, sigma, 4);
            let fine = noise_sigma(&m, 1).unwrap();
            let across = noise_sigma_across_scales(&m, 1, NOISE_LEVELS).unwrap();
            assert!(
                across >= fine && across < 1.15 * sigma + 0.3,
                "σ {sigma}: finest level {fine}, across scales {across}"
            );
        }
    }

    #[test]
    fn low_passed_noise_hides_from_the_finest_level_but_not_from_the_coarser() {
        // White noise σ 4 blurred by a Gaussian of σ 1 px (what demosaicing
        // and a codec's quantized high frequencies do): the 3x3 mask at full
        // resolution sees a fraction of it; the 4x4 means keep more.
        let raw = noisy_flat(120.0, 4.0, 5);
        let blurred = gaussian(&raw, 1.0);
        let fine = noise_sigma(&blurred, 1).unwrap();
        let across = noise_sigma_across_scales(&blurred, 1, NOISE_LEVELS).unwrap();
        assert!(fine < 1.2, "finest level {fine}");
        // The 4x4 means' own finest frequencies are still damped by the
        // blur (to ~0.7 at their Nyquist), so about half of σ comes back.
        assert!(
            across > 1.8 && across > 2.0 * fine && across < 4.6,
            "across scales {across}, finest level {fine}"
        );
    }

    #[test]
    fn the_noise_of_the_dark_levels_counts_where_most_pixels_are_quiet() {
        // A gamma-encoded frame: a dark tenth (a marker's black cells)
        // carries σ 6, the bright veil σ 1.5.
        let mut m = noisy_flat(180.0, 1.5, 6);
        let dark = noisy_flat(40.0, 6.0, 7);
        Mat::roi(&dark, core::Rect::new(0, 0, 300, 20))
            .unwrap()
            .copy_to(&mut Mat::roi_mut(&mut m, core::Rect::new(0, 0, 300, 20)).unwrap())
            .unwrap();
        let fine = noise_sigma(&m, 1).unwrap();
        let across = noise_sigma_across_scales(&m, 1, NOISE_LEVELS).unwrap();
        assert!(fine < 2.2, "finest level, all pixels {fine}");
        assert!(across > 5.0 && across < 7.0, "across scales {across}");
    }

    #[test]
    fn noise_estimate_ignores_a_step_edge() {
        let mut m = Mat::new_rows_cols_with_default(100, 100, CV_8UC1, Scalar::all(40.0)).unwrap();
        for y in 0..100 {
            for v in &mut m.at_row_mut::<u8>(y).unwrap()[50..] {
                *v = 200;
            }
        }
        assert!(noise_sigma(&m, 1).unwrap() <= QUANTIZATION_SIGMA + 1e-12);
    }

    #[test]
    fn denoising_is_off_for_strong_edges_and_grows_as_they_sink_into_noise() {
        let params = RestoreParams::default();
        let water = |contrast: f64, noise: f64| WaterEstimate {
            backscatter: 110.0,
            bright: 140.0,
            mean: 120.0,
            veil_fraction: 0.8,
            contrast: 0.1,
            noise_sigma: noise,
            local_contrast: contrast,
            c_per_m: 10.0,
        };
        // Edge step / noise 26: no smoothing.
        assert_eq!(denoise_sigma_px(&water(26.0, 1.0), &params), 0.0);
        // 3.4 (calibrated water at 12.20 /m): σ with the target met.
        let s = denoise_sigma_px(&water(3.6, 1.05), &params);
        assert!(
            s > params.denoise_min_sigma_px && s < params.denoise_max_sigma_px,
            "{s}"
        );
        let snr_after = 3.6 / 1.05 * noise_reduction(s);
        assert!(
            (snr_after - params.denoise_edge_snr).abs() < 1e-6,
            "{snr_after}"
        );
        // Nothing contrasted: the largest σ.
        assert_eq!(
            denoise_sigma_px(&water(0.0, 1.0), &params),
            params.denoise_max_sigma_px
        );
    }

    #[test]
    fn percentile_of_a_two_level_histogram() {
        let mut h = [0u64; 256];
        h[10] = 30;
        h[200] = 70;
        assert_eq!(percentile(&h, 0.02), 10.0);
        assert_eq!(percentile(&h, 0.30), 10.0);
        assert_eq!(percentile(&h, 0.31), 200.0);
    }

    #[test]
    fn veil_raises_estimated_attenuation() {
        let params = RestoreParams::default();
        // Clear: black 10, white 200. Veiled: black 120, white 200.
        let make = |black: f64| {
            let mut m =
                Mat::new_rows_cols_with_default(160, 160, CV_8UC1, Scalar::all(200.0)).unwrap();
            for y in 40..120 {
                for v in &mut m.at_row_mut::<u8>(y).unwrap()[40..120] {
                    *v = black as u8;
                }
            }
            m
        };
        let est = |m: &Mat| {
            let coarse = crate::restore::coarse_level(m, 8).unwrap();
            WaterEstimate::from_image(m, &coarse, &params).unwrap()
        };
        let clear = est(&make(10.0));
        let veiled = est(&make(120.0));
        assert_eq!(clear.backscatter, 10.0);
        assert_eq!(veiled.backscatter, 120.0);
        assert!(veiled.c_per_m > clear.c_per_m + 1.0);
        assert!(veiled.contrast < clear.contrast);
    }
}
