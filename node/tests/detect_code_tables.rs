//! Parity of `proto/data/codes/*.txt` with the libraries they were extracted
//! from: OpenCV 4.6's ArUco dictionaries and libapriltag 3.

use opencv::{aruco, core, prelude::*};
use shoal_node::baseline::apriltag_ffi::{Family, FamilyHandle};
use shoal_proto::marker::{code_bit, CodeSet};

/// OpenCV's drawn marker, one pixel per module including the black border, `true` = white.
fn opencv_marker(dict: aruco::PREDEFINED_DICTIONARY_NAME, id: u32, modules: usize) -> Vec<bool> {
    let d = aruco::get_predefined_dictionary(dict).unwrap();
    let mut img = core::Mat::default();
    aruco::draw_marker(&d, id as i32, modules as i32, &mut img, 1).unwrap();
    (0..modules * modules)
        .map(|k| {
            *img.at_2d::<u8>((k / modules) as i32, (k % modules) as i32)
                .unwrap()
                > 127
        })
        .collect()
}

/// IDs checked: a spread sample plus the paper's IDs 10, 15, 17.
fn sample_ids(len: usize) -> Vec<u32> {
    let mut ids: Vec<u32> = (0..len as u32).step_by(37).collect();
    ids.extend([10, 15, 17, len as u32 - 1]);
    ids
}

#[test]
fn aruco_tables_match_opencv_dictionaries() {
    use aruco::PREDEFINED_DICTIONARY_NAME as D;
    for (set, dict) in [
        (CodeSet::Aruco4x4_1000, D::DICT_4X4_1000),
        (CodeSet::Aruco5x5_1000, D::DICT_5X5_1000),
        (CodeSet::Aruco6x6_1000, D::DICT_6X6_1000),
    ] {
        assert_eq!(set.len(), 1000, "{set}");
        let m = set.modules();
        for id in sample_ids(1000) {
            let ours = set.module_grid(id).unwrap();
            assert_eq!(ours, opencv_marker(dict, id, m), "{set} id {id}");
        }
        let d = aruco::get_predefined_dictionary(dict).unwrap();
        assert_eq!(
            set.table().max_correction_bits,
            d.max_correction_bits() as u32,
            "{set}"
        );
    }
}

#[test]
fn smaller_aruco_dictionaries_are_prefixes() {
    use aruco::PREDEFINED_DICTIONARY_NAME as D;
    for id in [0, 10, 15, 17, 49] {
        assert_eq!(
            CodeSet::Aruco4x4_50.module_grid(id).unwrap(),
            opencv_marker(D::DICT_4X4_50, id, 6)
        );
        assert_eq!(
            CodeSet::Aruco6x6_250.module_grid(id).unwrap(),
            opencv_marker(D::DICT_6X6_250, id, 8)
        );
    }
}

#[test]
fn apriltag_tables_match_libapriltag_renders() {
    for (set, fam) in [
        (CodeSet::AprilTag16h5, Family::Tag16h5),
        (CodeSet::AprilTag36h11, Family::Tag36h11),
    ] {
        let f = FamilyHandle::new(fam).unwrap();
        assert_eq!(set.len(), f.ncodes(), "{set}");
        let m = set.modules();
        for id in sample_ids(f.ncodes()) {
            let (w, px) = f.render(id as usize).unwrap();
            let off = (w - m) / 2;
            let theirs: Vec<bool> = (0..m * m)
                .map(|k| px[(off + k / m) * w + off + k % m] > 127)
                .collect();
            assert_eq!(set.module_grid(id).unwrap(), theirs, "{set} id {id}");
        }
    }
}

#[test]
fn enhanced_marker_17_is_opencv_4x4_50_marker_17_inside_a_white_ring() {
    use aruco::PREDEFINED_DICTIONARY_NAME as D;
    let grid = CodeSet::Shoal.module_grid(17).unwrap();
    let code = opencv_marker(D::DICT_4X4_50, 17, 6);
    for r in 0..10 {
        for c in 0..10 {
            let ring = r.min(c).min(9 - r).min(9 - c);
            let expected = match ring {
                0 => false, // black frame
                1 => true,  // white ring
                _ => code[(r - 2) * 6 + (c - 2)],
            };
            assert_eq!(grid[r * 10 + c], expected, "module ({r}, {c})");
        }
    }
    // The paper's other example IDs decode to distinct codes.
    let codes: Vec<u64> = [10, 15, 17]
        .iter()
        .map(|&i| CodeSet::Shoal.code(i).unwrap())
        .collect();
    assert!(codes[0] != codes[1] && codes[1] != codes[2]);
    assert!(code_bit(codes[2], 4, 0, 0) == code[7]);
}
