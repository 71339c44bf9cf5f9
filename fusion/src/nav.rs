//! The vehicles' own navigation in fusion: each vehicle's [`NavState`]s
//! (depth, roll/pitch, velocity) kept over the window, and the test that
//! settles the planar flip by gravity.
//!
//! A marker seen by one camera has two poses that explain its corners almost
//! equally well (IPPE's twins); they differ by a tilt of the marker about the
//! line of sight. Without navigation, fusion settles the choice by votes in
//! triangles and by the previous map's attitude ([`crate::consistency`]). With
//! both vehicles' roll and pitch, it does not have to guess: hypothesis
//! `observer_from_target` predicts gravity in the target's body as
//! `Rᵀ·g_observer`, and the target's IMU measures it. The angle between the
//! two, over the combined standard deviation (both IMUs, the hypothesis'
//! own rotation, the time between the frame and the nav samples), is gated
//! with χ²₂; a hypothesis that fails is rejected as
//! [`RejectReason::Gravity`](proto::RejectReason::Gravity). Likewise the
//! target's depth below the observer, `g_observerᵀ·t`, against the pressure
//! sensors' difference (χ²₁): [`RejectReason::Depth`](proto::RejectReason::Depth)
//! (a misread ID puts the target where another vehicle is, rarely at its
//! depth). Gravity cannot see a twin turned about the vertical (a marker seen
//! obliquely in azimuth from a level vehicle); when both vehicles also send a
//! heading, the target's heading through the observer's attitude is gated
//! against its own compass (χ²₁): [`RejectReason::Heading`](proto::RejectReason::Heading),
//! each compass carried to the frame's capture by the turn rate its samples
//! show (`NavAt::yaw_at_frame`).
//! Vehicles without nav data are settled as before.

use crate::window::Admission;
use proto::config::Fleet;
use proto::nav::NavState;
use proto::{VehicleId, WireMessage};
use serde::{Deserialize, Serialize};
use std::collections::BTreeMap;

/// Settings of the nav checks.
#[derive(Debug, Clone, Copy, PartialEq, Serialize, Deserialize)]
pub struct NavParams {
    /// Use nav data at all (default true; false: the votes and the attitude prior alone).
    pub enabled: bool,
    /// A nav sample is used for a frame captured at most this far from it, s (default 0.5).
    pub max_gap_s: f64,
    /// Tilt change allowed per second between a frame and its nav sample, rad/s (default 10°/s).
    pub tilt_rate_rad_per_s: f64,
    /// Depth change allowed per second between a frame and its nav sample, m/s (default 0.5).
    pub depth_rate_mps: f64,
    /// Floor on the combined tilt standard deviation, rad (default 1°): an
    /// optimistic PnP covariance must not turn a true hypothesis away.
    pub min_tilt_std_rad: f64,
    /// Floor on the combined depth standard deviation, m (default 2 cm).
    pub min_depth_std_m: f64,
    /// Gate on the squared tilt residual over its variance (default 18.42 = χ²₂ at 99.99 %).
    pub tilt_gate_chi2: f64,
    /// Gate on the squared depth residual over its variance (default 15.14 = χ²₁ at 99.99 %).
    pub depth_gate_chi2: f64,
    /// Gate on the squared heading residual over its variance (default 15.14 = χ²₁ at 99.99 %).
    pub heading_gate_chi2: f64,
    /// Samples kept per vehicle at most (default 512; the oldest go first).
    pub max_samples_per_vehicle: usize,
    /// A vehicle no camera sees is carried forward by odometry (both its own
    /// and the reference's nav with velocity and heading) for at most this
    /// long after it was last localized, s (default 10; 0: never), state `Predicted`.
    #[serde(default = "default_max_predict_s")]
    pub max_predict_s: f64,
    /// A localized (`Live`) vehicle's pose is carried by the same odometry
    /// from the newest frame it rests on to the map's time, its covariance
    /// grown likewise, so that a map published between camera frames says
    /// where the vehicles are now (default false: as of their frames).
    /// Without both vehicles' odometry over the interval the pose is left as solved.
    /// Off by default: the heading change is the difference of two compass
    /// samples, and their noise swings a vehicle metres away by it, which
    /// costs a formation holding still more than it gains (median 2.6 → 20 mm
    /// with 0.5° of compass noise) and pays only from ~0.1 m/s of relative
    /// motion (47 → 32 mm at ~0.2 m/s; docs/results.md, nav). Turn it on for
    /// a manoeuvring fleet or a smooth (filtered) heading.
    #[serde(default = "default_propagate_live")]
    pub propagate_live: bool,
    /// Solve the window as a factor graph over time: a state per vehicle
    /// and time slot, odometry between-factors from each vehicle's own nav
    /// (velocity and heading), the marker edges at their slots; the map is
    /// the states at the newest accepted frame (`solve/smooth.rs`).
    /// Vehicles without odometry keep one state. Default false.
    #[serde(default)]
    pub odometry_factors: bool,
    /// The time slots' length, s (default 0.1; at least 1 ms): frames within
    /// half a slot of its time share a state, moved to it by their vehicles' odometry.
    #[serde(default = "default_odometry_slot_s")]
    pub odometry_slot_s: f64,
    /// The graph over time's budget of states (default 240): each vehicle
    /// over time keeps `max(1, budget / vehicles)` states, its state at the
    /// newest accepted frame and its newest slots with a frame; older frames
    /// are left out of it (3 vehicles: 80 states, the whole window; 100
    /// vehicles: 2). The solve's cost grows far faster
    /// than the states (a vehicles × slots lattice: 100 vehicles, 2 s of
    /// 10 Hz frames: ~20 ms at 200 states, ~100 ms at 400, ~0.7 s at 800;
    /// docs/results.md, nav).
    #[serde(default = "default_odometry_max_states")]
    pub odometry_max_states: usize,
}

