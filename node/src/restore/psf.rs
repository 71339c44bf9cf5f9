//! The generalized-Gaussian point spread function of forward scatter (paper
//! §4.2, Eq. (14)) and Wiener deconvolution with it in the frequency domain.
//!
//! **Reading of Eq. (14).** The paper writes
//! `h(u,v) = exp(−((u²+v²)/A)^{p/2}) / (2Γ(1+1/p)·A)` with
//! `A = σ·(Γ(1/p)/Γ(3/p))^{1/2}` and `σ = 1/(2√p)`. `A` so defined is the
//! scale of the standard generalized Gaussian whose standard deviation is
//! `σ` (Nadarajah 2005), and `2Γ(1+1/p)·A` is that distribution's 1-D
//! normalizer; for these to be consistent the exponent must be
//! `(r/A)^p = ((u²+v²)/A²)^{p/2}`, which we use: `h(r) ∝ exp(−(r/A)^p)`,
//! normalized numerically on the pixel grid (the 1-D normalizer does not
//! normalize a 2-D kernel). p = 2 is a Gaussian, p = 1 a Laplacian, p < 1
//! heavier tails.
//!
//! **Units.** σ = 1/(2√p) carries no unit in the paper; we scale it by
//! `psf_px_per_unit` pixels (measured against the simulator's blur, see
//! `docs/restoration.md`).
//!
//! **The unscattered part.** Eq. (14) is the PSF of the light that forward
//! scatter displaces; of the light that reaches the camera from an object at
//! optical depth `τ = c·d`, the share `e^{−s·τ}` (`s` the forward-scatter
//! share of `c`) is not scattered at all and stays sharp [Jaffe 1990]: the
//! whole PSF is `direct·δ + (1 − direct)·h` ([`GgPsf::direct`]; the
//! simulator renders the same mixture, `docs/water-model.md`). Its spectrum
//! never falls below `direct`, so the Wiener filter lifts detail finer than
//! the halo instead of removing it: with `h` alone, frequencies where
//! `|H|² ≪ K` are cut, which on a marker a few metres away erases its 3 px
//! modules. HOIRM's detail-keeping restoration deconvolves the mixture; its
//! frame restoration keeps `h` alone by default, whose cut also removes
//! noise (`docs/restoration.md`, "Fine detail").
//!
//! **Wiener filter.** `Ĵ = F⁻¹[ H* / (|H|² + K(ρ)) · F[I − mean] ] + mean` with
//! `K(ρ)` the noise-to-signal power ratio at radial frequency ρ: white
//! noise over a signal spectrum `∝ 1/(1 + (ρ/ρ0)²)` whose mean is the
//! measured signal variance, so `K(ρ) = K·mean(g)/g(ρ)` with `K =
//! σ_noise²/σ_signal²` (a flat `K` over-amplifies the highest frequencies,
//! where a real image has little power and the noise all of it); the mean is taken out so the filter's
//! DC gain `1/(1+K)` does not darken the image. The region is reflected by
//! half the kernel radius on each side before the DFT so the circular
//! convolution does not wrap the opposite border in. DFT sizes are rounded
//! up to multiples of 32 and the PSF's spectrum is cached per (DFT size, p,
//! σ, direct share) (`Transfer`), so consecutive frames reuse it; `K`
//! (quantized to steps of 25 %) is measured per region, so the filter is
//! made from that spectrum on each call, in the pass that applies it to the
//! region's half spectrum (`apply_wiener`). The DFTs are realfft's and
//! rustfft's ([`super::dft2`]), a third of OpenCV's time on these sizes.

use super::dft2::{Dft2, Dft2Planner, Dft2Work};
use super::RestoreError;
use opencv::core::{self, Mat, Scalar, BORDER_REFLECT_101, CV_32F, CV_32FC1, CV_8U};
use opencv::prelude::*;
use realfft::num_complex::Complex32;
use std::collections::HashMap;

/// Γ(x) for x > 0 (Lanczos approximation, g = 7, relative error < 1e-13).
pub fn gamma(x: f64) -> f64 {
    const G: f64 = 7.0;
    const C: [f64; 9] = [
        0.999_999_999_999_809_9,
        676.520_368_121_885_1,
        -1_259.139_216_722_402_8,
        771.323_428_777_653_1,
        -176.615_029_162_140_6,
        12.507_343_278_686_905,
        -0.138_571_095_265_720_12,
        9.984_369_578_019_572e-6,
        1.505_632_735_149_311_6e-7,
    ];
    if x < 0.5 {
        // Reflection formula.
        return std::f64::consts::PI / ((std::f64::consts::PI * x).sin() * gamma(1.0 - x));
    }
    let x = x - 1.0;
    let mut a = C[0];
    let t = x + G + 0.5;
    for (i, &c) in C.iter().enumerate().skip(1) {
        a += c / (x + i as f64);
    }
    (2.0 * std::f64::consts::PI).sqrt() * t.powf(x + 0.5) * (-t).exp() * a
}

