//! Camera profiles (issue #16): the ideal profile is the renderer bit for
//! bit, the profiled path without an image effect is too, and each effect
//! changes the frame by the amount its physics says.

use nalgebra::Vector3;
use shoal_proto::camera::Distortion;
use shoal_proto::{CameraModel, CodeSet, GrayImage, Pose};
use shoal_sim_bridge::profile::{CameraProfile, Effect, MotionBlur, RollingShutter};
use shoal_sim_bridge::render::motion::{RigidMotion, StaticView, Twist};
use shoal_sim_bridge::render::realistic::{calibration_error, render_profiled, ProfiledFrame};
use shoal_sim_bridge::render::{facing_camera, Renderer, Scene};
use shoal_sim_bridge::water::{WaterParams, WaterPresets};

/// A small camera so that tests of many sub-frames stay fast in debug builds.
fn small_camera() -> CameraModel {
    CameraModel {
        width: 320,
        height: 240,
        fx: 300.0,
        fy: 300.0,
        cx: 159.5,
        cy: 119.5,
        distortion: Distortion::PlumbBob([0.0; 5]),
    }
}

/// Marker side (m) and range (m): modules of 12 px on `small_camera`.
const SIDE_M: f64 = 0.2;
const RANGE_M: f64 = 0.5;

fn marker_scene() -> Scene {
    Scene::single_marker(
        CodeSet::Shoal,
        17,
        SIDE_M,
        facing_camera([0.0, 0.0, RANGE_M], [0.0; 3]),
    )
}

/// The marker moving along the camera's x axis at `v` m/s, the camera still.
fn sliding(v: f64) -> RigidMotion {
    RigidMotion {
        world_from_camera: Pose::identity(),
        scene: marker_scene(),
        camera: Twist::default(),
        targets: Twist {
            linear_mps: Vector3::new(v, 0.0, 0.0),
            angular_radps: Vector3::zeros(),
        },
    }
}

fn profile(effects: &[Effect]) -> CameraProfile {
    CameraProfile::only(effects)
}

fn render(
    p: &CameraProfile,
    cam: &CameraModel,
    tl: &dyn shoal_sim_bridge::render::motion::Timeline,
    water: &WaterParams,
    seed: u64,
) -> ProfiledFrame {
    render_profiled(&mut Renderer::new(), p, cam, None, tl, water, 0.0, seed).unwrap()
}

fn at(img: &GrayImage, x: usize, y: usize) -> f64 {
    f64::from(img.data[y * img.width as usize + x])
}

/// Pixel column of the marker's left outer edge (white quiet zone → black border) at `time` after a slide of `v`.
fn left_edge_u(cam: &CameraModel, v: f64, time_s: f64) -> f64 {
    cam.cx + cam.fx * (v * time_s - 0.5 * SIDE_M) / RANGE_M
}

/// Position (centroid) and spread (variance) of the intensity drop across
/// row `y` within `half` px of `u`.
fn edge_stats(img: &GrayImage, y: usize, u: f64, half: f64) -> (f64, f64) {
    let (x0, x1) = ((u - half).floor() as usize, (u + half).ceil() as usize);
    let d: Vec<(f64, f64)> = (x0..x1)
        .map(|x| (x as f64 + 0.5, (at(img, x, y) - at(img, x + 1, y)).max(0.0)))
        .collect();
    let total: f64 = d.iter().map(|(_, v)| v).sum();
    let mean = d.iter().map(|(x, v)| x * v).sum::<f64>() / total;
    let var = d.iter().map(|(x, v)| (x - mean).powi(2) * v).sum::<f64>() / total;
    (mean, var)
}

#[test]
fn the_ideal_profile_is_the_renderer_bit_for_bit() {
    let cam = CameraModel::vehicle_1440();
    let water = WaterPresets::builtin().get(3.92).unwrap();
    let scene = Scene::single_marker(
        CodeSet::Shoal,
        17,
        0.1,
        facing_camera([0.05, 0.0, 0.8], [0.0, 0.3, 0.0]),
    );
    let direct = Renderer::new()
        .render(&cam, &Pose::identity(), &scene, &water, 1.5, 42)
        .unwrap();
    let tl = StaticView {
        world_from_camera: Pose::identity(),
        scene,
    };
    let via = render_profiled(
        &mut Renderer::new(),
        &CameraProfile::ideal(),
        &cam,
        None,
        &tl,
        &water,
        1.5,
        42,
    )
    .unwrap();
    assert_eq!(via.output, direct);
    assert_eq!(via.node_camera, cam);
}

