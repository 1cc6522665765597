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
//! The module has three layers, so that the libtorch-free parts can move to a crate that
//! actors link (actors must not link libtorch):
//! - pure: [`WeightsPublisher`], the service ([`WeightsGrpc`], [`serve`], [`run`]), the client
//!   ([`subscribe`]) and the `.safetensors` conversion ([`snapshot_to_safetensors`],
//!   [`snapshot_from_safetensors`], [`write_safetensors_file`], [`read_safetensors_file`]);
//! - tch: [`snapshot_from_tensors`] and [`tensors_from_snapshot`], the only functions here that
//!   name `tch` types.
//!
//! # The `.safetensors` layout of a snapshot
//!
//! Tensor name → dtype, shape, little-endian row-major data, exactly as in the snapshot. The
//! header's `__metadata__` holds the snapshot's free-form `metadata` map plus these reserved
//! keys (every key starting with `mapless.` is reserved; a snapshot whose own metadata uses
//! the prefix is refused):
//!
//! | key | value |
//! |---|---|
//! | `mapless.version` | the weights version, decimal |
//! | `mapless.algorithm` | `ddpg`, `td3` or `sac` |
//! | `mapless.obs_dim`, `mapless.act_dim` | decimal |
//! | `mapless.created_unix_ms` | decimal |
//! | `mapless.tensor_order` | JSON array of the tensor names in snapshot order (safetensors sorts them) |
//! | `mapless.data_crc32` | CRC-32 (IEEE) of the tensors' data concatenated in that order, 8 hex digits |
//!
//! safetensors itself checks the header and the offsets; the CRC catches flipped bits in the
//! data, which the format alone would load silently.

use std::collections::HashMap;
use std::fs;
use std::future::Future;
use std::io::Write as _;
use std::net::SocketAddr;
use std::path::{Path, PathBuf};
use std::pin::Pin;
use std::sync::Arc;
use std::time::{Duration, SystemTime, UNIX_EPOCH};

use mapless_proto::v1::weights_service_server::{WeightsService, WeightsServiceServer};
use mapless_proto::v1::{Algorithm, Dtype, NamedTensor, ProtocolVersion, SubscribeRequest, WeightsSnapshot};
use mapless_proto::{MAX_MESSAGE_BYTES, check_protocol_version};
use mapless_replay::server::{BearerAuth, Security};
use prost::Message as _;
use tokio::net::TcpListener;
use tokio::sync::{mpsc, watch};
use tokio_stream::Stream;
use tokio_stream::wrappers::ReceiverStream;
use tonic::service::interceptor::InterceptedService;
use tonic::transport::server::TcpIncoming;
use tonic::transport::{Identity, Server, ServerTlsConfig};
use tonic::{Request, Response, Status};
use tracing::{Instrument as _, debug, info, info_span, warn};

use crate::error::LearnerError;
use crate::source::GrpcEndpoint;

/// Default address of the learner's weights service: loopback only. Any other address needs
/// TLS and a bearer token (the replay service's rule, see [`serve`]).
pub const DEFAULT_WEIGHTS_LISTEN: &str = "127.0.0.1:50052";

/// Prefix of the `__metadata__` keys this module writes itself.
pub const RESERVED_METADATA_PREFIX: &str = "mapless.";
/// `__metadata__` key: the weights version.
pub const META_VERSION: &str = "mapless.version";
/// `__metadata__` key: `ddpg`, `td3` or `sac`.
pub const META_ALGORITHM: &str = "mapless.algorithm";
/// `__metadata__` key: observation length.
pub const META_OBS_DIM: &str = "mapless.obs_dim";
/// `__metadata__` key: action length.
pub const META_ACT_DIM: &str = "mapless.act_dim";
/// `__metadata__` key: publication time.
pub const META_CREATED_UNIX_MS: &str = "mapless.created_unix_ms";
/// `__metadata__` key: tensor names in snapshot order, a JSON array.
pub const META_TENSOR_ORDER: &str = "mapless.tensor_order";
/// `__metadata__` key: CRC-32 of the tensor data, 8 lowercase hex digits.
pub const META_DATA_CRC32: &str = "mapless.data_crc32";

