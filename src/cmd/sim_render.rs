//! `shoal sim render`: one simulated camera frame, through a camera profile
//! (`--profile ideal|realistic`, `--effect NAME…`, `--profile-file F`;
//! `docs/water-model.md`, "Camera effects").

use anyhow::{bail, Context};
use clap::Args;
use shoal_proto::config::Fleet;
use shoal_sim_bridge::profile::CameraProfile;
use shoal_sim_bridge::render::motion::FleetTimeline;
use shoal_sim_bridge::render::realistic::{render_profiled, ProfiledFrame};
use shoal_sim_bridge::render::{write_frame_pair, write_png, Renderer};
use shoal_sim_bridge::water::WaterPresets;
use shoal_sim_bridge::world::{Formation, SwarmWorld};
use std::path::{Path, PathBuf};

#[derive(Debug, Args)]
pub struct RenderArgs {
    #[arg(long, default_value = "configs/fleets/paper.toml")]
    fleet: PathBuf,
    #[arg(long, default_value_t = 0.5, value_parser = super::args::non_negative)]
    water: f64,
    /// Observer vehicle (default: the fleet's reference vehicle).
    #[arg(long)]
    vehicle: Option<u32>,
    /// Camera name (forward, up, down, port, starboard) or index.
    #[arg(long, default_value = "starboard")]
    camera: String,
    #[arg(long, default_value = "line")]
    formation: String,
    #[arg(long, default_value_t = 1.75, value_parser = super::args::positive)]
    spacing: f64,
    #[arg(long, default_value_t = 7)]
    seed: u64,
    /// Simulated time of the frame (s): the world runs to it first (the vehicles move).
    #[arg(long, default_value_t = 0.0, value_parser = super::args::non_negative)]
    time: f64,
    #[command(flatten)]
    profile: shoal::eval::profiles::ProfileArgs,
    /// Seed of the profile's own draws (PSF family, marine snow, calibration error).
    #[arg(long)]
    profile_seed: Option<u64>,
    /// Output: a `.png` (the clean twin beside it), or a folder that gets
    /// `frame.png`, `clean.png` and `truth.json` (visible markers, the node's
    /// calibration, what the profile did).
    #[arg(long)]
    out: PathBuf,
}

fn formation(name: &str) -> anyhow::Result<Formation> {
    Ok(match name {
        "line" => Formation::Line,
        "column" => Formation::Column,
        "v" => Formation::V,
        "circle" => Formation::Circle,
        other => bail!("formation {other:?}: expected line, column, v or circle"),
    })
}

pub fn run(a: RenderArgs) -> anyhow::Result<()> {
    let profile = match a
        .profile
        .selected(a.profile_seed)
        .context("the camera profile (--profile, --effect, --profile-file)")?
    {
        Some(p) => p,
        None => CameraProfile::selected("ideal", &[], None)?,
    };
    let fleet = Fleet::load(&a.fleet)?;
    let vehicle = a.vehicle.unwrap_or(fleet.reference_vehicle);
    let v = fleet
        .vehicle(vehicle)
        .with_context(|| format!("vehicle {vehicle} is not in the fleet"))?;
    let cam_index = match a.camera.parse::<u8>() {
        Ok(i) => i,
        Err(_) => v
            .cameras
            .iter()
            .find(|c| c.name == a.camera)
            .map(|c| c.index)
            .with_context(|| format!("vehicle {vehicle} has no camera {:?}", a.camera))?,
    };
    let cam = v
        .cameras
        .get(cam_index as usize)
        .with_context(|| format!("vehicle {vehicle} has no camera {cam_index}"))?;
    let water = WaterPresets::builtin().get(a.water)?;
    let mut world = SwarmWorld::new(&fleet, formation(&a.formation)?, a.spacing, a.seed)?;
    world.step(a.time);
    let timeline = FleetTimeline {
        fleet: &fleet,
        world,
        vehicle,
        camera_index: cam_index,
    };
    let mut frame = render_profiled(
        &mut Renderer::new(),
        &profile,
        &cam.model,
        cam.port.as_ref(),
        &timeline,
        &water,
        a.time,
        a.seed,
    )?;
    for vm in &mut frame.output.visible {
        vm.observer = vehicle;
        vm.camera = cam_index;
    }
    let written = write_outputs(&frame, &a.out)?;
    shoal::outln!(
        "profile {} ({}): wrote {}",
        profile.name,
        if profile.is_ideal() {
            "no effect".to_string()
        } else {
            profile
                .enabled
                .iter()
                .map(|e| e.name())
                .collect::<Vec<_>>()
                .join(", ")
        },
        written.join(", ")
    );
    let r = &frame.report;
    if !profile.is_ideal() {
        shoal::outln!(
            "  {} sub-frame(s), image motion {:.0} px/s, gain {:.2}, {} snow particles{}",
            r.sub_frames,
            r.image_speed_px_per_s,
            r.gain,
            r.snow_particles,
            r.psf
                .as_ref()
                .map_or(String::new(), |p| format!(", PSF {p}"))
        );
    }
    for m in &frame.output.visible {
        shoal::outln!(
            "  sees {}#{} on vehicle {} at {:.2} m, {:.0}% visible",
            m.codes,
            m.marker,
            m.target_vehicle,
            m.range_m,
            m.visible_fraction * 100.0
        );
    }
    Ok(())
}

/// Write the frame as the user asked: a PNG and its twin, or a folder.
fn write_outputs(frame: &ProfiledFrame, out: &Path) -> anyhow::Result<Vec<String>> {
    let is_png = out
        .extension()
        .is_some_and(|e| e.eq_ignore_ascii_case("png"));
    if is_png {
        if let Some(dir) = out.parent().filter(|d| !d.as_os_str().is_empty()) {
            std::fs::create_dir_all(dir)
                .with_context(|| format!("cannot create {}", dir.display()))?;
        }
        let clean = write_frame_pair(&frame.output, out)?;
        return Ok(vec![out.display().to_string(), clean.display().to_string()]);
    }
    std::fs::create_dir_all(out).with_context(|| format!("cannot create {}", out.display()))?;
    let (img, clean, truth) = (
        out.join("frame.png"),
        out.join("clean.png"),
        out.join("truth.json"),
    );
    write_png(&frame.output.image, &img)?;
    write_png(&frame.output.clean, &clean)?;
    let c = &frame.node_camera;
    let json = serde_json::json!({
        "visible": frame.output.visible,
        "node_camera": {
            "width": c.width, "height": c.height,
            "fx": c.fx, "fy": c.fy, "cx": c.cx, "cy": c.cy,
            "distortion": format!("{:?}", c.distortion),
        },
        "port": frame.port.map(|p| serde_json::json!({
            "distance_m": p.distance_m, "glass_m": p.glass_m,
            "n_glass": p.n_glass, "n_water": p.n_water,
        })),
        "report": {
            "sub_frames": frame.report.sub_frames,
            "reference_s": frame.report.reference_s,
            "image_speed_px_per_s": frame.report.image_speed_px_per_s,
            "gain": frame.report.gain,
            "psf": frame.report.psf,
            "snow_particles": frame.report.snow_particles,
        },
    });
    std::fs::write(&truth, serde_json::to_string_pretty(&json)? + "\n")
        .with_context(|| format!("cannot write {}", truth.display()))?;
    Ok(vec![
        img.display().to_string(),
        clean.display().to_string(),
        truth.display().to_string(),
    ])
}
