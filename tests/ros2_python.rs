//! shoal as a ROS 2 citizen over `rmw_zenoh` (issue #20), checked by an
//! independent client: `tests/python/ros2_listen.py` joins the demo's router
//! with Python `eclipse-zenoh`, decodes every sample with `rosbags` (its own
//! CDR deserializer, Jazzy type definitions and RIHS01 hashes) and checks the
//! keys, attachments and liveliness tokens. Here the decoded values are
//! compared with the wire messages they came from. A recorder in the ROS 2
//! profile runs beside it; `tests/python/ros2_mcap.py` decodes its log with
//! the reference `mcap` reader and a `rosbags` type store built only from the
//! file's own `ros2msg` schemas, and the same comparisons are made.

use shoal::demo::DemoConfig;
use shoal_bus::{client_of, free_port, Bus, Subscription};
use shoal_proto::messages::{FleetMap, Observation};
use shoal_proto::{Cov6, Pose};
use std::collections::HashMap;
use std::path::Path;
use std::process::Command;
use std::time::Duration;

const DOMAIN: u32 = 42;

fn python_has(modules: &str, packages: &[&str]) -> Result<(), String> {
    let ok = |c: &mut Command| c.output().map(|o| o.status.success()).unwrap_or(false);
    let import = format!("import {modules}");
    if ok(Command::new("python3").args(["-c", &import])) {
        return Ok(());
    }
    eprintln!(
        "installing: python3 -m pip install --quiet {}",
        packages.join(" ")
    );
    let mut pip = Command::new("python3");
    pip.args(["-m", "pip", "install", "--quiet"]).args(packages);
    if ok(&mut pip) && ok(Command::new("python3").args(["-c", &import])) {
        Ok(())
    } else {
        Err(format!(
            "the ROS 2 check needs Python packages {packages:?} (`./run test` installs them; or python3 -m pip install {})",
            packages.join(" ")
        ))
    }
}

/// FRD → FLU signs of `(x, y, z, rx, ry, rz)`.
const FLU: [f64; 6] = [1.0, -1.0, -1.0, 1.0, -1.0, -1.0];

fn f64s(v: &serde_json::Value) -> Vec<f64> {
    v.as_array()
        .unwrap()
        .iter()
        .map(|x| x.as_f64().unwrap())
        .collect()
}

/// A decoded ROS pose (FLU) against the FRD pose and covariance it came from.
fn check_pose(
    ros: &serde_json::Value,
    pose: &Pose,
    cov: Option<&Cov6>,
    what: &str,
) -> Result<(), String> {
    let t = pose.translation.vector;
    let p = f64s(&ros["position"]);
    let want = [t.x, -t.y, -t.z];
    if (0..3).any(|k| (p[k] - want[k]).abs() > 1e-9) {
        return Err(format!("{what}: position {p:?} vs {want:?}"));
    }
    let q = pose.rotation.quaternion();
    let o = f64s(&ros["orientation"]);
    let want = [q.i, -q.j, -q.k, q.w];
    let same = (0..4).all(|k| (o[k] - want[k]).abs() < 1e-9);
    let negated = (0..4).all(|k| (o[k] + want[k]).abs() < 1e-9);
    if !(same || negated) {
        return Err(format!("{what}: orientation {o:?} vs {want:?}"));
    }
    if let Some(cov) = cov {
        let c = f64s(&ros["covariance"]);
        if c.len() != 36 {
            return Err(format!("{what}: {} covariance entries", c.len()));
        }
        for i in 0..6 {
            for j in 0..6 {
                let want = cov[(i, j)] * FLU[i] * FLU[j];
                if (c[i * 6 + j] - want).abs() > 1e-12 * want.abs().max(1e-12) {
                    return Err(format!(
                        "{what}: covariance ({i},{j}) {} vs {want}",
                        c[i * 6 + j]
                    ));
                }
            }
        }
    }
    Ok(())
}

