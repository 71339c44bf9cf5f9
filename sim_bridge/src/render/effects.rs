//! The camera effects that act on a rendered frame's light (floats, DN
//! before noise) and on its sensor: spot-lamp pattern, marine snow,
//! vignetting, auto-exposure, Poisson–Gaussian noise with analog gain,
//! gamma, the Bayer mosaic and its demosaicing. Equations and sources:
//! `docs/water-model.md`, "Camera effects". The OpenCV-backed ones (PSF
//! convolution, codecs) are in `codec.rs`.

use super::noise::{RowRng, Sensor};
use crate::profile::{MarineSnow, SpotLamps};
use crate::water::WaterParams;
use nalgebra::Vector3;
use rand::Rng;
use rand_chacha::ChaCha8Rng;
use rand_distr::{Distribution, Poisson};
use shoal_proto::CameraModel;

/// A smooth per-pixel field `f(x, y)` of the in-air ray `(x, y, 1)`,
/// evaluated on an 8-pixel grid and interpolated bilinearly (exact at the grid nodes).
pub fn smooth_field(cam: &CameraModel, f: impl Fn(f64, f64) -> f64) -> Vec<f32> {
    let (w, h) = (cam.width as usize, cam.height as usize);
    let step = 8usize;
    let gw = (w - 1) / step + 2;
    let gh = (h - 1) / step + 2;
    let mut grid = vec![0.0f32; gw * gh];
    for gy in 0..gh {
        for gx in 0..gw {
            let (x, y) = cam.ray((gx * step) as f64, (gy * step) as f64);
            grid[gy * gw + gx] = f(x, y) as f32;
        }
    }
    let mut out = vec![0.0f32; w * h];
    let inv = 1.0 / step as f32;
    for y in 0..h {
        let gy = y / step;
        let ty = (y % step) as f32 * inv;
        for x in 0..w {
            let gx = x / step;
            let tx = (x % step) as f32 * inv;
            let g = |i: usize, j: usize| grid[j * gw + i];
            out[y * w + x] = (g(gx, gy) * (1.0 - tx) + g(gx + 1, gy) * tx) * (1.0 - ty)
                + (g(gx, gy + 1) * (1.0 - tx) + g(gx + 1, gy + 1) * tx) * ty;
        }
    }
    out
}

/// `V = 1 − strength·(1 − cos⁴θ)`, θ the ray's angle to the optical axis.
pub fn vignetting(x: f64, y: f64, strength: f64) -> f64 {
    let cos2 = 1.0 / (1.0 + x * x + y * y);
    1.0 - strength * (1.0 - cos2 * cos2)
}

/// The irradiance of the two spot lamps at the point `p` (camera frame, m),
/// summed, each a Gaussian beam `exp(−2θ²/θ_b²)` falling off as `1/d²`
/// and attenuated by `e^(−c·d)` over the lamp-to-point distance `d`.
pub fn lamp_irradiance(l: &SpotLamps, c_per_m: f64, p: &Vector3<f64>) -> f64 {
    let theta_b = l.beam_half_angle_deg.to_radians();
    let toe = l.toe_out_deg.to_radians();
    [-1.0, 1.0]
        .iter()
        .map(|side: &f64| {
            let pos = Vector3::new(side * 0.5 * l.separation_m, 0.0, 0.0);
            let axis = Vector3::new(side * toe.sin(), 0.0, toe.cos());
            let q = p - pos;
            let d = q.norm().max(1e-3);
            let theta = (q.dot(&axis) / d).clamp(-1.0, 1.0).acos();
            (-2.0 * theta * theta / (theta_b * theta_b)).exp() * (-c_per_m * d).exp() / (d * d)
        })
        .sum()
}

/// The light field of the spot lamps over the image (multiplies the frame):
/// `a + (1 − a)·E(x)/E(axis)`, `E` the lamps' irradiance at `range_m` along each pixel's ray.
pub fn lamp_field(cam: &CameraModel, l: &SpotLamps, c_per_m: f64) -> Vec<f32> {
    let at = |x: f64, y: f64| {
        let d = Vector3::new(x, y, 1.0);
        lamp_irradiance(l, c_per_m, &(d * (l.range_m / d.norm())))
    };
    let axis = at(0.0, 0.0).max(1e-12);
    let a = l.ambient_share;
    smooth_field(cam, |x, y| a + (1.0 - a) * at(x, y) / axis)
}