/// Corner frequency of the signal spectrum model (cycles per pixel): the
/// Wiener filter assumes image power falling as `1/(1 + (ρ/ρ0)²)`, the
/// `1/f²` of natural images and of step edges, flat below `ρ0` (structures
/// of 16 px and larger, a marker module at working range).
pub const SIGNAL_CORNER_CYCLES_PER_PX: f64 = 1.0 / 8.0;

/// Largest kernel radius considered, pixels (beyond it the heaviest tails used are < 1e-5).
pub const MAX_RADIUS_PX: i32 = 32;

/// Eq. (14)'s PSF with shape `p` and standard deviation `sigma_px` (pixels),
/// mixed with the light that arrives unscattered: `direct·δ + (1 − direct)·h`
/// (Jaffe's decomposition of the transmitted signal, see the module doc).
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct GgPsf {
    pub p: f64,
    pub sigma_px: f64,
    /// Share of the transmitted light that is not scattered (0..1): a sharp
    /// image under the halo. 0 is the paper's Eq. (14) alone.
    pub direct: f64,
}

impl GgPsf {
    /// `A(p, σ) = σ·sqrt(Γ(1/p)/Γ(3/p))`, pixels.
    pub fn scale_px(&self) -> f64 {
        self.sigma_px * (gamma(1.0 / self.p) / gamma(3.0 / self.p)).sqrt()
    }

    /// Radius beyond which `exp(−(r/A)^p) < e^{−12}` (capped at [`MAX_RADIUS_PX`]).
    pub fn radius_px(&self) -> i32 {
        let r = self.scale_px() * 12f64.powf(1.0 / self.p);
        (r.ceil() as i32).clamp(1, MAX_RADIUS_PX)
    }

    /// Unnormalized profile `exp(−(r/A)^p)`.
    pub fn profile(&self, r: f64) -> f64 {
        self.profile_with_scale(r, self.scale_px())
    }

    /// [`Self::profile`] with `A` ([`Self::scale_px`]) given, for many radii.
    fn profile_with_scale(&self, r: f64, scale_px: f64) -> f64 {
        (-(r / scale_px).powf(self.p)).exp()
    }

    /// `direct` as used (clamped to 0..1; NaN as 0).
    fn direct_share(&self) -> f64 {
        if self.direct.is_nan() {
            0.0
        } else {
            self.direct.clamp(0.0, 1.0)
        }
    }

    /// The normalized `(2R+1)²` kernel, f32 (for blurring test images and
    /// for display): the halo's mass `1 − direct`, the centre's `direct` more.
    pub fn kernel(&self) -> Result<Mat, RestoreError> {
        let r = self.radius_px();
        let n = 2 * r + 1;
        let mut k = Mat::new_rows_cols_with_default(n, n, CV_32FC1, Scalar::all(0.0))?;
        let mut sum = 0.0;
        for y in 0..n {
            let row = k.at_row_mut::<f32>(y)?;
            for x in 0..n {
                let v = self.profile(((x - r) as f64).hypot((y - r) as f64));
                row[x as usize] = v as f32;
                sum += v;
            }
        }
        let mut out = Mat::default();
        let direct = self.direct_share();
        k.convert_to(&mut out, CV_32F, (1.0 - direct) / sum, 0.0)?;
        *out.at_2d_mut::<f32>(r, r)? += direct as f32;
        Ok(out)
    }

    fn key(&self) -> (u32, u32, u32) {
        (
            (self.p * 1000.0).round() as u32,
            (self.sigma_px * 1000.0).round() as u32,
            (self.direct_share() * 1000.0).round() as u32,
        )
    }
}

/// Wiener deconvolution with a cache of the PSF spectra its filters are
/// made from, and the DFT plans and buffers it runs in ([`dft2`]).
#[derive(Debug, Default)]
pub struct Wiener {
    /// Per (DFT size, PSF). The filter itself also depends on the
    /// noise-to-signal ratio, measured per region, and is applied from
    /// the spectrum in the same pass that multiplies the image's spectrum
    /// ([`apply_wiener`]).
    transfers: HashMap<TransferKey, Transfer>,
    planner: Dft2Planner,
    work: Dft2Work,
    image: Vec<f32>,
    spectrum: Vec<Complex32>,
}

/// PSF spectra kept before the cache is cleared.
const TRANSFER_LIMIT: usize = 12;

type TransferKey = (usize, usize, (u32, u32, u32));

/// `K` is quantized to `1.25^k`.
fn quantize_nsr(nsr: f64) -> f64 {
    let k = (nsr.max(1e-9).ln() / 1.25f64.ln()).round() as i32;
    1.25f64.powi(k)
}

impl Wiener {
    pub fn new() -> Self {
        Self::default()
    }

    /// Number of cached PSF spectra.
    pub fn cached_spectra(&self) -> usize {
        self.transfers.len()
    }

    /// The PSF spectrum of a `rows`x`cols` DFT, made when not cached.
    fn transfer(&mut self, dft: &Dft2, psf: &GgPsf) -> Result<&Transfer, RestoreError> {
        let key = (dft.rows(), dft.cols(), psf.key());
        if !self.transfers.contains_key(&key) {
            if self.transfers.len() >= TRANSFER_LIMIT {
                self.transfers.clear();
            }
            let t = Transfer::new(dft, psf, &mut self.work)?;
            self.transfers.insert(key, t);
        }
        Ok(&self.transfers[&key])
    }

