//! `shoal board generate` and `shoal calibrate`: print a board, calibrate a
//! camera from it (`shoal_node::board`, `shoal_node::calibrate`).

use anyhow::{bail, Context};
use clap::{Args, Subcommand};
use shoal_node::board::{Board, BoardDetector};
use shoal_node::calibrate::{self, CalibrateOptions, CalibrationInput, LensKind};
use shoal_proto::config::{write_calibration_yaml, CalibrationFormat};
use shoal_proto::files::OutputFile;
use shoal_proto::CodeSet;
use std::path::PathBuf;

/// Which board: a ChArUco board (`--charuco COLSxROWS`) or a grid of shoal markers (`--shoal-grid COLSxROWS`).
#[derive(Debug, Args, Clone)]
pub struct BoardArgs {
    /// A ChArUco board of COLSxROWS squares (e.g. 5x7), OpenCV 4.6's layout.
    #[arg(long, value_name = "COLSxROWS", conflicts_with = "shoal_grid")]
    charuco: Option<String>,
    /// Side of a ChArUco square, millimetres (measure the print).
    #[arg(long, default_value_t = 40.0, value_parser = super::args::positive)]
    square_mm: f64,
    /// Side of a ChArUco marker, millimetres.
    #[arg(long, default_value_t = 30.0, value_parser = super::args::positive)]
    marker_mm: f64,
    /// The ChArUco markers' dictionary: aruco4x4_50 … aruco6x6_1000.
    #[arg(long, default_value = "aruco4x4_50")]
    dict: String,
    /// A grid of COLSxROWS shoal markers (12 corners each).
    #[arg(long, value_name = "COLSxROWS")]
    shoal_grid: Option<String>,
    /// Footprint of a grid marker (its outer black frame), millimetres.
    #[arg(long, default_value_t = 100.0, value_parser = super::args::positive)]
    side_mm: f64,
    /// Gap between grid markers, edge to edge, millimetres (at least two quiet zones).
    #[arg(long, default_value_t = 30.0, value_parser = super::args::positive)]
    gap_mm: f64,
    /// ID of the grid's first marker (row by row from the top left).
    #[arg(long, default_value_t = 0)]
    first_id: u32,
}

fn cols_rows(s: &str, flag: &str) -> anyhow::Result<(u32, u32)> {
    let (c, r) = s
        .split_once(['x', 'X'])
        .with_context(|| format!("{flag} {s}: expected COLSxROWS, e.g. 5x7"))?;
    let parse = |v: &str| {
        v.trim()
            .parse::<u32>()
            .with_context(|| format!("{flag} {s}: `{v}` is not a whole number"))
    };
    Ok((parse(c)?, parse(r)?))
}

impl BoardArgs {
    pub fn board(&self) -> anyhow::Result<Board> {
        let board = match (&self.charuco, &self.shoal_grid) {
            (Some(cr), None) => {
                let (cols, rows) = cols_rows(cr, "--charuco")?;
                Board::Charuco {
                    cols,
                    rows,
                    square_m: self.square_mm / 1e3,
                    marker_m: self.marker_mm / 1e3,
                    codes: self.dict.parse::<CodeSet>()?,
                }
            }
            (None, Some(cr)) => {
                let (cols, rows) = cols_rows(cr, "--shoal-grid")?;
                Board::ShoalGrid {
                    cols,
                    rows,
                    side_m: self.side_mm / 1e3,
                    gap_m: self.gap_mm / 1e3,
                    first_id: self.first_id,
                }
            }
            _ => bail!("give the board: --charuco COLSxROWS or --shoal-grid COLSxROWS"),
        };
        board.validate()?;
        Ok(board)
    }
}

#[derive(Debug, Subcommand)]
pub enum BoardCmd {
    /// Write a printable calibration board at true size (SVG in millimetres, or PNG at --dpi).
    Generate {
        #[command(flatten)]
        board: BoardArgs,
        /// Output file: `.svg` or `.png`.
        #[arg(long)]
        out: PathBuf,
        /// Resolution of a PNG.
        #[arg(long, default_value_t = 300.0, value_parser = super::args::positive)]
        dpi: f64,
    },
}

pub fn run_board(cmd: BoardCmd) -> anyhow::Result<()> {
    let BoardCmd::Generate { board, out, dpi } = cmd;
    let board = board.board()?;
    let ext = out
        .extension()
        .and_then(|e| e.to_str())
        .unwrap_or("")
        .to_ascii_lowercase();
    let bytes = match ext.as_str() {
        "svg" => board.svg()?.into_bytes(),
        "png" => board.png(dpi)?,
        _ => bail!("{}: output must end in .svg or .png", out.display()),
    };
    OutputFile::write_whole(&out, &[], &bytes)?;
    let (w, h) = board.size_m();
    shoal::outln!(
        "wrote {} ({}; pattern {:.1} x {:.1} mm)",
        out.display(),
        board.describe(),
        w * 1e3,
        h * 1e3
    );
    Ok(())
}

