//! A Zenoh router configuration with mutual TLS and access control, generated
//! from a fleet file (`shoal config router-acl`; docs/deploy.md).
//!
//! The rules are those of `configs/zenoh/tls-router.json5` (which is this
//! generator's output for the paper fleet, and what `tests/access_control.rs`
//! runs): deny by default; every vehicle may subscribe, query and watch
//! liveliness anywhere under the fleet's keys; `vehicle-<id>` may publish only
//! under its own ID; the shore services (`fusion`, `ground-station`,
//! `simulator`, `recorder`) may do anything under the fleet's keys. Subjects
//! are certificate common names.

use serde_json::{json, Value};
use shoal_proto::config::Fleet;
use shoal_proto::keys::Keys;
use std::path::PathBuf;

/// Certificate common names of the shore-side services.
pub const SHORE_SERVICES: [&str; 4] = ["fusion", "ground-station", "simulator", "recorder"];

/// Where the router finds its certificates.
#[derive(Debug, Clone, PartialEq, Eq)]
pub struct TlsFiles {
    /// The fleet CA every client certificate must be signed by.
    pub ca: PathBuf,
    pub certificate: PathBuf,
    pub private_key: PathBuf,
}

impl TlsFiles {
    /// Each file that is missing, unreadable or not PEM, with what it is and why.
    /// (The router reads them when it starts; a generated configuration that
    /// names absent files fails only then, on the router's host.)
    pub fn problems(&self) -> Vec<String> {
        let mut out = Vec::new();
        for (which, path) in [
            ("CA certificate", &self.ca),
            ("router certificate", &self.certificate),
            ("router private key", &self.private_key),
        ] {
            match shoal_proto::files::read_text_bounded(path, 1 << 20) {
                Ok(text) if text.contains("-----BEGIN ") => {}
                Ok(_) => out.push(format!("{which} {}: not a PEM file", path.display())),
                Err(e) => out.push(format!("{which} {}: {e}", path.display())),
            }
        }
        out
    }

    /// `ca.pem`, `router.pem`, `router.key` in `dir`.
    pub fn in_dir(dir: impl Into<PathBuf>) -> Self {
        let dir = dir.into();
        Self {
            ca: dir.join("ca.pem"),
            certificate: dir.join("router.pem"),
            private_key: dir.join("router.key"),
        }
    }
}

#[derive(Debug, thiserror::Error)]
pub enum AclError {
    #[error("fleet name {name:?} cannot be a key prefix: {reason}")]
    FleetName { name: String, reason: String },
    #[error("{which} path {path:?} is not valid UTF-8")]
    Path { which: &'static str, path: PathBuf },
    #[error("listener {0:?}: mutual TLS needs a `tls/` or `quic/` endpoint (a plain `tcp/` or `udp/` one would accept clients with no certificate, and no rule could tell them apart)")]
    Listener(String),
    #[error("the generated configuration is not a valid Zenoh configuration: {0}")]
    Zenoh(String),
}

/// The vehicle-side message kinds of publishing under one's own ID.
const OWN_MESSAGES: [&str; 5] = [
    "put",
    "delete",
    "liveliness_token",
    "declare_queryable",
    "reply",
];

/// The router configuration (JSON5 text, with a header comment) for `fleet`,
/// listening on `listen` (a Zenoh endpoint such as `tls/0.0.0.0:7447`).
/// Checked by parsing it back as a `zenoh::Config`.
pub fn router_config(fleet: &Fleet, listen: &str, tls: &TlsFiles) -> Result<String, AclError> {
    if !(listen.starts_with("tls/") || listen.starts_with("quic/")) {
        return Err(AclError::Listener(listen.to_string()));
    }
    let keys = Keys::new(&fleet.name).map_err(|e| AclError::FleetName {
        name: fleet.name.clone(),
        reason: e.to_string(),
    })?;
    let all = keys.everything();
    let path = |which: &'static str, p: &PathBuf| {
        p.to_str().map(str::to_owned).ok_or_else(|| AclError::Path {
            which,
            path: p.clone(),
        })
    };
    let ids: Vec<_> = fleet.vehicles.iter().map(|v| v.id).collect();
    let cn = |id: &shoal_proto::VehicleId| format!("vehicle-{id}");

