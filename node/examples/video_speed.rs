//! shoal's detector against OpenCV ArUco's on every frame of a video, one
//! thread, alternated frame by frame (twice over), the frames decoded to
//! grey beforehand: the per-frame times, the reads, and their ratio
//! (issue #15's speed target on real footage is a ratio ≤ 1).
//!
//! `cargo run --release -p shoal-node --example video_speed -- VIDEO [CODES]`
//! (CODES as `shoal detect --codes`, default apriltag16h5: the tank video).

use opencv::prelude::*;
use opencv::{imgproc, videoio};
use shoal_node::baseline::OpenCvAruco;
use shoal_node::detect::{ContrastOffset, DetectParams, MarkerDetector, ShoalDetector};
use shoal_proto::marker::CodeSet;
use std::time::Instant;

fn main() -> Result<(), Box<dyn std::error::Error>> {
    let mut args = std::env::args().skip(1);
    let path = args
        .next()
        .ok_or("usage: video_speed VIDEO [CODES] (e.g. test_vid.mp4 apriltag16h5)")?;
    let codes = CodeSet::from_name(&args.next().unwrap_or_else(|| "apriltag16h5".into()))?;
    opencv::core::set_num_threads(1)?;
    let mut cap = videoio::VideoCapture::from_file(&path, videoio::CAP_ANY)?;
    if !cap.is_opened()? {
        return Err(format!("{path}: not a video OpenCV can open").into());
    }
    let mut frames = Vec::new();
    let mut frame = Mat::default();
    while cap.read(&mut frame)? && !frame.empty() {
        let mut gray = Mat::default();
        imgproc::cvt_color(&frame, &mut gray, imgproc::COLOR_BGR2GRAY, 0)?;
        frames.push(gray);
    }
    if frames.is_empty() {
        return Err(format!("{path}: no frame decoded").into());
    }
    let mut shoal = ShoalDetector::new(codes, DetectParams::default());
    // The same detector with flat regions judged in grey levels alone, as
    // before the noise-relative rule (docs/detector.md, *Flat is relative
    // to the noise*).
    let defaults = DetectParams::default();
    let mut absolute = ShoalDetector::new(
        codes,
        DetectParams {
            contrast_offset: defaults.contrast_offset.map(|c| ContrastOffset {
                flat_below_sigmas: 0.0,
                ..c
            }),
            ..defaults
        },
    );
    let mut opencv = OpenCvAruco::new(codes)?;
    let (mut t, mut n_read) = ([0.0; 3], [0usize; 3]);
    for _ in 0..2 {
        for (i, gray) in frames.iter().enumerate() {
            // The two shoal detectors take turns at going first on a frame
            // (the first pays for bringing it into the cache).
            let order = if i % 2 == 0 { [0, 1, 2] } else { [1, 0, 2] };
            for k in order {
                let t0 = Instant::now();
                n_read[k] += match k {
                    0 => shoal.detect(gray)?.len(),
                    1 => absolute.detect(gray)?.len(),
                    _ => opencv.detect(gray)?.len(),
                };
                t[k] += t0.elapsed().as_secs_f64();
            }
        }
    }
    let ms = |s: f64| s / (2.0 * frames.len() as f64) * 1e3;
    println!(
        "{} frames ({codes}): shoal {:.3} ms/frame ({} reads), shoal with flat in grey levels {:.3} ms/frame ({} reads), OpenCV ArUco {:.3} ms/frame ({} reads); shoal/OpenCV {:.2}, flat in grey levels/OpenCV {:.2}",
        frames.len(),
        ms(t[0]),
        n_read[0],
        ms(t[1]),
        n_read[1],
        ms(t[2]),
        n_read[2],
        t[0] / t[2],
        t[1] / t[2]
    );
    Ok(())
}
