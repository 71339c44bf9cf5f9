//! `shoal eval <experiment>`: the paper's measurements repeated on shoal (library: `shoal::eval`).

use anyhow::Context;
use clap::Args;
use shoal::eval::{self, EvalOptions, Experiment};
use shoal_node::restore::Method;
use std::path::PathBuf;

#[derive(Debug, Args)]
pub struct EvalArgs {
    /// features | accuracy | accuracy-yaw | accuracy-rmse | detection | restoration | calibrate-water | fit-noise | fusion | swarm
    experiment: String,
    /// Output directory: CSV of every trial, plots (PNG, SVG), summary.json.
    #[arg(long)]
    out: PathBuf,
    /// The reduced run used in CI (well under a minute each in a debug build).
    #[arg(long)]
    quick: bool,
    /// Frames (or trials) per condition, overriding the experiment's default (100 frames, 1000 trials).
    #[arg(long)]
    frames: Option<usize>,
    /// Seed of every random stream (pose jitter, sensor noise).
    #[arg(long, default_value_t = 1)]
    seed: u64,
    /// Restoration applied to every marker's frames in the accuracy experiments: none, clahe, dcp, udcp, hoirm.
    #[arg(long, default_value = "hoirm")]
    restore: String,
    /// No progress bar.
    #[arg(long)]
    no_progress: bool,
    /// Water presets file (configs/water.toml format), e.g. OUT/water-calibrated.toml from `calibrate-water`.
    #[arg(long)]
    water: Option<PathBuf>,
    /// Also save the first frame of every condition, raw and restored, as PNG under OUT/frames/.
    #[arg(long)]
    save_frames: bool,
}

pub fn run_eval(a: EvalArgs) -> anyhow::Result<()> {
    let experiment: Experiment = a.experiment.parse()?;
    let restore: Method = a.restore.parse()?;
    let opts = EvalOptions {
        out: a.out.clone(),
        quick: a.quick,
        frames: a.frames,
        seed: a.seed,
        restore,
        progress: !a.no_progress,
        save_frames: a.save_frames,
        water: a.water.clone(),
    };
    let summary = eval::run(experiment, &opts).with_context(|| format!("eval {experiment}"))?;
    println!("{}", serde_json::to_string_pretty(&summary)?);
    println!("wrote {}", a.out.join("summary.json").display());
    Ok(())
}
