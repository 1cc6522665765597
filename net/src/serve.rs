//! The server side of the cluster's security rule, and the one way its gRPC services are
//! served (the replay's `ReplayService`, the learner's `WeightsService`).
//!
//! ```text
//!  TcpListener ─► [TLS, when configured] ─► bearer-token check ─► the service's routes
//!                                             (UNAUTHENTICATED)     + grpc.health.v1.Health
//!  ready future ─► health SERVING
//!  shutdown future ─► health NOT_SERVING, stop = true (streams end UNAVAILABLE) ─► HTTP/2 GOAWAY
//!                  ─► at most `grace` later, return
//! ```
//!
//! Security rule: a loopback address is reachable only from this host, so plain HTTP/2 is
//! allowed there; any other address (including 0.0.0.0) needs TLS *and* a bearer token, and
//! [`serve_secured`] refuses to start without both, because otherwise anyone who can reach
//! the port could write to the replay or read the policy.

use std::future::Future;
use std::net::SocketAddr;
use std::path::{Path, PathBuf};
use std::sync::Arc;
use std::time::Duration;

use serde::{Deserialize, Serialize};
use tokio::net::TcpListener;
use tokio::sync::watch;
use tonic::service::interceptor::InterceptedService;
use tonic::service::{Interceptor, Routes};
use tonic::transport::server::TcpIncoming;
use tonic::transport::{Identity, Server, ServerTlsConfig};
use tonic::{Request, Status};
use tracing::{info, warn};

pub use crate::health::Health;

/// HTTP/2 pings that find dead peers (a crashed host sends no RST), so their streams are
/// released within interval + timeout [inferred: 10 s + 20 s].
pub const KEEPALIVE_INTERVAL: Duration = Duration::from_secs(10);
/// See [`KEEPALIVE_INTERVAL`].
pub const KEEPALIVE_TIMEOUT: Duration = Duration::from_secs(20);

/// PEM files for a server's TLS identity, as they appear in a config file.
#[derive(Clone, Debug, Serialize, Deserialize, PartialEq)]
#[serde(deny_unknown_fields)]
pub struct TlsFiles {
    /// Certificate chain, leaf first.
    pub cert: PathBuf,
    /// Private key of the leaf certificate.
    pub key: PathBuf,
}

/// TLS identity, PEM-encoded.
#[derive(Clone)]
pub struct TlsPem {
    pub cert: Vec<u8>,
    pub key: Vec<u8>,
}

/// A server's transport security: TLS and a bearer token, each optional on loopback, both
/// required elsewhere.
#[derive(Clone, Default)]
pub struct Security {
    pub tls: Option<TlsPem>,
    pub token: Option<String>,
}

impl std::fmt::Debug for Security {
    // Never print the token or the key.
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.debug_struct("Security").field("tls", &self.tls.is_some()).field("token", &self.token.is_some()).finish()
    }
}

