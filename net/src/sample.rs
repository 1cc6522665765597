//! The learner's replay client: minibatches from the replay service's `Sample` stream, and
//! priority updates back (`UpdatePriorities`), over one background thread.
//!
//! ```text
//!  SampleClient: caller ◄── bounded queue (queue_depth) ◄── sample task ◄══ Sample stream (prefetch)
//!                caller ──► bounded queue ──► priority task ══► UpdatePriorities (async)
//!                           └──────── background thread: current-thread tokio runtime ──┘
//! ```
//!
//! The background thread keeps its queue full, so `next_batch` returns at once whenever the
//! replay service keeps up; decoding and validation happen off the caller's thread. The
//! stream's flow-control window is sized to the prefetch ([`sample_stream_window`]), so a
//! priority update shows in the minibatches within about `server_prefetch` + `queue_depth` of
//! them (plus what the transport buffers, ~64 KiB), not after the megabytes a default HTTP/2
//! window lets the server push ahead. When the stream breaks (the service restarts, the
//! network drops) it reconnects with exponential backoff and the caller merely waits. Errors
//! that retrying cannot fix (wrong table, wrong token, a protocol or dims mismatch) stop the
//! client: `next_batch` returns [`NetError::Stopped`] from then on.
//!
//! TLS and the bearer token come from the [`GrpcEndpoint`]. The client hands out
//! `mapless.v1.SampledBatch`es as received (validated); turning them into tensors is the
//! learner's business.

use std::sync::atomic::{AtomicBool, AtomicU64, Ordering};
use std::sync::mpsc::{Receiver, RecvTimeoutError, SyncSender, TrySendError};
use std::sync::{Arc, Mutex};
use std::thread::JoinHandle;
use std::time::Duration;

use mapless_proto::MAX_MESSAGE_BYTES;
use mapless_proto::v1::replay_service_client::ReplayServiceClient;
use mapless_proto::v1::{PriorityUpdate, PriorityUpdateResponse, ProtocolVersion, SampleRequest, SampledBatch, Selector, ServerInfoRequest};
use tokio::sync::{Notify, watch};
use tonic::Code;
use tonic::transport::Channel;
use tracing::{debug, info, warn};

use crate::endpoint::{GrpcEndpoint, NetError};

/// The client name in [`NetError::ClientConfig`] and [`NetError::Stopped`].
const CLIENT: &str = "sample client";

fn config_error(reason: String) -> NetError {
    NetError::ClientConfig { client: CLIENT, reason }
}

fn stopped(reason: String) -> NetError {
    NetError::Stopped { client: CLIENT, reason }
}

/// What a [`SampleClient`] has done and what went wrong, for logs and TensorBoard.
#[derive(Clone, Debug, Default, PartialEq)]
pub struct SampleStats {
    /// Minibatches handed to the caller.
    pub batches: u64,
    /// Sample streams (re)opened after the first one.
    pub reconnects: u64,
    /// Sample streams that broke or could not be opened (each is followed by a backoff).
    pub stream_errors: u64,
    /// Minibatches received that failed `SampledBatch::validate` and were dropped.
    pub invalid_batches: u64,
    /// Priority updates acknowledged by the service (or applied, by a sampler in the same
    /// process that keeps these counters).
    pub priority_updates: u64,
    /// Priority updates that failed after retries and were dropped.
    pub priority_update_errors: u64,
    /// Priority updates dropped because the outgoing queue was full.
    pub priority_updates_dropped: u64,
    /// The most recent error, if any.
    pub last_error: Option<String>,
}

