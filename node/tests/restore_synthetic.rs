//! HOIRM and the baselines on synthetic degraded marker frames
//! (`shoal_test_support::synthetic`), independent of the simulator.

use opencv::core::{Mat, Scalar, CV_8UC1, CV_8UC3};
use opencv::prelude::*;
use shoal_node::image_file::ImageError;
use shoal_node::metrics::{cnr_mat, gray_from_mat, ssim};
use shoal_node::restore::{
    restore_file, restorer, Hoirm, Method, RestoreError, RestoreParams, Restorer, StageOrder,
};
use shoal_test_support::synthetic::{marker_frame, Degradation, SyntheticFrame};

/// A 640x480 frame with a 192-px marker (16-px modules).
fn frame(c_per_m: f64, seed: u64) -> SyntheticFrame {
    marker_frame(640, 480, 300, 250, 16, &Degradation::for_c(c_per_m), seed).unwrap()
}

fn cnr_of(img: &Mat, f: &SyntheticFrame) -> f64 {
    cnr_mat(img, &f.white, &f.black).unwrap()
}

/// Edge sharpness of `img` across the marker's cell borders: the mean
/// gradient (central differences) projected on the clean image's edge
/// normal, over the pixels where the clean gradient is at least half its
/// peak, divided by the step between the white and the black cells' means.
/// The clean frame's one-pixel steps read 0.50; blur lowers it. It is
/// invariant to any affine grey-level change, so a gain cannot raise it,
/// and a low-pass filter can only lower it: the measure a CNR gained by
/// smoothing cannot fake.
fn edge_sharpness(img: &Mat, f: &SyntheticFrame) -> f64 {
    let (clean, g) = (
        gray_from_mat(&f.clean).unwrap(),
        gray_from_mat(img).unwrap(),
    );
    let (w, h) = (g.width as usize, g.height as usize);
    let r = f.marker;
    // The marker's outer square and the quiet-zone edge around it.
    let xs = (r.x - 2).max(1) as usize..((r.x + r.width + 2) as usize).min(w - 1);
    let ys = (r.y - 2).max(1) as usize..((r.y + r.height + 2) as usize).min(h - 1);
    let grad = |im: &shoal_proto::GrayImage, x: usize, y: usize| {
        let p = |x: usize, y: usize| im.data[y * w + x] as f64;
        (
            (p(x + 1, y) - p(x - 1, y)) / 2.0,
            (p(x, y + 1) - p(x, y - 1)) / 2.0,
        )
    };
    let mut peak = 0.0f64;
    for y in ys.clone() {
        for x in xs.clone() {
            let (gx, gy) = grad(&clean, x, y);
            peak = peak.max(gx.hypot(gy));
        }
    }
    let (mut sum, mut n) = (0.0, 0usize);
    for y in ys.clone() {
        for x in xs.clone() {
            let (cx, cy) = grad(&clean, x, y);
            let m = cx.hypot(cy);
            if m >= 0.5 * peak {
                let (gx, gy) = grad(&g, x, y);
                sum += (gx * cx + gy * cy) / m;
                n += 1;
            }
        }
    }
    let mean = |mask: &[bool]| {
        let (s, k) = g
            .data
            .iter()
            .zip(mask)
            .filter(|(_, m)| **m)
            .fold((0.0, 0usize), |(s, k), (v, _)| (s + *v as f64, k + 1));
        s / k as f64
    };
    (sum / n as f64) / (mean(&f.white) - mean(&f.black))
}

/// What a restoration did to the marker: CNR of its cells and the sharpness of their edges.
#[derive(Debug, Clone, Copy)]
struct Marker {
    cnr: f64,
    sharpness: f64,
}

fn marker_scores(img: &Mat, f: &SyntheticFrame) -> Marker {
    Marker {
        cnr: cnr_of(img, f),
        sharpness: edge_sharpness(img, f),
    }
}

fn gaussian(img: &Mat, sigma_px: f64) -> Mat {
    let mut out = Mat::default();
    opencv::imgproc::gaussian_blur_def(img, &mut out, opencv::core::Size::new(0, 0), sigma_px)
        .unwrap();
    out
}

