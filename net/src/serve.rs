//! The server side of the cluster's security rule, and the one way its gRPC services are
//! served (the replay's `ReplayService`, the learner's `WeightsService`).
//!
//! ```text
//!  TcpListener ─► [TLS, when configured] ─► bearer-token check ─► role check ─► the service's routes
//!                                             (UNAUTHENTICATED)   (PERMISSION_DENIED)  + grpc.health.v1.Health
//!  ready future ─► health SERVING
//!  shutdown future ─► health NOT_SERVING, stop = true (streams end UNAVAILABLE) ─► HTTP/2 GOAWAY
//!                  ─► at most `grace` later, return
//! ```
//!
//! Security rule: a loopback address is reachable only from this host, so plain HTTP/2 is
//! allowed there; any other address (including 0.0.0.0) needs TLS *and* a bearer token, and
//! [`serve_secured`] refuses to start without both, because otherwise anyone who can reach
//! the port could write to the replay or read the policy.
//!
//! Roles: a service accepts a full-rights token (`auth_token_file`, every method) and one
//! token per [`Role`] (`auth_token_files: {actor, learner}`); each method needs what
//! [`METHOD_RIGHTS`] says, so a leaked actor token can insert but cannot read the replay.
//!
//! | method (path)                               | needs          |
//! |---------------------------------------------|----------------|
//! | `/mapless.v1.ReplayService/Insert`          | actor          |
//! | `/mapless.v1.ReplayService/RegisterActor`   | actor          |
//! | `/mapless.v1.WeightsService/Subscribe`      | actor          |
//! | `/mapless.v1.StatsService/Report`           | actor          |
//! | `/mapless.v1.ReplayService/Sample`          | learner        |
//! | `/mapless.v1.ReplayService/UpdatePriorities`| learner        |
//! | `/mapless.v1.ReplayService/ServerInfo`      | learner        |
//! | `/grpc.health.v1.Health/{Check,Watch}`      | any valid token|
//! | anything else                               | full-rights    |
//!
//! The full-rights token may call every method. Publishing weights is the learner process's
//! own doing (in memory); no RPC publishes, so no token can.

use std::collections::BTreeMap;
use std::future::Future;
use std::net::SocketAddr;
use std::path::{Path, PathBuf};
use std::pin::Pin;
use std::sync::{Arc, Mutex};
use std::task::{Context, Poll};
use std::time::Duration;

use serde::{Deserialize, Serialize};
use tokio::net::TcpListener;
use tokio::sync::watch;
use tonic::Status;
use tonic::codegen::{Service, http};
use tonic::server::NamedService;
use tonic::service::Routes;
use tonic::transport::server::TcpIncoming;
use tonic::transport::{Identity, Server, ServerTlsConfig};
use tracing::{debug, info, warn};

pub use crate::health::Health;
use crate::metrics::{Exposition, labels};

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

/// Who holds a bearer token, and so which gRPC methods it may call ([`METHOD_RIGHTS`]).
#[derive(Clone, Copy, Debug, PartialEq, Eq, Hash)]
pub enum Role {
    /// Actors: insert transitions, register for a slot, subscribe to weights, report stats.
    Actor,
    /// The learner: sample minibatches, update priorities, read the replay's server info.
    /// (It publishes weights inside its own process; no RPC publishes.)
    Learner,
    /// The single `auth_token_file` token: every method, as before roles existed.
    Full,
}

impl Role {
    /// The role's name in messages and docs.
    pub fn name(self) -> &'static str {
        match self {
            Role::Actor => "actor",
            Role::Learner => "learner",
            Role::Full => "full-rights",
        }
    }
}

/// What a gRPC method asks of the caller's token.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum Need {
    /// Any token the service accepts, whatever its role (health checks).
    AnyToken,
    /// A token of this role, or the full-rights token.
    Role(Role),
}

