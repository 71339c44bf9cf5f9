//! The water's and the sensor's contributions that do not need ray casting:
//! the forward-scatter PSF (paper Eq. (14)) and its convolution, the
//! analytic veiling light and vignetting, the lamp's backscatter integral,
//! and Poisson–Gaussian sensor noise. Equations: `docs/water-model.md`.

use super::noise::{RowRng, Sensor};
use crate::water::WaterParams;
use rand::{Rng, SeedableRng};
use rand_chacha::ChaCha8Rng;

/// Γ(x) for x > 0 (Lanczos, g = 7, n = 9; relative error ~1e-15).
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
        return std::f64::consts::PI / ((std::f64::consts::PI * x).sin() * gamma(1.0 - x));
    }
    let x = x - 1.0;
    let mut a = C[0];
    let t = x + G + 0.5;
    for (i, c) in C.iter().enumerate().skip(1) {
        a += c / (x + i as f64);
    }
    (2.0 * std::f64::consts::PI).sqrt() * t.powf(x + 0.5) * (-t).exp() * a
}

/// The paper's `A(p, σ) = σ·(Γ(1/p)/Γ(3/p))^0.5` with `σ = 1/(2√p)` (Eq. (14)).
pub fn psf_a(p: f64) -> f64 {
    let sigma = 1.0 / (2.0 * p.sqrt());
    sigma * (gamma(1.0 / p) / gamma(3.0 / p)).sqrt()
}

/// A generalized-Gaussian PSF in pixels: `h(ρ) ∝ exp(−(ρ²/(A·w²))^(p/2))`,
/// i.e. Eq. (14) with its `(u, v)` measured in units of the width `w` pixels.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct Psf {
    pub p: f64,
    /// Radial scale `a = w·√A` in pixels.
    pub scale_px: f64,
}

impl Psf {
    /// The PSF for an object at range `r_m` seen by a camera of focal length `f_px`.
    pub fn for_range(water: &WaterParams, f_px: f64, r_m: f64) -> Psf {
        let width_px = f_px * water.psf_angle_rad * (water.c_per_m * r_m.max(0.0)).sqrt();
        Psf {
            p: water.psf_shape_p,
            scale_px: width_px * psf_a(water.psf_shape_p).sqrt(),
        }
    }

    /// Radius (px) beyond which the kernel is below e^-7 of its peak.
    pub fn radius_px(&self) -> f64 {
        self.scale_px * 7f64.powf(1.0 / self.p)
    }

    #[inline]
    fn value(&self, rho: f64) -> f64 {
        (-(rho / self.scale_px).powf(self.p)).exp()
    }
}

/// An axis-aligned pixel rectangle, inclusive bounds.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub struct Rect {
    pub x0: usize,
    pub y0: usize,
    pub x1: usize,
    pub y1: usize,
}

impl Rect {
    pub fn width(&self) -> usize {
        self.x1 + 1 - self.x0
    }
    pub fn height(&self) -> usize {
        self.y1 + 1 - self.y0
    }
    pub fn union(&self, o: &Rect) -> Rect {
        Rect {
            x0: self.x0.min(o.x0),
            y0: self.y0.min(o.y0),
            x1: self.x1.max(o.x1),
            y1: self.y1.max(o.y1),
        }
    }
    pub fn overlaps(&self, o: &Rect) -> bool {
        self.x0 <= o.x1 && o.x0 <= self.x1 && self.y0 <= o.y1 && o.y0 <= self.y1
    }
    /// Grown by `m` pixels, clipped to a `w`x`h` image.
    pub fn dilated(&self, m: usize, w: usize, h: usize) -> Rect {
        Rect {
            x0: self.x0.saturating_sub(m),
            y0: self.y0.saturating_sub(m),
            x1: (self.x1 + m).min(w - 1),
            y1: (self.y1 + m).min(h - 1),
        }
    }
}

/// Convolve `src` (a full `w`-wide frame, zero outside the objects) with the
/// PSF inside `rect` and add the result to `dst`. Wide kernels are applied
/// on a grid of `d`x`d` cells (box-averaged, then bilinearly upsampled), so
/// the cost stays ~`(2·8+1)²` per cell whatever the width; the PSF's mass is
/// conserved.
pub fn blur_add(
    src: &[f32],
    w: usize,
    rect: Rect,
    psf: &Psf,
    dst: &mut [f32],
    scratch: &mut Vec<f32>,
) {
    blur_add_threads(src, w, rect, psf, dst, scratch, 1);
}

