//! Simulated navigation sensors: what each vehicle's pressure sensor, IMU and
//! DVL would report of its ground truth, as [`NavState`]s.
//!
//! Each sensor has white noise per sample and a constant bias per vehicle
//! (drawn once from the seed: a pressure sensor's offset, an IMU mounted a
//! little off level). The reported standard deviations are the honest ones:
//! noise and bias together. The DVL loses bottom lock now and then
//! (`velocity_dropout`): no velocity in that sample.

use crate::SimError;
use rand::{Rng, SeedableRng};
use rand_chacha::ChaCha8Rng;
use rand_distr::{Distribution, StandardNormal};
use shoal_proto::geometry::wrap_angle;
use shoal_proto::nav::{BodyVelocity, Depth, Heading, NavState, Tilt};
use shoal_proto::{VehicleId, VehicleTruth};
use std::collections::BTreeMap;

/// Noise and bias of the simulated sensors. `Default`: a small AUV's
/// (pressure sensor 1 cm + 2 cm offset, IMU tilt 0.1° + 0.2° misalignment,
/// AHRS heading 0.5° + 1.5° offset, DVL 1 cm/s, 5 % of samples without
/// bottom lock).
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct NavSensorParams {
    pub depth_noise_m: f64,
    /// Standard deviation of the per-vehicle depth offset.
    pub depth_bias_m: f64,
    pub tilt_noise_rad: f64,
    /// Standard deviation of the per-vehicle roll and pitch offsets.
    pub tilt_bias_rad: f64,
    /// The vehicle has a compass / AHRS heading (false: roll, pitch and depth only).
    pub heading: bool,
    pub heading_noise_rad: f64,
    /// Standard deviation of the per-vehicle heading offset (a compass near a hull).
    pub heading_bias_rad: f64,
    pub velocity_noise_mps: f64,
    /// Probability a sample has no velocity (DVL without bottom lock).
    pub velocity_dropout: f64,
}

impl Default for NavSensorParams {
    fn default() -> Self {
        Self {
            depth_noise_m: 0.01,
            depth_bias_m: 0.02,
            tilt_noise_rad: 0.1f64.to_radians(),
            tilt_bias_rad: 0.2f64.to_radians(),
            heading: true,
            heading_noise_rad: 0.5f64.to_radians(),
            heading_bias_rad: 1.5f64.to_radians(),
            velocity_noise_mps: 0.01,
            velocity_dropout: 0.05,
        }
    }
}

impl NavSensorParams {
    /// Every value finite and non-negative, the dropout a probability.
    pub fn validate(&self) -> Result<(), SimError> {
        let fields = [
            ("depth_noise_m", self.depth_noise_m),
            ("depth_bias_m", self.depth_bias_m),
            ("tilt_noise_rad", self.tilt_noise_rad),
            ("tilt_bias_rad", self.tilt_bias_rad),
            ("heading_noise_rad", self.heading_noise_rad),
            ("heading_bias_rad", self.heading_bias_rad),
            ("velocity_noise_mps", self.velocity_noise_mps),
        ];
        for (field, value) in fields {
            if !(value.is_finite() && value >= 0.0) {
                return Err(SimError::InvalidArgument {
                    field,
                    value,
                    reason: "must be finite and non-negative",
                });
            }
        }
        if !(0.0..=1.0).contains(&self.velocity_dropout) {
            return Err(SimError::InvalidArgument {
                field: "velocity_dropout",
                value: self.velocity_dropout,
                reason: "must be a probability in 0..=1",
            });
        }
        Ok(())
    }
}

/// Smallest standard deviation reported, so that a noiseless setting still
/// gives a valid (positive definite) covariance.
const MIN_STD: f64 = 1e-6;

/// The sensors of every vehicle, seeded.
#[derive(Debug, Clone)]
pub struct NavSensors {
    params: NavSensorParams,
    seed: u64,
    rng: ChaCha8Rng,
    /// Per vehicle: depth, roll, pitch and heading offsets.
    bias: BTreeMap<VehicleId, [f64; 4]>,
}

impl NavSensors {
    pub fn new(params: NavSensorParams, seed: u64) -> Result<Self, SimError> {
        params.validate()?;
        Ok(Self {
            params,
            seed,
            rng: ChaCha8Rng::seed_from_u64(seed ^ 0x6e61_7673),
            bias: BTreeMap::new(),
        })
    }

    pub fn params(&self) -> &NavSensorParams {
        &self.params
    }

    fn normal(&mut self) -> f64 {
        StandardNormal.sample(&mut self.rng)
    }

    /// The vehicle's offsets: drawn from the seed and the vehicle's ID, so
    /// they do not depend on the order vehicles are first measured in.
    fn bias_of(&mut self, vehicle: VehicleId) -> [f64; 4] {
        let p = self.params;
        let seed = self.seed;
        *self.bias.entry(vehicle).or_insert_with(|| {
            let mut rng = ChaCha8Rng::seed_from_u64(seed ^ (u64::from(vehicle) << 32) ^ 0x6269);
            let mut n = || -> f64 { StandardNormal.sample(&mut rng) };
            [
                p.depth_bias_m * n(),
                p.tilt_bias_rad * n(),
                p.tilt_bias_rad * n(),
                p.heading_bias_rad * n(),
            ]
        })
    }

