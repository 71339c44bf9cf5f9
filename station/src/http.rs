//! A small HTTP/1.1 server on `std::net`, enough for the station page: GET
//! of a few embedded files, one JSON endpoint and one server-sent-events
//! stream. One named thread per connection, at most [`MAX_CONNECTIONS`] at a
//! time; requests are read with a deadline and a size limit.
//!
//! Why not a framework: the page needs four routes and a push stream, and
//! SSE is plain HTTP; `std::net` does it without an async stack of its own
//! (the `foxglove` server brings tokio, but exposes no HTTP routing).

use crate::StationError;
use shoal_bus::Worker;
use std::io::{BufRead, BufReader, Read, Write};
use std::net::{SocketAddr, TcpListener, TcpStream};
use std::sync::atomic::{AtomicBool, AtomicUsize, Ordering};
use std::sync::{Arc, Condvar, Mutex};
use std::time::Duration;

/// Open connections beyond this get `503`.
pub const MAX_CONNECTIONS: usize = 32;
/// A request head larger than this gets `431`.
const MAX_HEAD_BYTES: usize = 8 * 1024;
/// Time a client has to send its request head.
const READ_TIMEOUT: Duration = Duration::from_secs(5);
/// An idle event stream sends a comment this often (detects closed clients, keeps proxies open).
const KEEPALIVE: Duration = Duration::from_secs(2);

const INDEX_HTML: &str = include_str!("../web/index.html");
const APP_JS: &str = include_str!("../web/app.js");
const STYLE_CSS: &str = include_str!("../web/style.css");

/// The newest snapshot and its number; event streams wait on it.
#[derive(Debug, Default)]
pub struct Hub {
    latest: Mutex<(u64, Arc<str>)>,
    changed: Condvar,
}

impl Hub {
    pub fn new() -> Arc<Hub> {
        Arc::new(Hub {
            latest: Mutex::new((0, Arc::from("{}"))),
            changed: Condvar::new(),
        })
    }

    /// Publish snapshot number `seq`.
    pub fn publish(&self, seq: u64, json: String) {
        if let Ok(mut g) = self.latest.lock() {
            *g = (seq, Arc::from(json));
        }
        self.changed.notify_all();
    }

    pub fn latest(&self) -> (u64, Arc<str>) {
        self.latest
            .lock()
            .map(|g| g.clone())
            .unwrap_or((0, Arc::from("{}")))
    }

    /// Wait up to `timeout` for a snapshot newer than `seen`.
    fn wait_newer(&self, seen: u64, timeout: Duration) -> Option<(u64, Arc<str>)> {
        let g = self.latest.lock().ok()?;
        let (g, _) = self
            .changed
            .wait_timeout_while(g, timeout, |(seq, _)| *seq <= seen)
            .ok()?;
        (g.0 > seen).then(|| g.clone())
    }
}

/// The running HTTP server.
#[derive(Debug)]
pub struct HttpServer {
    pub addr: SocketAddr,
    worker: Worker,
}

impl HttpServer {
    /// Bind `addr` and serve in a background thread.
    pub fn start(addr: SocketAddr, hub: Arc<Hub>) -> Result<HttpServer, StationError> {
        let listener = TcpListener::bind(addr).map_err(|source| StationError::Bind {
            what: "HTTP",
            addr,
            source,
        })?;
        let addr = listener.local_addr().map_err(|source| StationError::Bind {
            what: "HTTP",
            addr,
            source,
        })?;
        // Non-blocking accept so that `stop` is noticed within one poll period.
        listener
            .set_nonblocking(true)
            .map_err(|source| StationError::Bind {
                what: "HTTP",
                addr,
                source,
            })?;
        let open = Arc::new(AtomicUsize::new(0));
        let worker = Worker::spawn("station-http", move |st| {
            accept_loop(listener, hub, st, open)
        })
        .map_err(|e| StationError::Thread(e.to_string()))?;
        Ok(HttpServer { addr, worker })
    }

    /// Stop accepting; open event streams end within one keep-alive period (2 s).
    pub fn stop(self) {
        self.worker.stop();
    }
}

fn accept_loop(
    listener: TcpListener,
    hub: Arc<Hub>,
    stop: Arc<AtomicBool>,
    open: Arc<AtomicUsize>,
) {
    while !stop.load(Ordering::Relaxed) {
        match listener.accept() {
            Ok((stream, peer)) => {
                if stream.set_nonblocking(false).is_err() {
                    continue;
                }
                if open.fetch_add(1, Ordering::SeqCst) >= MAX_CONNECTIONS {
                    open.fetch_sub(1, Ordering::SeqCst);
                    let mut s = stream;
                    let _ = respond(&mut s, 503, "text/plain", b"too many connections\n", false);
                    continue;
                }
                let (hub, stop, open2) = (hub.clone(), stop.clone(), open.clone());
                let spawned = std::thread::Builder::new()
                    .name("station-conn".into())
                    .spawn(move || {
                        if let Err(e) = serve(stream, &hub, &stop) {
                            tracing::debug!("station: connection from {peer}: {e}");
                        }
                        open2.fetch_sub(1, Ordering::SeqCst);
                    });
                if let Err(e) = spawned {
                    open.fetch_sub(1, Ordering::SeqCst);
                    tracing::warn!("station: cannot start a connection thread: {e}");
                }
            }
            Err(e) if e.kind() == std::io::ErrorKind::WouldBlock => {
                std::thread::sleep(Duration::from_millis(50));
            }
            Err(e) => {
                tracing::warn!("station: accept: {e}");
                std::thread::sleep(Duration::from_millis(200));
            }
        }
    }
}