#[test]
fn without_an_image_effect_the_profiled_path_is_the_renderer_too() {
    // Calibration error changes the node's camera, not a pixel: the
    // sub-frame, sensor and encoding stages must then reproduce the
    // renderer's noise and rounding exactly.
    let cam = small_camera();
    let water = WaterPresets::builtin().get(1.38).unwrap();
    let tl = sliding(0.0);
    let direct = Renderer::new()
        .render(&cam, &Pose::identity(), &marker_scene(), &water, 0.0, 7)
        .unwrap();
    let via = render(&profile(&[Effect::Calibration]), &cam, &tl, &water, 7);
    assert_eq!(via.output.image, direct.image);
    assert_ne!(via.node_camera, cam);
}

#[test]
fn motion_blur_widens_an_edge_by_the_distance_travelled() {
    let cam = small_camera();
    let water = WaterParams::clear();
    let (v, t_exp) = (0.6, 0.010);
    let mut p = profile(&[Effect::MotionBlur]);
    p.params.motion_blur = MotionBlur {
        exposure_s: t_exp,
        max_step_px: 0.1,
        max_samples: 64,
    };
    let still = render(&p, &cam, &sliding(0.0), &water, 1);
    let moving = render(&p, &cam, &sliding(v), &water, 1);
    let expected_px = v * t_exp * cam.fx / RANGE_M; // 3.6 px
    let y = cam.cy.round() as usize;
    let (_, var0) = edge_stats(&still.output.image, y, left_edge_u(&cam, 0.0, 0.0), 4.0);
    // The still edge lies on a pixel boundary (u = 99.5): one step, no spread.
    assert!(var0 < 0.01, "still edge spread {var0}");
    let (mid, var1) = edge_stats(
        &moving.output.image,
        y,
        left_edge_u(&cam, v, 0.5 * t_exp),
        0.5 * expected_px + 2.0,
    );
    // A box blur of length L has variance L²/12; the pixel's own box adds
    // 1/12, and sampling the ramp at whole pixels another 1/12 (Sheppard).
    let measured = (12.0 * var1 - 2.0).sqrt();
    println!("blur {measured:.3} px, expected {expected_px:.3}");
    // Sheppard's correction is exact only on average over the edge's phase: 0.1 px (3 %).
    const WIDTH_TOL_PX: f64 = 0.1;
    assert!(
        (measured - expected_px).abs() < WIDTH_TOL_PX,
        "blur {measured:.3} px, expected {expected_px:.3}"
    );
    // The blurred edge is centred on the mid-exposure position.
    assert!(
        (mid - left_edge_u(&cam, v, 0.5 * t_exp)).abs() < 0.15,
        "{mid}"
    );
}

#[test]
fn rolling_shutter_shears_a_moving_vertical_edge() {
    let cam = small_camera();
    let water = WaterParams::clear();
    let (v, line) = (0.6, 100e-6);
    let mut p = profile(&[Effect::RollingShutter]);
    p.params.rolling_shutter = RollingShutter { line_time_s: line };
    p.params.motion_blur.max_step_px = 0.25;
    let frame = render(&p, &cam, &sliding(v), &water, 1);
    let (y1, y2) = (70usize, 170usize);
    let guess = left_edge_u(&cam, v, 120.0 * line);
    let (u1, _) = edge_stats(&frame.output.image, y1, guess, 5.0);
    let (u2, _) = edge_stats(&frame.output.image, y2, guess, 5.0);
    let expected = v * cam.fx / RANGE_M * line * (y2 - y1) as f64; // 3.6 px
    println!("shear {:.3} px, expected {expected:.3}", u2 - u1);
    // Each row blends the two sub-frames around its time (0.25 px apart):
    // the blend of two shifted edges has its centroid where the edge is,
    // 8-bit rounding and the edge's sampling leave 0.1 px.
    const SHEAR_TOL_PX: f64 = 0.1;
    assert!(
        ((u2 - u1) - expected).abs() < SHEAR_TOL_PX,
        "shear {:.3} px, expected {expected:.3}",
        u2 - u1
    );
    // A still marker is not sheared.
    let still = render(&p, &cam, &sliding(0.0), &water, 1);
    let g0 = left_edge_u(&cam, 0.0, 0.0);
    let (s1, _) = edge_stats(&still.output.image, y1, g0, 5.0);
    let (s2, _) = edge_stats(&still.output.image, y2, g0, 5.0);
    assert!((s2 - s1).abs() < 0.05, "{s1} {s2}");
}

