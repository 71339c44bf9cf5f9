//! HOIRM's ambient-light estimate (paper §4.2, Eq. (11)–(13)), kept per
//! camera as a running state.
//!
//! Eq. (11) blurs each frame, `Set_n = Img_n * G(σ)`; Eq. (12) sums them,
//! `B_L = Σ_n w_n·Set_n`, with weights that depend on the frames' relative
//! times and sum to `α < 1`. We take
//!
//! ```text
//! w_n = α · e^{−(t_k − t_n)/τ} / Σ_m e^{−(t_k − t_m)/τ}      (frames n = 1..k seen so far)
//! ```
//!
//! (newer frames weigh more; `τ` sets the memory). This needs no frame list:
//! with `S_k = e^{−(t_k − t_{k−1})/τ}·S_{k−1} + Set_k` and
//! `N_k = e^{−(t_k − t_{k−1})/τ}·N_{k−1} + 1`, by induction
//! `S_k = Σ_n e^{−(t_k − t_n)/τ}·Set_n` and `N_k = Σ_n e^{−(t_k − t_n)/τ}`, so
//! `B_L = α·S_k / N_k` is exactly Eq. (12) with the weights above
//! (`ambient_running_state_equals_eq12_weighted_sum` checks it). Frame gaps of
//! any length are handled, as the decay uses the stamps, not a frame count.
//!
//! The blurred frames are low-pass by construction, so the state lives on
//! the 1/8 level (Eq. (11)'s σ divided by 8): 64 times less memory and work,
//! and the same `B_L` after up-sampling to well under a grey level.

use super::RestoreError;
use opencv::core::{Mat, Size, BORDER_REFLECT_101, CV_32F};
use opencv::imgproc;
use opencv::prelude::*;

/// The running Eq. (12) state of one camera.
#[derive(Debug)]
pub struct AmbientLight {
    tau_s: f64,
    sigma_px: f64,
    /// `S_k`, f32, at the level the frames are given.
    sum: Mat,
    /// `N_k`.
    norm: f64,
    last_stamp_ns: Option<u64>,
}

impl AmbientLight {
    /// `tau_s`: memory of the weights; `sigma_px`: Eq. (11)'s σ at the level of the frames given.
    pub fn new(tau_s: f64, sigma_px: f64) -> Self {
        Self {
            tau_s,
            sigma_px,
            sum: Mat::default(),
            norm: 0.0,
            last_stamp_ns: None,
        }
    }

    /// Forget every frame (a new sequence, or the image size changed).
    pub fn reset(&mut self) {
        self.sum = Mat::default();
        self.norm = 0.0;
        self.last_stamp_ns = None;
    }

    /// Number of frames' worth of weight in the state (`N_k`).
    pub fn effective_frames(&self) -> f64 {
        self.norm
    }

    /// Eq. (11): the Gaussian-blurred frame, f32.
    pub fn blurred(&self, frame: &Mat) -> Result<Mat, RestoreError> {
        let mut f = Mat::default();
        frame.convert_to(&mut f, CV_32F, 1.0, 0.0)?;
        let mut set = Mat::default();
        imgproc::gaussian_blur(
            &f,
            &mut set,
            Size::new(0, 0),
            self.sigma_px,
            self.sigma_px,
            BORDER_REFLECT_101,
        )?;
        Ok(set)
    }

    /// Add a frame taken at `stamp_ns` and return `S_k / N_k`, the
    /// Eq. (12) weighted mean with weights summing to 1 (multiply by `α` for `B_L`).
    /// A stamp earlier than the previous one (replay restarted) or a new
    /// frame size starts the state afresh.
    pub fn update(&mut self, frame: &Mat, stamp_ns: u64) -> Result<Mat, RestoreError> {
        let set = self.blurred(frame)?;
        let size_changed = self.sum.empty() || self.sum.size()? != set.size()?;
        let went_back = self.last_stamp_ns.is_some_and(|t| stamp_ns < t);
        if size_changed || went_back {
            self.reset();
        }
        match self.last_stamp_ns {
            None => {
                self.sum = set;
                self.norm = 1.0;
            }
            Some(prev) => {
                let dt_s = (stamp_ns - prev) as f64 * 1e-9;
                let decay = if self.tau_s > 0.0 {
                    (-dt_s / self.tau_s).exp()
                } else {
                    0.0
                };
                let mut next = Mat::default();
                opencv::core::add_weighted(&self.sum, decay, &set, 1.0, 0.0, &mut next, -1)?;
                self.sum = next;
                self.norm = decay * self.norm + 1.0;
            }
        }
        self.last_stamp_ns = Some(stamp_ns);
        let mut mean = Mat::default();
        self.sum
            .convert_to(&mut mean, CV_32F, 1.0 / self.norm, 0.0)?;
        Ok(mean)
    }
}

