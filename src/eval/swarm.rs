//! `swarm` (paper §6.3): the paper's three vehicles (IDs 10, 15, 17, five
//! 1440x1080 cameras each) in line abreast at 0.5 /m, every camera rendered
//! and run through the node's real chain (`node::pipeline::CameraPipeline`:
//! HOIRM → detector → PnP) and every observation fused
//! (`shoal_fusion::Fusion`) — directly, without Zenoh, so the run is
//! deterministic. Measures the per-frame processing time, the fused relative
//! pose error of every pair, and, over a sweep of the formation spacing, the
//! largest spacing at which each vehicle is still localized.
//!
//! With `--profile` (issue #16) every camera's frames go through that
//! camera profile ([`render_profiled`] over the swarm's own motion, so the
//! blur and the rolling shutter are the vehicles'), and every node holds
//! the calibration a lab would have for its camera
//! ([`super::profiles::node_camera`], drawn per camera): behind the port,
//! an in-water pinhole, off by the calibration error. The observations are
//! stamped, and the errors taken against the ground truth, at the
//! exposure's reference time.

use super::features::plot_or_warn;
use super::plot::{self, Grouped};
use super::table::{median, quantile, Csv};
use super::{EvalError, EvalOptions};
use opencv::prelude::*;
use serde_json::{json, Map, Value};
use shoal_fusion::{Fusion, FusionParams};
use shoal_node::pipeline::{CameraPipeline, PipelineParams};
use shoal_proto::config::Fleet;
use shoal_proto::{VehicleId, VehicleState, VehicleTruth};
use shoal_sim_bridge::profile::CameraProfile;
use shoal_sim_bridge::render::motion::FleetTimeline;
use shoal_sim_bridge::render::realistic::render_profiled;
use shoal_sim_bridge::render::{render_fleet_view, RenderOutput, Renderer};
use shoal_sim_bridge::water::WaterParams;
use shoal_sim_bridge::world::{Formation, SwarmWorld};
use std::collections::BTreeMap;
use std::path::Path;
use std::sync::Arc;

/// The paper's trial water (1/m).
pub const WATER_C_PER_M: f64 = 0.5;
/// The paper's frame interval is not given; 10 Hz as the node service.
const DT_S: f64 = 0.1;
/// The paper's mean processing time per frame (ms, Jetson Orin NX) and its effective range (m).
pub const PAPER_FRAME_MS: f64 = 61.28;
pub const PAPER_RANGE_M: f64 = 4.0;
/// Formation spacings of the range sweep (m).
const SWEEP_M: [f64; 5] = [1.75, 2.5, 3.5, 4.5, 5.5];

/// One run of the swarm at one spacing.
struct Trial {
    /// Per camera image: restore + detect + pose, ms.
    camera_ms: Vec<f64>,
    /// Per vehicle frame (its five cameras), ms.
    vehicle_ms: Vec<f64>,
    /// (a, b) → per-map (position error m, angle error deg).
    pair_errors: BTreeMap<(VehicleId, VehicleId), Vec<(f64, f64)>>,
    /// Vehicle → maps in which it was Live.
    live: BTreeMap<VehicleId, usize>,
    maps: usize,
    observations: usize,
    /// Camera frames on which HOIRM's detail-keeping restoration was
    /// searched, and the markers read only there (`pipeline::detect_restoration`).
    fine_searches: usize,
    fine_reads: usize,
}

fn relative(truth: &[VehicleTruth], a: VehicleId, b: VehicleId) -> Option<shoal_proto::Pose> {
    let wa = truth.iter().find(|t| t.vehicle == a)?.world_from_body;
    let wb = truth.iter().find(|t| t.vehicle == b)?.world_from_body;
    Some(wa.inverse() * wb)
}

