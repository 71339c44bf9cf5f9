//! `shoal eval probe record-cost`: what recording a camera frame costs,
//! stage by stage (envelope decode, PNG, Foxglove protobuf, raw and
//! Foxglove writes with zstd), on the first 60 camera frames of a log. The
//! log is rewritten into a scratch file in the system's temporary folder,
//! removed afterwards.

use crate::eval::EvalError;
use shoal_record::foxglove;
use shoal_record::reader::{scan, Item};
use shoal_record::writer::{LogWriter, WriterOptions};
use std::path::PathBuf;
use std::time::Instant;

/// Frames taken from the log.
const MAX_FRAMES: usize = 60;

#[derive(Debug, clap::Args)]
pub struct RecordCostArgs {
    /// An MCAP log with camera frames (`shoal record --frames`, `shoal demo --mcap-frames`).
    #[arg(value_name = "LOG")]
    pub mcap: PathBuf,
    /// zstd level of the rewritten log (0 = the recorder's default).
    #[arg(long, default_value_t = 0)]
    pub zstd_level: u32,
    /// Write the wire bytes only (no Foxglove image channel).
    #[arg(long)]
    pub raw_only: bool,
}

fn setup(what: &str, e: impl std::fmt::Display) -> EvalError {
    EvalError::Setup(format!("{what}: {e}"))
}

pub fn run(a: &RecordCostArgs) -> Result<(), EvalError> {
    let path = &a.mcap;
    // The recorder's errors name the file themselves.
    let log = |e: shoal_record::RecordError| EvalError::Setup(e.to_string());
    let fleet = shoal_record::refuse::fleet_of(path, path).map_err(log)?;
    let mut frames: Vec<(String, Vec<u8>)> = Vec::new();
    scan(path, |item| -> Result<(), shoal_record::reader::Stop> {
        if let Item::Message { channel, data, .. } = item {
            if channel.is_wire() && channel.topic.ends_with("/frame") && frames.len() < MAX_FRAMES {
                frames.push((channel.topic.clone(), data.to_vec()));
            }
        }
        Ok(())
    })
    .map_err(|e| setup(&path.display().to_string(), e))?;
    if frames.is_empty() {
        return Err(setup(
            &path.display().to_string(),
            "no camera frame in the log",
        ));
    }
    let n = frames.len() as f64;
    let out = std::env::temp_dir().join(format!("shoal-record-cost-{}.mcap", std::process::id()));
    let opts = WriterOptions {
        zstd_level: a.zstd_level,
        ..WriterOptions::default()
    };
    let mut t_png_only = 0.0;
    let (mut t_decode, mut t_png, mut t_raw_write, mut t_fox_write) = (0.0, 0.0, 0.0, 0.0);
    let write = |e: shoal_record::RecordError| EvalError::Setup(e.to_string());
    let mut w = LogWriter::create(&out, &opts, &Default::default(), None, 0).map_err(write)?;
    for (i, (key, bytes)) in frames.iter().enumerate() {
        let t = Instant::now();
        let f =
            foxglove::FrameView::parse(bytes).ok_or_else(|| setup(key, "not a camera frame"))?;
        t_decode += t.elapsed().as_secs_f64();
        let t = Instant::now();
        let mut png = Vec::new();
        let enc = image::codecs::png::PngEncoder::new_with_quality(
            &mut png,
            image::codecs::png::CompressionType::Fast,
            image::codecs::png::FilterType::Sub,
        );
        image::ImageEncoder::write_image(
            enc,
            f.data,
            f.width,
            f.height,
            image::ExtendedColorType::L8,
        )
        .map_err(|e| setup(key, e))?;
        t_png_only += t.elapsed().as_secs_f64();
        let t = Instant::now();
        let m = foxglove::camera_image(&fleet, &f).map_err(|e| setup(key, e))?;
        t_png += t.elapsed().as_secs_f64();
        let t = Instant::now();
        w.write_wire(
            key,
            Some(shoal_proto::MessageKind::CameraFrame),
            bytes,
            i as u64,
            i as u64,
        )
        .map_err(write)?;
        w.flush().map_err(write)?;
        t_raw_write += t.elapsed().as_secs_f64();
        let t = Instant::now();
        if !a.raw_only {
            w.write_foxglove(&m, i as u64, i as u64).map_err(write)?;
            w.flush().map_err(write)?;
        }
        t_fox_write += t.elapsed().as_secs_f64();
    }
    w.finish().map_err(write)?;
    let size = std::fs::metadata(&out)
        .map_err(|source| EvalError::Io {
            path: out.clone(),
            source,
        })?
        .len() as f64;
    crate::outln!("PNG alone {:.1} ms", t_png_only / n * 1e3);
    crate::outln!(
        "{} frames{}, zstd level {}: per frame decode {:.1} ms, PNG+protobuf {:.1} ms, raw write+zstd {:.1} ms, Foxglove write+zstd {:.1} ms; {:.2} MB per frame on disk (raw + PNG)",
        n,
        if a.raw_only { " (raw only)" } else { "" },
        if a.zstd_level == 0 { 3 } else { a.zstd_level },
        t_decode / n * 1e3,
        t_png / n * 1e3,
        t_raw_write / n * 1e3,
        t_fox_write / n * 1e3,
        size / n / 1e6
    );
    // A scratch file: only its size was wanted.
    let _ = std::fs::remove_file(&out);
    Ok(())
}
