//! Restoration cost per 1440x1080 frame on ONE core (`cv::setNumThreads(1)`):
//! HOIRM with ROI-limited and full-frame deconvolution side by side, its
//! stages, and the baselines. Budget: 10 ms per frame for HOIRM.
//!
//! `cargo bench -p shoal-node --bench restore`

use criterion::{criterion_group, criterion_main, Criterion};
use opencv::core::{Mat, Size};
use opencv::imgproc;
use opencv::prelude::*;
use shoal_node::restore::psf::Wiener;
use shoal_node::restore::water;
use shoal_node::restore::{restorer, Hoirm, Method, RestoreParams};
use shoal_test_support::synthetic::{marker_frame, Degradation};
use std::hint::black_box;
use std::time::Duration;

fn frames() -> Vec<Mat> {
    // A 288-px marker (24-px modules, ~0.17 m at 1.2 m with fx = 1250) at three positions.
    [(500, 400), (760, 560), (900, 620)]
        .iter()
        .enumerate()
        .map(|(i, &(x, y))| {
            marker_frame(1440, 1080, x, y, 24, &Degradation::for_c(10.13), i as u64)
                .unwrap()
                .degraded
        })
        .collect()
}

fn bench(c: &mut Criterion) {
    opencv::core::set_num_threads(1).unwrap();
    let frames = frames();
    let mut g = c.benchmark_group("restore_1440x1080_1core");
    g.sample_size(30).measurement_time(Duration::from_secs(4));

    for (name, roi_only, deconv_level) in [
        ("hoirm_roi", true, 0),
        ("hoirm_roi_deconv_half_level", true, 1),
        ("hoirm_full_frame", false, 0),
    ] {
        let params = RestoreParams {
            roi_only,
            deconv_level,
            ..RestoreParams::default()
        };
        let mut h = Hoirm::new(params);
        let mut k = 0u64;
        g.bench_function(name, |b| {
            b.iter(|| {
                k += 1;
                let f = &frames[(k % 3) as usize];
                black_box(h.restore_with_params(f, k * 33_333_333).unwrap());
            })
        });
    }

    // Stage costs, to see where the time goes.
    let f = &frames[0];
    g.bench_function("stage_coarse_level_1_8", |b| {
        b.iter(|| {
            let mut out = Mat::default();
            imgproc::resize(
                f,
                &mut out,
                Size::new(180, 135),
                0.0,
                0.0,
                imgproc::INTER_AREA,
            )
            .unwrap();
            black_box(out)
        })
    });
    g.bench_function("stage_clahe_full_frame", |b| {
        let mut cl = imgproc::create_clahe(3.5, Size::new(12, 9)).unwrap();
        b.iter(|| {
            let mut out = Mat::default();
            cl.apply(f, &mut out).unwrap();
            black_box(out)
        })
    });
    let psf = Hoirm::new(RestoreParams::default()).parameters_for(10.13).1;
    let roi = Mat::roi(f, opencv::core::Rect::new(300, 200, 400, 400))
        .unwrap()
        .try_clone()
        .unwrap();
    let mut wiener = Wiener::new();
    g.bench_function("stage_wiener_400x400", |b| {
        b.iter(|| black_box(wiener.deconvolve(&roi, &psf, 0.01).unwrap()))
    });
    // The frame's noise estimate: the 3x3 mask at full resolution alone, and
    // across scales and in the dark levels (what `WaterEstimate` reads).
    g.bench_function("stage_noise_full_frame_single_scale", |b| {
        b.iter(|| black_box(water::noise_sigma(f, 16).unwrap()))
    });
    g.bench_function("stage_noise_full_frame_across_scales", |b| {
        b.iter(|| black_box(water::noise_sigma_across_scales(f, 16, water::NOISE_LEVELS).unwrap()))
    });
    g.bench_function("stage_pyr_down_full_frame", |b| {
        b.iter(|| {
            let mut out = Mat::default();
            imgproc::pyr_down_def(f, &mut out).unwrap();
            black_box(out)
        })
    });

    for m in [Method::None, Method::Clahe, Method::Dcp, Method::Udcp] {
        let mut r = restorer(m, &RestoreParams::default());
        if matches!(m, Method::Dcp | Method::Udcp) {
            g.sample_size(10);
        }
        g.bench_function(format!("baseline_{m}"), |b| {
            b.iter(|| black_box(r.restore(f, 0).unwrap()))
        });
    }
    g.finish();
}

criterion_group!(benches, bench);
criterion_main!(benches);
