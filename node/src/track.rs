//! A per-target constant-velocity tracker on SE(3), so a node can bridge
//! short occlusions (the paper names occlusion as its main limitation, §6.3).
//!
//! Error-state Kalman filter: the nominal pose is kept on SE(3); the state
//! is `x = (ξ, v)` — the pose error in shoal's convention (`δt`, `δθ`, see
//! `proto::geometry`) and its rate — with `F = [[I, dt·I], [0, I]]`, white
//! acceleration noise, and the PnP covariance as the measurement noise.
//! Measurements are passed through untouched to fusion (the filter's output
//! is correlated in time, and fusion assumes independent observations);
//! only when a target goes unseen does the node publish the filter's
//! prediction, flagged `predicted`, for at most `max_gap_s`.

use nalgebra::{SMatrix, SVector};
use shoal_proto::geometry::{difference, perturb, Cov6, Pose};

type M12 = SMatrix<f64, 12, 12>;
type V12 = SVector<f64, 12>;

/// Tracker tuning.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct TrackParams {
    /// Acceleration noise density, translation (m/s² per √Hz).
    pub accel_noise_m: f64,
    /// Angular acceleration noise density (rad/s² per √Hz).
    pub accel_noise_rad: f64,
    /// Longest occlusion bridged by predictions (s).
    pub max_gap_s: f64,
}

impl Default for TrackParams {
    fn default() -> Self {
        // AUVs of the paper's size accelerate gently: ~0.2 m/s², ~0.2 rad/s².
        Self {
            accel_noise_m: 0.2,
            accel_noise_rad: 0.2,
            max_gap_s: 1.0,
        }
    }
}

/// One tracked relative pose.
#[derive(Debug, Clone)]
pub struct Track {
    pose: Pose,
    p: M12,
    /// `(v, ω)` in the convention of `ξ`.
    velocity: SVector<f64, 6>,
    last_measured_ns: u64,
    stamp_ns: u64,
}

impl Track {
    /// Start a track at a measurement, velocity unknown (large prior).
    pub fn new(pose: Pose, cov: Cov6, stamp_ns: u64) -> Track {
        let mut p = M12::zeros();
        p.fixed_view_mut::<6, 6>(0, 0).copy_from(&cov);
        for i in 6..9 {
            p[(i, i)] = 0.5f64.powi(2); // up to ~0.5 m/s relative speed
        }
        for i in 9..12 {
            p[(i, i)] = 0.5f64.powi(2); // ~0.5 rad/s
        }
        Track {
            pose,
            p,
            velocity: SVector::zeros(),
            last_measured_ns: stamp_ns,
            stamp_ns,
        }
    }

    /// The filter's pose and covariance predicted to `stamp_ns`
    /// (without changing the track).
    pub fn predict(&self, stamp_ns: u64, params: &TrackParams) -> (Pose, Cov6) {
        let (x, p) = self.propagated(stamp_ns, params);
        let pose = perturb(&self.pose, &x.fixed_rows::<6>(0).into_owned());
        (pose, p.fixed_view::<6, 6>(0, 0).into_owned())
    }

    fn propagated(&self, stamp_ns: u64, params: &TrackParams) -> (V12, M12) {
        let dt = stamp_ns.saturating_sub(self.stamp_ns) as f64 * 1e-9;
        let mut f = M12::identity();
        for i in 0..6 {
            f[(i, i + 6)] = dt;
        }
        let mut x = V12::zeros();
        x.fixed_rows_mut::<6>(6).copy_from(&self.velocity);
        let x = f * x;
        // Discrete white-acceleration noise per axis: [[dt³/3, dt²/2], [dt²/2, dt]]·q².
        let mut q = M12::zeros();
        for i in 0..6 {
            let s2 = if i < 3 {
                params.accel_noise_m.powi(2)
            } else {
                params.accel_noise_rad.powi(2)
            };
            q[(i, i)] = s2 * dt.powi(3) / 3.0;
            q[(i, i + 6)] = s2 * dt.powi(2) / 2.0;
            q[(i + 6, i)] = s2 * dt.powi(2) / 2.0;
            q[(i + 6, i + 6)] = s2 * dt;
        }
        (x, f * self.p * f.transpose() + q)
    }

