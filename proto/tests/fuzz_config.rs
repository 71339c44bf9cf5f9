//! Fuzzing configuration loading (issue #10): fleet TOML and camera
//! calibration YAML, from random text and from the shipped files with random
//! damage. Loading must never panic; a refused file's error must name the
//! file and the field; an accepted file must hold only finite, usable values.
//!
//! Cases per property: `SHOAL_FUZZ_CASES` (default 1000).
//! Longer on demand: `SHOAL_FUZZ_CASES=100000 cargo test -p shoal-proto --test fuzz_config`.

use proptest::prelude::*;
use proptest::test_runner::Config as ProptestConfig;
use shoal_proto::config::{parse_calibration_yaml, Fleet};
use shoal_proto::geometry::pose_is_finite;
use std::path::Path;

/// Failures print the minimal input; no regression files in the source tree.
fn fuzz_config(default_cases: u32) -> ProptestConfig {
    ProptestConfig {
        failure_persistence: None,
        ..ProptestConfig::with_cases(shoal_proto::samples::fuzz_cases(default_cases))
    }
}

const PAPER_TOML: &str = include_str!("../../configs/fleets/paper.toml");
const PAPER_EQ3_YAML: &str = include_str!("../../configs/cameras/paper_eq3.yaml");
const VEHICLE_YAML: &str = include_str!("../../configs/cameras/vehicle_1440.yaml");

/// The name given to the parser; every error must carry it.
const FLEET_PATH: &str = "fuzzed/paper.toml";

/// Values a hostile or careless editor might put where a number belongs.
const BAD_VALUES: [&str; 12] = [
    "nan",
    "inf",
    "-inf",
    "-1",
    "0",
    "1e308",
    "-1e308",
    "99999999999999999999",
    "\"ten\"",
    "[]",
    "{}",
    "true",
];

/// Every accepted fleet is usable: finite mounts, valid cameras, its reference present.
fn assert_usable(f: &Fleet) {
    assert!(f.vehicle(f.reference_vehicle).is_some());
    for v in &f.vehicles {
        assert!(v.hull.diameter_m.is_finite() && v.hull.diameter_m > 0.0);
        assert!(v.hull.length_m.is_finite() && v.hull.length_m > 0.0);
        for c in &v.cameras {
            assert_eq!(
                c.model.problem(),
                None,
                "vehicle {} camera {}",
                v.id,
                c.name
            );
            assert!(pose_is_finite(&c.body_from_camera));
        }
        for m in &v.markers {
            assert!(m.side_m.is_finite() && m.side_m > 0.0);
            assert!(pose_is_finite(&m.body_from_marker));
        }
    }
}

/// Spans `(key, value range)` of `key = <number>` and `key = [numbers]` in `text`.
fn numeric_values(text: &str) -> Vec<(String, std::ops::Range<usize>)> {
    let mut out = Vec::new();
    let bytes = text.as_bytes();
    let mut i = 0;
    while i < bytes.len() {
        if bytes[i] == b'=' {
            // The key: the identifier before ` = `.
            let mut k_end = i;
            while k_end > 0 && bytes[k_end - 1] == b' ' {
                k_end -= 1;
            }
            let mut k_start = k_end;
            while k_start > 0
                && (bytes[k_start - 1].is_ascii_alphanumeric() || bytes[k_start - 1] == b'_')
            {
                k_start -= 1;
            }
            let mut v_start = i + 1;
            while v_start < bytes.len() && bytes[v_start] == b' ' {
                v_start += 1;
            }
            let mut v_end = v_start;
            if v_start < bytes.len() && bytes[v_start] == b'[' {
                while v_end < bytes.len() && bytes[v_end] != b']' && bytes[v_end] != b'\n' {
                    v_end += 1;
                }
                if v_end < bytes.len() && bytes[v_end] == b']' {
                    v_end += 1;
                    if text[v_start + 1..v_end - 1].contains('{') {
                        v_end = v_start; // an array of tables, not of numbers
                    }
                } else {
                    v_end = v_start; // a multi-line array of tables
                }
            } else {
                while v_end < bytes.len()
                    && (bytes[v_end].is_ascii_digit() || b".-+eE".contains(&bytes[v_end]))
                {
                    v_end += 1;
                }
            }
            if k_start < k_end && v_end > v_start {
                out.push((text[k_start..k_end].to_string(), v_start..v_end));
            }
        }
        i += 1;
    }
    out
}

#[test]
fn the_shipped_fleet_has_numbers_to_damage() {
    let spans = numeric_values(PAPER_TOML);
    for key in [
        "reference_vehicle",
        "xyz_m",
        "rpy_deg",
        "id",
        "side_m",
        "diameter_m",
        "length_m",
    ] {
        assert!(spans.iter().any(|(k, _)| k == key), "no {key} found");
    }
    let f = Fleet::parse(PAPER_TOML, Path::new(FLEET_PATH)).unwrap();
    assert_usable(&f);
}

#[test]
fn nan_mount_angle_is_refused_naming_the_mount() {
    let bad = PAPER_TOML.replacen("rpy_deg = [90, 0, 90]", "rpy_deg = [nan, 0, 90]", 1);
    let e = Fleet::parse(&bad, Path::new(FLEET_PATH))
        .unwrap_err()
        .to_string();
    assert!(
        e.contains(FLEET_PATH) && e.contains("body_from_camera"),
        "{e}"
    );
}

