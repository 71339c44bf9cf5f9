//! Fuzzing image decoding on the node's image-folder path (issue #10):
//! PNG, BMP, PGM, TIFF and JPEG files cut short, with bytes overwritten, or
//! replaced by random bytes, read by `source::read_image_gray` (what
//! `LocalSource::Images` uses). Each read gives a well-formed 8-bit image or an
//! error naming the file, never a panic or a crash; the reader thread skips
//! and counts unreadable files and delivers the good ones.
//!
//! Cases per property: `SHOAL_FUZZ_CASES` (default 512).
//! Longer on demand: `SHOAL_FUZZ_CASES=20000 cargo test -p shoal-node --test fuzz_image`.

use opencv::core::{Mat, Vector, CV_8UC1};
use opencv::imgcodecs;
use opencv::prelude::*;
use proptest::prelude::*;
use proptest::test_runner::Config as ProptestConfig;
use shoal_node::source::{read_image_gray, spawn_reader, LocalSource};
use shoal_proto::messages::{CameraInfo, StampSource, WireMessage};
use shoal_proto::queue::DropOldestQueue;
use shoal_proto::CameraModel;
use std::path::{Path, PathBuf};
use std::sync::atomic::{AtomicBool, Ordering};
use std::sync::{Arc, OnceLock};

/// Failures print the minimal input; no regression files in the source tree.
fn fuzz_config(default_cases: u32) -> ProptestConfig {
    ProptestConfig {
        failure_persistence: None,
        ..ProptestConfig::with_cases(shoal_proto::samples::fuzz_cases(default_cases))
    }
}

const EXTENSIONS: [&str; 5] = ["png", "bmp", "pgm", "tif", "jpg"];
const W: i32 = 64;
const H: i32 = 48;

fn scratch_dir(name: &str) -> PathBuf {
    let dir = Path::new(env!("CARGO_TARGET_TMPDIR"))
        .join(format!("fuzz_image-{}", std::process::id()))
        .join(name);
    std::fs::create_dir_all(&dir).unwrap();
    dir
}

/// A 64x48 grey test image encoded in each format.
fn encoded() -> &'static Vec<Vec<u8>> {
    static FILES: OnceLock<Vec<Vec<u8>>> = OnceLock::new();
    FILES.get_or_init(|| {
        let mut m = Mat::new_rows_cols_with_default(H, W, CV_8UC1, 0.into()).unwrap();
        for y in 0..H {
            for x in 0..W {
                *m.at_2d_mut::<u8>(y, x).unwrap() = ((x * 4 + y * 2) % 256) as u8;
            }
        }
        EXTENSIONS
            .iter()
            .map(|ext| {
                let mut buf = Vector::<u8>::new();
                assert!(
                    imgcodecs::imencode(&format!(".{ext}"), &m, &mut buf, &Vector::new()).unwrap()
                );
                buf.to_vec()
            })
            .collect()
    })
}

/// Read `bytes` saved as `name`: Ok must be a consistent image, Err must name the file.
fn read_back(dir: &Path, name: &str, bytes: &[u8]) -> Result<(u32, u32), String> {
    let path = dir.join(name);
    std::fs::write(&path, bytes).unwrap();
    let out = match read_image_gray(&path) {
        Ok(g) => {
            assert!(g.width > 0 && g.height > 0);
            assert_eq!(g.data.len(), g.width as usize * g.height as usize);
            Ok((g.width, g.height))
        }
        Err(e) => {
            let e = e.to_string();
            assert!(e.contains(name), "error does not name the file: {e}");
            Err(e)
        }
    };
    let _ = std::fs::remove_file(&path);
    out
}

#[test]
fn intact_files_of_every_format_read_at_their_size() {
    let dir = scratch_dir("intact");
    for (ext, bytes) in EXTENSIONS.iter().zip(encoded()) {
        assert_eq!(
            read_back(&dir, &format!("ok.{ext}"), bytes),
            Ok((W as u32, H as u32)),
            "{ext}"
        );
    }
}

