//! Transport set-up for the replay service: its configuration, the security rule for
//! non-loopback listeners, and [`run`]/[`serve`], which tests start on `127.0.0.1:0`.
//!
//! ```text
//!  TcpListener ─► [TLS, when configured] ─► bearer-token and role check ─► ReplayServiceServer(ReplayGrpc)
//!                                    (UNAUTHENTICATED, PERMISSION_DENIED)     16 MiB limits both ways
//!                                                                 + grpc.health.v1.Health
//!  shutdown future ─► health NOT_SERVING, streams end UNAVAILABLE ─► HTTP/2 GOAWAY
//!                  ─► at most `shutdown_grace` later, return
//! ```
//!
//! Health: [`serve`] gets an open table (its log already recovered), so the replay reports
//! SERVING (for `""` and `mapless.v1.ReplayService`) as soon as it serves, and NOT_SERVING from
//! the shutdown signal on.
//!
//! Security rule: a loopback address is reachable only from this host, so plain HTTP/2 is
//! allowed there; any other address (including 0.0.0.0) needs TLS *and* a bearer token, and
//! the server refuses to start without both, because otherwise anyone who can reach the port
//! can fill the table with garbage or read every transition. With a token per role
//! (`auth_token_files`), an actor's token may only insert and register, the learner's only
//! sample, update priorities and read the server info (`mapless_net::serve::METHOD_RIGHTS`).

use std::future::Future;
use std::net::SocketAddr;
use std::path::{Path, PathBuf};
use std::sync::Arc;
use std::time::Duration;

use mapless_net::health::Health;
use mapless_net::serve::{Readiness, ServeError, serve_secured};
use mapless_net::serve::{RoleTokenFiles, Security, TlsFiles};
use mapless_proto::MAX_MESSAGE_BYTES;
use mapless_proto::v1::replay_service_server::ReplayServiceServer;
use serde::{Deserialize, Serialize};
use tokio::net::TcpListener;
use tonic::server::NamedService;
use tonic::service::Routes;
use tracing::info;

use crate::config::{PersistenceConfig, TableConfig};
use crate::error::ReplayError;
use crate::grpc::{DEFAULT_MAX_PREFETCH, DEFAULT_MAX_SAMPLE_STREAMS, ReplayGrpc};
use crate::registry::{ActorRegistry, DEFAULT_MAX_ACTOR_SLOTS};
use crate::table::Table;

/// Default gRPC address: loopback only.
pub const DEFAULT_LISTEN: &str = "127.0.0.1:50051";
/// Default Prometheus address: loopback only (9464 is the OpenTelemetry Prometheus port).
pub const DEFAULT_METRICS_LISTEN: &str = "127.0.0.1:9464";