/// How a [`SampleClient`] samples. [`SampleConfig::new`] gives the defaults.
#[derive(Clone, Debug)]
pub struct SampleConfig {
    /// The replay service.
    pub endpoint: GrpcEndpoint,
    /// Table to sample; "" means the server's only table.
    pub table: String,
    /// Rows per minibatch (SampleRequest.batch_size).
    pub batch_size: u32,
    /// Minibatches the server draws ahead (SampleRequest.prefetch; the server clamps it)
    /// [default 4]. Also sizes the stream's HTTP/2 window ([`sample_stream_window`]), which
    /// bounds how many drawn minibatches can be on their way: raise it where the round trip
    /// to the replay service is long (a window of 4 paper-size minibatches, ~100 KB, carries
    /// ~4,000 minibatches/s over a 1 ms round trip, ~200/s over 20 ms).
    pub server_prefetch: u32,
    /// Minibatches decoded and waiting on this side, ready for `next_batch` [default 4].
    pub queue_depth: usize,
    /// Importance-sampling exponent β in [0, 1] (SampleRequest.importance_beta) [default
    /// `None`: the table's own β, `replay.sampler.beta`, 0 for a uniform table].
    pub importance_beta: Option<f32>,
    /// Observation and action lengths the learner was built for; when set, a server whose
    /// table has other dims stops the client with a clear error instead of feeding it.
    pub expected_dims: Option<(usize, usize)>,
    /// First wait after a broken stream; doubles up to `backoff_max` [default 100 ms].
    pub backoff_initial: Duration,
    /// Longest wait between reconnection attempts [default 5 s].
    pub backoff_max: Duration,
    /// Priority updates waiting to be sent; when full, new ones are dropped (and counted)
    /// rather than stalling the caller [default 64].
    pub priority_queue_depth: usize,
}

impl SampleConfig {
    /// Defaults for sampling `batch_size` rows from the only table at `endpoint`.
    pub fn new(endpoint: impl Into<GrpcEndpoint>, batch_size: u32) -> Self {
        Self {
            endpoint: endpoint.into(),
            table: String::new(),
            batch_size,
            server_prefetch: 4,
            queue_depth: 4,
            importance_beta: None,
            expected_dims: None,
            backoff_initial: Duration::from_millis(100),
            backoff_max: Duration::from_secs(5),
            priority_queue_depth: 64,
        }
    }

    fn validate(&self) -> Result<(), NetError> {
        let bad = |reason: String| Err(config_error(reason));
        if self.batch_size == 0 {
            return bad("batch_size is 0".into());
        }
        if self.queue_depth == 0 || self.priority_queue_depth == 0 {
            return bad("queue_depth and priority_queue_depth must be >= 1".into());
        }
        if let Some(beta) = self.importance_beta
            && !(0.0..=1.0).contains(&beta)
        {
            return bad(format!("importance_beta is {beta}, must be in [0, 1]"));
        }
        if self.backoff_initial.is_zero() || self.backoff_max < self.backoff_initial {
            return bad("backoff_initial must be > 0 and <= backoff_max".into());
        }
        if let Some((obs, act)) = self.expected_dims
            && (obs == 0 || act == 0)
        {
            return bad("expected_dims must be >= 1".into());
        }
        self.endpoint.check()
    }
}

/// Counters shared between the update thread and the background thread.
#[derive(Default)]
struct Shared {
    reconnects: AtomicU64,
    stream_errors: AtomicU64,
    invalid_batches: AtomicU64,
    priority_updates: AtomicU64,
    priority_update_errors: AtomicU64,
    priority_updates_dropped: AtomicU64,
    /// Set when the table samples uniformly: updates are then not sent at all.
    uniform: AtomicBool,
    last_error: Mutex<Option<String>>,
}

impl Shared {
    fn record_error(&self, counter: &AtomicU64, error: &str) {
        counter.fetch_add(1, Ordering::Relaxed);
        if let Ok(mut last) = self.last_error.lock() {
            *last = Some(error.to_owned());
        }
    }
}

/// Samples from the replay service over gRPC, prefetching on a background thread; see the
/// module doc.
///
/// Threading: owned by one thread (`Send`, used through `&mut self`). Dropping it stops the
/// background thread (and waits for it, at most a moment).
pub struct SampleClient {
    batches: Receiver<Result<SampledBatch, NetError>>,
    /// Wakes the sample task when the queue has room again.
    room: Arc<Notify>,
    priorities: tokio::sync::mpsc::Sender<(Vec<u64>, Vec<f64>)>,
    shared: Arc<Shared>,
    stop: watch::Sender<bool>,
    thread: Option<JoinHandle<()>>,
    batches_delivered: u64,
    /// Why the client stopped for good, once it has.
    stopped: Option<String>,
    endpoint: String,
}

impl std::fmt::Debug for SampleClient {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.debug_struct("SampleClient").field("endpoint", &self.endpoint).field("stopped", &self.stopped).finish()
    }
}