/// One particle of marine snow in the camera frame.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct Particle {
    /// Pixel position of its centre.
    pub u: f64,
    pub v: f64,
    /// Depth along the optical axis (m).
    pub z_m: f64,
    pub diameter_m: f64,
}

/// Draw the particles of one frame: uniform in the camera's frustum (a
/// margin of 20 px around the image) between `near_m` and `far_m`, sizes
/// from `N(d) ∝ d^-3`.
pub fn draw_snow(cam: &CameraModel, s: &MarineSnow, rng: &mut ChaCha8Rng) -> Vec<Particle> {
    let margin = 20.0;
    let (w, h) = (
        f64::from(cam.width) + 2.0 * margin,
        f64::from(cam.height) + 2.0 * margin,
    );
    // Frustum volume: ∫ (w/fx)(h/fy) z² dz.
    let volume = w / cam.fx * h / cam.fy * (s.far_m.powi(3) - s.near_m.powi(3)) / 3.0;
    let mean = s.density_per_m3 * volume;
    let count = if mean > 0.0 {
        Poisson::new(mean).map_or(mean, |p| p.sample(rng)) as usize
    } else {
        0
    };
    let (n3, f3) = (s.near_m.powi(3), s.far_m.powi(3));
    let (a, b) = (
        (s.min_diameter_mm * 1e-3).powi(-2),
        (s.max_diameter_mm * 1e-3).powi(-2),
    );
    (0..count)
        .map(|_| {
            let z = (n3 + rng.gen::<f64>() * (f3 - n3)).cbrt();
            let d = (a - rng.gen::<f64>() * (a - b)).powf(-0.5);
            Particle {
                u: rng.gen::<f64>() * w - margin,
                v: rng.gen::<f64>() * h - margin,
                z_m: z,
                diameter_m: d,
            }
        })
        .collect()
}

/// Add the particles to `dn` (linear DN of one colour channel with
/// attenuation `c_per_m`): each is a disc of the defocus blur circle
/// `b = f·D·|1/z − 1/z_f|` (quadrature-summed with its own image), whose
/// total light is its radiance times its in-focus image area, and which
/// hides the same share of what lies behind it.
pub fn add_snow(
    dn: &mut [f32],
    cam: &CameraModel,
    water: &WaterParams,
    c_per_m: f64,
    s: &MarineSnow,
    lamps: &SpotLamps,
    particles: &[Particle],
) {
    let (w, h) = (cam.width as i64, cam.height as i64);
    let gain = 255.0 * water.exposure;
    let f = 0.5 * (cam.fx + cam.fy);
    for p in particles {
        let (x, y) = cam.ray(
            p.u.clamp(0.0, (w - 1) as f64),
            p.v.clamp(0.0, (h - 1) as f64),
        );
        let pos = Vector3::new(x * p.z_m, y * p.z_m, p.z_m);
        let range = pos.norm();
        let back = (-c_per_m * range).exp();
        // Lamp light (two-way attenuation inside `lamp_irradiance` and `back`)
        // plus the ambient light a horizontal Lambertian reflector gets (0.75).
        let radiance = s.albedo
            * (s.lamp_power * lamp_irradiance(lamps, c_per_m, &pos) * back
                + 0.75 * water.illumination * back);
        let image_d = p.diameter_m * f / p.z_m;
        let defocus = f * s.aperture_mm * 1e-3 * (1.0 / p.z_m - 1.0 / s.focus_m).abs();
        let disc_d = (defocus * defocus + image_d * image_d).sqrt().max(0.5);
        let area = std::f64::consts::PI * 0.25 * image_d * image_d;
        let r = 0.5 * disc_d;
        let (x0, x1) = (
            (p.u - r - 1.0).floor() as i64,
            (p.u + r + 1.0).ceil() as i64,
        );
        let (y0, y1) = (
            (p.v - r - 1.0).floor() as i64,
            (p.v + r + 1.0).ceil() as i64,
        );
        // Anti-aliased disc weights, normalized to the particle's image area.
        let mut weights = Vec::new();
        let mut total = 0.0;
        for yy in y0..=y1 {
            for xx in x0..=x1 {
                let dist = ((xx as f64 - p.u).powi(2) + (yy as f64 - p.v).powi(2)).sqrt();
                let cover = (r + 0.5 - dist).clamp(0.0, 1.0);
                if cover > 0.0 {
                    total += cover;
                    weights.push((xx, yy, cover));
                }
            }
        }
        if total <= 0.0 {
            continue;
        }
        let light = (gain * radiance) as f32;
        for (xx, yy, cover) in weights {
            if xx < 0 || yy < 0 || xx >= w || yy >= h {
                continue;
            }
            let share = (cover * area / total).min(1.0) as f32;
            let i = (yy * w + xx) as usize;
            dn[i] += share * (light - dn[i]);
        }
    }
}

