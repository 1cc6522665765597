//! Versioned policy weights: published by the learner, followed by the actors
//! (`WeightsService.Subscribe`, proto/mapless/v1/weights.proto), and stored as `.safetensors`.
//!
//! ```text
//!  update thread ─publish(v)─► WeightsPublisher ── tokio watch: the newest snapshot only
//!                                   │ (never blocks; a clone is an Arc)
//!        ┌──────────────────────────┼──────────────────────────┐
//!   Subscribe task             Subscribe task             Subscribe task    one per stream,
//!   [≤ 1 queued]               [≤ 1 queued]               [≤ 1 queued]      newest-wins
//!        ▼                          ▼                          ▼
//!    actor: subscribe(endpoint, min_version) ─► WeightsSubscription::next()
//! ```
//!
//! Memory per subscriber is bounded by two snapshots (one queued in its channel, one being
//! encoded); a subscriber slower than the learner skips versions instead of queueing them.
//!
//! Here: the publishing side — [`WeightsPublisher`] and the service ([`WeightsGrpc`], [`serve`],
//! [`run`]) — and the only functions that name `tch` types, [`snapshot_from_tensors`] and
//! [`tensors_from_snapshot`]. The client that follows the stream is
//! `mapless_net::weights::{subscribe, follow}`; the `.safetensors` files are
//! `mapless_proto::weights_file`. Neither needs libtorch.
//!
//! The `.safetensors` layout of a snapshot and its codec live in
//! [`mapless_proto::weights_file`] (actors and `mapless eval` read policies without libtorch).

use std::collections::HashMap;
use std::future::Future;
use std::net::SocketAddr;
use std::pin::Pin;
use std::sync::Arc;
use std::time::{Duration, SystemTime, UNIX_EPOCH};

use mapless_net::health::Health;
use mapless_net::serve::{Readiness, Security, serve_secured};
use mapless_proto::v1::weights_service_server::{WeightsService, WeightsServiceServer};
use mapless_proto::v1::{Algorithm, NamedTensor, ProtocolVersion, SubscribeRequest, WeightsSnapshot};
use mapless_proto::{MAX_MESSAGE_BYTES, check_protocol_version};
use prost::Message as _;
use tokio::net::TcpListener;
use tokio::sync::{mpsc, watch};
use tokio_stream::Stream;
use tokio_stream::wrappers::ReceiverStream;
use tonic::server::NamedService;
use tonic::service::Routes;
use tonic::{Request, Response, Status};
use tracing::{Instrument as _, debug, info, info_span, warn};

use crate::error::LearnerError;

/// Default address of the learner's weights service: loopback only. Any other address needs
/// TLS and a bearer token (the replay service's rule, see [`serve`]).
pub const DEFAULT_WEIGHTS_LISTEN: &str = "127.0.0.1:50052";

/// Newest published snapshot; `None` before the first publication.
type Latest = Option<Arc<WeightsSnapshot>>;

fn invalid(origin: impl Into<String>, reason: impl Into<String>) -> LearnerError {
    LearnerError::InvalidWeights { origin: origin.into(), reason: reason.into() }
}

/// Milliseconds since the Unix epoch (0 if the clock is before it).
pub fn unix_ms_now() -> u64 {
    SystemTime::now().duration_since(UNIX_EPOCH).map(|d| d.as_millis() as u64).unwrap_or(0)
}

// ---------------------------------------------------------------------------------------------
// Publisher
// ---------------------------------------------------------------------------------------------

/// Holds the newest published snapshot and wakes every subscriber stream.
///
/// Cheap to clone (an `Arc`), `Send + Sync`. [`WeightsPublisher::publish`] is synchronous and
/// O(1) apart from its checks (validation and the encoded size, O(bytes)): it swaps one
/// pointer under a short lock and never waits for subscribers, however slow. Only the newest
/// snapshot is kept.
#[derive(Clone)]
pub struct WeightsPublisher {
    latest: Arc<watch::Sender<Latest>>,
}

impl std::fmt::Debug for WeightsPublisher {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.debug_struct("WeightsPublisher").field("latest_version", &self.latest_version()).field("subscribers", &self.subscriber_count()).finish()
    }
}

impl Default for WeightsPublisher {
    fn default() -> Self {
        Self::new()
    }
}

impl WeightsPublisher {
    /// A publisher with nothing published yet.
    pub fn new() -> Self {
        let (latest, _) = watch::channel(None);
        Self { latest: Arc::new(latest) }
    }

