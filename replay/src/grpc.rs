//! `ReplayService` over gRPC: the transport around one [`Table`]. Service logic stays in the
//! table; this file maps streams to table calls and errors to statuses.
//!
//! ```text
//!  Insert (bidi), one task per stream, one actor per stream:
//!    inbound ──batch──► spawn_blocking(Table::insert, polled) ──ack──► [acks, depth 8] ──► client
//!    (the next batch is read only after the previous one is acked: a rate-limited table stops
//!     reading, and HTTP/2 flow control then blocks the client — the limiter is the one throttle)
//!
//!  Sample (server stream), one async task per stream, at most `max_sample_streams` open
//!  (beyond that: RESOURCE_EXHAUSTED, counted in `replay_sample_streams_refused_total`):
//!    reserve slot in [minibatches, depth prefetch] ─► spawn_blocking(Table::try_sample_as) ─► send ─► client
//!                                                      │ limiter says no
//!                                                      └► await Table::changed / deadline / client gone ─► retry
//!    (float columns packed, or as `*_f32le` bytes when the request sets float_columns_as_bytes:
//!     then encoding and the client's decoding are a memcpy per column)
//!    (a slot is reserved before drawing, so at most `prefetch` drawn minibatches wait unread)
//! ```
//!
//! Threading: the table blocks on a std `Condvar` (rate limiter), so every table call that can
//! wait runs on tokio's blocking pool, never on a runtime worker. Blocking calls wait in slices
//! of [`POLL_INTERVAL`] and between slices check whether their peer went away or the server is
//! stopping, so a vanished client releases its thread (and its actor's stream slot) within one
//! slice instead of wedging until the limiter opens.
//!
//! Sample streams are the exception: they are long-lived and a learner's may sit behind the
//! rate limiter for minutes, so they hold no blocking thread while they wait. Each draw is a
//! short `spawn_blocking` of the non-waiting [`Table::try_sample_as`] (it still takes the table's
//! lock, which an insert may hold while its journal writes, so not on a runtime worker); when
//! the limiter says no, the stream's task awaits [`Table::changed`] (fired with the condvar),
//! its deadline, its client going away or the server stopping. Tokio's blocking pool (512
//! threads) therefore stays free for inserts, priority updates and persistence however many
//! samplers wait. Open streams are still bounded ([`DEFAULT_MAX_SAMPLE_STREAMS`]): each holds
//! up to `prefetch` drawn minibatches in memory, and a client that keeps opening streams gets
//! a clear RESOURCE_EXHAUSTED rather than a slow server.

use std::collections::HashSet;
use std::sync::{Arc, Mutex};
use std::time::{Duration, Instant};

use mapless_proto::v1::replay_service_server::ReplayService;
use mapless_proto::v1::{
    InsertAck, PriorityUpdate, PriorityUpdateResponse, RegisterActorRequest, RegisterActorResponse, SampleRequest, SampledBatch, ServerInfoRequest, ServerInfoResponse, TransitionBatch,
};
use mapless_proto::{FloatEncoding, MAX_ACTOR_ID_BYTES, MAX_MESSAGE_BYTES, check_protocol_version};
use tokio::sync::{OwnedSemaphorePermit, Semaphore, mpsc, watch};
use tokio_stream::wrappers::ReceiverStream;
use tonic::{Request, Response, Status, Streaming};
use tracing::{Instrument, debug, info, info_span, warn};

use crate::actors::ActorStats;
use crate::config::SamplerConfig;
use crate::error::ReplayError;
use crate::registry::ActorRegistry;
use crate::table::Table;

/// How long a blocked table call waits before checking whether its peer is still there.
/// Bounds how long a vanished client keeps a thread and its actor's stream slot.
pub const POLL_INTERVAL: Duration = Duration::from_millis(100);

/// Acks buffered per Insert stream before the server stops reading (a client that does not
/// read its acks is throttled like one the rate limiter blocks).
pub const ACK_CHANNEL_DEPTH: usize = 8;

/// Largest `SampleRequest.prefetch` honoured unless configured otherwise; larger values are
/// clamped (replay.proto: "values above the server's maximum (16 by default) are clamped").
pub const DEFAULT_MAX_PREFETCH: u32 = 16;

