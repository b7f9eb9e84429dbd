//! Exposure: TLS on the listeners (rustls, ring provider), client
//! certificates for vehicles on the ingest listener (mTLS), bearer tokens
//! with two roles for the HTTP API, and the rule that the daemon does not
//! start on a non-loopback address without them unless told `--insecure`.
//!
//! - **TLS** (`[tls] cert`, `key`: PEM files) covers both listeners: the
//!   MCAP ingest (TLS then the same byte stream) and the HTTP API (HTTPS).
//! - **mTLS** (`[tls] client_ca`): the ingest listener then requires a client
//!   certificate signed by that CA; a connection without one fails its
//!   handshake and never reaches the decoder.
//! - **Tokens** (`[auth] read_tokens_file`, `ingest_tokens_file`: one token
//!   per line, `#` comments): when any is configured, every HTTP route but
//!   `/healthz` and the dashboard's static files needs `Authorization:
//!   Bearer <token>` (or `?access_token=`, RFC 6750 §2.3, for the browser's
//!   `EventSource`, which cannot set headers). The read role reads the API,
//!   the event stream and `/metrics`; the ingest role uploads runs
//!   (`POST /v1/runs`), and nothing else. Tokens are kept as SHA-256 digests and compared in
//!   constant time (`subtle`), all of them each time; they are never logged.
//! - **Exposure rule**: an ingest listener off loopback needs TLS and client
//!   certificates; an HTTP listener off loopback needs TLS and read tokens.
//!   Otherwise `serve` refuses to start, naming TLS and `--insecure`.

use std::net::SocketAddr;
use std::path::{Path, PathBuf};
use std::sync::Arc;

use rustls::pki_types::pem::PemObject as _;
use rustls::pki_types::{CertificateDer, PrivateKeyDer};
use sha2::{Digest as _, Sha256};
use subtle::ConstantTimeEq as _;

use super::config::Config;
use super::ServeError;

/// A token's role.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum Role {
    /// Reads the API, the event stream, the metrics.
    Read,
    /// Posts runs.
    Ingest,
}

/// The configured bearer tokens (SHA-256 digests).
#[derive(Clone, Default)]
pub struct Tokens {
    read: Vec<[u8; 32]>,
    ingest: Vec<[u8; 32]>,
}

impl std::fmt::Debug for Tokens {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        // Never the digests, let alone the tokens.
        f.debug_struct("Tokens")
            .field("read", &self.read.len())
            .field("ingest", &self.ingest.len())
            .finish()
    }
}

/// A token file other users can read gives them its role (the docs' recipe
/// wrote them 0644 and the daemon said nothing; a helper's trial).
fn warn_if_shared(path: &std::path::Path) {
    #[cfg(unix)]
    {
        use std::os::unix::fs::PermissionsExt as _;
        if let Ok(meta) = std::fs::metadata(path) {
            let mode = meta.permissions().mode() & 0o777;
            if mode & 0o077 != 0 {
                tracing::warn!(
                    file = %path.display(),
                    mode = format!("{mode:04o}"),
                    "this token file can be read by other users of this machine, who then have \
                     its role: `chmod 600` it"
                );
            }
        }
    }
    #[cfg(not(unix))]
    let _ = path;
}

/// A token shorter than this is warned of at start.
const MIN_TOKEN_CHARS: usize = 16;

fn digest(token: &str) -> [u8; 32] {
    Sha256::digest(token.as_bytes()).into()
}