/// Everything the `mapless-replay` binary reads from its YAML file (flags override it).
///
/// ```yaml
/// listen: 127.0.0.1:50051
/// metrics_listen: 127.0.0.1:9464     # null disables /metrics
/// tls: { cert: server.pem, key: server.key }
/// auth_token_files: { actor: actor-token.txt, learner: learner-token.txt }
/// table: { name: transitions, capacity: 1000000, obs_dim: 17, act_dim: 2 }
/// persistence: { dir: /var/lib/mapless/replay }
/// ```
#[derive(Clone, Debug, Serialize, Deserialize, PartialEq)]
#[serde(default, deny_unknown_fields)]
pub struct ServerConfig {
    /// gRPC address. Loopback by default; any other address needs `tls` and a token
    /// (`auth_token_files` or `auth_token_file`).
    pub listen: SocketAddr,
    /// Prometheus text exposition at `http://<addr>/metrics`; none disables it. Loopback, or
    /// any address with `metrics_token_file` (a Prometheus beside it on a private network).
    pub metrics_listen: Option<SocketAddr>,
    /// File holding the bearer token a scraper of `/metrics` must send (trimmed; plain HTTP, so
    /// for a private network); needed beyond loopback [default: none, loopback only; ours:
    /// the exposition names every actor and shows the table's state].
    pub metrics_token_file: Option<PathBuf>,
    /// Server certificate chain and private key (PEM files).
    pub tls: Option<TlsFiles>,
    /// File whose content (trimmed) is a full-rights bearer token: a request carrying it as
    /// `authorization: Bearer <token>` may call every method (the one token of configs written
    /// before `auth_token_files`; prefer those). A file, not a flag, so the token stays out of `ps`.
    pub auth_token_file: Option<PathBuf>,
    /// Files holding one role's token each (`{actor: FILE, learner: FILE}`, trimmed, distinct):
    /// the actor's may Insert and RegisterActor, the learner's Sample, UpdatePriorities and
    /// ServerInfo; either may ask the health service. Another method is PERMISSION_DENIED
    /// (counted in `replay_auth_refusals_total`), so a leaked actor token cannot read the table.
    /// Accepted beside `auth_token_file`.
    #[serde(skip_serializing_if = "RoleTokenFiles::is_empty")]
    pub auth_token_files: RoleTokenFiles,
    /// Largest SampleRequest.prefetch honoured; larger requests are clamped [replay.proto: 16].
    pub max_prefetch: u32,
    /// Most Sample streams open at once; one more is refused with RESOURCE_EXHAUSTED (and
    /// counted in `replay_sample_streams_refused_total`) instead of slowing everyone down
    /// [default: 256 — a learner opens one or a few; each open stream may hold `prefetch`
    /// drawn minibatches in memory]. Must be ≥ 1.
    pub max_sample_streams: u32,
    /// After a shutdown signal, how long open streams may take to end before they are cut.
    pub shutdown_grace_ms: u64,
    /// Seed of the sampler's random stream.
    pub seed: u64,
    /// Log lines as JSON objects instead of human-readable text.
    pub log_json: bool,
    /// The table this server hosts.
    pub table: TableConfig,
    /// Where the table persists itself (`dir: null`, the default, keeps it in memory only).
    pub persistence: PersistenceConfig,
    /// Also ingest over iceoryx2 shared memory, for actors on this host [default: on].
    pub shm_enabled: bool,
    /// Shared-memory ingest settings; none derives them from the table name
    /// (`mapless/replay/<table>`).
    pub shm: Option<mapless_net::shm::ShmConfig>,
    /// Most actor names that may hold a slot (`RegisterActor`, `mapless-actor --index auto`);
    /// a new name beyond it is refused with RESOURCE_EXHAUSTED. Slots are never released, so
    /// this bounds the names ever registered with this data directory [default: 4096 — one
    /// actor process per core of a large cluster; the bound keeps a client that invents names
    /// from growing the slot file without limit]. Must be ≥ 1.
    pub max_actor_slots: u32,
}

impl Default for ServerConfig {
    fn default() -> Self {
        ServerConfig {
            listen: DEFAULT_LISTEN.parse().expect("valid default address"),
            metrics_listen: Some(DEFAULT_METRICS_LISTEN.parse().expect("valid default address")),
            metrics_token_file: None,
            tls: None,
            auth_token_file: None,
            auth_token_files: RoleTokenFiles::default(),
            max_prefetch: DEFAULT_MAX_PREFETCH,
            max_sample_streams: DEFAULT_MAX_SAMPLE_STREAMS,
            shutdown_grace_ms: 5_000,
            seed: 0,
            log_json: false,
            table: TableConfig::default(),
            persistence: PersistenceConfig::default(),
            shm_enabled: true,
            shm: None,
            max_actor_slots: DEFAULT_MAX_ACTOR_SLOTS,
        }
    }
}

impl ServerConfig {
    /// The shared-memory ingest settings in effect.
    pub fn shm_config(&self) -> mapless_net::shm::ShmConfig {
        self.shm.clone().unwrap_or_else(|| mapless_net::shm::ShmConfig::for_table(&self.table.name))
    }
}

