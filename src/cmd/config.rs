use anyhow::Context;
use clap::Subcommand;
use shoal_proto::config::{parse_calibration_yaml, Fleet};
use std::path::PathBuf;

#[derive(Debug, Subcommand)]
pub enum ConfigCmd {
    /// Load and validate a fleet file (TOML) or a camera calibration (OpenCV/ROS YAML), and print a summary.
    Check {
        /// `configs/fleets/paper.toml`, `configs/cameras/vehicle_1440.yaml`, …
        file: PathBuf,
    },
    /// Write the Zenoh router configuration (mutual TLS + access control) for a fleet:
    /// each `vehicle-<id>` certificate may publish only under its own ID (docs/deploy.md).
    RouterAcl {
        #[arg(long, default_value = "configs/fleets/paper.toml")]
        fleet: PathBuf,
        /// The router's listening endpoint.
        #[arg(long, default_value = "tls/0.0.0.0:7447")]
        listen: String,
        /// Directory with the fleet CA (`ca.pem`) and the router's `router.pem` / `router.key`.
        #[arg(long, default_value = "/etc/shoal/tls")]
        tls_dir: PathBuf,
        /// Output file (default: standard output).
        #[arg(long)]
        out: Option<PathBuf>,
        /// The TLS files are on the router's host, not this one: do not check them here.
        #[arg(long)]
        files_elsewhere: bool,
    },
}

pub fn run(cmd: ConfigCmd) -> anyhow::Result<()> {
    match cmd {
        ConfigCmd::Check { file } => {
            let ext = file.extension().and_then(|e| e.to_str()).unwrap_or("");
            if ext == "yaml" || ext == "yml" {
                let text = shoal_proto::files::read_text_bounded(
                    &file,
                    shoal_proto::files::MAX_CONFIG_BYTES,
                )
                .with_context(|| format!("cannot read {}", file.display()))?;
                let m = parse_calibration_yaml(&text)
                    .map_err(|e| anyhow::anyhow!("{}: {e}", file.display()))?;
                shoal::outln!(
                    "camera {}: {}x{}, fx {:.2} fy {:.2}, principal point ({:.2}, {:.2}), distortion {} {:?}",
                    file.display(),
                    m.width,
                    m.height,
                    m.fx,
                    m.fy,
                    m.cx,
                    m.cy,
                    m.distortion.ros_name(),
                    m.distortion.coefficients()
                );
            } else {
                let fleet = Fleet::load(&file)?;
                shoal::out!("{}", fleet.summary());
                shoal::outln!("ok");
            }
            Ok(())
        }
        ConfigCmd::RouterAcl {
            fleet,
            listen,
            tls_dir,
            out,
            files_elsewhere,
        } => {
            let fleet = Fleet::load(&fleet)?;
            let tls = shoal_bus::acl::TlsFiles::in_dir(tls_dir);
            let text = shoal_bus::acl::router_config(&fleet, &listen, &tls)?;
            let problems = tls.problems();
            if !files_elsewhere && !problems.is_empty() {
                anyhow::bail!(
                    "the router could not start with these TLS files:\n  {}\n(make them with docs/deploy.md section 1, or pass --files-elsewhere when they are on the router's host)",
                    problems.join("\n  ")
                );
            }
            match out {
                Some(path) => {
                    shoal_proto::files::OutputFile::write_whole(
                        &path,
                        &[&fleet.source],
                        text.as_bytes(),
                    )?;
                    shoal::errln!(
                        "wrote {} ({} vehicles)",
                        path.display(),
                        fleet.vehicles.len()
                    );
                }
                None => shoal::out!("{text}"),
            }
            Ok(())
        }
    }
}
