//! Output folders for tests that write files: one per test process under
//! the system's temporary folder, and those of test processes that have
//! ended cleared on first use. Each run of a suite otherwise left its eval
//! outputs behind (~30 folders a run: 550 of them, a few MB, on this
//! machine after ~20 runs).

use std::path::PathBuf;
use std::sync::Once;

/// `<tmp>/<prefix>-<name>-<pid>`, emptied; the first call in a process
/// also removes every `<prefix>-…-<pid>` folder whose process is gone.
pub fn scratch_dir(prefix: &str, name: &str) -> PathBuf {
    static SWEEP: Once = Once::new();
    let tmp = std::env::temp_dir();
    SWEEP.call_once(|| sweep_ended(&tmp, prefix));
    let dir = tmp.join(format!("{prefix}-{name}-{}", std::process::id()));
    let _ = std::fs::remove_dir_all(&dir);
    dir
}

/// Remove the folders `<prefix>-…-<pid>` under `tmp` of processes that no
/// longer run (Linux: no `/proc/<pid>`). Nothing is removed where `/proc`
/// is not there to ask.
fn sweep_ended(tmp: &std::path::Path, prefix: &str) {
    if !std::path::Path::new("/proc/self").exists() {
        return;
    }
    let Ok(entries) = std::fs::read_dir(tmp) else {
        return;
    };
    for e in entries.flatten() {
        let name = e.file_name().to_string_lossy().into_owned();
        let Some(rest) = name.strip_prefix(&format!("{prefix}-")) else {
            continue;
        };
        let Some(pid) = rest.rsplit('-').next().and_then(|p| p.parse::<u32>().ok()) else {
            continue;
        };
        if pid != std::process::id() && !std::path::Path::new(&format!("/proc/{pid}")).exists() {
            let _ = std::fs::remove_dir_all(e.path());
        }
    }
}