/// Sample streams open at once unless configured otherwise (`max_sample_streams` in the
/// server's config); one more is refused with RESOURCE_EXHAUSTED. A learner opens one or a
/// few, so 256 leaves room for many learners and evaluators while bounding what open streams
/// can hold: each keeps up to `prefetch` drawn minibatches (16 × 8,192 rows at most) in memory.
pub const DEFAULT_MAX_SAMPLE_STREAMS: u32 = 256;

/// Most keys one `PriorityUpdate` may carry: what fits in one message at 16 bytes a key
/// (8 for the key, 8 for its priority).
pub const MAX_PRIORITY_KEYS: usize = MAX_MESSAGE_BYTES / 16;

/// The gRPC face of one table. A plain struct: wrap it in
/// [`ReplayServiceServer`](mapless_proto::v1::replay_service_server::ReplayServiceServer)
/// (with [`MAX_MESSAGE_BYTES`] limits), or let [`crate::server::serve`] do it.
pub struct ReplayGrpc {
    table: Arc<Table>,
    /// actor_ids with an open Insert stream. Exactly-once needs one stream per actor at a time
    /// (replay.proto, Insert): a second one is refused with ABORTED.
    open_streams: Arc<Mutex<HashSet<String>>>,
    max_prefetch: u32,
    /// One permit per open Sample stream; none left means RESOURCE_EXHAUSTED.
    sample_streams: Arc<Semaphore>,
    max_sample_streams: u32,
    /// Becomes true when the server stops: open streams end with UNAVAILABLE.
    stopping: Option<watch::Receiver<bool>>,
    /// Actor name → slot (`RegisterActor`).
    registry: Arc<ActorRegistry>,
}

impl ReplayGrpc {
    /// A service over `table` that runs until it is dropped.
    pub fn new(table: Arc<Table>) -> ReplayGrpc {
        ReplayGrpc {
            table,
            open_streams: Arc::default(),
            max_prefetch: DEFAULT_MAX_PREFETCH,
            sample_streams: Arc::new(Semaphore::new(DEFAULT_MAX_SAMPLE_STREAMS as usize)),
            max_sample_streams: DEFAULT_MAX_SAMPLE_STREAMS,
            stopping: None,
            registry: Arc::default(),
        }
    }

    /// Answers `RegisterActor` from `registry` (default: a table in memory only, for a server
    /// without a data directory).
    pub fn with_registry(mut self, registry: Arc<ActorRegistry>) -> ReplayGrpc {
        self.registry = registry;
        self
    }

    /// Ends every open stream with UNAVAILABLE once `stopping` turns true (so a graceful
    /// shutdown is not held up by long-lived streams).
    pub fn with_shutdown(mut self, stopping: watch::Receiver<bool>) -> ReplayGrpc {
        self.stopping = Some(stopping);
        self
    }

    /// Largest prefetch a Sample stream gets (≥ 1).
    pub fn with_max_prefetch(mut self, max_prefetch: u32) -> ReplayGrpc {
        self.max_prefetch = max_prefetch.max(1);
        self
    }

    /// Most Sample streams open at once (≥ 1); one more is refused with RESOURCE_EXHAUSTED.
    /// Set it before serving: streams already open keep their permits from the old limit.
    pub fn with_max_sample_streams(mut self, max_sample_streams: u32) -> ReplayGrpc {
        self.max_sample_streams = max_sample_streams.max(1);
        self.sample_streams = Arc::new(Semaphore::new(self.max_sample_streams as usize));
        self
    }

    pub fn table(&self) -> &Arc<Table> {
        &self.table
    }

    /// v1 servers host one table: "" or its name (replay.proto, ReplayService).
    fn check_table(&self, name: &str) -> Result<(), Status> {
        let ours = &self.table.config().name;
        if name.is_empty() || name == ours { Ok(()) } else { Err(Status::not_found(format!("no table `{name}` on this server; it hosts `{ours}` (or pass \"\")"))) }
    }

    fn stop_flag(&self) -> StopFlag {
        StopFlag(self.stopping.clone())
    }
}

/// Whether the server is stopping; readable from blocking threads and awaitable.
#[derive(Clone)]
struct StopFlag(Option<watch::Receiver<bool>>);

