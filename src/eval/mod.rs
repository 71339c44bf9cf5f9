//! `shoal eval <experiment>`: the paper's measurements (§3.1, §6) repeated on
//! shoal, with the baselines run on identical frames in the same run.
//!
//! Every experiment writes into its output directory a CSV of every trial or
//! frame, plots as PNG and SVG, and a `summary.json` holding its headline
//! figures under stable names (so a later run can be compared with an
//! earlier one), each beside the paper's figure where the paper gives one.
//!
//! | experiment        | paper                  | module          |
//! |-------------------|------------------------|-----------------|
//! | `features`        | §3.1, Fig. 3           | [`features`]    |
//! | `accuracy`        | §6.2, Figs. 11–14      | [`accuracy`]    |
//! | `accuracy-yaw`    | §6.2, Fig. 15          | [`accuracy`]    |
//! | `accuracy-rmse`   | §6.2, Figs. 16–17      | [`accuracy`]    |
//! | `detection`       | §6.1, Table 5          | [`detection`]   |
//! | `restoration`     | §6.1, Tables 1–4       | [`restoration`] |
//! | `calibrate-water` | Table 5's CLAHE row    | [`calibrate`]   |
//! | `fusion`          | (shoal's own)          | [`fusion`]      |
//! | `swarm`           | §6.3                   | [`swarm`]       |
//! | `links`           | (acoustic-rate links)  | [`links`]       |
//! | `nav`             | (vehicles' own nav)    | [`nav`]         |
//! | `real`            | (real recordings)      | [`real`]        |
//! | `refraction`      | (flat-port refraction) | [`refraction`]  |
//! | `profiles`        | (camera profiles, #16) | [`profiles`]    |
//! | `nees`            | (covariance, #16)      | [`nees`]        |
//!
//! `quick` runs a reduced version of each (seconds in a debug build) for CI.
//! The development probes (`shoal eval probe <name>`) are in [`probe`].

pub mod accuracy;
pub mod calibrate;
pub mod detection;
pub mod features;
pub mod fusion;
pub mod links;
pub mod nav;
pub mod nees;
pub mod node_rate;
pub mod noise;
pub mod plot;
pub mod probe;
pub mod profiles;
pub mod real;
pub mod refraction;
pub mod restoration;
pub mod restore_params;
pub mod scene;
pub mod swarm;
pub mod table;

use indicatif::{ProgressBar, ProgressStyle};
use shoal_node::restore::{Method, RestoreParams};
use shoal_sim_bridge::water::WaterPresets;
use std::path::{Path, PathBuf};

/// The experiments, in the order of issue #6's priorities.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum Experiment {
    Features,
    Accuracy,
    AccuracyYaw,
    AccuracyRmse,
    Detection,
    Restoration,
    CalibrateWater,
    FitNoise,
    Fusion,
    Swarm,
    Links,
    Nav,
    Real,
    Refraction,
    /// Issue #18: one vehicle's node fed its five cameras at 10 frames/s.
    NodeRate,
    /// Issue #16: the ideal against the realistic camera profile.
    Profiles,
    /// Issue #16: covariance honesty of the node as shipped.
    Nees,
    /// Issue #16: the simulator set to a real recording's conditions, against it.
    RealTwin,
}

impl Experiment {
    pub const ALL: [Experiment; 18] = [
        Experiment::Features,
        Experiment::Accuracy,
        Experiment::AccuracyYaw,
        Experiment::AccuracyRmse,
        Experiment::Detection,
        Experiment::Restoration,
        Experiment::CalibrateWater,
        Experiment::FitNoise,
        Experiment::Fusion,
        Experiment::Swarm,
        Experiment::Links,
        Experiment::Nav,
        Experiment::Real,
        Experiment::Refraction,
        Experiment::NodeRate,
        Experiment::Profiles,
        Experiment::Nees,
        Experiment::RealTwin,
    ];

