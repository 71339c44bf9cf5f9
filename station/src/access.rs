//! Who may use the station's HTTP server: every request passes [`guard`]
//! before any route runs.
//!
//! 1. **Host** (DNS rebinding): a page on `evil.example` whose name is made
//!    to resolve to 127.0.0.1 reaches a loopback server with `Host:
//!    evil.example`; so only the station's own names are answered — the
//!    address it is bound to, `localhost`, `127.0.0.1`, `[::1]`, and names
//!    given with `--allow-host` — each with the station's port. A station
//!    bound to every interface (`0.0.0.0`, `::`) also answers to any IP
//!    literal: a rebound request always carries a DNS name. Anything else is
//!    `421 Misdirected Request`.
//! 2. **Origin**: a request a browser sends on behalf of another page carries
//!    that page's origin; it must be the station's own (`scheme://Host`), else
//!    `403 Forbidden`. Requests without `Origin` (typed URLs, same-origin
//!    GETs, scripts) pass.
//! 3. **Token** (optional): with one set, every request needs `Authorization:
//!    Bearer TOKEN`, or the cookie the page URL `/?token=TOKEN` sets
//!    (HttpOnly, SameSite=Strict; a browser's `EventSource` cannot send
//!    headers), else `401 Unauthorized`. The `?token=` visit is answered with
//!    a redirect to the same page without it, so the token does not stay in
//!    the address bar or the history. Tokens are compared in constant time.

use crate::StationError;
use axum::extract::{Request, State};
use axum::http::header::{
    HeaderMap, HeaderName, HeaderValue, AUTHORIZATION, CACHE_CONTROL, CONTENT_TYPE, COOKIE, HOST,
    LOCATION, ORIGIN, SET_COOKIE, WWW_AUTHENTICATE,
};
use axum::http::{StatusCode, Uri};
use axum::middleware::Next;
use axum::response::{IntoResponse, Response};
use std::net::{IpAddr, SocketAddr};
use std::sync::Arc;
use subtle::ConstantTimeEq;

/// Shortest token accepted: 16 characters (e.g. `openssl rand -hex 16` gives 32).
pub const MIN_TOKEN_LEN: usize = 16;
/// Longest token accepted (it travels in a header and a cookie).
pub const MAX_TOKEN_LEN: usize = 256;

/// A host as a `Host` header or `--allow-host` names it.
#[derive(Debug, Clone, PartialEq, Eq)]
enum HostName {
    Ip(IpAddr),
    /// A DNS name, lower case.
    Name(String),
}

/// One name the station answers to; without a port, at the station's own port.
#[derive(Debug, Clone, PartialEq, Eq)]
pub struct AllowedHost {
    host: HostName,
    port: Option<u16>,
}

/// Split `host[:port]` / `[v6][:port]` (a `Host` header, or the authority of
/// an `Origin`). `None` when it is not one.
fn parse_authority(text: &str) -> Option<(HostName, Option<u16>)> {
    let (host, port) = if let Some(rest) = text.strip_prefix('[') {
        let (v6, after) = rest.split_once(']')?;
        let ip: std::net::Ipv6Addr = v6.parse().ok()?;
        let port = match after {
            "" => None,
            p => Some(p.strip_prefix(':')?),
        };
        (HostName::Ip(IpAddr::V6(ip)), port)
    } else {
        let (host, port) = match text.rsplit_once(':') {
            Some((h, p)) => (h, Some(p)),
            None => (text, None),
        };
        let valid_name = !host.is_empty()
            && host
                .bytes()
                .all(|b| b.is_ascii_alphanumeric() || b == b'-' || b == b'.');
        if !valid_name {
            return None;
        }
        match host.parse::<std::net::Ipv4Addr>() {
            Ok(ip) => (HostName::Ip(IpAddr::V4(ip)), port),
            Err(_) => (HostName::Name(host.to_ascii_lowercase()), port),
        }
    };
    let port = match port {
        None => None,
        Some(p) if !p.is_empty() && p.bytes().all(|b| b.is_ascii_digit()) => Some(p.parse().ok()?),
        Some(_) => return None,
    };
    Some((host, port))
}

