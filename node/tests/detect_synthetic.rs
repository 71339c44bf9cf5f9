//! The detector on simulated frames: IDs, rotations, all 12 corners, clipped
//! and occluded frames, other code sets, and no guesses on noise.

use nalgebra::{Translation3, UnitQuaternion, Vector3};
use shoal_node::detect::{DetectParams, Detection, ShoalDetector};
use shoal_proto::image::GrayImage;
use shoal_proto::{camera::CameraModel, geometry::Pose, marker::CodeSet};
use shoal_sim_bridge::render::{Renderer, Scene};
use shoal_sim_bridge::water::WaterParams;

const SIDE_M: f64 = 0.1;
/// Corner accuracy on clean renders: the refinement reaches ~0.1 px; 0.3 px
/// leaves room for the renderer's anti-aliasing.
const CLEAN_CORNER_TOL_PX: f64 = 0.3;

fn facing(x: f64, y: f64, z: f64, roll_deg: f64, yaw_deg: f64) -> Pose {
    Pose::from_parts(
        Translation3::new(x, y, z),
        UnitQuaternion::from_axis_angle(&Vector3::z_axis(), roll_deg.to_radians())
            * UnitQuaternion::from_axis_angle(&Vector3::x_axis(), std::f64::consts::PI)
            * UnitQuaternion::from_axis_angle(&Vector3::y_axis(), yaw_deg.to_radians()),
    )
}

fn render(codes: CodeSet, id: u32, pose: Pose, water: &WaterParams) -> GrayImage {
    render_seeded(codes, id, pose, water, 5)
}

/// [`render`] with the renderer's noise seed given.
fn render_seeded(codes: CodeSet, id: u32, pose: Pose, water: &WaterParams, seed: u64) -> GrayImage {
    let cam = CameraModel::vehicle_1440();
    let scene = Scene::single_marker(codes, id, SIDE_M, pose);
    Renderer::new()
        .render(&cam, &Pose::identity(), &scene, water, 0.0, seed)
        .unwrap()
        .image
}

fn corner_errors(d: &Detection, pose: &Pose) -> Vec<f64> {
    let cam = CameraModel::vehicle_1440();
    let all = d.codes.corners_3d(SIDE_M);
    d.corner_ids
        .iter()
        .zip(&d.corners_px)
        .map(|(&i, p)| {
            let q = cam.project(&(pose * all[i as usize])).unwrap();
            ((q.x - p[0]).powi(2) + (q.y - p[1]).powi(2)).sqrt()
        })
        .collect()
}

#[test]
fn decodes_id_17_under_rotation_with_all_twelve_corners() {
    for roll in [0.0, 90.0, 180.0, 270.0, 33.0] {
        let pose = facing(0.01, -0.02, 0.61, roll, 30.0);
        let img = render(CodeSet::Shoal, 17, pose, &WaterParams::clear());
        let found = ShoalDetector::new(CodeSet::Shoal, DetectParams::default())
            .detect_gray(&img)
            .unwrap();
        assert_eq!(found.len(), 1, "roll {roll}: {found:?}");
        let d = &found[0];
        assert_eq!((d.id, d.hamming), (17, 0));
        assert_eq!(d.corner_ids, (0..12).collect::<Vec<u8>>());
        let errs = corner_errors(d, &pose);
        assert!(
            errs.iter().all(|&e| e < CLEAN_CORNER_TOL_PX),
            "roll {roll}: {errs:?}"
        );
    }
}

#[test]
fn reads_the_papers_ids_in_turbid_water() {
    for id in [10, 15, 17] {
        let pose = facing(0.0, 0.0, 0.61, 0.0, 30.0);
        let img = render(CodeSet::Shoal, id, pose, &WaterParams::preset(1.38));
        let found = ShoalDetector::new(CodeSet::Shoal, DetectParams::default())
            .detect_gray(&img)
            .unwrap();
        assert_eq!(found.iter().map(|d| d.id).collect::<Vec<_>>(), vec![id]);
    }
}

#[test]
fn clipped_outer_frame_still_gives_the_code_corners() {
    // Shifted so the outer frame runs off the left image border but the code square stays inside.
    let pose = facing(-0.31, 0.0, 0.61, 0.0, 0.0);
    let img = render(CodeSet::Shoal, 17, pose, &WaterParams::clear());
    let found = ShoalDetector::new(CodeSet::Shoal, DetectParams::default())
        .detect_gray(&img)
        .unwrap();
    assert_eq!(found.len(), 1, "{found:?}");
    let d = &found[0];
    assert_eq!(d.id, 17);
    assert!(
        !d.corner_ids.contains(&0),
        "outer frame is clipped: {:?}",
        d.corner_ids
    );
    assert!(d.corner_ids.ends_with(&[8, 9, 10, 11]));
    assert!(corner_errors(d, &pose)
        .iter()
        .all(|&e| e < CLEAN_CORNER_TOL_PX));
}