    /// Deconvolve an 8-bit image (any size ≥ 1x1) with `psf` and noise-to-signal ratio `nsr`.
    pub fn deconvolve(
        &mut self,
        src: &(impl MatTraitConst + core::ToInputArray),
        psf: &GgPsf,
        nsr: f64,
    ) -> Result<Mat, RestoreError> {
        let (padded, r) = padded_for_dft(src, psf)?;
        let (h, w, rows, cols) = (src.rows(), src.cols(), padded.rows(), padded.cols());
        let mean = core::mean(&padded, &core::no_array())?[0];
        let dft = self.planner.plan(rows as usize, cols as usize);
        let mut image = std::mem::take(&mut self.image);
        let mut spectrum = std::mem::take(&mut self.spectrum);
        image.clear();
        let shift = mean as f32;
        for y in 0..rows {
            image.extend(
                padded
                    .at_row::<u8>(y)?
                    .iter()
                    .map(|&v| f32::from(v) - shift),
            );
        }
        spectrum.resize(dft.spectrum_len(), Complex32::default());
        let done = (|| {
            dft.forward(&mut image, &mut spectrum, &mut self.work)?;
            apply_wiener(self.transfer(&dft, psf)?, quantize_nsr(nsr), &mut spectrum);
            dft.inverse(&mut spectrum, &mut image, &mut self.work)?;
            // The inverse is unscaled; the mean goes back, rounded as OpenCV's
            // `convertTo` rounds (half to even) and saturated.
            let scale = 1.0 / (rows as f32 * cols as f32);
            let mut out = Mat::new_rows_cols_with_default(h, w, CV_8U, Scalar::all(0.0))?;
            let (r, w, cols) = (r as usize, w as usize, cols as usize);
            for y in 0..h as usize {
                let from = &image[(y + r) * cols + r..][..w];
                for (o, &v) in out.at_row_mut::<u8>(y as i32)?.iter_mut().zip(from) {
                    *o = (v * scale + shift).round_ties_even().clamp(0.0, 255.0) as u8;
                }
            }
            Ok(out)
        })();
        (self.image, self.spectrum) = (image, spectrum);
        done
    }
}

/// `src` padded for its DFT, and the pad `r` on its top and left: by half
/// the kernel radius (at least 4) on each side, the kernel's mass beyond it
/// being small and what wraps around landing in the region's outer margin,
/// then out to the DFT size ([`round_dft`]); reflected, or replicated where
/// the source is no larger than the pad.
fn padded_for_dft(
    src: &(impl MatTraitConst + core::ToInputArray),
    psf: &GgPsf,
) -> Result<(Mat, i32), RestoreError> {
    let r = (psf.radius_px() / 2).max(4);
    let (h, w) = (src.rows(), src.cols());
    let rows = round_dft(h + 2 * r)?;
    let cols = round_dft(w + 2 * r)?;
    let border = if h > rows - h - r && w > cols - w - r && h > r && w > r {
        BORDER_REFLECT_101
    } else {
        core::BORDER_REPLICATE
    };
    let mut padded = Mat::default();
    core::copy_make_border(
        src,
        &mut padded,
        r,
        rows - h - r,
        r,
        cols - w - r,
        border,
        Scalar::all(0.0),
    )?;
    Ok((padded, r))
}

/// The DFT size used for `n` samples: a multiple of 32 (for cache reuse)
/// that OpenCV's DFT handles fast.
fn round_dft(n: i32) -> Result<i32, RestoreError> {
    let m = (n + 31) / 32 * 32;
    Ok(core::get_optimal_dft_size(m)?)
}

/// The PSF (its halo `1 − direct` of the mass, the unscattered `direct`
/// at the origin) wrapped around the origin of a `rows`x`cols` grid,
/// row-major f32.
fn wrapped_psf(rows: usize, cols: usize, psf: &GgPsf) -> Vec<f32> {
    let r = psf.radius_px().max(0) as usize;
    // The profile at each offset (dx, dy) within the radius, made once: the
    // grid's four quadrants repeat it.
    let scale = psf.scale_px();
    let profile: Vec<f64> = (0..=r)
        .flat_map(|dy| {
            (0..=r).map(move |dx| psf.profile_with_scale((dx as f64).hypot(dy as f64), scale))
        })
        .collect();
    let mut grid = vec![0f32; rows * cols];
    let mut sum = 0.0;
    for (y, row) in grid.chunks_exact_mut(cols).enumerate() {
        let dy = y.min(rows - y);
        if dy > r {
            continue;
        }
        for (x, cell) in row.iter_mut().enumerate() {
            let dx = x.min(cols - x);
            if dx > r {
                continue;
            }
            let v = profile[dy * (r + 1) + dx];
            *cell = v as f32;
            sum += v;
        }
    }
    let direct = psf.direct_share();
    let scale = ((1.0 - direct) / sum) as f32;
    for v in &mut grid {
        *v *= scale;
    }
    grid[0] += direct as f32;
    grid
}

