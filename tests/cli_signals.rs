//! Issue #22: commands stopped by a signal, and commands whose reader goes
//! away. `shoal demo` stopped by SIGTERM finishes its log (summary, footer:
//! an indexed reader opens it) and prints what it did; killed by SIGKILL it
//! loses at most the record it was writing. A closed stdout (`| head`) never
//! panics a command.

use shoal_record::reader::scan_wire;
use std::path::{Path, PathBuf};
use std::process::{Child, Command, Stdio};
use std::time::{Duration, Instant};

fn scratch(name: &str) -> PathBuf {
    let dir =
        Path::new(env!("CARGO_TARGET_TMPDIR")).join(format!("cli_signals-{}", std::process::id()));
    std::fs::create_dir_all(&dir).unwrap();
    dir.join(name)
}

/// A long demo writing `log`, side cameras only, no station.
fn start_demo(log: &Path) -> Child {
    Command::new(env!("CARGO_BIN_EXE_shoal"))
        .args([
            "demo",
            "--duration",
            "120",
            "--cameras",
            "port,starboard",
            "--no-station",
            "--mcap",
        ])
        .arg(log)
        .env("SHOAL_LOG", "warn")
        .stdout(Stdio::piped())
        .stderr(Stdio::piped())
        .spawn()
        .expect("start shoal demo")
}

/// Wait until the log holds some observations (the recorder closes a chunk every second).
fn wait_for_observations(demo: &mut Child, log: &Path) {
    let deadline = Instant::now() + Duration::from_secs(120);
    loop {
        assert!(
            demo.try_wait().unwrap().is_none(),
            "the demo exited before it was signalled"
        );
        let mut obs = 0;
        if log.exists() {
            let _ = scan_wire(log, |c, _, _| -> Result<(), ()> {
                obs += u64::from(c.topic.ends_with("/obs"));
                Ok(())
            });
        }
        if obs > 0 {
            return;
        }
        assert!(Instant::now() < deadline, "no observation logged in 120 s");
        std::thread::sleep(Duration::from_millis(500));
    }
}

fn signal(child: &Child, sig: &str) {
    let ok = Command::new("kill")
        .args([sig, &child.id().to_string()])
        .status()
        .expect("kill")
        .success();
    assert!(ok, "kill {sig} failed");
}

fn wait_with_deadline(mut child: Child, limit: Duration) -> std::process::Output {
    let deadline = Instant::now() + limit;
    while child.try_wait().unwrap().is_none() {
        if Instant::now() > deadline {
            let _ = child.kill();
            panic!("the process did not exit within {limit:?} of the signal");
        }
        std::thread::sleep(Duration::from_millis(100));
    }
    child.wait_with_output().unwrap()
}

#[test]
fn a_demo_stopped_by_sigterm_finishes_its_log_and_says_what_it_did() {
    let log = scratch("term.mcap");
    let mut demo = start_demo(&log);
    wait_for_observations(&mut demo, &log);
    signal(&demo, "-TERM");
    let out = wait_with_deadline(demo, Duration::from_secs(60));
    let stdout = String::from_utf8_lossy(&out.stdout);
    let stderr = String::from_utf8_lossy(&out.stderr);
    assert!(out.status.success(), "exit {:?}: {stderr}", out.status);
    assert!(stdout.contains("interrupted at"), "{stdout}");
    assert!(stdout.contains("log:"), "no log summary printed: {stdout}");
    let info = shoal_record::info(&log).unwrap();
    assert!(info.complete, "log left incomplete: {:?}", info.damage);
    assert!(info.messages > 0);
    // The strict, indexed reader of the `mcap` crate opens it too.
    let buf = std::fs::read(&log).unwrap();
    assert!(shoal_record::mcap::Summary::read(&buf).unwrap().is_some());
}

#[test]
fn a_demo_killed_by_sigkill_loses_at_most_its_last_record() {
    let log = scratch("kill.mcap");
    let mut demo = start_demo(&log);
    wait_for_observations(&mut demo, &log);
    std::thread::sleep(Duration::from_millis(1500));
    signal(&demo, "-KILL");
    let _ = wait_with_deadline(demo, Duration::from_secs(10));
    let mut obs = 0u64;
    let outcome = scan_wire(&log, |c, _, _| -> Result<(), ()> {
        obs += u64::from(c.topic.ends_with("/obs"));
        Ok(())
    })
    .unwrap();
    assert!(obs > 0);
    assert!(!outcome.complete);
    // Everything up to the record being written when it died was read.
    assert!(outcome.skipped_regions <= 1, "{:?}", outcome.skipped);
    if let Some(s) = outcome.skipped.first() {
        assert_eq!(s.offset + s.bytes, outcome.file_bytes, "{s:?}");
    }
}

#[test]
fn a_closed_stdout_never_panics_a_command() {
    let fleet = Path::new(env!("CARGO_MANIFEST_DIR")).join("configs/fleets/paper.toml");
    let fleet = fleet.to_str().unwrap();
    for args in [
        vec!["config", "check", fleet],
        vec!["marker", "generate", "--help"],
        vec!["--help"],
    ] {
        let (reader, writer) = std::io::pipe().unwrap();
        drop(reader);
        let out = Command::new(env!("CARGO_BIN_EXE_shoal"))
            .args(&args)
            .stdout(writer)
            .stderr(Stdio::piped())
            .output()
            .unwrap();
        let stderr = String::from_utf8_lossy(&out.stderr);
        assert!(!stderr.contains("panicked"), "{args:?}: {stderr}");
        assert_ne!(out.status.code(), Some(101), "{args:?}: {stderr}");
    }
}

/// A closed stderr (`2>&-`, or a reader that went away) must not panic a
/// command either: the summary and error lines are dropped, the exit status
/// still says what happened.
#[test]
fn a_closed_stderr_never_panics_a_command() {
    let dir = scratch("closed-stderr");
    let missing = dir.join("missing.png");
    let missing = missing.to_str().unwrap();
    for (args, code) in [
        (vec!["detect", missing], Some(1)),
        (vec!["config", "check", "/nonexistent.toml"], Some(1)),
    ] {
        let (reader, writer) = std::io::pipe().unwrap();
        drop(reader);
        let out = Command::new(env!("CARGO_BIN_EXE_shoal"))
            .args(&args)
            .stdout(Stdio::piped())
            .stderr(writer)
            .output()
            .unwrap();
        assert_eq!(out.status.code(), code, "{args:?}");
    }
}