fn default_odometry_max_states() -> usize {
    240
}

fn default_odometry_slot_s() -> f64 {
    0.1
}

fn default_propagate_live() -> bool {
    false
}

fn default_max_predict_s() -> f64 {
    10.0
}

impl Default for NavParams {
    fn default() -> Self {
        Self {
            enabled: true,
            max_gap_s: 0.5,
            tilt_rate_rad_per_s: 10f64.to_radians(),
            depth_rate_mps: 0.5,
            min_tilt_std_rad: 1f64.to_radians(),
            min_depth_std_m: 0.02,
            tilt_gate_chi2: 18.42,
            depth_gate_chi2: 15.14,
            heading_gate_chi2: 15.14,
            max_samples_per_vehicle: 512,
            max_predict_s: default_max_predict_s(),
            propagate_live: default_propagate_live(),
            odometry_factors: false,
            odometry_slot_s: default_odometry_slot_s(),
            odometry_max_states: default_odometry_max_states(),
        }
    }
}

/// Why a [`NavState`] was not admitted.
#[derive(Debug, Clone, PartialEq, Eq, thiserror::Error)]
pub enum NavRejected {
    #[error("vehicle {0} is not in the fleet")]
    UnknownVehicle(VehicleId),
    #[error("nav state of vehicle {claimed} arrived on vehicle {arrived_on}'s key")]
    SenderMismatch {
        claimed: VehicleId,
        arrived_on: VehicleId,
    },
    #[error("nav state stamped {stamp_ns} ns is older than the window")]
    Stale { stamp_ns: u64 },
    #[error("nav state stamped {stamp_ns} ns is from the future beyond the clock-skew bound")]
    ClockSkew { stamp_ns: u64 },
    #[error("nav state field {field}: {why}")]
    Invalid { field: &'static str, why: String },
}

/// The checks every nav state or span passes before it is held: its vehicle
/// is the key's (`(claimed, arrived_on)`) and in the fleet, its fields
/// valid, it begins no later than the clock-skew bound after `now_ns` and
/// ends within `window_ns` before it (`(skew, window)`).
fn admissible(
    fleet: &Fleet,
    (claimed, arrived_on): (VehicleId, VehicleId),
    valid: Result<(), (&'static str, String)>,
    (from_ns, to_ns): (u64, u64),
    now_ns: u64,
    (max_clock_skew_ns, window_ns): (u64, u64),
) -> Result<(), NavRejected> {
    if claimed != arrived_on {
        return Err(NavRejected::SenderMismatch {
            claimed,
            arrived_on,
        });
    }
    if fleet.vehicle(claimed).is_none() {
        return Err(NavRejected::UnknownVehicle(claimed));
    }
    valid.map_err(|(field, why)| NavRejected::Invalid { field, why })?;
    if from_ns > now_ns.saturating_add(max_clock_skew_ns) {
        return Err(NavRejected::ClockSkew { stamp_ns: from_ns });
    }
    if to_ns.saturating_add(window_ns) < now_ns {
        return Err(NavRejected::Stale { stamp_ns: to_ns });
    }
    Ok(())
}

/// Spacing of the samples a linked navigation span is held as ([`NavWindow::admit_span`]).
pub const LINKED_NAV_STEP_NS: u64 = 50_000_000;

/// Each vehicle's nav samples over the window, by stamp.
#[derive(Debug, Clone, Default)]
pub(crate) struct NavWindow {
    samples: BTreeMap<VehicleId, BTreeMap<u64, NavState>>,
    /// Per vehicle whose nav crosses a link ([`NavWindow::admit_span`]),
    /// its spans: `(from_ns, to_ns)` → when it arrived.
    linked: BTreeMap<VehicleId, BTreeMap<(u64, u64), u64>>,
}

/// A vehicle's nav at a frame's capture: the nearest sample and how far it is.
#[derive(Debug, Clone, Copy, PartialEq)]
pub(crate) struct NavAt<'a> {
    pub state: &'a NavState,
    pub gap_s: f64,
    /// The frame's time minus the sample's, s (`±gap_s`).
    pub offset_s: f64,
    /// The heading's turn rate between the nearest sample and the neighbour
    /// across the frame (else the one before it), rad/s, where both have a
    /// compass: the heading at the frame is the sample's turned on by it.
    pub yaw_rate_rad_per_s: Option<f64>,
}

impl NavAt<'_> {
    /// The compass heading carried to the frame's time by the turn rate the
    /// samples show (the sample's own without a rate), rad.
    pub fn yaw_at_frame(&self) -> Option<f64> {
        let h = self.state.heading?;
        Some(h.yaw_rad + self.yaw_rate_rad_per_s.unwrap_or(0.0) * self.offset_s)
    }
}