/// [`blur_add`] in bands of rows over up to `threads` threads; every
/// output value is summed in the same order as on one thread, so the
/// result is the same.
pub fn blur_add_threads(
    src: &[f32],
    w: usize,
    rect: Rect,
    psf: &Psf,
    dst: &mut [f32],
    scratch: &mut Vec<f32>,
    threads: usize,
) {
    /// Grid rows per task.
    const BAND: usize = 8;
    // Also catches a NaN width.
    if psf.scale_px.is_nan() || psf.scale_px <= 0.05 {
        for y in rect.y0..=rect.y1 {
            let row = y * w;
            for x in rect.x0..=rect.x1 {
                dst[row + x] += src[row + x];
            }
        }
        return;
    }
    let radius = psf.radius_px();
    let d = ((radius / 8.0).ceil() as usize).max(1);
    let gw = rect.width().div_ceil(d);
    let gh = rect.height().div_ceil(d);
    let (kernel, kr) = cell_kernel(psf, radius, d);
    let kside = (2 * kr + 1) as usize;

    // Box-average the source into cells (each cell summed row by row).
    scratch.clear();
    scratch.resize(2 * gw * gh, 0.0);
    let (grid, out) = scratch.split_at_mut(gw * gh);
    let inv = 1.0 / (d * d) as f32;
    let tasks: Vec<_> = grid.chunks_mut(BAND * gw).enumerate().collect();
    super::par::run_tasks(tasks, threads, |(b, cells)| {
        let gy0 = b * BAND;
        for (r, cell_row) in cells.chunks_mut(gw).enumerate() {
            let y_lo = rect.y0 + (gy0 + r) * d;
            for y in y_lo..(y_lo + d).min(rect.y1 + 1) {
                for x in rect.x0..=rect.x1 {
                    cell_row[(x - rect.x0) / d] += src[y * w + x];
                }
            }
            cell_row.iter_mut().for_each(|g| *g *= inv);
        }
    });
    // Scatter each non-zero cell through the kernel (sources are sparse);
    // each band takes the sources reaching its rows, in the same order.
    let grid = &*grid;
    let tasks: Vec<_> = out.chunks_mut(BAND * gw).enumerate().collect();
    super::par::run_tasks(tasks, threads, |(b, band)| {
        let (o0, o1) = (b * BAND, b * BAND + band.len() / gw);
        let lo = o0.saturating_sub(kr as usize);
        for gy in lo..(o1 + kr as usize).min(gh) {
            for gx in 0..gw {
                let s = grid[gy * gw + gx];
                if s == 0.0 {
                    continue;
                }
                for j in -kr..=kr {
                    let oy = gy as isize + j;
                    if oy < o0 as isize || oy >= o1 as isize {
                        continue;
                    }
                    let krow =
                        &kernel[((j + kr) as usize) * kside..((j + kr) as usize + 1) * kside];
                    let orow = (oy as usize - o0) * gw;
                    for (ki, &k) in krow.iter().enumerate() {
                        let ox = gx as isize + ki as isize - kr;
                        if ox >= 0 && ox < gw as isize {
                            band[orow + ox as usize] += s * k;
                        }
                    }
                }
            }
        }
    });
    let out = &*out;
    let tasks: Vec<_> = dst
        .chunks_mut(w)
        .enumerate()
        .skip(rect.y0)
        .take(rect.height())
        .collect();
    let tasks: Vec<Vec<_>> = tasks
        .into_iter()
        .fold(Vec::new(), |mut acc: Vec<Vec<_>>, row| {
            match acc.last_mut() {
                Some(band) if band.len() < BAND * d => band.push(row),
                _ => acc.push(vec![row]),
            }
            acc
        });
    super::par::run_tasks(tasks, threads, |rows| {
        for (y, row) in rows {
            upsample_row(out, gw, gh, d, rect, y, row);
        }
    });
}