    /// What `truth`'s vehicle's sensors report at `stamp_ns`.
    pub fn measure(&mut self, truth: &VehicleTruth, stamp_ns: u64) -> NavState {
        let p = self.params;
        let [depth_bias, roll_bias, pitch_bias, heading_bias] = self.bias_of(truth.vehicle);
        let (roll, pitch, yaw) = truth.world_from_body.rotation.euler_angles();
        let depth_std = p.depth_noise_m.hypot(p.depth_bias_m).max(MIN_STD);
        let tilt_var = p.tilt_noise_rad.hypot(p.tilt_bias_rad).max(MIN_STD).powi(2);
        let depth =
            truth.world_from_body.translation.z + depth_bias + p.depth_noise_m * self.normal();
        let roll = roll + roll_bias + p.tilt_noise_rad * self.normal();
        let pitch = pitch + pitch_bias + p.tilt_noise_rad * self.normal();
        let heading_noise = p.heading_noise_rad * self.normal();
        let heading = p.heading.then(|| Heading {
            yaw_rad: wrap_angle(yaw + heading_bias + heading_noise),
            std_rad: p.heading_noise_rad.hypot(p.heading_bias_rad).max(MIN_STD),
        });
        let lost = self.rng.gen_bool(p.velocity_dropout);
        let velocity = (!lost).then(|| {
            let v = truth.velocity_body;
            let s = p.velocity_noise_mps;
            let var = s.max(MIN_STD).powi(2);
            BodyVelocity {
                velocity_mps: [
                    v[0] + s * self.normal(),
                    v[1] + s * self.normal(),
                    v[2] + s * self.normal(),
                ],
                covariance: [[var, 0.0, 0.0], [0.0, var, 0.0], [0.0, 0.0, var]],
            }
        });
        NavState {
            vehicle: truth.vehicle,
            stamp_ns,
            depth: Some(Depth {
                depth_m: depth,
                std_m: depth_std,
            }),
            tilt: Some(Tilt {
                roll_rad: wrap_angle(roll),
                pitch_rad: pitch.clamp(-std::f64::consts::FRAC_PI_2, std::f64::consts::FRAC_PI_2),
                covariance: [[tilt_var, 0.0], [0.0, tilt_var]],
            }),
            heading,
            velocity,
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use shoal_proto::geometry::pose_from_xyz_rpy;
    use shoal_proto::WireMessage;

    fn truth(vehicle: VehicleId) -> VehicleTruth {
        VehicleTruth {
            vehicle,
            world_from_body: pose_from_xyz_rpy([1.0, 2.0, 5.0], [0.05, -0.1, 2.0]),
            velocity_body: [0.4, 0.0, 0.01],
        }
    }

    #[test]
    fn samples_scatter_around_truth_plus_a_per_vehicle_offset_with_honest_sigmas() {
        let mut s = NavSensors::new(NavSensorParams::default(), 7).expect("valid");
        let n = 4000;
        let (mut d, mut d2, mut r, mut lost) = (0.0, 0.0, 0.0, 0);
        for k in 0..n {
            let m = s.measure(&truth(15), k);
            assert_eq!(m.validate(), Ok(()));
            let dd = m.depth.expect("depth").depth_m - 5.0;
            d += dd;
            d2 += dd * dd;
            r += m.tilt.expect("tilt").roll_rad - 0.05;
            lost += usize::from(m.velocity.is_none());
        }
        let (mean, nf) = (d / n as f64, n as f64);
        let std = (d2 / nf - mean * mean).sqrt();
        // The offset is one draw of σ 2 cm; the scatter about it is the 1 cm noise.
        assert!(mean.abs() < 0.08, "depth offset {mean}");
        assert!((std - 0.01).abs() < 0.001, "depth noise {std}");
        assert!((r / nf).abs() < 4.0 * 0.2f64.to_radians(), "roll offset");
        let rate = lost as f64 / nf;
        assert!((rate - 0.05).abs() < 0.015, "dropout rate {rate}");
        let m = s.measure(&truth(15), 0);
        let reported = m.depth.expect("depth").std_m;
        assert!((reported - 0.01f64.hypot(0.02)).abs() < 1e-12);
        // Offsets are the vehicle's own, whatever order vehicles come in.
        let mut a = NavSensors::new(NavSensorParams::default(), 7).expect("valid");
        let mut b = NavSensors::new(NavSensorParams::default(), 7).expect("valid");
        a.measure(&truth(10), 0);
        assert_eq!(a.bias_of(15), b.bias_of(15));
        assert_ne!(a.bias_of(10), a.bias_of(15));
    }

    #[test]
    fn bad_parameters_are_named() {
        let p = NavSensorParams {
            tilt_noise_rad: f64::NAN,
            ..NavSensorParams::default()
        };
        let e = NavSensors::new(p, 1).expect_err("NaN refused").to_string();
        assert!(e.contains("tilt_noise_rad"), "{e}");
        let p = NavSensorParams {
            velocity_dropout: 1.5,
            ..NavSensorParams::default()
        };
        let e = NavSensors::new(p, 1).expect_err("1.5 refused").to_string();
        assert!(e.contains("velocity_dropout"), "{e}");
    }
}
