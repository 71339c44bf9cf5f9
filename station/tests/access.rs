//! Who may use the station's page, over real sockets: a foreign `Host` and a
//! cross-origin request are refused, the station's own names are served;
//! with a token, requests without it (or with a wrong one) get 401, the
//! right bearer gets 200, and the page URL's `?token=` sets a cookie that
//! then opens the event stream; HTTPS with a generated certificate; the
//! connection cap; a public address without a token is refused.

use shoal_bus::{free_port, Bus, Connect};
use shoal_proto::config::Fleet;
use shoal_station::{StationConfig, StationError, StationHandle, TlsFiles};
use std::io::{BufRead, BufReader, Read, Write};
use std::net::{IpAddr, Ipv4Addr, SocketAddr, TcpStream};
use std::sync::Arc;
use std::time::Duration;

const PAPER: &str = include_str!("../../configs/fleets/paper.toml");
const TOKEN: &str = "7f3a9c0e5b2d4f6a8c1e3b5d7f9a0c2e";

fn fleet() -> Arc<Fleet> {
    Arc::new(Fleet::parse(PAPER, std::path::Path::new("configs/fleets/paper.toml")).unwrap())
}

fn config() -> StationConfig {
    StationConfig {
        http_port: 0,
        foxglove_port: None,
        ..StationConfig::default()
    }
}

/// A station on its own Zenoh router (kept alive beside it).
fn start(cfg: StationConfig) -> (StationHandle, Bus) {
    let bus = Bus::open(&Connect::Router {
        port: free_port().unwrap(),
    })
    .unwrap();
    let station = shoal_station::spawn(&bus, fleet(), cfg).unwrap();
    (station, bus)
}

/// A response: status, head (lower-cased names), body.
struct Reply {
    status: u16,
    head: String,
    body: String,
}

fn parse(text: &str) -> Reply {
    let (head, body) = text.split_once("\r\n\r\n").unwrap_or((text, ""));
    Reply {
        status: head.get(9..12).and_then(|s| s.parse().ok()).unwrap_or(0),
        head: head.to_ascii_lowercase(),
        body: body.to_string(),
    }
}

/// `GET path` with these header lines (each `Name: value`), read to the end.
fn get(addr: SocketAddr, path: &str, headers: &[String]) -> Reply {
    let mut s = TcpStream::connect(addr).unwrap();
    s.set_read_timeout(Some(Duration::from_secs(5))).unwrap();
    let mut req = format!("GET {path} HTTP/1.1\r\n");
    for h in headers {
        req.push_str(h);
        req.push_str("\r\n");
    }
    req.push_str("\r\n");
    s.write_all(req.as_bytes()).unwrap();
    let mut text = String::new();
    s.read_to_string(&mut text).unwrap();
    parse(&text)
}

fn host(addr: SocketAddr) -> String {
    format!("Host: {addr}")
}

#[test]
fn foreign_host_and_cross_origin_are_refused_and_own_names_served() {
    let (station, _bus) = start(StationConfig {
        allow_hosts: vec!["vessel.local".into()],
        ..config()
    });
    let addr = station.http_addr();
    let port = addr.port();
    for good in [
        format!("Host: 127.0.0.1:{port}"),
        format!("Host: localhost:{port}"),
        format!("Host: [::1]:{port}"),
        format!("Host: vessel.local:{port}"),
    ] {
        let r = get(addr, "/api/snapshot", std::slice::from_ref(&good));
        assert_eq!(r.status, 200, "{good}: {}", r.body);
        assert!(r.head.contains("application/json"), "{}", r.head);
    }
    // DNS rebinding: the attacker's name, resolved to 127.0.0.1.
    for foreign in [
        format!("Host: rebind.evil.example:{port}"),
        "Host: rebind.evil.example".to_string(),
        format!("Host: localhost:{}", port.wrapping_add(1)),
    ] {
        let r = get(addr, "/api/snapshot", std::slice::from_ref(&foreign));
        assert_eq!(r.status, 421, "{foreign}: {}", r.body);
        assert!(r.body.contains("--allow-host"), "{}", r.body);
        assert!(!r.body.contains("\"vehicles\""), "leaked: {}", r.body);
    }
    // Every route, the page and the event stream included.
    for path in ["/", "/events", "/app.js", "/nope"] {
        let r = get(addr, path, &["Host: evil.example".into()]);
        assert_eq!(r.status, 421, "{path}");
    }
    // A page of another origin (its script fetching ours): refused; our own origin: served.
    let cross = get(
        addr,
        "/api/snapshot",
        &[host(addr), "Origin: http://evil.example".into()],
    );
    assert_eq!(cross.status, 403, "{}", cross.body);
    assert!(cross.body.contains("cross-origin"), "{}", cross.body);
    let same = get(
        addr,
        "/api/snapshot",
        &[host(addr), format!("Origin: http://{addr}")],
    );
    assert_eq!(same.status, 200, "{}", same.body);
    // Hardened responses, and no token needed when none is set.
    let page = get(addr, "/", &[host(addr)]);
    assert_eq!(page.status, 200);
    assert!(
        page.head.contains("cache-control: no-store"),
        "{}",
        page.head
    );
    assert!(
        page.head.contains("x-content-type-options: nosniff"),
        "{}",
        page.head
    );
    station.stop();
}