/// Parse one `--allow-host` value: `NAME`, `NAME:PORT`, an IP address, `[V6]:PORT`.
pub fn parse_allowed_host(text: &str) -> Result<AllowedHost, StationError> {
    let bad = |reason: &str| StationError::AllowHost {
        name: text.to_string(),
        reason: reason.to_string(),
    };
    // A bare IPv6 address (`::1`) has colons of its own.
    if let Ok(ip) = text.parse::<std::net::Ipv6Addr>() {
        return Ok(AllowedHost {
            host: HostName::Ip(IpAddr::V6(ip)),
            port: None,
        });
    }
    if text.contains("://") || text.contains('/') {
        return Err(bad(
            "give a host name, not a URL (e.g. `vessel.local` or `vessel.local:8443`)",
        ));
    }
    match parse_authority(text) {
        Some((host, port)) => Ok(AllowedHost { host, port }),
        None => Err(bad(
            "not a host name (letters, digits, `-` and `.`), an IP address, or either with `:PORT`",
        )),
    }
}

/// Check a token's form: [`MIN_TOKEN_LEN`]..=[`MAX_TOKEN_LEN`] characters
/// of `A-Z a-z 0-9 - . _ ~ + / =` (hex, base64 and URL-safe base64 fit), so
/// it travels unchanged in a header, a cookie and a URL.
pub fn check_token(token: &str) -> Result<(), StationError> {
    let len = token.chars().count();
    if !(MIN_TOKEN_LEN..=MAX_TOKEN_LEN).contains(&len) {
        return Err(StationError::Token(format!(
            "it has {len} characters; give {MIN_TOKEN_LEN} to {MAX_TOKEN_LEN} (e.g. `openssl rand -hex 16`)"
        )));
    }
    if let Some(c) = token
        .chars()
        .find(|c| !(c.is_ascii_alphanumeric() || "-._~+/=".contains(*c)))
    {
        return Err(StationError::Token(format!(
            "{c:?} is not allowed; use letters, digits and `-._~+/=` (e.g. `openssl rand -hex 16`)"
        )));
    }
    Ok(())
}

/// A checked token ([`check_token`]); its `Debug` does not show it.
#[derive(Clone, PartialEq, Eq)]
pub struct Token(String);

impl Token {
    /// Check `text` and keep it.
    pub fn new(text: &str) -> Result<Token, StationError> {
        check_token(text)?;
        Ok(Token(text.to_string()))
    }
}

impl std::fmt::Debug for Token {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.write_str("Token(…)")
    }
}

/// What [`Access::decide`] says about a request.
#[derive(Debug, Clone, PartialEq, Eq)]
pub enum Decision {
    /// Serve it.
    Pass,
    /// The page URL carried the right `?token=`: keep it in a cookie and
    /// send the browser to the same page without it.
    SetCookie { location: String, cookie: String },
    /// Refuse with this status and message.
    Refuse { status: StatusCode, message: String },
}

/// The station's access rules, for the address it is bound to.
#[derive(Debug)]
pub struct Access {
    tls: bool,
    port: u16,
    names: Vec<AllowedHost>,
    any_ip: bool,
    token: Option<Token>,
    cookie: String,
}

impl Access {
    /// Rules for a server bound to `bound` (its real port, after binding).
    pub fn new(
        bound: SocketAddr,
        tls: bool,
        allowed: &[AllowedHost],
        token: Option<Token>,
    ) -> Access {
        let own = |host| AllowedHost { host, port: None };
        let mut names = vec![
            own(HostName::Name("localhost".into())),
            own(HostName::Ip(IpAddr::V4(std::net::Ipv4Addr::LOCALHOST))),
            own(HostName::Ip(IpAddr::V6(std::net::Ipv6Addr::LOCALHOST))),
        ];
        if !bound.ip().is_unspecified() {
            names.push(own(HostName::Ip(bound.ip())));
        }
        names.extend(allowed.iter().cloned());
        let mut seen = Vec::new();
        names.retain(|n| {
            let new = !seen.contains(n);
            seen.push(n.clone());
            new
        });
        Access {
            tls,
            port: bound.port(),
            names,
            any_ip: bound.ip().is_unspecified(),
            token,
            // Cookies are shared by every port of a host: one name per station port.
            cookie: format!("shoal_station_token_{}", bound.port()),
        }
    }