#[test]
fn occluded_frame_still_gives_the_code_corners() {
    let pose = facing(0.0, 0.0, 0.61, 0.0, 0.0);
    let mut img = render(CodeSet::Shoal, 17, pose, &WaterParams::clear());
    // A grey bar across the top of the frame (not the code).
    let cam = CameraModel::vehicle_1440();
    let top = cam
        .project(&(pose * CodeSet::Shoal.corners_3d(SIDE_M)[0]))
        .unwrap();
    for y in (top.y as usize - 12)..(top.y as usize + 14) {
        for x in 500..900 {
            img.data[y * img.width as usize + x] = 128;
        }
    }
    let found = ShoalDetector::new(CodeSet::Shoal, DetectParams::default())
        .detect_gray(&img)
        .unwrap();
    assert_eq!(found.len(), 1);
    assert_eq!(found[0].id, 17);
    assert!(!found[0].corner_ids.contains(&0));
    assert!(corner_errors(&found[0], &pose)
        .iter()
        .all(|&e| e < CLEAN_CORNER_TOL_PX));
}

#[test]
fn reads_aruco_and_apriltag_code_sets() {
    for (codes, id) in [
        (CodeSet::Aruco4x4_50, 17),
        (CodeSet::Aruco5x5_100, 42),
        (CodeSet::Aruco6x6_250, 200),
        (CodeSet::AprilTag16h5, 7),
        (CodeSet::AprilTag36h11, 301),
    ] {
        let pose = facing(0.02, 0.01, 0.61, 90.0, 25.0);
        let img = render(codes, id, pose, &WaterParams::clear());
        let found = ShoalDetector::new(codes, DetectParams::default())
            .detect_gray(&img)
            .unwrap();
        assert_eq!(
            found.iter().map(|d| d.id).collect::<Vec<_>>(),
            vec![id],
            "{codes}"
        );
        assert_eq!(found[0].corner_ids, vec![0, 1, 2, 3]);
        assert!(
            corner_errors(&found[0], &pose)
                .iter()
                .all(|&e| e < CLEAN_CORNER_TOL_PX),
            "{codes}"
        );
    }
}

#[test]
fn does_not_guess_on_noise_or_a_blank_frame() {
    let mut state = 12345u64;
    let data: Vec<u8> = (0..640 * 480)
        .map(|_| {
            state = state
                .wrapping_mul(6364136223846793005)
                .wrapping_add(1442695040888963407);
            (state >> 56) as u8
        })
        .collect();
    let noise = GrayImage::from_vec(640, 480, data).unwrap();
    let mut det = ShoalDetector::new(CodeSet::Shoal, DetectParams::default());
    assert!(det.detect_gray(&noise).unwrap().is_empty());
    assert!(det
        .detect_gray(&GrayImage::filled(64, 48, 200))
        .unwrap()
        .is_empty());
    // A marker of another code set (AprilTag) is not read as an enhanced marker.
    let img = render(
        CodeSet::AprilTag36h11,
        3,
        facing(0.0, 0.0, 0.61, 0.0, 0.0),
        &WaterParams::clear(),
    );
    assert!(det.detect_gray(&img).unwrap().is_empty());
}

#[test]
fn rejects_a_malformed_image() {
    let bad = GrayImage {
        width: 10,
        height: 10,
        data: vec![0; 7],
    };
    let mut det = ShoalDetector::new(CodeSet::Shoal, DetectParams::default());
    assert!(det.detect_gray(&bad).is_err());
}

#[test]
fn another_fiducials_black_square_is_not_read_as_an_enhanced_marker() {
    // A plain ArUco 4x4 marker carries the enhanced marker's code square
    // (the same code table) but no frame around it: with the frame required
    // (the default) it is not a shoal marker; without, it reads as one.
    let pose = facing(0.0, 0.0, 0.61, 0.0, 20.0);
    let img = render(CodeSet::Aruco4x4_50, 17, pose, &WaterParams::clear());
    let found = ShoalDetector::new(CodeSet::Shoal, DetectParams::default())
        .detect_gray(&img)
        .unwrap();
    assert!(found.is_empty(), "{found:?}");
    let loose = DetectParams {
        require_frame: false,
        ..DetectParams::default()
    };
    let found = ShoalDetector::new(CodeSet::Shoal, loose)
        .detect_gray(&img)
        .unwrap();
    assert_eq!(found.iter().map(|d| d.id).collect::<Vec<_>>(), vec![17]);
    // Its black square, and the edge of the white around it as the frame's
    // inner edge: never the outer frame edge.
    assert!(!found[0].corner_ids.contains(&0), "{found:?}");
    // The enhanced marker itself in turbid water, its outer edge too faint
    // to fit, is still read: the frame shows in the pixels.
    for water in [1.38, 3.92] {
        let img = render(
            CodeSet::Shoal,
            17,
            facing(0.0, 0.0, 0.61, 0.0, 20.0),
            &WaterParams::preset(water),
        );
        let found = ShoalDetector::new(CodeSet::Shoal, DetectParams::default())
            .detect_gray(&img)
            .unwrap();
        assert_eq!(
            found.iter().map(|d| d.id).collect::<Vec<_>>(),
            vec![17],
            "{water} /m"
        );
    }
}