#[test]
fn with_a_token_only_requests_carrying_it_are_served() {
    let (station, _bus) = start(StationConfig {
        token: Some(TOKEN.into()),
        ..config()
    });
    let addr = station.http_addr();
    for path in ["/", "/api/snapshot", "/events", "/app.js"] {
        let r = get(addr, path, &[host(addr)]);
        assert_eq!(r.status, 401, "{path}: {}", r.body);
        assert!(r.head.contains("www-authenticate: bearer"), "{}", r.head);
        assert!(r.body.contains("?token="), "{}", r.body);
    }
    let wrong = get(
        addr,
        "/api/snapshot",
        &[
            host(addr),
            "Authorization: Bearer 7f3a9c0e5b2d4f6a8c1e3b5d7f9a0c2f".into(),
        ],
    );
    assert_eq!(wrong.status, 401, "{}", wrong.body);
    let wrong_url = get(
        addr,
        "/?token=7f3a9c0e5b2d4f6a8c1e3b5d7f9a0c2f",
        &[host(addr)],
    );
    assert_eq!(wrong_url.status, 401, "{}", wrong_url.body);
    assert!(!wrong_url.head.contains("set-cookie"), "{}", wrong_url.head);
    let right = get(
        addr,
        "/api/snapshot",
        &[host(addr), format!("Authorization: Bearer {TOKEN}")],
    );
    assert_eq!(right.status, 200, "{}", right.body);
    let _: serde_json::Value = serde_json::from_str(&right.body).unwrap();
    // A foreign Host is refused even with the token.
    let foreign = get(
        addr,
        "/api/snapshot",
        &[
            "Host: evil.example".into(),
            format!("Authorization: Bearer {TOKEN}"),
        ],
    );
    assert_eq!(foreign.status, 421);

    // The page URL with the token: a cookie, and the page again without the token.
    let visit = get(addr, &format!("/?token={TOKEN}"), &[host(addr)]);
    assert_eq!(visit.status, 303, "{}", visit.body);
    assert!(visit.head.contains("\r\nlocation: /\r\n"), "{}", visit.head);
    let cookie_line = visit
        .head
        .lines()
        .find(|l| l.starts_with("set-cookie:"))
        .expect("a cookie");
    assert!(cookie_line.contains("httponly"), "{cookie_line}");
    assert!(cookie_line.contains("samesite=strict"), "{cookie_line}");
    let cookie = format!(
        "Cookie: {}",
        cookie_line["set-cookie:".len()..]
            .split(';')
            .next()
            .unwrap()
            .trim()
    );
    let page = get(addr, "/", &[host(addr), cookie.clone()]);
    assert_eq!(page.status, 200);
    assert!(page.body.contains("/app.js"), "{}", page.body);

    // The cookie opens the event stream (what the page's EventSource sends).
    let mut s = TcpStream::connect(addr).unwrap();
    s.set_read_timeout(Some(Duration::from_secs(5))).unwrap();
    write!(
        s,
        "GET /events HTTP/1.1\r\n{}\r\n{cookie}\r\n\r\n",
        host(addr)
    )
    .unwrap();
    let mut lines = BufReader::new(&s);
    let mut line = String::new();
    lines.read_line(&mut line).unwrap();
    assert!(line.starts_with("HTTP/1.1 200"), "{line}");
    let mut events = 0;
    while events < 3 {
        line.clear();
        assert!(lines.read_line(&mut line).unwrap() > 0, "stream closed");
        if line.starts_with("id: ") {
            events += 1;
        }
    }
    drop(lines);
    station.stop();
}