/// HTTP/2 pings that find dead peers (a crashed actor host sends no RST).
const KEEPALIVE_INTERVAL: Duration = Duration::from_secs(10);
const KEEPALIVE_TIMEOUT: Duration = Duration::from_secs(20);

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
    /// TLS and bearer token, as for the replay service: optional on loopback, both required on
    /// any other address.
    pub security: Security,
    /// After the shutdown signal, how long open connections may take to close before they
    /// are cut.
    pub shutdown_grace: Duration,
}

impl Default for ServeOptions {
    fn default() -> Self {
        Self { security: Security::default(), shutdown_grace: Duration::from_secs(5) }
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

/// Serves the `WeightsService` over `publisher` on `listener` until `shutdown` resolves; then
/// every open stream ends with UNAVAILABLE, connections get an HTTP/2 GOAWAY, and it returns
/// at most `options.shutdown_grace` later.
///
/// Refuses a non-loopback listener without both TLS and a bearer token. Messages are limited
/// to [`MAX_MESSAGE_BYTES`] both ways.
pub async fn serve(listener: TcpListener, publisher: WeightsPublisher, options: ServeOptions, shutdown: impl Future<Output = ()> + Send + 'static) -> Result<(), LearnerError> {
    let addr = listener.local_addr().map_err(|e| serve_error("?".into(), format!("listener has no address: {e}")))?;
    let security = &options.security;
    if !addr.ip().is_loopback() && (security.tls.is_none() || security.token.is_none()) {
        return Err(serve_error(
            addr.to_string(),
            "refusing to serve on a non-loopback address without TLS and a bearer token: \
             anyone who can reach the port could read the policy. For a local run use 127.0.0.1"
                .into(),
        ));
    }
    let (stop_tx, stop_rx) = watch::channel(false);
    let service = WeightsGrpc::new(&publisher).with_shutdown(stop_rx.clone()).into_server();
    let service = InterceptedService::new(service, BearerAuth::new(security.token.as_deref()));
    let mut builder = Server::builder().http2_keepalive_interval(Some(KEEPALIVE_INTERVAL)).http2_keepalive_timeout(Some(KEEPALIVE_TIMEOUT));
    if let Some(tls) = &security.tls {
        builder = builder.tls_config(ServerTlsConfig::new().identity(Identity::from_pem(&tls.cert, &tls.key))).map_err(|e| serve_error(addr.to_string(), format!("TLS: {e}")))?;
    }
    info!(%addr, tls = security.tls.is_some(), token = security.token.is_some(), "weights gRPC serving");
    let incoming = TcpIncoming::from(listener).with_nodelay(Some(true));
    let signal = async move {
        shutdown.await;
        info!("weights service shutting down: ending open streams");
        let _ = stop_tx.send(true);
    };
    let serving = builder.add_service(service).serve_with_incoming_shutdown(incoming, signal);
    tokio::pin!(serving);
    let mut stopping = stop_rx;
    let grace = options.shutdown_grace;
    tokio::select! {
        result = &mut serving => result.map_err(|e| serve_error(addr.to_string(), e.to_string()))?,
        () = async {
            // Reachable only once the signal fired; its sender lives inside `serving`.
            if stopping.wait_for(|s| *s).await.is_ok() {
                tokio::time::sleep(grace).await;
            } else {
                std::future::pending::<()>().await;
            }
        } => warn!(?grace, "connections still open after the shutdown grace period; closing them"),
    }
    Ok(())
}

// ---------------------------------------------------------------------------------------------
// Client
// ---------------------------------------------------------------------------------------------

/// An open Subscribe stream, checked: every snapshot passes [`WeightsSnapshot::validate`] and
/// versions strictly increase. (The client lives in the libtorch-free `mapless-actor`
/// crate; this wrapper speaks [`LearnerError`].)
#[derive(Debug)]
pub struct WeightsSubscription(mapless_actor::weights::WeightsSubscription);

/// Opens a Subscribe stream at `endpoint` for versions `>= min_version` (0 or 1: any).
/// See [`mapless_actor::weights::subscribe`].
pub async fn subscribe(endpoint: &GrpcEndpoint, min_version: u64, subscriber_id: &str) -> Result<WeightsSubscription, LearnerError> {
    Ok(WeightsSubscription(mapless_actor::weights::subscribe(endpoint, min_version, subscriber_id).await?))
}

impl WeightsSubscription {
    /// The next snapshot; see [`mapless_actor::weights::WeightsSubscription::next`].
    pub async fn next(&mut self) -> Result<Option<WeightsSnapshot>, LearnerError> {
        Ok(self.0.next().await?)
    }

    /// Highest version received on this stream (`min_version - 1` before the first).
    pub fn last_version(&self) -> u64 {
        self.0.last_version()
    }
}

// ---------------------------------------------------------------------------------------------
// .safetensors (pure Rust)
// ---------------------------------------------------------------------------------------------

fn algorithm_name(algorithm: i32) -> Option<&'static str> {
    match Algorithm::try_from(algorithm).ok()? {
        Algorithm::Ddpg => Some("ddpg"),
        Algorithm::Td3 => Some("td3"),
        Algorithm::Sac => Some("sac"),
        Algorithm::Unspecified => None,
    }
}

fn algorithm_from_name(name: &str) -> Option<Algorithm> {
    match name.to_ascii_lowercase().as_str() {
        "ddpg" | "algorithm_ddpg" => Some(Algorithm::Ddpg),
        "td3" | "algorithm_td3" => Some(Algorithm::Td3),
        "sac" | "algorithm_sac" => Some(Algorithm::Sac),
        _ => None,
    }
}

fn to_st_dtype(dtype: Dtype) -> Option<safetensors::Dtype> {
    match dtype {
        Dtype::F32 => Some(safetensors::Dtype::F32),
        Dtype::F64 => Some(safetensors::Dtype::F64),
        Dtype::F16 => Some(safetensors::Dtype::F16),
        Dtype::Bf16 => Some(safetensors::Dtype::BF16),
        Dtype::Unspecified => None,
    }
}

fn from_st_dtype(dtype: safetensors::Dtype) -> Option<Dtype> {
    match dtype {
        safetensors::Dtype::F32 => Some(Dtype::F32),
        safetensors::Dtype::F64 => Some(Dtype::F64),
        safetensors::Dtype::F16 => Some(Dtype::F16),
        safetensors::Dtype::BF16 => Some(Dtype::Bf16),
        _ => None,
    }
}

fn data_crc32<'a>(data: impl IntoIterator<Item = &'a [u8]>) -> String {
    let mut hasher = crc32fast::Hasher::new();
    for chunk in data {
        hasher.update(chunk);
    }
    format!("{:08x}", hasher.finalize())
}