impl NavWindow {
    /// Admit `nav` (arrived on `arrived_on`'s key) at `now_ns`.
    pub fn admit(
        &mut self,
        fleet: &Fleet,
        nav: NavState,
        arrived_on: VehicleId,
        now_ns: u64,
        limits: &Admission,
        max_samples: usize,
    ) -> Result<(), NavRejected> {
        admissible(
            fleet,
            (nav.vehicle, arrived_on),
            nav.validate(),
            (nav.stamp_ns, nav.stamp_ns),
            now_ns,
            (limits.max_clock_skew_ns, limits.window_ns),
        )?;
        let list = self.samples.entry(nav.vehicle).or_default();
        list.insert(nav.stamp_ns, nav);
        while list.len() > max_samples.max(1) {
            list.pop_first();
        }
        Ok(())
    }

    /// Admit a span of `span.vehicle`'s nav that crossed a slow link (arrived
    /// on `arrived_on`'s key at `now_ns`; kept, like linked observations, for
    /// the link window) as samples every [`LINKED_NAV_STEP_NS`] across it,
    /// each stating the span's parts: the span bounds what held at every
    /// instant in it, so a frame captured within it is checked against it
    /// with no more than half a step of gap. Samples already held at those
    /// stamps (the vehicle's own, full-rate) are kept.
    pub fn admit_span(
        &mut self,
        fleet: &Fleet,
        span: &proto::compact::NavSpan,
        arrived_on: VehicleId,
        now_ns: u64,
        limits: &Admission,
        max_samples: usize,
    ) -> Result<(), NavRejected> {
        admissible(
            fleet,
            (span.vehicle, arrived_on),
            span.validate(),
            (span.from_ns, span.to_ns),
            now_ns,
            (limits.max_clock_skew_ns, limits.link_window_ns),
        )?;
        let arrived = self.linked.entry(span.vehicle).or_default();
        arrived.entry((span.from_ns, span.to_ns)).or_insert(now_ns);
        while arrived.len() > max_samples.max(1) {
            arrived.pop_first();
        }
        let list = self.samples.entry(span.vehicle).or_default();
        let mut t = span.from_ns;
        loop {
            list.entry(t).or_insert_with(|| span.state_at(t));
            if t >= span.to_ns {
                break;
            }
            t = (t + LINKED_NAV_STEP_NS).min(span.to_ns);
        }
        while list.len() > max_samples.max(1) {
            list.pop_first();
        }
        Ok(())
    }