impl SampleClient {
    /// Starts the background thread, which connects (and keeps reconnecting) on its own:
    /// this returns at once, even when the service is not up yet. Fails only on a config
    /// that can never work ([`NetError::ClientConfig`], or the endpoint's
    /// [`NetError::Config`]).
    pub fn start(config: SampleConfig) -> Result<Self, NetError> {
        config.validate()?;
        let runtime = tokio::runtime::Builder::new_current_thread().enable_all().build().map_err(|e| config_error(format!("cannot start the background runtime: {e}")))?;
        let (batch_tx, batches) = std::sync::mpsc::sync_channel(config.queue_depth);
        let (priority_tx, priority_rx) = tokio::sync::mpsc::channel(config.priority_queue_depth);
        let (stop, stop_rx) = watch::channel(false);
        let room = Arc::new(Notify::new());
        let shared = Arc::new(Shared::default());
        let endpoint = config.endpoint.uri().to_owned();
        let thread = {
            let room = Arc::clone(&room);
            let shared = Arc::clone(&shared);
            std::thread::Builder::new()
                .name("replay-source".into())
                .spawn(move || {
                    runtime.block_on(async move {
                        let priorities = tokio::spawn(priority_loop(config.clone(), priority_rx, Arc::clone(&shared), stop_rx.clone()));
                        sample_loop(&config, &batch_tx, &room, &shared, stop_rx).await;
                        priorities.abort();
                        let _ = priorities.await;
                    });
                })
                .map_err(|e| config_error(format!("cannot start the background thread: {e}")))?
        };
        Ok(Self { batches, room, priorities: priority_tx, shared, stop, thread: Some(thread), batches_delivered: 0, stopped: None, endpoint })
    }

    /// The next minibatch. Blocks until one is available (the replay rate limiter may hold it
    /// back, e.g. during warm-up). [`NetError::Stopped`] once the client has stopped for good.
    pub fn next_batch(&mut self) -> Result<SampledBatch, NetError> {
        if let Some(reason) = &self.stopped {
            return Err(stopped(reason.clone()));
        }
        match self.batches.recv() {
            Ok(item) => self.take(item),
            Err(_) => Err(self.disconnected()),
        }
    }

    /// Like [`SampleClient::next_batch`], but gives up after `timeout` with `Ok(None)` (for a
    /// caller that wants to look at its stop flag or log that it is waiting).
    pub fn next_batch_timeout(&mut self, timeout: Duration) -> Result<Option<SampledBatch>, NetError> {
        if let Some(reason) = &self.stopped {
            return Err(stopped(reason.clone()));
        }
        match self.batches.recv_timeout(timeout) {
            Ok(item) => self.take(item).map(Some),
            Err(RecvTimeoutError::Timeout) => Ok(None),
            Err(RecvTimeoutError::Disconnected) => Err(self.disconnected()),
        }
    }

    fn take(&mut self, item: Result<SampledBatch, NetError>) -> Result<SampledBatch, NetError> {
        self.room.notify_one();
        match item {
            Ok(batch) => {
                self.batches_delivered += 1;
                Ok(batch)
            }
            Err(e) => {
                let reason = e.to_string();
                self.stopped = Some(reason.clone());
                Err(stopped(reason))
            }
        }
    }

    fn disconnected(&mut self) -> NetError {
        let reason = "the background sampling thread ended".to_owned();
        self.stopped = Some(reason.clone());
        stopped(reason)
    }

    /// Queues new priorities for `keys` and returns at once; the caller has checked them
    /// (equal lengths, every value finite and not negative). The background thread sends them
    /// with a few retries. Not sent at all when `keys` is empty or the table samples
    /// uniformly; dropped (and counted in [`SampleStats::priority_updates_dropped`]) when the
    /// outgoing queue is full, rather than stalling the caller. [`NetError::Stopped`] once
    /// the background thread is gone.
    pub fn update_priorities(&mut self, keys: &[u64], priorities: Vec<f64>) -> Result<(), NetError> {
        if keys.is_empty() || self.shared.uniform.load(Ordering::Relaxed) {
            return Ok(());
        }
        match self.priorities.try_send((keys.to_vec(), priorities)) {
            Ok(()) => Ok(()),
            Err(tokio::sync::mpsc::error::TrySendError::Full(_)) => {
                self.shared.record_error(&self.shared.priority_updates_dropped, "priority update dropped: the outgoing queue is full");
                Ok(())
            }
            Err(tokio::sync::mpsc::error::TrySendError::Closed(_)) => Err(stopped(self.stopped.clone().unwrap_or_else(|| "the background priority task ended".into()))),
        }
    }