fn box_filter(img: &Mat, side_px: i32) -> Mat {
    let mut out = Mat::default();
    opencv::imgproc::blur_def(img, &mut out, opencv::core::Size::new(side_px, side_px)).unwrap();
    out
}

/// The plain low-passes a restoration must beat: no filter at all, and a
/// Gaussian of every strength from barely there (σ 0.4 px) to wider than
/// the marker's blur (3 px), σ growing 5 % a step — so a low-pass between
/// two steps is within a few per cent of one of them. The CNR of the
/// smoothed input peaks inside this range (σ ≈ 1.3–2 px on these frames)
/// and falls beyond it as the blur reaches the cells' masks.
const LOW_PASS_SIGMA_MIN_PX: f64 = 0.4;
const LOW_PASS_SIGMA_MAX_PX: f64 = 3.0;
const LOW_PASS_SIGMA_STEP: f64 = 1.05;
/// By how much a restoration must beat each of them on CNR *or* on edge
/// sharpness (10 %). Measured on these frames (seeds 1–3), HOIRM's
/// smallest lead over the family is 15 % (CNR at 8.22 /m against σ ≈ 1.5)
/// while a 3x3 box or a Gaussian between two of the family's σs leads by
/// at most the 5 % step: 10 % separates the two.
const BEAT_MARGIN: f64 = 1.10;

fn low_pass_sigmas_px() -> Vec<f64> {
    let mut s = vec![0.0];
    let mut sigma = LOW_PASS_SIGMA_MIN_PX;
    while sigma <= LOW_PASS_SIGMA_MAX_PX {
        s.push(sigma);
        sigma *= LOW_PASS_SIGMA_STEP;
    }
    s
}

/// True if `candidate` beats `input` and every Gaussian low-pass of it by
/// [`BEAT_MARGIN`] on CNR or on edge sharpness (the low-pass that comes
/// closest on both is the one of "matched strength").
fn beats_every_low_pass(candidate: &Mat, input: &Mat, f: &SyntheticFrame) -> Result<(), String> {
    let c = marker_scores(candidate, f);
    for sigma in low_pass_sigmas_px() {
        let l = if sigma == 0.0 {
            marker_scores(input, f)
        } else {
            marker_scores(&gaussian(input, sigma), f)
        };
        if c.cnr <= BEAT_MARGIN * l.cnr && c.sharpness <= BEAT_MARGIN * l.sharpness {
            let what = if sigma == 0.0 {
                "the input itself".to_string()
            } else {
                format!("the Gaussian σ {sigma:.2} px of the input")
            };
            return Err(format!("{c:?} does not beat {what}, {l:?}"));
        }
    }
    Ok(())
}

/// HOIRM separates the marker's cells better than the input and than any
/// plain low-pass of it: a higher CNR at the same edge sharpness, or
/// sharper edges at the same CNR. The criterion is checked to reject the
/// input itself and two low-passes outside the family (a Gaussian between
/// its σs, a 3x3 box), which raise CNR just as well by blurring.
///
/// Not at 10.13 /m: there HOIRM (denoised before CLAHE, deconvolved on the
/// 1/2 level) reads CNR 5.3 / sharpness 0.12, and a plain Gaussian of σ 1.5
/// px of the input 5.9 / 0.18 (seeds 1–3) — a low-pass does better on these
/// frames; measured, not asserted (docs/restoration.md, "Turbid water").
/// Nor at 8.22 /m since the denoising starts at 1 px (session 21; it
/// started at 2): this frame asks for 1.5–2 px, and HOIRM reads CNR 8.11 /
/// sharpness 0.150 against a Gaussian of σ 0.75 px of the input's 7.40 /
/// 0.263 (1.096x in CNR, under the 1.10 margin). The gate moved for the
/// realistic camera's frames, which ask for the same smoothing and lost
/// AprilTag 3 and shoal reads without it (docs/results.md, "accuracy").
#[test]
fn hoirm_beats_the_input_and_every_low_pass_of_it_in_turbid_water() {
    for c in [6.12, 12.20] {
        let f = frame(c, 1);
        let out = restorer(Method::Hoirm, &RestoreParams::default())
            .restore(&f.degraded, 0)
            .unwrap();
        let h = marker_scores(&out.image, &f);
        let input = marker_scores(&f.degraded, &f);
        if let Err(e) = beats_every_low_pass(&out.image, &f.degraded, &f) {
            panic!("c = {c}: HOIRM {h:?}, input {input:?}: {e}");
        }
        for (name, other) in [
            ("no-op", f.degraded.clone()),
            ("Gaussian σ 1.2 px", gaussian(&f.degraded, 1.2)),
            ("3x3 box", box_filter(&f.degraded, 3)),
        ] {
            assert!(
                beats_every_low_pass(&other, &f.degraded, &f).is_err(),
                "c = {c}: the criterion passes a {name}: {:?}",
                marker_scores(&other, &f)
            );
        }
    }
}