    /// For a vehicle whose nav crosses a link, when nav usable for a frame
    /// captured at `stamp_ns` arrived: `Some(Some(t))` the earliest arrival
    /// of a span within `max_gap_ns` of it, `Some(None)` none yet; `None`
    /// for a vehicle whose nav does not cross a link.
    pub fn linked_arrival(
        &self,
        vehicle: VehicleId,
        stamp_ns: u64,
        max_gap_ns: u64,
    ) -> Option<Option<u64>> {
        let spans = self.linked.get(&vehicle)?;
        Some(
            spans
                .iter()
                .filter(|((from, to), _)| {
                    from.saturating_sub(max_gap_ns) <= stamp_ns
                        && stamp_ns <= to.saturating_add(max_gap_ns)
                })
                .map(|(_, t)| *t)
                .min(),
        )
    }

    /// Forget samples older than `keep_ns` before `now_ns`.
    pub fn evict(&mut self, now_ns: u64, keep_ns: u64) {
        let oldest = now_ns.saturating_sub(keep_ns);
        for list in self.samples.values_mut() {
            *list = list.split_off(&oldest);
        }
        self.samples.retain(|_, l| !l.is_empty());
        // A vehicle whose linked nav has all aged out no longer holds frames back.
        for spans in self.linked.values_mut() {
            spans.retain(|(_, to), _| *to >= oldest);
        }
        self.linked.retain(|_, spans| !spans.is_empty());
    }

    /// `vehicle`'s sample nearest to `stamp_ns`, if one is within `max_gap_ns`.
    pub fn at(&self, vehicle: VehicleId, stamp_ns: u64, max_gap_ns: u64) -> Option<NavAt<'_>> {
        let list = self.samples.get(&vehicle)?;
        let before = list.range(..=stamp_ns).next_back();
        let after = list.range(stamp_ns..).next();
        let gap = |s: u64| s.abs_diff(stamp_ns);
        let nearest = match (before, after) {
            (Some(b), Some(a)) => {
                if gap(*a.0) < gap(*b.0) {
                    a
                } else {
                    b
                }
            }
            (Some(x), None) | (None, Some(x)) => x,
            (None, None) => return None,
        };
        if gap(*nearest.0) > max_gap_ns {
            return None;
        }
        // The turn rate from the sample on the frame's other side, else the
        // one before the nearest.
        let other = match (before, after) {
            (Some(b), Some(a)) if a.0 != b.0 => Some(if nearest.0 == a.0 { b } else { a }),
            _ => list.range(..*nearest.0).next_back(),
        };
        let yaw_rate_rad_per_s = other.and_then(|(t, s)| {
            let (h_other, h_nearest) = (s.heading?, nearest.1.heading?);
            let dt = (i128::from(*nearest.0) - i128::from(*t)) as f64 * 1e-9;
            (dt != 0.0)
                .then(|| proto::geometry::wrap_angle(h_nearest.yaw_rad - h_other.yaw_rad) / dt)
        });
        Some(NavAt {
            state: nearest.1,
            gap_s: gap(*nearest.0) as f64 * 1e-9,
            offset_s: (i128::from(stamp_ns) - i128::from(*nearest.0)) as f64 * 1e-9,
            yaw_rate_rad_per_s,
        })
    }

    /// Samples held (all vehicles).
    pub fn len(&self) -> usize {
        self.samples.values().map(BTreeMap::len).sum()
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::solve::testing::{paper_fleet, LIMITS, S};
    use proto::nav::{Depth, Tilt};

    fn nav(vehicle: VehicleId, stamp_ns: u64) -> NavState {
        NavState {
            vehicle,
            stamp_ns,
            depth: Some(Depth {
                depth_m: 5.0,
                std_m: 0.02,
            }),
            tilt: Some(Tilt {
                roll_rad: 0.0,
                pitch_rad: 0.0,
                covariance: [[1e-5, 0.0], [0.0, 1e-5]],
            }),
            heading: None,
            velocity: None,
        }
    }

    #[test]
    fn admission_names_what_is_wrong_and_keeps_the_newest_samples() {
        let fleet = paper_fleet();
        let mut w = NavWindow::default();
        let now = 100 * S;
        let admit =
            |w: &mut NavWindow, n: NavState, on: VehicleId| w.admit(&fleet, n, on, now, &LIMITS, 3);
        assert_eq!(admit(&mut w, nav(10, now), 10), Ok(()));
        assert_eq!(
            admit(&mut w, nav(10, now), 15),
            Err(NavRejected::SenderMismatch {
                claimed: 10,
                arrived_on: 15
            })
        );
        assert_eq!(
            admit(&mut w, nav(99, now), 99),
            Err(NavRejected::UnknownVehicle(99))
        );
        assert_eq!(
            admit(&mut w, nav(10, now - 3 * S), 10),
            Err(NavRejected::Stale {
                stamp_ns: now - 3 * S
            })
        );
        assert_eq!(
            admit(&mut w, nav(10, now + S), 10),
            Err(NavRejected::ClockSkew { stamp_ns: now + S })
        );
        let mut bad = nav(10, now);
        bad.tilt.as_mut().expect("tilt").roll_rad = f64::NAN;
        assert!(matches!(
            admit(&mut w, bad, 10),
            Err(NavRejected::Invalid {
                field: "tilt.roll_rad",
                ..
            })
        ));
        for k in 1..=4 {
            admit(&mut w, nav(10, now - k * S / 10), 10).expect("admitted");
        }
        assert_eq!(w.len(), 3, "at most three samples per vehicle here");
        assert!(
            w.at(10, now - 4 * S / 10, 0).is_none(),
            "the oldest went first"
        );
    }

    #[test]
    fn the_nearest_sample_within_the_gap_is_used() {
        let fleet = paper_fleet();
        let mut w = NavWindow::default();
        let now = 100 * S;
        for t in [now - S, now - S / 2] {
            w.admit(&fleet, nav(15, t), 15, now, &LIMITS, 512)
                .expect("admitted");
        }
        let at = w.at(15, now - 6 * S / 10, S / 5).expect("a sample");
        assert_eq!(at.state.stamp_ns, now - S / 2);
        assert!((at.gap_s - 0.1).abs() < 1e-12);
        let at = w.at(15, now - 9 * S / 10, S / 5).expect("a sample");
        assert_eq!(at.state.stamp_ns, now - S);
        assert!(
            w.at(15, now, S / 5).is_none(),
            "0.5 s away is beyond the gap"
        );
        assert!(w.at(17, now, S).is_none(), "no samples of 17");
        w.evict(now, S * 3 / 4);
        assert_eq!(w.len(), 1);
    }
}