    pub fn name(self) -> &'static str {
        match self {
            Experiment::Features => "features",
            Experiment::Accuracy => "accuracy",
            Experiment::AccuracyYaw => "accuracy-yaw",
            Experiment::AccuracyRmse => "accuracy-rmse",
            Experiment::Detection => "detection",
            Experiment::Restoration => "restoration",
            Experiment::CalibrateWater => "calibrate-water",
            Experiment::FitNoise => "fit-noise",
            Experiment::Fusion => "fusion",
            Experiment::Swarm => "swarm",
            Experiment::Links => "links",
            Experiment::Nav => "nav",
            Experiment::Real => "real",
            Experiment::Refraction => "refraction",
            Experiment::NodeRate => "node-rate",
            Experiment::Profiles => "profiles",
            Experiment::Nees => "nees",
            Experiment::RealTwin => "real-twin",
        }
    }
}

impl std::fmt::Display for Experiment {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.write_str(self.name())
    }
}

impl std::str::FromStr for Experiment {
    type Err = EvalError;
    fn from_str(s: &str) -> Result<Self, Self::Err> {
        Experiment::ALL
            .into_iter()
            .find(|e| e.name().eq_ignore_ascii_case(s.trim()))
            .ok_or_else(|| EvalError::UnknownExperiment {
                name: s.to_string(),
                known: Experiment::ALL.map(|e| e.name()).join(", "),
            })
    }
}

/// How to run an experiment.
#[derive(Debug, Clone)]
pub struct EvalOptions {
    /// Output directory (created if missing).
    pub out: PathBuf,
    /// The reduced CI variant.
    pub quick: bool,
    /// Frames (or trials) per condition, overriding the experiment's default.
    pub frames: Option<usize>,
    /// Seeds every random stream (pose jitter, sensor noise).
    pub seed: u64,
    /// Restoration applied to the frames of every marker in the accuracy
    /// experiments (the same for all methods, so only the markers and their
    /// detectors differ).
    pub restore: Method,
    /// Show a progress bar on stderr.
    pub progress: bool,
    /// Save the first frame of every condition (raw and restored PNG) under `out/frames/`.
    pub save_frames: bool,
    /// Water presets file (`configs/water.toml` format, e.g. the output of
    /// `calibrate-water`); `None` = the built-in presets.
    pub water: Option<PathBuf>,
    /// Root of the real recordings for `real` (`None`: [`real::data_root`]'s defaults).
    pub data: Option<PathBuf>,
    /// `real`: run only the named split of every recording (e.g. `dev` while tuning).
    pub split: Option<String>,
    /// Parameters of every restorer the experiment builds (tuning runs:
    /// `--restore-param`, [`restore_params`]); default [`RestoreParams::default`].
    pub restore_params: RestoreParams,
    /// The camera profile frames are rendered through (`--profile`, issue
    /// #16); `None`: the ideal renderer every figure used so far. Taken by
    /// [`PROFILE_EXPERIMENTS`] only; the others refuse it.
    pub profile: Option<shoal_sim_bridge::profile::CameraProfile>,
}

/// The experiments that render through `--profile` (the rest refuse it
/// rather than ignore it).
pub const PROFILE_EXPERIMENTS: [Experiment; 11] = [
    Experiment::Detection,
    Experiment::Restoration,
    Experiment::Accuracy,
    Experiment::AccuracyYaw,
    Experiment::AccuracyRmse,
    Experiment::FitNoise,
    Experiment::Swarm,
    Experiment::NodeRate,
    // No images: their observation model fitted to `realistic` (`ObsSynthParams::realistic`).
    Experiment::Fusion,
    Experiment::Links,
    Experiment::Nav,
];

impl EvalOptions {
    /// The camera profile's name for summaries and plot titles (`ideal`
    /// without `--profile`).
    pub fn profile_name(&self) -> &str {
        self.profile.as_ref().map_or("ideal", |p| p.name.as_str())
    }

