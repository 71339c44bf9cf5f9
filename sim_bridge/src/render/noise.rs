//! The sensor's Poisson–Gaussian noise (`docs/water-model.md`, "Sensor"):
//! a pixel of mean `m` DN with `g` electrons per DN and read noise `σ_r` DN
//! reads `Poisson(m·g)/g + σ_r·z`, the Poisson drawn exactly below 30
//! electrons and as a Gaussian of the same variance, `m + z·√(m/g + σ_r²)`,
//! above (z standard normal).
//!
//! Random numbers: row `y` of a frame with seed `s` draws from its own
//! counter-based stream, SplitMix64 [Steele, Lea & Flood, OOPSLA 2014] started at a hash
//! of `(s, y)`. Each row's draws depend on nothing else, so rows can be
//! noised in any order on any number of threads and the frame is the same;
//! the generator costs a few arithmetic operations per draw. The normal
//! draws are an exact ziggurat, two per 64-bit output ([`fill_standard_normal`]),
//! the small Poisson counts an exact inversion of the distribution function.

use rand::RngCore;

/// Below this many photo-electrons the shot noise is drawn as an exact
/// Poisson count; above, as a Gaussian of the same variance.
pub const EXACT_POISSON_BELOW: f64 = 30.0;

/// SplitMix64's finalizer: a bijection of `u64` with good avalanche.
#[inline]
fn mix64(mut z: u64) -> u64 {
    z = (z ^ (z >> 30)).wrapping_mul(0xBF58_476D_1CE4_E5B9);
    z = (z ^ (z >> 27)).wrapping_mul(0x94D0_49BB_1331_11EB);
    z ^ (z >> 31)
}

/// The random stream of one image row: SplitMix64 (output `n` is
/// `mix64(start + n·γ)`), its start a hash of the frame seed and the row.
#[derive(Debug, Clone)]
pub struct RowRng {
    state: u64,
}

impl RowRng {
    const GAMMA: u64 = 0x9E37_79B9_7F4A_7C15;

    /// The stream of row `row` of the frame seeded `seed`. Distinct rows of
    /// one seed start at distinct, scattered points of the 2⁶⁴-long sequence.
    pub fn new(seed: u64, row: u64) -> RowRng {
        RowRng {
            state: mix64(
                mix64(seed ^ 0x5348_4F41_4C5F_4E53) ^ row.wrapping_mul(0xD1B5_4A32_D192_ED03),
            ),
        }
    }

    /// A uniform draw in `[0, 1)` (53 random bits).
    #[inline]
    pub fn uniform(&mut self) -> f64 {
        (self.next_u64() >> 11) as f64 * (1.0 / (1u64 << 53) as f64)
    }
}

impl RngCore for RowRng {
    #[inline]
    fn next_u32(&mut self) -> u32 {
        (self.next_u64() >> 32) as u32
    }

    #[inline]
    fn next_u64(&mut self) -> u64 {
        self.state = self.state.wrapping_add(Self::GAMMA);
        mix64(self.state)
    }

    fn fill_bytes(&mut self, dest: &mut [u8]) {
        for chunk in dest.chunks_mut(8) {
            let b = self.next_u64().to_le_bytes();
            chunk.copy_from_slice(&b[..chunk.len()]);
        }
    }

    fn try_fill_bytes(&mut self, dest: &mut [u8]) -> Result<(), rand::Error> {
        self.fill_bytes(dest);
        Ok(())
    }
}

/// Marsaglia and Tsang's ziggurat for the standard normal [J. Stat. Softw.
/// 5(8), 2000], 128 layers, in `f32`, two draws from each 64-bit output:
/// each half gives a signed 24-bit value and, from other bits, the layer (the
/// original's shared bits between value and layer are a known flaw [Leong
/// et al., J. Stat. Softw. 12(7), 2005]). About 99 % of draws are one integer
/// comparison and one product; the wedges and the tail (|z| > 3.44) are
/// sampled exactly, in `f64`.
struct Ziggurat {
    /// Per layer: the largest |value| accepted at once, the value's scale,
    /// and the density at the layer's lower edge.
    k: [u32; 128],
    w: [f32; 128],
    f: [f64; 128],
}

