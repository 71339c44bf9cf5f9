//! The station page's HTTP server: axum routes on a tokio runtime that the
//! server owns (one thread, `station-http`), so callers stay synchronous and
//! the station's compute stays on its own thread.
//!
//! Routes: `/` (the page with the current snapshot embedded), `/app.js`,
//! `/style.css`, `/api/snapshot` (JSON) and `/events` (server-sent events,
//! one snapshot per update). Every request passes [`access::guard`] first
//! (Host/Origin check, optional token).
//!
//! The accept loop is ours rather than `axum::serve`, for what that lacks:
//! at most [`MAX_CONNECTIONS`] open connections (the rest get `503`), a
//! deadline for the request head and the TLS handshake, a bound on the head's
//! size (`431`), and HTTPS through tokio-rustls. One request per connection
//! (`Connection: close`), as the page needs: one load, then one event stream.

use crate::access::{self, Access};
use crate::StationError;
use axum::body::{Body, Bytes};
use axum::extract::State;
use axum::http::header::CONTENT_TYPE;
use axum::http::{HeaderName, HeaderValue, StatusCode};
use axum::response::{IntoResponse, Response};
use axum::routing::get;
use axum::Router;
use hyper_util::rt::{TokioIo, TokioTimer};
use hyper_util::service::TowerToHyperService;
use std::net::SocketAddr;
use std::sync::Arc;
use std::thread::JoinHandle;
use std::time::Duration;
use tokio::io::{AsyncReadExt, AsyncWriteExt};
use tokio::net::{TcpListener, TcpStream};
use tokio::sync::{oneshot, watch, Semaphore};
use tokio_rustls::TlsAcceptor;

/// Open connections beyond this get `503`.
pub const MAX_CONNECTIONS: usize = 32;
/// A request head larger than this gets `431` (hyper's smallest read buffer).
const MAX_HEAD_BYTES: usize = 8 * 1024;
/// Time a client has to finish the TLS handshake, and then its request head.
const READ_TIMEOUT: Duration = Duration::from_secs(5);
/// Time a refused connection (over the cap) is given to take its `503`.
const REFUSAL_TIMEOUT: Duration = Duration::from_secs(1);
/// An idle event stream sends a comment this often (detects closed clients, keeps proxies open).
const KEEPALIVE: Duration = Duration::from_secs(2);

const INDEX_HTML: &str = include_str!("../web/index.html");
const APP_JS: &str = include_str!("../web/app.js");
const STYLE_CSS: &str = include_str!("../web/style.css");

/// A snapshot's number and JSON.
type Snapshot = (u64, Arc<str>);

/// The newest snapshot and its number; event streams wait on it.
#[derive(Debug)]
pub struct Hub {
    latest: watch::Sender<Snapshot>,
}

impl Hub {
    pub fn new() -> Arc<Hub> {
        Arc::new(Hub {
            latest: watch::Sender::new((0, Arc::from("{}"))),
        })
    }

    /// Publish snapshot number `seq` (from any thread; never blocks on readers).
    pub fn publish(&self, seq: u64, json: String) {
        self.latest.send_replace((seq, Arc::from(json)));
    }

    pub fn latest(&self) -> Snapshot {
        self.latest.borrow().clone()
    }
}

/// What the server needs besides its address: access rules and, for HTTPS, the TLS configuration.
#[derive(Debug, Clone, Default)]
pub struct ServeOptions {
    pub allowed_hosts: Vec<access::AllowedHost>,
    pub token: Option<access::Token>,
    pub tls: Option<Arc<rustls::ServerConfig>>,
}

/// The running HTTP server.
#[derive(Debug)]
pub struct HttpServer {
    pub addr: SocketAddr,
    /// Serving HTTPS.
    pub tls: bool,
    shutdown: Option<oneshot::Sender<()>>,
    thread: Option<JoinHandle<()>>,
}

