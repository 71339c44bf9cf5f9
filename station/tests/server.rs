//! The station's servers over real sockets: the snapshot endpoint follows
//! Zenoh, the event stream pushes at its rate, a taken port is a clear
//! error, and the Foxglove server sends the MCAP logs' channels, schemas
//! and bytes.

use shoal_bus::{client_of, free_port, Bus, Connect};
use shoal_proto::config::Fleet;
use shoal_proto::geometry::Pose;
use shoal_proto::{FleetMap, VehicleEstimate, VehicleState};
use shoal_station::{StationConfig, StationError};
use std::io::{BufRead, BufReader, Read, Write};
use std::net::{IpAddr, Ipv4Addr, TcpStream};
use std::sync::Arc;
use std::time::{Duration, Instant};

const PAPER: &str = include_str!("../../configs/fleets/paper.toml");

fn fleet() -> Arc<Fleet> {
    Arc::new(Fleet::parse(PAPER, std::path::Path::new("configs/fleets/paper.toml")).unwrap())
}

fn config(http_port: u16, foxglove_port: Option<u16>) -> StationConfig {
    StationConfig {
        bind: IpAddr::V4(Ipv4Addr::LOCALHOST),
        http_port,
        foxglove_port,
        rate_hz: 10.0,
        ..StationConfig::default()
    }
}

fn get(addr: std::net::SocketAddr, path: &str) -> (u16, String) {
    let mut s = TcpStream::connect(addr).unwrap();
    s.set_read_timeout(Some(Duration::from_secs(5))).unwrap();
    write!(s, "GET {path} HTTP/1.1\r\nHost: {addr}\r\n\r\n").unwrap();
    let mut text = String::new();
    s.read_to_string(&mut text).unwrap();
    let status = text[9..12].parse().unwrap();
    let body = text
        .split_once("\r\n\r\n")
        .map(|(_, b)| b.to_string())
        .unwrap_or_default();
    (status, body)
}

fn map(seq: u64, y_m: f64) -> FleetMap {
    let est = |vehicle, p: Pose| VehicleEstimate {
        vehicle,
        state: VehicleState::Live,
        reference_from_vehicle: p,
        covariance: nalgebra::Matrix6::identity() * 1e-4,
        last_seen_ns: seq * 100_000_000,
    };
    FleetMap {
        fleet: "paper".into(),
        producer: "central".into(),
        seq,
        stamp_ns: seq * 100_000_000,
        reference: 10,
        vehicles: vec![
            est(10, Pose::identity()),
            est(15, Pose::translation(0.0, y_m, 0.0)),
        ],
        edges: vec![],
        solve_time_us: 100,
    }
}

#[test]
fn snapshot_and_event_stream_follow_the_published_map() {
    let port = free_port().unwrap();
    let router = Bus::open(&Connect::Router { port }).unwrap();
    let station = shoal_station::spawn(&router, fleet(), config(0, None)).unwrap();
    let publisher = Bus::open(&client_of(port)).unwrap();
    let p = publisher
        .publisher::<FleetMap>(fleet().keys().map())
        .unwrap();
    let addr = station.http_addr();
    let deadline = Instant::now() + Duration::from_secs(20);
    let mut seq = 1;
    loop {
        p.put(&map(seq, 1.5 + 0.01 * seq as f64)).unwrap();
        // Two station periods (10 Hz) for the map to reach the snapshot; before
        // the subscription matches, a map is lost and the next one is tried.
        std::thread::sleep(Duration::from_millis(200));
        let (status, body) = get(addr, "/api/snapshot");
        assert_eq!(status, 200);
        let v: serde_json::Value = serde_json::from_str(&body).unwrap();
        if v["map"]["seq"].as_u64() == Some(seq) {
            let v15 = v["vehicles"]
                .as_array()
                .unwrap()
                .iter()
                .find(|x| x["id"] == 15)
                .unwrap();
            let y = v15["estimate"]["position_m"][1].as_f64().unwrap();
            assert!((y - (1.5 + 0.01 * seq as f64)).abs() < 1e-9, "{v15}");
            break;
        }
        assert!(
            Instant::now() < deadline,
            "the snapshot never showed map {seq}: {body}"
        );
        seq += 1;
    }
    // The page and its script are served; unknown paths are 404.
    assert!(get(addr, "/").1.contains("/app.js"));
    assert!(get(addr, "/app.js").1.contains("EventSource"));
    assert_eq!(get(addr, "/nope").0, 404);

    // Server-sent events: at least 5 snapshots a second, numbered upward.
    let s = TcpStream::connect(addr).unwrap();
    s.set_read_timeout(Some(Duration::from_secs(5))).unwrap();
    (&s).write_all(format!("GET /events HTTP/1.1\r\nHost: {addr}\r\n\r\n").as_bytes())
        .unwrap();
    let mut lines = BufReader::new(&s);
    let started = Instant::now();
    let mut ids = Vec::new();
    let mut line = String::new();
    while ids.len() < 11 {
        line.clear();
        assert!(lines.read_line(&mut line).unwrap() > 0, "stream closed");
        if let Some(id) = line.strip_prefix("id: ") {
            ids.push(id.trim().parse::<u64>().unwrap());
        }
        assert!(
            started.elapsed() < Duration::from_secs(10),
            "too slow: {ids:?}"
        );
    }
    let rate = 10.0 / started.elapsed().as_secs_f64();
    assert!(rate >= 5.0, "{rate:.1} snapshots/s");
    assert!(ids.windows(2).all(|w| w[1] > w[0]), "{ids:?}");
    station.stop();
}