/// One vehicle's dead-reckoned pose at a nav sample: its odometry frame's
/// origin is arbitrary (where integration began, axes of the compass), only
/// differences between two points are used.
#[derive(Debug, Clone, Copy, PartialEq)]
pub(crate) struct OdoPoint {
    pub odo_from_body: proto::Pose,
    /// Position variance per axis accumulated since the origin, m².
    pub position_var: f64,
    /// Attitude variance of this sample's own roll/pitch/heading, rad².
    pub attitude_var: f64,
}

/// Each vehicle's track integrated from its nav samples that carry a tilt
/// and a heading: position advances by the attitude-rotated body velocity
/// (the last one known through a DVL dropout, with its variance grown).
#[derive(Debug, Clone, Default)]
pub(crate) struct Odometry {
    tracks: BTreeMap<VehicleId, BTreeMap<u64, OdoPoint>>,
    /// Per vehicle: the last velocity known (m/s, body) and its variance per axis.
    velocity: BTreeMap<VehicleId, (nalgebra::Vector3<f64>, f64)>,
}

/// Variance added per second of DVL dropout to the velocity carried over, (m/s)²/s.
const DROPOUT_VELOCITY_VAR_PER_S: f64 = 0.05 * 0.05;
/// A gap between nav samples longer than this breaks the track, s.
const MAX_ODOMETRY_GAP_S: f64 = 2.0;

