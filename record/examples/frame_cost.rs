//! Cost of recording camera frames, stage by stage, on the frames of a real
//! log: `cargo run -p shoal-record --example frame_cost -- LOG.mcap [zstd_level [raw]]`.

use shoal_record::foxglove;
use shoal_record::reader::{read_file, scan, Item};
use shoal_record::writer::{LogWriter, WriterOptions};
use std::time::Instant;

fn main() -> Result<(), Box<dyn std::error::Error>> {
    let args: Vec<String> = std::env::args().collect();
    let path = std::path::PathBuf::from(
        args.get(1)
            .ok_or("usage: frame_cost LOG.mcap [zstd_level]")?,
    );
    let level: u32 = args.get(2).map_or(Ok(0), |s| s.parse())?;
    let raw_only = args.get(3).is_some_and(|a| a == "raw");
    let buf = read_file(&path)?;
    let fleet = shoal_record::refuse::fleet_of(&buf, &path)?;
    let mut frames: Vec<(String, Vec<u8>)> = Vec::new();
    scan(&buf, |item| -> Result<(), shoal_record::reader::Stop> {
        if let Item::Message { channel, data, .. } = item {
            if channel.is_wire() && channel.topic.ends_with("/frame") && frames.len() < 60 {
                frames.push((channel.topic.clone(), data.to_vec()));
            }
        }
        Ok(())
    })
    .map_err(|e| e.to_string())?;
    let n = frames.len() as f64;
    let out = std::env::temp_dir().join("frame_cost.mcap");
    let opts = WriterOptions {
        zstd_level: level,
        ..WriterOptions::default()
    };
    let (mut t_png_only, mut t_b64) = (0.0, 0.0);
    let (mut t_decode, mut t_png, mut t_raw_write, mut t_fox_write) = (0.0, 0.0, 0.0, 0.0);
    let mut w = LogWriter::create(&out, &opts, &Default::default(), None, 0)?;
    for (i, (key, bytes)) in frames.iter().enumerate() {
        let t = Instant::now();
        let f = foxglove::FrameView::parse(bytes).ok_or("not a frame")?;
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
        )?;
        t_png_only += t.elapsed().as_secs_f64();
        let t = Instant::now();
        let _ = foxglove::base64(&png);
        t_b64 += t.elapsed().as_secs_f64();
        let t = Instant::now();
        let m = foxglove::camera_image(&fleet, &f)?;
        t_png += t.elapsed().as_secs_f64();
        let t = Instant::now();
        w.write_wire(
            key,
            Some(shoal_proto::MessageKind::CameraFrame),
            bytes,
            i as u64,
            i as u64,
        )?;
        w.flush()?;
        t_raw_write += t.elapsed().as_secs_f64();
        let t = Instant::now();
        if !raw_only {
            w.write_foxglove(&m.topic, m.schema, &m.value, i as u64, i as u64)?;
            w.flush()?;
        }
        t_fox_write += t.elapsed().as_secs_f64();
    }
    w.finish()?;
    let size = std::fs::metadata(&out)?.len() as f64;
    println!(
        "PNG alone {:.1} ms, base64 alone {:.1} ms",
        t_png_only / n * 1e3,
        t_b64 / n * 1e3
    );
    println!(
        "{} frames{}, zstd level {}: per frame decode {:.1} ms, PNG+base64+JSON {:.1} ms, raw write+zstd {:.1} ms, Foxglove write+zstd {:.1} ms; {:.2} MB per frame on disk (raw + PNG)",
        n,
        if raw_only { " (raw only)" } else { "" },
        if level == 0 { 3 } else { level },
        t_decode / n * 1e3,
        t_png / n * 1e3,
        t_raw_write / n * 1e3,
        t_fox_write / n * 1e3,
        size / n / 1e6
    );
    Ok(())
}
