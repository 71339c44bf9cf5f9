//! The swarm world: N vehicles moving in a NED world with a simulation clock,
//! deterministic for a seed.
//!
//! Each vehicle is in one of three modes:
//! - [`Mode::Formation`]: it holds its slot of a scripted formation (line
//!   abreast, column, V, circle) whose reference point moves at the
//!   formation velocity; slots breathe with a slow random drift
//!   (Ornstein–Uhlenbeck), and a water current pushes everyone;
//! - [`Mode::Random`]: random manoeuvres (speed and yaw rate redrawn every
//!   5–15 s);
//! - [`Mode::Commanded`]: closed loop, the body velocity and yaw rate of the
//!   last [`SwarmWorld::apply_command`].
//!
//! Dynamics are first order: body velocity and yaw rate approach their
//! commanded values with time constants [`SwarmWorld::tau_velocity_s`] and
//! [`SwarmWorld::tau_yaw_s`]; position integrates `R(yaw)·v_body + current`.
//! Frames: world NED, body FRD (x forward, y starboard, z down); positive yaw
//! rate turns to starboard.

use crate::error::SimError;
use nalgebra::{Translation3, UnitQuaternion, Vector3};
use rand::{Rng, SeedableRng};
use rand_chacha::ChaCha8Rng;
use rand_distr::{Distribution, StandardNormal};
use shoal_proto::config::Fleet;
use shoal_proto::geometry::wrap_angle;
use shoal_proto::{Pose, VehicleCommand, VehicleId, VehicleTruth};

/// Scripted formations. All vehicles head along the formation heading
/// (north by default).
#[derive(Debug, Clone, Copy, PartialEq, Eq, Default)]
pub enum Formation {
    /// Line abreast: side by side along the world east axis, heading north,
    /// staggered along-track so side cameras face neighbours' side markers.
    /// With the paper fleet (60° cameras 0.6–0.95 m ahead of mid-body
    /// markers) neighbours see each other's markers whole from ~1.75 m apart.
    #[default]
    Line,
    /// One behind the other, `spacing_m` of water between hulls.
    Column,
    /// A leader at the apex, the others alternating behind to port and starboard at 45°.
    V,
    /// On a circle with `spacing_m` between neighbours, all heading north.
    Circle,
}

/// How a vehicle is being driven.
#[derive(Debug, Clone, Copy, PartialEq)]
pub enum Mode {
    Formation,
    Random,
    Commanded,
}

#[derive(Debug, Clone)]
struct Vehicle {
    id: VehicleId,
    position: Vector3<f64>,
    yaw: f64,
    velocity_body: Vector3<f64>,
    yaw_rate: f64,
    cmd_velocity: Vector3<f64>,
    cmd_yaw_rate: f64,
    mode: Mode,
    /// Slot in the formation frame (x along the heading, y to starboard, z down).
    slot: Vector3<f64>,
    /// Slow random offset from the slot (OU process), world frame.
    drift: Vector3<f64>,
    next_manoeuvre_s: f64,
    /// Roll/pitch wobble phases (rad) and frequencies (rad/s).
    wobble: [f64; 4],
}

/// The simulated swarm.
#[derive(Debug, Clone)]
pub struct SwarmWorld {
    vehicles: Vec<Vehicle>,
    time_ns: u64,
    rng: ChaCha8Rng,
    /// Water current, world frame (m/s).
    current: Vector3<f64>,
    /// Formation reference point (world) and its velocity.
    reference: Vector3<f64>,
    pub formation_velocity: Vector3<f64>,
    pub formation_heading: f64,
    /// First-order time constants of the vehicles' velocity and yaw-rate response (s).
    pub tau_velocity_s: f64,
    pub tau_yaw_s: f64,
    /// Standard deviation (m) and correlation time (s) of the slot drift.
    pub drift_std_m: f64,
    pub drift_tau_s: f64,
    /// Roll/pitch wobble amplitude (rad).
    pub wobble_rad: f64,
    /// Speed limit of formation keeping (m/s).
    pub max_speed_mps: f64,
}

/// Default depth of the formation (m, NED down).
pub const DEFAULT_DEPTH_M: f64 = 5.0;