#[test]
fn empty_and_missing_files_are_errors() {
    let dir = scratch_dir("empty");
    for ext in EXTENSIONS {
        assert!(read_back(&dir, &format!("empty.{ext}"), &[]).is_err());
    }
    let e = read_image_gray(&dir.join("absent.png"))
        .unwrap_err()
        .to_string();
    assert!(e.contains("absent.png"), "{e}");
}

#[test]
fn the_folder_source_skips_and_counts_unreadable_files() {
    let dir = scratch_dir("folder");
    let png = &encoded()[0];
    std::fs::write(dir.join("a_good.png"), png).unwrap();
    std::fs::write(dir.join("b_empty.png"), []).unwrap();
    std::fs::write(dir.join("c_half.png"), &png[..png.len() / 2]).unwrap();
    std::fs::write(dir.join("d_text.jpg"), b"not an image at all").unwrap();
    std::fs::write(dir.join("e_good.bmp"), &encoded()[1]).unwrap();
    let queue = DropOldestQueue::new(16);
    let counters = Arc::new(shoal_node::vehicle::SourceCounters::default());
    let info = CameraInfo {
        model: CameraModel::vehicle_1440(),
        body_from_camera: shoal_proto::Pose::identity(),
    };
    let thread = spawn_reader(
        LocalSource::Images {
            dir: dir.clone(),
            camera: 0,
            rate_hz: 200.0,
        },
        10,
        info,
        queue.clone(),
        counters.clone(),
        Arc::new(AtomicBool::new(false)),
    )
    .unwrap();
    thread.join().expect("the reader thread does not panic");
    let frames = queue.drain();
    assert_eq!(counters.unreadable.load(Ordering::Relaxed), 3);
    assert_eq!(frames.len(), 2);
    assert_eq!(counters.stamp_source(), StampSource::Playback);
    for f in &frames {
        assert_eq!(
            (f.info.model.width, f.info.model.height),
            (W as u32, H as u32)
        );
        f.validate()
            .expect("a delivered frame is a valid CameraFrame");
    }
    assert_eq!(frames.iter().map(|f| f.seq).collect::<Vec<_>>(), vec![0, 4]);
}

/// Issue #22: a file cut short was read as a whole picture (grey bottom, no
/// word said). Cut at every byte, each format is an error naming the file.
#[test]
fn a_file_cut_at_any_byte_is_an_error() {
    use shoal_node::image_file::{decode_gray, MAX_IMAGE_PIXELS};
    for (ext, bytes) in EXTENSIONS.iter().zip(encoded()) {
        let name = format!("cut.{ext}");
        for len in 0..bytes.len() {
            match decode_gray(&name, &bytes[..len], MAX_IMAGE_PIXELS) {
                Err(e) => assert!(e.to_string().contains(&name), "{e}"),
                Ok(_) => panic!(
                    "{ext} cut at {len} of {} bytes was read as whole",
                    bytes.len()
                ),
            }
        }
    }
}

proptest! {
    #![proptest_config(fuzz_config(512))]

    /// A valid file of each format cut short and/or with bytes overwritten.
    #[test]
    fn damaged_image_files_decode_or_fail_cleanly(
        which in 0usize..EXTENSIONS.len(),
        flips in proptest::collection::vec((any::<usize>(), 1u8..=255), 0..8),
        cut in proptest::option::of(any::<usize>()),
    ) {
        let mut bytes = encoded()[which].clone();
        for (at, v) in flips {
            let i = at % bytes.len();
            bytes[i] ^= v;
        }
        if let Some(c) = cut {
            bytes.truncate(c % (bytes.len() + 1));
        }
        let _ = read_back(&scratch_dir("damaged"), &format!("f.{}", EXTENSIONS[which]), &bytes);
    }

    /// Random bytes behind a file's real magic number, or none at all.
    #[test]
    fn random_bytes_with_an_image_extension_fail_cleanly(
        which in 0usize..EXTENSIONS.len(),
        keep_magic in 0usize..16,
        noise in proptest::collection::vec(any::<u8>(), 0..4096),
    ) {
        let head = &encoded()[which][..keep_magic];
        let mut bytes = head.to_vec();
        bytes.extend_from_slice(&noise);
        let _ = read_back(&scratch_dir("random"), &format!("r.{}", EXTENSIONS[which]), &bytes);
    }
}