/// Encodes a snapshot as the bytes of a `.safetensors` file (layout in the module doc).
///
/// Validates the snapshot first ([`WeightsSnapshot::validate`]) and refuses metadata keys
/// with the reserved `mapless.` prefix.
pub fn snapshot_to_safetensors(snapshot: &WeightsSnapshot) -> Result<Vec<u8>, LearnerError> {
    let origin = || format!("snapshot version {}", snapshot.version);
    snapshot.validate().map_err(|e| invalid(origin(), e.to_string()))?;
    if let Some(key) = snapshot.metadata.keys().find(|k| k.starts_with(RESERVED_METADATA_PREFIX)) {
        return Err(invalid(origin(), format!("metadata key `{key}` uses the reserved prefix `{RESERVED_METADATA_PREFIX}`")));
    }
    let algorithm = algorithm_name(snapshot.algorithm).ok_or_else(|| invalid(origin(), format!("unknown algorithm {}", snapshot.algorithm)))?;

    let mut views = Vec::with_capacity(snapshot.tensors.len());
    for tensor in &snapshot.tensors {
        // validate() above guarantees a known dtype and a consistent byte length.
        let dtype = Dtype::try_from(tensor.dtype).ok().and_then(to_st_dtype).ok_or_else(|| invalid(origin(), format!("tensor `{}`: unknown dtype", tensor.name)))?;
        let shape = tensor.shape.iter().map(|&d| usize::try_from(d)).collect::<Result<Vec<usize>, _>>().map_err(|_| invalid(origin(), format!("tensor `{}`: dimension exceeds usize", tensor.name)))?;
        let view = safetensors::tensor::TensorView::new(dtype, shape, &tensor.data).map_err(|e| invalid(origin(), format!("tensor `{}`: {e}", tensor.name)))?;
        views.push((tensor.name.as_str(), view));
    }

    let order: Vec<&str> = snapshot.tensors.iter().map(|t| t.name.as_str()).collect();
    let mut metadata: HashMap<String, String> = snapshot.metadata.clone().into_iter().collect();
    metadata.insert(META_VERSION.into(), snapshot.version.to_string());
    metadata.insert(META_ALGORITHM.into(), algorithm.into());
    metadata.insert(META_OBS_DIM.into(), snapshot.obs_dim.to_string());
    metadata.insert(META_ACT_DIM.into(), snapshot.act_dim.to_string());
    metadata.insert(META_CREATED_UNIX_MS.into(), snapshot.created_unix_ms.to_string());
    metadata.insert(META_TENSOR_ORDER.into(), serde_json::to_string(&order).map_err(|e| invalid(origin(), e.to_string()))?);
    metadata.insert(META_DATA_CRC32.into(), data_crc32(snapshot.tensors.iter().map(|t| t.data.as_slice())));
    safetensors::serialize(views, Some(metadata)).map_err(|e| invalid(origin(), format!("safetensors: {e}")))
}

