//! Numeric arguments every command refuses at parse time (issue #22): a
//! rate, size, spacing or duration that is zero, negative, infinite or NaN
//! is an error naming the flag (exit 2), never a panic, a flipped pose or a
//! silent default.

use std::process::Command;

/// Runs `shoal ARGS`; returns (exit code, stderr).
fn shoal(args: &[&str]) -> (Option<i32>, String) {
    let out = Command::new(env!("CARGO_BIN_EXE_shoal"))
        .args(args)
        .env_remove("SHOAL_STATION_TOKEN")
        .output()
        .expect("run shoal");
    (
        out.status.code(),
        String::from_utf8_lossy(&out.stderr).into_owned(),
    )
}

#[test]
fn bad_numbers_are_refused_with_the_flag_named() {
    let dir = std::env::temp_dir().join(format!("shoal-cli-args-{}", std::process::id()));
    std::fs::create_dir_all(&dir).unwrap();
    let out = dir.join("x.png");
    let out = out.to_str().unwrap();
    let cases: &[(&[&str], &str)] = &[
        (
            &["link", "--vehicle", "10", "--rate-bps", "0"],
            "--rate-bps",
        ),
        (
            &["link", "--vehicle", "10", "--rate-bps", "NaN"],
            "--rate-bps",
        ),
        (
            &["fuse", "in.mcap", "--out", "o.mcap", "--rate", "inf"],
            "--rate",
        ),
        (
            &["fuse", "in.mcap", "--out", "o.mcap", "--rate", "0"],
            "--rate",
        ),
        (
            &["fuse", "in.mcap", "--out", "o.mcap", "--rate", "NaN"],
            "--rate",
        ),
        (
            &["fuse", "in.mcap", "--out", "o.mcap", "--window", "0"],
            "--window",
        ),
        (
            &["fuse", "in.mcap", "--out", "o.mcap", "--window", "inf"],
            "--window",
        ),
        (
            &["sim", "render", "--out", out, "--spacing", "0"],
            "--spacing",
        ),
        (
            &["sim", "render", "--out", out, "--spacing=-1"],
            "--spacing",
        ),
        (
            &["sim", "render", "--out", out, "--spacing", "NaN"],
            "--spacing",
        ),
        (
            &[
                "marker",
                "generate",
                "--id",
                "17",
                "--out",
                out,
                "--size-mm=-100",
            ],
            "--size-mm",
        ),
        (
            &[
                "marker", "generate", "--id", "17", "--out", out, "--dpi", "0",
            ],
            "--dpi",
        ),
        (&["detect", "--size-mm=-100", out], "--size-mm"),
        (&["demo", "--duration", "inf"], "--duration"),
        (&["demo", "--ros2-domain", "233"], "--ros2-domain"),
        (&["fusion", "--ros2-domain", "x"], "--ros2-domain"),
        (&["demo", "--time-scale", "0"], "--time-scale"),
        (
            &[
                "relay",
                "--listen",
                "tcp/127.0.0.1:1",
                "--to",
                "tcp/127.0.0.1:2",
                "--loss",
                "1.5",
            ],
            "--loss",
        ),
    ];
    for (args, flag) in cases {
        let (code, err) = shoal(args);
        assert_eq!(code, Some(2), "shoal {args:?}: exit {code:?}, stderr {err}");
        assert!(
            err.contains("invalid value") && err.contains(flag),
            "shoal {args:?}: stderr does not name {flag}: {err}"
        );
    }
    assert!(
        !std::path::Path::new(out).exists(),
        "a refused command wrote its output"
    );
    let _ = std::fs::remove_dir_all(&dir);
}

/// `shoal station`'s access options: each refusal says what and how, before
/// any server or Zenoh session starts, and never panics.
#[test]
fn station_access_options_are_refused_with_a_reason() {
    let (code, err) = shoal(&["station", "--tls-cert", "cert.pem"]);
    assert_eq!(code, Some(2), "{err}");
    assert!(err.contains("--tls-key"), "{err}");
    let cases: &[(&[&str], &str)] = &[
        (
            &["station", "--bind", "0.0.0.0", "--no-foxglove"],
            "--insecure-public",
        ),
        (
            &[
                "station",
                "--bind",
                "0.0.0.0",
                "--token",
                "0123456789abcdef0123",
            ],
            "--no-foxglove",
        ),
        (&["station", "--token", "secret"], "16"),
        (
            &["station", "--allow-host", "http://vessel.local/"],
            "--allow-host",
        ),
        (
            &[
                "station",
                "--tls-cert",
                "/nonexistent/station-cert.pem",
                "--tls-key",
                "/nonexistent/station-key.pem",
            ],
            "/nonexistent/station-cert.pem",
        ),
    ];
    for (args, says) in cases {
        let (code, err) = shoal(args);
        assert_eq!(code, Some(1), "shoal {args:?}: exit {code:?}, stderr {err}");
        assert!(
            err.contains(says),
            "shoal {args:?}: stderr lacks {says:?}: {err}"
        );
        assert!(!err.contains("panicked"), "shoal {args:?}: {err}");
    }
}