/// The cameras as the fleet's nodes hold them: through `profile`, each
/// camera's calibration as a lab would have it ([`super::profiles::lab_fleet`],
/// no calibration σ stated); without one, `fleet` itself.
fn node_fleet(
    fleet: &Arc<Fleet>,
    profile: Option<&CameraProfile>,
    seed: u64,
) -> Result<Arc<Fleet>, EvalError> {
    let Some(profile) = profile else {
        return Ok(fleet.clone());
    };
    let held = super::profiles::lab_fleet(fleet, profile, seed, false)?;
    Ok(Arc::new(held))
}

/// One camera's frame at the start of `world`'s next `DT_S`: through
/// `profile` over the swarm's motion during the exposure, else the ideal
/// render at that instant. Also the seconds after the start the frame's
/// ground truth refers to.
#[allow(clippy::too_many_arguments)]
fn render_camera(
    renderer: &mut Renderer,
    profile: Option<&CameraProfile>,
    fleet: &Fleet,
    world: &SwarmWorld,
    (v, cam): (VehicleId, u8),
    water: &WaterParams,
    k: u64,
    seed: u64,
) -> Result<(RenderOutput, f64), EvalError> {
    let time_s = world.time_ns() as f64 * 1e-9;
    let Some(profile) = profile else {
        let truth = world.truth();
        let out = render_fleet_view(renderer, fleet, &truth, v, cam, water, time_s, k, seed)?;
        return Ok((out, 0.0));
    };
    let camera = &fleet
        .vehicle(v)
        .and_then(|x| x.cameras.get(cam as usize))
        .ok_or_else(|| EvalError::Setup(format!("vehicle {v} has no camera {cam}")))?;
    let timeline = FleetTimeline {
        fleet,
        world: world.clone(),
        vehicle: v,
        camera_index: cam,
    };
    let f = render_profiled(
        renderer,
        profile,
        &camera.model,
        camera.port.as_ref(),
        &timeline,
        water,
        time_s,
        seed,
    )?;
    Ok((f.output, f.report.reference_s))
}