/// A self-signed certificate for `localhost` / 127.0.0.1, written as PEM files.
fn certificate(dir: &std::path::Path) -> (TlsFiles, rustls::pki_types::CertificateDer<'static>) {
    std::fs::create_dir_all(dir).unwrap();
    let c =
        rcgen::generate_simple_self_signed(vec!["localhost".into(), "127.0.0.1".into()]).unwrap();
    let files = TlsFiles {
        cert: dir.join("cert.pem"),
        key: dir.join("key.pem"),
    };
    std::fs::write(&files.cert, c.cert.pem()).unwrap();
    std::fs::write(&files.key, c.key_pair.serialize_pem()).unwrap();
    (files, c.cert.der().clone())
}

/// `GET path` over TLS, trusting only `cert`, to the server name `name`.
fn get_tls(
    addr: SocketAddr,
    name: &str,
    cert: &rustls::pki_types::CertificateDer<'static>,
    path: &str,
    headers: &[String],
) -> Reply {
    let mut roots = rustls::RootCertStore::empty();
    roots.add(cert.clone()).unwrap();
    let provider = Arc::new(rustls::crypto::ring::default_provider());
    let config = rustls::ClientConfig::builder_with_provider(provider)
        .with_safe_default_protocol_versions()
        .unwrap()
        .with_root_certificates(roots)
        .with_no_client_auth();
    let server_name = rustls::pki_types::ServerName::try_from(name.to_string()).unwrap();
    let conn = rustls::ClientConnection::new(Arc::new(config), server_name).unwrap();
    let tcp = TcpStream::connect(addr).unwrap();
    tcp.set_read_timeout(Some(Duration::from_secs(5))).unwrap();
    let mut tls = rustls::StreamOwned::new(conn, tcp);
    let mut req = format!("GET {path} HTTP/1.1\r\n");
    for h in headers {
        req.push_str(h);
        req.push_str("\r\n");
    }
    req.push_str("\r\n");
    tls.write_all(req.as_bytes()).unwrap();
    let mut bytes = Vec::new();
    // A peer that closes without close_notify ends in UnexpectedEof after the data.
    match tls.read_to_end(&mut bytes) {
        Ok(_) => {}
        Err(e) if e.kind() == std::io::ErrorKind::UnexpectedEof => {}
        Err(e) => panic!("TLS read: {e}"),
    }
    parse(&String::from_utf8_lossy(&bytes))
}

#[test]
fn https_with_a_generated_certificate_serves_the_page() {
    let dir = std::env::temp_dir().join(format!("shoal-station-https-{}", std::process::id()));
    let (files, cert) = certificate(&dir);
    let (station, _bus) = start(StationConfig {
        tls: Some(files),
        token: Some(TOKEN.into()),
        ..config()
    });
    let addr = station.http_addr();
    assert_eq!(station.url(), format!("https://{addr}/"));
    let port = addr.port();
    let r = get_tls(
        addr,
        "localhost",
        &cert,
        "/api/snapshot",
        &[
            format!("Host: localhost:{port}"),
            format!("Authorization: Bearer {TOKEN}"),
        ],
    );
    assert_eq!(r.status, 200, "{}", r.body);
    let _: serde_json::Value = serde_json::from_str(&r.body).unwrap();
    // The cookie is marked Secure over HTTPS.
    let visit = get_tls(
        addr,
        "localhost",
        &cert,
        &format!("/?token={TOKEN}"),
        &[format!("Host: localhost:{port}")],
    );
    assert_eq!(visit.status, 303);
    assert!(visit.head.contains("; secure"), "{}", visit.head);
    // Same checks as over HTTP.
    let no_token = get_tls(
        addr,
        "localhost",
        &cert,
        "/",
        &[format!("Host: localhost:{port}")],
    );
    assert_eq!(no_token.status, 401);
    // Plain HTTP to the HTTPS port gets no page.
    let mut s = TcpStream::connect(addr).unwrap();
    s.set_read_timeout(Some(Duration::from_secs(10))).unwrap();
    // The server may refuse the handshake and close before the write ends
    // (a broken pipe): either way no page may come back.
    let _ = write!(
        s,
        "GET / HTTP/1.1\r\nHost: localhost:{port}\r\nAuthorization: Bearer {TOKEN}\r\n\r\n"
    );
    let mut text = Vec::new();
    let _ = s.read_to_end(&mut text);
    assert!(
        !String::from_utf8_lossy(&text).contains("HTTP/1.1 200"),
        "plain HTTP served over the TLS port"
    );
    station.stop();
    std::fs::remove_dir_all(dir).unwrap();
}