    /// Makes `snapshot` the newest version and returns its version.
    ///
    /// Refuses (and keeps the previous snapshot) a snapshot that fails
    /// [`WeightsSnapshot::validate`], whose version is not strictly above the newest published
    /// one, or whose encoding exceeds [`MAX_MESSAGE_BYTES`] (no subscriber could receive it).
    pub fn publish(&self, snapshot: WeightsSnapshot) -> Result<u64, LearnerError> {
        let version = snapshot.version;
        let origin = || format!("publish version {version}");
        snapshot.validate().map_err(|e| invalid(origin(), e.to_string()))?;
        let bytes = snapshot.encoded_len();
        if bytes > MAX_MESSAGE_BYTES {
            return Err(invalid(origin(), format!("encodes to {bytes} bytes, above the {MAX_MESSAGE_BYTES}-byte message limit")));
        }
        let snapshot = Arc::new(snapshot);
        let mut newest = 0;
        // Check and swap under the channel's lock, so concurrent publishers cannot reorder.
        let replaced = self.latest.send_if_modified(|latest| {
            newest = latest.as_ref().map_or(0, |s| s.version);
            if version <= newest {
                return false;
            }
            *latest = Some(snapshot);
            true
        });
        if !replaced {
            return Err(invalid(origin(), format!("version {version} is not newer than the published version {newest}; versions strictly increase")));
        }
        debug!(version, bytes, "weights published");
        Ok(version)
    }

    /// The newest published snapshot, if any.
    pub fn latest(&self) -> Option<Arc<WeightsSnapshot>> {
        self.latest.borrow().clone()
    }

    /// The newest published version; 0 before the first publication.
    pub fn latest_version(&self) -> u64 {
        self.latest.borrow().as_ref().map_or(0, |s| s.version)
    }

    /// Open subscriber streams (plus services built on this publisher that hold a receiver).
    pub fn subscriber_count(&self) -> usize {
        self.latest.receiver_count()
    }

    fn receiver(&self) -> watch::Receiver<Latest> {
        self.latest.subscribe()
    }
}

// ---------------------------------------------------------------------------------------------
// Service
// ---------------------------------------------------------------------------------------------

/// The `WeightsService` implementation over a [`WeightsPublisher`]. Transport set-up is in
/// [`serve`]; tests and embedders may also add it to their own tonic server.
pub struct WeightsGrpc {
    latest: watch::Receiver<Latest>,
    stopping: Option<watch::Receiver<bool>>,
}

impl WeightsGrpc {
    /// Serves what `publisher` publishes.
    pub fn new(publisher: &WeightsPublisher) -> Self {
        Self { latest: publisher.receiver(), stopping: None }
    }

    /// Ends every stream with UNAVAILABLE once `stopping` turns true.
    pub fn with_shutdown(mut self, stopping: watch::Receiver<bool>) -> Self {
        self.stopping = Some(stopping);
        self
    }

    /// The service wrapped for tonic, with [`MAX_MESSAGE_BYTES`] limits both ways.
    pub fn into_server(self) -> WeightsServiceServer<Self> {
        WeightsServiceServer::new(self).max_decoding_message_size(MAX_MESSAGE_BYTES).max_encoding_message_size(MAX_MESSAGE_BYTES)
    }
}

/// Resolves when `stopping` turns true; never if there is no signal or its sender is gone
/// without stopping.
async fn stopped(stopping: &mut Option<watch::Receiver<bool>>) {
    match stopping {
        Some(rx) => {
            if rx.wait_for(|stop| *stop).await.is_err() {
                std::future::pending::<()>().await;
            }
        }
        None => std::future::pending::<()>().await,
    }
}

fn shutting_down() -> Status {
    Status::unavailable("the learner's weights service is shutting down; reconnect with min_version = last received + 1")
}

/// Feeds one Subscribe stream. Invariant: `sent` is the highest version this stream has
/// delivered (or the client already has), so every send is strictly newer than the last.
async fn feed_subscriber(mut latest: watch::Receiver<Latest>, mut stopping: Option<watch::Receiver<bool>>, mut sent: u64, tx: mpsc::Sender<Result<WeightsSnapshot, Status>>) {
    let mut delivered = 0u64;
    loop {
        // Newest first: whatever was published while we waited on a slow client is skipped.
        let next = latest.borrow_and_update().as_ref().filter(|s| s.version > sent).cloned();
        if let Some(snapshot) = next {
            let version = snapshot.version;
            let message = WeightsSnapshot::clone(&snapshot);
            drop(snapshot);
            tokio::select! {
                biased;
                () = stopped(&mut stopping) => break,
                sent_ok = tx.send(Ok(message)) => {
                    if sent_ok.is_err() {
                        debug!(delivered, "subscriber went away");
                        return;
                    }
                }
            }
            sent = version;
            delivered += 1;
            debug!(version, "snapshot queued for subscriber");
            continue;
        }
        tokio::select! {
            biased;
            () = stopped(&mut stopping) => break,
            () = tx.closed() => {
                debug!(delivered, "subscriber went away");
                return;
            }
            changed = latest.changed() => {
                if changed.is_err() {
                    // Every publisher handle is gone: nothing new will ever come.
                    let _ = tx
                        .send(Err(Status::unavailable("the learner stopped publishing weights")))
                        .await;
                    return;
                }
            }
        }
    }
    info!(delivered, "ending subscriber stream: shutting down");
    let _ = tx.send(Err(shutting_down())).await;
}

