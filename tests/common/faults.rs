//! Shared by the fault tests: fleet, scratch dirs, Zenoh router configs,
//! map error against ground truth.

#![allow(dead_code)] // each test binary uses a different part

use shoal_proto::config::Fleet;
use shoal_proto::geometry::difference;
use shoal_proto::messages::{FleetMap, VehicleState, VehicleTruth};
use std::path::{Path, PathBuf};
use std::sync::Arc;
use std::time::{Duration, Instant};

pub fn root() -> &'static Path {
    Path::new(env!("CARGO_MANIFEST_DIR"))
}

pub fn fleet_path() -> PathBuf {
    root().join("configs/fleets/paper.toml")
}

pub fn fleet() -> Arc<Fleet> {
    Arc::new(Fleet::load(&fleet_path()).expect("paper fleet"))
}

/// A fresh per-process directory under the target's test scratch space.
pub fn scratch(name: &str) -> PathBuf {
    let dir = Path::new(env!("CARGO_TARGET_TMPDIR")).join(format!("{name}-{}", std::process::id()));
    let _ = std::fs::remove_dir_all(&dir);
    std::fs::create_dir_all(&dir).expect("scratch dir");
    dir
}

fn list(endpoints: &[String]) -> String {
    let l: Vec<String> = endpoints.iter().map(|e| format!("\"tcp/{e}\"")).collect();
    format!("[{}]", l.join(", "))
}

/// A Zenoh router config: listens on `listen`, connects to `connect`
/// (another router, possibly through a relay), retrying every ≤ 0.5 s.
pub fn write_router_config(path: &Path, listen: &[String], connect: &[String]) -> PathBuf {
    let text = format!(
        "{{\n  mode: \"router\",\n  listen: {{ endpoints: {} }},\n  connect: {{\n    endpoints: {},\n    \
         retry: {{ period_init_ms: 100, period_max_ms: 500, period_increase_factor: 2 }},\n  }},\n  \
         scouting: {{ multicast: {{ enabled: false }}, gossip: {{ enabled: false }} }},\n}}\n",
        list(listen),
        list(connect)
    );
    std::fs::write(path, text).expect("write router config");
    path.to_path_buf()
}

/// A Zenoh client config of the router at `router`.
pub fn write_client_config(path: &Path, router: &str) -> PathBuf {
    let text = format!(
        "{{\n  mode: \"client\",\n  connect: {{ endpoints: {}, timeout_ms: 15000 }},\n  \
         scouting: {{ multicast: {{ enabled: false }} }},\n}}\n",
        list(&[router.to_string()])
    );
    std::fs::write(path, text).expect("write client config");
    path.to_path_buf()
}

/// Error of one vehicle's estimate against the truth.
#[derive(Debug, Clone, Copy)]
pub struct VehicleError {
    pub vehicle: u32,
    pub state: VehicleState,
    pub position_m: f64,
    pub angle_deg: f64,
    /// Squared Mahalanobis distance of the position error under the map's
    /// own position covariance (χ² with 3 DoF if the map is consistent).
    pub position_nees: f64,
}

/// Errors of every vehicle the map has a pose for (any state but
/// `Unobserved`), its pose relative to the map's reference against the truth.
pub fn map_errors(map: &FleetMap, truth: &[VehicleTruth]) -> Vec<VehicleError> {
    let world_from = |v: u32| {
        truth
            .iter()
            .find(|t| t.vehicle == v)
            .map(|t| t.world_from_body)
    };
    let Some(world_from_ref) = world_from(map.reference) else {
        return vec![];
    };
    map.vehicles
        .iter()
        .filter(|e| e.state != VehicleState::Unobserved)
        .filter_map(|e| {
            let true_pose = world_from_ref.inverse() * world_from(e.vehicle)?;
            let d = difference(&e.reference_from_vehicle, &true_pose);
            let dp = d.fixed_rows::<3>(0).into_owned();
            let cov = e.covariance.fixed_view::<3, 3>(0, 0).into_owned();
            let position_nees = cov
                .try_inverse()
                .map_or(f64::INFINITY, |inv| (dp.transpose() * inv * dp)[0]);
            Some(VehicleError {
                vehicle: e.vehicle,
                state: e.state,
                position_m: dp.norm(),
                angle_deg: d.fixed_rows::<3>(3).norm().to_degrees(),
                position_nees,
            })
        })
        .collect()
}

pub fn state_of(map: &FleetMap, v: u32) -> Option<VehicleState> {
    map.vehicles
        .iter()
        .find(|e| e.vehicle == v)
        .map(|e| e.state)
}

pub fn all_live(map: &FleetMap) -> bool {
    !map.vehicles.is_empty() && map.vehicles.iter().all(|e| e.state == VehicleState::Live)
}

/// Largest position difference (m) between two maps' poses of the same vehicles.
pub fn disagreement_m(a: &FleetMap, b: &FleetMap) -> f64 {
    a.vehicles
        .iter()
        .filter_map(|ea| {
            let eb = b.vehicles.iter().find(|e| e.vehicle == ea.vehicle)?;
            Some(
                difference(&ea.reference_from_vehicle, &eb.reference_from_vehicle)
                    .fixed_rows::<3>(0)
                    .norm(),
            )
        })
        .fold(0.0, f64::max)
}

/// Poll `f` until it returns `Some` or `timeout` passes.
pub fn wait_for<T>(timeout: Duration, mut f: impl FnMut() -> Option<T>) -> Option<T> {
    let deadline = Instant::now() + timeout;
    loop {
        if let Some(t) = f() {
            return Some(t);
        }
        if Instant::now() >= deadline {
            return None;
        }
        std::thread::sleep(Duration::from_millis(50));
    }
}

/// Running max / samples of a figure.
#[derive(Debug, Default, Clone)]
pub struct Figure {
    pub samples: Vec<f64>,
}

impl Figure {
    pub fn add(&mut self, x: f64) {
        if x.is_finite() {
            self.samples.push(x);
        }
    }
    pub fn max(&self) -> f64 {
        self.samples.iter().copied().fold(0.0, f64::max)
    }
    pub fn percentile(&self, p: f64) -> f64 {
        if self.samples.is_empty() {
            return f64::NAN;
        }
        let mut s = self.samples.clone();
        s.sort_by(f64::total_cmp);
        s[((s.len() - 1) as f64 * p).round() as usize]
    }
}