/// The paper's swarm range (§6.3: 100 mm markers read to 4 m at 0.5 /m) on
/// the 1440x1080 camera: from 3.5 m a module is ≤ 3.6 px, under 1.8 px on
/// the half-resolution level the quads are searched on. The code square's
/// contour there sits a level's half pixel inside its edge and its polygon
/// corners are off by up to 2.5 px; read and refined from where the contour
/// stands (not the square's true edge), it failed the read or the corner
/// refinement beyond ~3 m (1 and 2 of these 12 at 3.5 and 4 m before the
/// fix, 12 and 12 after; at 4.5 m 3 and 6, not asserted, only that no
/// other ID is read: the half level's binarization of a 1.4 px frame is
/// the next limit).
#[test]
fn reads_the_100_mm_marker_at_the_papers_swarm_range() {
    let water = WaterParams::preset(0.5);
    let mut detector = ShoalDetector::new(CodeSet::Shoal, DetectParams::default());
    for (range_m, at_least) in [(3.5, 12), (4.0, 11), (4.5, 0)] {
        let mut read = 0;
        for k in 0..12 {
            // Sub-pixel phases and off-axis positions, and a noise seed each.
            let x = -0.4 + 0.071 * k as f64;
            let y = 0.05 * ((k % 5) as f64 - 2.0);
            let pose = facing(x, y, range_m, 7.0 * k as f64, 15.0);
            let cam = CameraModel::vehicle_1440();
            let scene = Scene::single_marker(CodeSet::Shoal, 15, SIDE_M, pose);
            let img = Renderer::new()
                .render(&cam, &Pose::identity(), &scene, &water, 0.0, 100 + k)
                .unwrap()
                .image;
            let found = detector.detect_gray(&img).unwrap();
            assert!(found.iter().all(|d| d.id == 15), "{range_m} m: {found:?}");
            read += usize::from(!found.is_empty());
        }
        assert!(
            read >= at_least,
            "{range_m} m: {read} of 12 read, {at_least} expected"
        );
    }
}

/// A 100 mm marker 4.5–5 m away at 0.5 /m through HOIRM, as the node reads
/// it. HOIRM takes the strongest contrast in view for an object at 0.6 m and
/// estimates water of 5–6 /m, so it smooths the marker's region (σ 1.7–2.7
/// px) and deconvolves it with the scatter halo alone: both erase its
/// 2–3 px modules, and the frame's restoration reads none of these frames.
/// The region's detail-keeping restoration (`Restored::fine`: no smoothing,
/// the unscattered part of the PSF kept), searched because nothing was read
/// there, reads them: 6 of 6 at each range here (12 and 11 of 12 over the
/// swarm-range test's poses; the raw frame 6 and 3 of 12, CLAHE 2 and 0).
#[test]
fn hoirm_reads_the_100_mm_marker_at_5_m_on_its_detail_keeping_restoration() {
    use shoal_node::pipeline::detect_restoration;
    use shoal_node::restore::{restorer, Method, RestoreParams};
    let water = WaterParams::preset(0.5);
    let mut detector = ShoalDetector::new(CodeSet::Shoal, DetectParams::default());
    for range_m in [4.5, 5.0] {
        let (mut read, mut fine) = (0, 0);
        for k in 0..6 {
            let x = -0.4 + 0.142 * k as f64;
            let y = 0.05 * ((k % 5) as f64 - 2.0);
            let pose = facing(x, y, range_m, 14.0 * k as f64, 15.0);
            let img = render_seeded(CodeSet::Shoal, 15, pose, &water, 200 + k);
            let raw = shoal_node::mat::gray_to_mat(&img).unwrap();
            let restored = restorer(Method::Hoirm, &RestoreParams::default())
                .restore(&raw, 0)
                .unwrap();
            let found = detect_restoration(&mut detector, &restored, &raw).unwrap();
            let recipe = restored
                .fine
                .as_ref()
                .expect("HOIRM smoothed the marker's region");
            let other = opencv::core::Mat::new_rows_cols_with_default(
                540,
                720,
                opencv::core::CV_8UC1,
                opencv::core::Scalar::all(0.0),
            )
            .unwrap();
            assert!(
                matches!(
                    recipe.image(&restored.image, &other, &recipe.regions),
                    Err(shoal_node::restore::RestoreError::FrameMismatch { .. })
                ),
                "another frame is refused"
            );
            assert!(
                found.detections.iter().all(|d| d.id == 15),
                "{range_m} m: {:?}",
                found.detections
            );
            read += usize::from(!found.detections.is_empty());
            fine += found.fine_reads;
        }
        assert!(
            read >= 5,
            "{range_m} m: {read} of 6 read ({fine} on the fine restoration)"
        );
    }
}

