//! Step 1b of the solve: every frame hypothesis checked against both
//! vehicles' own navigation (`crate::nav`): gravity (roll/pitch), depth and
//! heading.
//! A hypothesis that fails is taken out of its frame before the groups are
//! formed, and its verdict is the reason it failed.

use super::frames::Frame;
use crate::consistency::Candidate;
use crate::nav::{NavAt, NavParams, NavWindow};
use crate::seconds_to_ns;
use nalgebra::{Matrix3, SymmetricEigen, UnitQuaternion};
use proto::geometry::wrap_angle;
use proto::RejectReason;

/// Per frame and hypothesis, the nav verdict (`None`: passed or not checked).
pub(crate) type NavVerdicts = Vec<[Option<RejectReason>; 2]>;

/// What the checks did.
#[derive(Debug, Clone, Copy, Default, PartialEq, Eq)]
pub(crate) struct NavCheckStats {
    /// Hypotheses checked against gravity (both vehicles had a tilt).
    pub tilt_checked: usize,
    /// Hypotheses checked against depth (both had a depth, the observer a tilt).
    pub depth_checked: usize,
    /// Hypotheses checked against heading (both had a heading and a tilt).
    pub heading_checked: usize,
}

fn largest_eigenvalue(m: Matrix3<f64>) -> f64 {
    SymmetricEigen::new((m + m.transpose()) * 0.5)
        .eigenvalues
        .max()
        .max(0.0)
}

/// The verdict on one hypothesis given the observer's and the target's nav.
fn check_one(
    c: &Candidate,
    observer: &NavAt<'_>,
    target: &NavAt<'_>,
    p: &NavParams,
    stats: &mut NavCheckStats,
) -> Option<RejectReason> {
    let rotation_var = largest_eigenvalue(c.covariance.fixed_view::<3, 3>(3, 3).into_owned());
    let tilt_var = |n: &NavAt<'_>| {
        n.state
            .tilt
            .map(|t| t.max_std_rad().powi(2) + (n.gap_s * p.tilt_rate_rad_per_s).powi(2))
    };
    let (o_tilt, t_tilt) = (observer.state.tilt, target.state.tilt);
    if let (Some(ot), Some(tt), Some(ov), Some(tv)) =
        (o_tilt, t_tilt, tilt_var(observer), tilt_var(target))
    {
        stats.tilt_checked += 1;
        let predicted = c.a_from_b.rotation.inverse() * ot.gravity_in_body();
        let angle = predicted.angle(&tt.gravity_in_body());
        let var = (ov + tv + rotation_var).max(p.min_tilt_std_rad.powi(2));
        if angle * angle / var > p.tilt_gate_chi2 {
            return Some(RejectReason::Gravity);
        }
    }
    if let (Some(ot), Some(ov), Some(od), Some(td)) = (
        o_tilt,
        tilt_var(observer),
        observer.state.depth,
        target.state.depth,
    ) {
        stats.depth_checked += 1;
        let depth_var = |n: &NavAt<'_>, std: f64| std * std + (n.gap_s * p.depth_rate_mps).powi(2);
        let t = c.a_from_b.translation.vector;
        let below = ot.gravity_in_body().dot(&t);
        let residual = below - (td.depth_m - od.depth_m);
        let translation_var =
            largest_eigenvalue(c.covariance.fixed_view::<3, 3>(0, 0).into_owned());
        let var = (depth_var(observer, od.std_m)
            + depth_var(target, td.std_m)
            + translation_var
            + t.norm_squared() * ov)
            .max(p.min_depth_std_m.powi(2));
        if residual * residual / var > p.depth_gate_chi2 {
            return Some(RejectReason::Depth);
        }
    }
    if let (Some(ot), Some(oh), Some(th), Some(o_yaw), Some(t_yaw), Some(ov)) = (
        o_tilt,
        observer.state.heading,
        target.state.heading,
        observer.yaw_at_frame(),
        target.yaw_at_frame(),
        tilt_var(observer),
    ) {
        stats.heading_checked += 1;
        // The target's attitude in the world through the observer's own,
        // then its yaw against the target's compass; both compasses carried
        // to the frame's time by the turn their samples show (a vehicle
        // turns faster than it rolls: 18° in the 0.45 s to a sample at
        // 40°/s), what is left of the gap's motion bounded by the tilt rate.
        let world_from_observer =
            UnitQuaternion::from_euler_angles(ot.roll_rad, ot.pitch_rad, o_yaw);
        let (_, _, yaw) = (world_from_observer * c.a_from_b.rotation).euler_angles();
        let residual = wrap_angle(yaw - t_yaw);
        let heading_var =
            |n: &NavAt<'_>, std: f64| std * std + (n.gap_s * p.tilt_rate_rad_per_s).powi(2);
        let var = (heading_var(observer, oh.std_rad)
            + heading_var(target, th.std_rad)
            + rotation_var
            + ov)
            .max(p.min_tilt_std_rad.powi(2));
        if residual * residual / var > p.heading_gate_chi2 {
            return Some(RejectReason::Heading);
        }
    }
    None
}