    /// Through `--profile`: the profile with its effects seeded by the run's
    /// seed, and the calibration the node would hold (through the port, a
    /// lab's in-water calibration; moved by the calibration error) as the
    /// detectors' and PnP's lens. Without it: no profile, `cam` itself.
    pub fn seeded_profile_and_lens(
        &self,
        cam: &shoal_proto::CameraModel,
    ) -> Result<
        (
            Option<shoal_sim_bridge::profile::CameraProfile>,
            shoal_proto::CameraModel,
        ),
        EvalError,
    > {
        let profile = self.profile.clone().map(|p| p.with_seed(self.seed));
        let lens = match &profile {
            Some(p) => profiles::node_camera(p, cam, self.seed)?,
            None => *cam,
        };
        Ok((profile, lens))
    }

    /// Defaults: full run, seed 1, HOIRM for every marker, progress bar on.
    pub fn new(out: impl Into<PathBuf>) -> EvalOptions {
        EvalOptions {
            out: out.into(),
            quick: false,
            frames: None,
            seed: 1,
            restore: Method::Hoirm,
            progress: true,
            save_frames: false,
            water: None,
            data: None,
            split: None,
            restore_params: RestoreParams::default(),
            profile: None,
        }
    }

    /// The water presets to render with: `water` if given, else the built-in ones.
    pub fn presets(&self) -> Result<WaterPresets, EvalError> {
        match &self.water {
            Some(path) => Ok(WaterPresets::load(path)?),
            None => Ok(WaterPresets::builtin()),
        }
    }

    /// `frames` if given, else `quick` or `full`.
    pub fn count(&self, quick: usize, full: usize) -> usize {
        self.frames
            .unwrap_or(if self.quick { quick } else { full })
            .max(1)
    }

    /// A progress bar of `len` steps (hidden unless `progress`).
    pub fn bar(&self, len: usize, what: &str) -> ProgressBar {
        if !self.progress {
            return ProgressBar::hidden();
        }
        let bar = ProgressBar::new(len as u64);
        if let Ok(style) = ProgressStyle::with_template(
            "{msg:>24} [{bar:40}] {pos}/{len} {elapsed_precise} (eta {eta})",
        ) {
            bar.set_style(style.progress_chars("=> "));
        }
        bar.set_message(what.to_string());
        bar
    }
}