#[derive(Debug, Args)]
pub struct CalibrateArgs {
    #[command(flatten)]
    board: BoardArgs,
    /// Lens model: plumb_bob, rational_polynomial or equidistant (fisheye).
    #[arg(long, default_value = "plumb_bob")]
    model: String,
    /// The calibration, as OpenCV YAML (`shoal node`, `shoal detect --camera` and OpenCV read it).
    #[arg(long)]
    out: PathBuf,
    /// Also as ROS `camera_info` YAML.
    #[arg(long)]
    ros_out: Option<PathBuf>,
    /// ROS `camera_name`.
    #[arg(long, default_value = "camera")]
    name: String,
    /// A picture of where in the image board points were seen (PNG).
    #[arg(long)]
    coverage: Option<PathBuf>,
    /// Per-view report (JSON lines: name, points, reprojection RMS, tilt, or why it was rejected).
    #[arg(long)]
    report: Option<PathBuf>,
    /// Frames of a live camera (`camera:N` input) to read.
    #[arg(long, default_value_t = 300)]
    frames: u32,
    /// Images, folders of images, videos, or `camera:N` (a live camera).
    #[arg(required = true)]
    inputs: Vec<String>,
}

pub fn run_calibrate(a: CalibrateArgs) -> anyhow::Result<()> {
    let board = a.board.board()?;
    let lens: LensKind = a.model.parse().map_err(anyhow::Error::msg)?;
    let inputs: Vec<CalibrationInput> = a
        .inputs
        .iter()
        .map(|s| match s.strip_prefix("camera:") {
            Some(n) => n
                .parse()
                .map(|device| CalibrationInput::Camera {
                    device,
                    frames: a.frames,
                })
                .with_context(|| format!("{s}: expected camera:N (a device index)")),
            None => {
                let p = PathBuf::from(s);
                if !p.exists() {
                    bail!("{s}: no such file or folder");
                }
                Ok(CalibrationInput::Path(p))
            }
        })
        .collect::<anyhow::Result<_>>()?;
    let opts = CalibrateOptions {
        lens,
        ..CalibrateOptions::default()
    };
    let mut detector = BoardDetector::new(board)?;
    shoal::errln!("board: {}", board.describe());
    let mut frames = 0usize;
    let (views, size) = calibrate::gather_views(&inputs, &mut detector, &opts, |name, kept| {
        frames += 1;
        if frames.is_multiple_of(25) {
            shoal::errln!("{frames} frames read, {kept} views kept (last: {name})");
        }
    })?;
    let Some((width, height)) = size else {
        bail!("no frame could be read from the inputs");
    };
    for (name, why) in &views.rejected {
        shoal::errln!("not used: {name}: {why}");
    }
    let kept_points = views.kept.clone();
    let cal = calibrate::calibrate(views, width, height, &opts)?;
    print_summary(&cal, width, height);
    let m = &cal.model;
    let yaml = write_calibration_yaml(m, CalibrationFormat::OpenCv, &a.name, Some(cal.rms_px));
    OutputFile::write_whole(&a.out, &[], yaml.as_bytes())?;
    shoal::outln!("wrote {}", a.out.display());
    if let Some(p) = &a.ros_out {
        let yaml = write_calibration_yaml(m, CalibrationFormat::Ros, &a.name, Some(cal.rms_px));
        OutputFile::write_whole(p, &[], yaml.as_bytes())?;
        shoal::outln!("wrote {}", p.display());
    }
    if let Some(p) = &a.coverage {
        let kept: Vec<_> = kept_points
            .into_iter()
            .filter(|(n, _)| cal.views.iter().any(|v| &v.name == n))
            .collect();
        OutputFile::write_whole(p, &[], &calibrate::coverage_png(&kept, width, height)?)?;
        shoal::outln!("wrote {}", p.display());
    }
    if let Some(p) = &a.report {
        OutputFile::write_whole(p, &[], report_lines(&cal).as_bytes())?;
        shoal::outln!("wrote {}", p.display());
    }
    Ok(())
}

fn print_summary(cal: &calibrate::Calibration, width: u32, height: u32) {
    let m = &cal.model;
    shoal::outln!(
        "{}x{} {}: fx {:.2} fy {:.2} cx {:.2} cy {:.2}{}",
        width,
        height,
        m.distortion.ros_name(),
        m.fx,
        m.fy,
        m.cx,
        m.cy,
        cal.std_intrinsics
            .map(|s| format!(" (σ {:.2} {:.2} {:.2} {:.2} px)", s[0], s[1], s[2], s[3]))
            .unwrap_or_default()
    );
    shoal::outln!("distortion {:?}", m.distortion.coefficients());
    shoal::outln!(
        "{} views kept ({} rejected), reprojection RMS {:.3} px; board points in {:.0} % of the image",
        cal.views.len(),
        cal.rejected.len(),
        cal.rms_px,
        cal.coverage.fraction() * 100.0
    );
    for v in &cal.views {
        shoal::outln!(
            "  {:<50} {:>4} points  RMS {:.3} px  tilt {:>4.1}°",
            v.name,
            v.points,
            v.rms_px,
            v.tilt_deg
        );
    }
    for w in &cal.warnings {
        shoal::errln!("warning: {w}");
    }
}

fn report_lines(cal: &calibrate::Calibration) -> String {
    let mut out = String::new();
    for v in &cal.views {
        let line = serde_json::json!({
            "view": v.name, "kept": true, "points": v.points, "rms_px": v.rms_px, "tilt_deg": v.tilt_deg,
        });
        out.push_str(&format!("{line}\n"));
    }
    for (name, why) in &cal.rejected {
        let line = serde_json::json!({"view": name, "kept": false, "reason": why.to_string()});
        out.push_str(&format!("{line}\n"));
    }
    out
}