/// The fine pass is for regions that stood out and read nothing; a frame
/// restored whole because its regions passed `roi_max_fraction` (through
/// the realistic camera: empty views, whose correlated noise passes as
/// regions) is searched once, unless `fine_pass_whole_frame`. The 4.5 m
/// frame above, its fallback forced by a `roi_max_fraction` its one region
/// exceeds.
#[test]
fn a_frame_restored_whole_is_searched_again_only_when_asked() {
    use shoal_node::restore::{restorer, Method, RestoreParams};
    let pose = facing(-0.4, -0.1, 4.5, 0.0, 15.0);
    let img = render_seeded(CodeSet::Shoal, 15, pose, &WaterParams::preset(0.5), 200);
    let raw = shoal_node::mat::gray_to_mat(&img).unwrap();
    let fine_regions = |params: RestoreParams| {
        let restored = restorer(Method::Hoirm, &params).restore(&raw, 0).unwrap();
        let whole = restored.rois.len() == 1 && restored.rois[0].area() == 1440 * 1080;
        (whole, restored.fine.map(|f| f.regions))
    };
    let (whole, regions) = fine_regions(RestoreParams::default());
    assert!(!whole, "the marker's region is a region");
    assert!(
        regions.is_some_and(|r| !r.is_empty() && r.iter().all(|r| r.area() < 1440 * 1080 / 4)),
        "its region is searched again"
    );
    let forced = RestoreParams {
        roi_max_fraction: 1e-4,
        ..RestoreParams::default()
    };
    assert_eq!(fine_regions(forced.clone()), (true, None));
    let (whole, regions) = fine_regions(RestoreParams {
        fine_pass_whole_frame: true,
        ..forced
    });
    assert!(whole);
    assert_eq!(
        regions.map(|r| r.iter().map(|r| r.area()).collect::<Vec<_>>()),
        Some(vec![1440 * 1080])
    );
}

/// What `vehicle`'s starboard camera sees of the paper's fleet line abreast
/// `spacing_m` apart at 0.5 /m, `time_s` into the run (seed 7, as `shoal
/// sim render --spacing S --time T --vehicle V`): one frame whose only
/// visible marker is `marker`.
fn paper_fleet_view(
    spacing_m: f64,
    time_s: f64,
    vehicle: u32,
    marker: u32,
) -> shoal_sim_bridge::render::RenderOutput {
    use shoal_sim_bridge::render::render_fleet_view;
    use shoal_sim_bridge::world::{Formation, SwarmWorld};
    let fleet = shoal_proto::config::Fleet::load(
        &std::path::Path::new(env!("CARGO_MANIFEST_DIR")).join("../configs/fleets/paper.toml"),
    )
    .unwrap();
    let mut world = SwarmWorld::new(&fleet, Formation::Line, spacing_m, 7).unwrap();
    world.step(time_s);
    let water = WaterParams::preset(0.5);
    let frame = render_fleet_view(
        &mut Renderer::new(),
        &fleet,
        &world.truth(),
        vehicle,
        4,
        &water,
        time_s,
        0,
        7,
    )
    .unwrap();
    let ids: Vec<u32> = frame.visible.iter().map(|v| v.marker).collect();
    assert_eq!(ids, vec![marker], "the scene");
    frame
}

/// A code square is read again on its refined edges, on the restored and
/// the raw frame, and a disagreement is settled by the fewer corrected
/// bits. The paper's fleet 3.5 m abreast at 0.5 /m: vehicle 10's starboard
/// camera sees marker 35 (vehicle 15's port side) at 3.46 m. HOIRM
/// estimates 3.3 /m in this scene, hands the detector its smoothed level
/// and rings the 3.7 px modules; the contour of the half-resolution level
/// is a module off, and its grid read one corrected bit from marker 17 —
/// a fleet ID, a wrong read. On its refined edges the raw frame reads 35
/// with no bit corrected.
#[test]
fn a_far_marker_through_hoirm_is_read_as_itself() {
    use shoal_node::restore::{restorer, Method, RestoreParams};
    let frame = paper_fleet_view(3.5, 0.0, 10, 35);
    let raw = shoal_node::mat::gray_to_mat(&frame.image).unwrap();
    let restored = restorer(Method::Hoirm, &RestoreParams::default())
        .restore(&raw, 0)
        .unwrap();
    let found = ShoalDetector::new(CodeSet::Shoal, DetectParams::default())
        .detect_with_raw_fit(&restored.image, &raw)
        .unwrap();
    let read: Vec<(u32, u32)> = found.iter().map(|d| (d.id, d.hamming)).collect();
    assert_eq!(read, vec![(35, 0)], "{found:?}");
}

/// On the half-resolution level a far marker's one-module frame (1.4 level
/// px) breaks: its contour is no quad, only a *blob* whose convex hull is
/// nearly one and which is darker than its surround; the blob's window is
/// searched again at full resolution. The paper's fleet 4.5 m abreast at
/// 0.5 /m: vehicle 15's starboard camera sees marker 37 at 4.45 m (2.8 px
/// per module), which only the blob's window finds.
#[test]
fn a_far_markers_broken_contour_is_searched_again_at_full_resolution() {
    let frame = paper_fleet_view(4.5, 0.1, 15, 37);
    let found = ShoalDetector::new(CodeSet::Shoal, DetectParams::default())
        .detect_gray(&frame.image)
        .unwrap();
    let read: Vec<u32> = found.iter().map(|d| d.id).collect();
    assert_eq!(read, vec![37], "{found:?}");
}

