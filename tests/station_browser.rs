//! The ground-station page in a real headless browser (Debian's chromium,
//! installed with apt-get when missing): during a simulated three-vehicle
//! swarm the page loads, shows the three vehicles, and updates as they move
//! — in the same page, without reloading (checked through the DevTools
//! protocol: the page's own DOM read twice, seconds apart).
//!
//! A station with a token is opened from its `?token=` URL: the page then
//! streams by its HttpOnly cookie, with the token gone from the address bar.
//!
//! `SHOAL_STATION_SCREENSHOT=path.png` also saves a screenshot of the page.

use shoal::demo::{DemoConfig, SimulatedSwarm};
use shoal_station::StationConfig;
use std::io::{BufRead, BufReader, Read, Write};
use std::net::TcpStream;
use std::process::{Child, Command, Stdio};
use std::sync::atomic::{AtomicUsize, Ordering};
use std::time::{Duration, Instant};

/// The whole test's budget; each wait below fails with a message at its own deadline.
const BUDGET: Duration = Duration::from_secs(90);

/// Debian's chromium, installed when missing (CI runs as root on a fresh machine).
fn chromium() -> String {
    if let Ok(p) = std::env::var("CHROMIUM") {
        return p;
    }
    let found = |name: &str| {
        Command::new("sh")
            .args(["-c", &format!("command -v {name}")])
            .output()
            .ok()
            .filter(|o| o.status.success())
            .map(|o| String::from_utf8_lossy(&o.stdout).trim().to_string())
    };
    if let Some(p) = found("chromium") {
        return p;
    }
    eprintln!("chromium missing: apt-get install -y chromium");
    let status = Command::new("apt-get")
        .args(["install", "-y", "--no-install-recommends", "chromium"])
        .env("DEBIAN_FRONTEND", "noninteractive")
        .status();
    match (status, found("chromium")) {
        (Ok(s), Some(p)) if s.success() => p,
        (s, _) => panic!(
            "the browser test needs Debian's chromium and `apt-get install -y chromium` failed ({s:?}); \
             install it or set CHROMIUM=/path/to/chromium"
        ),
    }
}

/// A headless chromium in its own process group (killed as a group on drop).
struct Browser {
    child: Child,
    devtools_port: u16,
    profile: std::path::PathBuf,
}

impl Drop for Browser {
    fn drop(&mut self) {
        // Only our chromium: its process group is its own PID.
        let _ = Command::new("kill")
            .args(["-KILL", "--", &format!("-{}", self.child.id())])
            .status();
        let _ = self.child.wait();
        let _ = std::fs::remove_dir_all(&self.profile);
    }
}

fn launch(chromium_path: &str, url: &str, deadline: Instant) -> Browser {
    use std::os::unix::process::CommandExt;
    // One profile per browser: the tests of this file run in parallel in one process.
    static LAUNCHED: AtomicUsize = AtomicUsize::new(0);
    let profile = std::env::temp_dir().join(format!(
        "shoal-chromium-{}-{}",
        std::process::id(),
        LAUNCHED.fetch_add(1, Ordering::Relaxed)
    ));
    let mut child = Command::new(chromium_path)
        .args([
            "--headless=new",
            "--no-sandbox",
            "--disable-gpu",
            "--disable-dev-shm-usage",
            "--no-first-run",
            "--window-size=1400,900",
            "--remote-debugging-port=0",
            "--remote-allow-origins=*",
        ])
        .arg(format!("--user-data-dir={}", profile.display()))
        .arg(url)
        .stdin(Stdio::null())
        .stdout(Stdio::null())
        .stderr(Stdio::piped())
        .process_group(0)
        .spawn()
        .expect("cannot start chromium");
    // chromium prints "DevTools listening on ws://127.0.0.1:PORT/devtools/browser/…".
    let stderr = child.stderr.take().unwrap();
    let (tx, rx) = std::sync::mpsc::channel();
    std::thread::Builder::new()
        .name("chromium-stderr".into())
        .spawn(move || {
            for line in BufReader::new(stderr).lines().map_while(Result::ok) {
                if let Some(rest) = line.split("ws://127.0.0.1:").nth(1) {
                    let port: String = rest.chars().take_while(char::is_ascii_digit).collect();
                    let _ = tx.send(port.parse::<u16>().ok());
                }
            }
        })
        .unwrap();
    let wait = deadline
        .saturating_duration_since(Instant::now())
        .min(Duration::from_secs(40));
    let devtools_port = rx
        .recv_timeout(wait)
        .ok()
        .flatten()
        .expect("chromium did not start its DevTools server within 40 s");
    Browser {
        child,
        devtools_port,
        profile,
    }
}