fn required<'a>(metadata: &'a HashMap<String, String>, key: &str, origin: &dyn Fn() -> String) -> Result<&'a str, LearnerError> {
    metadata.get(key).map(String::as_str).ok_or_else(|| invalid(origin(), format!("`__metadata__` has no `{key}`; not a mapless weights file")))
}

fn parse_number<T: std::str::FromStr>(metadata: &HashMap<String, String>, key: &str, origin: &dyn Fn() -> String) -> Result<T, LearnerError> {
    let text = required(metadata, key, origin)?;
    text.parse().map_err(|_| invalid(origin(), format!("`__metadata__.{key}` is `{text}`, not a number")))
}

/// Decodes the bytes of a `.safetensors` file written by [`snapshot_to_safetensors`]. `origin`
/// names the bytes in errors (a path, a URL).
///
/// Every problem is an [`LearnerError::InvalidWeights`] naming it: a malformed or truncated
/// header, offsets that do not cover the data, a missing reserved key, a dtype the contract
/// does not carry, a data checksum mismatch, or a snapshot that then fails
/// [`WeightsSnapshot::validate`].
pub fn snapshot_from_safetensors(bytes: &[u8], origin: &str) -> Result<WeightsSnapshot, LearnerError> {
    let origin_fn = || origin.to_owned();
    let origin_ref: &dyn Fn() -> String = &origin_fn;
    let not_safetensors = |e: safetensors::SafeTensorError| invalid(origin, format!("not a valid .safetensors file: {e}"));
    let (_, header) = safetensors::SafeTensors::read_metadata(bytes).map_err(not_safetensors)?;
    let file = safetensors::SafeTensors::deserialize(bytes).map_err(not_safetensors)?;
    let mut metadata = header.metadata().clone().unwrap_or_default();

    let version: u64 = parse_number(&metadata, META_VERSION, origin_ref)?;
    let algorithm_text = required(&metadata, META_ALGORITHM, origin_ref)?;
    let algorithm = algorithm_from_name(algorithm_text).ok_or_else(|| invalid(origin, format!("`__metadata__.{META_ALGORITHM}` is `{algorithm_text}`; expected ddpg, td3 or sac")))?;
    let obs_dim: u32 = parse_number(&metadata, META_OBS_DIM, origin_ref)?;
    let act_dim: u32 = parse_number(&metadata, META_ACT_DIM, origin_ref)?;
    let created_unix_ms: u64 = parse_number(&metadata, META_CREATED_UNIX_MS, origin_ref)?;
    let order: Vec<String> = match metadata.get(META_TENSOR_ORDER) {
        Some(text) => serde_json::from_str(text).map_err(|e| invalid(origin, format!("`__metadata__.{META_TENSOR_ORDER}` is not a JSON list of names: {e}")))?,
        // Written by another tool: file (offset) order.
        None => header.offset_keys(),
    };
    if order.len() != file.len() {
        return Err(invalid(origin, format!("`__metadata__.{META_TENSOR_ORDER}` names {} tensors, the file holds {}", order.len(), file.len())));
    }

    let mut tensors = Vec::with_capacity(order.len());
    for name in order {
        let view = file.tensor(&name).map_err(|e| invalid(origin, e.to_string()))?;
        let dtype = from_st_dtype(view.dtype()).ok_or_else(|| invalid(origin, format!("tensor `{name}` has dtype {}; weights carry F32, F64, F16 or BF16", view.dtype())))?;
        tensors.push(NamedTensor { name, shape: view.shape().iter().map(|&d| d as u64).collect(), dtype: dtype as i32, data: view.data().to_vec() });
    }
    if let Some(expected) = metadata.get(META_DATA_CRC32) {
        let actual = data_crc32(tensors.iter().map(|t| t.data.as_slice()));
        if !expected.eq_ignore_ascii_case(&actual) {
            return Err(invalid(origin, format!("tensor data checksum is {actual}, the header says {expected}: the file is corrupt")));
        }
    }
    metadata.retain(|k, _| !k.starts_with(RESERVED_METADATA_PREFIX));
    let snapshot =
        WeightsSnapshot { protocol_version: ProtocolVersion::V1 as i32, version, algorithm: algorithm as i32, created_unix_ms, obs_dim, act_dim, tensors, metadata: metadata.into_iter().collect() };
    snapshot.validate().map_err(|e| invalid(origin, e.to_string()))?;
    Ok(snapshot)
}