#[test]
fn vignetting_darkens_the_corners_by_the_cos4_law() {
    let cam = CameraModel::vehicle_1440();
    let water = WaterPresets::builtin().get(0.5).unwrap().noiseless();
    let tl = StaticView {
        world_from_camera: Pose::identity(),
        scene: Scene::empty(),
    };
    let base = render(&profile(&[Effect::Calibration]), &cam, &tl, &water, 1);
    let p = profile(&[Effect::Vignetting]);
    let vig = render(&p, &cam, &tl, &water, 1);
    let s = p.params.vignetting.strength;
    for (x, y) in [(0usize, 0usize), (1432, 1072), (720, 536), (0, 536)] {
        let (rx, ry) = cam.ray(x as f64, y as f64);
        let cos2 = 1.0 / (1.0 + rx * rx + ry * ry);
        let expect = at(&base.output.image, x, y) * (1.0 - s * (1.0 - cos2 * cos2));
        // 8-bit rounding of both frames.
        assert!(
            (at(&vig.output.image, x, y) - expect).abs() <= 1.0,
            "({x},{y}): {} vs {expect:.2}",
            at(&vig.output.image, x, y)
        );
    }
    assert!(at(&vig.output.image, 0, 0) < 0.7 * at(&base.output.image, 0, 0));
}

fn rms(a: &GrayImage, b: &GrayImage) -> f64 {
    let n = a.data.len() as f64;
    (a.data
        .iter()
        .zip(&b.data)
        .map(|(x, y)| (f64::from(*x) - f64::from(*y)).powi(2))
        .sum::<f64>()
        / n)
        .sqrt()
}

#[test]
fn lower_jpeg_quality_loses_more() {
    let cam = small_camera();
    let water = WaterPresets::builtin().get(0.5).unwrap();
    let tl = StaticView {
        world_from_camera: Pose::identity(),
        scene: marker_scene(),
    };
    let base = render(&profile(&[Effect::Calibration]), &cam, &tl, &water, 3);
    let err = |q: u8| {
        let mut p = profile(&[Effect::Jpeg]);
        p.params.jpeg.quality = q;
        rms(
            &render(&p, &cam, &tl, &water, 3).output.image,
            &base.output.image,
        )
    };
    let (e100, e75, e30) = (err(100), err(75), err(30));
    assert!(e100 < 1.0 && e100 < e75 && e75 < e30, "{e100} {e75} {e30}");
    let mut h = profile(&[Effect::H264]);
    h.params.h264.qp = 36;
    let e_h = rms(
        &render(&h, &cam, &tl, &water, 3).output.image,
        &base.output.image,
    );
    assert!(e_h > e100, "{e_h}");
}

/// Connected groups of pixels at least `dn` brighter than in `base`.
fn bright_blobs(img: &GrayImage, base: &GrayImage, dn: f64) -> usize {
    let (w, h) = (img.width as usize, img.height as usize);
    let mut seen = vec![false; w * h];
    let bright = |i: usize| f64::from(img.data[i]) - f64::from(base.data[i]) >= dn;
    let mut blobs = 0;
    for start in 0..w * h {
        if seen[start] || !bright(start) {
            continue;
        }
        blobs += 1;
        let mut stack = vec![start];
        seen[start] = true;
        while let Some(i) = stack.pop() {
            let (x, y) = (i % w, i / w);
            for (nx, ny) in [
                (x.wrapping_sub(1), y),
                (x + 1, y),
                (x, y.wrapping_sub(1)),
                (x, y + 1),
            ] {
                if nx < w && ny < h {
                    let j = ny * w + nx;
                    if !seen[j] && bright(j) {
                        seen[j] = true;
                        stack.push(j);
                    }
                }
            }
        }
    }
    blobs
}

