//! Access control over Zenoh (issue #10): a router with mutual TLS and
//! Zenoh's access control, configured by the shipped example
//! `configs/zenoh/tls-router.json5` (certificate paths and port
//! substituted), and clients configured by `configs/zenoh/tls-vehicle.json5`,
//! with a CA and certificates generated for the test.
//!
//! - vehicle 10 (certificate CN `vehicle-10`) publishes its observations and
//!   fusion receives them;
//! - the same vehicle publishing under vehicle 15's keys, or commanding
//!   vehicle 15, is dropped by the router;
//! - a process whose certificate is signed by another CA, or that presents
//!   none, or that speaks plain TCP, cannot open a session;
//! - an observation vehicle 10 publishes on its own key but that claims
//!   vehicle 15 as its observer reaches fusion and is rejected
//!   (`RejectReason::ObserverMismatch`).

use rcgen::{
    BasicConstraints, CertificateParams, DnType, ExtendedKeyUsagePurpose, IsCa, KeyPair,
    KeyUsagePurpose, SanType,
};
use shoal_bus::{free_port, Bus, Connect, Publisher, Received, Subscription};
use shoal_fusion::FusionParams;
use shoal_proto::clock::ManualClock;
use shoal_proto::config::Fleet;
use shoal_proto::messages::*;
use shoal_services::fusion::{FusionConfig, Placement};
use shoal_sim_bridge::obs_synth::{line_abreast, ObsSynth, ObsSynthParams};
use std::path::{Path, PathBuf};
use std::sync::Arc;
use std::time::Duration;

#[path = "common/wait.rs"]
mod wait;
use wait::wait_for;

fn root() -> &'static Path {
    Path::new(env!("CARGO_MANIFEST_DIR"))
}

fn scratch() -> PathBuf {
    let dir = Path::new(env!("CARGO_TARGET_TMPDIR"))
        .join(format!("access_control-{}", std::process::id()));
    let _ = std::fs::remove_dir_all(&dir);
    std::fs::create_dir_all(&dir).unwrap();
    dir
}

/// A certificate authority for the test.
struct Ca {
    cert: rcgen::Certificate,
    key: KeyPair,
}

impl Ca {
    fn new(name: &str) -> Ca {
        let key = KeyPair::generate().unwrap();
        let mut p = CertificateParams::new(Vec::<String>::new()).unwrap();
        p.distinguished_name.push(DnType::CommonName, name);
        p.is_ca = IsCa::Ca(BasicConstraints::Unconstrained);
        p.key_usages = vec![
            KeyUsagePurpose::KeyCertSign,
            KeyUsagePurpose::CrlSign,
            KeyUsagePurpose::DigitalSignature,
        ];
        Ca {
            cert: p.self_signed(&key).unwrap(),
            key,
        }
    }

    /// Write `<name>.pem` / `<name>.key` for a leaf with common name `cn`
    /// (valid for `localhost` and 127.0.0.1 as a server, and as a client).
    fn issue(&self, dir: &Path, name: &str, cn: &str) -> (PathBuf, PathBuf) {
        let key = KeyPair::generate().unwrap();
        let mut p = CertificateParams::new(vec!["localhost".to_string()]).unwrap();
        p.subject_alt_names
            .push(SanType::IpAddress(std::net::Ipv4Addr::LOCALHOST.into()));
        p.distinguished_name.push(DnType::CommonName, cn);
        p.key_usages = vec![
            KeyUsagePurpose::DigitalSignature,
            KeyUsagePurpose::KeyEncipherment,
        ];
        p.extended_key_usages = vec![
            ExtendedKeyUsagePurpose::ServerAuth,
            ExtendedKeyUsagePurpose::ClientAuth,
        ];
        let cert = p.signed_by(&key, &self.cert, &self.key).unwrap();
        let (c, k) = (
            dir.join(format!("{name}.pem")),
            dir.join(format!("{name}.key")),
        );
        std::fs::write(&c, cert.pem()).unwrap();
        std::fs::write(&k, key.serialize_pem()).unwrap();
        (c, k)
    }
}