/// Mean along-body position of a vehicle's side-looking cameras (0 if none).
fn side_camera_x(v: &shoal_proto::config::Vehicle) -> f64 {
    let xs: Vec<f64> = v
        .cameras
        .iter()
        .filter(|c| (c.body_from_camera.rotation * Vector3::z()).y.abs() > 0.7)
        .map(|c| c.body_from_camera.translation.vector.x)
        .collect();
    if xs.is_empty() {
        0.0
    } else {
        xs.iter().sum::<f64>() / xs.len() as f64
    }
}

/// Formation slots (x forward along the heading, y starboard) for the fleet's vehicles in order.
fn slots(fleet: &Fleet, formation: Formation, spacing_m: f64) -> Vec<Vector3<f64>> {
    let n = fleet.vehicles.len();
    let mid = (n as f64 - 1.0) / 2.0;
    match formation {
        Formation::Line => fleet
            .vehicles
            .iter()
            .enumerate()
            .map(|(i, v)| {
                // Put the midpoint between a vehicle's side cameras and its
                // (mid-body) markers on a common line: neighbours' cameras
                // and markers are then as nearly abreast as both allow.
                Vector3::new(-0.5 * side_camera_x(v), (i as f64 - mid) * spacing_m, 0.0)
            })
            .collect(),
        Formation::Column => {
            let mut x = 0.0;
            let mut out = Vec::with_capacity(n);
            for (i, v) in fleet.vehicles.iter().enumerate() {
                if i > 0 {
                    let prev = &fleet.vehicles[i - 1];
                    x -= spacing_m + 0.5 * (prev.hull.length_m + v.hull.length_m);
                }
                out.push(Vector3::new(x, 0.0, 0.0));
            }
            out
        }
        Formation::V => (0..n)
            .map(|i| {
                let k = i.div_ceil(2) as f64;
                let side = if i % 2 == 1 { 1.0 } else { -1.0 };
                let d = k * spacing_m * std::f64::consts::FRAC_1_SQRT_2;
                Vector3::new(-d, side * d, 0.0)
            })
            .collect(),
        Formation::Circle => {
            let r = if n > 1 {
                spacing_m / (2.0 * (std::f64::consts::PI / n as f64).sin())
            } else {
                0.0
            };
            (0..n)
                .map(|i| {
                    let a = std::f64::consts::TAU * i as f64 / n as f64;
                    Vector3::new(r * a.cos(), r * a.sin(), 0.0)
                })
                .collect()
        }
    }
}

impl SwarmWorld {
    /// Every vehicle of `fleet` at its slot of `formation` (neighbours
    /// `spacing_m` apart), at [`DEFAULT_DEPTH_M`], heading north, in
    /// formation mode; the formation moves north at 0.2 m/s.
    /// A spacing that is not a positive finite length is an error (it was
    /// once replaced by 1.5 m without a word).
    pub fn new(
        fleet: &Fleet,
        formation: Formation,
        spacing_m: f64,
        seed: u64,
    ) -> Result<Self, SimError> {
        if !(spacing_m.is_finite() && spacing_m > 0.0) {
            return Err(SimError::Spacing(spacing_m));
        }
        let mut rng = ChaCha8Rng::seed_from_u64(seed);
        let reference = Vector3::new(0.0, 0.0, DEFAULT_DEPTH_M);
        let vehicles = fleet
            .vehicles
            .iter()
            .zip(slots(fleet, formation, spacing_m))
            .map(|(v, slot)| Vehicle {
                id: v.id,
                position: reference + slot,
                yaw: 0.0,
                velocity_body: Vector3::zeros(),
                yaw_rate: 0.0,
                cmd_velocity: Vector3::zeros(),
                cmd_yaw_rate: 0.0,
                mode: Mode::Formation,
                slot,
                drift: Vector3::zeros(),
                next_manoeuvre_s: 0.0,
                wobble: [
                    rng.gen_range(0.0..std::f64::consts::TAU),
                    rng.gen_range(0.0..std::f64::consts::TAU),
                    rng.gen_range(0.3..0.8),
                    rng.gen_range(0.3..0.8),
                ],
            })
            .collect();
        Ok(SwarmWorld {
            vehicles,
            time_ns: 0,
            rng,
            current: Vector3::zeros(),
            reference,
            formation_velocity: Vector3::new(0.2, 0.0, 0.0),
            formation_heading: 0.0,
            tau_velocity_s: 2.0,
            tau_yaw_s: 1.0,
            drift_std_m: 0.05,
            drift_tau_s: 30.0,
            wobble_rad: 0.5f64.to_radians(),
            max_speed_mps: 1.0,
        })
    }