/// One trial: `fleet` rendered (through `profile`, seeded), `held` the
/// cameras as the nodes hold them ([`node_fleet`]).
fn run_trial(
    opts: &EvalOptions,
    (fleet, held): (&Arc<Fleet>, &Arc<Fleet>),
    profile: Option<&CameraProfile>,
    spacing_m: f64,
    frames: usize,
    what: &str,
) -> Result<Trial, EvalError> {
    let water = opts.presets()?.get(WATER_C_PER_M)?;
    let mut world = SwarmWorld::new(fleet, Formation::Line, spacing_m, opts.seed)
        .map_err(|e| EvalError::Setup(e.to_string()))?;
    let mut renderer = Renderer::new();
    let setup = |e: shoal_node::pipeline::PipelineError| EvalError::Setup(e.to_string());
    let mut pipelines = Vec::new();
    for v in &fleet.vehicles {
        for c in 0..v.cameras.len() {
            pipelines.push((
                v.id,
                c as u8,
                CameraPipeline::new(
                    held.clone(),
                    v.id,
                    c as u8,
                    PipelineParams {
                        restore: opts.restore,
                        restore_params: opts.restore_params.clone(),
                        ..PipelineParams::default()
                    },
                )
                .map_err(setup)?,
            ));
        }
    }
    let mut fusion = Fusion::new(held, FusionParams::default(), "eval");
    let ids: Vec<VehicleId> = fleet.vehicles.iter().map(|v| v.id).collect();
    let mut trial = Trial {
        camera_ms: Vec::new(),
        vehicle_ms: Vec::new(),
        pair_errors: BTreeMap::new(),
        live: BTreeMap::new(),
        maps: 0,
        observations: 0,
        fine_searches: 0,
        fine_reads: 0,
    };
    let bar = opts.bar(frames, what);
    for k in 0..frames {
        world.step(DT_S);
        // Every camera's exposure has the same reference time (one profile).
        let mut reference_s = 0.0;
        let mut rendered = Vec::with_capacity(pipelines.len());
        for (v, cam, _) in &pipelines {
            let seed = super::profiles::camera_seed(opts.seed, *v, *cam, k as u64);
            let (frame, r) = render_camera(
                &mut renderer,
                profile,
                fleet,
                &world,
                (*v, *cam),
                &water,
                k as u64,
                seed,
            )?;
            reference_s = r;
            rendered.push(frame);
        }
        let mut at_reference = world.clone();
        if reference_s > 0.0 {
            at_reference.step(reference_s);
        }
        let truth = at_reference.truth();
        let stamp_ns = at_reference.time_ns();
        let mut per_vehicle: BTreeMap<VehicleId, f64> = BTreeMap::new();
        for ((v, _cam, pipeline), frame) in pipelines.iter_mut().zip(&rendered) {
            let mat = shoal_node::mat::gray_as_mat(&frame.image)?;
            let owned = mat.try_clone().map_err(shoal_node::mat::MatError::from)?;
            let out = pipeline
                .process(&owned, stamp_ns, k as u64)
                .map_err(|e| EvalError::Setup(e.to_string()))?;
            let ms = out.restore_ms + out.detect_ms + out.pose_ms;
            trial.fine_searches += usize::from(out.fine_searched);
            trial.fine_reads += out.fine_reads;
            trial.camera_ms.push(ms);
            *per_vehicle.entry(*v).or_insert(0.0) += ms;
            for obs in out.observations {
                trial.observations += 1;
                let _ = fusion.ingest(obs, *v, stamp_ns);
            }
        }
        trial.vehicle_ms.extend(per_vehicle.values());
        let map = fusion.solve(stamp_ns);
        trial.maps += 1;
        let est: BTreeMap<VehicleId, _> = map
            .vehicles
            .iter()
            .filter(|e| e.state == VehicleState::Live)
            .map(|e| (e.vehicle, e.reference_from_vehicle))
            .collect();
        for id in est.keys() {
            *trial.live.entry(*id).or_insert(0) += 1;
        }
        for (i, &a) in ids.iter().enumerate() {
            for &b in &ids[i + 1..] {
                let (Some(ea), Some(eb), Some(t)) =
                    (est.get(&a), est.get(&b), relative(&truth, a, b))
                else {
                    continue;
                };
                let e = ea.inverse() * eb;
                let d = (e.translation.vector - t.translation.vector).norm();
                let ang = (e.rotation * t.rotation.inverse()).angle().to_degrees();
                trial.pair_errors.entry((a, b)).or_default().push((d, ang));
            }
        }
        bar.inc(1);
    }
    bar.finish_and_clear();
    Ok(trial)
}

/// Every pair's fused errors over the trial's maps: written to
/// `swarm-pairs.csv` in `out`, returned for the summary.
fn pair_errors(main: &Trial, out: &Path) -> Result<Map<String, Value>, EvalError> {
    let mut pairs = Map::new();
    let mut csv = Csv::new(&[
        "pair",
        "maps_localized",
        "median_position_error_mm",
        "p90_position_error_mm",
        "median_angle_error_deg",
    ]);
    for ((a, b), errs) in &main.pair_errors {
        let d: Vec<f64> = errs.iter().map(|e| e.0 * 1e3).collect();
        let g: Vec<f64> = errs.iter().map(|e| e.1).collect();
        csv.row(vec![
            format!("{a}-{b}"),
            errs.len().to_string(),
            format!("{:.3}", median(&d).unwrap_or(f64::NAN)),
            format!("{:.3}", quantile(&d, 0.9).unwrap_or(f64::NAN)),
            format!("{:.4}", median(&g).unwrap_or(f64::NAN)),
        ]);
        pairs.insert(
            format!("{a}-{b}"),
            json!({
                "maps_localized": errs.len(),
                "median_position_error_mm": median(&d),
                "p90_position_error_mm": quantile(&d, 0.9),
                "median_angle_error_deg": median(&g),
            }),
        );
    }
    csv.write(&out.join("swarm-pairs.csv"))?;
    Ok(pairs)
}