/// The shipped router config with the test's certificate paths and port.
fn router_config(dir: &Path, port: u16) -> PathBuf {
    let text = std::fs::read_to_string(root().join("configs/zenoh/tls-router.json5")).unwrap();
    let replaced = text
        .replace(
            "/etc/shoal/tls/ca.pem",
            &dir.join("ca.pem").display().to_string(),
        )
        .replace(
            "/etc/shoal/tls/router.pem",
            &dir.join("router.pem").display().to_string(),
        )
        .replace(
            "/etc/shoal/tls/router.key",
            &dir.join("router.key").display().to_string(),
        )
        .replace("tls/0.0.0.0:7447", &format!("tls/127.0.0.1:{port}"));
    assert!(
        !replaced.contains("/etc/shoal/tls/")
            && replaced.contains(&format!("tls/127.0.0.1:{port}")),
        "the router config's placeholders changed"
    );
    let path = dir.join("router.json5");
    std::fs::write(&path, replaced).unwrap();
    path
}

/// The shipped client config for the process holding `cert`/`key`, trusting `ca`.
fn client_config(
    dir: &Path,
    port: u16,
    ca: &Path,
    cert: Option<(&Path, &Path)>,
    name: &str,
) -> PathBuf {
    let text = std::fs::read_to_string(root().join("configs/zenoh/tls-vehicle.json5")).unwrap();
    let mut replaced = text
        .replace("/etc/shoal/tls/ca.pem", &ca.display().to_string())
        .replace("tls/router.example:7447", &format!("tls/localhost:{port}"));
    match cert {
        Some((c, k)) => {
            replaced = replaced
                .replace("/etc/shoal/tls/vehicle.pem", &c.display().to_string())
                .replace("/etc/shoal/tls/vehicle.key", &k.display().to_string());
        }
        None => {
            // No client certificate at all.
            replaced = replaced
                .lines()
                .filter(|l| !l.contains("/etc/shoal/tls/vehicle."))
                .collect::<Vec<_>>()
                .join("\n");
        }
    }
    assert!(
        !replaced.contains("/etc/shoal"),
        "a placeholder is left in {name}"
    );
    let path = dir.join(format!("{name}.json5"));
    std::fs::write(&path, replaced).unwrap();
    path
}