/// The ziggurat's rightmost layer edge and its layers' common area.
const ZIG_R: f64 = 3.442_619_855_899;
const ZIG_V: f64 = 9.912_563_035_262_17e-3;
/// 2²³: the scale of a signed 24-bit value.
const ZIG_M: f64 = 8_388_608.0;

impl Ziggurat {
    fn new() -> Ziggurat {
        let mut z = Ziggurat {
            k: [0; 128],
            w: [0.0; 128],
            f: [0.0; 128],
        };
        let (mut dn, mut tn) = (ZIG_R, ZIG_R);
        let q = ZIG_V / (-0.5 * dn * dn).exp();
        z.k[0] = (dn / q * ZIG_M) as u32;
        z.k[1] = 0;
        z.w[0] = (q / ZIG_M) as f32;
        z.w[127] = (dn / ZIG_M) as f32;
        z.f[0] = 1.0;
        z.f[127] = (-0.5 * dn * dn).exp();
        for i in (1..=126).rev() {
            dn = (-2.0 * (ZIG_V / dn + (-0.5 * dn * dn).exp()).ln()).sqrt();
            z.k[i + 1] = (dn / tn * ZIG_M) as u32;
            tn = dn;
            z.f[i] = (-0.5 * dn * dn).exp();
            z.w[i] = (dn / ZIG_M) as f32;
        }
        z
    }

    fn get() -> &'static Ziggurat {
        static TABLES: std::sync::OnceLock<Ziggurat> = std::sync::OnceLock::new();
        TABLES.get_or_init(Ziggurat::new)
    }

    /// One draw from 32 random bits: value (signed, bits 0–23) and layer
    /// (bits 24–30); a rejection draws further from `rng`.
    #[inline]
    fn draw(&self, bits: u32, rng: &mut RowRng) -> f32 {
        let hz = ((bits << 8) as i32) >> 8;
        let iz = ((bits >> 24) & 127) as usize;
        if hz.unsigned_abs() < self.k[iz] {
            return hz as f32 * self.w[iz];
        }
        self.slow(hz, iz, rng)
    }

    #[cold]
    fn slow(&self, mut hz: i32, mut iz: usize, rng: &mut RowRng) -> f32 {
        loop {
            let x = f64::from(hz) * f64::from(self.w[iz]);
            if iz == 0 {
                // The tail beyond R (Marsaglia 1964).
                let (mut t, mut y);
                loop {
                    t = -(1.0 - rng.uniform()).ln() / ZIG_R;
                    y = -(1.0 - rng.uniform()).ln();
                    if y + y >= t * t {
                        break;
                    }
                }
                return (if hz > 0 { ZIG_R + t } else { -(ZIG_R + t) }) as f32;
            }
            // The wedge between this layer's rectangle and the curve.
            if self.f[iz] + rng.uniform() * (self.f[iz - 1] - self.f[iz]) < (-0.5 * x * x).exp() {
                return x as f32;
            }
            let bits = (rng.next_u64() >> 32) as u32;
            hz = ((bits << 8) as i32) >> 8;
            iz = ((bits >> 24) & 127) as usize;
            if hz.unsigned_abs() < self.k[iz] {
                return hz as f32 * self.w[iz];
            }
        }
    }
}

/// Standard normal draws into `z`, two from each of `rng`'s outputs ([`Ziggurat`]).
pub fn fill_standard_normal(rng: &mut RowRng, z: &mut [f32]) {
    let zig = Ziggurat::get();
    let mut pairs = z.chunks_exact_mut(2);
    for pair in &mut pairs {
        let bits = rng.next_u64();
        pair[0] = zig.draw(bits as u32, rng);
        pair[1] = zig.draw((bits >> 32) as u32, rng);
    }
    if let [last] = pairs.into_remainder() {
        let bits = rng.next_u64();
        *last = zig.draw(bits as u32, rng);
    }
}