#[tonic::async_trait]
impl WeightsService for WeightsGrpc {
    type SubscribeStream = Pin<Box<dyn Stream<Item = Result<WeightsSnapshot, Status>> + Send>>;

    async fn subscribe(&self, request: Request<SubscribeRequest>) -> Result<Response<Self::SubscribeStream>, Status> {
        let peer = request.remote_addr();
        let request = request.into_inner();
        let span = info_span!(
            "Subscribe",
            subscriber_id = %request.subscriber_id,
            min_version = request.min_version,
            peer = ?peer
        );
        if let Err(e) = check_protocol_version(request.protocol_version) {
            span.in_scope(|| warn!(error = %e, "subscribe refused"));
            return Err(e.to_status());
        }
        if self.stopping.as_ref().is_some_and(|s| *s.borrow()) {
            return Err(shutting_down());
        }
        span.in_scope(|| info!("subscriber stream opened"));
        // Capacity 1: at most one snapshot waits for the client; the task holds at most one
        // more. Anything published meanwhile replaces, not queues.
        let (tx, rx) = mpsc::channel(1);
        // 0 and 1 both mean "any".
        let already_have = request.min_version.saturating_sub(1);
        tokio::spawn(feed_subscriber(self.latest.clone(), self.stopping.clone(), already_have, tx).instrument(span));
        Ok(Response::new(Box::pin(ReceiverStream::new(rx))))
    }
}

/// How [`serve`] runs.
#[derive(Clone, Debug)]
pub struct ServeOptions {
    /// TLS and bearer tokens, as for the replay service: optional on loopback, TLS and a token
    /// required on any other address. `Subscribe` needs the actor role (or the full-rights
    /// token); refusals are counted in `security.refusals`.
    pub security: Security,
    /// After the shutdown signal, how long open connections may take to close before they
    /// are cut.
    pub shutdown_grace: Duration,
    /// What the gRPC health service reports: SERVING once the publisher holds a snapshot (an
    /// actor that subscribes gets weights at once), NOT_SERVING before, and from the shutdown
    /// signal or the holder's [`Health::drain`] on (the learner drains at its stop signal,
    /// while it finishes its last update and checkpoint).
    pub health: Health,
}

impl Default for ServeOptions {
    fn default() -> Self {
        Self { security: Security::default(), shutdown_grace: Duration::from_secs(5), health: Health::new() }
    }
}

/// Serves `publisher` on `listener` with plain HTTP/2 and no token (loopback listeners only)
/// until `shutdown` resolves.
pub async fn run(listener: TcpListener, publisher: WeightsPublisher, shutdown: impl Future<Output = ()> + Send + 'static) -> Result<(), LearnerError> {
    serve(listener, publisher, ServeOptions::default(), shutdown).await
}

/// Binds `addr` (e.g. [`DEFAULT_WEIGHTS_LISTEN`]) and serves `publisher` on it; see [`serve`].
pub async fn bind_and_serve(addr: SocketAddr, publisher: WeightsPublisher, options: ServeOptions, shutdown: impl Future<Output = ()> + Send + 'static) -> Result<(), LearnerError> {
    let listener = TcpListener::bind(addr).await.map_err(|e| serve_error(addr.to_string(), format!("cannot bind: {e}")))?;
    serve(listener, publisher, options, shutdown).await
}

fn serve_error(addr: String, reason: String) -> LearnerError {
    LearnerError::Grpc { service: "weights", endpoint: addr, code: tonic::Code::Unavailable, message: reason }
}

/// The gRPC names the health service answers for, besides `""`.
const GRPC_NAMES: &[&str] = &[<WeightsServiceServer<WeightsGrpc> as NamedService>::NAME];

