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
use shoal_node::detect::{DetectParams, MarkerDetector, ShoalDetector};
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
    let mut opencv = OpenCvAruco::new(codes)?;
    let (mut t_shoal, mut t_opencv, mut n_shoal, mut n_opencv) = (0.0, 0.0, 0, 0);
    for _ in 0..2 {
        for gray in &frames {
            let t = Instant::now();
            n_shoal += shoal.detect(gray)?.len();
            t_shoal += t.elapsed().as_secs_f64();
            let t = Instant::now();
            n_opencv += opencv.detect(gray)?.len();
            t_opencv += t.elapsed().as_secs_f64();
        }
    }
    let n = 2.0 * frames.len() as f64;
    println!(
        "{} frames ({codes}): shoal {:.3} ms/frame ({n_shoal} reads), OpenCV ArUco {:.3} ms/frame ({n_opencv} reads), shoal/OpenCV {:.2}",
        frames.len(),
        t_shoal / n * 1e3,
        t_opencv / n * 1e3,
        t_shoal / t_opencv
    );
    Ok(())
}