/// Every gRPC method the cluster's services serve, by its path, and what it needs. A path not
/// listed here needs the full-rights token: a new RPC is closed to role tokens until it is added.
pub const METHOD_RIGHTS: &[(&str, Need)] = &[
    ("/mapless.v1.ReplayService/Insert", Need::Role(Role::Actor)),
    ("/mapless.v1.ReplayService/RegisterActor", Need::Role(Role::Actor)),
    ("/mapless.v1.WeightsService/Subscribe", Need::Role(Role::Actor)),
    ("/mapless.v1.StatsService/Report", Need::Role(Role::Actor)),
    ("/mapless.v1.ReplayService/Sample", Need::Role(Role::Learner)),
    ("/mapless.v1.ReplayService/UpdatePriorities", Need::Role(Role::Learner)),
    ("/mapless.v1.ReplayService/ServerInfo", Need::Role(Role::Learner)),
    ("/grpc.health.v1.Health/Check", Need::AnyToken),
    ("/grpc.health.v1.Health/Watch", Need::AnyToken),
];

/// `path`'s entry in [`METHOD_RIGHTS`], if it has one.
fn known_method(path: &str) -> Option<(&'static str, Need)> {
    METHOD_RIGHTS.iter().find(|(p, _)| *p == path).copied()
}

/// Files holding one role's bearer token each: `auth_token_files` in the replay's and the
/// learner's configs. Each role's token may call only its role's methods ([`METHOD_RIGHTS`]).
///
/// ```yaml
/// auth_token_files: { actor: /secrets/actor-token, learner: /secrets/learner-token }
/// ```
#[derive(Clone, Debug, Default, Serialize, Deserialize, PartialEq)]
#[serde(default, deny_unknown_fields)]
pub struct RoleTokenFiles {
    /// The actors' token: Insert, RegisterActor, weights Subscribe, stats Report, health.
    pub actor: Option<PathBuf>,
    /// The learner's token: Sample, UpdatePriorities, ServerInfo, health.
    pub learner: Option<PathBuf>,
}

impl RoleTokenFiles {
    /// Whether no role has a token file.
    pub fn is_empty(&self) -> bool {
        self.actor.is_none() && self.learner.is_none()
    }
}

/// Bearer tokens with one role each (read from [`RoleTokenFiles`]).
#[derive(Clone, Default, PartialEq)]
pub struct RoleTokens {
    pub actor: Option<String>,
    pub learner: Option<String>,
}

impl RoleTokens {
    /// Whether no role has a token.
    pub fn is_empty(&self) -> bool {
        self.actor.is_none() && self.learner.is_none()
    }
}

/// Requests a service's token check refused, by gRPC service, method and reason
/// (`missing_token`, `wrong_token`: UNAUTHENTICATED; `forbidden`: PERMISSION_DENIED). A path
/// outside [`METHOD_RIGHTS`] counts as service and method `other`, so a client inventing paths
/// cannot grow the series without bound. Shared by every clone.
#[derive(Clone, Default)]
pub struct AuthRefusals(Arc<Mutex<BTreeMap<RefusalKey, u64>>>);