    /// Simulation time (ns since the start).
    pub fn time_ns(&self) -> u64 {
        self.time_ns
    }

    /// Simulation time (s).
    pub fn time_s(&self) -> f64 {
        self.time_ns as f64 * 1e-9
    }

    /// Set the water current (world NED, m/s).
    pub fn set_current(&mut self, world_velocity_mps: [f64; 3]) -> Result<(), SimError> {
        if let Some(&bad) = world_velocity_mps.iter().find(|v| !v.is_finite()) {
            return Err(SimError::InvalidArgument {
                field: "current",
                value: bad,
                reason: "must be finite",
            });
        }
        self.current = Vector3::from(world_velocity_mps);
        Ok(())
    }

    /// Drive vehicle `vehicle` in `mode` from now on.
    pub fn set_mode(&mut self, vehicle: VehicleId, mode: Mode) -> Result<(), SimError> {
        let t = self.time_s();
        let v = self.vehicle_mut(vehicle)?;
        v.mode = mode;
        v.next_manoeuvre_s = t;
        Ok(())
    }

    /// Closed-loop control: the vehicle now tracks this body velocity and
    /// yaw rate (first-order response) until the next command or mode change.
    pub fn apply_command(&mut self, cmd: &VehicleCommand) -> Result<(), SimError> {
        if let Some(&bad) = cmd
            .velocity_body
            .iter()
            .chain([&cmd.yaw_rate])
            .find(|v| !v.is_finite())
        {
            return Err(SimError::InvalidArgument {
                field: "command",
                value: bad,
                reason: "must be finite",
            });
        }
        let v = self.vehicle_mut(cmd.vehicle)?;
        v.mode = Mode::Commanded;
        v.cmd_velocity = Vector3::from(cmd.velocity_body);
        v.cmd_yaw_rate = cmd.yaw_rate;
        Ok(())
    }

    fn vehicle_mut(&mut self, id: VehicleId) -> Result<&mut Vehicle, SimError> {
        self.vehicles
            .iter_mut()
            .find(|v| v.id == id)
            .ok_or(SimError::UnknownVehicle {
                vehicle: id,
                context: "world",
            })
    }

    /// Advance the world by `dt_s` (split into steps of at most 50 ms); the
    /// clock advances by `dt_s` rounded to whole nanoseconds. A non-positive
    /// or non-finite `dt_s` does nothing.
    pub fn step(&mut self, dt_s: f64) {
        if !(dt_s.is_finite() && dt_s > 0.0) {
            return;
        }
        let total_ns = (dt_s * 1e9).round() as u64;
        let max_ns = 50_000_000u64;
        let mut done = 0u64;
        while done < total_ns {
            let ns = (total_ns - done).min(max_ns);
            self.substep(ns as f64 * 1e-9);
            done += ns;
            self.time_ns += ns;
        }
    }