/// What every Wiener filter of one DFT size and PSF shares
/// ([`apply_wiener`]): the PSF's spectrum and the signal model's shape.
#[derive(Debug)]
struct Transfer {
    /// The half spectrum of the PSF wrapped around the origin of the grid
    /// (column by column, as [`Dft2::forward`] gives it).
    h: Vec<Complex32>,
    /// `(f/ρ0)²` of each row's and each half-spectrum column's frequency
    /// (`f` folded to the nearer of ±f, cycles per pixel).
    row_term: Vec<f64>,
    col_term: Vec<f64>,
    /// Mean over the whole grid of the signal spectrum's shape
    /// `g(ρ) = 1/(1 + (ρ/ρ0)²)`.
    mean_g: f64,
}

impl Transfer {
    fn new(dft: &Dft2, psf: &GgPsf, work: &mut Dft2Work) -> Result<Transfer, RestoreError> {
        let (rows, cols) = (dft.rows(), dft.cols());
        let mut h = vec![Complex32::default(); dft.spectrum_len()];
        dft.forward(&mut wrapped_psf(rows, cols, psf), &mut h, work)?;
        let term = |n: usize| -> Vec<f64> {
            (0..n)
                .map(|u| {
                    let f = u.min(n - u) as f64 / n as f64 / SIGNAL_CORNER_CYCLES_PER_PX;
                    f * f
                })
                .collect()
        };
        let (row_term, all_cols) = (term(rows), term(cols));
        let mut mean_g = 0.0;
        for a in &row_term {
            for b in &all_cols {
                mean_g += 1.0 / (1.0 + a + b);
            }
        }
        mean_g /= rows as f64 * cols as f64;
        let col_term = all_cols[..dft.half()].to_vec();
        Ok(Transfer {
            h,
            row_term,
            col_term,
            mean_g,
        })
    }
}

/// `spectrum` (a half spectrum of the size of `t`, column by column) times
/// `W = H*/(|H|² + K(ρ))` for the PSF of `t`, the filter made in the same
/// pass. The signal spectrum's shape `g` is scaled so its mean is the
/// measured signal variance: `K(ρ) = K·mean(g)/g(ρ)`.
fn apply_wiener(t: &Transfer, k: f64, spectrum: &mut [Complex32]) {
    let km = k * t.mean_g;
    let rows = t.row_term.len();
    for ((column, h), ct) in spectrum
        .chunks_exact_mut(rows)
        .zip(t.h.chunks_exact(rows))
        .zip(&t.col_term)
    {
        for ((s, h), rt) in column.iter_mut().zip(h).zip(&t.row_term) {
            let (re, im) = (f64::from(h.re), f64::from(h.im));
            let d = re * re + im * im + km * (1.0 + rt + ct);
            *s *= Complex32::new((re / d) as f32, (-im / d) as f32);
        }
    }
}

/// Largest side (pixels) of the central window [`edge_blur_sigma_px`] looks at.
pub const BLUR_PROBE_MAX_SIDE_PX: i32 = 256;

/// Smoothing scales (pixels) of [`edge_blur_sigma_px`].
pub const BLUR_PROBE_SCALES_PX: (f64, f64) = (1.5, 4.0);

/// Gradient energy `Σ|∇(img ∗ G_s)|²` of an f32 image (Sobel / 8: a
/// derivative per pixel).
fn gradient_energy(img: &Mat, s: f64) -> Result<f64, RestoreError> {
    blurred_gradient_energy(img, s, BORDER_REFLECT_101)
}

/// Per-pixel gradient energy of unit white noise after the same operators.
fn noise_gradient_factor(s: f64) -> Result<f64, RestoreError> {
    let half = (4.0 * s).ceil() as i32 + 3;
    let n = 2 * half + 1;
    let mut delta = Mat::new_rows_cols_with_default(n, n, CV_32FC1, Scalar::all(0.0))?;
    *delta.at_2d_mut::<f32>(half, half)? = 1.0;
    blurred_gradient_energy(&delta, s, core::BORDER_CONSTANT)
}

/// `Σ|∇(img ∗ G_s)|²` with the given border handling (Sobel / 8).
fn blurred_gradient_energy(img: &Mat, s: f64, border: i32) -> Result<f64, RestoreError> {
    let mut g = Mat::default();
    opencv::imgproc::gaussian_blur(img, &mut g, core::Size::new(0, 0), s, s, border)?;
    let mut e = 0.0;
    for (dx, dy) in [(1, 0), (0, 1)] {
        let mut d = Mat::default();
        opencv::imgproc::sobel(&g, &mut d, CV_32F, dx, dy, 3, 1.0 / 8.0, 0.0, border)?;
        e += d.dot(&d)?;
    }
    Ok(e)
}