    let mut rules = vec![
        json!({
            "id": "fleet-read",
            "messages": ["declare_subscriber", "query", "declare_liveliness_subscriber", "liveliness_query"],
            "flows": ["ingress", "egress"],
            "permission": "allow",
            "key_exprs": [all],
        }),
        json!({
            "id": "fleet-deliver",
            "messages": ["put", "delete", "reply", "liveliness_token", "declare_queryable"],
            "flows": ["egress"],
            "permission": "allow",
            "key_exprs": [all],
        }),
    ];
    rules.extend(ids.iter().map(|id| {
        json!({
            "id": format!("{}-own", cn(id)),
            "messages": OWN_MESSAGES,
            "flows": ["ingress"],
            "permission": "allow",
            "key_exprs": [keys.vehicle_all(*id)],
        })
    }));
    rules.push(json!({
        "id": "shore-all",
        "messages": [
            "put", "delete", "declare_subscriber", "query", "declare_queryable", "reply",
            "liveliness_token", "declare_liveliness_subscriber", "liveliness_query",
        ],
        "flows": ["ingress", "egress"],
        "permission": "allow",
        "key_exprs": [all],
    }));

    let mut subjects = vec![json!({
        "id": "vehicles",
        "cert_common_names": ids.iter().map(cn).collect::<Vec<_>>(),
    })];
    subjects.extend(
        ids.iter()
            .map(|id| json!({ "id": cn(id), "cert_common_names": [cn(id)] })),
    );
    subjects.push(json!({ "id": "shore", "cert_common_names": SHORE_SERVICES }));

    let mut policies =
        vec![json!({ "rules": ["fleet-read", "fleet-deliver"], "subjects": ["vehicles"] })];
    policies.extend(
        ids.iter()
            .map(|id| json!({ "rules": [format!("{}-own", cn(id))], "subjects": [cn(id)] })),
    );
    policies.push(json!({ "rules": ["shore-all"], "subjects": ["shore"] }));

    let config = json!({
        "mode": "router",
        "listen": { "endpoints": [listen] },
        "connect": { "endpoints": [] },
        "scouting": { "multicast": { "enabled": false } },
        "transport": { "link": { "tls": {
            "root_ca_certificate": path("CA certificate", &tls.ca)?,
            "listen_certificate": path("router certificate", &tls.certificate)?,
            "listen_private_key": path("router private key", &tls.private_key)?,
            "enable_mtls": true,
        } } },
        "access_control": {
            "enabled": true,
            "default_permission": "deny",
            "rules": rules,
            "subjects": subjects,
            "policies": policies,
        },
    });
    let body = serde_json::to_string_pretty(&config).map_err(|e| AclError::Zenoh(e.to_string()))?;
    zenoh::Config::from_json5(&body).map_err(|e| AclError::Zenoh(e.to_string()))?;
    // The fleet's name and path as JSON strings: a newline or `*/` in either
    // stays inside its comment line instead of becoming configuration.
    let quoted = |s: &str| serde_json::to_string(s).unwrap_or_default();
    Ok(format!(
        "// Zenoh router for fleet {}: mutual TLS, access control by certificate CN\n\
         // (vehicle-<id> publishes only under its own ID; {} may do anything in the fleet).\n\
         // Generated by `shoal config router-acl` from {}; see docs/deploy.md.\n{body}\n",
        quoted(&fleet.name),
        SHORE_SERVICES.join(", "),
        quoted(&fleet.source.display().to_string()),
    ))
}

/// The parsed JSON of [`router_config`]'s output (for comparisons).
pub fn parse_generated(text: &str) -> Result<Value, serde_json::Error> {
    let body: String = text
        .lines()
        .filter(|l| !l.trim_start().starts_with("//"))
        .collect::<Vec<_>>()
        .join("\n");
    serde_json::from_str(&body)
}

#[cfg(test)]
mod tests {
    use super::*;
    use std::path::Path;

    fn paper() -> Fleet {
        let root = Path::new(env!("CARGO_MANIFEST_DIR")).join("..");
        Fleet::load(&root.join("configs/fleets/paper.toml")).unwrap()
    }