impl Tokens {
    /// Reads the token files of `config` (none configured: auth is off).
    pub fn load(config: &Config) -> Result<Self, ServeError> {
        let read = |path: &Option<PathBuf>| -> Result<Vec<[u8; 32]>, ServeError> {
            let Some(path) = path else {
                return Ok(Vec::new());
            };
            let text = std::fs::read_to_string(path).map_err(|e| ServeError::Invalid {
                key: "auth".into(),
                reason: format!("{}: cannot read it: {e}", path.display()),
            })?;
            let mut tokens = Vec::new();
            for (i, line) in text.lines().enumerate() {
                let token = line.trim();
                if token.is_empty() || token.starts_with('#') {
                    continue;
                }
                // what an operator gets wrong (a helper's trial): the header's
                // word copied in made the real token fail with 401
                if token
                    .get(..7)
                    .is_some_and(|p| p.eq_ignore_ascii_case("bearer "))
                {
                    return Err(ServeError::Invalid {
                        key: "auth".into(),
                        reason: format!(
                            "{}:{}: the line starts with `Bearer `: write the token alone (clients \
                             send it as `Authorization: Bearer <token>`)",
                            path.display(),
                            i + 1
                        ),
                    });
                }
                if token.len() < MIN_TOKEN_CHARS {
                    tracing::warn!(
                        file = %path.display(),
                        line = i + 1,
                        "a token of {} characters is easy to guess: use at least {MIN_TOKEN_CHARS} \
                         random ones (`openssl rand -hex 32`)",
                        token.len()
                    );
                }
                tokens.push(digest(token));
            }
            if tokens.is_empty() {
                return Err(ServeError::Invalid {
                    key: "auth".into(),
                    reason: format!("{}: no token in the file", path.display()),
                });
            }
            warn_if_shared(path);
            Ok(tokens)
        };
        let tokens = Self {
            read: read(&config.auth.read_tokens_file)?,
            ingest: read(&config.auth.ingest_tokens_file)?,
        };
        // One token in both files had the read role alone, and its uploads
        // were refused as a read token's (a helper's trial).
        if tokens.read.iter().any(|t| tokens.ingest.contains(t)) {
            return Err(ServeError::Invalid {
                key: "auth".into(),
                reason: "a token is in both the read_tokens_file and the ingest_tokens_file: give \
                         each token one role (a client that reads and uploads uses two)"
                    .into(),
            });
        }
        Ok(tokens)
    }

    /// Tokens from lists (tests).
    #[must_use]
    pub fn from_lists(read: &[&str], ingest: &[&str]) -> Self {
        Self {
            read: read.iter().map(|t| digest(t)).collect(),
            ingest: ingest.iter().map(|t| digest(t)).collect(),
        }
    }

    /// Whether authentication is on.
    #[must_use]
    pub fn enabled(&self) -> bool {
        !(self.read.is_empty() && self.ingest.is_empty())
    }

    /// The role of `token`, comparing against every configured digest in
    /// constant time (the time does not depend on which one matches).
    #[must_use]
    pub fn role(&self, token: &str) -> Option<Role> {
        let d = digest(token);
        let mut read = subtle::Choice::from(0);
        for t in &self.read {
            read |= t.ct_eq(&d);
        }
        let mut ingest = subtle::Choice::from(0);
        for t in &self.ingest {
            ingest |= t.ct_eq(&d);
        }
        if bool::from(read) {
            Some(Role::Read)
        } else if bool::from(ingest) {
            Some(Role::Ingest)
        } else {
            None
        }
    }
}

/// The certificates of a PEM file, at least one; else why not, in words
/// (the TLS listeners' chain, and NATS's CA and client certificate).
pub(crate) fn pem_certificates(path: &Path) -> Result<Vec<CertificateDer<'static>>, String> {
    let certs: Vec<CertificateDer<'static>> = CertificateDer::pem_file_iter(path)
        .map_err(|e| pem_problem(&e))?
        .collect::<Result<_, _>>()
        .map_err(|e| format!("not a PEM certificate: {e}"))?;
    if certs.is_empty() {
        return Err("no certificate in the file".into());
    }
    Ok(certs)
}

/// A PEM reading error in words: a missing or unreadable file as such, not
/// as a file that is not PEM (a helper's trial: a missing key file read
/// "not a PEM private key: I/O error: No such file or directory").
pub(crate) fn pem_problem(e: &rustls::pki_types::pem::Error) -> String {
    match e {
        rustls::pki_types::pem::Error::Io(io) => format!("cannot read it: {io}"),
        rustls::pki_types::pem::Error::NoItemsFound => {
            "no PEM item of that kind in the file".into()
        }
        other => format!("not PEM: {other:?}"),
    }
}