/// The PSF integrated over `d`x`d` cells (4x4 samples per cell), normalized
/// to unit sum, and its half width in cells.
fn cell_kernel(psf: &Psf, radius: f64, d: usize) -> (Vec<f32>, isize) {
    let kr = (radius / d as f64).ceil() as isize;
    let kside = (2 * kr + 1) as usize;
    let mut kernel = vec![0.0f64; kside * kside];
    let sub = 4;
    for j in -kr..=kr {
        for i in -kr..=kr {
            let mut acc = 0.0;
            for sj in 0..sub {
                for si in 0..sub {
                    let ox = (i as f64 + (si as f64 + 0.5) / sub as f64 - 0.5) * d as f64;
                    let oy = (j as f64 + (sj as f64 + 0.5) / sub as f64 - 0.5) * d as f64;
                    acc += psf.value((ox * ox + oy * oy).sqrt());
                }
            }
            kernel[((j + kr) as usize) * kside + (i + kr) as usize] = acc;
        }
    }
    let total: f64 = kernel.iter().sum();
    (kernel.iter().map(|k| (k / total) as f32).collect(), kr)
}

/// Add the cell grid `out` (`gw`x`gh` cells of `d` px over `rect`) to
/// frame row `y` (`row`): bilinearly from cell centres, or cell by cell
/// when `d` is 1.
fn upsample_row(
    out: &[f32],
    gw: usize,
    gh: usize,
    d: usize,
    rect: Rect,
    y: usize,
    row: &mut [f32],
) {
    if d == 1 {
        let cells = &out[(y - rect.y0) * gw..(y - rect.y0 + 1) * gw];
        for (o, c) in row[rect.x0..=rect.x1].iter_mut().zip(cells) {
            *o += c;
        }
        return;
    }
    let fy = ((y - rect.y0) as f32 + 0.5) / d as f32 - 0.5;
    let y0 = fy.floor().clamp(0.0, (gh - 1) as f32) as usize;
    let y1 = (y0 + 1).min(gh - 1);
    let ty = (fy - y0 as f32).clamp(0.0, 1.0);
    for x in rect.x0..=rect.x1 {
        let fx = ((x - rect.x0) as f32 + 0.5) / d as f32 - 0.5;
        let x0 = fx.floor().clamp(0.0, (gw - 1) as f32) as usize;
        let x1 = (x0 + 1).min(gw - 1);
        let tx = (fx - x0 as f32).clamp(0.0, 1.0);
        let a = out[y0 * gw + x0] * (1.0 - tx) + out[y0 * gw + x1] * tx;
        let b = out[y1 * gw + x0] * (1.0 - tx) + out[y1 * gw + x1] * tx;
        row[x] += a * (1.0 - ty) + b * ty;
    }
}

/// `G(r) = ∫_{z0}^{r} e^(−2cz)/z² dz`, the lamp's backscatter along a ray
/// ending at range `r` (lamp at the camera, z0 its stand-off), tabulated.
#[derive(Debug, Clone)]
pub struct LampIntegral {
    /// Samples of G at log-spaced ranges from z0 to 100 m, normalized by G(∞).
    table: Vec<f64>,
    log_r0: f64,
    step: f64,
    /// G(∞).
    pub total: f64,
}

/// Stand-off between the lamp and the first lit water (m).
pub const LAMP_Z0_M: f64 = 0.1;

impl LampIntegral {
    pub fn new(c_per_m: f64) -> LampIntegral {
        let n = 256;
        let (r0, r1) = (LAMP_Z0_M, 100.0f64);
        let log_r0 = r0.ln();
        let step = (r1.ln() - log_r0) / (n - 1) as f64;
        let mut table = vec![0.0; n];
        let f = |z: f64| (-2.0 * c_per_m * z).exp() / (z * z);
        for i in 1..n {
            // Simpson on each log interval (z = e^s, dz = z ds).
            let (sa, sb) = (log_r0 + (i - 1) as f64 * step, log_r0 + i as f64 * step);
            let g = |s: f64| {
                let z = s.exp();
                f(z) * z
            };
            let sm = 0.5 * (sa + sb);
            table[i] = table[i - 1] + (sb - sa) / 6.0 * (g(sa) + 4.0 * g(sm) + g(sb));
        }
        // Tail beyond 100 m: ≤ e^(−200c)/100, negligible but added for c = 0.
        let total = table[n - 1] + if c_per_m == 0.0 { 1.0 / r1 } else { 0.0 };
        let table = table.iter().map(|g| g / total).collect();
        LampIntegral {
            table,
            log_r0,
            step,
            total,
        }
    }

