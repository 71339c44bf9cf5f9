//! A lab's path from a board to a calibration, end to end through the
//! `shoal` binary: `shoal board generate` prints boards at true size, and
//! `shoal calibrate` on frames the simulator renders of a grid of shoal
//! markers in water recovers the renderer's camera (fx, fy within 0.2 %,
//! the principal point within 1 px), writes OpenCV and ROS YAML that read
//! back as that camera, and says which views it did not use and why.

use nalgebra::{Translation3, UnitQuaternion, Vector3};
use shoal_node::board::Board;
use shoal_proto::camera::CameraModel;
use shoal_proto::config::parse_calibration_yaml;
use shoal_proto::geometry::Pose;
use shoal_proto::marker::CodeSet;
use shoal_sim_bridge::render::{write_png, Renderer, Scene, SceneMarker};
use shoal_sim_bridge::water::WaterParams;
use std::path::Path;
use std::process::Command;

const SHOAL: &str = env!("CARGO_BIN_EXE_shoal");

/// A fresh folder per test and process (nextest runs each test in its own).
fn scratch(test: &str) -> std::path::PathBuf {
    let dir = Path::new(env!("CARGO_TARGET_TMPDIR"))
        .join(format!("calibrate-{test}-{}", std::process::id()));
    let _ = std::fs::remove_dir_all(&dir);
    std::fs::create_dir_all(&dir).unwrap();
    dir
}

fn board() -> Board {
    Board::ShoalGrid {
        cols: 4,
        rows: 3,
        side_m: 0.1,
        gap_m: 0.03,
        first_id: 0,
    }
}

/// The board at `camera_from_board` as scene markers (camera at the world origin).
fn scene(camera_from_board: &Pose) -> Scene {
    let Board::ShoalGrid { side_m, .. } = board() else {
        unreachable!()
    };
    let mut scene = Scene::single_marker(CodeSet::Shoal, 0, side_m, Pose::identity());
    scene.markers.clear();
    // Marker frame (x right, y up, z out of the face) in the board frame
    // (x right, y down, z into the board): a half turn about x.
    let flip = UnitQuaternion::from_axis_angle(&Vector3::x_axis(), std::f64::consts::PI);
    for (id, [cx, cy]) in board().shoal_markers() {
        let board_from_marker = Pose::from_parts(Translation3::new(cx, cy, 0.0), flip);
        scene.markers.push(SceneMarker {
            codes: CodeSet::Shoal,
            id,
            side_m,
            world_from_marker: camera_from_board * board_from_marker,
            owner: 0,
        });
    }
    scene
}

/// Views a lab would take: the board over the whole image, 0.9–1.4 m away,
/// tilted 0–40° in varied directions.
fn render_views(cam: &CameraModel, dir: &Path) -> usize {
    let (bw, bh) = board().size_m();
    let mut renderer = Renderer::new();
    let water = WaterParams::preset(0.5);
    let mut n = 0;
    let tilts = [
        (0.0, 0.0),
        (0.6, 0.1),
        (-0.5, 0.3),
        (0.2, -0.65),
        (-0.3, -0.4),
        (0.45, 0.5),
    ];
    for (k, (fx, fy)) in [
        (-0.3, -0.25),
        (0.0, -0.25),
        (0.3, -0.25),
        (-0.3, 0.0),
        (0.0, 0.0),
        (0.3, 0.0),
        (-0.3, 0.25),
        (0.0, 0.25),
        (0.3, 0.25),
    ]
    .into_iter()
    .enumerate()
    {
        for j in 0..2 {
            let z = if (k + j) % 2 == 0 { 1.0 } else { 1.3 };
            let (rx, ry) = tilts[(k + 3 * j) % tilts.len()];
            // The board's centre on the ray through the image point (fx, fy)
            // (fractions of the half-size), turned about its own centre.
            let centre = Vector3::new(fx * z * 1.15, fy * z * 0.86, z);
            let turn = UnitQuaternion::from_euler_angles(rx, ry, 0.05 * k as f64);
            let pose = Pose::from_parts(Translation3::from(centre), turn)
                * Pose::from_parts(
                    Translation3::new(-bw / 2.0, -bh / 2.0, 0.0),
                    UnitQuaternion::identity(),
                );
            let out = renderer
                .render(
                    cam,
                    &Pose::identity(),
                    &scene(&pose),
                    &water,
                    0.0,
                    100 + n as u64,
                )
                .expect("render");
            write_png(&out.image, &dir.join(format!("view{n:02}.png"))).expect("png");
            n += 1;
        }
    }
    n
}