/// The Eq. (12) weights `w_n` for frames of the given ages (seconds before
/// the current frame, the current one 0): `α·e^{−age/τ}` normalized to sum
/// to `α`. With `τ = 0` only the current frame counts.
pub fn eq12_weights(ages_s: &[f64], tau_s: f64, alpha: f64) -> Vec<f64> {
    let raw: Vec<f64> = ages_s
        .iter()
        .map(|&a| {
            if tau_s > 0.0 {
                (-a / tau_s).exp()
            } else if a == 0.0 {
                1.0
            } else {
                0.0
            }
        })
        .collect();
    let s: f64 = raw.iter().sum();
    if s <= 0.0 {
        return vec![0.0; ages_s.len()];
    }
    raw.iter().map(|r| alpha * r / s).collect()
}

#[cfg(test)]
mod tests {
    use super::*;
    use opencv::core::{Scalar, CV_8UC1};
    use rand::{Rng, SeedableRng};
    use rand_chacha::ChaCha8Rng;

    fn random_frame(rng: &mut ChaCha8Rng) -> Mat {
        let mut m = Mat::new_rows_cols_with_default(30, 40, CV_8UC1, Scalar::all(0.0)).unwrap();
        for y in 0..30 {
            for v in m.at_row_mut::<u8>(y).unwrap() {
                *v = rng.gen();
            }
        }
        m
    }

    #[test]
    fn eq12_weights_sum_to_alpha_and_favour_recent_frames() {
        let w = eq12_weights(&[0.0, 0.1, 0.35, 2.0], 0.5, 0.8);
        assert!((w.iter().sum::<f64>() - 0.8).abs() < 1e-12);
        assert!(w.windows(2).all(|p| p[0] > p[1]));
        assert_eq!(eq12_weights(&[0.0, 0.1], 0.0, 0.5), vec![0.5, 0.0]);
    }

    #[test]
    fn ambient_running_state_equals_eq12_weighted_sum() {
        let mut rng = ChaCha8Rng::seed_from_u64(11);
        let tau = 0.3;
        let mut state = AmbientLight::new(tau, 2.0);
        // Irregular frame times, as with dropped frames.
        let stamps_ns: [u64; 6] = [
            1_000_000_000,
            1_033_000_000,
            1_066_000_000,
            1_200_000_000,
            1_233_000_000,
            1_900_000_000,
        ];
        let mut sets = Vec::new();
        let mut last = Mat::default();
        for &t in &stamps_ns {
            let f = random_frame(&mut rng);
            sets.push(state.blurred(&f).unwrap());
            last = state.update(&f, t).unwrap();
        }
        let now = *stamps_ns.last().unwrap();
        let ages: Vec<f64> = stamps_ns.iter().map(|&t| (now - t) as f64 * 1e-9).collect();
        let alpha = 0.7;
        let w = eq12_weights(&ages, tau, alpha);
        for y in 0..30 {
            for x in 0..40 {
                let explicit: f64 = sets
                    .iter()
                    .zip(&w)
                    .map(|(s, wn)| wn * *s.at_2d::<f32>(y, x).unwrap() as f64)
                    .sum();
                let running = alpha * *last.at_2d::<f32>(y, x).unwrap() as f64;
                assert!(
                    (explicit - running).abs() < 1e-3,
                    "({x},{y}): {explicit} vs {running}"
                );
            }
        }
    }

    #[test]
    fn ambient_state_restarts_when_time_goes_back_or_size_changes() {
        let mut rng = ChaCha8Rng::seed_from_u64(12);
        let mut state = AmbientLight::new(1.0, 2.0);
        state.update(&random_frame(&mut rng), 5_000).unwrap();
        state.update(&random_frame(&mut rng), 6_000).unwrap();
        assert!(state.effective_frames() > 1.5);
        let f = random_frame(&mut rng);
        let mean = state.update(&f, 1_000).unwrap();
        assert_eq!(state.effective_frames(), 1.0);
        let set = state.blurred(&f).unwrap();
        assert_eq!(
            *mean.at_2d::<f32>(3, 4).unwrap(),
            *set.at_2d::<f32>(3, 4).unwrap()
        );
        let small = Mat::new_rows_cols_with_default(20, 20, CV_8UC1, Scalar::all(9.0)).unwrap();
        state.update(&small, 2_000).unwrap();
        assert_eq!(state.effective_frames(), 1.0);
    }
}