/// Serves `publisher` on `listener` until `shutdown` resolves, with `options.security`'s TLS and
/// token (`mapless_net::serve::serve_secured`: a non-loopback listener without both is
/// refused). Open Subscribe streams end with UNAVAILABLE at shutdown. Health: see
/// [`ServeOptions::health`].
pub async fn serve(listener: TcpListener, publisher: WeightsPublisher, options: ServeOptions, shutdown: impl Future<Output = ()> + Send + 'static) -> Result<(), LearnerError> {
    let addr = listener.local_addr().map_or_else(|_| "?".to_owned(), |a| a.to_string());
    let mut published = publisher.receiver();
    let ready = async move {
        // An Err (every sender gone) means nothing will ever be published: stay not serving.
        if published.wait_for(Option::is_some).await.is_err() {
            std::future::pending::<()>().await;
        }
    };
    let readiness = Readiness { grpc_names: GRPC_NAMES, health: options.health.clone(), ready };
    let make = |auth: mapless_net::BearerAuth, stop| Routes::new(auth.wrap(WeightsGrpc::new(&publisher).with_shutdown(stop).into_server()));
    serve_secured("the weights service", listener, &options.security, options.shutdown_grace, readiness, make, shutdown).await.map_err(|e| serve_error(addr, e.to_string()))
}

// ---------------------------------------------------------------------------------------------
// tch (the only part that names libtorch types)
// ---------------------------------------------------------------------------------------------

/// Builds a snapshot from the policy's parameters, in the order and with the names given.
///
/// Each tensor is detached, converted to f32 (floating-point kinds only; integer or bool
/// tensors are refused), moved to the CPU, made contiguous and copied out row-major as
/// little-endian bytes. Non-finite values are refused (an actor must never load NaN
/// weights), naming the tensor and the element. `created_unix_ms` is now; the result passes
/// [`WeightsSnapshot::validate`].
pub fn snapshot_from_tensors(
    version: u64,
    algorithm: Algorithm,
    obs_dim: usize,
    act_dim: usize,
    tensors: &[(String, tch::Tensor)],
    metadata: HashMap<String, String>,
) -> Result<WeightsSnapshot, LearnerError> {
    let origin = || format!("tensors for version {version}");
    let dim = |name: &str, d: usize| u32::try_from(d).map_err(|_| invalid(origin(), format!("{name} {d} exceeds u32")));
    let mut named = Vec::with_capacity(tensors.len());
    for (name, tensor) in tensors {
        let kind = tensor.f_kind()?;
        if !matches!(kind, tch::Kind::Float | tch::Kind::Double | tch::Kind::Half | tch::Kind::BFloat16) {
            return Err(invalid(origin(), format!("tensor `{name}` has kind {kind:?}; weights are floating point")));
        }
        let cpu = tch::no_grad(|| tensor.f_detach()?.f_to_kind(tch::Kind::Float)?.f_to_device(tch::Device::Cpu)?.f_contiguous())?;
        let shape = cpu.size().iter().map(|&d| u64::try_from(d)).collect::<Result<Vec<u64>, _>>().map_err(|_| invalid(origin(), format!("tensor `{name}` has a negative dimension")))?;
        let numel = cpu.numel();
        let mut values = vec![0f32; numel];
        cpu.f_copy_data(&mut values, numel)?;
        if let Some(i) = values.iter().position(|v| !v.is_finite()) {
            return Err(invalid(origin(), format!("tensor `{name}` element {i} is {}; refusing to publish non-finite weights", values[i])));
        }
        let named_tensor = NamedTensor::from_f32(name.clone(), shape, &values).map_err(|e| invalid(origin(), e.to_string()))?;
        named.push(named_tensor);
    }
    let snapshot = WeightsSnapshot {
        protocol_version: ProtocolVersion::V1 as i32,
        version,
        algorithm: algorithm as i32,
        created_unix_ms: unix_ms_now(),
        obs_dim: dim("obs_dim", obs_dim)?,
        act_dim: dim("act_dim", act_dim)?,
        tensors: named,
        metadata,
    };
    snapshot.validate().map_err(|e| invalid(origin(), e.to_string()))?;
    Ok(snapshot)
}

/// The snapshot's tensors as CPU `tch` tensors (F32 only), in snapshot order, bit-exact.
pub fn tensors_from_snapshot(snapshot: &WeightsSnapshot) -> Result<Vec<(String, tch::Tensor)>, LearnerError> {
    let origin = || format!("snapshot version {}", snapshot.version);
    snapshot
        .tensors
        .iter()
        .map(|t| {
            let values = t.to_f32_vec().map_err(|e| invalid(origin(), e.to_string()))?;
            let shape = t.shape.iter().map(|&d| i64::try_from(d)).collect::<Result<Vec<i64>, _>>().map_err(|_| invalid(origin(), format!("tensor `{}`: dimension exceeds i64", t.name)))?;
            let tensor = tch::Tensor::f_from_slice(&values)?.f_reshape(shape.as_slice())?;
            Ok((t.name.clone(), tensor))
        })
        .collect()
}