/// Why the server could not start or stopped serving.
#[derive(Debug, thiserror::Error)]
pub enum ServerError {
    #[error("config file {path}: {problem}")]
    ConfigFile { path: PathBuf, problem: String },
    // `error`, not `source`: the message already includes it, so a cause chain would repeat it.
    #[error("cannot read {what} {path}: {error}")]
    Read { what: &'static str, path: PathBuf, error: std::io::Error },
    #[error(
        "refusing to serve on {addr}: a non-loopback address needs TLS (tls.cert + tls.key, or --tls-cert/--tls-key) \
         and a bearer token (auth_token_files: {{actor, learner}}, auth_token_file, or --auth-token-file); without both, anyone who can reach the port can \
         write to and read the replay table. For a local run use 127.0.0.1."
    )]
    Insecure { addr: SocketAddr },
    #[error(
        "refusing to serve /metrics on {addr} without a token: anyone who can reach it would read every actor id \
         and the table's state. Set metrics_token_file (scrapers send it as a bearer token), bind loopback \
         (metrics_listen: 127.0.0.1:9464, the default), or `--no-metrics`."
    )]
    InsecureMetrics { addr: SocketAddr },
    #[error(transparent)]
    Replay(#[from] ReplayError),
    #[error(transparent)]
    Serve(#[from] ServeError),
    #[error(transparent)]
    Io(#[from] std::io::Error),
}

impl ServerConfig {
    /// Reads a YAML file; missing keys take their defaults, unknown keys are errors.
    pub fn from_yaml_file(path: &Path) -> Result<ServerConfig, ServerError> {
        let text = std::fs::read_to_string(path).map_err(|error| ServerError::Read { what: "config file", path: path.into(), error })?;
        serde_yaml::from_str(&text).map_err(|e| ServerError::ConfigFile { path: path.into(), problem: e.to_string() })
    }

    /// The table's own checks plus the security rule (see the module doc).
    pub fn validate(&self) -> Result<(), ServerError> {
        self.table.validate()?;
        self.persistence.validate()?;
        if self.max_sample_streams == 0 {
            return Err(ReplayError::InvalidConfig("max_sample_streams must be ≥ 1 (it bounds the Sample streams open at once)".into()).into());
        }
        if self.max_actor_slots == 0 {
            return Err(ReplayError::InvalidConfig("max_actor_slots must be ≥ 1 (it bounds the actor names that may register)".into()).into());
        }
        if !self.listen.ip().is_loopback() && (self.tls.is_none() || (self.auth_token_file.is_none() && self.auth_token_files.is_empty())) {
            return Err(ServerError::Insecure { addr: self.listen });
        }
        // As the actors' and the learner's: /metrics stays on the host it describes, unless a
        // token guards it.
        if let Some(m) = self.metrics_listen
            && !m.ip().is_loopback()
            && self.metrics_token_file.is_none()
        {
            return Err(ServerError::InsecureMetrics { addr: m });
        }
        Ok(())
    }

    /// Reads the TLS and token files.
    pub fn security(&self) -> Result<Security, ServerError> {
        Ok(Security::read(self.tls.as_ref(), self.auth_token_file.as_deref(), &self.auth_token_files)?)
    }

    /// What [`serve`] needs besides the listener and the table (with an actor-slot table in
    /// memory; [`ServerConfig::open_registry`] loads the durable one).
    pub fn serve_options(&self) -> Result<ServeOptions, ServerError> {
        Ok(ServeOptions {
            security: self.security()?,
            max_prefetch: self.max_prefetch,
            max_sample_streams: self.max_sample_streams,
            shutdown_grace: Duration::from_millis(self.shutdown_grace_ms),
            registry: Arc::new(ActorRegistry::in_memory(self.max_actor_slots)),
            health: Health::new(),
        })
    }

    /// The actor-slot table kept in `persistence.dir` (in memory without one), loaded from its
    /// file. Open the table first: [`crate::DurableTable::open`] locks the directory against a
    /// second replay, which would hand out the same slots.
    pub fn open_registry(&self) -> Result<ActorRegistry, ServerError> {
        Ok(ActorRegistry::open(self.persistence.dir.as_deref(), self.max_actor_slots)?)
    }
}

/// How [`serve`] runs.
#[derive(Clone, Debug)]
pub struct ServeOptions {
    pub security: Security,
    pub max_prefetch: u32,
    /// See [`ServerConfig::max_sample_streams`].
    pub max_sample_streams: u32,
    pub shutdown_grace: Duration,
    /// Actor name → slot, answered by `RegisterActor` (default: in memory only).
    pub registry: Arc<ActorRegistry>,
    /// What the gRPC health service (and the process's `/healthz`) reports: serving from the
    /// start of [`serve`], draining from its shutdown signal.
    pub health: Health,
}

impl Default for ServeOptions {
    fn default() -> Self {
        ServeOptions {
            security: Security::default(),
            max_prefetch: DEFAULT_MAX_PREFETCH,
            max_sample_streams: DEFAULT_MAX_SAMPLE_STREAMS,
            shutdown_grace: Duration::from_secs(5),
            registry: Arc::default(),
            health: Health::new(),
        }
    }
}

/// Serves `table` on `listener` with plain HTTP/2 and no token (loopback listeners only)
/// until `shutdown` resolves; then open streams end with UNAVAILABLE and it returns.
pub async fn run(listener: TcpListener, table: Arc<Table>, shutdown: impl Future<Output = ()> + Send + 'static) -> Result<(), ServerError> {
    serve(listener, table, ServeOptions::default(), shutdown).await
}

/// The gRPC names the health service answers for, besides `""`.
const GRPC_NAMES: &[&str] = &[<ReplayServiceServer<ReplayGrpc> as NamedService>::NAME];

/// Serves `table` on `listener` until `shutdown` resolves. Refuses a non-loopback listener
/// without TLS and a token. Does not close the table (the caller owns it and may share it
/// with other ingest paths). Health: SERVING while it serves (the table is open), NOT_SERVING
/// from `shutdown` on.
pub async fn serve(listener: TcpListener, table: Arc<Table>, options: ServeOptions, shutdown: impl Future<Output = ()> + Send + 'static) -> Result<(), ServerError> {
    let name = table.config().name.clone();
    info!(table = %name, "replay gRPC starting");
    let make = |auth: mapless_net::BearerAuth, stop| {
        let grpc = ReplayGrpc::new(table).with_max_prefetch(options.max_prefetch).with_max_sample_streams(options.max_sample_streams).with_registry(Arc::clone(&options.registry)).with_shutdown(stop);
        let service = ReplayServiceServer::new(grpc).max_decoding_message_size(MAX_MESSAGE_BYTES).max_encoding_message_size(MAX_MESSAGE_BYTES);
        Routes::new(auth.wrap(service))
    };
    let readiness = Readiness { grpc_names: GRPC_NAMES, health: options.health.clone(), ready: std::future::ready(()) };
    serve_secured("the replay", listener, &options.security, options.shutdown_grace, readiness, make, shutdown).await.map_err(|e| match e {
        ServeError::Insecure { addr, .. } => ServerError::Insecure { addr },
        e => ServerError::Serve(e),
    })
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn default_config_is_loopback_and_valid() {
        let c = ServerConfig::default();
        assert!(c.listen.ip().is_loopback());
        assert_eq!(c.listen.port(), 50051);
        assert_eq!(c.metrics_listen, Some("127.0.0.1:9464".parse().unwrap()));
        assert_eq!(c.max_sample_streams, 256);
        c.validate().unwrap();
        let none = ServerConfig { max_sample_streams: 0, ..ServerConfig::default() };
        assert!(none.validate().unwrap_err().to_string().contains("max_sample_streams"));
    }

    #[test]
    fn non_loopback_needs_tls_and_token() {
        let mut c = ServerConfig { listen: "0.0.0.0:50051".parse().unwrap(), ..ServerConfig::default() };
        assert!(matches!(c.validate(), Err(ServerError::Insecure { .. })));
        c.tls = Some(TlsFiles { cert: "c.pem".into(), key: "k.pem".into() });
        assert!(matches!(c.validate(), Err(ServerError::Insecure { .. })), "TLS alone is not enough");
        c.tls = None;
        c.auth_token_file = Some("t".into());
        assert!(matches!(c.validate(), Err(ServerError::Insecure { .. })), "a token alone is not enough");
        c.tls = Some(TlsFiles { cert: "c.pem".into(), key: "k.pem".into() });
        c.validate().unwrap();
        c.auth_token_file = None;
        c.auth_token_files.actor = Some("a".into());
        c.validate().expect("a role token is a token");
    }

    #[test]
    fn metrics_stay_on_loopback_unless_a_token_guards_them() {
        let mut c = ServerConfig { metrics_listen: Some("0.0.0.0:9464".parse().unwrap()), ..ServerConfig::default() };
        let err = c.validate().unwrap_err();
        assert!(matches!(err, ServerError::InsecureMetrics { .. }), "{err}");
        assert!(err.to_string().contains("127.0.0.1:9464") && err.to_string().contains("metrics_token_file"), "{err}");
        c.metrics_token_file = Some("metrics-token".into());
        c.validate().expect("a token guards a routable /metrics");
        c.metrics_token_file = None;
        ServerConfig { metrics_listen: None, ..ServerConfig::default() }.validate().unwrap();
        ServerConfig { metrics_listen: Some("[::1]:0".parse().unwrap()), ..ServerConfig::default() }.validate().unwrap();
    }

    #[test]
    fn role_token_files_parse() {
        let c: ServerConfig = serde_yaml::from_str("auth_token_files: { actor: /s/actor, learner: /s/learner }\n").unwrap();
        assert_eq!(c.auth_token_files.actor.as_deref(), Some(Path::new("/s/actor")));
        assert_eq!(c.auth_token_files.learner.as_deref(), Some(Path::new("/s/learner")));
        assert!(serde_yaml::from_str::<ServerConfig>("auth_token_files: { sampler: /s/x }\n").is_err(), "unknown role");
    }

    #[test]
    fn yaml_overrides_defaults_and_rejects_unknown_keys() {
        let c: ServerConfig = serde_yaml::from_str("listen: 127.0.0.1:6000\ntable: { capacity: 10, obs_dim: 3, rate_limiter: { min_size_to_sample: 1 } }\n").unwrap();
        assert_eq!(c.listen.port(), 6000);
        assert_eq!(c.table.capacity, 10);
        assert_eq!(c.table.act_dim, 2);
        assert!(serde_yaml::from_str::<ServerConfig>("listne: 127.0.0.1:6000\n").is_err());
    }
}
