//! A vehicle's own navigation: what its pressure sensor, IMU and DVL (or
//! visual-inertial odometry) know without any camera. Fusion uses depth and
//! roll/pitch to settle what a single marker cannot: the planar-flip twin of
//! a marker pose implies a tilt of the target that its own IMU contradicts.
//!
//! Heading, when a vehicle has one worth sending (an INS; a compass with its
//! error stated honestly), settles the twins gravity cannot: a marker seen
//! obliquely in azimuth from a level vehicle has a twin turned about the
//! vertical, which changes no vehicle's tilt.
//!
//! Frames as everywhere in shoal: world NED (z down), body FRD. Roll and
//! pitch are the body's attitude in the local level frame
//! (`world_from_body = Rz(yaw)·Ry(pitch)·Rx(roll)`, yaw unknown here);
//! depth is the body origin's, metres below the surface (NED z).

use crate::messages::{MessageKind, VehicleId, WireMessage};
use nalgebra::Vector3;
use serde::{Deserialize, Serialize};

/// Depth of the body origin below the surface, from a pressure sensor.
#[derive(Debug, Clone, Copy, PartialEq, Serialize, Deserialize)]
pub struct Depth {
    /// Metres, positive down.
    pub depth_m: f64,
    /// Standard deviation, m (noise and bias together).
    pub std_m: f64,
}

/// Roll and pitch from the IMU's gravity vector.
#[derive(Debug, Clone, Copy, PartialEq, Serialize, Deserialize)]
pub struct Tilt {
    pub roll_rad: f64,
    pub pitch_rad: f64,
    /// Covariance of (roll, pitch), rad² (noise and bias together).
    pub covariance: [[f64; 2]; 2],
}

impl Tilt {
    /// The largest standard deviation of the covariance, rad.
    pub fn max_std_rad(&self) -> f64 {
        let [[a, b], [_, d]] = self.covariance;
        let mean = 0.5 * (a + d);
        let spread = (0.25 * (a - d) * (a - d) + b * b).sqrt();
        (mean + spread).max(0.0).sqrt()
    }

    /// Gravity's direction in the body frame (unit; world +z is down).
    pub fn gravity_in_body(&self) -> Vector3<f64> {
        gravity_in_body(self.roll_rad, self.pitch_rad)
    }
}

/// Gravity's direction (world +z, NED) in a body frame of this roll and pitch:
/// `(R_world_from_body)ᵀ · e_z`, which yaw does not change.
pub fn gravity_in_body(roll_rad: f64, pitch_rad: f64) -> Vector3<f64> {
    let (sr, cr) = roll_rad.sin_cos();
    let (sp, cp) = pitch_rad.sin_cos();
    Vector3::new(-sp, sr * cp, cr * cp)
}

/// Heading (yaw about world down, from north), from a compass, an AHRS or
/// an INS.
#[derive(Debug, Clone, Copy, PartialEq, Serialize, Deserialize)]
pub struct Heading {
    pub yaw_rad: f64,
    /// Standard deviation, rad (noise and bias together: a magnetic compass
    /// near a hull is off by degrees).
    pub std_rad: f64,
}

/// Body-frame velocity, from a DVL or odometry.
#[derive(Debug, Clone, Copy, PartialEq, Serialize, Deserialize)]
pub struct BodyVelocity {
    /// Forward, starboard, down, m/s.
    pub velocity_mps: [f64; 3],
    /// Covariance, (m/s)².
    pub covariance: [[f64; 3]; 3],
}

/// One vehicle's navigation state at one instant; each part is optional (a
/// vehicle without a DVL sends no velocity).
#[derive(Debug, Clone, Copy, PartialEq, Serialize, Deserialize)]
pub struct NavState {
    pub vehicle: VehicleId,
    /// Time of the measurement, on the same clock as the cameras' captures.
    pub stamp_ns: u64,
    pub depth: Option<Depth>,
    pub tilt: Option<Tilt>,
    pub heading: Option<Heading>,
    pub velocity: Option<BodyVelocity>,
}

/// Depths a vehicle can report: a little above the surface (waves, a
/// surfaced vehicle) to the deepest ocean.
pub const DEPTH_RANGE_M: (f64, f64) = (-10.0, 11_000.0);
/// Largest believable speed through the water, m/s.
pub const MAX_SPEED_MPS: f64 = 20.0;

fn covariance_problem<const N: usize>(c: &[[f64; N]; N], max_std: f64) -> Option<String> {
    if !c.iter().flatten().all(|v| v.is_finite()) {
        return Some("has a non-finite entry".into());
    }
    for i in 0..N {
        if c[i][i] <= 0.0 {
            return Some(format!("variance {i} is not positive"));
        }
        if c[i][i].sqrt() > max_std {
            return Some(format!(
                "standard deviation {i} is {:.3}, above {max_std}",
                c[i][i].sqrt()
            ));
        }
        for j in 0..i {
            if (c[i][j] - c[j][i]).abs() > 1e-12 * (1.0 + c[i][j].abs()) {
                return Some("is not symmetric".into());
            }
        }
    }
    let m = nalgebra::SMatrix::<f64, N, N>::from_fn(|i, j| c[i][j]);
    if m.cholesky().is_none() {
        return Some("is not positive definite".into());
    }
    None
}

