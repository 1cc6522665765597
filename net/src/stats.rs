//! Episode statistics: the actor's reporter (best effort, `StatsService.Report`) and the
//! collector that serves that RPC (run by `mapless train`, the run's supervisor, on loopback,
//! and by `mapless monitor` beside a compose cluster, with TLS and the actors' token).

use std::time::Duration;

use mapless_proto::MAX_MESSAGE_BYTES;
use mapless_proto::v1::stats_service_client::StatsServiceClient;
use mapless_proto::v1::stats_service_server::{StatsService, StatsServiceServer};
use mapless_proto::v1::{EpisodeStats, ProtocolVersion, ReportSummary};
use tokio::net::TcpListener;
use tokio::sync::{mpsc, watch};
use tokio_stream::wrappers::ReceiverStream;
use tonic::server::NamedService;
use tonic::service::Routes;
use tonic::{Request, Response, Status, Streaming};

use crate::endpoint::GrpcEndpoint;
use crate::health::Health;
use crate::serve::{Readiness, Security, ServeError, serve_secured};

/// Checks an [`EpisodeStats`] record against the contract (stats.proto).
pub fn validate(e: &EpisodeStats) -> Result<(), String> {
    if e.protocol_version != ProtocolVersion::V1 as i32 {
        return Err(format!("unsupported protocol_version {}", e.protocol_version));
    }
    if e.actor_id.is_empty() {
        return Err("actor_id is empty".into());
    }
    if e.episode_id == 0 {
        return Err("episode_id must be >= 1".into());
    }
    if e.terminal == e.truncated {
        return Err("exactly one of terminal and truncated must be set".into());
    }
    if !e.episode_return.is_finite() {
        return Err(format!("episode_return is {}", e.episode_return));
    }
    for (name, v) in [("eqs", e.eqs), ("ees", e.ees), ("distance_m", e.distance_m), ("shaded_time_s", e.shaded_time_s)] {
        if !v.is_finite() || v < 0.0 {
            return Err(format!("{name} is {v}; must be finite and >= 0"));
        }
    }
    Ok(())
}

/// Sends records from `rx` to the collector at `endpoint` until `rx` closes, reopening the
/// stream (with backoff) after a failure. Records in flight when a stream breaks may be lost
/// (statistics are best effort and never hold up training).
pub async fn report(endpoint: GrpcEndpoint, mut rx: mpsc::Receiver<EpisodeStats>) {
    let mut backoff = std::time::Duration::from_millis(100);
    let mut pending: Option<EpisodeStats> = None;
    loop {
        let first = match pending.take() {
            Some(e) => e,
            None => match rx.recv().await {
                Some(e) => e,
                None => return,
            },
        };
        let channel = match endpoint.connect("stats").await {
            Ok(c) => c,
            Err(e) => {
                tracing::debug!(error = %e, "stats collector unreachable; retrying");
                pending = Some(first);
                tokio::time::sleep(backoff).await;
                backoff = (backoff * 2).min(std::time::Duration::from_secs(5));
                continue;
            }
        };
        backoff = std::time::Duration::from_millis(100);
        let mut client = StatsServiceClient::new(channel).max_encoding_message_size(MAX_MESSAGE_BYTES);
        let (tx, inner) = mpsc::channel(256);
        let _ = tx.send(first).await;
        let Ok(request) = endpoint.request("stats", ReceiverStream::new(inner)) else { return };
        let call = tokio::spawn(async move { client.report(request).await });
        // Forward until our input ends or the stream breaks.
        loop {
            match rx.recv().await {
                Some(e) => {
                    if tx.send(e).await.is_err() {
                        break;
                    }
                    if call.is_finished() {
                        break;
                    }
                }
                None => {
                    drop(tx);
                    let _ = call.await;
                    return;
                }
            }
        }
        drop(tx);
        if let Ok(Err(status)) = call.await {
            tracing::debug!(status = %status.message(), "stats stream ended; reopening");
        }
    }
}

/// The `StatsService` of a run: valid records go to `tx`; invalid ones end their stream with
/// INVALID_ARGUMENT (earlier records are kept) and are counted by the caller through logs.
#[derive(Clone)]
pub struct Collector {
    tx: mpsc::Sender<EpisodeStats>,
}

#[tonic::async_trait]
impl StatsService for Collector {
    async fn report(&self, request: Request<Streaming<EpisodeStats>>) -> Result<Response<ReportSummary>, Status> {
        let mut stream = request.into_inner();
        let mut summary = ReportSummary::default();
        let mut sum = 0.0;
        while let Some(e) = stream.message().await? {
            if let Err(why) = validate(&e) {
                tracing::warn!(actor_id = %e.actor_id, reason = %why, "invalid episode record");
                return Err(if e.protocol_version != ProtocolVersion::V1 as i32 { Status::failed_precondition(why) } else { Status::invalid_argument(why) });
            }
            summary.episodes += 1;
            summary.terminal += u64::from(e.terminal);
            summary.truncated += u64::from(e.truncated);
            sum += e.episode_return;
            if self.tx.send(e).await.is_err() {
                return Err(Status::unavailable("the run is shutting down"));
            }
        }
        if summary.episodes > 0 {
            summary.mean_return = sum / summary.episodes as f64;
        }
        Ok(Response::new(summary))
    }
}

/// The gRPC names the collector's health service answers for.
const GRPC_NAMES: &[&str] = &[<StatsServiceServer<Collector> as NamedService>::NAME];

/// Serves a [`Collector`] on `listener` until `stop` turns true, with the gRPC health service
/// beside it (SERVING until `stop`), under the cluster's security rule ([`serve_secured`]): on
/// loopback (`mapless train`'s supervisor) `security` may be empty; anywhere else (the compose
/// cluster's `mapless monitor`) it needs TLS and a token, and `Report` takes the actor role's.
pub async fn serve_collector(listener: TcpListener, security: &Security, tx: mpsc::Sender<EpisodeStats>, mut stop: watch::Receiver<bool>) -> Result<(), ServeError> {
    let readiness = Readiness { grpc_names: GRPC_NAMES, health: Health::new(), ready: std::future::ready(()) };
    let make = |auth: crate::serve::BearerAuth, _stopped: watch::Receiver<bool>| Routes::new(auth.wrap(StatsServiceServer::new(Collector { tx }).max_decoding_message_size(MAX_MESSAGE_BYTES)));
    let shutdown = async move {
        let _ = stop.wait_for(|s| *s).await;
    };
    serve_secured("the stats collector", listener, security, Duration::from_secs(5), readiness, make, shutdown).await
}
