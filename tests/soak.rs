//! The soak, short (issue #22): one cycle of faults — the link to the ground
//! station cut for 3 s, fusion killed and restarted, a vehicle's session
//! closed for 2 s — in 26 s of the simulated swarm. Every fault is recovered
//! from (a map with every vehicle Live) within 5 s, no map goes missing
//! outside the fusion restart, and memory and open files stay flat. The
//! hour-long run is `shoal soak` (docs/results.md, "Soak").

use shoal::soak::{run, SoakConfig};
use std::sync::atomic::AtomicBool;

#[test]
fn one_cycle_of_faults_is_survived_with_flat_resources() {
    let cfg = SoakConfig {
        duration_s: 26.0,
        every_s: 24.0,
        partition_s: 3.0,
        recover_s: 5.0,
        seed: 7,
    };
    let report = run(&cfg, &AtomicBool::new(false), |line| eprintln!("{line}")).unwrap();
    eprintln!("{}", report.summary());
    assert!(report.passed(), "{}", report.summary());
    let kinds: Vec<&str> = report.events.iter().map(|e| e.what.as_str()).collect();
    assert_eq!(report.events.len(), 3, "{kinds:?}");
    assert!(kinds[0].starts_with("link cut") && kinds[1].starts_with("fusion killed"));
    assert!(kinds[2].starts_with("vehicle 10"));
    for e in &report.events {
        let r = e.recovered_after_s.unwrap_or_else(|| panic!("{e:?}"));
        assert!(r <= cfg.recover_s, "{e:?}");
    }
    // Maps at 10 Hz: at least 8 a second over the run.
    assert!(
        report.maps_received as f64 >= 8.0 * 24.0,
        "{}",
        report.maps_received
    );
    assert!(report.samples.len() >= 3);
}