/// (gRPC service, method, reason) of a refusal.
type RefusalKey = (&'static str, &'static str, &'static str);

impl AuthRefusals {
    fn record(&self, path: &str, reason: &'static str) {
        let (service, method) = match known_method(path) {
            Some((p, _)) => p[1..].split_once('/').unwrap_or(("other", "other")),
            None => ("other", "other"),
        };
        *self.0.lock().unwrap_or_else(std::sync::PoisonError::into_inner).entry((service, method, reason)).or_default() += 1;
    }

    /// Refusals so far of `service`'s `method` (as in the path `/service/method`) for `reason`.
    pub fn count(&self, service: &str, method: &str, reason: &str) -> u64 {
        let counts = self.0.lock().unwrap_or_else(std::sync::PoisonError::into_inner);
        counts.iter().filter(|((s, m, r), _)| *s == service && *m == method && *r == reason).map(|(_, n)| n).sum()
    }

    /// Adds the counter family `name` (e.g. `replay_auth_refusals`; `_total` is appended) to `x`.
    pub fn write(&self, x: &mut Exposition, name: &str) {
        let counts = self.0.lock().unwrap_or_else(std::sync::PoisonError::into_inner).clone();
        x.counters(
            name,
            "Requests refused by the bearer-token check: reason=missing_token or wrong_token (UNAUTHENTICATED), forbidden (PERMISSION_DENIED: the token's role may not call the method).",
            counts.into_iter().map(|((service, method, reason), n)| (labels([("service", service), ("method", method), ("reason", reason)]), n as f64)),
        );
    }
}

/// A server's transport security: TLS and bearer tokens, each optional on loopback; TLS and at
/// least one token required elsewhere.
#[derive(Clone, Default)]
pub struct Security {
    pub tls: Option<TlsPem>,
    /// The full-rights token (`auth_token_file`): every method, the one token of configs
    /// written before roles.
    pub token: Option<String>,
    /// Tokens with one role each (`auth_token_files`).
    pub role_tokens: RoleTokens,
    /// Where the token check counts what it refuses (for `/metrics`).
    pub refusals: AuthRefusals,
}

impl std::fmt::Debug for Security {
    // Never print a token or the key.
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.debug_struct("Security")
            .field("tls", &self.tls.is_some())
            .field("token", &self.token.is_some())
            .field("actor_token", &self.role_tokens.actor.is_some())
            .field("learner_token", &self.role_tokens.learner.is_some())
            .finish()
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
    /// Reads the TLS files, the full-rights token file and the role token files (each
    /// trimmed; an empty one is an error, and so is one token given two roles, which would
    /// leave it unclear what it may do).
    pub fn read(tls: Option<&TlsFiles>, token_file: Option<&Path>, role_files: &RoleTokenFiles) -> Result<Security, ServeError> {
        let read = |what, path: &Path| std::fs::read(path).map_err(|error| ServeError::Read { what, path: path.into(), error });
        let tls = match tls {
            Some(files) => Some(TlsPem { cert: read("TLS certificate", &files.cert)?, key: read("TLS key", &files.key)? }),
            None => None,
        };
        let mut seen: Vec<(PathBuf, String)> = Vec::new();
        let mut token = |path: Option<&Path>| -> Result<Option<String>, ServeError> {
            let Some(path) = path else { return Ok(None) };
            let raw = read("token file", path)?;
            let token = String::from_utf8_lossy(&raw).trim().to_owned();
            if token.is_empty() {
                return Err(ServeError::File { path: path.into(), problem: "the token file is empty".into() });
            }
            if let Some((other, _)) = seen.iter().find(|(_, t)| *t == token) {
                return Err(ServeError::File { path: path.into(), problem: format!("holds the same token as {}; each role needs a token of its own", other.display()) });
            }
            seen.push((path.to_path_buf(), token.clone()));
            Ok(Some(token))
        };
        let full = token(token_file)?;
        let role_tokens = RoleTokens { actor: token(role_files.actor.as_deref())?, learner: token(role_files.learner.as_deref())? };
        Ok(Security { tls, token: full, role_tokens, refusals: AuthRefusals::default() })
    }

    /// Whether any token is configured (without one, every request passes).
    pub fn has_token(&self) -> bool {
        self.token.is_some() || !self.role_tokens.is_empty()
    }

    /// Whether `addr` may be served with this security (see the module doc).
    pub fn allows(&self, addr: &SocketAddr) -> bool {
        addr.ip().is_loopback() || (self.tls.is_some() && self.has_token())
    }

    /// The token check every request of a service served with this security passes.
    pub fn auth(&self) -> BearerAuth {
        let bearer = |t: &String| format!("Bearer {t}").into_bytes();
        let tokens = [(Role::Full, &self.token), (Role::Actor, &self.role_tokens.actor), (Role::Learner, &self.role_tokens.learner)]
            .into_iter()
            .filter_map(|(role, t)| t.as_ref().map(|t| (role, bearer(t))))
            .collect();
        BearerAuth { tokens: Arc::new(tokens), refusals: self.refusals.clone() }
    }
}

/// Checks `authorization: Bearer <token>` on every request against the configured tokens, then
/// the token's role against the method's need ([`METHOD_RIGHTS`]): no or an unknown token is
/// UNAUTHENTICATED, a known token without the right PERMISSION_DENIED; each refusal is counted
/// in [`AuthRefusals`]. Passes everything when no token is configured.
#[derive(Clone)]
pub struct BearerAuth {
    tokens: Arc<Vec<(Role, Vec<u8>)>>,
    refusals: AuthRefusals,
}

impl BearerAuth {
    /// The role of the token in `authorization` (the header's raw value), if it may call
    /// `path`; `Ok(None)` when no token is configured.
    pub fn check(&self, path: &str, authorization: Option<&[u8]>) -> Result<Option<Role>, Status> {
        if self.tokens.is_empty() {
            return Ok(None);
        }
        let refuse = |reason, status: Status| {
            self.refusals.record(path, reason);
            debug!(method = path, reason, "request refused");
            Err(status)
        };
        let Some(got) = authorization else {
            return refuse("missing_token", Status::unauthenticated("missing `authorization: Bearer <token>` metadata"));
        };
        // Every token is compared, in constant time, so the time taken tells nothing.
        let mut role = None;
        for (r, expected) in self.tokens.iter() {
            if constant_time_eq(got, expected) {
                role = Some(*r);
            }
        }
        let Some(role) = role else { return refuse("wrong_token", Status::unauthenticated("wrong bearer token")) };
        let need = known_method(path).map(|(_, need)| need);
        match need {
            _ if role == Role::Full => Ok(Some(role)),
            Some(Need::AnyToken) => Ok(Some(role)),
            Some(Need::Role(r)) if r == role => Ok(Some(role)),
            Some(Need::Role(r)) => {
                refuse("forbidden", Status::permission_denied(format!("{path} needs the {} role (or the full-rights token); this request's token has the {} role", r.name(), role.name())))
            }
            None => refuse("forbidden", Status::permission_denied(format!("{path} is open to the full-rights token only; this request's token has the {} role", role.name()))),
        }
    }

    /// `service` behind this check.
    pub fn wrap<S>(&self, service: S) -> Authorized<S> {
        Authorized { inner: service, auth: self.clone() }
    }
}

/// A gRPC service behind a [`BearerAuth`] check (a refused request never reaches it). Unlike
/// a tonic interceptor, it sees the request's path, which the role check needs.
#[derive(Clone)]
pub struct Authorized<S> {
    inner: S,
    auth: BearerAuth,
}

impl<S: NamedService> NamedService for Authorized<S> {
    const NAME: &'static str = S::NAME;
}

impl<S, B, R> Service<http::Request<B>> for Authorized<S>
where
    S: Service<http::Request<B>, Response = http::Response<R>>,
    S::Future: Send + 'static,
    S::Error: Send + 'static,
    R: Default + Send + 'static,
{
    type Response = http::Response<R>;
    type Error = S::Error;
    type Future = Pin<Box<dyn Future<Output = Result<http::Response<R>, S::Error>> + Send>>;

    fn poll_ready(&mut self, cx: &mut Context<'_>) -> Poll<Result<(), S::Error>> {
        self.inner.poll_ready(cx)
    }

    fn call(&mut self, request: http::Request<B>) -> Self::Future {
        let authorization = request.headers().get(http::header::AUTHORIZATION).map(http::HeaderValue::as_bytes);
        match self.auth.check(request.uri().path(), authorization) {
            Ok(_) => Box::pin(self.inner.call(request)),
            Err(status) => Box::pin(std::future::ready(Ok(status.into_http()))),
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
/// `make` gets the token check to wrap each service in (`auth.wrap(svc)`)
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
    let routes = make(security.auth(), stop_rx.clone()).add_service(security.auth().wrap(health_service));
    let mut builder = Server::builder().http2_keepalive_interval(Some(KEEPALIVE_INTERVAL)).http2_keepalive_timeout(Some(KEEPALIVE_TIMEOUT));
    if let Some(tls) = &security.tls {
        builder = builder.tls_config(ServerTlsConfig::new().identity(Identity::from_pem(&tls.cert, &tls.key))).map_err(transport)?;
    }
    info!(service, %addr, tls = security.tls.is_some(), full_token = security.token.is_some(), actor_token = security.role_tokens.actor.is_some(), learner_token = security.role_tokens.learner.is_some(), "gRPC serving");
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

    fn check(auth: &BearerAuth, path: &str, token: Option<&str>) -> Result<Option<Role>, tonic::Code> {
        let header = token.map(|t| format!("Bearer {t}"));
        auth.check(path, header.as_deref().map(str::as_bytes)).map_err(|s| s.code())
    }

    const INSERT: &str = "/mapless.v1.ReplayService/Insert";
    const SAMPLE: &str = "/mapless.v1.ReplayService/Sample";

    #[test]
    fn bearer_check_needs_the_exact_token() {
        let auth = Security { token: Some("s3cret".into()), ..Security::default() }.auth();
        assert_eq!(check(&auth, SAMPLE, Some("s3cret")), Ok(Some(Role::Full)));
        assert_eq!(check(&auth, SAMPLE, Some("s3cre")), Err(tonic::Code::Unauthenticated));
        assert_eq!(check(&auth, SAMPLE, None), Err(tonic::Code::Unauthenticated));
        assert_eq!(check(&Security::default().auth(), SAMPLE, None), Ok(None));
        assert_eq!(auth.refusals.count("mapless.v1.ReplayService", "Sample", "wrong_token"), 1);
        assert_eq!(auth.refusals.count("mapless.v1.ReplayService", "Sample", "missing_token"), 1);
    }

    #[test]
    fn each_role_calls_only_its_methods() {
        let security = Security { token: Some("full".into()), role_tokens: RoleTokens { actor: Some("a".into()), learner: Some("l".into()) }, ..Security::default() };
        let auth = security.auth();
        for (path, need) in METHOD_RIGHTS {
            assert!(check(&auth, path, Some("full")).is_ok(), "{path}: the full-rights token may call everything");
            let (actor, learner) = (check(&auth, path, Some("a")), check(&auth, path, Some("l")));
            match need {
                Need::AnyToken => assert!(actor.is_ok() && learner.is_ok(), "{path}"),
                Need::Role(Role::Actor) => assert_eq!((actor, learner), (Ok(Some(Role::Actor)), Err(tonic::Code::PermissionDenied)), "{path}"),
                Need::Role(Role::Learner) => assert_eq!((actor, learner), (Err(tonic::Code::PermissionDenied), Ok(Some(Role::Learner))), "{path}"),
                Need::Role(Role::Full) => unreachable!("no listed method is full-rights only"),
            }
        }
        let denied = auth.check(SAMPLE, Some(b"Bearer a")).unwrap_err();
        assert!(denied.message().contains(SAMPLE) && denied.message().contains("learner role") && denied.message().contains("actor role"), "{}", denied.message());
        assert_eq!(check(&auth, "/mapless.v1.ReplayService/Invented", Some("a")), Err(tonic::Code::PermissionDenied), "unlisted: full-rights only");
        assert_eq!(check(&auth, "/mapless.v1.ReplayService/Invented", Some("full")), Ok(Some(Role::Full)));
        assert_eq!(check(&auth, INSERT, Some("x")), Err(tonic::Code::Unauthenticated));
        assert_eq!(security.refusals.count("mapless.v1.ReplayService", "Sample", "forbidden"), 2);
        assert_eq!(security.refusals.count("other", "other", "forbidden"), 1);
        let mut x = Exposition::new();
        security.refusals.write(&mut x, "replay_auth_refusals");
        let text = x.text();
        assert!(text.contains(r#"replay_auth_refusals_total{service="mapless.v1.ReplayService",method="Sample",reason="forbidden"} 2"#), "{text}");
    }

    /// Every RPC of the generated servers is in the table, so none is left to the
    /// full-rights-only default by oversight.
    #[test]
    fn every_generated_method_has_a_right() {
        let generated = include_str!("../../proto/src/gen/mapless.v1.rs");
        let mut paths: Vec<&str> = generated.split('"').filter(|s| s.starts_with("/mapless.v1.") && s.matches('/').count() == 2).collect();
        paths.sort_unstable();
        paths.dedup();
        assert!(paths.len() >= 7, "{paths:?}");
        for p in paths {
            assert!(known_method(p).is_some(), "{p} is not in METHOD_RIGHTS");
        }
    }

    #[test]
    fn non_loopback_needs_tls_and_token() {
        let public: SocketAddr = "0.0.0.0:1".parse().unwrap();
        let tls = Some(TlsPem { cert: vec![], key: vec![] });
        assert!(Security::default().allows(&"127.0.0.1:1".parse().unwrap()));
        assert!(!Security::default().allows(&public));
        assert!(!Security { tls: tls.clone(), ..Security::default() }.allows(&public), "TLS alone is not enough");
        assert!(!Security { token: Some("t".into()), ..Security::default() }.allows(&public), "a token alone is not enough");
        assert!(Security { tls: tls.clone(), token: Some("t".into()), ..Security::default() }.allows(&public));
        assert!(Security { tls, role_tokens: RoleTokens { actor: Some("a".into()), learner: None }, ..Security::default() }.allows(&public));
    }

    #[test]
    fn token_files_are_read_checked_and_distinct() {
        let dir = std::env::temp_dir().join(format!("mapless-net-token-{}", std::process::id()));
        std::fs::create_dir_all(&dir).unwrap();
        let f = dir.join("token");
        std::fs::write(&f, " \n").unwrap();
        assert!(matches!(Security::read(None, Some(&f), &RoleTokenFiles::default()), Err(ServeError::File { .. })));
        std::fs::write(&f, "abc\n").unwrap();
        assert_eq!(Security::read(None, Some(&f), &RoleTokenFiles::default()).unwrap().token.as_deref(), Some("abc"));
        let (a, l) = (dir.join("actor"), dir.join("learner"));
        std::fs::write(&a, "aaa\n").unwrap();
        std::fs::write(&l, "abc").unwrap();
        let files = RoleTokenFiles { actor: Some(a.clone()), learner: Some(l.clone()) };
        let err = Security::read(None, Some(&f), &files).unwrap_err().to_string();
        assert!(err.contains("same token"), "{err}");
        std::fs::write(&l, "lll").unwrap();
        let s = Security::read(None, None, &files).unwrap();
        assert_eq!((s.token, s.role_tokens.actor.as_deref(), s.role_tokens.learner.as_deref()), (None, Some("aaa"), Some("lll")));
        let _ = std::fs::remove_dir_all(&dir);
    }

    #[test]
    fn role_token_files_take_known_keys_only() {
        let files: RoleTokenFiles = serde_json::from_str(r#"{"actor": "/s/a"}"#).unwrap();
        assert_eq!((files.actor.as_deref(), files.learner), (Some(Path::new("/s/a")), None));
        assert!(serde_json::from_str::<RoleTokenFiles>(r#"{"actors": "x"}"#).is_err(), "unknown keys are errors");
    }
}