    /// Counters since the client was started.
    pub fn stats(&self) -> SampleStats {
        let s = &self.shared;
        SampleStats {
            batches: self.batches_delivered,
            reconnects: s.reconnects.load(Ordering::Relaxed),
            stream_errors: s.stream_errors.load(Ordering::Relaxed),
            invalid_batches: s.invalid_batches.load(Ordering::Relaxed),
            priority_updates: s.priority_updates.load(Ordering::Relaxed),
            priority_update_errors: s.priority_update_errors.load(Ordering::Relaxed),
            priority_updates_dropped: s.priority_updates_dropped.load(Ordering::Relaxed),
            last_error: s.last_error.lock().ok().and_then(|l| l.clone()),
        }
    }
}

impl Drop for SampleClient {
    fn drop(&mut self) {
        let _ = self.stop.send(true);
        self.room.notify_one();
        if let Some(thread) = self.thread.take() {
            let _ = thread.join();
        }
    }
}

/// Status codes after which retrying the same request cannot succeed.
fn is_fatal(code: Code) -> bool {
    matches!(code, Code::InvalidArgument | Code::NotFound | Code::FailedPrecondition | Code::Unauthenticated | Code::PermissionDenied | Code::Unimplemented | Code::OutOfRange)
}

/// Why opening a stream failed: worth retrying or not.
enum OpenError {
    Retry(NetError),
    Fatal(NetError),
}

fn classify(error: NetError) -> OpenError {
    match &error {
        NetError::Grpc { code, .. } if is_fatal(*code) => OpenError::Fatal(error),
        NetError::Grpc { .. } => OpenError::Retry(error),
        _ => OpenError::Fatal(error),
    }
}

/// A connected client and an open Sample stream, with the dims to check batches against.
struct OpenStream {
    stream: tonic::Streaming<SampledBatch>,
    obs_dim: usize,
    act_dim: usize,
}

pub(crate) async fn connect_client(endpoint: &GrpcEndpoint) -> Result<ReplayServiceClient<Channel>, NetError> {
    let channel = endpoint.connect("replay").await?;
    Ok(ReplayServiceClient::new(channel).max_decoding_message_size(MAX_MESSAGE_BYTES).max_encoding_message_size(MAX_MESSAGE_BYTES))
}

/// About the bytes one encoded minibatch of `rows` rows takes: per row the key, probability,
/// weight, reward, flags, episode id, step and policy version (varints at their longest),
/// plus the float columns; 128 bytes for the header fields, the columns' tags and lengths and a
/// short table name, and gRPC's 5-byte frame prefix. Saturates instead of overflowing.
pub fn minibatch_wire_bytes(rows: u32, obs_dim: usize, act_dim: usize) -> u64 {
    let floats = (obs_dim as u64).saturating_mul(2).saturating_add(act_dim as u64);
    let per_row = (10 + 8 + 4 + 4 + 1 + 1 + 10 + 5 + 10u64).saturating_add(floats.saturating_mul(4));
    (128 + 5u64).saturating_add(u64::from(rows).saturating_mul(per_row))
}

/// HTTP/2 window of the Sample stream's connection: room for `prefetch` minibatches (at least
/// one 16 KiB frame). The transport's own default (2 MiB) lets the server push thousands of
/// small minibatches ahead of the update loop, each drawn with the priorities of its moment;
/// this keeps what is in flight to about `prefetch` minibatches on the wire, `prefetch` drawn
/// and waiting at the server and `queue_depth` decoded here.
pub fn sample_stream_window(config: &SampleConfig, obs_dim: usize, act_dim: usize) -> u32 {
    let bytes = u64::from(config.server_prefetch.max(1)).saturating_mul(minibatch_wire_bytes(config.batch_size, obs_dim, act_dim));
    // 2³¹ − 1 is HTTP/2's largest window.
    bytes.clamp(16 * 1024, (1 << 31) - 1) as u32
}