/// Method and path of a request head; `Err(status)` for a malformed or oversized head.
fn read_request(stream: &TcpStream) -> Result<(String, String), u16> {
    let mut reader = BufReader::new(stream.take(MAX_HEAD_BYTES as u64 + 1));
    let mut line = String::new();
    let mut total = 0usize;
    let mut first: Option<String> = None;
    loop {
        line.clear();
        let n = reader.read_line(&mut line).map_err(|_| 400u16)?;
        total += n;
        if total > MAX_HEAD_BYTES {
            return Err(431);
        }
        if n == 0 {
            return Err(400); // closed before the end of the head
        }
        if line == "\r\n" || line == "\n" {
            break;
        }
        if first.is_none() {
            first = Some(line.trim_end().to_string());
        }
    }
    let first = first.ok_or(400u16)?;
    let mut parts = first.split(' ');
    match (parts.next(), parts.next(), parts.next()) {
        (Some(m), Some(p), Some(v)) if v.starts_with("HTTP/1.") => {
            Ok((m.to_string(), p.to_string()))
        }
        _ => Err(400),
    }
}

fn reason(status: u16) -> &'static str {
    match status {
        200 => "OK",
        400 => "Bad Request",
        404 => "Not Found",
        405 => "Method Not Allowed",
        431 => "Request Header Fields Too Large",
        503 => "Service Unavailable",
        _ => "Error",
    }
}

fn respond(
    stream: &mut TcpStream,
    status: u16,
    content_type: &str,
    body: &[u8],
    head_only: bool,
) -> std::io::Result<()> {
    let head = format!(
        "HTTP/1.1 {status} {}\r\nContent-Type: {content_type}\r\nContent-Length: {}\r\nCache-Control: no-store\r\nConnection: close\r\n\r\n",
        reason(status),
        body.len()
    );
    stream.write_all(head.as_bytes())?;
    if !head_only {
        stream.write_all(body)?;
    }
    stream.flush()
}

fn serve(mut stream: TcpStream, hub: &Hub, stop: &AtomicBool) -> std::io::Result<()> {
    stream.set_read_timeout(Some(READ_TIMEOUT))?;
    stream.set_write_timeout(Some(READ_TIMEOUT))?;
    let (method, target) = match read_request(&stream) {
        Ok(r) => r,
        Err(status) => return respond(&mut stream, status, "text/plain", b"bad request\n", false),
    };
    let head_only = method == "HEAD";
    if method != "GET" && !head_only {
        return respond(&mut stream, 405, "text/plain", b"GET only\n", false);
    }
    let path = target.split('?').next().unwrap_or("");
    match path {
        "/" | "/index.html" => {
            let page = index_with_snapshot(&hub.latest().1);
            respond(
                &mut stream,
                200,
                "text/html; charset=utf-8",
                page.as_bytes(),
                head_only,
            )
        }
        "/app.js" => respond(
            &mut stream,
            200,
            "text/javascript; charset=utf-8",
            APP_JS.as_bytes(),
            head_only,
        ),
        "/style.css" => respond(
            &mut stream,
            200,
            "text/css; charset=utf-8",
            STYLE_CSS.as_bytes(),
            head_only,
        ),
        "/api/snapshot" => {
            let (_, json) = hub.latest();
            respond(
                &mut stream,
                200,
                "application/json",
                json.as_bytes(),
                head_only,
            )
        }
        "/events" if !head_only => stream_events(stream, hub, stop),
        _ => respond(&mut stream, 404, "text/plain", b"not found\n", head_only),
    }
}

/// The page with the current snapshot embedded (a JSON `<script>` block;
/// `</` is escaped as `<\/`, which JSON reads back as the same string, so a
/// name cannot close the block).
pub fn index_with_snapshot(json: &str) -> String {
    INDEX_HTML.replacen("__SNAPSHOT__", &json.replace("</", "<\\/"), 1)
}

/// Server-sent events: every new snapshot as one `data:` line (JSON has no
/// raw newlines), starting with the current one.
fn stream_events(mut stream: TcpStream, hub: &Hub, stop: &AtomicBool) -> std::io::Result<()> {
    stream.write_all(
        b"HTTP/1.1 200 OK\r\nContent-Type: text/event-stream\r\nCache-Control: no-store\r\nConnection: keep-alive\r\nX-Accel-Buffering: no\r\n\r\nretry: 1000\n\n",
    )?;
    let (mut seen, json) = hub.latest();
    write_event(&mut stream, seen, &json)?;
    while !stop.load(Ordering::Relaxed) {
        match hub.wait_newer(seen, KEEPALIVE) {
            Some((seq, json)) => {
                seen = seq;
                write_event(&mut stream, seq, &json)?;
            }
            None => {
                stream.write_all(b": keepalive\n\n")?;
                stream.flush()?;
            }
        }
    }
    Ok(())
}

fn write_event(stream: &mut TcpStream, seq: u64, json: &str) -> std::io::Result<()> {
    // serde_json escapes control characters, so the snapshot is one line.
    let mut out = Vec::with_capacity(json.len() + 32);
    write!(out, "id: {seq}\ndata: {json}\n\n")?;
    stream.write_all(&out)?;
    stream.flush()
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn embedded_snapshot_cannot_close_its_script_block() {
        let json = serde_json::json!({"name": "evil</script><script>alert(1)"}).to_string();
        let page = index_with_snapshot(&json);
        let start = page.find("type=\"application/json\">").unwrap() + 24;
        let end = start + page[start..].find("</script>").unwrap();
        let back: serde_json::Value = serde_json::from_str(&page[start..end]).unwrap();
        assert_eq!(back["name"], "evil</script><script>alert(1)");
        assert!(!page.contains("__SNAPSHOT__"));
    }
}