    /// G(r)/G(∞).
    pub fn fraction(&self, r: f64) -> f64 {
        if r <= LAMP_Z0_M {
            return 0.0;
        }
        let s = (r.ln() - self.log_r0) / self.step;
        let i = s.floor() as usize;
        if i + 1 >= self.table.len() {
            return 1.0;
        }
        let t = s - i as f64;
        self.table[i] * (1.0 - t) + self.table[i + 1] * t
    }
}

/// The slow ambient light: a temporal factor on all natural light and a
/// smooth spatial pattern on the veil, fixed by the water's `ambient_seed`.
#[derive(Debug, Clone)]
pub struct Ambient {
    pub temporal: f64,
    waves: [(f64, f64, f64, f64); 3],
    amplitude: f64,
}

impl Ambient {
    pub fn new(water: &WaterParams, time_s: f64) -> Ambient {
        let mut rng = ChaCha8Rng::seed_from_u64(water.ambient_seed);
        let phase0: f64 = rng.gen_range(0.0..std::f64::consts::TAU);
        let period = water.ambient_period_s.max(1e-3);
        let temporal =
            1.0 + water.ambient_temporal * (std::f64::consts::TAU * time_s / period + phase0).sin();
        let mut waves = [(0.0, 0.0, 0.0, 0.0); 3];
        for w in waves.iter_mut() {
            let fx: f64 = rng.gen_range(0.3..1.2) * if rng.gen_bool(0.5) { 1.0 } else { -1.0 };
            let fy: f64 = rng.gen_range(0.3..1.2) * if rng.gen_bool(0.5) { 1.0 } else { -1.0 };
            let speed: f64 = rng.gen_range(0.5..1.5);
            let ph: f64 = rng.gen_range(0.0..std::f64::consts::TAU);
            *w = (
                fx,
                fy,
                ph + std::f64::consts::TAU * speed * time_s / period,
                0.0,
            );
        }
        Ambient {
            temporal,
            waves,
            amplitude: water.ambient_spatial,
        }
    }

    /// Spatial factor at normalized image position (0..1, 0..1).
    pub fn spatial(&self, un: f64, vn: f64) -> f64 {
        let m: f64 = self
            .waves
            .iter()
            .map(|(fx, fy, ph, _)| (std::f64::consts::TAU * (fx * un + fy * vn) + ph).sin())
            .sum::<f64>()
            / 3.0;
        1.0 + self.amplitude * m
    }
}

/// Add Poisson–Gaussian noise to a frame in DN (floats) and quantize to 8 bits.
/// Row `y` draws from its own stream of `seed` ([`RowRng`]), so output is
/// identical for a seed whatever the evaluation order.
pub fn quantize_with_noise(dn: &[f32], w: usize, water: &WaterParams, seed: u64, out: &mut [u8]) {
    for (y, (row_in, row_out)) in dn.chunks(w).zip(out.chunks_mut(w)).enumerate() {
        quantize_row(row_in, y, water, seed, row_out);
    }
}

/// Row `y` of [`quantize_with_noise`].
pub fn quantize_row(row_in: &[f32], y: usize, water: &WaterParams, seed: u64, row_out: &mut [u8]) {
    if water.is_noiseless() {
        for (o, &v) in row_out.iter_mut().zip(row_in) {
            *o = super::noise::quantize_f32(v);
        }
        return;
    }
    let sensor = Sensor::new(water.gain_e_per_dn, water.read_noise_dn);
    let mut rng = RowRng::new(seed, y as u64);
    sensor.quantize(row_in, &mut rng, row_out);
}