    /// Fuse a measurement taken at `stamp_ns`. Measurements older than the
    /// track are ignored (returns false).
    pub fn update(&mut self, pose: &Pose, cov: &Cov6, stamp_ns: u64, params: &TrackParams) -> bool {
        if stamp_ns < self.stamp_ns {
            return false;
        }
        let (x_pred, p_pred) = self.propagated(stamp_ns, params);
        let nominal = perturb(&self.pose, &x_pred.fixed_rows::<6>(0).into_owned());
        let innovation = difference(pose, &nominal);
        let s = p_pred.fixed_view::<6, 6>(0, 0).into_owned() + cov;
        let Some(s_inv) = s.try_inverse() else {
            return false;
        };
        let k = p_pred.fixed_view::<12, 6>(0, 0).into_owned() * s_inv;
        let mut x = V12::zeros();
        x.fixed_rows_mut::<6>(6)
            .copy_from(&x_pred.fixed_rows::<6>(6));
        let x = x + k * innovation;
        let mut h = SMatrix::<f64, 6, 12>::zeros();
        h.fixed_view_mut::<6, 6>(0, 0).copy_from(&Cov6::identity());
        let i_kh = M12::identity() - k * h;
        // Joseph form keeps P symmetric positive definite.
        let p = i_kh * p_pred * i_kh.transpose() + k * cov * k.transpose();
        self.pose = perturb(&nominal, &x.fixed_rows::<6>(0).into_owned());
        self.velocity = x.fixed_rows::<6>(6).into_owned();
        self.p = (p + p.transpose()) * 0.5;
        // The pose error is folded into the nominal pose (error state reset to zero).
        self.stamp_ns = stamp_ns;
        self.last_measured_ns = stamp_ns;
        true
    }

    /// Time of the newest measurement.
    pub fn last_measured_ns(&self) -> u64 {
        self.last_measured_ns
    }

    /// Can this track still be bridged at `stamp_ns`?
    pub fn bridges(&self, stamp_ns: u64, params: &TrackParams) -> bool {
        stamp_ns > self.last_measured_ns
            && (stamp_ns - self.last_measured_ns) as f64 * 1e-9 <= params.max_gap_s
    }

    /// Estimated relative velocity `(v, ω)`.
    pub fn velocity(&self) -> SVector<f64, 6> {
        self.velocity
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use shoal_proto::geometry::pose_from_xyz_rpy;

    fn truth(t_s: f64) -> Pose {
        // 0.2 m/s along x, slow yaw.
        pose_from_xyz_rpy([1.0 + 0.2 * t_s, 0.5, 0.0], [0.0, 0.0, 0.05 * t_s])
    }

    #[test]
    fn bridges_an_occlusion_by_constant_velocity() {
        let params = TrackParams::default();
        let cov = Cov6::identity() * 1e-6;
        let mut track = Track::new(truth(0.0), cov, 0);
        for k in 1..=20 {
            let t = k as f64 * 0.1;
            assert!(track.update(&truth(t), &cov, (t * 1e9) as u64, &params));
        }
        // Occluded for 0.5 s: the prediction follows the motion.
        let (pred, pcov) = track.predict(2_500_000_000, &params);
        let err = difference(&pred, &truth(2.5));
        assert!(
            err.fixed_rows::<3>(0).norm() < 0.01,
            "translation error {}",
            err.fixed_rows::<3>(0).norm()
        );
        assert!(
            err.fixed_rows::<3>(3).norm() < 0.005,
            "rotation error {}",
            err.fixed_rows::<3>(3).norm()
        );
        // And its uncertainty has grown beyond the measurements'.
        assert!(pcov[(0, 0)] > cov[(0, 0)]);
        assert!(track.bridges(2_500_000_000, &params));
        assert!(!track.bridges(3_500_000_000, &params));
    }

    #[test]
    fn stale_measurements_are_ignored() {
        let params = TrackParams::default();
        let cov = Cov6::identity() * 1e-6;
        let mut track = Track::new(truth(1.0), cov, 1_000_000_000);
        assert!(!track.update(&truth(0.5), &cov, 500_000_000, &params));
    }
}