pub fn run(opts: &EvalOptions) -> Result<Value, EvalError> {
    let frames = opts.count(2, 100);
    let sweep_frames = if opts.quick {
        1
    } else {
        opts.frames.unwrap_or(10).min(10)
    };
    let sweep: Vec<f64> = if opts.quick {
        vec![1.75, 5.5]
    } else {
        SWEEP_M.to_vec()
    };
    let fleet = Arc::new(
        Fleet::parse(
            crate::demo::PAPER_FLEET,
            Path::new("configs/fleets/paper.toml"),
        )
        .map_err(|e| EvalError::Setup(e.to_string()))?,
    );
    // Drawn once: the profile's seed, and the nodes' calibrations (a lab
    // calibration each through the port: ~0.4 s per camera).
    let profile = opts.profile.clone().map(|p| p.with_seed(opts.seed));
    let held = node_fleet(&fleet, profile.as_ref(), opts.seed)?;
    let fleets = (&fleet, &held);
    let main = run_trial(
        opts,
        fleets,
        profile.as_ref(),
        SWEEP_M[0],
        frames,
        "swarm: frames",
    )?;

    let pairs = pair_errors(&main, &opts.out)?;

    // Range sweep: the largest spacing at which each vehicle is Live in at least half the maps.
    let mut sweep_csv = Csv::new(&[
        "spacing_m",
        "vehicle",
        "maps_live",
        "maps",
        "observations",
        "camera_frames",
        "fine_searches",
        "fine_reads",
    ]);
    let mut largest: BTreeMap<VehicleId, f64> = BTreeMap::new();
    let mut live_frac: Vec<Vec<Option<f64>>> = vec![Vec::new(); fleet.vehicles.len()];
    for &s in &sweep {
        let t = run_trial(
            opts,
            fleets,
            profile.as_ref(),
            s,
            sweep_frames,
            &format!("swarm: spacing {s} m"),
        )?;
        for (vi, v) in fleet.vehicles.iter().enumerate() {
            let live = t.live.get(&v.id).copied().unwrap_or(0);
            sweep_csv.row(vec![
                s.to_string(),
                v.id.to_string(),
                live.to_string(),
                t.maps.to_string(),
                t.observations.to_string(),
                t.camera_ms.len().to_string(),
                t.fine_searches.to_string(),
                t.fine_reads.to_string(),
            ]);
            let frac = live as f64 / t.maps.max(1) as f64;
            live_frac[vi].push(Some(frac));
            // The reference vehicle is in every map by definition.
            if frac >= 0.5 && v.id != fleet.reference_vehicle {
                let e = largest.entry(v.id).or_insert(0.0);
                *e = e.max(s);
            }
        }
    }
    sweep_csv.write(&opts.out.join("swarm-range.csv"))?;
    let plots = plot_or_warn(plot::bars(
        &opts.out.join("eval-swarm-range"),
        &Grouped {
            title: format!(
                "Maps in which each vehicle is localized, by formation spacing (c = {WATER_C_PER_M} /m, {} camera, {})",
                opts.profile_name(),
                opts.restore.name()
            ),
            x_label: "line-abreast spacing (m)".into(),
            y_label: "fraction of maps Live".into(),
            categories: sweep.iter().map(|s| format!("{s}")).collect(),
            series: fleet.vehicles.iter().map(|v| format!("vehicle {}", v.id)).collect(),
        },
        &live_frac,
    ));
    let mean = |v: &[f64]| (!v.is_empty()).then(|| v.iter().sum::<f64>() / v.len() as f64);
    Ok(json!({
        "frames": frames,
        "water_c_per_m": WATER_C_PER_M,
        "camera_profile": opts.profile_name(),
        "restore": opts.restore.name(),
        "setup": "paper fleet (configs/fleets/paper.toml), line abreast 1.75 m, 10 Hz, every camera rendered and run through CameraPipeline (--restore, default HOIRM; shoal detector; PnP) and one Fusion, no Zenoh",
        "processing": {
            "mean_camera_frame_ms": mean(&main.camera_ms),
            "median_camera_frame_ms": median(&main.camera_ms),
            "mean_vehicle_frame_ms": mean(&main.vehicle_ms),
            "build": if cfg!(debug_assertions) { "debug" } else { "release" },
        },
        "observations": main.observations,
        "fine_pass": {
            "camera_frames": main.camera_ms.len(),
            "searched": main.fine_searches,
            "reads": main.fine_reads,
        },
        "maps": main.maps,
        "live_maps": main.live.iter().map(|(k, v)| (k.to_string(), json!(v))).collect::<Map<_, _>>(),
        "results": pairs,
        "range": {
            "spacings_m": sweep,
            "frames_per_spacing": sweep_frames,
            "largest_spacing_localized_m": largest.iter().map(|(k, v)| (k.to_string(), json!(v))).collect::<Map<_, _>>(),
        },
        "paper": { "mean_frame_ms": PAPER_FRAME_MS, "effective_range_m": PAPER_RANGE_M },
        "plots": plots,
    }))
}