/// `1/k` for `k = 1 …`, so the inversion's recurrence needs no division.
const INV: [f64; 128] = {
    let mut t = [0.0; 128];
    let mut k = 1;
    while k < 128 {
        t[k] = 1.0 / k as f64;
        k += 1;
    }
    t
};

/// An exact Poisson count of mean `lambda` (`0 < lambda <`
/// [`EXACT_POISSON_BELOW`]) by inversion: the smallest `k` with
/// `u < F(k)`, `F` summed from `p(0) = e^(−λ)` by `p(k) = p(k−1)·λ/k`.
/// (Beyond `k = 127`, ≥ 97 above a mean under 30, `F` differs from 1 by
/// less than 1e-40: the search stops there.)
#[inline]
pub fn poisson_small(lambda: f64, rng: &mut RowRng) -> u32 {
    let u = rng.uniform();
    let mut p = (-lambda).exp();
    let mut f = p;
    let mut k = 0usize;
    while u >= f && k < INV.len() - 1 {
        k += 1;
        p *= lambda * INV[k];
        f += p;
    }
    k as u32
}

/// A sensor's noise parameters, with what every pixel's draw needs precomputed.
#[derive(Debug, Clone, Copy)]
pub struct Sensor {
    gain: f64,
    inv_gain: f64,
    read: f64,
    read_var: f64,
}

/// Pixels per run of [`Sensor::noisy`]: the draws of a row go run by run.
const RUN: usize = 256;

impl Sensor {
    /// `gain` electrons per DN (∞: no shot noise), `read` DN of read noise.
    pub fn new(gain: f64, read: f64) -> Sensor {
        Sensor {
            gain,
            inv_gain: if gain.is_finite() { 1.0 / gain } else { 0.0 },
            read,
            read_var: read * read,
        }
    }

    /// Noisy linear DN (not clipped) of the means `mean · pre` (one row, or
    /// its first pixels; a negative mean is 0), drawing from `rng`: run by
    /// run of [`RUN`] pixels, first one standard normal `z` per pixel, then
    /// `m + z·√(m/g + σ_r²)` for every pixel in `f32` (a loop the compiler
    /// vectorizes), then, for the pixels under [`EXACT_POISSON_BELOW`]
    /// electrons, `Poisson(m·g)/g + σ_r·z`, the count exact from a further
    /// uniform. Several times faster than drawing one pixel at a time, whose
    /// dependent steps (draw, square root, rounding) left the processor
    /// waiting. [`Self::quantize`] draws the same.
    pub fn noisy(&self, mean: &[f32], pre: f32, rng: &mut RowRng, out: &mut [f32]) {
        let mut z = [0f32; RUN];
        for (m_run, o_run) in mean.chunks(RUN).zip(out.chunks_mut(RUN)) {
            self.noisy_run(m_run, pre, rng, &mut z[..m_run.len()], o_run);
        }
    }

    /// [`Self::noisy`] of `mean` (`pre` = 1) rounded to 8 bits as the
    /// renderer's frames are ([`quantize_f32`]).
    pub fn quantize(&self, mean: &[f32], rng: &mut RowRng, out: &mut [u8]) {
        let (mut z, mut v) = ([0f32; RUN], [0f32; RUN]);
        for (m_run, o_run) in mean.chunks(RUN).zip(out.chunks_mut(RUN)) {
            let n = m_run.len();
            self.noisy_run(m_run, 1.0, rng, &mut z[..n], &mut v[..n]);
            for (o, &x) in o_run.iter_mut().zip(&v[..n]) {
                *o = quantize_f32(x);
            }
        }
    }