impl HttpServer {
    /// Bind `addr` and serve on the server's own runtime thread. Binding
    /// happens here, so a taken port is an error of this call.
    pub fn start(
        addr: SocketAddr,
        hub: Arc<Hub>,
        options: ServeOptions,
    ) -> Result<HttpServer, StationError> {
        let bind_error = |source| StationError::Bind {
            what: "HTTP",
            addr,
            source,
        };
        let listener = std::net::TcpListener::bind(addr).map_err(bind_error)?;
        let addr = listener.local_addr().map_err(bind_error)?;
        listener.set_nonblocking(true).map_err(bind_error)?;
        let runtime = tokio::runtime::Builder::new_current_thread()
            .enable_io()
            .enable_time()
            .build()
            .map_err(|e| StationError::Thread(format!("station HTTP runtime: {e}")))?;
        let listener = {
            let _in_runtime = runtime.enter();
            TcpListener::from_std(listener).map_err(bind_error)?
        };
        let tls = options.tls.is_some();
        let access = Arc::new(Access::new(
            addr,
            tls,
            &options.allowed_hosts,
            options.token,
        ));
        let app = router(hub, access);
        let acceptor = options.tls.map(TlsAcceptor::from);
        let (shutdown, stopped) = oneshot::channel();
        let thread = std::thread::Builder::new()
            .name("station-http".into())
            .spawn(move || {
                runtime.block_on(accept_loop(listener, app, acceptor, stopped));
                // Dropping the runtime ends the open connections (event streams included).
                drop(runtime);
            })
            .map_err(|e| StationError::Thread(e.to_string()))?;
        Ok(HttpServer {
            addr,
            tls,
            shutdown: Some(shutdown),
            thread: Some(thread),
        })
    }

    /// Stop accepting and close the open connections (event streams included).
    pub fn stop(mut self) {
        self.shutdown();
    }

    fn shutdown(&mut self) {
        if let Some(s) = self.shutdown.take() {
            let _ = s.send(());
        }
        if let Some(t) = self.thread.take() {
            shoal_bus::worker::join_reporting(t);
        }
    }
}

impl Drop for HttpServer {
    fn drop(&mut self) {
        self.shutdown();
    }
}

fn router(hub: Arc<Hub>, access: Arc<Access>) -> Router {
    Router::new()
        .route("/", get(page))
        .route("/index.html", get(page))
        .route(
            "/app.js",
            get(|| async { text("text/javascript; charset=utf-8", APP_JS) }),
        )
        .route(
            "/style.css",
            get(|| async { text("text/css; charset=utf-8", STYLE_CSS) }),
        )
        .route("/api/snapshot", get(snapshot))
        .route("/events", get(events))
        .fallback(|| async { (StatusCode::NOT_FOUND, "not found\n") })
        .with_state(hub)
        .layer(axum::middleware::from_fn_with_state(access, access::guard))
}

fn text(content_type: &'static str, body: impl Into<Body>) -> Response {
    ([(CONTENT_TYPE, content_type)], body.into()).into_response()
}

async fn page(State(hub): State<Arc<Hub>>) -> Response {
    text(
        "text/html; charset=utf-8",
        index_with_snapshot(&hub.latest().1),
    )
}

async fn snapshot(State(hub): State<Arc<Hub>>) -> Response {
    text("application/json", hub.latest().1.to_string())
}