    #[test]
    fn paper_fleet_generates_the_shipped_router_config() {
        let root = Path::new(env!("CARGO_MANIFEST_DIR")).join("..");
        let shipped = std::fs::read_to_string(root.join("configs/zenoh/tls-router.json5")).unwrap();
        let shipped: Value = json5::from_str(&shipped).unwrap();
        let text = router_config(
            &paper(),
            "tls/0.0.0.0:7447",
            &TlsFiles::in_dir("/etc/shoal/tls"),
        )
        .unwrap();
        assert_eq!(parse_generated(&text).unwrap(), shipped, "{text}");
    }

    /// Issue #22: the fleet path went into the header comment unescaped
    /// (a newline in it became configuration), a plain `tcp/` listener was
    /// accepted for a mutual-TLS ACL, and absent TLS files were not noticed.
    #[test]
    fn header_is_escaped_listener_must_be_tls_and_files_are_checked() {
        let mut fleet = paper();
        fleet.source = PathBuf::from("/tmp/evil\n\"mode\": \"peer\",\n// x.toml");
        let text = router_config(
            &fleet,
            "tls/0.0.0.0:7447",
            &TlsFiles::in_dir("/etc/shoal/tls"),
        )
        .unwrap();
        let header: Vec<&str> = text.lines().take_while(|l| l.starts_with("//")).collect();
        assert_eq!(header.len(), 3, "{text}");
        assert!(header[2].contains(r#"evil\n\"mode\""#), "{}", header[2]);
        assert_eq!(parse_generated(&text).unwrap()["mode"], "router");
        for listen in ["tcp/0.0.0.0:7447", "udp/0.0.0.0:7447", "0.0.0.0:7447"] {
            let e = router_config(&paper(), listen, &TlsFiles::in_dir("/x")).unwrap_err();
            assert!(matches!(e, AclError::Listener(_)), "{listen}: {e}");
        }
        assert!(router_config(&paper(), "quic/0.0.0.0:7447", &TlsFiles::in_dir("/x")).is_ok());

        let dir = std::env::temp_dir().join(format!("shoal-acl-{}", std::process::id()));
        std::fs::create_dir_all(&dir).unwrap();
        let tls = TlsFiles::in_dir(&dir);
        assert_eq!(tls.problems().len(), 3);
        let pem = "-----BEGIN CERTIFICATE-----\nMIIB\n-----END CERTIFICATE-----\n";
        std::fs::write(&tls.ca, pem).unwrap();
        std::fs::write(&tls.certificate, pem).unwrap();
        std::fs::write(&tls.private_key, "not a key").unwrap();
        let p = tls.problems();
        assert_eq!(p.len(), 1, "{p:?}");
        assert!(
            p[0].contains("router private key") && p[0].contains("not a PEM file"),
            "{p:?}"
        );
        std::fs::remove_dir_all(&dir).ok();
    }

    #[test]
    fn every_vehicle_gets_its_own_publish_rule_and_nothing_more() {
        let mut fleet = paper();
        fleet.name = "trial-7".into();
        let mut extra = fleet.vehicles[0].clone();
        extra.id = 42;
        fleet.vehicles.push(extra);
        let text = router_config(&fleet, "tls/[::]:7447", &TlsFiles::in_dir("/tls")).unwrap();
        let v = parse_generated(&text).unwrap();
        let rules = v["access_control"]["rules"].as_array().unwrap();
        let own = rules.iter().find(|r| r["id"] == "vehicle-42-own").unwrap();
        assert_eq!(own["key_exprs"], json!(["shoal/trial-7/42/**"]));
        assert_eq!(own["flows"], json!(["ingress"]));
        let vehicles = &v["access_control"]["subjects"][0];
        assert_eq!(
            vehicles["cert_common_names"],
            json!(["vehicle-10", "vehicle-15", "vehicle-17", "vehicle-42"])
        );
        // Fleet-wide rules cover the new fleet name only.
        assert!(rules
            .iter()
            .filter(|r| !r["id"].as_str().unwrap().ends_with("-own"))
            .all(|r| r["key_exprs"] == json!(["shoal/trial-7/**"])));
    }

    #[test]
    fn a_fleet_name_that_cannot_be_a_key_is_refused() {
        let mut fleet = paper();
        fleet.name = "bad/name".into();
        let err = router_config(&fleet, "tls/0.0.0.0:7447", &TlsFiles::in_dir("/tls")).unwrap_err();
        assert!(matches!(err, AclError::FleetName { .. }), "{err}");
    }
}