    fn substep(&mut self, dt: f64) {
        let t = self.time_s();
        self.reference += self.formation_velocity * dt;
        let heading_rot = UnitQuaternion::from_euler_angles(0.0, 0.0, self.formation_heading);
        let a_v = 1.0 - (-dt / self.tau_velocity_s.max(1e-3)).exp();
        let a_y = 1.0 - (-dt / self.tau_yaw_s.max(1e-3)).exp();
        let ou_decay = (-dt / self.drift_tau_s.max(1e-3)).exp();
        let ou_kick = self.drift_std_m * (1.0 - ou_decay * ou_decay).sqrt();
        for v in &mut self.vehicles {
            // Slot drift (OU), horizontal mostly.
            for k in 0..3 {
                let z: f64 = StandardNormal.sample(&mut self.rng);
                let scale = if k == 2 { 0.3 } else { 1.0 };
                v.drift[k] = v.drift[k] * ou_decay + ou_kick * scale * z;
            }
            match v.mode {
                Mode::Formation => {
                    let target = self.reference + heading_rot * v.slot + v.drift;
                    let k_p = 0.3;
                    let mut want = self.formation_velocity + (target - v.position) * k_p;
                    if want.norm() > self.max_speed_mps {
                        want *= self.max_speed_mps / want.norm();
                    }
                    let body = UnitQuaternion::from_euler_angles(0.0, 0.0, v.yaw).inverse() * want;
                    v.cmd_velocity = body;
                    v.cmd_yaw_rate =
                        (1.0 * wrap_angle(self.formation_heading - v.yaw)).clamp(-0.3, 0.3);
                }
                Mode::Random => {
                    if t >= v.next_manoeuvre_s {
                        v.cmd_velocity = Vector3::new(
                            self.rng.gen_range(0.1..0.5),
                            0.0,
                            self.rng.gen_range(-0.02..0.02),
                        );
                        v.cmd_yaw_rate = self.rng.gen_range(-0.1..0.1);
                        v.next_manoeuvre_s = t + self.rng.gen_range(5.0..15.0);
                    }
                }
                Mode::Commanded => {}
            }
            v.velocity_body += (v.cmd_velocity - v.velocity_body) * a_v;
            v.yaw_rate += (v.cmd_yaw_rate - v.yaw_rate) * a_y;
            v.yaw = wrap_angle(v.yaw + v.yaw_rate * dt);
            let world_v =
                UnitQuaternion::from_euler_angles(0.0, 0.0, v.yaw) * v.velocity_body + self.current;
            v.position += world_v * dt;
        }
    }

    /// Every vehicle's ground truth now.
    pub fn truth(&self) -> Vec<VehicleTruth> {
        let t = self.time_s();
        self.vehicles
            .iter()
            .map(|v| {
                let roll = self.wobble_rad * (v.wobble[2] * t + v.wobble[0]).sin();
                let pitch = self.wobble_rad * (v.wobble[3] * t + v.wobble[1]).sin();
                let world_from_body: Pose = Pose::from_parts(
                    Translation3::from(v.position),
                    UnitQuaternion::from_euler_angles(roll, pitch, v.yaw),
                );
                VehicleTruth {
                    vehicle: v.id,
                    world_from_body,
                    velocity_body: v.velocity_body.into(),
                }
            })
            .collect()
    }

    /// The ground-truth message for this instant (`visible`: the rendered
    /// frames' [`shoal_proto::VisibleMarker`]s of this tick, if any).
    pub fn sim_truth(
        &self,
        tick: u64,
        water_c_per_m: f64,
        visible: Vec<shoal_proto::VisibleMarker>,
    ) -> shoal_proto::SimTruth {
        shoal_proto::SimTruth {
            stamp_ns: self.time_ns,
            tick,
            water_c_per_m,
            vehicles: self.truth(),
            visible,
        }
    }

    /// The vehicles' IDs, in fleet order.
    pub fn vehicle_ids(&self) -> Vec<VehicleId> {
        self.vehicles.iter().map(|v| v.id).collect()
    }

