//! Fuzzing the water presets loader (issue #10): `configs/water.toml` with
//! random damage and random text. Loading never panics; a refused file's
//! error names the file and the field (or the preset / knob holding it); an
//! accepted file gives finite, valid water at every preset.
//!
//! Cases per property: `SHOAL_FUZZ_CASES` (default 1000).
//! Longer on demand: `SHOAL_FUZZ_CASES=100000 cargo test -p shoal-sim-bridge --test fuzz_water`.

use proptest::prelude::*;
use proptest::test_runner::Config as ProptestConfig;
use shoal_sim_bridge::water::WaterPresets;
use std::path::Path;

/// Failures print the minimal input; no regression files in the source tree.
fn fuzz_config(default_cases: u32) -> ProptestConfig {
    ProptestConfig {
        failure_persistence: None,
        ..ProptestConfig::with_cases(shoal_proto::samples::fuzz_cases(default_cases))
    }
}

const WATER_TOML: &str = include_str!("../../configs/water.toml");
const WATER_PATH: &str = "fuzzed/water.toml";
const BAD_VALUES: [&str; 10] = [
    "nan",
    "inf",
    "-inf",
    "-1",
    "0",
    "1e308",
    "-1e308",
    "\"clear\"",
    "[]",
    "true",
];

/// `(key, value range)` of every `key = <number>` line.
fn numeric_values(text: &str) -> Vec<(String, std::ops::Range<usize>)> {
    let mut out = Vec::new();
    let mut offset = 0;
    for line in text.split_inclusive('\n') {
        let code = line.split('#').next().unwrap_or("");
        if let Some((k, v)) = code.split_once('=') {
            let key = k.trim();
            let value = v.trim();
            if !key.is_empty() && value.parse::<f64>().is_ok() {
                let start = offset + line.find(value).unwrap_or(0);
                out.push((key.to_string(), start..start + value.len()));
            }
        }
        offset += line.len();
    }
    out
}

fn assert_usable(w: &WaterPresets) {
    assert!(!w.presets.is_empty());
    for c in w.coefficients() {
        let p = w.get(c).expect("every preset's own c is in range");
        p.validate().expect("an accepted preset is valid");
    }
}

/// `noise_scale = 1e308` passes the knob check (finite, non-negative) but
/// divides every preset's `gain_e_per_dn` by 1e616 = inf, leaving 0: water the
/// renderer cannot use. Each preset is validated with the knobs applied.
#[test]
fn a_noise_knob_that_zeroes_the_gain_is_refused() {
    let text = WATER_TOML.replacen("noise_scale = 1.0", "noise_scale = 1e308", 1);
    assert_ne!(text, WATER_TOML);
    let e = WaterPresets::parse(&text, Path::new(WATER_PATH))
        .expect_err("a knob that makes every preset invalid is refused")
        .to_string();
    assert!(
        e.contains("gain_e_per_dn") || e.contains("noise_scale"),
        "{e}"
    );
}

#[test]
fn the_shipped_water_file_loads_and_has_numbers_to_damage() {
    let w = WaterPresets::parse(WATER_TOML, Path::new(WATER_PATH)).unwrap();
    assert_usable(&w);
    let keys: Vec<String> = numeric_values(WATER_TOML)
        .into_iter()
        .map(|(k, _)| k)
        .collect();
    for k in ["c_per_m", "psf_shape_p", "noise_scale", "vignetting"] {
        assert!(keys.iter().any(|x| x == k), "no {k}");
    }
}

proptest! {
    #![proptest_config(fuzz_config(1000))]

    #[test]
    fn random_text_never_panics_the_water_loader(text in "(?s).{0,300}") {
        match WaterPresets::parse(&text, Path::new(WATER_PATH)) {
            Ok(w) => assert_usable(&w),
            Err(e) => prop_assert!(e.to_string().contains(WATER_PATH)),
        }
    }

    #[test]
    fn a_damaged_water_value_is_refused_naming_its_field(pick in any::<usize>(), bad in 0usize..BAD_VALUES.len()) {
        let spans = numeric_values(WATER_TOML);
        let (key, range) = spans[pick % spans.len()].clone();
        let mut text = WATER_TOML.to_string();
        text.replace_range(range, BAD_VALUES[bad]);
        match WaterPresets::parse(&text, Path::new(WATER_PATH)) {
            Ok(w) => assert_usable(&w),
            Err(e) => {
                let e = e.to_string();
                prop_assert!(e.contains(WATER_PATH), "{e}");
                // Two presets made equal by the damage are named as such.
                let same_c = key == "c_per_m" && e.contains("same c_per_m");
                prop_assert!(e.contains(&key) || same_c,
                    "error for `{key}` = {} does not name it: {e}", BAD_VALUES[bad]);
            }
        }
    }

    #[test]
    fn a_cut_or_garbled_water_file_never_panics(
        cut in any::<usize>(),
        garble in proptest::collection::vec((any::<usize>(), any::<char>()), 1..4),
        cut_it in any::<bool>(),
    ) {
        let text: String = if cut_it {
            WATER_TOML.chars().take(cut % (WATER_TOML.chars().count() + 1)).collect()
        } else {
            let mut chars: Vec<char> = WATER_TOML.chars().collect();
            let n = chars.len();
            for (at, c) in garble {
                chars[at % n] = c;
            }
            chars.into_iter().collect()
        };
        match WaterPresets::parse(&text, Path::new(WATER_PATH)) {
            Ok(w) => assert_usable(&w),
            Err(e) => prop_assert!(e.to_string().contains(WATER_PATH)),
        }
    }
}