/// `v.round().clamp(0.0, 255.0) as u8` of an `f32` (NaN gives 0), without
/// the libm call `round` compiles to on baseline x86-64.
#[inline]
pub fn round_to_u8_f32(v: f32) -> u8 {
    if v.is_nan() || v < 0.0 {
        return 0;
    }
    if v >= 254.5 {
        return 255;
    }
    let t = v as u32;
    (t + u32::from(v - t as f32 >= 0.5)) as u8
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn gamma_matches_known_values() {
        assert!((gamma(1.0) - 1.0).abs() < 1e-12);
        assert!((gamma(0.5) - std::f64::consts::PI.sqrt()).abs() < 1e-12);
        assert!((gamma(5.0) - 24.0).abs() < 1e-10);
        // Eq. (14) at p = 2: σ = 1/(2√2), Γ(1/2)/Γ(3/2) = 2, so A = 1/2.
        assert!((psf_a(2.0) - 0.5).abs() < 1e-12);
    }

    #[test]
    fn blur_conserves_mass_at_every_width() {
        let (w, h) = (200, 160);
        let mut src = vec![0.0f32; w * h];
        for y in 70..90 {
            for x in 90..110 {
                src[y * w + x] = 1.0;
            }
        }
        let total: f32 = src.iter().sum();
        for scale in [0.3, 2.0, 9.0] {
            for p in [1.0, 2.0] {
                let psf = Psf { p, scale_px: scale };
                let r = psf.radius_px().ceil() as usize;
                let rect = Rect {
                    x0: 90,
                    y0: 70,
                    x1: 109,
                    y1: 89,
                }
                .dilated(r, w, h);
                let mut dst = vec![0.0f32; w * h];
                blur_add(&src, w, rect, &psf, &mut dst, &mut Vec::new());
                let got: f32 = dst.iter().sum();
                assert!(
                    (got - total).abs() < 1e-3 * total,
                    "scale {scale} p {p}: {got} vs {total}"
                );
                // Wider PSFs spread further.
                if scale > 1.0 {
                    assert!(dst[80 * w + 90 - 2] > 0.0);
                }
            }
        }
    }

    #[test]
    fn fast_rounding_is_round_then_clamp() {
        let mut values = vec![
            f64::NAN,
            f64::INFINITY,
            f64::NEG_INFINITY,
            -0.0,
            0.0,
            -0.5,
            -0.49999999999999994,
            0.49999999999999994,
            0.5,
            1.5,
            2.5,
            254.49999999999997,
            254.5,
            255.0,
            255.5,
            1e300,
        ];
        let mut state = 0x2545_f491_4f6c_dd1du64;
        for i in 0..200_000 {
            state ^= state << 13;
            state ^= state >> 7;
            state ^= state << 17;
            let v = (state >> 11) as f64 / (1u64 << 53) as f64 * 270.0 - 7.0;
            values.push(v);
            // Exact halves and their neighbours.
            let half = (i % 520) as f64 * 0.5 - 2.0;
            values.extend([half, half.next_up(), half.next_down()]);
        }
        for v in values {
            let f = v as f32;
            assert_eq!(
                round_to_u8_f32(f),
                f.round().clamp(0.0, 255.0) as u8,
                "{f:e}"
            );
            for g in [f.next_up(), f.next_down()] {
                assert_eq!(
                    round_to_u8_f32(g),
                    g.round().clamp(0.0, 255.0) as u8,
                    "{g:e}"
                );
            }
        }
    }

    #[test]
    fn blur_on_threads_is_the_blur_on_one() {
        let (w, h) = (300, 200);
        let mut src = vec![0.0f32; w * h];
        let mut state = 12345u32;
        for y in 40..150 {
            for x in 60..250 {
                state = state.wrapping_mul(1_664_525).wrapping_add(1_013_904_223);
                src[y * w + x] = (state >> 8) as f32 / (1u32 << 24) as f32;
            }
        }
        for (scale, p) in [(0.5, 1.5), (3.0, 2.0), (12.0, 1.0), (30.0, 1.5)] {
            let psf = Psf { p, scale_px: scale };
            let rect = Rect {
                x0: 60,
                y0: 40,
                x1: 249,
                y1: 149,
            }
            .dilated(psf.radius_px().ceil() as usize + 1, w, h);
            let mut one = vec![0.25f32; w * h];
            blur_add(&src, w, rect, &psf, &mut one, &mut Vec::new());
            for threads in [2, 3, 7] {
                let mut many = vec![0.25f32; w * h];
                blur_add_threads(&src, w, rect, &psf, &mut many, &mut Vec::new(), threads);
                assert!(
                    one.iter()
                        .zip(&many)
                        .all(|(a, b)| a.to_bits() == b.to_bits()),
                    "scale {scale}, {threads} threads"
                );
            }
        }
    }

    #[test]
    fn lamp_integral_rises_to_one() {
        let g = LampIntegral::new(2.0);
        assert_eq!(g.fraction(0.05), 0.0);
        assert!(g.fraction(0.5) > g.fraction(0.2));
        assert!((g.fraction(1e6) - 1.0).abs() < 1e-12);
    }
}