#[test]
fn calibrating_from_rendered_board_frames_recovers_the_renderers_camera() {
    let dir = scratch("rendered");
    let frames = dir.join("frames");
    std::fs::create_dir(&frames).unwrap();
    let cam = CameraModel::vehicle_1440();
    let n = render_views(&cam, &frames);
    let (yaml, ros, coverage) = (
        dir.join("cam.yaml"),
        dir.join("cam_ros.yaml"),
        dir.join("coverage.png"),
    );
    let run = Command::new(SHOAL)
        .args([
            "calibrate",
            "--shoal-grid",
            "4x3",
            "--side-mm",
            "100",
            "--gap-mm",
            "30",
            "--out",
        ])
        .arg(&yaml)
        .arg("--ros-out")
        .arg(&ros)
        .arg("--coverage")
        .arg(&coverage)
        .arg(&frames)
        .output()
        .unwrap();
    let (stdout, stderr) = (
        String::from_utf8_lossy(&run.stdout),
        String::from_utf8_lossy(&run.stderr),
    );
    assert!(run.status.success(), "{stdout}\n{stderr}");
    eprintln!("{stdout}{stderr}");
    for file in [&yaml, &ros] {
        let got = parse_calibration_yaml(&std::fs::read_to_string(file).unwrap()).unwrap();
        let (dfx, dfy) = (got.fx / cam.fx - 1.0, got.fy / cam.fy - 1.0);
        let (dcx, dcy) = (got.cx - cam.cx, got.cy - cam.cy);
        eprintln!(
            "{}: fx {:+.3} %, fy {:+.3} %, cx {dcx:+.2} px, cy {dcy:+.2} px",
            file.display(),
            dfx * 100.0,
            dfy * 100.0
        );
        assert!(dfx.abs() < 0.002 && dfy.abs() < 0.002, "{got:?}");
        assert!(dcx.abs() < 1.0 && dcy.abs() < 1.0, "{got:?}");
    }
    assert!(std::fs::metadata(&coverage).unwrap().len() > 1000);
    let kept: usize = stdout
        .lines()
        .find_map(|l| l.split(" views kept").next()?.parse().ok())
        .expect("a views-kept line");
    assert!(kept >= n - 2, "{kept} of {n} views kept:\n{stderr}");
}

#[test]
fn boards_are_generated_at_true_size_and_bad_ones_refused() {
    let dir = scratch("boards");
    let svg = dir.join("board.svg");
    let ok = Command::new(SHOAL)
        .args([
            "board",
            "generate",
            "--charuco",
            "5x7",
            "--square-mm",
            "40",
            "--marker-mm",
            "30",
            "--out",
        ])
        .arg(&svg)
        .output()
        .unwrap();
    assert!(
        ok.status.success(),
        "{}",
        String::from_utf8_lossy(&ok.stderr)
    );
    let text = std::fs::read_to_string(&svg).unwrap();
    assert!(text.contains(r#"width="224.000mm""#), "{}", &text[..200]);
    let png = dir.join("grid.png");
    let ok = Command::new(SHOAL)
        .args([
            "board",
            "generate",
            "--shoal-grid",
            "3x2",
            "--dpi",
            "150",
            "--out",
        ])
        .arg(&png)
        .output()
        .unwrap();
    assert!(
        ok.status.success(),
        "{}",
        String::from_utf8_lossy(&ok.stderr)
    );
    assert_eq!(&std::fs::read(&png).unwrap()[1..4], b"PNG");
    let bad = Command::new(SHOAL)
        .args([
            "board",
            "generate",
            "--charuco",
            "5x7",
            "--square-mm",
            "30",
            "--marker-mm",
            "40",
            "--out",
        ])
        .arg(dir.join("x.svg"))
        .output()
        .unwrap();
    let err = String::from_utf8_lossy(&bad.stderr);
    assert!(
        !bad.status.success() && err.contains("smaller than its square"),
        "{err}"
    );
    let none = Command::new(SHOAL)
        .args(["calibrate", "--charuco", "5x7", "--out"])
        .arg(dir.join("c.yaml"))
        .arg(dir.join("missing"))
        .output()
        .unwrap();
    let err = String::from_utf8_lossy(&none.stderr);
    assert!(
        !none.status.success() && err.contains("no such file or folder"),
        "{err}"
    );
}