#[test]
fn marine_snow_adds_bright_blobs_in_proportion_to_its_density() {
    let cam = CameraModel::vehicle_1440();
    let water = WaterPresets::builtin().get(0.5).unwrap().noiseless();
    let tl = StaticView {
        world_from_camera: Pose::identity(),
        scene: Scene::empty(),
    };
    let base = render(&profile(&[Effect::Calibration]), &cam, &tl, &water, 1);
    let count = |density: f64, seed: u64| {
        let mut p = profile(&[Effect::Snow]).with_seed(seed);
        p.params.snow.density_per_m3 = density;
        let f = render(&p, &cam, &tl, &water, 1);
        (
            bright_blobs(&f.output.image, &base.output.image, 8.0),
            f.report.snow_particles,
        )
    };
    let (b0, n0) = count(0.0, 1);
    assert_eq!((b0, n0), (0, 0));
    let (b1, n1) = (0..3)
        .map(|s| count(80.0, s))
        .fold((0, 0), |a, b| (a.0 + b.0, a.1 + b.1));
    let (b4, n4) = (0..3)
        .map(|s| count(320.0, s))
        .fold((0, 0), |a, b| (a.0 + b.0, a.1 + b.1));
    // Visible blobs are a fraction of the particles (far ones are faint).
    println!("blobs {b1} of {n1} particles, {b4} of {n4}");
    assert!(b1 > 30 && b1 < n1, "{b1} of {n1}");
    let ratio = b4 as f64 / b1 as f64;
    // Four times the density, four times the blobs (a few overlap): the
    // counts (~100 and ~400 over three frames) are Poisson, ±20 % on the
    // smaller at 2σ.
    assert!(
        (3.0..=5.0).contains(&ratio),
        "{b1} → {b4} ({n1} → {n4} particles)"
    );
}

#[test]
fn a_colour_camera_loses_the_red_light_first() {
    let cam = small_camera();
    let water = WaterParams::clear();
    let tl = StaticView {
        world_from_camera: Pose::identity(),
        scene: Scene::single_marker(
            CodeSet::Shoal,
            17,
            SIDE_M,
            facing_camera([0.0, 0.0, 1.0], [0.0; 3]),
        ),
    };
    let base = render(&profile(&[Effect::Calibration]), &cam, &tl, &water, 1);
    let p = profile(&[Effect::Colour]);
    let col = render(&p, &cam, &tl, &water, 1);
    // The quiet zone (white, one module outside the black square) at 1 m, its middle row.
    let u = (cam.cx - cam.fx * (0.5 * SIDE_M + 0.01) / 1.0).round() as usize;
    let y = cam.cy.round() as usize;
    let c = &p.params.colour;
    // Green keeps the preset's attenuation (0 here); luma weights of Rec. 601.
    let expect = at(&base.output.image, u, y)
        * (0.299 * (-c.extra_c_red_per_m).exp() + 0.587 + 0.114 * (-c.extra_c_blue_per_m).exp());
    assert!(
        (at(&col.output.image, u, y) - expect).abs() <= 1.0,
        "{} vs {expect:.2}",
        at(&col.output.image, u, y)
    );
}

#[test]
fn auto_exposure_brings_a_dark_frame_to_its_target() {
    let cam = small_camera();
    let water = WaterParams {
        exposure: 0.2,
        ..WaterPresets::builtin().get(0.5).unwrap()
    };
    let tl = StaticView {
        world_from_camera: Pose::identity(),
        scene: marker_scene(),
    };
    let p = profile(&[Effect::Exposure]);
    let f = render(&p, &cam, &tl, &water, 2);
    let e = p.params.exposure;
    assert!(
        f.report.gain > 1.0 && f.report.gain <= e.max_gain,
        "{}",
        f.report.gain
    );
    // Decode the gamma and meter again.
    let mean = f
        .output
        .image
        .data
        .iter()
        .map(|v| 255.0 * (f64::from(*v) / 255.0).powf(e.gamma))
        .sum::<f64>()
        / f.output.image.data.len() as f64;
    // Rounding dark pixels to 8 bits after gamma and the noise: 5 % of the target.
    assert!(
        (mean / (e.target_mean * 255.0) - 1.0).abs() < 0.05,
        "mean {mean}"
    );
}