/// HOIRM's second search (`pipeline::detect_restoration`) looks only near
/// its detail-keeping regions. Traced only inside windows, the detector
/// reads a marker inside one exactly as the whole frame's search does (the
/// same corners to the bit: the image is thresholded whole and a region
/// inside the window has the same contour), and nothing of a marker the
/// windows leave out or cut.
#[test]
fn a_search_within_windows_reads_the_markers_inside_them_as_the_whole_frame_search_does() {
    use shoal_node::detect::MarkerDetector;
    let cam = CameraModel::vehicle_1440();
    let water = WaterParams::preset(0.5);
    let mut scene = Scene::single_marker(
        CodeSet::Shoal,
        3,
        SIDE_M,
        facing(-0.3, 0.0, 1.2, 10.0, 15.0),
    );
    scene.markers.extend(
        Scene::single_marker(
            CodeSet::Shoal,
            7,
            SIDE_M,
            facing(0.3, 0.05, 1.5, -5.0, -20.0),
        )
        .markers,
    );
    let img = Renderer::new()
        .render(&cam, &Pose::identity(), &scene, &water, 0.0, 5)
        .unwrap()
        .image;
    let mat = shoal_node::mat::gray_to_mat(&img).unwrap();
    let mut det = ShoalDetector::new(CodeSet::Shoal, DetectParams::default());
    let whole = det.detect_restored(&mat, &mat).unwrap();
    let find = |ds: &[Detection], id: u32| ds.iter().find(|d| d.id == id).cloned();
    let (three, seven) = (
        find(&whole, 3).expect("marker 3"),
        find(&whole, 7).expect("marker 7"),
    );
    // A window around marker 7 (its corners' bounding box and 48 px).
    let around = |d: &Detection, m: f64| {
        let xs = d.corners_px.iter().map(|c| c[0]);
        let ys = d.corners_px.iter().map(|c| c[1]);
        let (x0, x1) = (
            xs.clone().fold(f64::MAX, f64::min) - m,
            xs.fold(f64::MIN, f64::max) + m,
        );
        let (y0, y1) = (
            ys.clone().fold(f64::MAX, f64::min) - m,
            ys.fold(f64::MIN, f64::max) + m,
        );
        opencv::core::Rect::new(x0 as i32, y0 as i32, (x1 - x0) as i32, (y1 - y0) as i32)
    };
    let within = det
        .detect_restored_within(&mat, &mat, &[around(&seven, 48.0)])
        .unwrap();
    assert_eq!(within.len(), 1, "{within:?}");
    assert_eq!(within[0].id, 7);
    assert_eq!(
        within[0].corners_px, seven.corners_px,
        "the same corners to the bit"
    );
    assert_eq!(within[0].corner_ids, seven.corner_ids);
    // A window that cuts marker 3 through its middle reads nothing of it.
    let whole3 = around(&three, 0.0);
    let half3 = opencv::core::Rect::new(whole3.x, whole3.y, whole3.width / 2, whole3.height);
    let cut = det.detect_restored_within(&mat, &mat, &[half3]).unwrap();
    assert!(cut.iter().all(|d| d.id != 3), "{cut:?}");
}

/// A tag36h11 tag (ID 7, axis-aligned, `MODULE_PX` per module) on a grey
/// card, with a dark wedge joined to its black square's bottom-left corner
/// and reaching `tip` px (left, down) beyond it — a shadow or the card's edge
/// touching the corner — blurred by a Gaussian of 1 px. Returns the frame
/// and the black square's outer corners (TL, TR, BR, BL; pixel edges).
fn tag_with_a_wedge_at_one_corner(tip: (i32, i32)) -> (GrayImage, [[f64; 2]; 4]) {
    use opencv::core::{Mat, Point, Vector, CV_8UC1};
    use opencv::prelude::*;
    const MODULE_PX: i32 = 12;
    let (size, x0, y0) = (200, 52, 48);
    let codes = CodeSet::AprilTag36h11;
    let m = codes.modules() as i32;
    let grid = codes.module_grid(7).unwrap();
    let (dark, light) = (50u8, 190u8);
    let mut img = Mat::new_rows_cols_with_default(
        size,
        size,
        CV_8UC1,
        opencv::core::Scalar::all(f64::from(light)),
    )
    .unwrap();
    for y in 0..m * MODULE_PX {
        for x in 0..m * MODULE_PX {
            let white = grid[((y / MODULE_PX) * m + x / MODULE_PX) as usize];
            *img.at_2d_mut::<u8>(y0 + y, x0 + x).unwrap() = if white { light } else { dark };
        }
    }
    let (bx, by) = (x0, y0 + m * MODULE_PX);
    let wedge: Vector<Point> = [
        (bx + 8, by - 1),
        (bx - 1, by - 10),
        (bx - tip.0, by + tip.1),
        (bx - tip.0 + 6, by + tip.1 + 4),
    ]
    .into_iter()
    .map(|(x, y)| Point::new(x, y))
    .collect();
    let polys: Vector<Vector<Point>> = [wedge].into_iter().collect();
    opencv::imgproc::fill_poly(
        &mut img,
        &polys,
        opencv::core::Scalar::all(f64::from(dark)),
        opencv::imgproc::LINE_8,
        0,
        Point::default(),
    )
    .unwrap();
    let (l, t) = (f64::from(x0) - 0.5, f64::from(y0) - 0.5);
    let (r, b) = (l + f64::from(m * MODULE_PX), t + f64::from(m * MODULE_PX));
    (blurred_by_a_pixel(&img), [[l, t], [r, t], [r, b], [l, b]])
}