fn io_error(path: &Path, error: std::io::Error) -> LearnerError {
    LearnerError::FileIo { path: path.to_owned(), error }
}

/// Writes `bytes` to `path` atomically: a temporary file in the same directory (`tempfile`),
/// fsync, rename over `path` (`persist`), fsync of the directory. A crash leaves either the old
/// file or the new one, never a torn one. The one atomic write of the workspace's services (the
/// policy, checkpoints' `LATEST`, the run's config and summary, the weights version file).
pub fn write_file_atomically(path: &Path, bytes: &[u8]) -> Result<(), LearnerError> {
    let dir = match path.parent() {
        Some(d) if !d.as_os_str().is_empty() => d.to_owned(),
        _ => PathBuf::from("."),
    };
    // rw-r--r-- (less the umask) as `fs::write` makes them, not tempfile's private 0600: a
    // policy or a run folder is read by other users and containers.
    let mode = <fs::Permissions as std::os::unix::fs::PermissionsExt>::from_mode(0o644);
    let mut tmp = tempfile::Builder::new().prefix(".").suffix(".tmp").permissions(mode).tempfile_in(&dir).map_err(|e| io_error(&dir, e))?;
    tmp.write_all(bytes).map_err(|e| io_error(tmp.path(), e))?;
    tmp.as_file().sync_all().map_err(|e| io_error(tmp.path(), e))?;
    // A failed persist drops (removes) the temporary file.
    tmp.persist(path).map_err(|e| io_error(path, e.error))?;
    // The rename itself is durable only once the directory is.
    if let Ok(d) = fs::File::open(&dir) {
        d.sync_all().map_err(|e| io_error(&dir, e))?;
    }
    Ok(())
}

/// [`snapshot_to_safetensors`], written atomically to `path` ([`write_file_atomically`]).
pub fn write_safetensors_file(path: &Path, snapshot: &WeightsSnapshot) -> Result<(), LearnerError> {
    let bytes = snapshot_to_safetensors(snapshot)?;
    write_file_atomically(path, &bytes)
}

/// Reads a `.safetensors` file written by [`write_safetensors_file`].
pub fn read_safetensors_file(path: &Path) -> Result<WeightsSnapshot, LearnerError> {
    let bytes = fs::read(path).map_err(|e| io_error(path, e))?;
    snapshot_from_safetensors(&bytes, &path.display().to_string())
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
