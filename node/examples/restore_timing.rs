//! Quick single-core timing of HOIRM and of the OpenCV operations it is
//! built from, on a synthetic 1440x1080 frame (the criterion bench
//! `benches/restore.rs` is the reference; this one is for profiling).
//!
//! Prints wall time and the thread's CPU time (robust to other load on the machine).
//!
//! `cargo run --release -p shoal-node --example restore_timing [frame.png ...]`

use opencv::core::{self, Mat, Rect, Size, CV_8U};
use opencv::imgproc;
use opencv::prelude::*;
use shoal_node::restore::psf::Wiener;
use shoal_node::restore::synthetic::{marker_frame, Degradation};
use shoal_node::restore::{water, Hoirm, RestoreParams};
use std::time::Instant;

/// CPU time of the calling thread, ns (Linux `schedstat`; `None` elsewhere):
/// unlike wall time it does not grow when other processes share the cores.
fn thread_cpu_ns() -> Option<u64> {
    let s = std::fs::read_to_string("/proc/thread-self/schedstat").ok()?;
    s.split_whitespace().next()?.parse().ok()
}

fn time<T>(name: &str, n: usize, mut f: impl FnMut() -> T) {
    let c0 = thread_cpu_ns();
    let t0 = Instant::now();
    for _ in 0..n {
        std::hint::black_box(f());
    }
    let wall = t0.elapsed().as_secs_f64() * 1e3 / n as f64;
    let cpu = match (c0, thread_cpu_ns()) {
        (Some(a), Some(b)) => format!("{:8.3} ms CPU", (b - a) as f64 * 1e-6 / n as f64),
        _ => String::new(),
    };
    println!("{name:<32} {wall:8.3} ms wall {cpu}");
}

fn main() {
    core::set_num_threads(1).unwrap();
    let f = marker_frame(1440, 1080, 500, 400, 24, &Degradation::for_c(10.13), 0)
        .unwrap()
        .degraded;
    let n = 40;
    let mut h = Hoirm::new(RestoreParams::default());
    let (r, p) = h.restore_with_params(&f, 0).unwrap();
    println!(
        "ROIs {:?}, level {}, psf {:?}",
        r.rois, r.pyramid_level, p.psf
    );
    let mut k = 0;
    time("hoirm_roi", n, || {
        k += 1;
        h.restore_with_params(&f, k * 33_000_000).unwrap()
    });
    // Frames given on the command line (e.g. simulator frames saved by
    // `shoal eval detection --save-frames`): HOIRM ROI-limited on each.
    for path in std::env::args().skip(1) {
        let g = opencv::imgcodecs::imread(&path, opencv::imgcodecs::IMREAD_GRAYSCALE).unwrap();
        if g.empty() {
            println!("{path}: not an image");
            continue;
        }
        // SHOAL_PSF_SIGMA_FROM_IMAGE=0: Eq. (14)'s σ only (to time the estimate).
        let params = RestoreParams {
            psf_sigma_from_image: std::env::var("SHOAL_PSF_SIGMA_FROM_IMAGE")
                .map_or(true, |v| v != "0"),
            ..RestoreParams::default()
        };
        let mut h = Hoirm::new(params);
        let (r, p) = h.restore_with_params(&g, 0).unwrap();
        let area: i32 = r.rois.iter().map(|r| r.area()).sum();
        println!(
            "{path}: est c {:.2}, denoise σ {:.2}, ROIs {} ({} kpx)",
            p.c_per_m,
            p.denoise_sigma_px,
            r.rois.len(),
            area / 1000
        );
        let mut k = 0;
        time("  hoirm_roi (this frame)", n, || {
            k += 1;
            h.restore_with_params(&g, k * 33_000_000).unwrap()
        });
    }
    let coarse = {
        let mut c = Mat::default();
        imgproc::resize(
            &f,
            &mut c,
            Size::new(180, 135),
            0.0,
            0.0,
            imgproc::INTER_AREA,
        )
        .unwrap();
        c
    };
    time("resize 1/8 INTER_AREA", n, || {
        let mut c = Mat::default();
        imgproc::resize(
            &f,
            &mut c,
            Size::new(180, 135),
            0.0,
            0.0,
            imgproc::INTER_AREA,
        )
        .unwrap();
        c
    });
    time("noise_sigma row step 8", n, || {
        water::noise_sigma(&f, 8).unwrap()
    });
    time("resize up INTER_LINEAR", n, || {
        let mut c = Mat::default();
        imgproc::resize(
            &coarse,
            &mut c,
            Size::new(1440, 1080),
            0.0,
            0.0,
            imgproc::INTER_LINEAR,
        )
        .unwrap();
        c
    });
    let up = {
        let mut c = Mat::default();
        imgproc::resize(
            &coarse,
            &mut c,
            Size::new(1440, 1080),
            0.0,
            0.0,
            imgproc::INTER_LINEAR,
        )
        .unwrap();
        c
    };
    time("add_weighted full", n, || {
        let mut o = Mat::default();
        core::add_weighted(&f, 2.0, &up, -2.0, 0.0, &mut o, CV_8U).unwrap();
        o
    });
    time("clone full", n, || f.try_clone().unwrap());
    let roi = Mat::roi(&f, Rect::new(300, 200, 416, 416))
        .unwrap()
        .try_clone()
        .unwrap();
    time("clahe 416", n, || {
        let mut c = imgproc::create_clahe(3.0, Size::new(4, 4)).unwrap();
        let mut o = Mat::default();
        c.apply(&roi, &mut o).unwrap();
        o
    });
    let mut w = Wiener::new();
    time("wiener 416", n, || {
        w.deconvolve(&roi, &p.psf, 0.01).unwrap()
    });
    time("pyr_down 384", n, || {
        let mut o = Mat::default();
        imgproc::pyr_down_def(&Mat::roi(&f, Rect::new(0, 0, 384, 384)).unwrap(), &mut o).unwrap();
        o
    });
}