#[test]
fn a_python_rosbags_client_decodes_every_ros2_topic_and_the_values_match_the_wire() {
    python_has("zenoh, rosbags", &["eclipse-zenoh", "rosbags"]).unwrap();
    let port = free_port().unwrap();
    let cfg = DemoConfig {
        duration_s: 12.0,
        frame_rate_hz: 2.0,
        cameras: Some(vec!["port".into(), "starboard".into()]),
        time_scale: 0.5,
        progress: false,
        log: None,
        router_port: Some(port),
        ros2: Some(DOMAIN),
        ..DemoConfig::default()
    };
    let fleet = std::sync::Arc::new(shoal::demo::load_fleet(&cfg).unwrap());
    let demo = std::thread::spawn(move || shoal::demo::run(&cfg, |_, _, _| {}));
    // The wire side, on the demo's router as soon as it is up.
    let bus = (0..50)
        .find_map(|_| {
            std::thread::sleep(Duration::from_millis(100));
            Bus::open(&client_of(port)).ok()
        })
        .expect("the demo's router did not come up");
    let keys = shoal_proto::Keys::new("paper").unwrap();
    let maps: Subscription<FleetMap> = bus.subscribe(&keys.map(), 4096).unwrap();
    let obs: Subscription<Observation> = bus.subscribe(&keys.all_observations(), 4096).unwrap();
    let log = std::env::temp_dir().join(format!("shoal-ros2-{}.mcap", std::process::id()));
    let recorder = shoal_services::recorder::Recorder::spawn(
        &bus,
        fleet,
        &log,
        shoal_record::RecordOptions {
            ros2_profile: true,
            ..Default::default()
        },
    )
    .unwrap();
    let script = Path::new(env!("CARGO_MANIFEST_DIR")).join("tests/python/ros2_listen.py");
    let out = Command::new("python3")
        .arg(&script)
        .arg(format!("tcp/127.0.0.1:{port}"))
        .arg(DOMAIN.to_string())
        .arg("18")
        .output()
        .unwrap();
    let summary = demo.join().unwrap().unwrap();
    let recorded = recorder.stop().unwrap();
    assert!(
        out.status.success(),
        "{}",
        String::from_utf8_lossy(&out.stderr)
    );
    let report: serde_json::Value = serde_json::from_slice(&out.stdout).unwrap();
    assert_eq!(
        report["problems"],
        serde_json::json!([]),
        "{}",
        report["problems"]
    );
    assert_eq!(report["nodes"], serde_json::json!(["shoal_fusion"]));

    // Maps by stamp: fusion solves faster than the simulated clock ticks, so
    // several maps can share one; a ROS sample must equal one of them.
    let mut maps_at: HashMap<u64, Vec<FleetMap>> = HashMap::new();
    for r in maps.drain() {
        maps_at.entry(r.msg.stamp_ns).or_default().push(r.msg);
    }
    assert!(
        maps_at.len() >= 10,
        "{} map stamps on the wire",
        maps_at.len()
    );
    let wire: Vec<Observation> = obs.drain().into_iter().map(|r| r.msg).collect();
    let check_all = |report: &serde_json::Value, what: &str| {
        let topics = report["topics"].as_object().unwrap();
        check_map_poses(topics, &maps_at);
        check_tf(topics, &maps_at);
        let observations = check_observations(topics, &wire);
        assert!(
            observations >= 5,
            "{what}: {observations} observations matched of {} sent",
            summary.observations_sent
        );
        check_diagnostics(topics);
    };
    check_all(&report, "live");

    // The ROS 2-profile log of the same run.
    let script = Path::new(env!("CARGO_MANIFEST_DIR")).join("tests/python/ros2_mcap.py");
    let out = Command::new("python3")
        .arg(&script)
        .arg(&log)
        .output()
        .unwrap();
    assert!(
        out.status.success(),
        "{}",
        String::from_utf8_lossy(&out.stderr)
    );
    let from_log: serde_json::Value = serde_json::from_slice(&out.stdout).unwrap();
    assert_eq!(
        from_log["problems"],
        serde_json::json!([]),
        "{}",
        from_log["problems"]
    );
    assert_eq!(from_log["profile"], "ros2");
    let written: u64 = recorded.channels.values().map(|c| c.messages).sum();
    assert_eq!(from_log["samples"].as_u64().unwrap(), written);
    assert!(
        recorded.channels.keys().all(|topic| topic.starts_with('/')),
        "only ROS 2 topics in a ros2-profile log: {:?}",
        recorded.channels.keys()
    );
    check_all(&from_log, "log");
    let _ = std::fs::remove_file(&log);
}

type Topics = serde_json::Map<String, serde_json::Value>;

