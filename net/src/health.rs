//! Whether a process can do its job, told the standard ways, and the probe a container runs.
//!
//! ```text
//!   Health: Starting ──serve()──► Serving ──drain()──► Draining     one per process; drain is final
//!      ├─► grpc.health.v1.Health (tonic-health), served beside every gRPC service by
//!      │   serve::serve_secured, for "" (the server) and the service's own name:
//!      │   SERVING while Serving, NOT_SERVING otherwise; behind the same TLS and token
//!      └─► GET /healthz on the process's /metrics endpoint (metrics::serve): 200 / 503
//!          — the actors' only answer, since they serve no gRPC
//!
//!   `mapless-replay health`, `mapless-learner health` ─► grpc_probe ─► Check("") ─┐ exit 0: SERVING
//!   `mapless-actor health`                            ─► http_probe ─► /healthz  ─┘ exit 1: anything else
//! ```
//!
//! When each process serves: the replay once its table is open (its log recovered) and its
//! gRPC listener bound; the learner once it has published weights; an actor once it acts and
//! its sink is connected. Each drains (NOT_SERVING) from its stop signal on, while it finishes
//! what it holds. Exit codes follow Docker's HEALTHCHECK: 0 healthy, 1 unhealthy (2 is reserved
//! there), so "not serving" and "unreachable" both exit 1 and differ in their message.

use std::net::SocketAddr;
use std::path::PathBuf;
use std::process::ExitCode;
use std::sync::Arc;
use std::time::Duration;

use tokio::sync::watch;
use tonic_health::ServingStatus;
use tonic_health::pb::HealthCheckRequest;
use tonic_health::pb::health_check_response::ServingStatus as WireStatus;
use tonic_health::pb::health_client::HealthClient;
use tonic_health::pb::health_server::HealthServer;
use tonic_health::server::{HealthReporter, HealthService};

use crate::endpoint::{ClientSecurity, GrpcEndpoint, NetError};

/// Where a process is in its life, as far as its health answers go.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum Phase {
    /// Not yet able to do its job (the learner before its first publication).
    Starting,
    /// Doing its job.
    Serving,
    /// Stopping: finishing what it holds; never serves again.
    Draining,
}

/// One process's health, shared by its gRPC health service and its `/healthz`. Cheap to clone;
/// every clone is the same state. Starts [`Phase::Starting`].
#[derive(Clone, Debug)]
pub struct Health {
    phase: Arc<watch::Sender<Phase>>,
}

impl Default for Health {
    fn default() -> Self {
        Self::new()
    }
}

impl Health {
    pub fn new() -> Self {
        Health { phase: Arc::new(watch::channel(Phase::Starting).0) }
    }

    /// Starting → Serving; no effect once draining (a stop signal may come before readiness).
    pub fn serve(&self) {
        self.phase.send_if_modified(|p| {
            let was = *p;
            if was == Phase::Starting {
                *p = Phase::Serving;
            }
            was == Phase::Starting
        });
    }

    /// → Draining, for good.
    pub fn drain(&self) {
        self.phase.send_if_modified(|p| std::mem::replace(p, Phase::Draining) != Phase::Draining);
    }

    pub fn phase(&self) -> Phase {
        *self.phase.borrow()
    }

    pub fn is_serving(&self) -> bool {
        self.phase() == Phase::Serving
    }