/// The blur of the edges in `img` (f32; a region holding a marker), as the
/// σ (pixels) of a Gaussian that would give them their width, or `None`
/// when the edges are too weak against the noise `noise_sigma` to tell.
///
/// For a step of height `a` and length `L` blurred to a total σ_t and
/// smoothed by `G_s`, the gradient energy is `a²·L / (2√π·√(σ_t² + s²))`:
/// the ratio `R` of the energies at two scales `s1 < s2` depends on σ_t
/// alone, `σ_t² = (s2² − R²·s1²)/(R² − 1)`, whatever the edges' number,
/// length and contrast. The noise's share of each energy (known from
/// `noise_sigma` and the operators) is subtracted first.
pub fn edge_blur_sigma_px(img: &Mat, noise_sigma: f64) -> Result<Option<f64>, RestoreError> {
    if img.rows() < 16 || img.cols() < 16 {
        return Ok(None);
    }
    // A central window of at most BLUR_PROBE_MAX_SIDE_PX a side (the
    // region is a marker plus margins; the estimate needs its edges, not all
    // of it, and costs two blurs and four Sobels per pixel).
    let (w, h) = (
        img.cols().min(BLUR_PROBE_MAX_SIDE_PX),
        img.rows().min(BLUR_PROBE_MAX_SIDE_PX),
    );
    let window = Mat::roi(
        img,
        core::Rect::new((img.cols() - w) / 2, (img.rows() - h) / 2, w, h),
    )?
    .try_clone()?;
    let img = &window;
    let (s1, s2) = BLUR_PROBE_SCALES_PX;
    let npix = f64::from(img.rows()) * f64::from(img.cols());
    let var = noise_sigma * noise_sigma;
    let e1 = gradient_energy(img, s1)? - npix * var * noise_gradient_factor(s1)?;
    let n2 = npix * var * noise_gradient_factor(s2)?;
    let e2 = gradient_energy(img, s2)? - n2;
    // The coarser energy must stand well above its own noise share.
    if !(e2 > n2.max(1e-9) && e1 > e2) {
        return Ok(None);
    }
    let r2 = (e1 / e2).powi(2);
    let sigma2 = (s2 * s2 - r2 * s1 * s1) / (r2 - 1.0);
    Ok(Some(sigma2.max(0.0).sqrt()))
}

#[cfg(test)]
mod tests {
    use super::*;
    use opencv::core::{Point, Rect, Size, Vec2f, CV_8UC1, DFT_COMPLEX_OUTPUT};
    use opencv::imgproc;

    /// `W = H*/(|H|² + K(ρ))` on the full complex spectrum (OpenCV's DFT of
    /// the same PSF grid), as sessions 1–37 made it before packing it: the
    /// reference [`apply_wiener`]'s filter must equal.
    fn wiener_on_full_spectrum(rows: i32, cols: i32, psf: &GgPsf, k: f64) -> Mat {
        let grid = wrapped_psf(rows as usize, cols as usize, psf);
        let grid = Mat::new_rows_cols_with_data(rows, cols, &grid)
            .unwrap()
            .try_clone()
            .unwrap();
        let mut hc = Mat::default();
        core::dft(&grid, &mut hc, DFT_COMPLEX_OUTPUT, 0).unwrap();
        // Signal spectrum shape g(ρ) = 1/(1 + (ρ/ρ0)²), scaled so its mean is
        // the measured signal variance: K(ρ) = K·mean(g)/g(ρ).
        let shape = |u: i32, v: i32| {
            let fu = u.min(rows - u) as f64 / rows as f64;
            let fv = v.min(cols - v) as f64 / cols as f64;
            1.0 / (1.0
                + (fu * fu + fv * fv) / (SIGNAL_CORNER_CYCLES_PER_PX * SIGNAL_CORNER_CYCLES_PER_PX))
        };
        let mut mean_g = 0.0;
        for u in 0..rows {
            for v in 0..cols {
                mean_g += shape(u, v);
            }
        }
        mean_g /= (rows * cols) as f64;
        for u in 0..rows {
            let row = hc.at_row_mut::<Vec2f>(u).unwrap();
            for v in 0..cols {
                let e = &mut row[v as usize];
                let (re, im) = (e[0] as f64, e[1] as f64);
                let d = re * re + im * im + k * mean_g / shape(u, v);
                e[0] = (re / d) as f32;
                e[1] = (-im / d) as f32;
            }
        }
        hc
    }

    #[test]
    fn the_filter_is_the_one_made_on_the_full_spectrum() {
        // Even sizes (every size `round_dft` gives) and odd ones (no
        // Nyquist row or column); a Gaussian halo and a heavy-tailed one
        // with unscattered light; a low and a high K.
        let psfs = [
            GgPsf {
                p: 2.0,
                sigma_px: 2.7,
                direct: 0.0,
            },
            GgPsf {
                p: 0.9,
                sigma_px: 5.1,
                direct: 0.35,
            },
        ];
        let (mut planner, mut work) = (Dft2Planner::default(), Dft2Work::default());
        for (rows, cols) in [(96, 96), (160, 192), (64, 90), (45, 63), (33, 40), (40, 33)] {
            let dft = planner.plan(rows, cols);
            for psf in &psfs {
                let t = Transfer::new(&dft, psf, &mut work).unwrap();
                for k in [2e-3, 0.1] {
                    // The filter itself: applied to a spectrum of ones.
                    let mut w = vec![Complex32::new(1.0, 0.0); dft.spectrum_len()];
                    apply_wiener(&t, k, &mut w);
                    let reference = wiener_on_full_spectrum(rows as i32, cols as i32, psf, k);
                    let (mut worst, mut largest) = (0f32, 0f32);
                    for u in 0..rows {
                        let row = reference.at_row::<Vec2f>(u as i32).unwrap();
                        for v in 0..dft.half() {
                            let (want, got) = (row[v], w[v * rows + u]);
                            worst =
                                worst.max((want[0] - got.re).abs().max((want[1] - got.im).abs()));
                            largest = largest.max(want[0].abs().max(want[1].abs()));
                        }
                    }
                    assert!(
                        largest > 0.5,
                        "{rows}x{cols}: the filter is not empty ({largest})"
                    );
                    assert!(
                        worst < 2e-5 * largest,
                        "{rows}x{cols}, {psf:?}, K {k}: differs by {worst} (largest {largest})"
                    );
                }
            }
        }
    }