/// Why a server could not start or stopped serving.
#[derive(Debug, thiserror::Error)]
pub enum ServeError {
    // `error`, not `source`: the message already includes it, so a cause chain would repeat it.
    #[error("cannot read {what} {path}: {error}")]
    Read { what: &'static str, path: PathBuf, error: std::io::Error },
    #[error("{path}: {problem}")]
    File { path: PathBuf, problem: String },
    #[error(
        "refusing to serve {service} on {addr}: a non-loopback address needs TLS and a bearer token; without both, \
         anyone who can reach the port can use the service. For a local run use 127.0.0.1."
    )]
    Insecure { service: &'static str, addr: SocketAddr },
    #[error("{service} on {addr}: gRPC transport: {error}")]
    Transport { service: &'static str, addr: String, error: tonic::transport::Error },
    #[error(transparent)]
    Io(#[from] std::io::Error),
}

impl Security {
    /// Reads the TLS files and the token file (trimmed; an empty one is an error).
    pub fn read(tls: Option<&TlsFiles>, token_file: Option<&Path>) -> Result<Security, ServeError> {
        let read = |what, path: &Path| std::fs::read(path).map_err(|error| ServeError::Read { what, path: path.into(), error });
        let tls = match tls {
            Some(files) => Some(TlsPem { cert: read("TLS certificate", &files.cert)?, key: read("TLS key", &files.key)? }),
            None => None,
        };
        let token = match token_file {
            Some(path) => {
                let raw = read("token file", path)?;
                let token = String::from_utf8_lossy(&raw).trim().to_owned();
                if token.is_empty() {
                    return Err(ServeError::File { path: path.into(), problem: "the token file is empty".into() });
                }
                Some(token)
            }
            None => None,
        };
        Ok(Security { tls, token })
    }

    /// Whether `addr` may be served with this security (see the module doc).
    pub fn allows(&self, addr: &SocketAddr) -> bool {
        addr.ip().is_loopback() || (self.tls.is_some() && self.token.is_some())
    }

    /// The token check every request of a service served with this security passes.
    pub fn auth(&self) -> BearerAuth {
        BearerAuth::new(self.token.as_deref())
    }
}

/// Checks `authorization: Bearer <token>` on every request; passes everything when no token
/// is configured.
#[derive(Clone)]
pub struct BearerAuth {
    expected: Option<Arc<[u8]>>,
}

impl BearerAuth {
    pub fn new(token: Option<&str>) -> BearerAuth {
        BearerAuth { expected: token.map(|t| Arc::from(format!("Bearer {t}").into_bytes())) }
    }
}

impl Interceptor for BearerAuth {
    fn call(&mut self, request: Request<()>) -> Result<Request<()>, Status> {
        let Some(expected) = &self.expected else { return Ok(request) };
        match request.metadata().get("authorization") {
            Some(got) if constant_time_eq(got.as_bytes(), expected) => Ok(request),
            Some(_) => Err(Status::unauthenticated("wrong bearer token")),
            None => Err(Status::unauthenticated("missing `authorization: Bearer <token>` metadata")),
        }
    }
}

/// Equality whose time does not depend on where the inputs first differ (`subtle`).
fn constant_time_eq(a: &[u8], b: &[u8]) -> bool {
    use subtle::ConstantTimeEq;
    a.ct_eq(b).into()
}

/// What a service tells the gRPC health protocol, besides its routes: its gRPC names (the
/// health service answers for them and for `""`), the process's [`Health`], and when it is
/// ready (for the replay at once; for the learner at its first publication).
pub struct Readiness<R> {
    pub grpc_names: &'static [&'static str],
    pub health: Health,
    pub ready: R,
}

/// Serves the routes `make` builds on `listener` until `shutdown` resolves, with `security`'s
/// TLS and keep-alive pings; refuses a non-loopback listener without TLS and a token.
///
/// `make` gets the token check to wrap each service in (`InterceptedService::new(svc, auth)`)
/// and a stop flag that turns true when `shutdown` resolves, so that open streams can end
/// with UNAVAILABLE; connections still open `grace` after that are closed.
///
/// Beside the routes it serves `grpc.health.v1.Health` behind the same token check: NOT_SERVING
/// until `readiness.ready` resolves, SERVING then, NOT_SERVING again from `shutdown` on (or
/// from any earlier [`Health::drain`] of the caller's). An open health `Watch` stream holds its
/// connection until `grace` ends it.
pub async fn serve_secured(
    service: &'static str,
    listener: TcpListener,
    security: &Security,
    grace: Duration,
    readiness: Readiness<impl Future<Output = ()> + Send>,
    make: impl FnOnce(BearerAuth, watch::Receiver<bool>) -> Routes,
    shutdown: impl Future<Output = ()> + Send + 'static,
) -> Result<(), ServeError> {
    let addr = listener.local_addr()?;
    if !security.allows(&addr) {
        return Err(ServeError::Insecure { service, addr });
    }
    let transport = |error| ServeError::Transport { service, addr: addr.to_string(), error };
    let (stop_tx, stop_rx) = watch::channel(false);
    let Readiness { grpc_names, health, ready } = readiness;
    let (health_service, follow_health) = health.grpc(grpc_names).await;
    let routes = make(security.auth(), stop_rx.clone()).add_service(InterceptedService::new(health_service, security.auth()));
    let mut builder = Server::builder().http2_keepalive_interval(Some(KEEPALIVE_INTERVAL)).http2_keepalive_timeout(Some(KEEPALIVE_TIMEOUT));
    if let Some(tls) = &security.tls {
        builder = builder.tls_config(ServerTlsConfig::new().identity(Identity::from_pem(&tls.cert, &tls.key))).map_err(transport)?;
    }
    info!(service, %addr, tls = security.tls.is_some(), token = security.token.is_some(), "gRPC serving");
    let incoming = TcpIncoming::from(listener).with_nodelay(Some(true));
    let draining = health.clone();
    let signal = async move {
        shutdown.await;
        draining.drain();
        info!(service, "shutting down: ending open streams");
        let _ = stop_tx.send(true);
    };
    let serving = builder.add_routes(routes).serve_with_incoming_shutdown(incoming, signal);
    tokio::pin!(serving);
    let mut stopped = stop_rx;
    // Readiness and the health service's statuses are followed while serving, never awaited
    // for their own sake.
    let ready_then_follow = async move {
        tokio::join!(
            async move {
                ready.await;
                health.serve();
            },
            follow_health
        );
        std::future::pending::<()>().await
    };
    tokio::select! {
        () = ready_then_follow => unreachable!("pending"),
        result = &mut serving => result.map_err(transport)?,
        () = async {
            // Only reachable once the signal fired; its sender lives inside `serving`.
            if stopped.wait_for(|s| *s).await.is_ok() {
                tokio::time::sleep(grace).await;
            } else {
                std::future::pending::<()>().await;
            }
        } => warn!(service, ?grace, "connections still open after the shutdown grace period; closing them"),
    }
    Ok(())
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn bearer_check_needs_the_exact_token() {
        let mut auth = BearerAuth::new(Some("s3cret"));
        let with = |v: &str| {
            let mut r = Request::new(());
            r.metadata_mut().insert("authorization", v.parse().unwrap());
            r
        };
        assert!(auth.call(with("Bearer s3cret")).is_ok());
        assert_eq!(auth.call(with("Bearer s3cre")).unwrap_err().code(), tonic::Code::Unauthenticated);
        assert_eq!(auth.call(Request::new(())).unwrap_err().code(), tonic::Code::Unauthenticated);
        assert!(BearerAuth::new(None).call(Request::new(())).is_ok());
    }

    #[test]
    fn non_loopback_needs_tls_and_token() {
        let public: SocketAddr = "0.0.0.0:1".parse().unwrap();
        let tls = Some(TlsPem { cert: vec![], key: vec![] });
        assert!(Security::default().allows(&"127.0.0.1:1".parse().unwrap()));
        assert!(!Security::default().allows(&public));
        assert!(!Security { tls: tls.clone(), token: None }.allows(&public), "TLS alone is not enough");
        assert!(!Security { tls: None, token: Some("t".into()) }.allows(&public), "a token alone is not enough");
        assert!(Security { tls, token: Some("t".into()) }.allows(&public));
    }

    #[test]
    fn an_empty_token_file_is_refused() {
        let dir = std::env::temp_dir().join(format!("mapless-net-token-{}", std::process::id()));
        std::fs::create_dir_all(&dir).unwrap();
        let f = dir.join("token");
        std::fs::write(&f, " \n").unwrap();
        assert!(matches!(Security::read(None, Some(&f)), Err(ServeError::File { .. })));
        std::fs::write(&f, "abc\n").unwrap();
        assert_eq!(Security::read(None, Some(&f)).unwrap().token.as_deref(), Some("abc"));
        let _ = std::fs::remove_dir_all(&dir);
    }
}