impl WireMessage for NavState {
    const KIND: MessageKind = MessageKind::NavState;
    fn validate(&self) -> Result<(), (&'static str, String)> {
        if let Some(d) = &self.depth {
            let (lo, hi) = DEPTH_RANGE_M;
            if !(d.depth_m.is_finite() && (lo..=hi).contains(&d.depth_m)) {
                return Err((
                    "depth.depth_m",
                    format!("{} m is outside {lo}..{hi} m", d.depth_m),
                ));
            }
            if !(d.std_m.is_finite() && d.std_m > 0.0 && d.std_m <= 100.0) {
                return Err(("depth.std_m", format!("{} m must be in (0, 100]", d.std_m)));
            }
        }
        if let Some(t) = &self.tilt {
            if !(t.roll_rad.is_finite() && t.roll_rad.abs() <= std::f64::consts::PI) {
                return Err(("tilt.roll_rad", format!("{} is outside ±π", t.roll_rad)));
            }
            if !(t.pitch_rad.is_finite() && t.pitch_rad.abs() <= std::f64::consts::FRAC_PI_2) {
                return Err(("tilt.pitch_rad", format!("{} is outside ±π/2", t.pitch_rad)));
            }
            if let Some(p) = covariance_problem(&t.covariance, 1.0) {
                return Err(("tilt.covariance", p));
            }
        }
        if let Some(h) = &self.heading {
            if !(h.yaw_rad.is_finite() && h.yaw_rad.abs() <= std::f64::consts::PI) {
                return Err(("heading.yaw_rad", format!("{} is outside ±π", h.yaw_rad)));
            }
            if !(h.std_rad.is_finite() && h.std_rad > 0.0 && h.std_rad <= std::f64::consts::PI) {
                return Err((
                    "heading.std_rad",
                    format!("{} must be in (0, π]", h.std_rad),
                ));
            }
        }
        if let Some(v) = &self.velocity {
            let speed = v.velocity_mps.iter().map(|x| x * x).sum::<f64>().sqrt();
            if !(speed.is_finite() && speed <= MAX_SPEED_MPS) {
                return Err((
                    "velocity.velocity_mps",
                    format!("speed {speed} m/s is not finite or above {MAX_SPEED_MPS} m/s"),
                ));
            }
            if let Some(p) = covariance_problem(&v.covariance, MAX_SPEED_MPS) {
                return Err(("velocity.covariance", p));
            }
        }
        Ok(())
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::geometry::pose_from_xyz_rpy;

    fn state() -> NavState {
        NavState {
            vehicle: 15,
            stamp_ns: 1_000,
            depth: Some(Depth {
                depth_m: 5.0,
                std_m: 0.02,
            }),
            tilt: Some(Tilt {
                roll_rad: 0.1,
                pitch_rad: -0.05,
                covariance: [[1e-5, 0.0], [0.0, 1e-5]],
            }),
            heading: Some(Heading {
                yaw_rad: 1.0,
                std_rad: 0.03,
            }),
            velocity: Some(BodyVelocity {
                velocity_mps: [0.5, 0.0, 0.0],
                covariance: [[1e-4, 0.0, 0.0], [0.0, 1e-4, 0.0], [0.0, 0.0, 1e-4]],
            }),
        }
    }

    #[test]
    fn gravity_in_body_is_the_world_down_axis_seen_from_the_body() {
        for (r, p, y) in [(0.0, 0.0, 0.0), (0.3, -0.2, 1.0), (-1.0, 0.7, -2.5)] {
            let world_from_body = pose_from_xyz_rpy([0.0; 3], [r, p, y]);
            let want = world_from_body.rotation.inverse() * Vector3::z();
            assert!((gravity_in_body(r, p) - want).norm() < 1e-12, "{r} {p} {y}");
        }
    }

    #[test]
    fn a_valid_state_passes_and_each_bad_field_is_named() {
        assert_eq!(state().validate(), Ok(()));
        let mut s = state();
        s.depth = Some(Depth {
            depth_m: f64::NAN,
            std_m: 0.02,
        });
        assert_eq!(s.validate().unwrap_err().0, "depth.depth_m");
        let mut s = state();
        s.depth = Some(Depth {
            depth_m: 3.0,
            std_m: 0.0,
        });
        assert_eq!(s.validate().unwrap_err().0, "depth.std_m");
        let mut s = state();
        s.tilt.as_mut().unwrap().pitch_rad = 2.0;
        assert_eq!(s.validate().unwrap_err().0, "tilt.pitch_rad");
        let mut s = state();
        s.tilt.as_mut().unwrap().covariance = [[1e-5, 1e-3], [1e-3, 1e-5]];
        let (field, why) = s.validate().unwrap_err();
        assert_eq!(field, "tilt.covariance");
        assert!(why.contains("positive definite"), "{why}");
        let mut s = state();
        s.heading.as_mut().unwrap().std_rad = -1.0;
        assert_eq!(s.validate().unwrap_err().0, "heading.std_rad");
        let mut s = state();
        s.velocity.as_mut().unwrap().velocity_mps = [50.0, 0.0, 0.0];
        assert_eq!(s.validate().unwrap_err().0, "velocity.velocity_mps");
        // Each part may be absent.
        let bare = NavState {
            depth: None,
            tilt: None,
            heading: None,
            velocity: None,
            ..state()
        };
        assert_eq!(bare.validate(), Ok(()));
    }

    #[test]
    fn the_largest_tilt_deviation_is_the_covariances_largest_eigenvalue() {
        let t = Tilt {
            roll_rad: 0.0,
            pitch_rad: 0.0,
            covariance: [[4e-4, 0.0], [0.0, 1e-4]],
        };
        assert!((t.max_std_rad() - 0.02).abs() < 1e-12);
        let t = Tilt {
            covariance: [[2e-4, 1e-4], [1e-4, 2e-4]],
            ..t
        };
        assert!((t.max_std_rad() - 3e-4f64.sqrt()).abs() < 1e-12);
    }
}