impl StopFlag {
    fn is_set(&self) -> bool {
        self.0.as_ref().is_some_and(|rx| *rx.borrow())
    }

    /// Resolves when the server starts stopping; never, if it has no shutdown signal.
    async fn wait(&mut self) {
        match &mut self.0 {
            Some(rx) => {
                if rx.wait_for(|stop| *stop).await.is_err() {
                    // The signal's sender is gone without stopping: nobody can stop us now.
                    std::future::pending::<()>().await;
                }
            }
            None => std::future::pending::<()>().await,
        }
    }
}

fn shutting_down() -> Status {
    Status::unavailable("replay server is shutting down; reconnect and resend unacknowledged batches")
}

/// Runs a table call that may block on the rate limiter, in slices of [`POLL_INTERVAL`] up to
/// `deadline` (None: without limit). Between slices it returns `None` if `cancelled()`.
/// A final DeadlineExceeded reports the whole wait, not the last slice.
fn wait_polled<T>(deadline: Option<Instant>, cancelled: impl Fn() -> bool, mut op: impl FnMut(Option<Instant>) -> Result<T, ReplayError>) -> Option<Result<T, ReplayError>> {
    let start = Instant::now();
    loop {
        let slice_end = Instant::now() + POLL_INTERVAL;
        let (until, last) = match deadline {
            Some(d) if d <= slice_end => (d, true),
            _ => (slice_end, false),
        };
        match op(Some(until)) {
            Err(ReplayError::DeadlineExceeded { op, state, .. }) if last => {
                return Some(Err(ReplayError::DeadlineExceeded { op, waited_ms: start.elapsed().as_millis() as u64, state }));
            }
            Err(ReplayError::DeadlineExceeded { .. }) => {
                if cancelled() {
                    return None;
                }
            }
            other => return Some(other),
        }
    }
}

/// The deadline a client set with `grpc-timeout` (tonic's `Request::set_timeout`), if any.
fn request_deadline<T>(request: &Request<T>) -> Option<Instant> {
    let value = request.metadata().get("grpc-timeout")?.to_str().ok()?;
    let timeout = parse_grpc_timeout(value)?;
    Some(Instant::now() + timeout)
}

/// `grpc-timeout` is 1–8 digits and a unit: H, M, S, m (ms), u (µs), n (ns)
/// (gRPC over HTTP/2, "Requests"). Malformed values are ignored, as tonic ignores them.
fn parse_grpc_timeout(value: &str) -> Option<Duration> {
    if value.len() < 2 || value.len() > 9 {
        return None;
    }
    let (digits, unit) = value.split_at(value.len() - 1);
    let n: u64 = digits.parse().ok()?;
    Some(match unit {
        "H" => Duration::from_secs(n * 3600),
        "M" => Duration::from_secs(n * 60),
        "S" => Duration::from_secs(n),
        "m" => Duration::from_millis(n),
        "u" => Duration::from_micros(n),
        "n" => Duration::from_nanos(n),
        _ => return None,
    })
}

/// Holds an actor's Insert-stream slot; frees it when dropped (stream end, any cause).
struct StreamSlot {
    open_streams: Arc<Mutex<HashSet<String>>>,
    actor_id: String,
}

impl StreamSlot {
    fn claim(open_streams: &Arc<Mutex<HashSet<String>>>, actor_id: &str) -> Option<StreamSlot> {
        let mut open = open_streams.lock().unwrap_or_else(|p| p.into_inner());
        open.insert(actor_id.to_owned()).then(|| StreamSlot { open_streams: Arc::clone(open_streams), actor_id: actor_id.to_owned() })
    }
}

impl Drop for StreamSlot {
    fn drop(&mut self) {
        self.open_streams.lock().unwrap_or_else(|p| p.into_inner()).remove(&self.actor_id);
    }
}

/// A status tonic produced while decoding a client message, as the status the client gets.
/// Returns None for transport failures (the peer reset the stream or went away): those are
/// not the client's data and are not counted as rejections.
fn decode_rejection(status: &Status) -> Option<Status> {
    match status.code() {
        // Length prefix above MAX_MESSAGE_BYTES; tonic stops before reading the body.
        tonic::Code::OutOfRange => Some(status.clone()),
        // prost could not parse the bytes (tonic-prost reports INTERNAL; for us it is the
        // client's malformed input, so INVALID_ARGUMENT), or a bad compression flag.
        tonic::Code::Internal
            if status.message().starts_with("failed to decode Protobuf message") || status.message().starts_with("protocol error: received message with invalid compression flag") =>
        {
            Some(Status::invalid_argument(format!("malformed TransitionBatch: {}", status.message())))
        }
        _ => None,
    }
}