#[test]
fn bad_tls_files_are_errors_not_panics() {
    let bus = Bus::open(&Connect::Router {
        port: free_port().unwrap(),
    })
    .unwrap();
    let cfg = StationConfig {
        tls: Some(TlsFiles {
            cert: "/nonexistent/station-cert.pem".into(),
            key: "/nonexistent/station-key.pem".into(),
        }),
        ..config()
    };
    let err = shoal_station::spawn(&bus, fleet(), cfg).unwrap_err();
    assert!(matches!(err, StationError::TlsRead { .. }), "{err:?}");
    assert!(
        err.to_string().contains("/nonexistent/station-cert.pem"),
        "{err}"
    );
}

#[test]
fn connections_beyond_the_cap_get_503() {
    let (station, _bus) = start(config());
    let addr = station.http_addr();
    // Fill every slot with an open event stream.
    let streams: Vec<TcpStream> = (0..shoal_station::http::MAX_CONNECTIONS)
        .map(|_| {
            let mut s = TcpStream::connect(addr).unwrap();
            s.set_read_timeout(Some(Duration::from_secs(5))).unwrap();
            write!(s, "GET /events HTTP/1.1\r\n{}\r\n\r\n", host(addr)).unwrap();
            let mut first = [0u8; 12];
            s.read_exact(&mut first).unwrap();
            assert_eq!(&first, b"HTTP/1.1 200");
            s
        })
        .collect();
    let r = get(addr, "/api/snapshot", &[host(addr)]);
    assert_eq!(r.status, 503, "{}", r.body);
    drop(streams);
    // Slots free again once those clients are gone (noticed at the next write, ≤ 1 s at 10 Hz).
    let deadline = std::time::Instant::now() + Duration::from_secs(10);
    loop {
        let r = get(addr, "/api/snapshot", &[host(addr)]);
        if r.status == 200 {
            break;
        }
        assert!(
            std::time::Instant::now() < deadline,
            "slots never freed: {}",
            r.status
        );
        std::thread::sleep(Duration::from_millis(100));
    }
    station.stop();
}

#[test]
fn public_address_needs_a_token_and_no_open_foxglove() {
    let public = StationConfig {
        bind: IpAddr::V4(Ipv4Addr::UNSPECIFIED),
        ..config()
    };
    let err = public.check().unwrap_err();
    assert!(
        matches!(err, StationError::PublicWithoutToken { .. }),
        "{err:?}"
    );
    assert!(err.to_string().contains("--insecure-public"), "{err}");
    let with_foxglove = StationConfig {
        token: Some(TOKEN.into()),
        foxglove_port: Some(0),
        ..public.clone()
    };
    let err = with_foxglove.check().unwrap_err();
    assert!(
        matches!(err, StationError::PublicFoxglove { .. }),
        "{err:?}"
    );
    assert!(err.to_string().contains("--no-foxglove"), "{err}");
    let with_token = StationConfig {
        token: Some(TOKEN.into()),
        ..public.clone()
    };
    assert!(with_token.check().is_ok());
    let insecure = StationConfig {
        insecure_public: true,
        foxglove_port: Some(0),
        ..public
    };
    assert!(insecure.check().is_ok());
    // Loopback needs neither.
    assert!(config().check().is_ok());
    // A weak token is refused before anything binds.
    let weak = StationConfig {
        token: Some("secret".into()),
        ..config()
    };
    assert!(matches!(weak.check().unwrap_err(), StationError::Token(_)));
}