    fn scheme(&self) -> &'static str {
        if self.tls {
            "https"
        } else {
            "http"
        }
    }

    /// The names this station answers to, for messages.
    fn names_text(&self) -> String {
        let mut out: Vec<String> = self
            .names
            .iter()
            .map(|a| {
                let host = match &a.host {
                    HostName::Ip(IpAddr::V6(ip)) => format!("[{ip}]"),
                    HostName::Ip(ip) => ip.to_string(),
                    HostName::Name(n) => n.clone(),
                };
                format!("{host}:{}", a.port.unwrap_or(self.port))
            })
            .collect();
        if self.any_ip {
            out.push(format!("any IP address:{}", self.port));
        }
        out.join(", ")
    }

    /// Whether `authority` (with `default_port` when it has none) is one of ours.
    fn allows(&self, authority: &str, default_port: u16) -> bool {
        let Some((host, port)) = parse_authority(authority) else {
            return false;
        };
        let port = port.unwrap_or(default_port);
        if self.any_ip && matches!(host, HostName::Ip(_)) && port == self.port {
            return true;
        }
        self.names
            .iter()
            .any(|a| a.host == host && a.port.unwrap_or(self.port) == port)
    }

    fn default_port(&self) -> u16 {
        if self.tls {
            443
        } else {
            80
        }
    }

    /// The decision for a request to `uri` with `headers`.
    pub fn decide(&self, uri: &Uri, headers: &HeaderMap) -> Decision {
        let refuse = |status, message: String| Decision::Refuse { status, message };
        let mut hosts = headers.get_all(HOST).iter();
        let host = match (hosts.next().map(HeaderValue::to_str), hosts.next()) {
            (Some(Ok(h)), None) => h,
            _ => {
                return refuse(
                    StatusCode::MISDIRECTED_REQUEST,
                    format!(
                        "this station needs exactly one Host header naming it ({})\n",
                        self.names_text()
                    ),
                )
            }
        };
        if !self.allows(host, self.default_port()) {
            return refuse(
                StatusCode::MISDIRECTED_REQUEST,
                format!(
                    "Host {host:?} is not a name of this station ({}). A foreign Host is how DNS \
                     rebinding reaches a local page, so it is refused; start the station with \
                     `--allow-host NAME` to accept another name.\n",
                    self.names_text()
                ),
            );
        }
        if let Some(origin) = headers.get(ORIGIN) {
            if !self.same_origin(origin, host) {
                let origin = String::from_utf8_lossy(origin.as_bytes());
                return refuse(
                    StatusCode::FORBIDDEN,
                    format!(
                        "cross-origin request from {origin:?} refused: the station's page only talks \
                         to its own origin ({}://{host})\n",
                        self.scheme()
                    ),
                );
            }
        }
        match &self.token {
            None => Decision::Pass,
            Some(Token(token)) => self.decide_token(token, uri, headers),
        }
    }

    /// `Origin` is `scheme://authority` of this very request's `Host`.
    fn same_origin(&self, origin: &HeaderValue, host: &str) -> bool {
        let Ok(origin) = origin.to_str() else {
            return false;
        };
        let Some(authority) = origin
            .strip_prefix(self.scheme())
            .and_then(|r| r.strip_prefix("://"))
        else {
            return false; // another scheme, or "null" (sandboxed frames, files)
        };
        let default_port = self.default_port();
        match (parse_authority(authority), parse_authority(host)) {
            (Some((oh, op)), Some((hh, hp))) => {
                oh == hh && op.unwrap_or(default_port) == hp.unwrap_or(default_port)
            }
            _ => false,
        }
    }

    fn decide_token(&self, token: &str, uri: &Uri, headers: &HeaderMap) -> Decision {
        let matches = |given: &[u8]| bool::from(given.ct_eq(token.as_bytes()));
        let page = matches!(uri.path(), "/" | "/index.html");
        if let Some(given) = page.then(|| query_token(uri)).flatten() {
            if !matches(&given) {
                return self.unauthorized("the token in the URL is not this station's");
            }
            let secure = if self.tls { "; Secure" } else { "" };
            return Decision::SetCookie {
                location: uri.path().to_string(),
                cookie: format!(
                    "{}={token}; Path=/; HttpOnly; SameSite=Strict{secure}",
                    self.cookie
                ),
            };
        }
        let bearer = headers
            .get_all(AUTHORIZATION)
            .iter()
            .filter_map(|v| v.as_bytes().strip_prefix(b"Bearer "))
            .any(|t| matches(t.trim_ascii()));
        let cookie = headers
            .get_all(COOKIE)
            .iter()
            .flat_map(|v| v.as_bytes().split(|&b| b == b';'))
            .filter_map(|pair| {
                let pair = pair.trim_ascii();
                pair.strip_prefix(self.cookie.as_bytes())?
                    .strip_prefix(b"=")
            })
            .any(matches);
        if bearer || cookie {
            Decision::Pass
        } else if headers.contains_key(AUTHORIZATION) {
            self.unauthorized("the Authorization header does not carry this station's token")
        } else {
            self.unauthorized("this station needs its token")
        }
    }

    fn unauthorized(&self, why: &str) -> Decision {
        Decision::Refuse {
            status: StatusCode::UNAUTHORIZED,
            message: format!(
                "{why}: open {}://HOST:{}/?token=TOKEN once in the browser (it then keeps a cookie), \
                 or send `Authorization: Bearer TOKEN`\n",
                self.scheme(),
                self.port
            ),
        }
    }
}