#[test]
#[allow(
    clippy::too_many_lines,
    reason = "one scenario in order (CA and certificates, router, one client per vehicle, then each key allowed or denied); its steps share every handle, so split they would only pass them around"
)]
fn mutual_tls_and_access_control_confine_each_vehicle_to_its_own_keys() {
    let dir = scratch();
    let ca = Ca::new("shoal test fleet CA");
    std::fs::write(dir.join("ca.pem"), ca.cert.pem()).unwrap();
    ca.issue(&dir, "router", "router");
    let fusion_cert = ca.issue(&dir, "fusion", "fusion");
    let v10_cert = ca.issue(&dir, "vehicle-10", "vehicle-10");
    // An impostor: the right name, the wrong CA.
    let rogue_ca = Ca::new("not the fleet CA");
    std::fs::write(dir.join("rogue-ca.pem"), rogue_ca.cert.pem()).unwrap();
    let rogue_cert = rogue_ca.issue(&dir, "rogue", "vehicle-10");

    let port = free_port().unwrap();
    let _router = Bus::open(&Connect::File(router_config(&dir, port))).expect("TLS router starts");
    let ca_path = dir.join("ca.pem");
    let open_as = |name: &str, cert: &(PathBuf, PathBuf)| {
        Bus::open(&Connect::File(client_config(
            &dir,
            port,
            &ca_path,
            Some((&cert.0, &cert.1)),
            name,
        )))
    };

    // Fusion (CN `fusion`, a shore service) and a shore-side witness of every
    // observation and command.
    let fleet = Arc::new(Fleet::load(&root().join("configs/fleets/paper.toml")).unwrap());
    let keys = fleet.keys();
    let clock = Arc::new(ManualClock::new(0));
    let fusion_bus = open_as("fusion", &fusion_cert).expect("fusion connects with its certificate");
    let fusion = shoal_services::fusion::spawn(
        &fusion_bus,
        FusionConfig {
            fleet: fleet.clone(),
            params: FusionParams {
                record_solve_time: false,
                ..FusionParams::default()
            },
            placement: Placement::Central,
            rate_hz: 20.0,
            queue_capacity: 1000,
            link: false,
        },
        clock.clone(),
    )
    .unwrap();
    let witness_bus = open_as("witness", &fusion_cert).unwrap();
    let witness: Subscription<Observation> = witness_bus
        .subscribe(&keys.all_observations(), 1000)
        .unwrap();
    let commands: Subscription<VehicleCommand> =
        witness_bus.subscribe(&keys.all_commands(), 100).unwrap();

    // Vehicle 10 with its own certificate.
    let v10 = open_as("vehicle-10", &v10_cert).expect("vehicle 10 connects with its certificate");
    let own: Publisher<Observation> = v10.publisher(keys.observations(10)).unwrap();
    let other: Publisher<Observation> = v10.publisher(keys.observations(15)).unwrap();
    let command_15: Publisher<VehicleCommand> = v10.publisher(keys.command(15)).unwrap();
    std::thread::sleep(Duration::from_millis(1500));

    let ids: Vec<u32> = fleet.vehicles.iter().map(|v| v.id).collect();
    let mut synth = ObsSynth::new(&fleet, ObsSynthParams::default(), 3);
    let stamp = 100_000_000;
    clock.advance_to(stamp);
    let seen_by_10: Vec<Observation> = synth
        .observe(&line_abreast(&ids, 1.75), stamp)
        .into_iter()
        .map(|o| o.obs)
        .filter(|o| o.observer == 10)
        .collect();
    assert!(
        !seen_by_10.is_empty(),
        "vehicle 10 sees no one in the synthetic formation"
    );

    // Forbidden first (same session, same link: delivered in order if at all),
    // then allowed: once the allowed ones are in, the forbidden ones would be too.
    let mut forged = seen_by_10[0].clone();
    forged.observer = 15;
    forged.frame_seq += 1000;
    other.put(&forged).unwrap();
    command_15
        .put(&VehicleCommand {
            vehicle: 15,
            stamp_ns: stamp,
            velocity_body: [2.0, 0.0, 0.0],
            yaw_rate: 1.0,
        })
        .unwrap();
    for o in &seen_by_10 {
        own.put(o).unwrap();
    }
    // Over the wire, on its own key, claiming to be vehicle 15.
    let mut mismatch = seen_by_10[0].clone();
    mismatch.observer = 15;
    mismatch.frame_seq += 2000;
    own.put(&mismatch).unwrap();
    let expected = seen_by_10.len() as u64 + 1;

    let stats = wait_for(
        "fusion to receive vehicle 10's observations",
        Duration::from_secs(10),
        || {
            let s = fusion.stats();
            (s.received >= expected).then_some(s)
        },
    );
    std::thread::sleep(Duration::from_millis(500));
    let got: Vec<Received<Observation>> = witness.drain();
    assert_eq!(
        got.len() as u64,
        expected,
        "the witness heard {} observations",
        got.len()
    );
    assert!(
        got.iter().all(|r| r.key == keys.observations(10)),
        "an observation under another vehicle's key got through: {:?}",
        got.iter().map(|r| &r.key).collect::<Vec<_>>()
    );
    assert!(
        commands.drain().is_empty(),
        "vehicle 10 commanded vehicle 15"
    );
    let stats_later = fusion.stats();
    assert_eq!(
        stats_later.received, expected,
        "fusion heard the forged observation"
    );
    assert_eq!(stats.received, expected);
    assert_eq!(
        stats_later
            .rejected_at_ingest
            .get(&RejectReason::ObserverMismatch),
        1,
        "the observation claiming another observer is rejected as such"
    );
    assert_eq!(stats_later.ingested, seen_by_10.len() as u64);

    // Processes that cannot prove they belong to the fleet cannot connect.
    let impostor = Bus::open(&Connect::File(client_config(
        &dir,
        port,
        &ca_path,
        Some((&rogue_cert.0, &rogue_cert.1)),
        "rogue",
    )));
    assert!(
        impostor.is_err(),
        "a certificate of another CA was accepted"
    );
    let anonymous = Bus::open(&Connect::File(client_config(
        &dir,
        port,
        &ca_path,
        None,
        "anonymous",
    )));
    assert!(
        anonymous.is_err(),
        "a client without a certificate was accepted"
    );
    let plain = Bus::open(&Connect::Client { port });
    assert!(
        plain.is_err(),
        "a plain-TCP client was accepted on the TLS port"
    );
    // Nor does a client trusting another CA accept the router.
    let distrustful = Bus::open(&Connect::File(client_config(
        &dir,
        port,
        &dir.join("rogue-ca.pem"),
        Some((&v10_cert.0, &v10_cert.1)),
        "distrustful",
    )));
    assert!(
        distrustful.is_err(),
        "a client accepted a router of another CA"
    );
    println!(
        "access control: {} own observations delivered, 1 forged-key observation and 1 command dropped by the router, 1 observer mismatch rejected by fusion, 4 uncertified clients refused",
        seen_by_10.len()
    );
    fusion.stop();
}