    /// One run of [`Self::noisy`] (`z`: scratch for its normals).
    fn noisy_run(&self, mean: &[f32], pre: f32, rng: &mut RowRng, z: &mut [f32], out: &mut [f32]) {
        let (inv_gain, read, read_var) =
            (self.inv_gain as f32, self.read as f32, self.read_var as f32);
        fill_standard_normal(rng, z);
        for ((o, &m), &zi) in out.iter_mut().zip(mean).zip(z.iter()) {
            let m = (m * pre).max(0.0);
            *o = m + zi * (m * inv_gain + read_var).sqrt();
        }
        if !self.gain.is_finite() {
            return;
        }
        // A little above the limit in DN, so that rounding to f32 loses no pixel.
        let poisson_below_dn = (EXACT_POISSON_BELOW * self.inv_gain * 1.001) as f32;
        for ((o, &m), &zi) in out.iter_mut().zip(mean).zip(z.iter()) {
            // Most pixels are far above the limit: one f32 comparison each.
            let m = m * pre;
            if !(m > 0.0 && m < poisson_below_dn) {
                continue;
            }
            let lambda = f64::from(m) * self.gain;
            if lambda < EXACT_POISSON_BELOW {
                let shot = poisson_small(lambda, rng) as f32 * inv_gain;
                *o = shot + read * zi;
            }
        }
    }
}