/// The percent-decoded `token` of a URL's query (`+` is kept as `+`).
fn query_token(uri: &Uri) -> Option<Vec<u8>> {
    uri.query()?
        .split('&')
        .find_map(|kv| kv.strip_prefix("token="))
        .map(|t| percent_encoding::percent_decode_str(t).collect())
}

/// Headers every response carries: nothing cached (snapshots and the page
/// change), no type sniffing, no referrer (a URL may hold a token), no framing.
fn harden(headers: &mut HeaderMap) {
    const FIXED: [(HeaderName, &str); 4] = [
        (CACHE_CONTROL, "no-store"),
        (HeaderName::from_static("x-content-type-options"), "nosniff"),
        (HeaderName::from_static("referrer-policy"), "no-referrer"),
        (HeaderName::from_static("x-frame-options"), "DENY"),
    ];
    for (name, value) in FIXED {
        headers.insert(name, HeaderValue::from_static(value));
    }
}

/// The axum middleware in front of every route.
pub async fn guard(State(access): State<Arc<Access>>, req: Request, next: Next) -> Response {
    let mut response = match access.decide(req.uri(), req.headers()) {
        Decision::Pass => next.run(req).await,
        Decision::SetCookie { location, cookie } => {
            match (
                HeaderValue::from_str(&location),
                HeaderValue::from_str(&cookie),
            ) {
                (Ok(location), Ok(cookie)) => (
                    StatusCode::SEE_OTHER,
                    [(LOCATION, location), (SET_COOKIE, cookie)],
                )
                    .into_response(),
                _ => StatusCode::BAD_REQUEST.into_response(),
            }
        }
        Decision::Refuse { status, message } => {
            tracing::debug!("station: refused ({status}): {}", message.trim_end());
            let mut r = (
                status,
                [(CONTENT_TYPE, "text/plain; charset=utf-8")],
                message,
            )
                .into_response();
            if status == StatusCode::UNAUTHORIZED {
                r.headers_mut().insert(
                    WWW_AUTHENTICATE,
                    HeaderValue::from_static("Bearer realm=\"shoal station\""),
                );
            }
            r
        }
    };
    harden(response.headers_mut());
    response
}

#[cfg(test)]
mod tests {
    use super::*;

    const TOKEN: &str = "0123456789abcdef-token";

    fn access(bind: &str, allowed: &[&str], token: Option<&str>) -> Access {
        let allowed: Vec<_> = allowed
            .iter()
            .map(|a| parse_allowed_host(a).unwrap())
            .collect();
        let token = token.map(|t| Token::new(t).unwrap());
        Access::new(bind.parse().unwrap(), false, &allowed, token)
    }