    /// [`Wiener::deconvolve`] as sessions 1–43 ran it, in OpenCV: the same
    /// padding, `dft` with the full complex spectrum, the filter of
    /// [`wiener_on_full_spectrum`], the inverse, `convertTo`.
    fn deconvolve_in_opencv(src: &Mat, psf: &GgPsf, nsr: f64) -> Mat {
        let (padded, r) = padded_for_dft(src, psf).unwrap();
        let (h, w, rows, cols) = (src.rows(), src.cols(), padded.rows(), padded.cols());
        let mean = core::mean(&padded, &core::no_array()).unwrap()[0];
        let mut f = Mat::default();
        padded.convert_to(&mut f, CV_32F, 1.0, -mean).unwrap();
        let mut spec = Mat::default();
        core::dft(&f, &mut spec, DFT_COMPLEX_OUTPUT, 0).unwrap();
        let filter = wiener_on_full_spectrum(rows, cols, psf, quantize_nsr(nsr));
        let mut prod = Mat::default();
        core::mul_spectrums(&spec, &filter, &mut prod, 0, false).unwrap();
        let mut g = Mat::default();
        let inverse = core::DFT_INVERSE | core::DFT_REAL_OUTPUT | core::DFT_SCALE;
        core::dft(&prod, &mut g, inverse, 0).unwrap();
        let mut out = Mat::default();
        Mat::roi(&g, Rect::new(r, r, w, h))
            .unwrap()
            .convert_to(&mut out, CV_8U, 1.0, mean)
            .unwrap();
        out
    }

    #[test]
    fn the_deconvolution_is_opencvs_to_a_grey_level() {
        use rand::{Rng, SeedableRng};
        let mut rng = rand_chacha::ChaCha8Rng::seed_from_u64(7);
        let psf = GgPsf {
            p: 1.1,
            sigma_px: 3.3,
            direct: 0.2,
        };
        let mut wiener = Wiener::new();
        // Even and odd sides, one smaller than the padding (replicated).
        for (h, w) in [(70, 90), (33, 41), (5, 120), (128, 128)] {
            // Bars of random levels under noise: edges to ring, flats to keep.
            let mut src = Mat::new_rows_cols_with_default(h, w, CV_8UC1, Scalar::all(0.0)).unwrap();
            let levels: Vec<f64> = (0..16).map(|_| rng.gen_range(20.0..230.0)).collect();
            for y in 0..h {
                let row = src.at_row_mut::<u8>(y).unwrap();
                for (x, v) in row.iter_mut().enumerate() {
                    let level = levels[(x / 7 + y as usize / 11) % levels.len()];
                    *v = (level + rng.gen_range(-6.0..6.0)).round() as u8;
                }
            }
            for nsr in [1e-3, 0.05] {
                let ours = wiener.deconvolve(&src, &psf, nsr).unwrap();
                let theirs = deconvolve_in_opencv(&src, &psf, nsr);
                let mut diff = Mat::default();
                core::absdiff(&ours, &theirs, &mut diff).unwrap();
                let mut worst = 0.0;
                core::min_max_loc(&diff, None, Some(&mut worst), None, None, &core::no_array())
                    .unwrap();
                let differing = core::count_non_zero(&diff).unwrap();
                assert!(
                    worst <= 1.0 && f64::from(differing) <= 0.01 * f64::from(h * w),
                    "{h}x{w}, NSR {nsr}: {differing} pixels differ, by up to {worst}"
                );
                // Not trivially equal: the deconvolution changed the image.
                assert!(
                    mean_abs_diff(&ours, &src) > 1.0,
                    "{h}x{w}: nothing deconvolved"
                );
            }
        }
    }

    #[test]
    fn gamma_matches_known_values() {
        assert!((gamma(5.0) - 24.0).abs() < 1e-10);
        assert!((gamma(0.5) - std::f64::consts::PI.sqrt()).abs() < 1e-12);
        assert!((gamma(1.5) - std::f64::consts::PI.sqrt() / 2.0).abs() < 1e-12);
        assert!((gamma(0.25) - 3.625_609_908_221_908).abs() < 1e-10);
    }