/// Auto-exposure: the gain that brings the frame's mean linear level to
/// `target · 255`, clamped to `[min, max]`.
pub fn auto_gain(mean_dn: f64, target: f64, min: f64, max: f64) -> f64 {
    if mean_dn > 0.0 {
        (target * 255.0 / mean_dn).clamp(min, max)
    } else {
        max
    }
}

/// Poisson–Gaussian sensor noise with gain `g`, linear DN out, clipped to
/// `0..=255`. The same model and random streams as the renderer's
/// (`optics::quantize_with_noise`, row `y` from [`RowRng`] stream `y`): below
/// 1 the gain is a shorter exposure (fewer electrons), above 1 an analog gain
/// that amplifies the electrons' and the read noise alike.
pub fn noisy_linear(dn: &[f32], w: usize, water: &WaterParams, g: f64, seed: u64) -> Vec<f32> {
    let sensor = Sensor::new(water.gain_e_per_dn, water.read_noise_dn);
    let (pre, post) = if g <= 1.0 { (g, 1.0) } else { (1.0, g) };
    let mut out = vec![0.0f32; dn.len()];
    for (y, (row_in, row_out)) in dn.chunks(w).zip(out.chunks_mut(w)).enumerate() {
        if water.is_noiseless() {
            for (o, &v) in row_out.iter_mut().zip(row_in) {
                *o = (f64::from(v) * pre * post).clamp(0.0, 255.0) as f32;
            }
            continue;
        }
        let mut rng = RowRng::new(seed, y as u64);
        sensor.noisy(row_in, pre as f32, &mut rng, row_out);
        let post = post as f32;
        for o in row_out.iter_mut() {
            // NaN stays NaN, and rounds to 0 in `encode` as in the renderer.
            *o = (*o * post).clamp(0.0, 255.0);
        }
    }
    out
}

/// Encode linear DN (0..=255) with gamma `gamma` (`255·(v/255)^(1/γ)`) and round to 8 bits.
pub fn encode(linear: &[f32], gamma: f64) -> Vec<u8> {
    if gamma == 1.0 {
        // The renderer's own rounding, so that an unprofiled frame is its bytes.
        return linear
            .iter()
            .map(|&v| super::noise::quantize_f32(v))
            .collect();
    }
    let lut: Vec<f64> = (0..=4096)
        .map(|i| 255.0 * (i as f64 / 4096.0).powf(1.0 / gamma))
        .collect();
    linear
        .iter()
        .map(|&v| {
            let t = (f64::from(v) / 255.0).clamp(0.0, 1.0) * 4096.0;
            let i = (t as usize).min(4095);
            let f = t - i as f64;
            (lut[i] * (1.0 - f) + lut[i + 1] * f)
                .round()
                .clamp(0.0, 255.0) as u8
        })
        .collect()
}

/// Colour of the photosite at `(x, y)` of an RGGB Bayer mosaic: 0 red, 1 green, 2 blue.
pub fn bayer_channel(x: usize, y: usize) -> usize {
    match (y % 2, x % 2) {
        (0, 0) => 0,
        (1, 1) => 2,
        _ => 1,
    }
}

