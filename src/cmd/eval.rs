//! `shoal eval <experiment>`: the paper's measurements repeated on shoal
//! (library: `shoal::eval`); `shoal eval probe <name>`: the diagnostics
//! (`shoal::eval::probe`).

use anyhow::Context;
use clap::{Args, Subcommand};
use shoal::eval::{self, EvalOptions, Experiment};
use shoal_node::restore::Method;
use std::path::PathBuf;

#[derive(Debug, Args)]
#[command(args_conflicts_with_subcommands = true, subcommand_negates_reqs = true)]
pub struct EvalArgs {
    #[command(subcommand)]
    command: Option<EvalCmd>,
    /// features | accuracy | accuracy-yaw | accuracy-rmse | detection | restoration | calibrate-water | fit-noise | fusion | swarm | links | nav | real | refraction | node-rate | profiles | nees
    #[arg(required = true)]
    experiment: Option<String>,
    /// Output directory: CSV of every trial, plots (PNG, SVG), summary.json.
    #[arg(long, required = true)]
    out: Option<PathBuf>,
    /// The reduced run used in CI (well under a minute each in a debug build).
    #[arg(long)]
    quick: bool,
    /// Frames (or trials) per condition, overriding the experiment's default (100 frames, 1000 trials).
    #[arg(long)]
    frames: Option<usize>,
    /// Seed of every random stream (pose jitter, sensor noise).
    #[arg(long, default_value_t = 1)]
    seed: u64,
    /// Restoration applied to every marker's frames in the accuracy experiments and to every camera in `swarm`: none, clahe, dcp, udcp, hoirm.
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
    /// Set a restoration parameter (a `RestoreParams` field) for every restorer of the experiment, e.g. `psf_px_per_unit=8`, `order=physical`; repeatable.
    #[arg(long = "restore-param", value_name = "NAME=VALUE")]
    restore_param: Vec<String>,
    // The camera profile the frames are rendered through (issue #16). Taken by
    // `detection`, `restoration`, `accuracy`, `accuracy-yaw`, `accuracy-rmse`, `fit-noise`,
    // `swarm` and `node-rate`; `fusion`, `links` and `nav` take `realistic` as the
    // observation model fitted to that camera; the other experiments refuse it
    // (`eval::run`, naming the experiment).
    #[command(flatten)]
    profile: shoal::eval::profiles::ProfileArgs,
    /// `real`: the folder of real recordings, one sub-folder with an eval.json each (default: $SHOAL_REAL_DATA, ../shared/data/real, data/real).
    #[arg(long)]
    data: Option<PathBuf>,
    /// `real`: only this split of each recording (`dev` while tuning; `holdout` only for the final figure).
    #[arg(long)]
    split: Option<String>,
}

#[derive(Debug, Subcommand)]
enum EvalCmd {
    /// Diagnostics kept from development: one stage questioned on simulated (or recorded) data, printed as text.
    #[command(subcommand)]
    Probe(shoal::eval::probe::Probe),
    /// Copy the public recordings' frames (each manifest's `fetch` block under configs/real/) into the data folder, checked against their SHA-256.
    StageReal {
        /// The data folder (default: $SHOAL_REAL_DATA, else ../shared/data/real).
        #[arg(long)]
        data: Option<PathBuf>,
        /// Take the repositories from local mirrors (`DIR/<owner>+<name>/repo` or `DIR/<owner>+<name>.git`) instead of cloning from GitHub.
        #[arg(long)]
        mirrors: Option<PathBuf>,
    },
}

pub fn run_eval(a: EvalArgs) -> anyhow::Result<()> {
    match &a.command {
        Some(EvalCmd::Probe(p)) => return Ok(shoal::eval::probe::run(p)?),
        Some(EvalCmd::StageReal { data, mirrors }) => {
            return stage_real(data.as_deref(), mirrors.as_deref())
        }
        None => {}
    }
    let (Some(name), Some(out)) = (&a.experiment, &a.out) else {
        anyhow::bail!("shoal eval needs an experiment and --out (or `probe <name>`)");
    };
    let experiment: Experiment = name.parse()?;
    let restore: Method = a.restore.parse()?;
    let opts = EvalOptions {
        out: out.clone(),
        quick: a.quick,
        frames: a.frames,
        seed: a.seed,
        restore,
        progress: !a.no_progress,
        save_frames: a.save_frames,
        water: a.water.clone(),
        data: a.data.clone(),
        split: a.split.clone(),
        restore_params: eval::restore_params::from_assignments(&a.restore_param)?,
        profile: a
            .profile
            .selected(None)
            .context("the camera profile (--profile, --effect, --profile-file)")?,
    };
    let summary = eval::run(experiment, &opts).with_context(|| format!("eval {experiment}"))?;
    shoal::outln!("{}", serde_json::to_string_pretty(&summary)?);
    shoal::outln!("wrote {}", out.join("summary.json").display());
    Ok(())
}

/// `shoal eval stage-real`.
fn stage_real(
    data: Option<&std::path::Path>,
    mirrors: Option<&std::path::Path>,
) -> anyhow::Result<()> {
    let root = match (data, std::env::var_os("SHOAL_REAL_DATA")) {
        (Some(d), _) => d.to_path_buf(),
        (None, Some(d)) => PathBuf::from(d),
        (None, None) => PathBuf::from(eval::real::DEFAULT_DATA_DIRS[0]),
    };
    let staged = eval::real::stage_all(&root, eval::real::manifest_dir(), mirrors, &mut |line| {
        eprintln!("{line}");
    })
    .with_context(|| format!("staging the real recordings into {}", root.display()))?;
    let written: usize = staged.iter().map(|s| s.written).sum();
    let present: usize = staged.iter().map(|s| s.present).sum();
    println!(
        "{} recordings under {}: {written} files written, {present} already staged",
        staged.len(),
        root.display()
    );
    Ok(())
}