#[test]
fn taken_http_port_is_a_clear_error() {
    let taken = std::net::TcpListener::bind("127.0.0.1:0").unwrap();
    let port = taken.local_addr().unwrap().port();
    let bus = Bus::open(&Connect::Router {
        port: free_port().unwrap(),
    })
    .unwrap();
    let err = shoal_station::spawn(&bus, fleet(), config(port, None)).unwrap_err();
    assert!(
        matches!(err, StationError::Bind { what: "HTTP", .. }),
        "{err:?}"
    );
    assert!(err.to_string().contains(&port.to_string()), "{err}");
}

/// Read one server-to-client WebSocket frame (unmasked, RFC 6455 §5.2).
fn read_frame(s: &mut impl Read) -> (u8, Vec<u8>) {
    let mut h = [0u8; 2];
    s.read_exact(&mut h).unwrap();
    let mut len = u64::from(h[1] & 0x7f);
    if len == 126 {
        let mut b = [0u8; 2];
        s.read_exact(&mut b).unwrap();
        len = u64::from(u16::from_be_bytes(b));
    } else if len == 127 {
        let mut b = [0u8; 8];
        s.read_exact(&mut b).unwrap();
        len = u64::from_be_bytes(b);
    }
    let mut payload = vec![0u8; len as usize];
    s.read_exact(&mut payload).unwrap();
    (h[0] & 0x0f, payload)
}

/// Standard base64 with padding (RFC 4648 §4), to compare the advertised schema.
fn base64(bytes: &[u8]) -> String {
    const A: &[u8; 64] = b"ABCDEFGHIJKLMNOPQRSTUVWXYZabcdefghijklmnopqrstuvwxyz0123456789+/";
    let mut out = String::new();
    for c in bytes.chunks(3) {
        let n = (u32::from(c[0]) << 16)
            | (u32::from(*c.get(1).unwrap_or(&0)) << 8)
            | u32::from(*c.get(2).unwrap_or(&0));
        for i in 0..4 {
            if i <= c.len() {
                out.push(A[(n >> (18 - 6 * i) & 63) as usize] as char);
            } else {
                out.push('=');
            }
        }
    }
    out
}

/// Write one client-to-server text frame (masked, RFC 6455 §5.3).
fn write_text_frame(s: &mut impl Write, text: &str) {
    let payload = text.as_bytes();
    assert!(payload.len() < 126, "short frames only");
    let mask = [0x37u8, 0xfa, 0x21, 0x3d];
    let mut frame = vec![0x81, 0x80 | payload.len() as u8];
    frame.extend_from_slice(&mask);
    frame.extend(payload.iter().enumerate().map(|(i, b)| b ^ mask[i % 4]));
    s.write_all(&frame).unwrap();
}

/// The channels a Foxglove server advertises until `/fused/poses` shows up,
/// topic → (channel id, schema name), each checked to declare the log's
/// protobuf schema record.
fn read_advertised(s: &mut TcpStream) -> std::collections::BTreeMap<String, (u64, String)> {
    use shoal_record::foxglove as fx;
    let deadline = Instant::now() + Duration::from_secs(10);
    // topic -> (channel id, schema name)
    let mut advertised = std::collections::BTreeMap::new();
    while Instant::now() < deadline && !advertised.contains_key("/fused/poses") {
        let (opcode, payload) = read_frame(s);
        if opcode != 1 {
            continue;
        }
        let v: serde_json::Value = serde_json::from_slice(&payload).unwrap();
        if v["op"] == "advertise" {
            for c in v["channels"].as_array().unwrap() {
                let name = c["schemaName"].as_str().unwrap().to_string();
                let schema = fx::FoxgloveSchema::ALL
                    .into_iter()
                    .find(|s| s.name() == name)
                    .unwrap_or_else(|| panic!("unexpected schema {c}"));
                assert_eq!(c["encoding"], "protobuf", "{c}");
                assert_eq!(c["schemaEncoding"], "protobuf", "{c}");
                assert_eq!(
                    c["schema"].as_str().unwrap(),
                    base64(&schema.schema().data),
                    "{name}: the advertised descriptor is not the log's"
                );
                advertised.insert(
                    c["topic"].as_str().unwrap().to_string(),
                    (c["id"].as_u64().unwrap(), name),
                );
            }
        }
    }
    advertised
}