/// Server-sent events: every new snapshot as one `data:` line (serde_json
/// escapes control characters, so JSON has no raw newlines), starting with
/// the current one; a comment after [`KEEPALIVE`] without one.
async fn events(State(hub): State<Arc<Hub>>) -> Response {
    let mut updates = hub.latest.subscribe();
    let (seq, json) = updates.borrow_and_update().clone();
    let first = format!("retry: 1000\n\nid: {seq}\ndata: {json}\n\n");
    let stream =
        futures_util::stream::unfold((updates, Some(first)), |(mut updates, first)| async move {
            let chunk = match first {
                Some(first) => first,
                None => match tokio::time::timeout(KEEPALIVE, updates.changed()).await {
                    Ok(Ok(())) => {
                        let (seq, json) = updates.borrow_and_update().clone();
                        format!("id: {seq}\ndata: {json}\n\n")
                    }
                    Ok(Err(_)) => return None, // the station stopped
                    Err(_) => ": keepalive\n\n".to_string(),
                },
            };
            Some((
                Ok::<_, std::convert::Infallible>(Bytes::from(chunk)),
                (updates, None),
            ))
        });
    let mut response = text("text/event-stream", Body::from_stream(stream));
    response.headers_mut().insert(
        HeaderName::from_static("x-accel-buffering"),
        HeaderValue::from_static("no"),
    );
    response
}

/// The page with the current snapshot embedded (a JSON `<script>` block;
/// `</` is escaped as `<\/`, which JSON reads back as the same string, so a
/// name cannot close the block).
pub fn index_with_snapshot(json: &str) -> String {
    INDEX_HTML.replacen("__SNAPSHOT__", &json.replace("</", "<\\/"), 1)
}

async fn accept_loop(
    listener: TcpListener,
    app: Router,
    tls: Option<TlsAcceptor>,
    mut stopped: oneshot::Receiver<()>,
) {
    let slots = Arc::new(Semaphore::new(MAX_CONNECTIONS));
    loop {
        let accepted = tokio::select! {
            _ = &mut stopped => return,
            accepted = listener.accept() => accepted,
        };
        let (stream, peer) = match accepted {
            Ok(a) => a,
            Err(e) => {
                // Out of file descriptors and the like: wait rather than spin.
                tracing::warn!("station: accept: {e}");
                tokio::time::sleep(Duration::from_millis(200)).await;
                continue;
            }
        };
        let Ok(slot) = slots.clone().try_acquire_owned() else {
            tokio::spawn(too_many(stream, tls.is_some()));
            continue;
        };
        let (app, tls) = (app.clone(), tls.clone());
        tokio::spawn(async move {
            if let Err(e) = connection(stream, app, tls).await {
                tracing::debug!("station: connection from {peer}: {e}");
            }
            drop(slot);
        });
    }
}

/// Answer `503` to a connection over [`MAX_CONNECTIONS`] (plain HTTP; over TLS it is just closed).
async fn too_many(mut stream: TcpStream, tls: bool) {
    if tls {
        return;
    }
    let reply = async {
        stream
            .write_all(
                b"HTTP/1.1 503 Service Unavailable\r\nContent-Type: text/plain\r\nContent-Length: 21\r\n\
                  Cache-Control: no-store\r\nConnection: close\r\n\r\ntoo many connections\n",
            )
            .await?;
        stream.shutdown().await?;
        // Read what the client sent: closing with it unread would reset the
        // connection and could destroy the reply before the client reads it.
        let mut sink = [0u8; 1024];
        while stream.read(&mut sink).await? > 0 {}
        Ok::<_, std::io::Error>(())
    };
    let _ = tokio::time::timeout(REFUSAL_TIMEOUT, reply).await;
}

async fn connection(
    stream: TcpStream,
    app: Router,
    tls: Option<TlsAcceptor>,
) -> Result<(), Box<dyn std::error::Error + Send + Sync>> {
    let _ = stream.set_nodelay(true);
    let mut http = hyper::server::conn::http1::Builder::new();
    http.timer(TokioTimer::new())
        .header_read_timeout(READ_TIMEOUT)
        .max_buf_size(MAX_HEAD_BYTES)
        .keep_alive(false);
    let service = TowerToHyperService::new(app);
    match tls {
        None => http.serve_connection(TokioIo::new(stream), service).await?,
        Some(acceptor) => {
            let stream = tokio::time::timeout(READ_TIMEOUT, acceptor.accept(stream))
                .await
                .map_err(|_| "TLS handshake timed out")??;
            http.serve_connection(TokioIo::new(stream), service).await?;
        }
    }
    Ok(())
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