/// `img` (8-bit grey) blurred by a Gaussian of 1 px, as a frame.
fn blurred_by_a_pixel(img: &opencv::core::Mat) -> GrayImage {
    use opencv::prelude::*;
    let mut blurred = opencv::core::Mat::default();
    opencv::imgproc::gaussian_blur(
        img,
        &mut blurred,
        opencv::core::Size::new(0, 0),
        1.0,
        1.0,
        opencv::core::BORDER_REPLICATE,
    )
    .unwrap();
    assert_eq!(blurred.typ(), opencv::core::CV_8UC1);
    GrayImage {
        width: blurred.cols() as u32,
        height: blurred.rows() as u32,
        data: blurred.data_bytes().unwrap().to_vec(),
    }
}

#[test]
fn a_dark_region_joined_at_one_corner_does_not_pull_that_corner_out() {
    // A shadow or the card's edge touching a tag's corner joins the black
    // region, and the contour's polygon runs out to the wedge's tip: one
    // corner 1–2 modules off. The build before read these with that corner
    // 13.5 and 25 px out; the tag turned 40° of the public rotation steps
    // (docs/detector.md, "A corner pulled out") was not read at all.
    for tip in [(16, 14), (22, 10)] {
        let (frame, truth) = tag_with_a_wedge_at_one_corner(tip);
        // The premise: some quad's corner is over a module (12 px) from the square's.
        let mat = shoal_node::mat::gray_as_mat(&frame).unwrap();
        let quads = shoal_node::detect::quads::find_quads(&DetectParams::default(), &mat).unwrap();
        let offs = |q: &[[f64; 2]; 4]| -> Vec<f64> {
            let mut d: Vec<f64> = q
                .iter()
                .map(|p| {
                    truth
                        .iter()
                        .map(|t| (p[0] - t[0]).hypot(p[1] - t[1]))
                        .fold(f64::INFINITY, f64::min)
                })
                .collect();
            d.sort_by(f64::total_cmp);
            d
        };
        assert!(
            quads.iter().any(|q| {
                let d = offs(&q.pts);
                d[2] < 3.0 && d[3] > 12.0
            }),
            "tip {tip:?}: no quad with three corners on the square's and one over a module off"
        );
        let mut det = ShoalDetector::new(CodeSet::AprilTag36h11, DetectParams::default());
        let found = det.detect_gray(&frame).unwrap();
        assert_eq!(found.len(), 1, "tip {tip:?}: {found:?}");
        assert_eq!(found[0].id, 7);
        let corners: [[f64; 2]; 4] = std::array::from_fn(|i| found[0].corners_px[i]);
        let err = offs(&corners)[3];
        assert!(
            err < 0.5,
            "tip {tip:?}: a corner {err:.2} px off: {corners:?}"
        );
    }
}

/// What joins a tag's black square to a dark neighbour in
/// [`tag_joined_to`].
#[derive(Clone, Copy, Debug)]
enum Neighbour {
    /// Nothing: the tag alone on its card.
    None,
    /// A stand: a dark bar from the bottom side, near its right end, down
    /// to the frame's bottom row (the region is cut by the frame's edge).
    Stand,
    /// A card's shaded edge: a dark bar along the left, joined to the
    /// lower quarter of the left side.
    CardEdge,
}