async fn open_stream(config: &SampleConfig, shared: &Shared) -> Result<OpenStream, OpenError> {
    let endpoint = &config.endpoint;
    let mut client = connect_client(endpoint).await.map_err(classify)?;
    let info_request = endpoint.request("replay", ServerInfoRequest { protocol_version: ProtocolVersion::V1 as i32 }).map_err(OpenError::Fatal)?;
    let info = client.server_info(info_request).await.map_err(|s| classify(endpoint.status_error("replay", &s)))?.into_inner();
    if !config.table.is_empty() && config.table != info.table {
        return Err(OpenError::Fatal(NetError::Grpc {
            service: "replay",
            endpoint: endpoint.uri().to_owned(),
            code: Code::NotFound,
            message: format!("no table `{}`; the server hosts `{}`", config.table, info.table),
        }));
    }
    let (obs_dim, act_dim) = (info.obs_dim as usize, info.act_dim as usize);
    if let Some((obs, act)) = config.expected_dims
        && (obs, act) != (obs_dim, act_dim)
    {
        return Err(OpenError::Fatal(NetError::Grpc {
            service: "replay",
            endpoint: endpoint.uri().to_owned(),
            code: Code::FailedPrecondition,
            message: format!("table `{}` holds obs_dim {obs_dim}, act_dim {act_dim}; this learner expects obs_dim {obs}, act_dim {act}", info.table),
        }));
    }
    shared.uniform.store(info.selector == Selector::Uniform as i32, Ordering::Relaxed);
    let request = endpoint
        .request(
            "replay",
            SampleRequest {
                protocol_version: ProtocolVersion::V1 as i32,
                table: config.table.clone(),
                batch_size: config.batch_size,
                prefetch: config.server_prefetch,
                // Wait without limit: the rate limiter legitimately holds samples back during
                // warm-up, and a broken connection shows up as a transport error anyway.
                timeout_ms: 0,
                max_batches: 0,
                importance_beta: config.importance_beta,
                ..SampleRequest::default()
            },
        )
        .map_err(OpenError::Fatal)?;
    // The stream gets its own connection, with a window sized to the prefetch now that the
    // minibatch size is known.
    let window = sample_stream_window(config, obs_dim, act_dim);
    let mut client = connect_client(&endpoint.clone().with_stream_window(window)).await.map_err(classify)?;
    let stream = client.sample(request).await.map_err(|s| classify(endpoint.status_error("replay", &s)))?.into_inner();
    Ok(OpenStream { stream, obs_dim, act_dim })
}

async fn wait_stop(stop: &mut watch::Receiver<bool>) {
    if stop.wait_for(|s| *s).await.is_err() {
        // The client is gone without saying stop; nothing will ever consume again.
        std::future::pending::<()>().await;
    }
}

/// How a pushed batch fared.
enum Push {
    Queued,
    /// The client is being dropped.
    Stop,
}

/// Puts `item` on the bounded queue, waiting (asynchronously) for room.
async fn push(tx: &SyncSender<Result<SampledBatch, NetError>>, room: &Notify, stop: &mut watch::Receiver<bool>, mut item: Result<SampledBatch, NetError>) -> Push {
    loop {
        match tx.try_send(item) {
            Ok(()) => return Push::Queued,
            Err(TrySendError::Disconnected(_)) => return Push::Stop,
            Err(TrySendError::Full(back)) => {
                item = back;
                // `notify_one` stores a permit when nobody waits, so a batch taken between
                // `try_send` and here is not missed.
                tokio::select! {
                    () = room.notified() => {}
                    () = wait_stop(stop) => return Push::Stop,
                }
            }
        }
    }
}