/// `v` clipped to 0–255 and rounded to the nearest integer, halves up
/// (`v + 0.5` floored; within one `f32` step below a half, as that sum
/// rounds); NaN gives 0. Branch-free and without a float-to-integer
/// conversion (which does not vectorize on baseline x86-64 when it must
/// saturate), so that a loop of it vectorizes: adding 1.5·2²³ leaves the
/// nearest integer in the low mantissa bits, and one step back where it
/// rounded up makes it the floor.
#[inline]
pub fn quantize_f32(v: f32) -> u8 {
    const SHIFT: f32 = 12_582_912.0;
    let x = v.clamp(0.0, 255.0) + 0.5;
    let nearest = (x + SHIFT) - SHIFT;
    let floor = if nearest > x { nearest - 1.0 } else { nearest };
    ((floor + SHIFT).to_bits() & 0xFF) as u8
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::render::optics::quantize_row;
    use crate::water::WaterParams;
    use rand_distr::{Distribution, StandardNormal};

    /// Pearson's χ² of `counts` against probabilities `p` (bins with an
    /// expected count under 5 pooled into their neighbour), and its degrees
    /// of freedom.
    fn chi_square(counts: &[u64], p: &[f64]) -> (f64, usize) {
        let n: u64 = counts.iter().sum();
        let (mut chi, mut dof) = (0.0, 0usize);
        let (mut o, mut e) = (0.0, 0.0);
        for (&c, &pk) in counts.iter().zip(p) {
            o += c as f64;
            e += pk * n as f64;
            if e >= 5.0 {
                chi += (o - e) * (o - e) / e;
                dof += 1;
                (o, e) = (0.0, 0.0);
            }
        }
        if e > 0.0 {
            chi += (o - e) * (o - e) / e.max(1e-300);
            dof += 1;
        }
        (chi, dof.saturating_sub(1))
    }

    /// The 99.99 % point of χ² with `k` degrees of freedom (Wilson–Hilferty).
    fn chi_square_limit(k: usize) -> f64 {
        let k = k as f64;
        let z = 3.719; // one-sided 1e-4
        let a = 2.0 / (9.0 * k);
        k * (1.0 - a + z * a.sqrt()).powi(3)
    }

    #[test]
    fn small_poisson_counts_follow_the_exact_distribution() {
        let mut rng = RowRng::new(7, 0);
        for lambda in [0.05, 0.9, 3.0, 11.9, 12.1, 21.0, 29.99] {
            let n = 200_000;
            let mut counts = vec![0u64; 128];
            for _ in 0..n {
                counts[poisson_small(lambda, &mut rng) as usize] += 1;
            }
            let mut p = vec![0.0; 128];
            p[0] = f64::exp(-lambda);
            for k in 1..128 {
                p[k] = p[k - 1] * lambda / k as f64;
            }
            let (chi, dof) = chi_square(&counts, &p);
            assert!(
                chi < chi_square_limit(dof),
                "λ {lambda}: χ² {chi:.1} on {dof}"
            );
            let mean = counts
                .iter()
                .enumerate()
                .map(|(k, &c)| k as f64 * c as f64)
                .sum::<f64>()
                / n as f64;
            // Within 5 standard errors of λ.
            assert!(
                (mean - lambda).abs() < 5.0 * (lambda / n as f64).sqrt(),
                "λ {lambda}: {mean}"
            );
        }
    }

    #[test]
    fn a_wrong_distribution_fails_the_chi_square() {
        // The test above has the power to see a 2 % error in the mean.
        let mut rng = RowRng::new(8, 0);
        let lambda = 12.0;
        let mut counts = vec![0u64; 128];
        for _ in 0..200_000 {
            counts[poisson_small(lambda * 1.02, &mut rng) as usize] += 1;
        }
        let mut p = vec![0.0; 128];
        p[0] = f64::exp(-lambda);
        for k in 1..128 {
            p[k] = p[k - 1] * lambda / k as f64;
        }
        let (chi, dof) = chi_square(&counts, &p);
        assert!(chi > chi_square_limit(dof), "χ² {chi:.1} on {dof}");
    }

    #[test]
    fn rows_are_distinct_streams_and_repeatable() {
        let a: Vec<u64> = (0..4).map(|_| RowRng::new(1, 5).next_u64()).collect();
        assert!(a.windows(2).all(|p| p[0] == p[1]));
        let first = |seed, row| RowRng::new(seed, row).next_u64();
        let mut seen = std::collections::BTreeSet::new();
        for seed in 0..20 {
            for row in 0..2000 {
                assert!(seen.insert(first(seed, row)), "seed {seed} row {row}");
            }
        }
    }

    #[test]
    fn uniform_draws_fill_the_unit_interval_evenly() {
        let mut rng = RowRng::new(3, 9);
        let n = 1_000_000;
        let mut bins = [0u64; 100];
        for _ in 0..n {
            let u = rng.uniform();
            assert!((0.0..1.0).contains(&u));
            bins[(u * 100.0) as usize] += 1;
        }
        let (chi, dof) = chi_square(&bins, &[0.01; 100]);
        assert!(chi < chi_square_limit(dof), "χ² {chi:.1} on {dof}");
    }

    /// Φ(x) from erfc (Press et al.'s Chebyshev fit, relative error < 1.2e-7).
    fn phi(x: f64) -> f64 {
        let z = (x / std::f64::consts::SQRT_2).abs();
        let t = 1.0 / (1.0 + 0.5 * z);
        let poly = -z * z - 1.265_512_23
            + t * (1.000_023_68
                + t * (0.374_091_96
                    + t * (0.096_784_18
                        + t * (-0.186_288_06
                            + t * (0.278_868_07
                                + t * (-1.135_203_98
                                    + t * (1.488_515_87
                                        + t * (-0.822_152_23 + t * 0.170_872_77))))))));
        let erfc = t * poly.exp();
        if x >= 0.0 {
            1.0 - 0.5 * erfc
        } else {
            0.5 * erfc
        }
    }

    /// The exact distribution of a pixel's 8-bit value under the model
    /// (`docs/water-model.md`): the reading `v` rounds to `k` when
    /// `k − ½ ≤ v < k + ½`, clipped to 0 and 255. The Gaussian's σ is
    /// `sigma_scale` times the model's (1 for the model itself).
    fn quantized_pmf(mean: f64, gain: f64, read: f64, sigma_scale: f64) -> Vec<f64> {
        let read = read * sigma_scale;
        // (probability, centre, σ) of the Gaussian components.
        let parts: Vec<(f64, f64, f64)> = if mean * gain < EXACT_POISSON_BELOW {
            let lambda = mean * gain;
            let mut p = (-lambda).exp();
            (0..128)
                .map(|n| {
                    if n > 0 {
                        p *= lambda / f64::from(n);
                    }
                    (p, f64::from(n) / gain, read)
                })
                .collect()
        } else {
            vec![(
                1.0,
                mean,
                sigma_scale * (mean / gain + read * read / (sigma_scale * sigma_scale)).sqrt(),
            )]
        };
        let cdf = |x: f64| {
            parts
                .iter()
                .map(|&(p, c, s)| p * phi((x - c) / s))
                .sum::<f64>()
        };
        (0..256)
            .map(|k| {
                let lo = if k == 0 { 0.0 } else { cdf(f64::from(k) - 0.5) };
                let hi = if k == 255 {
                    1.0
                } else {
                    cdf(f64::from(k) + 0.5)
                };
                hi - lo
            })
            .collect()
    }

    /// Histogram of 8-bit values of `rows` noised rows of a flat `mean` DN.
    fn flat_histogram(mean: f32, water: &WaterParams, rows: usize) -> Vec<u64> {
        let w = 1440;
        let row = vec![mean; w];
        let mut out = vec![0u8; w];
        let mut hist = vec![0u64; 256];
        for y in 0..rows {
            quantize_row(&row, y, water, 11, &mut out);
            for &v in &out {
                hist[v as usize] += 1;
            }
        }
        hist
    }

    #[test]
    fn rendered_pixels_have_the_model_distribution() {
        let water = WaterParams::preset(0.5);
        let (g, r) = (water.gain_e_per_dn, water.read_noise_dn);
        // Exact Poisson (0.4, 12, 28 electrons) and Gaussian (32 electrons, 40 and 200 DN).
        for mean in [0.02, 0.6, 1.4, 1.6, 40.0, 200.0] {
            let hist = flat_histogram(mean as f32, &water, 300);
            let n = hist.iter().sum::<u64>() as f64;
            let pmf = quantized_pmf(mean, g, r, 1.0);
            let (chi, dof) = chi_square(&hist, &pmf);
            assert!(
                chi < chi_square_limit(dof),
                "{mean} DN: χ² {chi:.1} on {dof}"
            );
            // The variance within 5 standard errors of the model's.
            let mu: f64 = pmf.iter().enumerate().map(|(k, p)| k as f64 * p).sum();
            let var: f64 = pmf
                .iter()
                .enumerate()
                .map(|(k, p)| (k as f64 - mu).powi(2) * p)
                .sum();
            let m4: f64 = pmf
                .iter()
                .enumerate()
                .map(|(k, p)| (k as f64 - mu).powi(4) * p)
                .sum();
            let got_mu = hist
                .iter()
                .enumerate()
                .map(|(k, &c)| k as f64 * c as f64)
                .sum::<f64>()
                / n;
            let got_var = hist
                .iter()
                .enumerate()
                .map(|(k, &c)| (k as f64 - got_mu).powi(2) * c as f64)
                .sum::<f64>()
                / (n - 1.0);
            let se = ((m4 - var * var) / n).sqrt();
            assert!(
                (got_var - var).abs() < 5.0 * se,
                "{mean} DN: variance {got_var:.4} vs {var:.4} ± {se:.4}"
            );
            assert!(
                (got_mu - mu).abs() < 5.0 * (var / n).sqrt(),
                "{mean} DN: mean {got_mu:.4} vs {mu:.4}"
            );
            // A model whose σ is 3 % off (15 % where the clipping at 0 hides most of it) is told apart.
            let off = quantized_pmf(mean, g, r, if mean < 1.0 { 1.15 } else { 1.03 });
            let (chi, dof) = chi_square(&hist, &off);
            assert!(
                chi > chi_square_limit(dof),
                "{mean} DN vs a wrong σ: χ² {chi:.1} on {dof}"
            );
        }
    }

    /// Kolmogorov–Smirnov's D of the sorted sample `sorted` against `cdf`.
    fn ks_distance(sorted: &[f64], cdf: impl Fn(f64) -> f64) -> f64 {
        let n = sorted.len() as f64;
        sorted
            .iter()
            .enumerate()
            .map(|(i, &x)| {
                let f = cdf(x);
                (f - i as f64 / n).abs().max(((i + 1) as f64 / n - f).abs())
            })
            .fold(0.0, f64::max)
    }

    /// D's 99.99 % critical value for `n` draws: √(ln(2/α)/2)/√n.
    fn ks_critical(n: usize) -> f64 {
        ((2.0f64 / 1e-4).ln() / 2.0).sqrt() / (n as f64).sqrt()
    }

    #[test]
    fn standard_normal_draws_pass_kolmogorov_smirnov() {
        let mut rng = RowRng::new(21, 4);
        let n = 200_000;
        let mut z: Vec<f64> = (0..n).map(|_| StandardNormal.sample(&mut rng)).collect();
        z.sort_by(f64::total_cmp);
        let (d, crit) = (ks_distance(&z, phi), ks_critical(n));
        assert!(d < crit, "KS D {d:.5} vs {crit:.5}");
        // And a 5 % wider normal fails it.
        let d_wide = z
            .iter()
            .enumerate()
            .map(|(i, &x)| (phi(x / 1.05) - (i as f64 + 0.5) / n as f64).abs())
            .fold(0.0, f64::max);
        assert!(d_wide > crit, "KS of a wider normal {d_wide:.5}");
    }

    #[test]
    fn quantize_f32_rounds_halves_up_and_clips() {
        let cases = [
            (f32::NAN, 0),
            (f32::INFINITY, 255),
            (f32::NEG_INFINITY, 0),
            (-0.3, 0),
            (0.49, 0),
            (0.5, 1),
            (1.5, 2),
            (2.5, 3),
            (127.5, 128),
            (254.49, 254),
            (254.5, 255),
            (255.0, 255),
            (1e9, 255),
        ];
        for (v, want) in cases {
            assert_eq!(quantize_f32(v), want, "{v}");
        }
        let mut rng = RowRng::new(5, 5);
        for _ in 0..200_000 {
            let v = (rng.uniform() * 270.0 - 7.0) as f32;
            let want = (f64::from(v) + 0.5).floor().clamp(0.0, 255.0) as u8;
            assert_eq!(quantize_f32(v), want, "{v}");
        }
    }

    #[test]
    fn ziggurat_draws_pass_kolmogorov_smirnov_and_fill_the_tails() {
        let mut rng = RowRng::new(33, 2);
        let n = 400_000;
        let mut z = vec![0f32; n];
        fill_standard_normal(&mut rng, &mut z[..n - 1]);
        fill_standard_normal(&mut rng, &mut z[n - 1..]);
        let mut z: Vec<f64> = z.iter().map(|&v| f64::from(v)).collect();
        z.sort_by(f64::total_cmp);
        let (d, crit) = (ks_distance(&z, phi), ks_critical(n));
        assert!(d < crit, "KS D {d:.5} vs {crit:.5}");
        // The tails, which KS hardly sees: counts beyond 2.5, 3.0, 3.44 (the
        // ziggurat's own tail), 4.0 on both sides against their expectation.
        let edges = [
            -4.0,
            -3.442_619_855_899,
            -3.0,
            -2.5,
            2.5,
            3.0,
            3.442_619_855_899,
            4.0,
        ];
        let mut p = Vec::new();
        let mut counts = Vec::new();
        let mut lo = f64::NEG_INFINITY;
        for &hi in edges.iter().chain([f64::INFINITY].iter()) {
            p.push(phi(hi) - phi(lo));
            counts.push(z.iter().filter(|&&x| x >= lo && x < hi).count() as u64);
            lo = hi;
        }
        let (chi, dof) = chi_square(&counts, &p);
        assert!(
            chi < chi_square_limit(dof),
            "tails: χ² {chi:.1} on {dof}: {counts:?}"
        );
        assert!(
            counts[0] > 0 && counts[8] > 0,
            "draws beyond ±4: {counts:?}"
        );
        // Beyond R the draws come from the tail sampler alone: their
        // distribution given |z| > R is Q(x)/Q(R), tested on its own.
        let mut tail_rng = RowRng::new(34, 0);
        let mut many = vec![0f32; 3_000_000];
        fill_standard_normal(&mut tail_rng, &mut many);
        let r = 3.442_619_855_899;
        let mut tail: Vec<f64> = many
            .iter()
            .map(|&v| f64::from(v).abs())
            .filter(|&v| v > r)
            .collect();
        tail.sort_by(f64::total_cmp);
        let q = |x: f64| 1.0 - phi(x);
        let nt = tail.len();
        let d_tail = ks_distance(&tail, |x| 1.0 - q(x) / q(r));
        let crit_tail = ks_critical(nt);
        assert!(
            nt > 1200 && d_tail < crit_tail,
            "{nt} tail draws, KS D {d_tail:.4} vs {crit_tail:.4}"
        );
        // Moments: mean 0, variance 1, kurtosis 3.
        let m = z.iter().sum::<f64>() / n as f64;
        let v = z.iter().map(|x| (x - m).powi(2)).sum::<f64>() / n as f64;
        let k = z.iter().map(|x| (x - m).powi(4)).sum::<f64>() / n as f64 / (v * v);
        assert!(
            m.abs() < 0.01 && (v - 1.0).abs() < 0.01 && (k - 3.0).abs() < 0.05,
            "{m} {v} {k}"
        );
    }

    #[test]
    fn frames_repeat_per_seed_and_neighbours_are_uncorrelated() {
        let water = WaterParams::preset(0.5);
        let (w, h) = (1440, 200);
        let dn = vec![40.0f32; w * h];
        let frame = |seed| {
            let mut out = vec![0u8; w * h];
            crate::render::optics::quantize_with_noise(&dn, w, &water, seed, &mut out);
            out
        };
        let a = frame(5);
        assert_eq!(a, frame(5));
        let b = frame(6);
        let same = a.iter().zip(&b).filter(|(x, y)| x == y).count();
        // Two independent draws agree about a sixth of the time at σ ≈ 1.73 DN.
        assert!(same < w * h / 3, "{same} of {} equal", w * h);
        // Correlation of each pixel with its right and lower neighbours, and
        // with the same pixel of another seed: within 5/√n of 0.
        let r: Vec<f64> = a.iter().map(|&v| f64::from(v) - 40.0).collect();
        let rb: Vec<f64> = b.iter().map(|&v| f64::from(v) - 40.0).collect();
        let corr = |pairs: &mut dyn Iterator<Item = (f64, f64)>| {
            let (mut sxy, mut sxx, mut syy, mut n) = (0.0, 0.0, 0.0, 0.0);
            for (x, y) in pairs {
                sxy += x * y;
                sxx += x * x;
                syy += y * y;
                n += 1.0;
            }
            (sxy / (sxx * syy).sqrt(), 5.0 / f64::sqrt(n))
        };
        let right = corr(
            &mut (0..h)
                .flat_map(|y| (0..w - 1).map(move |x| (y, x)))
                .map(|(y, x)| (r[y * w + x], r[y * w + x + 1])),
        );
        let down = corr(&mut (0..(h - 1) * w).map(|i| (r[i], r[i + w])));
        let seeds = corr(&mut r.iter().copied().zip(rb.iter().copied()));
        for (what, (c, lim)) in [("right", right), ("down", down), ("seeds", seeds)] {
            assert!(c.abs() < lim, "{what}: correlation {c:.5} (limit {lim:.5})");
        }
    }
}