/// The Wiener stage takes the forward-scatter halo out of the cells (and,
/// with its 1/f² signal prior, does not amplify the noise): at 6.12 /m its
/// output beats its own input (the de-attenuated stage) and every Gaussian
/// low-pass of it, a test that a no-op stage and a smoothing stage fail.
///
/// Not at 10.13 /m, where the frame is denoised before CLAHE and deconvolved
/// on the 1/2 level with the unsmoothed region's NSR (docs/restoration.md,
/// "Turbid water"): there the stage lowers both the CNR (5.4 → 5.3) and the
/// edge sharpness (0.131 → 0.117; seeds 1–3) — a no-op would do better on
/// these frames; measured, not asserted.
#[test]
fn wiener_stage_beats_a_no_op_and_every_low_pass_at_6_12() {
    let f = frame(6.12, 2);
    let params = RestoreParams {
        keep_stages: true,
        ..RestoreParams::default()
    };
    let out = restorer(Method::Hoirm, &params)
        .restore(&f.degraded, 0)
        .unwrap();
    let stages = out.stages.unwrap();
    let stage = |prefix: &str| {
        stages
            .iter()
            .find(|(n, _)| n.starts_with(prefix))
            .unwrap()
            .1
            .clone()
    };
    let (before, after) = (stage("de-attenuated"), stage("deblurred"));
    if let Err(e) = beats_every_low_pass(&after, &before, &f) {
        panic!(
            "Wiener stage: {:?} -> {:?}: {e}",
            marker_scores(&before, &f),
            marker_scores(&after, &f)
        );
    }
    for (name, other) in [
        ("no-op", before.clone()),
        ("Gaussian σ 1.2 px", gaussian(&before, 1.2)),
        ("3x3 box", box_filter(&before, 3)),
    ] {
        assert!(
            beats_every_low_pass(&other, &before, &f).is_err(),
            "the criterion passes a {name} stage: {:?}",
            marker_scores(&other, &f)
        );
    }
}

#[test]
fn hoirm_regions_of_interest_cover_the_marker_only() {
    let f = frame(8.22, 3);
    let out = restorer(Method::Hoirm, &RestoreParams::default())
        .restore(&f.degraded, 0)
        .unwrap();
    let m = f.marker;
    assert!(
        out.rois.iter().any(|r| (*r & m) == m),
        "no ROI covers the marker {m:?}: {:?}",
        out.rois
    );
    let area: i32 = out.rois.iter().map(|r| r.area()).sum();
    assert!(area < 640 * 480 / 2, "ROIs cover {area} px");
}

#[test]
fn roi_and_full_frame_deconvolution_agree_on_the_marker() {
    let f = frame(10.13, 4);
    let roi = restorer(Method::Hoirm, &RestoreParams::default())
        .restore(&f.degraded, 0)
        .unwrap();
    let full_params = RestoreParams {
        roi_only: false,
        ..RestoreParams::default()
    };
    let full = restorer(Method::Hoirm, &full_params)
        .restore(&f.degraded, 0)
        .unwrap();
    let crop =
        |m: &Mat| gray_from_mat(&Mat::roi(m, f.marker).unwrap().try_clone().unwrap()).unwrap();
    let s = ssim(&crop(&roi.image), &crop(&full.image)).unwrap();
    assert!(s > 0.97, "SSIM(ROI, full) on the marker = {s}");
}

