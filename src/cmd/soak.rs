//! `shoal soak`: the simulated swarm for an hour with faults on a schedule,
//! watching memory, open files and the ground station's maps (`shoal::soak`).

use clap::Args;
use shoal::soak::{run, SoakConfig};
use std::path::PathBuf;
use std::sync::atomic::AtomicBool;
use std::sync::Arc;

#[derive(Debug, Args)]
pub struct SoakArgs {
    /// Seconds of wall time.
    #[arg(long, default_value_t = 3600.0, value_parser = super::args::positive)]
    duration_s: f64,
    /// One cycle of faults (link cut, fusion restart, a vehicle's session closed) every this many seconds.
    #[arg(long, default_value_t = 60.0, value_parser = super::args::positive)]
    every_s: f64,
    /// How long each link cut lasts, seconds.
    #[arg(long, default_value_t = 5.0, value_parser = super::args::positive)]
    partition_s: f64,
    /// Bound on the time to a map with every vehicle Live after each fault, seconds.
    #[arg(long, default_value_t = 10.0, value_parser = super::args::positive)]
    recover_s: f64,
    #[arg(long, default_value_t = 7)]
    seed: u64,
    /// Also write the whole report (events, resource samples) as JSON here.
    #[arg(long)]
    report: Option<PathBuf>,
}

pub fn run_soak(a: SoakArgs) -> anyhow::Result<()> {
    let cfg = SoakConfig {
        duration_s: a.duration_s,
        every_s: a.every_s,
        partition_s: a.partition_s,
        recover_s: a.recover_s,
        seed: a.seed,
    };
    // Ctrl-C / SIGTERM end the run early with a report; a second one exits at once.
    let stop = Arc::new(AtomicBool::new(false));
    for sig in [signal_hook::consts::SIGINT, signal_hook::consts::SIGTERM] {
        signal_hook::flag::register_conditional_shutdown(sig, 130, stop.clone())?;
        signal_hook::flag::register(sig, stop.clone())?;
    }
    let report = run(&cfg, &stop, |line| shoal::errln!("{line}"))?;
    if let Some(path) = &a.report {
        let json = serde_json::to_vec_pretty(&report)?;
        shoal_proto::files::OutputFile::write_whole(path, &[], &json)?;
    }
    shoal::out!("{}", report.summary());
    if !report.passed() {
        anyhow::bail!("the soak found {} problem(s)", report.problems.len());
    }
    Ok(())
}