/// Keeps the queue full, reconnecting with exponential backoff; returns when the client is
/// dropped or after a fatal error (which it queues for `next_batch`).
async fn sample_loop(config: &SampleConfig, tx: &SyncSender<Result<SampledBatch, NetError>>, room: &Notify, shared: &Shared, mut stop: watch::Receiver<bool>) {
    let endpoint = config.endpoint.uri();
    let max_rows = config.batch_size as usize;
    let mut backoff = config.backoff_initial;
    let mut opened = 0u64;
    loop {
        if *stop.borrow() {
            return;
        }
        let opening = tokio::select! {
            opening = open_stream(config, shared) => opening,
            () = wait_stop(&mut stop) => return,
        };
        match opening {
            Ok(mut open) => {
                if opened > 0 {
                    shared.reconnects.fetch_add(1, Ordering::Relaxed);
                    info!(endpoint, "replay sample stream reopened");
                } else {
                    info!(endpoint, batch_size = config.batch_size, "replay sample stream opened");
                }
                opened += 1;
                loop {
                    let message = tokio::select! {
                        message = open.stream.message() => message,
                        () = wait_stop(&mut stop) => return,
                    };
                    match message {
                        Ok(Some(batch)) => {
                            backoff = config.backoff_initial;
                            if let Err(e) = batch.validate(open.obs_dim, open.act_dim, max_rows) {
                                let text = format!("invalid minibatch from {endpoint} dropped: {e}");
                                warn!("{text}");
                                shared.record_error(&shared.invalid_batches, &text);
                                continue;
                            }
                            if let Push::Stop = push(tx, room, &mut stop, Ok(batch)).await {
                                return;
                            }
                        }
                        Ok(None) => {
                            let text = format!("replay sample stream at {endpoint} ended without an error");
                            warn!("{text}; reopening");
                            shared.record_error(&shared.stream_errors, &text);
                            break;
                        }
                        Err(status) => {
                            let error = config.endpoint.status_error("replay", &status);
                            if is_fatal(status.code()) {
                                warn!(error = %error, "replay sample stream failed for good");
                                shared.record_error(&shared.stream_errors, &error.to_string());
                                let _ = push(tx, room, &mut stop, Err(error)).await;
                                return;
                            }
                            warn!(error = %error, ?backoff, "replay sample stream broke; reconnecting");
                            shared.record_error(&shared.stream_errors, &error.to_string());
                            break;
                        }
                    }
                }
            }
            Err(OpenError::Fatal(error)) => {
                warn!(error = %error, "cannot sample from the replay service");
                shared.record_error(&shared.stream_errors, &error.to_string());
                let _ = push(tx, room, &mut stop, Err(error)).await;
                return;
            }
            Err(OpenError::Retry(error)) => {
                debug!(error = %error, ?backoff, "replay service not reachable; retrying");
                shared.record_error(&shared.stream_errors, &error.to_string());
            }
        }
        tokio::select! {
            () = tokio::time::sleep(backoff) => {}
            () = wait_stop(&mut stop) => return,
        }
        backoff = (backoff * 2).min(config.backoff_max);
    }
}

/// Sends queued priority updates, each with a few retries; runs until the client is dropped.
async fn priority_loop(config: SampleConfig, mut updates: tokio::sync::mpsc::Receiver<(Vec<u64>, Vec<f64>)>, shared: Arc<Shared>, mut stop: watch::Receiver<bool>) {
    /// Attempts per update before it is dropped: priorities are a hint, a stale one is cheap
    /// to lose, and waiting longer would only let the queue overflow.
    const ATTEMPTS: u32 = 3;
    let mut client: Option<ReplayServiceClient<Channel>> = None;
    loop {
        let (keys, priorities) = tokio::select! {
            update = updates.recv() => match update {
                Some(u) => u,
                None => return,
            },
            () = wait_stop(&mut stop) => return,
        };
        if shared.uniform.load(Ordering::Relaxed) {
            continue;
        }
        let update = PriorityUpdate { protocol_version: ProtocolVersion::V1 as i32, table: config.table.clone(), keys, priorities };
        let mut backoff = config.backoff_initial;
        for attempt in 1..=ATTEMPTS {
            let outcome = tokio::select! {
                outcome = send_priorities(&config, &mut client, &update) => outcome,
                () = wait_stop(&mut stop) => return,
            };
            match outcome {
                Ok(response) => {
                    shared.priority_updates.fetch_add(1, Ordering::Relaxed);
                    debug!(updated = response.updated, unknown_keys = response.unknown_keys, "priorities updated");
                    break;
                }
                Err(NetError::Grpc { code: Code::FailedPrecondition, ref message, .. }) if message.contains("uniform") => {
                    // The table has no priorities; stop sending (ServerInfo also says so).
                    shared.uniform.store(true, Ordering::Relaxed);
                    break;
                }
                Err(error) => {
                    let fatal = matches!(&error, NetError::Grpc { code, .. } if is_fatal(*code));
                    if fatal || attempt == ATTEMPTS {
                        warn!(error = %error, attempt, "priority update dropped");
                        shared.record_error(&shared.priority_update_errors, &error.to_string());
                        break;
                    }
                    // A broken connection: dial again after a pause.
                    client = None;
                    tokio::select! {
                        () = tokio::time::sleep(backoff) => {}
                        () = wait_stop(&mut stop) => return,
                    }
                    backoff = (backoff * 2).min(config.backoff_max);
                }
            }
        }
    }
}