impl Odometry {
    /// Integrate `nav` (already admitted) into its vehicle's track; samples
    /// older than the track's newest, or without tilt or heading, are left out.
    pub fn add(&mut self, nav: &NavState, keep_ns: u64, max_samples: usize) {
        let (Some(tilt), Some(heading)) = (nav.tilt, nav.heading) else {
            return;
        };
        let rotation = nalgebra::UnitQuaternion::from_euler_angles(
            tilt.roll_rad,
            tilt.pitch_rad,
            heading.yaw_rad,
        );
        let attitude_var = tilt.max_std_rad().powi(2) + heading.std_rad.powi(2);
        let track = self.tracks.entry(nav.vehicle).or_default();
        let last = track.last_key_value().map(|(t, p)| (*t, *p));
        let known = self.velocity.get(&nav.vehicle).copied();
        let point = match (last, known) {
            (Some((t, _)), _) if nav.stamp_ns <= t => return,
            (Some((t, prev)), Some((v, v_var)))
                if (nav.stamp_ns - t) as f64 * 1e-9 <= MAX_ODOMETRY_GAP_S =>
            {
                let dt = (nav.stamp_ns - t) as f64 * 1e-9;
                let step = prev.odo_from_body.rotation * v * dt;
                let mut pose = prev.odo_from_body;
                pose.translation.vector += step;
                pose.rotation = rotation;
                // Velocity noise, and the step turned by the attitude's own noise.
                let step_var = v_var * dt * dt + step.norm_squared() * prev.attitude_var;
                OdoPoint {
                    odo_from_body: pose,
                    position_var: prev.position_var + step_var,
                    attitude_var,
                }
            }
            _ => {
                // A new track (first sample, a gap, or no velocity yet).
                track.clear();
                OdoPoint {
                    odo_from_body: proto::Pose::from_parts(
                        nalgebra::Translation3::identity(),
                        rotation,
                    ),
                    position_var: 0.0,
                    attitude_var,
                }
            }
        };
        track.insert(nav.stamp_ns, point);
        let oldest = nav.stamp_ns.saturating_sub(keep_ns);
        while track
            .first_key_value()
            .is_some_and(|(t, _)| *t < oldest || track.len() > max_samples.max(2))
        {
            track.pop_first();
        }
        match nav.velocity {
            Some(v) => {
                let c = v.covariance;
                let var = c[0][0].max(c[1][1]).max(c[2][2]);
                self.velocity
                    .insert(nav.vehicle, (nalgebra::Vector3::from(v.velocity_mps), var));
            }
            None => {
                if let Some((_, var)) = self.velocity.get_mut(&nav.vehicle) {
                    *var += DROPOUT_VELOCITY_VAR_PER_S;
                }
            }
        }
    }

    /// `vehicle`'s motion from `from_ns` to `now_ns`, in its body frame at
    /// `from_ns` (`body_then_from_body_now`), with the position variance
    /// integrated over it and the two ends' attitude variances (none when
    /// both ends rest on one sample: the attitude is the same, exactly).
    /// An instant within the track is its nearest sample, if one is within
    /// `max_gap_ns`; an instant past the newest sample (nav still in flight
    /// when a map is made, or a slow nav rate) is dead-reckoned on from it by
    /// the last velocity known, attitude held, for at most
    /// [`MAX_ODOMETRY_GAP_S`], its variance grown as through a DVL dropout.
    /// `None` when either end is not covered.
    pub fn motion(
        &self,
        vehicle: VehicleId,
        from_ns: u64,
        now_ns: u64,
        max_gap_ns: u64,
    ) -> Option<(proto::Pose, f64, f64)> {
        let track = self.tracks.get(&vehicle)?;
        let (&newest_ns, &newest) = track.last_key_value()?;
        let ahead = |t: u64| {
            let ahead_s = t.checked_sub(newest_ns)? as f64 * 1e-9;
            if ahead_s > MAX_ODOMETRY_GAP_S {
                return None;
            }
            let (v, v_var) = self.velocity.get(&vehicle)?;
            let step = newest.odo_from_body.rotation * v * ahead_s;
            let mut point = newest;
            point.odo_from_body.translation.vector += step;
            point.position_var +=
                (v_var + DROPOUT_VELOCITY_VAR_PER_S * ahead_s) * ahead_s * ahead_s
                    + step.norm_squared() * newest.attitude_var;
            Some((newest_ns, point))
        };
        let near = |t: u64| {
            let before = track.range(..=t).next_back();
            let after = track.range(t..).next();
            [before, after]
                .into_iter()
                .flatten()
                .min_by_key(|(s, _)| s.abs_diff(t))
                .filter(|(s, _)| s.abs_diff(t) <= max_gap_ns)
                .map(|(s, p)| (*s, *p))
        };
        let at = |t: u64| ahead(t).or_else(|| near(t));
        let ((ta, a), (tb, b)) = (at(from_ns)?, at(now_ns)?);
        // Both ends on one sample: its attitude at both, no error between them.
        let attitude_var = if ta == tb {
            0.0
        } else {
            a.attitude_var + b.attitude_var
        };
        Some((
            a.odo_from_body.inverse() * b.odo_from_body,
            (b.position_var - a.position_var).max(0.0),
            attitude_var,
        ))
    }
}