#[test]
fn a_heavy_tailed_psf_blurs_and_changes_per_frame() {
    let cam = small_camera();
    let water = WaterParams::clear();
    let tl = StaticView {
        world_from_camera: Pose::identity(),
        scene: marker_scene(),
    };
    let base = render(&profile(&[Effect::Calibration]), &cam, &tl, &water, 1);
    let p = profile(&[Effect::Psf]);
    let a = render(&p, &cam, &tl, &water, 1);
    let b = render(&p, &cam, &tl, &water, 2);
    assert_ne!(a.report.psf, b.report.psf);
    let y = cam.cy.round() as usize;
    let u = left_edge_u(&cam, 0.0, 0.0);
    let (_, v0) = edge_stats(&base.output.image, y, u, 5.0);
    let (_, va) = edge_stats(&a.output.image, y, u, 5.0);
    assert!(va > v0 + 0.1, "{v0} {va} ({:?})", a.report.psf);
}

#[test]
fn the_calibration_error_is_seeded_and_within_its_bounds() {
    let cam = CameraModel::vehicle_1440();
    let e = CameraProfile::realistic().params.calibration;
    let mut max_f: f64 = 0.0;
    let mut max_c: f64 = 0.0;
    for seed in 0..300 {
        let c = calibration_error(&cam, &e, seed);
        assert_eq!(c, calibration_error(&cam, &e, seed));
        let (df, dc) = ((c.fx / cam.fx - 1.0).abs(), (c.cx - cam.cx).abs());
        assert!(df <= e.focal_rel && (c.fy / cam.fy - 1.0).abs() <= e.focal_rel);
        assert!(dc <= e.principal_px && (c.cy - cam.cy).abs() <= e.principal_px);
        max_f = max_f.max(df);
        max_c = max_c.max(dc);
    }
    // Uniform draws fill their bounds.
    assert!(max_f > 0.95 * e.focal_rel && max_c > 0.95 * e.principal_px);
    assert_ne!(
        calibration_error(&cam, &e, 1),
        calibration_error(&cam, &e, 2)
    );
}

#[test]
fn the_port_effect_renders_through_a_window_and_keeps_the_node_in_water() {
    let cam = CameraModel::vehicle_1440();
    let water = WaterParams::clear();
    let tl = StaticView {
        world_from_camera: Pose::identity(),
        scene: Scene::single_marker(
            CodeSet::Shoal,
            17,
            0.1,
            facing_camera([0.3, 0.0, 1.0], [0.0; 3]),
        ),
    };
    let p = profile(&[Effect::Port]);
    let f = render(&p, &cam, &tl, &water, 1);
    let port = f.port.expect("the port effect renders through a port");
    assert_eq!(f.node_camera, cam);
    // 0.3 m off axis at 1 m: the in-water pinhole misplaces corners by pixels,
    // not by tens of them.
    let truth = &f.output.visible[0].corners_px;
    let pinhole = Renderer::new()
        .render(&cam, &Pose::identity(), &tl.scene, &water, 0.0, 1)
        .unwrap();
    let off = truth
        .iter()
        .zip(&pinhole.visible[0].corners_px)
        .map(|(a, b)| ((a[0] - b[0]).powi(2) + (a[1] - b[1]).powi(2)).sqrt())
        .fold(0.0, f64::max);
    assert!(off > 0.5 && off < 20.0, "{off} px through {port:?}");
}

#[test]
fn a_bad_profile_is_an_error_not_a_panic() {
    let cam = small_camera();
    let tl = sliding(0.1);
    let mut p = CameraProfile::realistic();
    p.params.motion_blur.exposure_s = f64::NAN;
    let err = render_profiled(
        &mut Renderer::new(),
        &p,
        &cam,
        None,
        &tl,
        &WaterParams::clear(),
        0.0,
        1,
    )
    .unwrap_err()
    .to_string();
    assert!(err.contains("motion_blur.exposure_s"), "{err}");
}