    /// The gRPC health service for `""` and `services` (full gRPC names), already showing the
    /// current phase, and the future that keeps it following the phase (run it beside the
    /// server; it ends only when every [`Health`] clone is gone).
    pub(crate) async fn grpc(&self, services: &[&'static str]) -> (HealthServer<HealthService>, impl Future<Output = ()> + Send + 'static) {
        let reporter = HealthReporter::new();
        let names: Vec<&'static str> = std::iter::once("").chain(services.iter().copied()).collect();
        let mut phase = self.phase.subscribe();
        // Copied out first: the watch's read guard must not be held across the await.
        let now = *phase.borrow_and_update();
        set_all(&reporter, &names, now).await;
        let server = HealthServer::new(HealthService::from_health_reporter(reporter.clone()));
        let follow = async move {
            while phase.changed().await.is_ok() {
                let now = *phase.borrow_and_update();
                set_all(&reporter, &names, now).await;
            }
        };
        (server, follow)
    }
}

async fn set_all(reporter: &HealthReporter, names: &[&'static str], phase: Phase) {
    let status = if phase == Phase::Serving { ServingStatus::Serving } else { ServingStatus::NotServing };
    for name in names {
        reporter.set_service_status(name, status).await;
    }
}

/// Name of a wire status as the protocol spells it (`SERVING`, `NOT_SERVING`, ...).
pub fn status_name(status: i32) -> &'static str {
    WireStatus::try_from(status).map_or("an unknown status", |s| s.as_str_name())
}

/// `grpc.health.v1.Health/Check` for `service` (`""`: the whole server) at `endpoint`, with its
/// TLS and token; the wire status (see [`status_name`]).
pub async fn check(endpoint: &GrpcEndpoint, service: &str) -> Result<i32, NetError> {
    let channel = endpoint.connect("health").await?;
    let request = endpoint.request("health", HealthCheckRequest { service: service.to_owned() })?;
    let response = HealthClient::new(channel).check(request).await.map_err(|s| endpoint.status_error("health", &s))?;
    Ok(response.into_inner().status)
}

/// Flags of `mapless-replay health` and `mapless-learner health`; each may come from the
/// environment instead (`MAPLESS_HEALTH_*`), so an image's HEALTHCHECK names no paths.
#[derive(Clone, Debug, clap::Args)]
pub struct GrpcProbeArgs {
    /// The service's gRPC address, `host:port` or a URI [default: its default listen address].
    #[arg(env = "MAPLESS_HEALTH_ADDR")]
    pub addr: Option<String>,
    /// CA certificate (PEM) to trust: the service speaks TLS.
    #[arg(long, env = "MAPLESS_HEALTH_TLS_CA_FILE", value_name = "FILE")]
    pub tls_ca_file: Option<PathBuf>,
    /// Name to check the service's certificate against [default: the address's host].
    #[arg(long, env = "MAPLESS_HEALTH_TLS_DOMAIN")]
    pub tls_domain: Option<String>,
    /// File holding the bearer token the service checks.
    #[arg(long, env = "MAPLESS_HEALTH_TOKEN_FILE", value_name = "FILE")]
    pub token_file: Option<PathBuf>,
    /// The service to ask about, by its gRPC name [default: "", the whole server].
    #[arg(long, default_value = "")]
    pub service: String,
    /// Longest the whole probe may take.
    #[arg(long, default_value_t = 5_000)]
    pub timeout_ms: u64,
}

/// Flags of `mapless-actor health`.
#[derive(Clone, Debug, clap::Args)]
pub struct HttpProbeArgs {
    /// The process's /metrics address (its `metrics_listen`), `host:port`.
    #[arg(env = "MAPLESS_HEALTH_ADDR")]
    pub addr: Option<SocketAddr>,
    /// Longest the whole probe may take.
    #[arg(long, default_value_t = 5_000)]
    pub timeout_ms: u64,
}

/// Runs a probe to its exit code: prints `SERVING …` on stdout and exits 0, or says why not on
/// stderr and exits 1.
fn finish(program: &str, outcome: Result<String, String>) -> ExitCode {
    match outcome {
        Ok(line) => {
            println!("{line}");
            ExitCode::SUCCESS
        }
        Err(why) => {
            eprintln!("{program} health: {why}");
            ExitCode::FAILURE
        }
    }
}

fn block_on_with_timeout<F: Future<Output = Result<String, String>>>(timeout_ms: u64, what: &str, f: F) -> Result<String, String> {
    let rt = tokio::runtime::Builder::new_current_thread().enable_all().build().map_err(|e| format!("cannot start the async runtime: {e}"))?;
    let limit = Duration::from_millis(timeout_ms);
    rt.block_on(async { tokio::time::timeout(limit, f).await.unwrap_or_else(|_| Err(format!("no answer from {what} within {limit:?}"))) })
}

/// `PROGRAM health` for a gRPC service: Check at `args.addr` (else `default_addr`).
pub fn grpc_probe(program: &str, args: &GrpcProbeArgs, default_addr: &str) -> ExitCode {
    let addr = args.addr.as_deref().unwrap_or(default_addr);
    let outcome = block_on_with_timeout(args.timeout_ms, addr, async {
        let security = ClientSecurity { tls_ca_file: args.tls_ca_file.clone(), tls_domain: args.tls_domain.clone(), token_file: args.token_file.clone() };
        let endpoint = security.endpoint(addr).map_err(|e| e.to_string())?.with_connect_timeout(Duration::from_millis(args.timeout_ms));
        let service = if args.service.is_empty() { "the server".to_owned() } else { args.service.clone() };
        match check(&endpoint, &args.service).await {
            Ok(s) if s == WireStatus::Serving as i32 => Ok(format!("SERVING: {service} at {}", endpoint.uri())),
            Ok(s) => Err(format!("{}: {service} at {}", status_name(s), endpoint.uri())),
            Err(e) => Err(format!("unreachable or refused: {e}")),
        }
    });
    finish(program, outcome)
}

/// `PROGRAM health` for a process without gRPC: `GET /healthz` at `args.addr`.
pub fn http_probe(program: &str, args: &HttpProbeArgs) -> ExitCode {
    // Not a clap requirement: clap's usage errors exit 2, which Docker reserves.
    let Some(addr) = args.addr else {
        return finish(program, Err("give the process's /metrics address (its metrics_listen) as ADDR or in MAPLESS_HEALTH_ADDR".into()));
    };
    let outcome = block_on_with_timeout(args.timeout_ms, &addr.to_string(), async move {
        match get_healthz(addr).await {
            Ok(200) => Ok(format!("SERVING: http://{addr}/healthz")),
            Ok(503) => Err(format!("NOT_SERVING: http://{addr}/healthz")),
            Ok(code) => Err(format!("http://{addr}/healthz answered HTTP {code}")),
            Err(e) => Err(format!("unreachable: http://{addr}/healthz: {e}")),
        }
    });
    finish(program, outcome)
}

/// The HTTP status of `GET /healthz` at `addr` (hyper's HTTP/1 client, one connection).
pub async fn get_healthz(addr: SocketAddr) -> Result<u16, String> {
    let stream = tokio::net::TcpStream::connect(addr).await.map_err(|e| e.to_string())?;
    let (mut sender, connection) = hyper::client::conn::http1::handshake(hyper_util::rt::TokioIo::new(stream)).await.map_err(|e| e.to_string())?;
    let request = hyper::Request::get("/healthz").header(hyper::header::HOST, addr.to_string()).body(String::new()).map_err(|e| e.to_string())?;
    // The connection is driven by its own task, as hyper's client examples do; it ends when
    // `sender` is dropped.
    tokio::spawn(connection);
    let response = sender.send_request(request).await.map_err(|e| e.to_string())?;
    Ok(response.status().as_u16())
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn draining_is_final_and_serve_only_leaves_starting() {
        let h = Health::new();
        assert_eq!(h.phase(), Phase::Starting);
        h.serve();
        assert!(h.is_serving());
        h.drain();
        h.serve();
        assert_eq!(h.phase(), Phase::Draining, "a late readiness must not undo a stop");
        let early = Health::new();
        early.drain();
        early.serve();
        assert!(!early.is_serving());
    }

    #[test]
    fn status_names_are_the_protocols() {
        assert_eq!(status_name(WireStatus::Serving as i32), "SERVING");
        assert_eq!(status_name(WireStatus::NotServing as i32), "NOT_SERVING");
        assert_eq!(status_name(42), "an unknown status");
    }
}

/// Flags of `mapless-replay info`.
#[derive(Clone, Debug, clap::Args)]
pub struct InfoArgs {
    /// The replay's gRPC address, `host:port` or a URI [default: its default listen address].
    pub addr: Option<String>,
    /// CA certificate (PEM) to trust: the replay speaks TLS.
    #[arg(long, value_name = "FILE")]
    pub tls_ca_file: Option<PathBuf>,
    /// Name to check the replay's certificate against [default: the address's host].
    #[arg(long)]
    pub tls_domain: Option<String>,
    /// File holding a bearer token the replay accepts (ServerInfo needs the learner role or
    /// the full-rights token).
    #[arg(long, value_name = "FILE")]
    pub token_file: Option<PathBuf>,
    /// Longest the whole call may take.
    #[arg(long, default_value_t = 5_000)]
    pub timeout_ms: u64,
}

/// `mapless-replay info`: the replay's ServerInfo (its table, and what each actor has stored),
/// one line per actor; exit 1 with the status when unreachable or refused.
pub fn replay_info(args: &InfoArgs, default_addr: &str) -> ExitCode {
    use mapless_proto::v1::{ProtocolVersion, ServerInfoRequest};
    let addr = args.addr.as_deref().unwrap_or(default_addr);
    let outcome = block_on_with_timeout(args.timeout_ms, addr, async {
        let security = ClientSecurity { tls_ca_file: args.tls_ca_file.clone(), tls_domain: args.tls_domain.clone(), token_file: args.token_file.clone() };
        let endpoint = security.endpoint(addr).map_err(|e| e.to_string())?.with_connect_timeout(Duration::from_millis(args.timeout_ms));
        let mut client = crate::sample::connect_client(&endpoint).await.map_err(|e| e.to_string())?;
        let request = endpoint.request("replay", ServerInfoRequest { protocol_version: ProtocolVersion::V1 as i32 }).map_err(|e| e.to_string())?;
        let info = client.server_info(request).await.map_err(|s| endpoint.status_error("replay", &s).to_string())?.into_inner();
        let mut out = format!(
            "table {}: {} rows of {} (obs {}, act {}), {} inserted since it was created; {} actors",
            info.table,
            info.size,
            info.capacity,
            info.obs_dim,
            info.act_dim,
            info.inserts_total,
            info.actors.len()
        );
        for a in &info.actors {
            out.push_str(&format!("\nactor {} rows={} batches={} duplicate_batches={} last_sequence={}", a.actor_id, a.rows, a.batches, a.duplicate_batches, a.last_sequence));
        }
        Ok(out)
    });
    match outcome {
        Ok(text) => {
            println!("{text}");
            ExitCode::SUCCESS
        }
        Err(why) => {
            eprintln!("mapless-replay info: {why}");
            ExitCode::FAILURE
        }
    }
}