/// Sample three channel images on an RGGB mosaic.
pub fn mosaic(channels: &[Vec<f32>; 3], w: usize) -> Vec<f32> {
    (0..channels[0].len())
        .map(|i| channels[bayer_channel(i % w, i / w)][i])
        .collect()
}

/// Bilinear demosaicing of an RGGB mosaic: every missing colour is the mean
/// of the nearest photosites of that colour (edge pixels use those inside the image).
pub fn demosaic(raw: &[f32], w: usize, h: usize) -> [Vec<f32>; 3] {
    let mut out = [
        vec![0.0f32; w * h],
        vec![0.0f32; w * h],
        vec![0.0f32; w * h],
    ];
    for y in 0..h {
        for x in 0..w {
            let i = y * w + x;
            let mut sum = [0.0f32; 3];
            let mut cnt = [0u32; 3];
            let own = bayer_channel(x, y);
            for dy in -1i64..=1 {
                for dx in -1i64..=1 {
                    let (xx, yy) = (x as i64 + dx, y as i64 + dy);
                    if xx < 0 || yy < 0 || xx >= w as i64 || yy >= h as i64 {
                        continue;
                    }
                    let c = bayer_channel(xx as usize, yy as usize);
                    // Green: the 4-neighbours only (the diagonal greens are farther).
                    if c == 1 && own != 1 && dx != 0 && dy != 0 {
                        continue;
                    }
                    sum[c] += raw[yy as usize * w + xx as usize];
                    cnt[c] += 1;
                }
            }
            for c in 0..3 {
                out[c][i] = if c == own {
                    raw[i]
                } else if cnt[c] > 0 {
                    sum[c] / cnt[c] as f32
                } else {
                    0.0
                };
            }
        }
    }
    out
}

/// Rec. 601 luma.
pub fn luma(rgb: &[Vec<f32>; 3]) -> Vec<f32> {
    rgb[0]
        .iter()
        .zip(&rgb[1])
        .zip(&rgb[2])
        .map(|((r, g), b)| 0.299 * r + 0.587 * g + 0.114 * b)
        .collect()
}

#[cfg(test)]
mod tests {
    use super::*;
    use rand::SeedableRng;

    #[test]
    fn demosaicing_a_flat_colour_returns_it() {
        let (w, h) = (8, 6);
        let ch = [vec![10.0f32; w * h], vec![50.0; w * h], vec![90.0; w * h]];
        let rgb = demosaic(&mosaic(&ch, w), w, h);
        for c in 0..3 {
            assert!(
                rgb[c].iter().all(|v| (*v - ch[c][0]).abs() < 1e-4),
                "channel {c}"
            );
        }
    }

    #[test]
    fn gamma_one_rounds_like_the_renderer() {
        assert_eq!(
            encode(&[0.49, 0.5, 254.6, 300.0, -3.0], 1.0),
            vec![0, 1, 255, 255, 0]
        );
        // Gamma 2.2 lifts the mid-tones: 18 % grey encodes near 118 DN.
        let g = encode(&[0.18 * 255.0], 2.2)[0];
        assert!((117..=119).contains(&g), "{g}");
    }

    #[test]
    fn snow_count_follows_the_density() {
        let cam = CameraModel::vehicle_1440();
        let mut rng = ChaCha8Rng::seed_from_u64(3);
        // The frustum (20 px margin all round) between 0.15 and 2.5 m.
        let volume =
            (1480.0 / cam.fx) * (1120.0 / cam.fy) * (2.5f64.powi(3) - 0.15f64.powi(3)) / 3.0;
        for density in [300.0, 1200.0] {
            let s = MarineSnow {
                density_per_m3: density,
                ..MarineSnow::default()
            };
            let n = draw_snow(&cam, &s, &mut rng).len() as f64;
            let mean = density * volume;
            // A Poisson count: within 4 standard deviations of its mean.
            assert!(
                (n - mean).abs() < 4.0 * mean.sqrt(),
                "{density}: {n} vs {mean:.0}"
            );
        }
    }
}