    #[test]
    fn gaussian_shape_has_the_requested_standard_deviation() {
        // p = 2: A = σ·sqrt(Γ(1/2)/Γ(3/2)) = σ√2, i.e. exp(−r²/(2σ²)).
        let psf = GgPsf {
            p: 2.0,
            sigma_px: 1.7,
            direct: 0.0,
        };
        assert!((psf.scale_px() - 1.7 * 2f64.sqrt()).abs() < 1e-12);
        let k = psf.kernel().unwrap();
        let r = psf.radius_px();
        let mut var_x = 0.0;
        let mut total = 0.0;
        for y in 0..k.rows() {
            for x in 0..k.cols() {
                let v = *k.at_2d::<f32>(y, x).unwrap() as f64;
                total += v;
                var_x += v * ((x - r) as f64).powi(2);
            }
        }
        assert!((total - 1.0).abs() < 1e-5);
        assert!((var_x.sqrt() - 1.7).abs() < 0.02, "σ_x = {}", var_x.sqrt());
    }

    #[test]
    fn smaller_p_has_heavier_tails() {
        let a = GgPsf {
            p: 2.0,
            sigma_px: 1.5,
            direct: 0.0,
        };
        let b = GgPsf {
            p: 0.8,
            sigma_px: 1.5,
            direct: 0.0,
        };
        assert!(b.profile(9.0) / b.profile(0.0) > 100.0 * a.profile(9.0) / a.profile(0.0));
        assert!(b.radius_px() > a.radius_px());
    }

    /// Mean absolute difference of two 8-bit images, grey levels.
    fn mean_abs_diff(a: &Mat, b: &Mat) -> f64 {
        let mut d = Mat::default();
        core::absdiff(a, b, &mut d).unwrap();
        core::mean(&d, &core::no_array()).unwrap()[0]
    }

    /// A 96x96 bar pattern blurred with the PSF; deconvolution must bring it
    /// closer to the original than the blurred image is.
    #[test]
    fn wiener_deconvolution_undoes_a_known_blur() {
        let mut sharp =
            Mat::new_rows_cols_with_default(96, 96, CV_8UC1, Scalar::all(60.0)).unwrap();
        for y in 0..96 {
            let row = sharp.at_row_mut::<u8>(y).unwrap();
            for x in 0..96usize {
                if ((x / 8) + (y as usize / 16)).is_multiple_of(2) {
                    row[x] = 190;
                }
            }
        }
        let psf = GgPsf {
            p: 1.2,
            sigma_px: 1.8,
            direct: 0.0,
        };
        let mut blurred = Mat::default();
        imgproc::filter_2d(
            &sharp,
            &mut blurred,
            -1,
            &psf.kernel().unwrap(),
            Point::new(-1, -1),
            0.0,
            BORDER_REFLECT_101,
        )
        .unwrap();
        let mut wiener = Wiener::new();
        let restored = wiener.deconvolve(&blurred, &psf, 1e-3).unwrap();
        assert_eq!(restored.size().unwrap(), Size::new(96, 96));
        let err = |m: &Mat| mean_abs_diff(&sharp, m);
        let (e_blur, e_rest) = (err(&blurred), err(&restored));
        assert!(e_rest < 0.5 * e_blur, "blurred {e_blur}, restored {e_rest}");
        // Same size and parameters again: served from the cache.
        wiener.deconvolve(&blurred, &psf, 1e-3).unwrap();
        assert_eq!(wiener.cached_spectra(), 1);
    }