/// A tag36h11 tag (ID 7, 10 px modules, `flip`: one data module inverted)
/// on a light card, joined to `neighbour`, turned `turn_deg` about the
/// frame's centre and blurred by a Gaussian of 1 px. Returns the frame and
/// the black square's outer corners (TL, TR, BR, BL as drawn).
fn tag_joined_to(neighbour: Neighbour, flip: bool, turn_deg: f64) -> (GrayImage, [[f64; 2]; 4]) {
    use opencv::core::{Mat, Point2f, Rect, Scalar, Size, BORDER_REPLICATE, CV_8UC1};
    use opencv::prelude::*;
    const MODULE_PX: i32 = 10;
    let (size, x0, y0) = (240, 80, 60);
    let codes = CodeSet::AprilTag36h11;
    let m = codes.modules() as i32;
    let mut grid = codes.module_grid(7).unwrap();
    if flip {
        let k = (3 * m + 4) as usize;
        grid[k] = !grid[k];
    }
    let (dark, light) = (50.0, 190.0);
    let mut img = Mat::new_rows_cols_with_default(size, size, CV_8UC1, Scalar::all(light)).unwrap();
    for y in 0..m * MODULE_PX {
        for x in 0..m * MODULE_PX {
            let white = grid[((y / MODULE_PX) * m + x / MODULE_PX) as usize];
            *img.at_2d_mut::<u8>(y0 + y, x0 + x).unwrap() = if white { 190 } else { 50 };
        }
    }
    let side = m * MODULE_PX;
    let bar = match neighbour {
        Neighbour::None => None,
        Neighbour::Stand => Some(Rect::new(x0 + side - 22, y0 + side, 12, size - y0 - side)),
        Neighbour::CardEdge => Some(Rect::new(x0 - 30, y0 + side - 20, 30, 14)),
    };
    if let Some(r) = bar {
        opencv::imgproc::rectangle(
            &mut img,
            r,
            Scalar::all(dark),
            -1,
            opencv::imgproc::LINE_8,
            0,
        )
        .unwrap();
    }
    let (l, t) = (f64::from(x0) - 0.5, f64::from(y0) - 0.5);
    let (r, b) = (l + f64::from(side), t + f64::from(side));
    let mut corners = [[l, t], [r, t], [r, b], [l, b]];
    let mut turned = img.clone();
    if turn_deg != 0.0 {
        let c = 0.5 * f64::from(size - 1);
        let rot = opencv::imgproc::get_rotation_matrix_2d(
            Point2f::new(c as f32, c as f32),
            turn_deg,
            1.0,
        )
        .unwrap();
        opencv::imgproc::warp_affine(
            &img,
            &mut turned,
            &rot,
            Size::new(size, size),
            opencv::imgproc::INTER_LINEAR,
            BORDER_REPLICATE,
            Scalar::all(0.0),
        )
        .unwrap();
        let a = |r: i32, k: i32| *rot.at_2d::<f64>(r, k).unwrap();
        corners = corners.map(|[x, y]| {
            [
                a(0, 0) * x + a(0, 1) * y + a(0, 2),
                a(1, 0) * x + a(1, 1) * y + a(1, 2),
            ]
        });
    }
    (blurred_by_a_pixel(&turned), corners)
}

/// The largest distance from a corner of `truth` to the nearest of `q`.
fn worst_corner(q: &[[f64; 2]; 4], truth: &[[f64; 2]; 4]) -> f64 {
    truth
        .iter()
        .map(|t| {
            q.iter()
                .map(|p| (p[0] - t[0]).hypot(p[1] - t[1]))
                .fold(f64::INFINITY, f64::min)
        })
        .fold(0.0, f64::max)
}

#[test]
fn a_tag_joined_to_a_dark_neighbour_is_read_on_the_sides_its_outline_keeps() {
    // A tag on a stand, or beside a card's shaded edge, is one dark region
    // with it: no quad of its own (and a stand reaching the frame's edge cut
    // the region out of the search altogether). The public rotation steps'
    // +70° tag and 14 tank-video reads at the frame's edge were missed so
    // (docs/detector.md, "A marker joined to its neighbour").
    for neighbour in [Neighbour::Stand, Neighbour::CardEdge] {
        for turn in [0.0, 17.0, -33.0] {
            let (frame, truth) = tag_joined_to(neighbour, false, turn);
            let what = format!("{neighbour:?}, turned {turn}°");
            // The premise: no quad of its own is found on the tag.
            let mat = shoal_node::mat::gray_as_mat(&frame).unwrap();
            let quads =
                shoal_node::detect::quads::find_quads(&DetectParams::default(), &mat).unwrap();
            let on_tag: Vec<_> = quads
                .iter()
                .filter(|q| worst_corner(&q.pts, &truth) < 5.0)
                .collect();
            assert!(!on_tag.is_empty(), "{what}: no quad on the tag at all");
            assert!(
                on_tag.iter().all(|q| q.exact_only),
                "{what}: the tag's region is a quad of its own: {on_tag:?}"
            );
            let mut det = ShoalDetector::new(CodeSet::AprilTag36h11, DetectParams::default());
            let found = det.detect_gray(&frame).unwrap();
            assert_eq!(found.len(), 1, "{what}: {found:?}");
            assert_eq!((found[0].id, found[0].hamming), (7, 0), "{what}");
            let corners: [[f64; 2]; 4] = std::array::from_fn(|i| found[0].corners_px[i]);
            let err = worst_corner(&corners, &truth);
            assert!(err < 0.5, "{what}: a corner {err:.2} px off: {corners:?}");
        }
    }
}

#[test]
fn a_joined_tag_reads_only_on_an_exact_code() {
    // Pieced together from a larger region's outline, a quad has more ways
    // to frame a code by chance: one bit off is refused there, and read
    // (one bit corrected) on the same tag standing alone.
    let mut det = ShoalDetector::new(CodeSet::AprilTag36h11, DetectParams::default());
    let (alone, _) = tag_joined_to(Neighbour::None, true, 17.0);
    let found = det.detect_gray(&alone).unwrap();
    assert_eq!(found.len(), 1, "{found:?}");
    assert_eq!((found[0].id, found[0].hamming), (7, 1));
    for neighbour in [Neighbour::Stand, Neighbour::CardEdge] {
        let (frame, _) = tag_joined_to(neighbour, true, 17.0);
        let found = det.detect_gray(&frame).unwrap();
        assert!(found.is_empty(), "{neighbour:?}: {found:?}");
    }
}