#[cfg(test)]
mod tests {
    use super::*;

    fn paper_fleet() -> Arc<Fleet> {
        Arc::new(
            Fleet::parse(
                crate::demo::PAPER_FLEET,
                Path::new("configs/fleets/paper.toml"),
            )
            .unwrap(),
        )
    }

    /// Through a profile every node holds its own camera's lab calibration
    /// (in-water pinhole behind the port, off by a per-camera calibration
    /// error), not the renderer's camera; without one, the fleet itself.
    #[test]
    fn each_node_holds_its_own_cameras_calibration_through_a_profile() {
        let fleet = paper_fleet();
        assert!(Arc::ptr_eq(&node_fleet(&fleet, None, 3).unwrap(), &fleet));
        // Two vehicles: ten lab calibrations (each a few hundred ms).
        let mut two = (*fleet).clone();
        two.vehicles.truncate(2);
        let fleet = Arc::new(two);
        let profile = CameraProfile::realistic().with_seed(3);
        let held = node_fleet(&fleet, Some(&profile), 3).unwrap();
        let mut focal = Vec::new();
        for (v, h) in fleet.vehicles.iter().zip(&held.vehicles) {
            for (c, hc) in v.cameras.iter().zip(&h.cameras) {
                assert_eq!(c.body_from_camera, hc.body_from_camera);
                let rel = hc.model.fx / c.model.fx - 1.0;
                // The port's lab calibration moves fx by well under 1 %; the
                // calibration error draws within ±0.3 % (+ the fit's own error).
                assert!(rel.abs() < 0.01 && rel != 0.0, "{} {}: {rel}", v.id, c.name);
                focal.push(hc.model.fx);
            }
        }
        focal.sort_by(f64::total_cmp);
        focal.dedup();
        assert_eq!(focal.len(), 10, "one draw per camera: {focal:?}");
        // Deterministic in the seed.
        let again = node_fleet(&fleet, Some(&profile), 3).unwrap();
        assert_eq!(
            again.vehicles[1].cameras[2].model,
            held.vehicles[1].cameras[2].model
        );
    }

    /// A fleet whose cameras already sit behind a port is refused with the
    /// camera named (the profile would add a second window).
    #[test]
    fn a_ported_fleet_through_a_profile_is_refused_by_name() {
        let mut fleet = (*paper_fleet()).clone();
        fleet.vehicles[2].cameras[4].port = Some(shoal_proto::FlatPort {
            distance_m: 0.01,
            glass_m: 0.008,
            n_glass: shoal_proto::FlatPort::N_ACRYLIC,
            n_water: shoal_proto::FlatPort::N_SEA_WATER,
        });
        let profile = CameraProfile::realistic();
        let e = node_fleet(&Arc::new(fleet), Some(&profile), 1).unwrap_err();
        let msg = e.to_string();
        assert!(msg.contains("vehicle 17 camera starboard"), "{msg}");
    }
}