proptest! {
    #![proptest_config(fuzz_config(1000))]

    #[test]
    fn random_text_never_panics_the_fleet_loader(text in "(?s).{0,400}") {
        if let Err(e) = Fleet::parse(&text, Path::new(FLEET_PATH)) {
            prop_assert!(e.to_string().contains(FLEET_PATH));
        }
    }

    /// One number of the shipped fleet file replaced by something bad: the
    /// file is refused naming that key (or the table holding it), or accepted
    /// and usable (e.g. `0` where zero is fine).
    #[test]
    fn a_damaged_value_is_refused_naming_its_field(pick in any::<usize>(), bad in 0usize..BAD_VALUES.len()) {
        let spans = numeric_values(PAPER_TOML);
        let (key, range) = spans[pick % spans.len()].clone();
        let mut text = PAPER_TOML.to_string();
        text.replace_range(range.clone(), BAD_VALUES[bad]);
        match Fleet::parse(&text, Path::new(FLEET_PATH)) {
            Ok(f) => assert_usable(&f),
            Err(e) => {
                let e = e.to_string();
                prop_assert!(e.contains(FLEET_PATH), "{e}");
                // The line's leading key, e.g. `body_from_camera` for `xyz_m`.
                let line_start = PAPER_TOML[..range.start].rfind('\n').map_or(0, |i| i + 1);
                let line = PAPER_TOML[line_start..].trim_start();
                let outer: String = line.chars().take_while(|c| c.is_ascii_alphanumeric() || *c == '_').collect();
                // Renumbering the reference vehicle is caught by the cross-check.
                let cross = key == "id" && e.contains("field `reference_vehicle`");
                prop_assert!(
                    e.contains(&key) || (!outer.is_empty() && e.contains(&outer)) || cross,
                    "error for `{key}` = {} does not name the field: {e}", BAD_VALUES[bad]
                );
            }
        }
    }

    /// The shipped fleet cut short, with a line deleted, or with bytes overwritten.
    #[test]
    fn a_cut_or_garbled_fleet_file_never_panics(
        cut in any::<usize>(),
        drop_line in any::<usize>(),
        garble in proptest::collection::vec((any::<usize>(), any::<char>()), 0..4),
        mode in 0u8..3,
    ) {
        let text: String = match mode {
            0 => PAPER_TOML.chars().take(cut % (PAPER_TOML.chars().count() + 1)).collect(),
            1 => {
                let lines: Vec<&str> = PAPER_TOML.lines().collect();
                let skip = drop_line % lines.len();
                lines.iter().enumerate().filter(|(i, _)| *i != skip).map(|(_, l)| *l).collect::<Vec<_>>().join("\n")
            }
            _ => {
                let mut chars: Vec<char> = PAPER_TOML.chars().collect();
                let n = chars.len();
                for (at, c) in garble {
                    chars[at % n] = c;
                }
                chars.into_iter().collect()
            }
        };
        match Fleet::parse(&text, Path::new(FLEET_PATH)) {
            Ok(f) => assert_usable(&f),
            Err(e) => prop_assert!(e.to_string().contains(FLEET_PATH)),
        }
    }

    #[test]
    fn random_text_never_panics_the_calibration_reader(text in "(?s).{0,400}") {
        if let Ok(model) = parse_calibration_yaml(&text) {
            prop_assert_eq!(model.problem(), None);
        }
    }

    /// The shipped calibrations cut, with lines dropped, or with a value replaced.
    #[test]
    fn a_damaged_calibration_is_refused_or_valid(
        which in any::<bool>(),
        cut in any::<usize>(),
        drop_line in any::<usize>(),
        pick in any::<usize>(),
        bad in 0usize..BAD_VALUES.len(),
        mode in 0u8..3,
    ) {
        let src = if which { PAPER_EQ3_YAML } else { VEHICLE_YAML };
        let text: String = match mode {
            0 => src.chars().take(cut % (src.chars().count() + 1)).collect(),
            1 => {
                let lines: Vec<&str> = src.lines().collect();
                let skip = drop_line % lines.len();
                lines.iter().enumerate().filter(|(i, _)| *i != skip).map(|(_, l)| *l).collect::<Vec<_>>().join("\n")
            }
            _ => {
                // Replace one number (a scalar or inside a `data: [...]` list).
                let spans: Vec<std::ops::Range<usize>> = number_spans(src);
                let r = spans[pick % spans.len()].clone();
                let mut t = src.to_string();
                t.replace_range(r, BAD_VALUES[bad]);
                t
            }
        };
        match parse_calibration_yaml(&text) {
            Ok(model) => prop_assert_eq!(model.problem(), None),
            Err(e) => prop_assert!(!e.to_string().is_empty()),
        }
    }
}

/// Byte ranges of the numbers in a YAML calibration.
fn number_spans(text: &str) -> Vec<std::ops::Range<usize>> {
    let b = text.as_bytes();
    let mut out = Vec::new();
    let mut i = 0;
    while i < b.len() {
        let starts_number =
            (b[i].is_ascii_digit() || b[i] == b'-') && (i == 0 || b" [,:".contains(&b[i - 1]));
        if starts_number {
            let s = i;
            while i < b.len() && (b[i].is_ascii_digit() || b".-+eE".contains(&b[i])) {
                i += 1;
            }
            out.push(s..i);
        } else {
            i += 1;
        }
    }
    out
}
