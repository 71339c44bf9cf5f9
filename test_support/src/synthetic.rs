//! Synthetic degraded marker frames for tests and benchmarks that must not
//! depend on the simulator: an enhanced-marker-like pattern (black
//! frame, white ring, black code border, 4x4 data bits, white quiet zone) on
//! a background, degraded as in the paper's Eq. (7):
//! `I = (f_d·J + (1 − f_d)·J * h_psf)·t + B∞·(1 − t) + n`.
//!
//! The degradation for a water of attenuation `c` ([`Degradation::for_c`])
//! imitates the simulator's model at a short range; the simulator
//! (`shoal_sim_bridge::render`) is the physically based reference.

use opencv::core::{self, Mat, Point, Rect, Scalar, BORDER_REFLECT_101, CV_8UC1};
use opencv::imgproc;
use opencv::prelude::*;
use shoal_node::restore::psf::{gamma, GgPsf};
use shoal_node::restore::RestoreError;
use shoal_proto::splitmix::SplitMix64;

/// How a clean frame is degraded.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct Degradation {
    /// Transmission `t` of the path to the marker (direct plus forward-scattered light).
    pub transmission: f64,
    /// Veiling light at infinity `B∞`, grey levels.
    pub backscatter_inf: f64,
    /// Forward-scatter PSF of the scattered part.
    pub psf: GgPsf,
    /// Part of the transmitted light that is not scattered (stays sharp).
    pub direct_fraction: f64,
    /// Additive Gaussian noise σ, grey levels.
    pub noise_sigma: f64,
}

impl Degradation {
    /// A stand-in for water of attenuation `c_per_m` seen at 0.35 m, shaped
    /// like the simulator's model (`docs/water-model.md`): 30 % of `c` is
    /// forward scatter, so `t = e^{−0.7·c·r}` of which `e^{−0.3·c·r}` is
    /// unscattered; the scattered part is spread by a generalized Gaussian of
    /// width `f·0.004 rad·√(c·r)` (f = 1250 px) and shape `p = 1.8 − 0.055·c`.
    pub fn for_c(c_per_m: f64) -> Self {
        let r = 0.35;
        let c = c_per_m.max(0.0);
        let p = (1.8 - 0.055 * c).clamp(1.0, 2.0);
        let width_px = 1250.0 * 0.004 * (c * r).sqrt();
        // The simulator's scale is width·√A(p) (its reading of Eq. (14));
        // GgPsf's is σ·√(Γ(1/p)/Γ(3/p)).
        let ratio = (gamma(1.0 / p) / gamma(3.0 / p)).sqrt();
        let a_paper = ratio / (2.0 * p.sqrt());
        let scale_px = (width_px * a_paper.sqrt()).max(0.3);
        Self {
            transmission: (-0.7 * c * r).exp(),
            backscatter_inf: 170.0,
            psf: GgPsf {
                p,
                sigma_px: scale_px / ratio,
                direct: 0.0,
            },
            direct_fraction: (-0.3 * c * r).exp(),
            noise_sigma: 1.5 + 0.25 * c,
        }
    }
}

/// A clean frame, its degraded version, and the marker's cell masks.
#[derive(Debug)]
pub struct SyntheticFrame {
    pub clean: Mat,
    pub degraded: Mat,
    /// Row-major masks of the marker's white and black cells (eroded by
    /// 2 px so the blurred cell borders do not count).
    pub white: Vec<bool>,
    pub black: Vec<bool>,
    /// The marker's outer black square, pixels.
    pub marker: Rect,
}

/// Grey levels of the clean scene.
const WHITE: f64 = 220.0;
const BLACK: f64 = 25.0;
const BACKGROUND: f64 = 110.0;

/// A `width`x`height` frame with a marker of `module_px`-pixel modules
/// centred at (`cx`, `cy`), degraded by `deg`; `seed` picks the data bits and the noise.
pub fn marker_frame(
    width: i32,
    height: i32,
    cx: i32,
    cy: i32,
    module_px: i32,
    deg: &Degradation,
    seed: u64,
) -> Result<SyntheticFrame, RestoreError> {
    let mut rng = SplitMix64::new(seed);
    // Background with a gentle vertical gradient (light from above).
    let mut clean = Mat::new_rows_cols_with_default(height, width, CV_8UC1, Scalar::all(0.0))?;
    for y in 0..height {
        let v = BACKGROUND * (1.15 - 0.3 * y as f64 / height as f64);
        for p in clean.at_row_mut::<u8>(y)? {
            *p = v.round() as u8;
        }
    }
    // 12x12 modules: quiet zone, black frame, white ring, black border, 4x4 data.
    let side = 12 * module_px;
    let x0 = cx - side / 2;
    let y0 = cy - side / 2;
    let mut cell = [[true; 12]; 12];
    for r in 0..12 {
        for c in 0..12 {
            let ring = r.min(c).min(11 - r).min(11 - c);
            cell[r][c] = match ring {
                0 => true,  // quiet zone
                1 => false, // black frame
                2 => true,  // white ring
                3 => false, // code border
                _ => rng.next_u64() & 1 == 1,
            };
        }
    }
    let mut white = vec![false; (width * height) as usize];
    let mut black = vec![false; (width * height) as usize];
    let inset = 2;
    for r in 0..12 {
        for c in 0..12 {
            let v = if cell[r][c] { WHITE } else { BLACK };
            let rect = Rect::new(
                x0 + c as i32 * module_px,
                y0 + r as i32 * module_px,
                module_px,
                module_px,
            );
            imgproc::rectangle(&mut clean, rect, Scalar::all(v), -1, imgproc::LINE_8, 0)?;
            let ring = r.min(c).min(11 - r).min(11 - c);
            if ring == 0 {
                continue; // the quiet zone is not part of the marker
            }
            for y in rect.y + inset..rect.y + rect.height - inset {
                for x in rect.x + inset..rect.x + rect.width - inset {
                    if x < 0 || y < 0 || x >= width || y >= height {
                        continue;
                    }
                    let i = (y * width + x) as usize;
                    if cell[r][c] {
                        white[i] = true;
                    } else {
                        black[i] = true;
                    }
                }
            }
        }
    }
    let mut blurred = Mat::default();
    imgproc::filter_2d(
        &clean,
        &mut blurred,
        core::CV_32F,
        &deg.psf.kernel()?,
        Point::new(-1, -1),
        0.0,
        BORDER_REFLECT_101,
    )?;
    let t = deg.transmission;
    let veil = deg.backscatter_inf * (1.0 - t);
    let mut degraded = Mat::new_rows_cols_with_default(height, width, CV_8UC1, Scalar::all(0.0))?;
    for y in 0..height {
        let b = blurred.at_row::<f32>(y)?;
        let cl = clean.at_row::<u8>(y)?;
        let o = degraded.at_row_mut::<u8>(y)?;
        for x in 0..width as usize {
            let j = deg.direct_fraction * cl[x] as f64 + (1.0 - deg.direct_fraction) * b[x] as f64;
            let v = j * t + veil + deg.noise_sigma * rng.normal();
            o[x] = v.round().clamp(0.0, 255.0) as u8;
        }
    }
    Ok(SyntheticFrame {
        clean,
        degraded,
        white,
        black,
        marker: Rect::new(
            x0 + module_px,
            y0 + module_px,
            10 * module_px,
            10 * module_px,
        ),
    })
}
