//! `shoal marker`, `shoal detect`, `shoal restore`: the tools a user points at their own markers and footage.

use anyhow::{bail, Context};
use clap::{Args, Subcommand};
use shoal_node::restore::{restore_file, Method};
use shoal_proto::config::parse_calibration_yaml;
use shoal_proto::CodeSet;
use std::path::PathBuf;

#[derive(Debug, Subcommand)]
pub enum MarkerCmd {
    /// Write a printable marker at true physical size (SVG, or PNG at --dpi), with ID, size and cut marks.
    Generate {
        /// Marker ID in the code set (the paper's vehicles: 10, 15, 17).
        #[arg(long)]
        id: u32,
        /// Side of the outer black square, millimetres.
        #[arg(long, default_value_t = 100.0, value_parser = super::args::positive)]
        size_mm: f64,
        /// Code set: shoal (the enhanced marker), aruco4x4_50, …, apriltag16h5, apriltag36h11.
        #[arg(long, default_value = "shoal")]
        codes: String,
        /// Output file: `.svg` or `.png`.
        #[arg(long)]
        out: PathBuf,
        /// Resolution of a PNG.
        #[arg(long, default_value_t = 300.0, value_parser = super::args::positive)]
        dpi: f64,
    },
}

pub fn run_marker(cmd: MarkerCmd) -> anyhow::Result<()> {
    let MarkerCmd::Generate {
        id,
        size_mm,
        codes,
        out,
        dpi,
    } = cmd;
    let codes: CodeSet = codes.parse()?;
    let ext = out
        .extension()
        .and_then(|e| e.to_str())
        .unwrap_or("")
        .to_ascii_lowercase();
    let bytes = match ext.as_str() {
        "svg" => shoal_node::print::marker_svg(codes, id, size_mm)?.into_bytes(),
        "png" => shoal_node::print::marker_png(codes, id, size_mm, dpi)?,
        _ => bail!("{}: output must end in .svg or .png", out.display()),
    };
    shoal_proto::files::OutputFile::write_whole(&out, &[], &bytes)?;
    shoal::outln!("wrote {} ({codes} #{id}, {size_mm} mm)", out.display());
    Ok(())
}

#[derive(Debug, Args)]
pub struct DetectArgs {
    /// Code set to read: shoal, aruco4x4_50 … aruco6x6_1000, apriltag16h5, apriltag36h11.
    #[arg(long, default_value = "shoal")]
    codes: String,
    /// Camera calibration (OpenCV or ROS YAML); with --size-mm, poses are printed too.
    #[arg(long)]
    camera: Option<PathBuf>,
    /// Marker side (outer black square), millimetres.
    #[arg(long, value_parser = super::args::positive)]
    size_mm: Option<f64>,
    /// Images, videos and/or folders (a folder: its images, sorted by name).
    #[arg(required = true)]
    inputs: Vec<PathBuf>,
}

pub fn run_detect(a: DetectArgs) -> anyhow::Result<()> {
    let codes: CodeSet = a.codes.parse()?;
    let camera = match &a.camera {
        Some(p) => {
            let text =
                shoal_proto::files::read_text_bounded(p, shoal_proto::files::MAX_CONFIG_BYTES)
                    .with_context(|| format!("cannot read {}", p.display()))?;
            Some(
                parse_calibration_yaml(&text)
                    .map_err(|e| anyhow::anyhow!("{}: {e}", p.display()))?,
            )
        }
        None => None,
    };
    if camera.is_some() != a.size_mm.is_some() {
        shoal::errln!("note: poses need both --camera and --size-mm; printing corners only");
    }
    let stdout = std::io::stdout();
    let mut out = stdout.lock();
    let summary = shoal_node::detect::detect_paths(
        &a.inputs,
        codes,
        camera,
        a.size_mm.map(|s| s / 1000.0),
        &mut out,
    )?;
    shoal::errln!(
        "{} files, {} frames, {} detections, {} unreadable or incomplete, {} warnings",
        summary.files,
        summary.frames,
        summary.detections,
        summary.errors,
        summary.warnings
    );
    if summary.errors > 0 && summary.frames == 0 {
        bail!("no input could be read");
    }
    if summary.errors > 0 {
        // What could be read is printed; the exit status says not everything was.
        bail!(
            "{} of {} inputs unreadable or incomplete (see their \"error\" lines)",
            summary.errors,
            summary.files
        );
    }
    Ok(())
}

#[derive(Debug, Args)]
pub struct RestoreArgs {
    /// Water attenuation coefficient, per metre (default: estimated from the image).
    #[arg(long, value_parser = super::args::non_negative)]
    water: Option<f64>,
    /// none, clahe, dcp, udcp, hoirm.
    #[arg(long, default_value = "hoirm")]
    method: String,
    input: PathBuf,
    output: PathBuf,
}

pub fn run_restore(a: RestoreArgs) -> anyhow::Result<()> {
    let method: Method = a.method.parse()?;
    restore_file(&a.input, &a.output, method, a.water)?;
    shoal::outln!("wrote {} ({method})", a.output.display());
    Ok(())
}