/// One Insert stream, from its first batch to its end. See the module diagram.
struct InsertSession {
    table: Arc<Table>,
    open_streams: Arc<Mutex<HashSet<String>>>,
    stop: StopFlag,
    deadline: Option<Instant>,
    acks: mpsc::Sender<Result<InsertAck, Status>>,
    /// Set by the first batch with a well-formed actor_id.
    slot: Option<StreamSlot>,
}

impl InsertSession {
    async fn run(mut self, mut inbound: Streaming<TransitionBatch>) {
        let mut stop = self.stop.clone();
        loop {
            let next = tokio::select! {
                biased;
                _ = self.acks.closed() => {
                    debug!("client went away");
                    return;
                }
                _ = stop.wait() => {
                    let _ = self.acks.send(Err(shutting_down())).await;
                    return;
                }
                next = inbound.message() => next,
            };
            let batch = match next {
                Ok(Some(batch)) => batch,
                // Half-closed: every batch read has been acked, so the stream ends with OK.
                Ok(None) => {
                    debug!("client half-closed");
                    return;
                }
                Err(status) => {
                    match decode_rejection(&status) {
                        Some(reply) => {
                            let who = self.slot.as_ref().map_or("", |s| s.actor_id.as_str());
                            self.table.record_rejection(who, reply.message());
                            let _ = self.acks.send(Err(reply)).await;
                        }
                        None => debug!(%status, "stream failed"),
                    }
                    return;
                }
            };
            if let Err(status) = self.check_actor(&batch) {
                let _ = self.acks.send(Err(status)).await;
                return;
            }
            let Some(reply) = self.insert(batch).await else {
                return; // the client went away while the insert was blocked
            };
            let failed = reply.is_err();
            if let Err(status) = &reply {
                debug!(%status, "insert failed; ending stream");
            }
            if self.acks.send(reply).await.is_err() || failed {
                return;
            }
        }
    }

    /// One actor per stream: the first batch claims the actor's slot, later batches must
    /// carry the same actor_id.
    fn check_actor(&mut self, batch: &TransitionBatch) -> Result<(), Status> {
        match &self.slot {
            Some(slot) if slot.actor_id != batch.actor_id => {
                let why = format!(
                    "batch of actor_id `{}` on the Insert stream of actor_id `{}`; a stream carries one actor",
                    batch.actor_id.chars().take(MAX_ACTOR_ID_BYTES).collect::<String>(),
                    slot.actor_id
                );
                self.table.record_rejection(&slot.actor_id, &why);
                Err(Status::invalid_argument(why))
            }
            Some(_) => Ok(()),
            // A malformed actor_id claims nothing: Table::insert rejects the batch and counts it.
            None if batch.actor_id.is_empty() || batch.actor_id.len() > MAX_ACTOR_ID_BYTES => Ok(()),
            None => {
                let slot = StreamSlot::claim(&self.open_streams, &batch.actor_id).ok_or_else(|| {
                    warn!(actor_id = %batch.actor_id, "second Insert stream for one actor refused");
                    Status::aborted(format!("another Insert stream of actor_id `{}` is open; use one stream per actor (retry after it ends)", batch.actor_id))
                })?;
                tracing::Span::current().record("actor_id", batch.actor_id.as_str());
                info!("insert stream opened");
                self.slot = Some(slot);
                Ok(())
            }
        }
    }

    /// Table::insert on the blocking pool; None when the client went away meanwhile.
    async fn insert(&self, batch: TransitionBatch) -> Option<Result<InsertAck, Status>> {
        let table = Arc::clone(&self.table);
        let acks = self.acks.clone();
        let stop = self.stop.clone();
        let deadline = self.deadline;
        let span = tracing::Span::current();
        let joined = tokio::task::spawn_blocking(move || {
            let _enter = span.enter();
            wait_polled(deadline, || acks.is_closed() || stop.is_set(), |until| table.insert(&batch, until))
        })
        .await;
        match joined {
            Ok(Some(result)) => Some(result.map_err(|e| e.to_status())),
            Ok(None) if self.stop.is_set() => Some(Err(shutting_down())),
            Ok(None) => None,
            Err(join) => Some(Err(Status::internal(format!("insert task failed: {join}")))),
        }
    }
}