/// One UpdatePriorities call, dialling first when there is no connection yet.
async fn send_priorities(config: &SampleConfig, client: &mut Option<ReplayServiceClient<Channel>>, update: &PriorityUpdate) -> Result<PriorityUpdateResponse, NetError> {
    let mut c = match client {
        Some(c) => c.clone(),
        None => {
            let c = connect_client(&config.endpoint).await?;
            *client = Some(c.clone());
            c
        }
    };
    let request = config.endpoint.request("replay", update.clone())?;
    c.update_priorities(request).await.map(tonic::Response::into_inner).map_err(|s| config.endpoint.status_error("replay", &s))
}

#[cfg(test)]
mod tests {
    use super::*;

    fn unreachable() -> SampleConfig {
        // Port 1 on loopback: nothing listens there, connecting fails at once.
        SampleConfig { backoff_initial: Duration::from_millis(10), backoff_max: Duration::from_millis(20), ..SampleConfig::new(GrpcEndpoint::new("http://127.0.0.1:1"), 8) }
    }

    #[test]
    fn configs_that_cannot_work_are_refused_by_field() {
        for (bad, needle) in [
            (SampleConfig { batch_size: 0, ..unreachable() }, "batch_size"),
            (SampleConfig { queue_depth: 0, ..unreachable() }, "queue_depth"),
            (SampleConfig { importance_beta: Some(1.5), ..unreachable() }, "importance_beta"),
            (SampleConfig { backoff_initial: Duration::ZERO, ..unreachable() }, "backoff_initial"),
            (SampleConfig { expected_dims: Some((0, 2)), ..unreachable() }, "expected_dims"),
        ] {
            let e = SampleClient::start(bad).expect_err("refused");
            assert!(matches!(e, NetError::ClientConfig { client: CLIENT, .. }), "{e:?}");
            let text = e.to_string();
            assert!(text.starts_with("invalid sample client config: ") && text.contains(needle), "{text}");
        }
    }

    #[test]
    fn the_stream_window_holds_the_prefetch_and_stays_within_http2_bounds() {
        let cfg = SampleConfig::new(GrpcEndpoint::new("http://127.0.0.1:1"), 256);
        let one = minibatch_wire_bytes(256, 32, 2);
        assert_eq!(u64::from(sample_stream_window(&cfg, 32, 2)), 4 * one);
        // Tiny minibatches: at least one 16 KiB frame.
        assert_eq!(sample_stream_window(&SampleConfig { batch_size: 1, server_prefetch: 1, ..cfg.clone() }, 1, 1), 16 * 1024);
        // Huge ones: HTTP/2's largest window, no overflow.
        assert_eq!(sample_stream_window(&SampleConfig { batch_size: u32::MAX, server_prefetch: u32::MAX, ..cfg }, usize::MAX, usize::MAX), (1 << 31) - 1);
    }

    #[test]
    fn an_unreachable_service_makes_the_caller_wait_and_counts_the_attempts() {
        let mut client = SampleClient::start(unreachable()).expect("starts without a server");
        assert!(client.next_batch_timeout(Duration::from_millis(200)).expect("no error, only waiting").is_none());
        client.update_priorities(&[1, 2], vec![0.5, 1.0]).expect("queued");
        // The background thread's first failed attempt may come after those 200 ms on a loaded
        // machine: look for up to 10 s.
        let until = std::time::Instant::now() + Duration::from_secs(10);
        let mut stats = client.stats();
        while (stats.stream_errors == 0 || stats.last_error.is_none()) && std::time::Instant::now() < until {
            std::thread::sleep(Duration::from_millis(20));
            stats = client.stats();
        }
        assert!(stats.stream_errors >= 1 && stats.last_error.is_some(), "{stats:?}");
        assert_eq!(stats.batches, 0);
        // Dropping stops the background thread promptly.
        let t = std::time::Instant::now();
        drop(client);
        assert!(t.elapsed() < Duration::from_secs(2));
    }
}