#[test]
fn water_estimate_grows_with_attenuation_and_override_is_reported() {
    let mut last = -1.0;
    for c in [2.0, 6.12, 10.13, 14.2] {
        let f = frame(c, 5);
        let out = restorer(Method::Hoirm, &RestoreParams::default())
            .restore(&f.degraded, 0)
            .unwrap();
        assert!(
            out.estimated_c_per_m > last,
            "c = {c}: estimate {} not above {last}",
            out.estimated_c_per_m
        );
        last = out.estimated_c_per_m;
    }
    let params = RestoreParams {
        c_per_m: Some(12.2),
        ..RestoreParams::default()
    };
    let out = restorer(Method::Hoirm, &params)
        .restore(&frame(6.12, 6).degraded, 0)
        .unwrap();
    assert_eq!(out.estimated_c_per_m, 12.2);
}

#[test]
fn every_method_returns_a_same_size_grey_image_and_its_name() {
    let f = frame(8.22, 7);
    let params = RestoreParams {
        keep_stages: true,
        ..RestoreParams::default()
    };
    for m in Method::ALL {
        let mut r = restorer(m, &params);
        assert_eq!(r.method(), m);
        assert_eq!(m.name().parse::<Method>().unwrap(), m);
        let out = r.restore(&f.degraded, 0).unwrap();
        assert_eq!(out.image.size().unwrap(), f.degraded.size().unwrap());
        assert_eq!(out.image.typ(), CV_8UC1);
        assert!(out.stages.is_some());
    }
    let stages = restorer(Method::Hoirm, &params)
        .restore(&f.degraded, 0)
        .unwrap()
        .stages
        .unwrap();
    let names: Vec<&str> = stages.iter().map(|(n, _)| n.as_str()).collect();
    assert!(names.iter().any(|n| n.starts_with("denoised")), "{names:?}");
    assert!(
        names.iter().any(|n| n.starts_with("de-attenuated")),
        "{names:?}"
    );
    assert!(
        names.iter().any(|n| n.starts_with("deblurred")),
        "{names:?}"
    );
    assert!(matches!(
        "fog".parse::<Method>(),
        Err(RestoreError::UnknownMethod { .. })
    ));
}

#[test]
fn both_stage_orders_run_and_differ() {
    let f = frame(10.13, 8);
    let phys = RestoreParams {
        order: StageOrder::Physical,
        ..RestoreParams::default()
    };
    let a = restorer(Method::Hoirm, &RestoreParams::default())
        .restore(&f.degraded, 0)
        .unwrap();
    let b = restorer(Method::Hoirm, &phys)
        .restore(&f.degraded, 0)
        .unwrap();
    let mut d = Mat::default();
    opencv::core::absdiff(&a.image, &b.image, &mut d).unwrap();
    assert!(opencv::core::count_non_zero(&d).unwrap() > 0);
}

#[test]
fn bad_inputs_are_errors_not_panics() {
    for m in Method::ALL {
        let mut r = restorer(m, &RestoreParams::default());
        assert!(matches!(
            r.restore(&Mat::default(), 0),
            Err(RestoreError::EmptyImage)
        ));
        let colour = Mat::new_rows_cols_with_default(64, 64, CV_8UC3, Scalar::all(0.0)).unwrap();
        assert!(matches!(
            r.restore(&colour, 0),
            Err(RestoreError::NotGray8 { .. })
        ));
        let tiny = Mat::new_rows_cols_with_default(8, 64, CV_8UC1, Scalar::all(0.0)).unwrap();
        assert!(matches!(
            r.restore(&tiny, 0),
            Err(RestoreError::TooSmall { .. })
        ));
        // A flat frame is legal and must come back (no ROI, no NaN).
        let flat = Mat::new_rows_cols_with_default(64, 80, CV_8UC1, Scalar::all(90.0)).unwrap();
        let out = r.restore(&flat, 0).unwrap();
        assert_eq!(out.image.size().unwrap(), flat.size().unwrap());
    }
    let bad = RestoreParams {
        c_per_m: Some(f64::NAN),
        ..RestoreParams::default()
    };
    let f = frame(6.12, 9);
    assert!(matches!(
        Hoirm::new(bad).restore(&f.degraded, 0),
        Err(RestoreError::BadParam {
            name: "c_per_m",
            ..
        })
    ));
}

