//! `tools/aarch64-parity.py`, the comparer behind `./run aarch64 parity`
//! (docs/aarch64.md), on hand-made outputs of the two binaries: it must
//! count the pixels and corners that differ, and fail when the two read
//! different markers or decode different trials.

use std::path::Path;
use std::process::Command;

const CSV_HEADER: &str = "c_per_m,distance_mm,yaw_deg,frame,method,codes,restoration,decoded,pose,wrong_ids,corners,distance_error_mm,angle_error_deg,yaw_error_deg,reprojection_rms_px,detect_ms";

fn write(path: &Path, text: &str) {
    std::fs::create_dir_all(path.parent().unwrap()).unwrap();
    std::fs::write(path, text).unwrap();
}

fn frame(path: &Path, pixels: [u8; 6]) {
    std::fs::create_dir_all(path.parent().unwrap()).unwrap();
    image::GrayImage::from_raw(3, 2, pixels.to_vec())
        .unwrap()
        .save(path)
        .unwrap();
}

fn detection(x: f64) -> String {
    format!(
        "{{\"source\":\"f.png\",\"frame\":null,\"codes\":\"shoal\",\"id\":15,\"corner_fit\":\"raw_sides\",\
         \"corners_px\":[[{x},10.0],[20.0,10.0],[20.0,20.0],[10.0,20.0]],\
         \"camera_from_marker\":{{\"t_m\":[0.0,0.0,0.61]}}}}\n\
         {{\"source\":\"bad.png\",\"error\":\"not an image\"}}\n"
    )
}

fn trial(decoded: u8, distance_error_mm: f64) -> String {
    format!(
        "{CSV_HEADER}\n0.5,610.0,30,0,shoal,shoal,hoirm,{decoded},{decoded},0,12,{distance_error_mm},0.002,0.002,0.007,3.1\n"
    )
}

fn run(dir: &Path) -> (bool, String) {
    let script = Path::new(env!("CARGO_MANIFEST_DIR")).join("tools/aarch64-parity.py");
    let out = Command::new("python3")
        .arg(script)
        .arg(dir)
        .output()
        .expect("python3 runs (./run test installs it)");
    let text =
        String::from_utf8_lossy(&out.stdout).into_owned() + &String::from_utf8_lossy(&out.stderr);
    (out.status.success(), text)
}

#[test]
fn the_parity_comparer_measures_small_differences_and_fails_on_different_reads() {
    let dir = std::env::temp_dir().join(format!("shoal_aarch64_parity_{}", std::process::id()));
    std::fs::remove_dir_all(&dir).ok();
    frame(&dir.join("x86_64/frames/a.png"), [0, 10, 20, 30, 40, 50]);
    frame(&dir.join("aarch64/frames/a.png"), [0, 10, 23, 30, 40, 50]);
    write(&dir.join("x86_64/detect.jsonl"), &detection(10.0));
    write(&dir.join("aarch64/detect.jsonl"), &detection(10.5));
    write(&dir.join("x86_64/accuracy/accuracy.csv"), &trial(1, 0.076));
    write(&dir.join("aarch64/accuracy/accuracy.csv"), &trial(1, 0.077));

    let (ok, text) = run(&dir);
    assert!(ok, "{text}");
    assert!(text.contains("1 of 6 pixel values differ"), "{text}");
    assert!(text.contains("largest difference 3 DN"), "{text}");
    assert!(text.contains("same markers: yes"), "{text}");
    assert!(text.contains("corners at most 5.00e-01 px apart"), "{text}");
    assert!(text.contains("shoal 1.0e-03 mm"), "{text}");

    // A trial decoded on one machine only, then a marker read on one only:
    // each fails the comparison, naming what differs.
    write(&dir.join("aarch64/accuracy/accuracy.csv"), &trial(0, 0.077));
    let (ok, text) = run(&dir);
    assert!(!ok, "{text}");
    assert!(text.contains("differ in 1"), "{text}");
    write(&dir.join("aarch64/accuracy/accuracy.csv"), &trial(1, 0.076));
    write(
        &dir.join("aarch64/detect.jsonl"),
        "{\"source\":\"bad.png\",\"error\":\"not an image\"}\n",
    );
    let (ok, text) = run(&dir);
    assert!(!ok, "{text}");
    assert!(text.contains("only on x86_64"), "{text}");

    // A missing output is an error, not a pass.
    std::fs::remove_file(dir.join("aarch64/frames/a.png")).unwrap();
    write(&dir.join("aarch64/detect.jsonl"), &detection(10.0));
    let (ok, text) = run(&dir);
    assert!(!ok && text.contains("missing"), "{text}");
    std::fs::remove_dir_all(&dir).ok();
}