/// Check every frame hypothesis against the nav of its two vehicles at the
/// frame's capture; a hypothesis that fails is removed from `frames` and its
/// reason returned. Frames without nav for both vehicles are left alone.
pub(crate) fn check(
    frames: &mut [Frame],
    nav: &NavWindow,
    params: &NavParams,
) -> (NavVerdicts, NavCheckStats) {
    let mut verdicts: NavVerdicts = vec![[None, None]; frames.len()];
    let mut stats = NavCheckStats::default();
    if !params.enabled {
        return (verdicts, stats);
    }
    let max_gap_ns = seconds_to_ns(params.max_gap_s);
    for (f, verdict) in frames.iter_mut().zip(&mut verdicts) {
        let (Some(o), Some(t)) = (
            nav.at(f.observer, f.stamp_ns, max_gap_ns),
            nav.at(f.target, f.stamp_ns, max_gap_ns),
        ) else {
            continue;
        };
        for h in 0..2 {
            let Some(c) = &f.hyps[h] else { continue };
            if let Some(reason) = check_one(c, &o, &t, params, &mut stats) {
                verdict[h] = Some(reason);
                f.hyps[h] = None;
            }
        }
    }
    (verdicts, stats)
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::solve::testing::{frame, paper_fleet, LIMITS, S};
    use proto::geometry::{pose_from_xyz_rpy, Pose};
    use proto::nav::{Depth, Heading, NavState, Tilt};
    use proto::VehicleId;

    /// Nav of a vehicle whose `world_from_body` is `pose`, 0.2° IMUs, 2 cm
    /// depth, no compass.
    fn nav_of(vehicle: VehicleId, pose: &Pose, stamp_ns: u64) -> NavState {
        let (roll, pitch, _) = pose.rotation.euler_angles();
        let v = 0.2f64.to_radians().powi(2);
        NavState {
            vehicle,
            stamp_ns,
            depth: Some(Depth {
                depth_m: pose.translation.z,
                std_m: 0.02,
            }),
            tilt: Some(Tilt {
                roll_rad: roll,
                pitch_rad: pitch,
                covariance: [[v, 0.0], [0.0, v]],
            }),
            heading: None,
            velocity: None,
        }
    }

    /// `nav_of` with a compass of 1.5°.
    fn with_compass(mut n: NavState, pose: &Pose) -> NavState {
        n.heading = Some(Heading {
            yaw_rad: pose.rotation.euler_angles().2,
            std_rad: 1.5f64.to_radians(),
        });
        n
    }

    fn window(navs: &[NavState]) -> NavWindow {
        let fleet = paper_fleet();
        let mut w = NavWindow::default();
        for n in navs {
            w.admit(&fleet, *n, n.vehicle, 10 * S, &LIMITS, 512)
                .expect("admitted");
        }
        w
    }

    #[test]
    fn the_flip_twin_fails_gravity_and_the_truth_passes() {
        // 10 pitched 5°, 15 rolled 10°, 2 m ahead and 0.3 m deeper.
        let w10 = pose_from_xyz_rpy([0.0, 0.0, 5.0], [0.0, 0.087, 0.4]);
        let w15 = pose_from_xyz_rpy([2.0, 0.5, 5.3], [0.17, 0.0, 0.2]);
        let truth = w10.inverse() * w15;
        // A twin: the target tilted 30° more about the line of sight's normal.
        let twin = truth * pose_from_xyz_rpy([0.0; 3], [0.0, 0.52, 0.0]);
        let nav = window(&[nav_of(10, &w10, 10 * S), nav_of(15, &w15, 10 * S)]);
        let mut frames = vec![
            frame(0, 10, 15, 10 * S, truth, Some(twin)),
            frame(1, 10, 15, 10 * S, twin, Some(truth)),
        ];
        let (verdicts, stats) = check(&mut frames, &nav, &NavParams::default());
        assert_eq!(
            verdicts,
            vec![
                [None, Some(RejectReason::Gravity)],
                [Some(RejectReason::Gravity), None]
            ]
        );
        assert!(frames[0].hyps[0].is_some() && frames[0].hyps[1].is_none());
        assert!(frames[1].hyps[0].is_none() && frames[1].hyps[1].is_some());
        assert_eq!(stats.tilt_checked, 4);
        // Switched off, nothing is checked.
        let mut frames = vec![frame(0, 10, 15, 10 * S, twin, Some(truth))];
        let off = NavParams {
            enabled: false,
            ..NavParams::default()
        };
        let (verdicts, _) = check(&mut frames, &nav, &off);
        assert_eq!(verdicts, vec![[None, None]]);
        assert!(frames[0].hyps[0].is_some());
    }

    #[test]
    fn a_target_at_the_wrong_depth_fails_and_a_twin_within_noise_passes() {
        let w10 = pose_from_xyz_rpy([0.0, 0.0, 5.0], [0.0, 0.0, 0.0]);
        let w15 = pose_from_xyz_rpy([2.0, 0.0, 5.0], [0.0, 0.0, 0.0]);
        let truth = w10.inverse() * w15;
        // Where another vehicle 0.5 m deeper would be (a misread ID).
        let deeper = pose_from_xyz_rpy([2.0, 0.0, 0.5], [0.0; 3]);
        // A "twin" 2° off: inside the 1° floor's gate (4.3°), kept.
        let near = truth * pose_from_xyz_rpy([0.0; 3], [0.0, 2f64.to_radians(), 0.0]);
        let nav = window(&[nav_of(10, &w10, 10 * S), nav_of(15, &w15, 10 * S)]);
        let mut frames = vec![frame(0, 10, 15, 10 * S, deeper, Some(near))];
        let (verdicts, stats) = check(&mut frames, &nav, &NavParams::default());
        assert_eq!(verdicts, vec![[Some(RejectReason::Depth), None]]);
        assert_eq!(stats.depth_checked, 2);
    }

    #[test]
    fn without_both_vehicles_nav_near_the_frame_nothing_is_checked() {
        let w10 = pose_from_xyz_rpy([0.0, 0.0, 5.0], [0.0; 3]);
        let w15 = pose_from_xyz_rpy([2.0, 0.0, 5.0], [0.3, 0.0, 0.0]);
        let wrong = w10.inverse() * w15 * pose_from_xyz_rpy([0.0; 3], [0.6, 0.0, 0.0]);
        // 15's nav only, and 10's 0.6 s before the frame (beyond the 0.5 s gap).
        let nav = window(&[
            nav_of(15, &w15, 10 * S),
            nav_of(10, &w10, 10 * S - 6 * S / 10),
        ]);
        let mut frames = vec![frame(0, 10, 15, 10 * S, wrong, None)];
        let (verdicts, stats) = check(&mut frames, &nav, &NavParams::default());
        assert_eq!(verdicts, vec![[None, None]]);
        assert_eq!(stats, NavCheckStats::default());
    }

    #[test]
    fn a_twin_turned_about_the_vertical_passes_gravity_and_fails_the_compass() {
        // Both level, 15 seen 40° off its face in azimuth: the twin is the
        // target turned about the vertical.
        let w10 = pose_from_xyz_rpy([0.0, 0.0, 5.0], [0.0, 0.0, 0.0]);
        let w15 = pose_from_xyz_rpy([2.0, 0.0, 5.0], [0.0, 0.0, 0.7]);
        let truth = w10.inverse() * w15;
        let twin = truth * pose_from_xyz_rpy([0.0; 3], [0.0, 0.0, -0.5]);
        let tilt_only = window(&[nav_of(10, &w10, 10 * S), nav_of(15, &w15, 10 * S)]);
        let mut frames = vec![frame(0, 10, 15, 10 * S, twin, Some(truth))];
        let (verdicts, stats) = check(&mut frames, &tilt_only, &NavParams::default());
        assert_eq!(verdicts, vec![[None, None]], "gravity cannot tell");
        assert_eq!((stats.tilt_checked, stats.heading_checked), (2, 0));
        let compass = window(&[
            with_compass(nav_of(10, &w10, 10 * S), &w10),
            with_compass(nav_of(15, &w15, 10 * S), &w15),
        ]);
        let mut frames = vec![frame(0, 10, 15, 10 * S, twin, Some(truth))];
        let (verdicts, stats) = check(&mut frames, &compass, &NavParams::default());
        assert_eq!(verdicts, vec![[Some(RejectReason::Heading), None]]);
        assert_eq!(stats.heading_checked, 2);
        // Across ±π: a compass at 179° and a hypothesis at -179° agree.
        let w15 = pose_from_xyz_rpy([2.0, 0.0, 5.0], [0.0, 0.0, 179f64.to_radians()]);
        let near =
            w10.inverse() * pose_from_xyz_rpy([2.0, 0.0, 5.0], [0.0, 0.0, -179f64.to_radians()]);
        let compass = window(&[
            with_compass(nav_of(10, &w10, 10 * S), &w10),
            with_compass(nav_of(15, &w15, 10 * S), &w15),
        ]);
        let mut frames = vec![frame(0, 10, 15, 10 * S, near, None)];
        let (verdicts, _) = check(&mut frames, &compass, &NavParams::default());
        assert_eq!(verdicts, vec![[None, None]]);
    }

    #[test]
    fn a_target_turning_between_its_compass_samples_keeps_its_true_hypothesis() {
        // 15 turns at 80°/s with nav once a second; the frame is 0.45 s
        // before its nearest sample, so its heading then is 36° short of
        // that sample's. Carried back by the turn the samples show, the
        // compass keeps the truth and still refuses a twin 60° about the
        // vertical.
        let yaw_at = |t_s: f64| 0.2 + 80f64.to_radians() * t_s;
        let w10 = pose_from_xyz_rpy([0.0, 0.0, 5.0], [0.0; 3]);
        let w15_at = |t_s: f64| pose_from_xyz_rpy([2.0, 0.0, 5.0], [0.0, 0.0, yaw_at(t_s)]);
        let truth = w10.inverse() * w15_at(9.55);
        let twin = truth * pose_from_xyz_rpy([0.0; 3], [0.0, 0.0, -60f64.to_radians()]);
        let nav = window(&[
            with_compass(nav_of(10, &w10, 9 * S), &w10),
            with_compass(nav_of(10, &w10, 10 * S), &w10),
            with_compass(nav_of(15, &w15_at(9.0), 9 * S), &w15_at(9.0)),
            with_compass(nav_of(15, &w15_at(10.0), 10 * S), &w15_at(10.0)),
        ]);
        let stamp = 9 * S + 55 * S / 100;
        let mut frames = vec![frame(0, 10, 15, stamp, truth, Some(twin))];
        let (verdicts, stats) = check(&mut frames, &nav, &NavParams::default());
        assert_eq!(verdicts, vec![[None, Some(RejectReason::Heading)]]);
        assert_eq!(stats.heading_checked, 2);
        // With only the nearest sample the turn is unknown (the tilt rate,
        // 10°/s, bounds it) and the true hypothesis, 36° off, is refused.
        let nav = window(&[
            with_compass(nav_of(10, &w10, 10 * S), &w10),
            with_compass(nav_of(15, &w15_at(10.0), 10 * S), &w15_at(10.0)),
        ]);
        let mut frames = vec![frame(0, 10, 15, stamp, truth, None)];
        let (verdicts, _) = check(&mut frames, &nav, &NavParams::default());
        assert_eq!(verdicts, vec![[Some(RejectReason::Heading), None]]);
    }
}