/// One Sample stream: an async task that holds a blocking thread only while it draws. See the
/// module doc for why it does not block on the rate limiter.
struct SampleSession {
    /// This stream's place under `max_sample_streams`. Declared before `tx`, so it is released
    /// before the client can see the stream end: a client that saw it end may open another.
    _slot: OwnedSemaphorePermit,
    table: Arc<Table>,
    rows: usize,
    beta: Option<f64>,
    floats: FloatEncoding,
    /// Per minibatch; 0 = wait as long as it takes.
    timeout_ms: u32,
    stop: StopFlag,
    tx: mpsc::Sender<Result<SampledBatch, Status>>,
}

impl SampleSession {
    async fn run(self, max_batches: u64) {
        let mut sent = 0u64;
        while max_batches == 0 || sent < max_batches {
            // Reserve before drawing: each prefetched minibatch is charged to the rate
            // limiter when drawn, so never draw more than `prefetch` ahead of the client.
            let Ok(permit) = self.tx.reserve().await else {
                debug!(sent, "client went away");
                return;
            };
            if self.stop.is_set() {
                permit.send(Err(shutting_down_sample()));
                return;
            }
            let deadline = (self.timeout_ms > 0).then(|| Instant::now() + Duration::from_millis(self.timeout_ms.into()));
            match self.draw(deadline).await {
                Some(Ok(batch)) => {
                    permit.send(Ok(batch));
                    sent += 1;
                }
                Some(Err(status)) => {
                    debug!(%status, sent, "sample stream ends");
                    permit.send(Err(status));
                    return;
                }
                None if self.stop.is_set() => {
                    permit.send(Err(shutting_down_sample()));
                    return;
                }
                None => {
                    debug!(sent, "client went away while the sampler was blocked");
                    return;
                }
            }
        }
        debug!(sent, "max_batches reached");
    }

    /// One minibatch, waiting for the rate limiter until `deadline` without holding a thread;
    /// None when the client went away or the server is stopping meanwhile.
    async fn draw(&self, deadline: Option<Instant>) -> Option<Result<SampledBatch, Status>> {
        let started = Instant::now();
        let table = Arc::clone(&self.table);
        let mut stop = self.stop.clone();
        let mut waited = false;
        let outcome = loop {
            // Enabled before trying, so a change between the try and the await still wakes us.
            let changed = table.changed();
            tokio::pin!(changed);
            changed.as_mut().enable();
            let (t, rows, beta, floats) = (Arc::clone(&table), self.rows, self.beta, self.floats);
            let span = tracing::Span::current();
            let attempt = tokio::task::spawn_blocking(move || {
                let _enter = span.enter();
                t.try_sample_as(rows, beta, floats)
            })
            .await;
            match attempt {
                Ok(Ok(Some(batch))) => break Some(Ok(batch)),
                Ok(Ok(None)) => {}
                Ok(Err(e)) => break Some(Err(e.to_status())),
                Err(join) => break Some(Err(Status::internal(format!("sample task failed: {join}")))),
            }
            waited = true;
            let expired = async {
                match deadline {
                    Some(d) => tokio::time::sleep_until(d.into()).await,
                    None => std::future::pending().await,
                }
            };
            tokio::select! {
                biased;
                _ = stop.wait() => break None,
                _ = self.tx.closed() => break None,
                _ = expired => break Some(Err(table.sample_deadline_exceeded(started.elapsed()).to_status())),
                _ = &mut changed => {} // an insert, sample or close: try again
            }
        };
        if waited {
            table.record_sample_blocked(started.elapsed());
        }
        outcome
    }
}

fn shutting_down_sample() -> Status {
    Status::unavailable("replay server is shutting down")
}

#[tonic::async_trait]
impl ReplayService for ReplayGrpc {
    type InsertStream = ReceiverStream<Result<InsertAck, Status>>;
    type SampleStream = ReceiverStream<Result<SampledBatch, Status>>;