/// Vehicle `v`'s estimates in the wire maps stamped `stamp`.
fn estimates(
    maps_at: &HashMap<u64, Vec<FleetMap>>,
    stamp: &serde_json::Value,
    v: u32,
) -> Vec<(Pose, Cov6)> {
    maps_at
        .get(&stamp.as_u64().unwrap())
        .into_iter()
        .flatten()
        .flat_map(|m| m.vehicles.iter().filter(|e| e.vehicle == v))
        .map(|e| (e.reference_from_vehicle, e.covariance))
        .collect()
}

/// `ros` equals one of `candidates` (with the covariance when `cov`).
fn matches_one(ros: &serde_json::Value, candidates: &[(Pose, Cov6)], cov: bool, what: &str) {
    let errors: Vec<String> = candidates
        .iter()
        .map(|(p, c)| check_pose(ros, p, cov.then_some(c), what))
        .filter_map(Result::err)
        .collect();
    assert!(errors.len() < candidates.len(), "{errors:?}");
}

/// Fused poses: every vehicle, each sample equal to its map's estimate.
fn check_map_poses(topics: &Topics, maps_at: &HashMap<u64, Vec<FleetMap>>) {
    for v in [10u32, 15, 17] {
        let topic = format!("/shoal/paper/auv{v}/pose");
        let msgs = topics[&topic]["messages"].as_array().unwrap();
        let mut matched = 0;
        for m in msgs {
            let candidates = estimates(maps_at, &m["stamp_ns"], v);
            if candidates.is_empty() {
                continue;
            }
            assert_eq!(m["frame_id"], "auv10/base_link");
            matches_one(m, &candidates, true, &topic);
            matched += 1;
        }
        assert!(
            matched >= 20,
            "{topic}: {matched} of {} matched a map",
            msgs.len()
        );
    }
}

/// /tf: the two followers under the reference, equal to the maps.
fn check_tf(topics: &Topics, maps_at: &HashMap<u64, Vec<FleetMap>>) {
    let mut transforms = 0;
    for m in topics["/tf"]["messages"].as_array().unwrap() {
        for t in m["transforms"].as_array().unwrap() {
            let child = t["child"].as_str().unwrap();
            let v: u32 = child
                .strip_prefix("auv")
                .and_then(|s| s.strip_suffix("/base_link"))
                .unwrap()
                .parse()
                .unwrap();
            let candidates = estimates(maps_at, &t["stamp_ns"], v);
            if candidates.is_empty() {
                continue;
            }
            let as_pose =
                serde_json::json!({"position": t["translation"], "orientation": t["rotation"]});
            matches_one(&as_pose, &candidates, false, child);
            assert_eq!(t["parent"], "auv10/base_link");
            transforms += 1;
        }
    }
    assert!(transforms >= 40, "{transforms} transforms matched");
}

/// Raw observations: each decoded one equals a wire observation; returns how many matched.
fn check_observations(topics: &Topics, wire: &[Observation]) -> usize {
    let mut observations = 0;
    for (topic, entry) in topics {
        let Some(rest) = topic.strip_prefix("/shoal/paper/observations/auv") else {
            continue;
        };
        let (o, t) = rest.split_once("/auv").unwrap();
        let (o, t): (u32, u32) = (o.parse().unwrap(), t.parse().unwrap());
        for m in entry["messages"].as_array().unwrap() {
            let stamp = m["stamp_ns"].as_u64().unwrap();
            let candidates: Vec<(Pose, Cov6)> = wire
                .iter()
                .filter(|w| w.observer == o && w.target_vehicle == Some(t) && w.stamp_ns == stamp)
                .map(|w| (w.observer_from_target, w.covariance))
                .collect();
            if candidates.is_empty() {
                continue;
            }
            assert_eq!(m["frame_id"], format!("auv{o}/base_link"));
            // Several cameras may see it at one stamp: the pose is one of theirs.
            matches_one(m, &candidates, true, topic);
            observations += 1;
        }
    }
    observations
}

/// Diagnostics: every node's health and every vehicle's map state.
fn check_diagnostics(topics: &Topics) {
    let names: Vec<String> = topics["/diagnostics"]["messages"]
        .as_array()
        .unwrap()
        .iter()
        .flat_map(|m| m["status"].as_array().unwrap().clone())
        .map(|s| s["name"].as_str().unwrap().to_string())
        .collect();
    for v in [10, 15, 17] {
        for who in ["node", "fusion"] {
            let name = format!("shoal {who} auv{v}");
            assert!(names.contains(&name), "no {name} in {names:?}");
        }
    }
}
