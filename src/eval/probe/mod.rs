//! `shoal eval probe <name>`: diagnostics kept from development, each a
//! question asked of one stage on simulated (or recorded) data, printed as
//! text rather than measured into a `summary.json`. The experiments proper
//! are [`super::Experiment`]s; timings are criterion benches
//! (`cargo bench -p shoal-node`, `-p shoal-fusion`, `-p shoal-sim-bridge`).
//!
//! | probe            | question                                                    | module           |
//! |------------------|-------------------------------------------------------------|------------------|
//! | `residuals`      | per-corner bias and spread of the detector's settings       | [`residuals`]    |
//! | `hoirm`          | what HOIRM estimates per frame, and does the detector cope  | [`hoirm`]        |
//! | `psf-scale`      | the pixel unit of Eq. (14)'s σ, fitted to the simulator     | [`psf_scale`]    |
//! | `restore-sheet`  | HOIRM stage by stage (CNR per stage) beside the baselines   | [`restore_sheet`]|
//! | `water-sheet`    | the simulator's water presets side by side                  | [`water_sheet`]  |
//! | `effects-sheet`  | the camera effects of issue #16, each alone and all together | [`effects_sheet`]|
//! | `code-tables`    | regenerate `proto/data/codes/` from OpenCV and libapriltag  | [`code_tables`]  |
//! | `record-cost`    | the recorder's cost per camera frame on a real log          | [`record_cost`]  |
//! | `big-log`        | a log of N GB from a real one, to measure reading costs     | [`big_log`]      |

pub mod big_log;
pub mod code_tables;
pub mod effects_sheet;
pub mod hoirm;
pub mod psf_scale;
pub mod record_cost;
pub mod residuals;
pub mod restore_sheet;
pub mod water_sheet;

use super::EvalError;

/// The probes, with their arguments.
#[derive(Debug, clap::Subcommand)]
pub enum Probe {
    /// Per-corner residuals and pose errors of shoal's detector settings on the accuracy test's frames.
    Residuals(residuals::ResidualsArgs),
    /// HOIRM + shoal's detector on the detection experiment's frames, with what HOIRM estimated per frame.
    Hoirm(hoirm::HoirmArgs),
    /// Fit the pixel unit of Eq. (14)'s PSF width to the simulator's blur.
    PsfScale(psf_scale::PsfScaleArgs),
    /// Contact sheet of HOIRM's stages and the baselines; marker CNR after every stage.
    RestoreSheet(restore_sheet::RestoreSheetArgs),
    /// Contact sheet of the simulator's water presets.
    WaterSheet(water_sheet::WaterSheetArgs),
    /// Contact sheet of the camera effects (issue #16): each alone and all together.
    EffectsSheet(effects_sheet::EffectsSheetArgs),
    /// Regenerate the ArUco / AprilTag code tables (proto/data/codes/) from the installed libraries.
    CodeTables(code_tables::CodeTablesArgs),
    /// Cost of recording camera frames, stage by stage, on the frames of a log.
    RecordCost(record_cost::RecordCostArgs),
    /// A log of a given size made of a real one repeated (stamps shifted), for memory measurements.
    BigLog(big_log::BigLogArgs),
}

/// Run `probe`, printing its findings on stdout.
pub fn run(probe: &Probe) -> Result<(), EvalError> {
    match probe {
        Probe::Residuals(a) => residuals::run(a),
        Probe::Hoirm(a) => hoirm::run(a),
        Probe::PsfScale(a) => psf_scale::run(a),
        Probe::RestoreSheet(a) => restore_sheet::run(a),
        Probe::WaterSheet(a) => water_sheet::run(a),
        Probe::EffectsSheet(a) => effects_sheet::run(a),
        Probe::CodeTables(a) => code_tables::run(a),
        Probe::RecordCost(a) => record_cost::run(a),
        Probe::BigLog(a) => big_log::run(a),
    }
}

/// Median of `v` (upper median; NaN when empty), sorting it in place.
fn median(v: &mut [f64]) -> f64 {
    if v.is_empty() {
        return f64::NAN;
    }
    v.sort_by(f64::total_cmp);
    v[v.len() / 2]
}

/// The water at `c_per_m`: from `file` (a `configs/water.toml`-format file)
/// if given, else the built-in presets (`WaterParams::preset`).
fn water(
    file: Option<&std::path::Path>,
    c_per_m: f64,
) -> Result<shoal_sim_bridge::water::WaterParams, EvalError> {
    match file {
        Some(p) => Ok(shoal_sim_bridge::water::WaterPresets::load(p)?.get(c_per_m)?),
        None => Ok(shoal_sim_bridge::water::WaterParams::preset(c_per_m)),
    }
}