    async fn insert(&self, request: Request<Streaming<TransitionBatch>>) -> Result<Response<Self::InsertStream>, Status> {
        let deadline = request_deadline(&request);
        let peer = request.remote_addr();
        let span = info_span!("Insert", table = %self.table.config().name, actor_id = tracing::field::Empty, peer = ?peer);
        let (acks, rx) = mpsc::channel(ACK_CHANNEL_DEPTH);
        let session = InsertSession { table: Arc::clone(&self.table), open_streams: Arc::clone(&self.open_streams), stop: self.stop_flag(), deadline, acks, slot: None };
        tokio::spawn(session.run(request.into_inner()).instrument(span));
        Ok(Response::new(ReceiverStream::new(rx)))
    }

    async fn sample(&self, request: Request<SampleRequest>) -> Result<Response<Self::SampleStream>, Status> {
        let peer = request.remote_addr();
        let req = request.into_inner();
        check_protocol_version(req.protocol_version)?;
        self.check_table(&req.table)?;
        let rows = req.validate(self.table.config().max_sample_rows)?;
        let prefetch = req.prefetch.clamp(1, self.max_prefetch);
        let floats = if req.float_columns_as_bytes { FloatEncoding::F32Le } else { FloatEncoding::Packed };
        let span = info_span!("Sample", table = %self.table.config().name, batch_size = rows, prefetch, max_batches = req.max_batches, peer = ?peer);
        let Ok(slot) = Arc::clone(&self.sample_streams).try_acquire_owned() else {
            self.table.record_sample_stream_refused();
            span.in_scope(|| warn!(limit = self.max_sample_streams, "sample stream refused: too many open"));
            return Err(Status::resource_exhausted(format!(
                "{} Sample streams are open on table `{}`, this server's limit (max_sample_streams in its config); retry after one ends, or raise the limit",
                self.max_sample_streams,
                self.table.config().name
            )));
        };
        span.in_scope(|| info!(timeout_ms = req.timeout_ms, importance_beta = ?req.importance_beta, float_columns_as_bytes = req.float_columns_as_bytes, "sample stream opened"));
        let (tx, rx) = mpsc::channel(prefetch as usize);
        let stream = SampleSession { _slot: slot, table: Arc::clone(&self.table), rows, beta: req.importance_beta.map(f64::from), floats, timeout_ms: req.timeout_ms, stop: self.stop_flag(), tx };
        tokio::spawn(stream.run(req.max_batches).instrument(span));
        Ok(Response::new(ReceiverStream::new(rx)))
    }

    async fn update_priorities(&self, request: Request<PriorityUpdate>) -> Result<Response<PriorityUpdateResponse>, Status> {
        let update = request.into_inner();
        check_protocol_version(update.protocol_version)?;
        self.check_table(&update.table)?;
        let span = info_span!("UpdatePriorities", table = %self.table.config().name, keys = update.keys.len());
        if self.table.config().sampler == SamplerConfig::Uniform {
            return Err(Status::failed_precondition(format!("table `{}` samples uniformly; it has no priorities to update", self.table.config().name)));
        }
        update.validate(MAX_PRIORITY_KEYS)?;
        let table = Arc::clone(&self.table);
        let (updated, unknown_keys) = tokio::task::spawn_blocking(move || {
            let _enter = span.enter();
            table.update_priorities(&update.keys, &update.priorities)
        })
        .await
        .map_err(|e| Status::internal(format!("update task failed: {e}")))?
        .map_err(|e| e.to_status())?;
        Ok(Response::new(PriorityUpdateResponse { updated, unknown_keys }))
    }

    async fn server_info(&self, request: Request<ServerInfoRequest>) -> Result<Response<ServerInfoResponse>, Status> {
        check_protocol_version(request.get_ref().protocol_version)?;
        let _span = info_span!("ServerInfo", table = %self.table.config().name).entered();
        Ok(Response::new(server_info(&self.table)))
    }