/// GET on chromium's DevTools HTTP server (it keeps the connection open, so
/// the body is read by its Content-Length).
fn http_get(port: u16, path: &str) -> String {
    let s = TcpStream::connect(("127.0.0.1", port)).unwrap();
    s.set_read_timeout(Some(Duration::from_secs(10))).unwrap();
    (&s).write_all(format!("GET {path} HTTP/1.1\r\nHost: 127.0.0.1:{port}\r\n\r\n").as_bytes())
        .unwrap();
    let mut reader = BufReader::new(&s);
    let mut length = 0usize;
    let mut line = String::new();
    loop {
        line.clear();
        reader.read_line(&mut line).unwrap();
        if line == "\r\n" || line.is_empty() {
            break;
        }
        if let Some((k, v)) = line.split_once(':') {
            if k.eq_ignore_ascii_case("content-length") {
                length = v.trim().parse().unwrap();
            }
        }
    }
    let mut body = vec![0u8; length];
    reader.read_exact(&mut body).unwrap();
    String::from_utf8_lossy(&body).into_owned()
}

/// A minimal DevTools-protocol client over one WebSocket (RFC 6455: client
/// frames masked, server frames not).
struct DevTools {
    stream: TcpStream,
    next_id: u64,
}

impl DevTools {
    fn connect(port: u16, page_url_prefix: &str, deadline: Instant) -> DevTools {
        // The page target chromium opened for our URL.
        let ws_url = loop {
            let list: serde_json::Value =
                serde_json::from_str(&http_get(port, "/json/list")).unwrap_or_default();
            let found = list.as_array().and_then(|targets| {
                targets
                    .iter()
                    .find(|t| {
                        t["type"] == "page"
                            && t["url"]
                                .as_str()
                                .is_some_and(|u| u.starts_with(page_url_prefix))
                    })
                    .and_then(|t| t["webSocketDebuggerUrl"].as_str().map(String::from))
            });
            if let Some(u) = found {
                break u;
            }
            assert!(
                Instant::now() < deadline,
                "no page target for {page_url_prefix}: {list}"
            );
            std::thread::sleep(Duration::from_millis(200));
        };
        let path = ws_url
            .split_once(&format!("127.0.0.1:{port}"))
            .map(|(_, p)| p.to_string())
            .expect("DevTools URL on loopback");
        let mut stream = TcpStream::connect(("127.0.0.1", port)).unwrap();
        stream
            .set_read_timeout(Some(Duration::from_secs(20)))
            .unwrap();
        write!(
            stream,
            "GET {path} HTTP/1.1\r\nHost: 127.0.0.1:{port}\r\nUpgrade: websocket\r\nConnection: Upgrade\r\n\
             Sec-WebSocket-Key: dGhlIHNhbXBsZSBub25jZQ==\r\nSec-WebSocket-Version: 13\r\n\r\n"
        )
        .unwrap();
        let mut head = Vec::new();
        let mut b = [0u8; 1];
        while !head.ends_with(b"\r\n\r\n") {
            stream.read_exact(&mut b).unwrap();
            head.push(b[0]);
        }
        let head = String::from_utf8_lossy(&head);
        assert!(
            head.starts_with("HTTP/1.1 101"),
            "DevTools handshake: {head}"
        );
        DevTools { stream, next_id: 1 }
    }

    fn send(&mut self, text: &str) {
        let payload = text.as_bytes();
        let mask = [0x37u8, 0xfa, 0x21, 0x3d];
        let mut frame = vec![0x81u8];
        match payload.len() {
            n if n < 126 => frame.push(0x80 | n as u8),
            n if n <= 0xffff => {
                frame.push(0x80 | 126);
                frame.extend_from_slice(&(n as u16).to_be_bytes());
            }
            n => {
                frame.push(0x80 | 127);
                frame.extend_from_slice(&(n as u64).to_be_bytes());
            }
        }
        frame.extend_from_slice(&mask);
        frame.extend(payload.iter().enumerate().map(|(i, b)| b ^ mask[i % 4]));
        self.stream.write_all(&frame).unwrap();
    }