/// How long before its end a server certificate is warned of at start.
pub const CERT_EXPIRY_WARNING_DAYS: i64 = 14;

/// What is wrong with a server certificate's validity at `now` (Unix
/// seconds): not yet valid, expired, or within
/// [`CERT_EXPIRY_WARNING_DAYS`] of its end; `None` when it is fine or
/// cannot be read as X.509 (rustls then says why, if it matters).
///
/// Before, a daemon started with an expired certificate said nothing: every
/// client's handshake failed, and the operator read only
/// `errors_total{kind="https_handshake"}` climbing.
#[must_use]
pub fn validity_problem(der: &CertificateDer<'_>, now: i64) -> Option<String> {
    let (_, cert) = x509_parser::parse_x509_certificate(der.as_ref()).ok()?;
    let validity = cert.validity();
    let (start, end) = (validity.not_before, validity.not_after);
    let days = |s: i64| s as f64 / 86_400.0;
    if now < start.timestamp() {
        return Some(format!(
            "is not valid until {start} (in {:.1} days): clients will refuse it",
            days(start.timestamp() - now)
        ));
    }
    let left = end.timestamp() - now;
    if left < 0 {
        return Some(format!(
            "expired on {end} ({:.1} days ago): clients will refuse it; renew it and restart",
            days(-left)
        ));
    }
    (left < CERT_EXPIRY_WARNING_DAYS * 86_400).then(|| {
        format!(
            "expires on {end} (in {:.1} days); renew it and restart",
            days(left)
        )
    })
}

fn tls_error(path: &Path, what: &str, e: impl std::fmt::Display) -> ServeError {
    ServeError::Invalid {
        key: "tls".into(),
        reason: format!("{}: {what}: {e}", path.display()),
    }
}

/// The TLS server configurations of the two listeners.
#[derive(Debug, Clone)]
pub struct TlsConfigs {
    /// The ingest listener's (requires client certificates when `client_ca` is set).
    pub ingest: Arc<rustls::ServerConfig>,
    /// The HTTP listener's (ALPN h2, http/1.1).
    pub http: Arc<rustls::ServerConfig>,
}

/// The TLS server configurations, or `None` without `[tls]`.
pub fn server_configs(config: &Config) -> Result<Option<TlsConfigs>, ServeError> {
    let tls = &config.tls;
    let (Some(cert), Some(key)) = (&tls.cert, &tls.key) else {
        return Ok(None);
    };
    let certs = pem_certificates(cert).map_err(|why| tls_error(cert, "certificate chain", why))?;
    let now = std::time::SystemTime::now()
        .duration_since(std::time::UNIX_EPOCH)
        .map_or(0, |d| i64::try_from(d.as_secs()).unwrap_or(i64::MAX));
    if let Some(problem) = validity_problem(&certs[0], now) {
        // Started anyway: clients then say why they refuse (an operator
        // renewing the certificate needs the daemon up to test it).
        tracing::warn!("{}: the server certificate {problem}", cert.display());
    }
    let key_der = PrivateKeyDer::from_pem_file(key)
        .map_err(|e| tls_error(key, "private key", pem_problem(&e)))?;
    let provider = Arc::new(rustls::crypto::ring::default_provider());
    let builder = || {
        rustls::ServerConfig::builder_with_provider(Arc::clone(&provider))
            .with_safe_default_protocol_versions()
            .map_err(|e| tls_error(cert, "protocol versions", e))
    };
    let http = builder()?
        .with_no_client_auth()
        .with_single_cert(certs.clone(), key_der.clone_key())
        .map_err(|e| tls_error(key, "certificate and key do not match", e))?;
    let ingest = match &tls.client_ca {
        None => builder()?.with_no_client_auth(),
        Some(ca) => {
            let mut roots = rustls::RootCertStore::empty();
            for c in CertificateDer::pem_file_iter(ca)
                .map_err(|e| tls_error(ca, "client CA", pem_problem(&e)))?
            {
                let c = c.map_err(|e| tls_error(ca, "not a PEM certificate", e))?;
                roots
                    .add(c)
                    .map_err(|e| tls_error(ca, "not a usable CA certificate", e))?;
            }
            if roots.is_empty() {
                // rustls would say "no root trust anchors were provided"
                return Err(tls_error(ca, "client CA", "no CA certificate in the file"));
            }
            let verifier = rustls::server::WebPkiClientVerifier::builder_with_provider(
                Arc::new(roots),
                Arc::clone(&provider),
            )
            .build()
            .map_err(|e| tls_error(ca, "client certificate verifier", e))?;
            builder()?.with_client_cert_verifier(verifier)
        }
    }
    .with_single_cert(certs, key_der)
    .map_err(|e| tls_error(key, "certificate and key do not match", e))?;
    let mut http = http;
    http.alpn_protocols = vec![b"h2".to_vec(), b"http/1.1".to_vec()];
    Ok(Some(TlsConfigs {
        ingest: Arc::new(ingest),
        http: Arc::new(http),
    }))
}