    fn headers(pairs: &[(&'static str, &str)]) -> HeaderMap {
        let mut h = HeaderMap::new();
        for (k, v) in pairs {
            h.append(*k, HeaderValue::from_str(v).unwrap());
        }
        h
    }

    fn status(d: &Decision) -> Option<StatusCode> {
        match d {
            Decision::Refuse { status, .. } => Some(*status),
            _ => None,
        }
    }

    fn host_status(a: &Access, host: &str) -> Option<StatusCode> {
        status(&a.decide(&Uri::from_static("/"), &headers(&[("host", host)])))
    }

    #[test]
    fn loopback_station_answers_only_to_its_own_names_and_port() {
        let a = access("127.0.0.1:8080", &[], None);
        for good in [
            "127.0.0.1:8080",
            "localhost:8080",
            "LOCALHOST:8080",
            "[::1]:8080",
            "[0:0::1]:8080",
        ] {
            assert_eq!(host_status(&a, good), None, "{good}");
        }
        for bad in [
            "evil.example:8080",
            "evil.example",
            "localhost:8081",
            "localhost",
            "127.0.0.1",
            "localhost.:8080",
            "127.0.0.2:8080",
            "2130706433:8080",
            "localhost:8080:8080",
            "[::1",
            "",
        ] {
            assert_eq!(
                host_status(&a, bad),
                Some(StatusCode::MISDIRECTED_REQUEST),
                "{bad:?}"
            );
        }
        // No Host at all, or two.
        let none = a.decide(&Uri::from_static("/"), &HeaderMap::new());
        assert_eq!(status(&none), Some(StatusCode::MISDIRECTED_REQUEST));
        let two = headers(&[("host", "localhost:8080"), ("host", "evil.example:8080")]);
        assert_eq!(
            status(&a.decide(&Uri::from_static("/"), &two)),
            Some(StatusCode::MISDIRECTED_REQUEST)
        );
    }

    #[test]
    fn allowed_names_and_the_bound_address_are_accepted() {
        let a = access(
            "192.0.2.7:8080",
            &["vessel.local", "proxy.example:443", "::2"],
            Some(TOKEN),
        );
        let auth = format!("Bearer {TOKEN}");
        let ok = |host: &str| {
            status(&a.decide(
                &Uri::from_static("/"),
                &headers(&[("host", host), ("authorization", &auth)]),
            ))
        };
        for good in [
            "192.0.2.7:8080",
            "vessel.local:8080",
            "Vessel.Local:8080",
            "proxy.example:443",
            "[::2]:8080",
        ] {
            assert_eq!(ok(good), None, "{good}");
        }
        for bad in ["proxy.example:8080", "192.0.2.8:8080", "vessel.local:443"] {
            assert_eq!(ok(bad), Some(StatusCode::MISDIRECTED_REQUEST), "{bad}");
        }
    }

    #[test]
    fn station_on_every_interface_answers_to_ip_literals_but_not_names() {
        let a = access("0.0.0.0:8080", &[], None);
        assert_eq!(host_status(&a, "10.1.2.3:8080"), None);
        assert_eq!(host_status(&a, "[fe80::1]:8080"), None);
        assert_eq!(
            host_status(&a, "10.1.2.3:8081"),
            Some(StatusCode::MISDIRECTED_REQUEST)
        );
        assert_eq!(
            host_status(&a, "evil.example:8080"),
            Some(StatusCode::MISDIRECTED_REQUEST)
        );
        assert_eq!(host_status(&a, "0.0.0.0:8080"), None);
    }

    #[test]
    fn cross_origin_requests_are_refused() {
        let a = access("127.0.0.1:8080", &[], None);
        let with_origin = |origin: &str| {
            status(&a.decide(
                &Uri::from_static("/events"),
                &headers(&[("host", "127.0.0.1:8080"), ("origin", origin)]),
            ))
        };
        assert_eq!(with_origin("http://127.0.0.1:8080"), None);
        for bad in [
            "http://evil.example",
            "http://evil.example:8080",
            "https://127.0.0.1:8080",
            "http://localhost:8080",
            "http://127.0.0.1:8081",
            "null",
            "http://127.0.0.1:8080.evil.example",
        ] {
            assert_eq!(with_origin(bad), Some(StatusCode::FORBIDDEN), "{bad}");
        }
    }

    #[test]
    fn token_is_needed_from_header_cookie_or_page_url() {
        let a = access("127.0.0.1:8080", &[], Some(TOKEN));
        let decide = |uri: &str, extra: &[(&'static str, &str)]| {
            let mut h = vec![("host", "127.0.0.1:8080")];
            h.extend_from_slice(extra);
            a.decide(&uri.parse().unwrap(), &headers(&h))
        };
        let bearer = format!("Bearer {TOKEN}");
        let cookie = format!("other=1; shoal_station_token_8080={TOKEN}");
        assert_eq!(
            status(&decide("/events", &[])),
            Some(StatusCode::UNAUTHORIZED)
        );
        assert_eq!(
            status(&decide(
                "/events",
                &[("authorization", "Bearer nope-nope-nope-nope")]
            )),
            Some(StatusCode::UNAUTHORIZED)
        );
        assert_eq!(
            status(&decide(
                "/events",
                &[("authorization", &format!("Basic {TOKEN}"))]
            )),
            Some(StatusCode::UNAUTHORIZED)
        );
        assert_eq!(
            decide("/events", &[("authorization", &bearer)]),
            Decision::Pass
        );
        assert_eq!(
            decide("/api/snapshot", &[("cookie", &cookie)]),
            Decision::Pass
        );
        // Another station's cookie (another port) is not ours.
        let other = format!("shoal_station_token_9090={TOKEN}");
        assert_eq!(
            status(&decide("/", &[("cookie", &other)])),
            Some(StatusCode::UNAUTHORIZED)
        );
        // A token prefix is not the token.
        let prefix = format!("Bearer {}", &TOKEN[..TOKEN.len() - 1]);
        assert_eq!(
            status(&decide("/", &[("authorization", &prefix)])),
            Some(StatusCode::UNAUTHORIZED)
        );
        // The page URL: right token → cookie and a redirect without it; wrong → 401.
        match decide(&format!("/?token={TOKEN}"), &[]) {
            Decision::SetCookie { location, cookie } => {
                assert_eq!(location, "/");
                assert_eq!(
                    cookie,
                    format!("shoal_station_token_8080={TOKEN}; Path=/; HttpOnly; SameSite=Strict")
                );
            }
            d => panic!("{d:?}"),
        }
        assert_eq!(
            status(&decide("/?token=wrong-wrong-wrong-wrong", &[])),
            Some(StatusCode::UNAUTHORIZED)
        );
        // Percent-encoded in the URL.
        let encoded = format!("/index.html?x=1&token={}", TOKEN.replace('-', "%2D"));
        assert!(
            matches!(decide(&encoded, &[]), Decision::SetCookie { location, .. } if location == "/index.html")
        );
        // Only the page takes a token in its URL.
        assert_eq!(
            status(&decide(&format!("/api/snapshot?token={TOKEN}"), &[])),
            Some(StatusCode::UNAUTHORIZED)
        );
        // The Host check comes first: a foreign Host with the right token is still refused.
        let foreign = a.decide(
            &Uri::from_static("/"),
            &headers(&[("host", "evil.example:8080"), ("authorization", &bearer)]),
        );
        assert_eq!(status(&foreign), Some(StatusCode::MISDIRECTED_REQUEST));
    }

    #[test]
    fn tokens_and_allowed_hosts_are_checked() {
        assert!(check_token("0123456789abcdef").is_ok());
        assert!(check_token("short").unwrap_err().to_string().contains("16"));
        assert!(check_token("0123456789abcdef;x").is_err());
        assert!(check_token("0123456789 abcdef").is_err());
        assert!(check_token(&"a".repeat(257)).is_err());
        assert!(parse_allowed_host("vessel.local").is_ok());
        assert!(parse_allowed_host("[fe80::1]:8443").is_ok());
        assert!(parse_allowed_host("http://vessel.local/").is_err());
        assert!(parse_allowed_host("vessel local").is_err());
        assert!(parse_allowed_host("vessel.local:99999").is_err());
        assert!(parse_allowed_host("").is_err());
    }
}
