//! HTTPS for a station reached beyond loopback: a certificate chain and its
//! private key, both PEM files, loaded once at start into a rustls server
//! configuration (ring provider, as Zenoh's TLS; TLS 1.2 and 1.3).
//!
//! Every failure names the file and what is wrong with it (unreadable, no
//! PEM certificate or key in it, a key that does not belong to the
//! certificate), so a mistyped path is one clear line, never a panic.

use crate::StationError;
use rustls::pki_types::pem::PemObject;
use rustls::pki_types::{CertificateDer, PrivateKeyDer};
use std::path::{Path, PathBuf};
use std::sync::Arc;

/// The PEM files of the station's HTTPS certificate.
#[derive(Debug, Clone, PartialEq, Eq)]
pub struct TlsFiles {
    /// Certificate chain, leaf first (PEM `CERTIFICATE` blocks).
    pub cert: PathBuf,
    /// The leaf's private key (PEM: PKCS#8, PKCS#1 or SEC1).
    pub key: PathBuf,
}

fn read(what: &'static str, path: &Path) -> Result<Vec<u8>, StationError> {
    std::fs::read(path).map_err(|source| StationError::TlsRead {
        what,
        path: path.to_path_buf(),
        source,
    })
}

fn pem_error(what: &'static str, path: &Path, reason: impl ToString) -> StationError {
    StationError::TlsPem {
        what,
        path: path.to_path_buf(),
        reason: reason.to_string(),
    }
}

/// Load `files` into a server configuration that offers HTTP/1.1 (ALPN).
pub fn server_config(files: &TlsFiles) -> Result<Arc<rustls::ServerConfig>, StationError> {
    let cert_pem = read("certificate", &files.cert)?;
    let chain = CertificateDer::pem_slice_iter(&cert_pem)
        .collect::<Result<Vec<_>, _>>()
        .map_err(|e| pem_error("certificate", &files.cert, e))?;
    if chain.is_empty() {
        return Err(pem_error(
            "certificate",
            &files.cert,
            "no `BEGIN CERTIFICATE` block in it",
        ));
    }
    let key_pem = read("private key", &files.key)?;
    let key = PrivateKeyDer::from_pem_slice(&key_pem).map_err(|e| {
        let reason = match e {
            rustls::pki_types::pem::Error::NoItemsFound => {
                "no `BEGIN PRIVATE KEY` (PKCS#8), `BEGIN RSA PRIVATE KEY` or `BEGIN EC PRIVATE KEY` block in it"
                    .to_string()
            }
            other => other.to_string(),
        };
        pem_error("private key", &files.key, reason)
    })?;
    let provider = Arc::new(rustls::crypto::ring::default_provider());
    let mut config = rustls::ServerConfig::builder_with_provider(provider)
        .with_safe_default_protocol_versions()
        .map_err(|e| StationError::TlsKey {
            cert: files.cert.clone(),
            key: files.key.clone(),
            reason: e.to_string(),
        })?
        .with_no_client_auth()
        // Checks that the key is valid and is the certificate's own.
        .with_single_cert(chain, key)
        .map_err(|e| StationError::TlsKey {
            cert: files.cert.clone(),
            key: files.key.clone(),
            reason: match e {
                rustls::Error::InconsistentKeys(rustls::InconsistentKeys::KeyMismatch) => {
                    "the key is another certificate's (its public key is not the certificate's)"
                        .to_string()
                }
                other => other.to_string(),
            },
        })?;
    config.alpn_protocols = vec![b"http/1.1".to_vec()];
    Ok(Arc::new(config))
}

#[cfg(test)]
mod tests {
    use super::*;

    fn write(dir: &Path, name: &str, text: &str) -> PathBuf {
        let p = dir.join(name);
        std::fs::write(&p, text).unwrap();
        p
    }

    fn temp_dir(tag: &str) -> PathBuf {
        let d =
            std::env::temp_dir().join(format!("shoal-station-tls-{tag}-{}", std::process::id()));
        std::fs::create_dir_all(&d).unwrap();
        d
    }

    #[test]
    fn loads_a_matching_certificate_and_key() {
        let d = temp_dir("ok");
        let c = rcgen::generate_simple_self_signed(vec!["localhost".into()]).unwrap();
        let files = TlsFiles {
            cert: write(&d, "cert.pem", &c.cert.pem()),
            key: write(&d, "key.pem", &c.key_pair.serialize_pem()),
        };
        let cfg = server_config(&files).unwrap();
        assert_eq!(cfg.alpn_protocols, vec![b"http/1.1".to_vec()]);
        std::fs::remove_dir_all(d).unwrap();
    }

    #[test]
    fn missing_file_names_its_path() {
        let files = TlsFiles {
            cert: "/nonexistent/shoal/cert.pem".into(),
            key: "/nonexistent/shoal/key.pem".into(),
        };
        let err = server_config(&files).unwrap_err();
        assert!(
            matches!(
                err,
                StationError::TlsRead {
                    what: "certificate",
                    ..
                }
            ),
            "{err:?}"
        );
        assert!(
            err.to_string().contains("/nonexistent/shoal/cert.pem"),
            "{err}"
        );
    }

    #[test]
    fn key_of_another_certificate_is_refused() {
        let d = temp_dir("mismatch");
        let a = rcgen::generate_simple_self_signed(vec!["localhost".into()]).unwrap();
        let b = rcgen::generate_simple_self_signed(vec!["localhost".into()]).unwrap();
        let files = TlsFiles {
            cert: write(&d, "cert.pem", &a.cert.pem()),
            key: write(&d, "key.pem", &b.key_pair.serialize_pem()),
        };
        let err = server_config(&files).unwrap_err();
        assert!(matches!(err, StationError::TlsKey { .. }), "{err:?}");
        assert!(err.to_string().contains("key.pem"), "{err}");
        assert!(err.to_string().contains("another certificate's"), "{err}");
        std::fs::remove_dir_all(d).unwrap();
    }

    #[test]
    fn files_swapped_or_empty_say_what_is_missing() {
        let d = temp_dir("swapped");
        let c = rcgen::generate_simple_self_signed(vec!["localhost".into()]).unwrap();
        let cert = write(&d, "cert.pem", &c.cert.pem());
        let key = write(&d, "key.pem", &c.key_pair.serialize_pem());
        // Key given as the certificate.
        let err = server_config(&TlsFiles {
            cert: key.clone(),
            key: cert.clone(),
        })
        .unwrap_err();
        assert!(
            matches!(
                err,
                StationError::TlsPem {
                    what: "certificate",
                    ..
                }
            ),
            "{err:?}"
        );
        // A certificate given as the key.
        let err = server_config(&TlsFiles {
            cert: cert.clone(),
            key: cert.clone(),
        })
        .unwrap_err();
        assert!(
            matches!(
                err,
                StationError::TlsPem {
                    what: "private key",
                    ..
                }
            ),
            "{err:?}"
        );
        assert!(err.to_string().contains("PRIVATE KEY"), "{err}");
        std::fs::remove_dir_all(d).unwrap();
    }
}