/// The exposure rule (see the module doc); `insecure` waives it, loudly.
pub fn check_exposure(
    config: &Config,
    ingest: SocketAddr,
    http: SocketAddr,
    tokens: &Tokens,
    insecure: bool,
) -> Result<(), ServeError> {
    let tls = config.tls.cert.is_some() && config.tls.key.is_some();
    let mut problems = Vec::new();
    let ingest_secured = tls && config.tls.client_ca.is_some();
    if !(ingest.ip().is_loopback() || ingest_secured) {
        problems.push(format!(
            "the ingest listener {ingest} is not on loopback and has no TLS with client certificates ([tls] cert, key, client_ca)"
        ));
    }
    let http_secured = tls && !tokens.read.is_empty();
    if !(http.ip().is_loopback() || http_secured) {
        problems.push(format!(
            "the HTTP listener {http} is not on loopback and has no TLS with bearer tokens ([tls] cert, key; [auth] read_tokens_file)"
        ));
    }
    if problems.is_empty() {
        return Ok(());
    }
    if insecure {
        for p in &problems {
            tracing::warn!("--insecure: {p}: anyone who reaches it can read or feed the fleet");
        }
        return Ok(());
    }
    Err(ServeError::Insecure(problems.join("; ")))
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn token_roles_and_unknown_tokens() {
        let t = Tokens::from_lists(&["r-secret"], &["i-secret", "i-2"]);
        assert!(t.enabled());
        assert_eq!(t.role("r-secret"), Some(Role::Read));
        assert_eq!(t.role("i-2"), Some(Role::Ingest));
        assert_eq!(t.role("r-secre"), None);
        assert_eq!(t.role(""), None);
        assert!(!Tokens::default().enabled());
        assert!(!format!("{t:?}").contains("secret"));
    }

    #[test]
    fn exposure_needs_tls_and_auth_off_loopback() {
        let mut c = Config::default();
        let lo: SocketAddr = "127.0.0.1:7410".parse().unwrap();
        let any: SocketAddr = "0.0.0.0:7411".parse().unwrap();
        let none = Tokens::default();
        assert!(check_exposure(&c, lo, lo, &none, false).is_ok());
        let err = check_exposure(&c, any, lo, &none, false)
            .unwrap_err()
            .to_string();
        assert!(
            err.contains("TLS") && err.contains("--insecure") && err.contains("0.0.0.0:7411"),
            "{err}"
        );
        assert!(check_exposure(&c, any, any, &none, true).is_ok());
        c.tls.cert = Some("c.pem".into());
        c.tls.key = Some("k.pem".into());
        let read = Tokens::from_lists(&["x"], &[]);
        assert!(check_exposure(&c, lo, any, &read, false).is_ok());
        assert!(check_exposure(&c, any, lo, &read, false).is_err());
        c.tls.client_ca = Some("ca.pem".into());
        assert!(check_exposure(&c, any, any, &read, false).is_ok());
    }
}