/// A 1100x800 frame (searched at half size): a small tag36h11 tag (ID 7,
/// 3 px modules) hanging 2 px below a post that comes down from a dark
/// border around the frame's top and sides, so that at half size the gap
/// closes and the tag is part of that border's region (longer than the
/// frame's own outline); below it, the 40 light cells (10 x 4) of a dark
/// grid (quads that read nothing). Blurred by a Gaussian of 1 px. Returns
/// the frame and the tag's outer corners.
fn small_tag_below_a_post() -> (GrayImage, [[f64; 2]; 4]) {
    use opencv::core::{Mat, Rect, Scalar, CV_8UC1};
    use opencv::prelude::*;
    const MODULE_PX: i32 = 3;
    let (w, h) = (1100, 800);
    let codes = CodeSet::AprilTag36h11;
    let m = codes.modules() as i32;
    let grid = codes.module_grid(7).unwrap();
    let (dark, light) = (Scalar::all(50.0), Scalar::all(190.0));
    let mut img = Mat::new_rows_cols_with_default(h, w, CV_8UC1, light).unwrap();
    let fill = |img: &mut Mat, r: Rect, v: Scalar| {
        opencv::imgproc::rectangle(img, r, v, -1, opencv::imgproc::LINE_8, 0).unwrap();
    };
    // The border: a band along the top, down both sides.
    fill(&mut img, Rect::new(0, 0, w, 60), dark);
    fill(&mut img, Rect::new(0, 0, 40, h), dark);
    fill(&mut img, Rect::new(w - 40, 0, 40, h), dark);
    // The tag, and the post ending two pixels above it (from an odd row:
    // each half-size pixel over the gap takes half of the post or tag).
    let (x0, y0) = (400, 203);
    for y in 0..m * MODULE_PX {
        for x in 0..m * MODULE_PX {
            let white = grid[((y / MODULE_PX) * m + x / MODULE_PX) as usize];
            *img.at_2d_mut::<u8>(y0 + y, x0 + x).unwrap() = if white { 190 } else { 50 };
        }
    }
    let side = m * MODULE_PX;
    fill(&mut img, Rect::new(x0 + 6, 60, 2, y0 - 2 - 60), dark);
    // The grid: 2 px lines, cells of 26 px.
    let (gx, gy, pitch, cols, rows) = (120, 420, 28, 10, 4);
    for r in 0..=rows {
        fill(
            &mut img,
            Rect::new(gx, gy + r * pitch, cols * pitch + 2, 2),
            dark,
        );
    }
    for c in 0..=cols {
        fill(
            &mut img,
            Rect::new(gx + c * pitch, gy, 2, rows * pitch + 2),
            dark,
        );
    }
    let (l, t) = (f64::from(x0) - 0.5, f64::from(y0) - 0.5);
    let (r, b) = (l + f64::from(side), t + f64::from(side));
    (blurred_by_a_pixel(&img), [[l, t], [r, t], [r, b], [l, b]])
}

#[test]
fn a_small_tag_joined_to_the_background_at_half_size_is_read_ahead_of_light_cells() {
    // The public rotation steps' +70° tag: at half size its border meets
    // the shelf's post behind it, and so the dark background that reaches
    // round the frame, whose outline was not searched; and the light
    // cells of the paper grid in front filled every full-resolution window
    // (docs/detector.md, "A marker joined to the background at half size").
    let (frame, truth) = small_tag_below_a_post();
    let params = DetectParams::default();
    assert!(frame.width as i32 > params.full_res_max_width);
    // The premises: at full size the tag's square is a quad of its own…
    let mat = shoal_node::mat::gray_as_mat(&frame).unwrap();
    let full = DetectParams {
        full_res_max_width: 2000,
        ..DetectParams::default()
    };
    let quads = shoal_node::detect::quads::find_quads(&full, &mat).unwrap();
    assert!(
        quads
            .iter()
            .any(|q| !q.exact_only && worst_corner(&q.pts, &truth) < 3.0),
        "no quad of its own at full size"
    );
    // …at half size only one pieced from the background's outline, and the
    // grid's cells outnumber the full-resolution windows.
    let quads = shoal_node::detect::quads::find_quads(&params, &mat).unwrap();
    let on_tag: Vec<_> = quads
        .iter()
        .filter(|q| worst_corner(&q.pts, &truth) < 4.0)
        .collect();
    assert!(!on_tag.is_empty(), "no quad on the tag at half size");
    assert!(on_tag.iter().all(|q| q.exact_only), "{on_tag:?}");
    let cells = quads
        .iter()
        .filter(|q| !q.exact_only && q.pts.iter().all(|c| c[1] > 400.0))
        .count();
    assert!(cells > params.max_full_res_regions, "{cells} cells");
    let mut det = ShoalDetector::new(CodeSet::AprilTag36h11, params);
    let found = det.detect_gray(&frame).unwrap();
    assert_eq!(found.len(), 1, "{found:?}");
    assert_eq!((found[0].id, found[0].hamming), (7, 0));
    let corners: [[f64; 2]; 4] = std::array::from_fn(|i| found[0].corners_px[i]);
    let err = worst_corner(&corners, &truth);
    assert!(err < 0.5, "a corner {err:.2} px off: {corners:?}");
}