/// The Foxglove live server sends what the recorder logs: same topics, same
/// schema records (the `foxglove` crate's protobuf descriptors), the same
/// protobuf bytes for the same map; and its MCAP sink on the same context
/// writes those bytes too.
#[test]
fn foxglove_server_sends_the_log_channels_schemas_and_bytes() {
    use shoal_record::foxglove as fx;
    let port = free_port().unwrap();
    let router = Bus::open(&Connect::Router { port }).unwrap();
    let mcap_path =
        std::env::temp_dir().join(format!("shoal-station-fox-{}.mcap", std::process::id()));
    let cfg = StationConfig {
        foxglove_mcap: Some(mcap_path.clone()),
        ..config(0, Some(0))
    };
    let station = shoal_station::spawn(&router, fleet(), cfg).unwrap();
    let fox = station.foxglove_port().unwrap();
    let publisher = Bus::open(&client_of(port)).unwrap();
    let p = publisher
        .publisher::<FleetMap>(fleet().keys().map())
        .unwrap();
    std::thread::sleep(Duration::from_millis(500));
    p.put(&map(1, 1.5)).unwrap();
    std::thread::sleep(Duration::from_millis(500));

    let mut s = TcpStream::connect(("127.0.0.1", fox)).unwrap();
    s.set_read_timeout(Some(Duration::from_secs(5))).unwrap();
    write!(
        s,
        "GET / HTTP/1.1\r\nHost: 127.0.0.1:{fox}\r\nUpgrade: websocket\r\nConnection: Upgrade\r\n\
         Sec-WebSocket-Key: dGhlIHNhbXBsZSBub25jZQ==\r\nSec-WebSocket-Version: 13\r\n\
         Sec-WebSocket-Protocol: foxglove.sdk.v1\r\n\r\n"
    )
    .unwrap();
    // Response head, byte by byte up to the blank line (frames follow it).
    let mut head = Vec::new();
    let mut b = [0u8; 1];
    while !head.ends_with(b"\r\n\r\n") {
        s.read_exact(&mut b).unwrap();
        head.push(b[0]);
    }
    let head = String::from_utf8_lossy(&head);
    assert!(head.starts_with("HTTP/1.1 101"), "{head}");
    let advertised = read_advertised(&mut s);
    for (topic, schema) in [
        ("/fused/tf", "foxglove.FrameTransforms"),
        ("/fused/poses", "foxglove.PosesInFrame"),
        ("/fused/scene", "foxglove.SceneUpdate"),
    ] {
        assert!(
            advertised.get(topic).is_some_and(|(_, s)| s == schema),
            "{topic} ({schema}) not advertised: {advertised:?}"
        );
    }
    // Subscribe to the poses, publish a new map, and compare the bytes sent
    // with what the recorder would log for it.
    let channel = advertised["/fused/poses"].0;
    write_text_frame(
        &mut s,
        &format!(r#"{{"op":"subscribe","subscriptions":[{{"id":7,"channelId":{channel}}}]}}"#),
    );
    std::thread::sleep(Duration::from_millis(300));
    let sent = map(2, 2.25);
    let expected = fx::fleet_map(&fleet(), &sent)
        .into_iter()
        .find(|m| m.topic == "/fused/poses")
        .unwrap()
        .encode()
        .unwrap();
    let deadline = Instant::now() + Duration::from_secs(10);
    let mut live = None;
    while Instant::now() < deadline && live.is_none() {
        p.put(&sent).unwrap();
        let (opcode, payload) = read_frame(&mut s);
        // Binary message data: op 1, subscription id (u32 LE), log time (u64 LE), payload.
        if opcode == 2 && payload.first() == Some(&1) && payload[1..5] == 7u32.to_le_bytes() {
            live = Some(payload[13..].to_vec());
        }
    }
    assert_eq!(
        live.as_deref(),
        Some(&expected[..]),
        "live bytes differ from the log's"
    );
    station.stop();

    // The MCAP sink on the same context holds the same channel and bytes.
    let bytes = std::fs::read(&mcap_path).unwrap();
    let _ = std::fs::remove_file(&mcap_path);
    let mut poses = Vec::new();
    for m in mcap::MessageStream::new(&bytes).unwrap() {
        let m = m.unwrap();
        if m.channel.topic == "/fused/poses" {
            let schema = m.channel.schema.as_ref().unwrap();
            assert_eq!(schema.name, "foxglove.PosesInFrame");
            assert_eq!(schema.encoding, "protobuf");
            assert_eq!(schema.data, fx::FoxgloveSchema::PosesInFrame.schema().data);
            assert_eq!(m.channel.message_encoding, "protobuf");
            poses.push(m.data.into_owned());
        }
    }
    assert!(
        poses.iter().any(|d| d[..] == expected[..]),
        "the station's MCAP lacks the map sent live ({} poses messages)",
        poses.len()
    );
}