    fn read_message(&mut self) -> Vec<u8> {
        let mut message = Vec::new();
        loop {
            let mut h = [0u8; 2];
            self.stream.read_exact(&mut h).unwrap();
            let mut len = u64::from(h[1] & 0x7f);
            if len == 126 {
                let mut b = [0u8; 2];
                self.stream.read_exact(&mut b).unwrap();
                len = u64::from(u16::from_be_bytes(b));
            } else if len == 127 {
                let mut b = [0u8; 8];
                self.stream.read_exact(&mut b).unwrap();
                len = u64::from_be_bytes(b);
            }
            let mut payload = vec![0u8; len as usize];
            self.stream.read_exact(&mut payload).unwrap();
            message.extend_from_slice(&payload);
            if h[0] & 0x80 != 0 {
                return message;
            }
        }
    }

    /// Call `method` and return its `result`.
    fn call(&mut self, method: &str, params: serde_json::Value) -> serde_json::Value {
        let id = self.next_id;
        self.next_id += 1;
        self.send(&serde_json::json!({"id": id, "method": method, "params": params}).to_string());
        loop {
            let v: serde_json::Value = serde_json::from_slice(&self.read_message()).unwrap();
            if v["id"] == id {
                assert!(v.get("error").is_none(), "{method}: {v}");
                return v["result"].clone();
            }
        }
    }

    /// What the page shows: update number, snapshots pushed to it, vehicle
    /// rows, the positions line and the connection state.
    fn page_state(&mut self) -> serde_json::Value {
        let expr = r##"JSON.stringify({
            update: Number(document.getElementById("update").textContent),
            received: Number(document.getElementById("received").textContent),
            rows: Array.from(document.querySelectorAll("#vehicles tbody tr")).map(r => r.id),
            hulls: document.querySelectorAll("#top line[stroke-linecap=round]").length,
            positions: document.getElementById("positions").textContent,
            conn: document.getElementById("conn").textContent
        })"##;
        let r = self.call(
            "Runtime.evaluate",
            serde_json::json!({"expression": expr, "returnByValue": true}),
        );
        // Before the page has loaded, the expression throws: report that instead.
        match r["result"]["value"].as_str() {
            Some(text) => serde_json::from_str(text).unwrap(),
            None => serde_json::json!({"not_ready": r}),
        }
    }
}

#[test]
fn station_page_shows_three_vehicles_and_updates_live_in_chromium() {
    let deadline = Instant::now() + BUDGET;
    let chromium_path = chromium(); // before the swarm: an install may take a while
    let cfg = DemoConfig {
        duration_s: 120.0, // stopped by the test long before
        frame_rate_hz: 1.0,
        cameras: Some(vec!["port".into(), "starboard".into()]),
        time_scale: 1.0,
        progress: false,
        log: None,
        station: Some(StationConfig {
            http_port: 0,
            foxglove_port: None,
            ..StationConfig::default()
        }),
        ..DemoConfig::default()
    };
    // Open loop: the followers drift, so the picture must change.
    let swarm = SimulatedSwarm::start(&cfg, vec![]).unwrap();
    let station = swarm.station().expect("the swarm started a station");
    let url = station.url();

    // Wait (bounded) until fusion has localized the swarm, so the page has something to show.
    loop {
        let v: serde_json::Value = serde_json::from_str(&station.latest().1).unwrap_or_default();
        let localized = v["vehicles"].as_array().map_or(0, |vs| {
            vs.iter().filter(|x| !x["estimate"].is_null()).count()
        });
        if localized == 3 {
            break;
        }
        assert!(
            Instant::now() + Duration::from_secs(45) < deadline,
            "fusion did not localize the three vehicles in time; last snapshot: {v}"
        );
        std::thread::sleep(Duration::from_millis(250));
    }

    let browser = launch(&chromium_path, &url, deadline);
    let mut devtools = DevTools::connect(browser.devtools_port, &url, deadline);
    // First look: the page is up, connected, and lists the three vehicles.
    let first = loop {
        let s = devtools.page_state();
        if s["received"].as_u64().unwrap_or(0) >= 1
            && s["positions"].as_str().unwrap_or("").matches(':').count() == 3
        {
            break s;
        }
        assert!(
            Instant::now() < deadline,
            "page never showed the swarm: {s}"
        );
        std::thread::sleep(Duration::from_millis(250));
    };
    assert_eq!(
        first["rows"],
        serde_json::json!(["veh-10", "veh-15", "veh-17"]),
        "{first}"
    );
    assert_eq!(
        first["hulls"].as_u64(),
        Some(6),
        "3 hulls + 3 ghosts in the top view: {first}"
    );
    assert_eq!(first["conn"], "live", "{first}");

    if let Ok(path) = std::env::var("SHOAL_STATION_SCREENSHOT") {
        let shot = devtools.call(
            "Page.captureScreenshot",
            serde_json::json!({"format": "png"}),
        );
        let png = decode_base64(shot["data"].as_str().unwrap());
        std::fs::write(&path, png).unwrap();
        eprintln!("screenshot written to {path}");
    }

    // Three seconds later, same page (no reload): more pushes, a newer map, vehicles moved.
    std::thread::sleep(Duration::from_secs(3));
    let second = devtools.page_state();
    eprintln!("page 3 s apart:\n  {first}\n  {second}");
    let pushed = second["received"].as_u64().unwrap() - first["received"].as_u64().unwrap();
    assert!(
        pushed >= 15,
        "only {pushed} updates pushed in 3 s (want ≥ 5 Hz): {first} → {second}"
    );
    assert!(
        second["update"].as_u64() > first["update"].as_u64(),
        "{first} → {second}"
    );
    assert_ne!(
        first["positions"], second["positions"],
        "the vehicles did not move on the page"
    );
    assert_eq!(second["conn"], "live", "{second}");
    drop(devtools);
    drop(browser);
    swarm.shutdown().unwrap();
}