/// Errors of the evaluation.
#[derive(Debug, thiserror::Error)]
pub enum EvalError {
    #[error("{}: {source}", path.display())]
    Io {
        path: PathBuf,
        #[source]
        source: std::io::Error,
    },
    #[error("rendering: {0}")]
    Render(#[from] shoal_sim_bridge::SimError),
    #[error("restoration: {0}")]
    Restore(#[from] shoal_node::restore::RestoreError),
    #[error("detection: {0}")]
    Detect(#[from] shoal_node::detect::DetectError),
    /// Restoring and detecting as the node does (its messages name the stage).
    #[error("{0}")]
    Pipeline(#[from] shoal_node::pipeline::PipelineError),
    #[error("image: {0}")]
    Image(#[from] shoal_node::mat::MatError),
    #[error("image metric: {0}")]
    Metric(#[from] shoal_node::metrics::MetricError),
    #[error("plot {}: {reason}", path.display())]
    Plot { path: PathBuf, reason: String },
    #[error("writing summary: {0}")]
    Json(#[from] serde_json::Error),
    #[error("setting up the experiment: {0}")]
    Setup(String),
    #[error("OpenCV: {0}")]
    OpenCv(String),
    #[error("unknown experiment {name:?}; known: {known}")]
    UnknownExperiment { name: String, known: String },
}

impl From<opencv::Error> for EvalError {
    fn from(e: opencv::Error) -> Self {
        EvalError::OpenCv(e.to_string())
    }
}

/// Run `experiment` into `opts.out`; returns the summary it wrote to `summary.json`.
pub fn run(experiment: Experiment, opts: &EvalOptions) -> Result<serde_json::Value, EvalError> {
    std::fs::create_dir_all(&opts.out).map_err(|source| EvalError::Io {
        path: opts.out.clone(),
        source,
    })?;
    if let Some(profile) = &opts.profile {
        if !PROFILE_EXPERIMENTS.contains(&experiment) {
            return Err(EvalError::Setup(format!(
                "camera profile `{}` (--profile, --effect, --profile-file): `{}` renders only \
                 through the ideal camera so far; the experiments that take a profile: {}",
                profile.name,
                experiment.name(),
                PROFILE_EXPERIMENTS.map(|e| e.name()).join(", ")
            )));
        }
    }
    let started = std::time::Instant::now();
    let mut summary = match experiment {
        Experiment::Features => features::run(opts)?,
        Experiment::Accuracy => accuracy::run_main(opts)?,
        Experiment::AccuracyYaw => accuracy::run_yaw(opts)?,
        Experiment::AccuracyRmse => accuracy::run_rmse(opts)?,
        Experiment::Detection => detection::run(opts)?,
        Experiment::Restoration => restoration::run(opts)?,
        Experiment::CalibrateWater => calibrate::run(opts)?,
        Experiment::FitNoise => noise::run(opts)?,
        Experiment::Fusion => fusion::run(opts)?,
        Experiment::Swarm => swarm::run(opts)?,
        Experiment::Links => links::run(opts)?,
        Experiment::Nav => nav::run(opts)?,
        Experiment::Real => real::run(opts)?,
        Experiment::Refraction => refraction::run(opts)?,
        Experiment::NodeRate => node_rate::run(opts)?,
        Experiment::Profiles => profiles::run(opts)?,
        Experiment::Nees => nees::run(opts)?,
        Experiment::RealTwin => real::twin::run(opts)?,
    };
    if let Some(obj) = summary.as_object_mut() {
        obj.insert("experiment".into(), experiment.name().into());
        obj.insert("quick".into(), opts.quick.into());
        obj.insert("seed".into(), opts.seed.into());
        obj.insert(
            "elapsed_s".into(),
            ((started.elapsed().as_secs_f64() * 10.0).round() / 10.0).into(),
        );
        obj.insert(
            "water_presets".into(),
            opts.water
                .as_ref()
                .map_or("built-in (configs/water.toml)".to_string(), |p| {
                    p.display().to_string()
                })
                .into(),
        );
        if opts.restore_params != RestoreParams::default() {
            obj.insert(
                "restore_params".into(),
                format!("{:?}", opts.restore_params).into(),
            );
        }
        obj.insert(
            "build".into(),
            if cfg!(debug_assertions) {
                "debug"
            } else {
                "release"
            }
            .into(),
        );
    }
    write_json(&opts.out.join("summary.json"), &summary)?;
    Ok(summary)
}

/// Write pretty JSON.
/// `VmRSS` and `VmHWM` (the peak since the process started or since
/// [`reset_peak_resident`]) of this process, kB.
pub(crate) fn resident_kb() -> (Option<u64>, Option<u64>) {
    let status = std::fs::read_to_string("/proc/self/status").unwrap_or_default();
    let field = |name: &str| {
        status
            .lines()
            .find(|l| l.starts_with(name))
            .and_then(|l| l.split_whitespace().nth(1))
            .and_then(|v| v.parse().ok())
    };
    (field("VmRSS:"), field("VmHWM:"))
}

/// Set this process's `VmHWM` back to its present resident size (Linux
/// 4.0 on: `5` into `/proc/self/clear_refs`), so the next [`resident_kb`]
/// gives the peak since now. False where the kernel does not allow it.
pub(crate) fn reset_peak_resident() -> bool {
    std::fs::write("/proc/self/clear_refs", "5").is_ok()
}

pub fn write_json(path: &Path, value: &serde_json::Value) -> Result<(), EvalError> {
    let text = serde_json::to_string_pretty(value)?;
    std::fs::write(path, text + "\n").map_err(|source| EvalError::Io {
        path: path.to_path_buf(),
        source,
    })
}

/// A water key for summaries, as the paper writes it: `"0.126"`, `"8.22"`, `"14.20"`.
pub fn water_key(c_per_m: f64) -> String {
    let hundredths = c_per_m * 100.0;
    if (hundredths - hundredths.round()).abs() < 1e-6 {
        format!("{c_per_m:.2}")
    } else {
        format!("{c_per_m:.3}")
    }
}