    async fn register_actor(&self, request: Request<RegisterActorRequest>) -> Result<Response<RegisterActorResponse>, Status> {
        let peer = request.remote_addr();
        let req = request.into_inner();
        if let Err(e) = check_protocol_version(req.protocol_version) {
            self.registry.record_refused();
            return Err(e.into());
        }
        // The name is checked (and a refusal counted) by the registry; the span shows at most
        // MAX_ACTOR_ID_BYTES of whatever was sent.
        let shown: String = req.name.chars().take(MAX_ACTOR_ID_BYTES).collect();
        let span = info_span!("RegisterActor", name = %shown, peer = ?peer);
        let registry = Arc::clone(&self.registry);
        let inner = span.clone();
        // Writing the slot file fsyncs: off the runtime's workers.
        let outcome = tokio::task::spawn_blocking(move || inner.in_scope(|| registry.register(&req.name))).await.map_err(|e| Status::internal(format!("register task failed: {e}")))?;
        let _enter = span.enter();
        match outcome {
            Ok(r) => {
                info!(slot = r.slot, known = r.known, registered = r.registered, "actor registered");
                Ok(Response::new(RegisterActorResponse { slot: r.slot, known: r.known, registered: r.registered }))
            }
            Err(e) => {
                warn!(error = %e, "actor registration refused");
                Err(e.to_status())
            }
        }
    }
}

/// `Table::info` plus the per-actor fields the transport adds from `Table::actors`: rejected
/// batches, the last rejection and the policy-version lag.
pub fn server_info(table: &Table) -> ServerInfoResponse {
    let mut info = table.info();
    let stats = table.actors();
    let newest = newest_policy_version(stats.values());
    for actor in &mut info.actors {
        if let Some(s) = stats.get(&actor.actor_id) {
            actor.rejected_batches = s.rejected_batches;
            actor.last_rejection = s.last_rejection.clone();
            actor.policy_version_lag = policy_version_lag(newest, s);
        }
    }
    info
}

/// The newest policy_version seen from any actor that has inserted something.
pub fn newest_policy_version<'a>(actors: impl IntoIterator<Item = &'a ActorStats>) -> u64 {
    actors.into_iter().filter(|a| a.batches > 0).map(|a| a.last_policy_version).max().unwrap_or(0)
}

/// How many policy versions `actor` is behind `newest`; 0 when it has inserted nothing.
pub fn policy_version_lag(newest: u64, actor: &ActorStats) -> u64 {
    if actor.batches > 0 { newest.saturating_sub(actor.last_policy_version) } else { 0 }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn grpc_timeout_header_parses_every_unit_and_rejects_junk() {
        assert_eq!(parse_grpc_timeout("5S"), Some(Duration::from_secs(5)));
        assert_eq!(parse_grpc_timeout("250m"), Some(Duration::from_millis(250)));
        assert_eq!(parse_grpc_timeout("2M"), Some(Duration::from_secs(120)));
        assert_eq!(parse_grpc_timeout("1H"), Some(Duration::from_secs(3600)));
        assert_eq!(parse_grpc_timeout("7u"), Some(Duration::from_micros(7)));
        assert_eq!(parse_grpc_timeout("9n"), Some(Duration::from_nanos(9)));
        assert_eq!(parse_grpc_timeout("S"), None);
        assert_eq!(parse_grpc_timeout("123456789S"), None);
        assert_eq!(parse_grpc_timeout("5x"), None);
    }

    #[test]
    fn polled_wait_reports_the_whole_wait_on_deadline() {
        let deadline = Instant::now() + Duration::from_millis(250);
        let r: Option<Result<(), ReplayError>> = wait_polled(
            Some(deadline),
            || false,
            |until| {
                std::thread::sleep(until.expect("always a slice deadline").saturating_duration_since(Instant::now()));
                Err(ReplayError::DeadlineExceeded { op: "insert", waited_ms: 1, state: String::new() })
            },
        );
        match r {
            Some(Err(ReplayError::DeadlineExceeded { waited_ms, .. })) => assert!(waited_ms >= 240, "{waited_ms}"),
            other => panic!("expected DeadlineExceeded, got {other:?}"),
        }
    }

    #[test]
    fn polled_wait_gives_up_when_cancelled() {
        let r: Option<Result<(), ReplayError>> = wait_polled(None, || true, |_| Err(ReplayError::DeadlineExceeded { op: "sample", waited_ms: 0, state: String::new() }));
        assert!(r.is_none());
    }
}