#[test]
fn restore_file_writes_a_restored_png() {
    let dir = std::env::temp_dir().join(format!("shoal-restore-{}", std::process::id()));
    std::fs::create_dir_all(&dir).unwrap();
    let input = dir.join("in.png");
    let output = dir.join("out.png");
    let f = frame(12.2, 10);
    opencv::imgcodecs::imwrite(
        input.to_str().unwrap(),
        &f.degraded,
        &opencv::core::Vector::new(),
    )
    .unwrap();
    restore_file(&input, &output, Method::Hoirm, Some(12.2)).unwrap();
    let back = opencv::imgcodecs::imread(
        output.to_str().unwrap(),
        opencv::imgcodecs::IMREAD_GRAYSCALE,
    )
    .unwrap();
    assert_eq!(back.size().unwrap(), f.degraded.size().unwrap());
    assert!(matches!(
        restore_file(&dir.join("missing.png"), &output, Method::None, None),
        Err(RestoreError::File(ImageError::Io { .. }))
    ));
    // Issue #22: the output is never the input, and a failed run leaves an
    // existing output as it was.
    let before = std::fs::read(&output).unwrap();
    let e = restore_file(&input, &input, Method::None, None).unwrap_err();
    assert!(e.to_string().contains("is the input"), "{e}");
    std::fs::write(dir.join("junk.png"), b"not a png").unwrap();
    assert!(restore_file(&dir.join("junk.png"), &output, Method::None, None).is_err());
    assert_eq!(std::fs::read(&output).unwrap(), before);
    // An image over the restoration limit is refused from its header, before decoding.
    let big = opencv::core::Mat::new_rows_cols_with_default(
        4001,
        4000,
        opencv::core::CV_8UC1,
        opencv::core::Scalar::all(0.0),
    )
    .unwrap();
    let big_path = dir.join("big.png");
    opencv::imgcodecs::imwrite(
        big_path.to_str().unwrap(),
        &big,
        &opencv::core::Vector::new(),
    )
    .unwrap();
    let e = restore_file(&big_path, &output, Method::Dcp, None).unwrap_err();
    assert!(
        matches!(e, RestoreError::File(ImageError::TooManyPixels { .. })),
        "{e}"
    );
    assert!(e.to_string().contains("for restoration"), "{e}");
    std::fs::remove_dir_all(&dir).ok();
}

#[test]
fn pyramid_level_image_matches_the_chosen_level() {
    let f = frame(12.2, 11);
    let out = restorer(Method::Hoirm, &RestoreParams::default())
        .restore(&f.degraded, 0)
        .unwrap();
    match &out.level_image {
        None => assert_eq!(out.pyramid_level, 0),
        Some(l) => {
            assert!(out.pyramid_level > 0);
            let expect = 640 >> out.pyramid_level;
            assert!((l.cols() - expect).abs() <= 1);
        }
    }
}

#[test]
fn hoirm_passes_clear_water_through_and_restores_turbid_water() {
    for (c, passed) in [(0.126, true), (1.38, true), (6.12, false)] {
        let f = frame(c, 5);
        let out = restorer(Method::Hoirm, &RestoreParams::default())
            .restore(&f.degraded, 0)
            .unwrap();
        let same = out.image.data_bytes().unwrap() == f.degraded.data_bytes().unwrap();
        assert_eq!(same, passed, "c = {c}: estimate {}", out.estimated_c_per_m);
    }
}