    /// A vehicle's current mode.
    pub fn mode(&self, vehicle: VehicleId) -> Option<Mode> {
        self.vehicles
            .iter()
            .find(|v| v.id == vehicle)
            .map(|v| v.mode)
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use std::path::Path;

    fn paper_fleet() -> Fleet {
        let path = Path::new(env!("CARGO_MANIFEST_DIR")).join("../configs/fleets/paper.toml");
        Fleet::load(&path).unwrap()
    }

    #[test]
    fn a_spacing_that_is_no_length_is_refused() {
        let fleet = paper_fleet();
        for bad in [0.0, -1.0, f64::NAN, f64::INFINITY] {
            let e = SwarmWorld::new(&fleet, Formation::Line, bad, 1).unwrap_err();
            assert!(matches!(e, SimError::Spacing(_)), "{bad}: {e}");
        }
    }

    #[test]
    fn line_puts_vehicles_side_by_side_along_east_heading_north() {
        let fleet = paper_fleet();
        let w = SwarmWorld::new(&fleet, Formation::Line, 1.5, 1).unwrap();
        let truth = w.truth();
        let east: Vec<f64> = truth
            .iter()
            .map(|t| t.world_from_body.translation.y)
            .collect();
        assert!((east[1] - east[0] - 1.5).abs() < 1e-12 && (east[2] - east[1] - 1.5).abs() < 1e-12);
        for t in &truth {
            let fwd = t.world_from_body.rotation * Vector3::x();
            assert!(fwd.x > 0.999, "{fwd}");
        }
    }

    #[test]
    fn same_seed_same_trajectories_and_clock_in_ns() {
        let fleet = paper_fleet();
        let run = |seed| {
            let mut w = SwarmWorld::new(&fleet, Formation::V, 2.0, seed).unwrap();
            w.set_current([0.05, -0.02, 0.0]).unwrap();
            w.set_mode(15, Mode::Random).unwrap();
            for _ in 0..200 {
                w.step(0.1);
            }
            (w.time_ns(), w.truth())
        };
        let (t1, a) = run(3);
        let (_, b) = run(3);
        let (_, c) = run(4);
        assert_eq!(t1, 20_000_000_000);
        assert_eq!(a, b);
        let w = SwarmWorld::new(&fleet, Formation::V, 2.0, 3).unwrap();
        let truth = w.sim_truth(0, 0.5, Vec::new());
        assert_eq!(truth.vehicles.len(), 3);
        assert!(shoal_proto::WireMessage::validate(&truth).is_ok());
        assert_ne!(a, c);
    }

    #[test]
    fn commanded_vehicle_follows_first_order_dynamics() {
        let fleet = paper_fleet();
        let mut w = SwarmWorld::new(&fleet, Formation::Column, 2.0, 9).unwrap();
        w.drift_std_m = 0.0;
        let cmd = VehicleCommand {
            vehicle: 10,
            stamp_ns: 0,
            velocity_body: [0.5, 0.0, 0.0],
            yaw_rate: 0.0,
        };
        w.apply_command(&cmd).unwrap();
        assert_eq!(w.mode(10), Some(Mode::Commanded));
        w.step(w.tau_velocity_s);
        let v = w.truth()[0].velocity_body[0];
        // One time constant: 1 − e^-1 of the step.
        assert!((v - 0.5 * (1.0 - (-1.0f64).exp())).abs() < 1e-3, "{v}");
        w.step(20.0);
        assert!((w.truth()[0].velocity_body[0] - 0.5).abs() < 1e-3);
        let bad = VehicleCommand { vehicle: 99, ..cmd };
        assert!(matches!(
            w.apply_command(&bad),
            Err(SimError::UnknownVehicle { .. })
        ));
        let nan = VehicleCommand {
            yaw_rate: f64::NAN,
            ..cmd
        };
        assert!(w.apply_command(&nan).is_err());
    }

    #[test]
    fn yaw_rate_command_turns_to_starboard() {
        let fleet = paper_fleet();
        let mut w = SwarmWorld::new(&fleet, Formation::Line, 2.0, 9).unwrap();
        w.apply_command(&VehicleCommand {
            vehicle: 17,
            stamp_ns: 0,
            velocity_body: [0.3, 0.0, 0.0],
            yaw_rate: 0.2,
        })
        .unwrap();
        let y0 = w.truth()[2].world_from_body.translation.y;
        w.step(10.0);
        let t = w.truth()[2];
        // Heading rotated from north towards east, and it moved east.
        assert!(t.world_from_body.rotation.euler_angles().2 > 0.5);
        assert!(t.world_from_body.translation.y > y0 + 0.3);
    }

    #[test]
    fn formation_holds_against_a_current() {
        let fleet = paper_fleet();
        let mut w = SwarmWorld::new(&fleet, Formation::Circle, 2.0, 5).unwrap();
        w.set_current([0.0, 0.1, 0.0]).unwrap();
        let before = w.truth();
        w.step(60.0);
        let after = w.truth();
        // The formation moved north ~12 m together; pairwise distances kept within 0.6 m.
        for i in 0..3 {
            let moved =
                after[i].world_from_body.translation.x - before[i].world_from_body.translation.x;
            assert!((moved - 12.0).abs() < 1.5, "{moved}");
            for j in i + 1..3 {
                let d0 = (before[i].world_from_body.translation.vector
                    - before[j].world_from_body.translation.vector)
                    .norm();
                let d1 = (after[i].world_from_body.translation.vector
                    - after[j].world_from_body.translation.vector)
                    .norm();
                assert!((d0 - d1).abs() < 0.6, "{d0} vs {d1}");
            }
        }
    }
}