    /// 3-px bars (a far marker's modules) seen through water that scatters
    /// half the light into a halo of σ 4.6 px and leaves half sharp (the
    /// simulator's `(1 − w)·δ + w·h`): deconvolved with that PSF the bars
    /// come back at every NSR; deconvolved with the halo alone (the paper's
    /// Eq. (14)) the result is further from them than the blurred input —
    /// over-amplified where the NSR is small, cut where it is not.
    #[test]
    fn the_unscattered_part_keeps_detail_finer_than_the_halo() {
        let mut sharp =
            Mat::new_rows_cols_with_default(96, 96, CV_8UC1, Scalar::all(60.0)).unwrap();
        for y in 0..96 {
            let row = sharp.at_row_mut::<u8>(y).unwrap();
            for x in 0..96usize {
                if (x / 3) % 2 == 0 {
                    row[x] = 190;
                }
            }
        }
        let water = GgPsf {
            p: 1.2,
            sigma_px: 4.6,
            direct: 0.5,
        };
        let k = water.kernel().unwrap();
        let r = water.radius_px();
        let total: f64 = (0..k.rows())
            .flat_map(|y| (0..k.cols()).map(move |x| (y, x)))
            .map(|(y, x)| f64::from(*k.at_2d::<f32>(y, x).unwrap()))
            .sum();
        assert!((total - 1.0).abs() < 1e-5, "kernel mass {total}");
        assert!(f64::from(*k.at_2d::<f32>(r, r).unwrap()) > 0.5);
        let mut blurred = Mat::default();
        imgproc::filter_2d(
            &sharp,
            &mut blurred,
            -1,
            &k,
            Point::new(-1, -1),
            0.0,
            BORDER_REFLECT_101,
        )
        .unwrap();
        // Bright bars less dark bars over the central 64x64.
        let bars = |m: &Mat| {
            let (mut on, mut off) = (0.0, 0.0);
            for y in 16..80 {
                let row = m.at_row::<u8>(y).unwrap();
                for x in 16..80usize {
                    if (x / 3) % 2 == 0 {
                        on += f64::from(row[x]);
                    } else {
                        off += f64::from(row[x]);
                    }
                }
            }
            (on - off) / (64.0 * 32.0)
        };
        let err = |m: &Mat| mean_abs_diff(&sharp, m);
        let mut wiener = Wiener::new();
        let halo = GgPsf {
            direct: 0.0,
            ..water
        };
        for nsr in [1e-3, 1e-2, 5e-2, 0.2] {
            let kept = wiener.deconvolve(&blurred, &water, nsr).unwrap();
            let cut = wiener.deconvolve(&blurred, &halo, nsr).unwrap();
            let (e_blur, e_kept, e_cut) = (err(&blurred), err(&kept), err(&cut));
            // Measured: kept 0.15 / 1.4 / 7.5 / 19 grey levels from the bars
            // (blurred 32), the halo alone 62 / 33 / 45 / 58.
            assert!(
                e_kept < 0.7 * e_blur && bars(&kept) > bars(&blurred),
                "NSR {nsr}: blurred {e_blur}, restored with the unscattered part {e_kept}"
            );
            assert!(
                e_cut > e_blur,
                "NSR {nsr}: blurred {e_blur}, restored with the halo alone {e_cut}"
            );
        }
        // With the NSR of a noisy region the halo alone cuts the bars
        // (10 grey levels of 66 left).
        let cut = wiener.deconvolve(&blurred, &halo, 0.2).unwrap();
        assert!(bars(&cut) < 0.25 * bars(&blurred), "{}", bars(&cut));
        assert_eq!(
            wiener.cached_spectra(),
            2,
            "the share is part of the spectrum's key, the NSR is not"
        );
    }

    /// Square rings blurred by a Gaussian of known σ, with noise: the two-scale
    /// gradient-energy estimate recovers σ.
    #[test]
    fn edge_blur_estimate_recovers_a_known_gaussian_blur() {
        use rand::SeedableRng;
        use rand_distr::{Distribution, Normal};
        // Rings 20 px wide: beyond σ ≈ 4 neighbouring edges overlap at the
        // coarser probe scale and the estimate reads low (σ 5 → 3.7).
        for (sigma, noise) in [(1.0, 1.0), (2.5, 1.0), (4.0, 2.0)] {
            let mut sharp =
                Mat::new_rows_cols_with_default(240, 240, CV_32FC1, Scalar::all(40.0)).unwrap();
            for y in 0..240 {
                let row = sharp.at_row_mut::<f32>(y).unwrap();
                for x in 0..240i32 {
                    // Concentric square rings 20 px wide, as a marker's.
                    let d = (x - 120).abs().max((y - 120).abs());
                    if d < 110 && (d / 20) % 2 == 0 {
                        row[x as usize] = 60.0;
                    }
                }
            }
            let mut blurred = Mat::default();
            imgproc::gaussian_blur(
                &sharp,
                &mut blurred,
                Size::new(0, 0),
                sigma,
                sigma,
                BORDER_REFLECT_101,
            )
            .unwrap();
            let mut rng = rand_chacha::ChaCha8Rng::seed_from_u64(5);
            let n = Normal::new(0.0, noise).unwrap();
            for y in 0..240 {
                for v in blurred.at_row_mut::<f32>(y).unwrap() {
                    *v += n.sample(&mut rng) as f32;
                }
            }
            let est = edge_blur_sigma_px(&blurred, noise).unwrap().unwrap();
            assert!(
                (est - sigma).abs() < 0.2 * sigma + 0.3,
                "σ {sigma}: estimated {est}"
            );
        }
    }

    #[test]
    fn edge_blur_estimate_gives_up_on_pure_noise() {
        use rand::SeedableRng;
        use rand_distr::{Distribution, Normal};
        let mut img =
            Mat::new_rows_cols_with_default(128, 128, CV_32FC1, Scalar::all(100.0)).unwrap();
        let mut rng = rand_chacha::ChaCha8Rng::seed_from_u64(9);
        let n = Normal::new(0.0, 2.0).unwrap();
        for y in 0..128 {
            for v in img.at_row_mut::<f32>(y).unwrap() {
                *v += n.sample(&mut rng) as f32;
            }
        }
        assert_eq!(edge_blur_sigma_px(&img, 2.0).unwrap(), None);
    }

    #[test]
    fn deconvolution_keeps_the_mean_of_a_flat_region() {
        let flat = Mat::new_rows_cols_with_default(40, 50, CV_8UC1, Scalar::all(137.0)).unwrap();
        let out = Wiener::new()
            .deconvolve(
                &flat,
                &GgPsf {
                    p: 1.0,
                    sigma_px: 1.0,
                    direct: 0.0,
                },
                0.05,
            )
            .unwrap();
        let m = core::mean(&out, &core::no_array()).unwrap()[0];
        assert!((m - 137.0).abs() < 0.5, "{m}");
    }
}