#[test]
fn station_page_with_a_token_opens_from_its_url_and_streams_by_cookie() {
    const TOKEN: &str = "4b1d0c9e2f7a6b3c8d5e0f1a2b3c4d5e";
    let deadline = Instant::now() + BUDGET;
    let chromium_path = chromium();
    // No swarm needed: the station pushes its (empty) snapshot at its rate all the same.
    let bus = shoal_bus::Bus::open(&shoal_bus::Connect::Router {
        port: shoal_bus::free_port().unwrap(),
    })
    .unwrap();
    let fleet = shoal_proto::config::Fleet::load(std::path::Path::new("configs/fleets/paper.toml"))
        .unwrap();
    let station = shoal_station::spawn(
        &bus,
        std::sync::Arc::new(fleet),
        StationConfig {
            http_port: 0,
            foxglove_port: None,
            token: Some(TOKEN.into()),
            ..StationConfig::default()
        },
    )
    .unwrap();
    let base = station.url();
    let browser = launch(&chromium_path, &format!("{base}?token={TOKEN}"), deadline);
    let mut devtools = DevTools::connect(browser.devtools_port, &base, deadline);
    let state = loop {
        let s = devtools.page_state();
        if s["received"].as_u64().unwrap_or(0) >= 5 {
            break s;
        }
        assert!(
            Instant::now() < deadline,
            "the page opened with ?token= never streamed: {s}"
        );
        std::thread::sleep(Duration::from_millis(250));
    };
    assert_eq!(state["conn"], "live", "{state}");
    let r = devtools.call(
        "Runtime.evaluate",
        serde_json::json!({
            "expression": "JSON.stringify({href: location.href, cookie: document.cookie})",
            "returnByValue": true
        }),
    );
    let seen: serde_json::Value =
        serde_json::from_str(r["result"]["value"].as_str().unwrap()).unwrap();
    // Redirected to the page without the token; the cookie is out of the script's reach.
    assert_eq!(seen["href"], base.as_str(), "{seen}");
    assert_eq!(seen["cookie"], "", "{seen}");
    drop(devtools);
    drop(browser);
    station.stop();
}

/// Standard base64 (the DevTools screenshot), without a dependency for one call.
fn decode_base64(text: &str) -> Vec<u8> {
    const ALPHABET: &[u8] = b"ABCDEFGHIJKLMNOPQRSTUVWXYZabcdefghijklmnopqrstuvwxyz0123456789+/";
    let mut out = Vec::with_capacity(text.len() * 3 / 4);
    let (mut acc, mut bits) = (0u32, 0u32);
    for c in text.bytes().filter(|&c| c != b'=') {
        let v = ALPHABET.iter().position(|&a| a == c).expect("base64") as u32;
        acc = (acc << 6) | v;
        bits += 6;
        if bits >= 8 {
            bits -= 8;
            out.push((acc >> bits) as u8);
            acc &= (1 << bits) - 1;
        }
    }
    out
}
