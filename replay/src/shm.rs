//! Same-host ingest over iceoryx2 shared memory: actors on the replay server's machine hand
//! batches over in shared memory instead of a socket, into the same [`Table`] the gRPC
//! `Insert` stream feeds.
//!
//! ```text
//!   actor process                                   replay process
//!   ShmWriter (iceoryx2 client) ── request ───────► ShmIngest thread (iceoryx2 server)
//!     window of unacked batches    payload: [u8] =    decode once ─► Table::insert(deadline)
//!     (kept for resend)            prost TransitionBatch     │
//!                                  user header: actor id, sequence, writer nonce,
//!                                    request number on the connection
//!                 ◄── WireAck (per request, nonce echoed) ───┘
//!                                                   janitor thread: Node::try_cleanup_dead_nodes
//! ```
//!
//! One iceoryx2 request-response service, `<prefix>/insert` (default prefix
//! `mapless/replay/<table>`). Request-response rather than publish-subscribe because it is
//! the pattern with a reverse channel per request: every batch gets exactly one answer,
//! routed to the writer that sent it, with no per-actor ack services to create and clean up.
//! Request overflow is disabled and a writer may have at most `max_in_flight` requests
//! outstanding, which is also the server's buffer per writer, so no request is ever
//! overwritten or dropped while both sides live.
//!
//! The payload is the same prost encoding as on the gRPC wire. [`ShmWriter`](mapless_net::shm::ShmWriter) always writes the
//! float columns in their `bytes *_f32le` encoding ([`TransitionBatch::encode_f32le`](mapless_proto::v1::TransitionBatch::encode_f32le), one
//! memcpy per column, whatever encoding the caller's batch holds). The ingest thread copies
//! the payload out of shared memory into a reused buffer, decodes it there (the float columns
//! are borrowed from the buffer, not copied), validates, and the table copies each column
//! into its storage with one memcpy; a persistent table logs the received bytes as they are.
//! A packed-float payload (older writers, `send_encoded`) is accepted too; prost then decodes
//! its floats one by one, which was the largest server-side cost for wide observations. A
//! hand-made columnar layout would save the remaining copy out of shared memory, but the wire
//! contract and its validation would then exist twice.
//!
//! # Delivery: at-least-once on the wire, exactly-once in the table
//!
//! A [`ShmWriter`](mapless_net::shm::ShmWriter) keeps every batch until its ack arrives. When the connection breaks
//! (server stopped or died, writer restarted) [`ShmWriter::reconnect`](mapless_net::shm::ShmWriter::reconnect) opens a new one and
//! resends every unacknowledged batch, oldest first, unchanged. The table de-duplicates on
//! (actor id, sequence): a batch at or below the actor's highest stored sequence is acked
//! with `duplicate = true` and not stored again. Batches of one actor must therefore arrive in
//! increasing sequence order, so one actor id has at most one connected writer at a time; a
//! second one is refused ([`ShmWriter::poll_acks`](mapless_net::shm::ShmWriter::poll_acks) fails with `ShmError::BadRequest`)
//! until the first disconnects or dies.
//! A writer connection is also a stream, as a gRPC `Insert` stream is: once one of its batches
//! is not stored and must be resent (refused because another writer owns its actor id, or for
//! a failed insert, dropped because its writer went away while it waited for the rate limiter,
//! or sent to an ingest that stopped: every request carries its number on its connection),
//! nothing later from that connection is stored, so the table never holds batch *k*+1 without
//! *k* and never takes *k*'s resend for a duplicate ([`Ingest::handle`]).
//!
//! Every answer echoes the nonce of its request's header (one per writer connection), and a
//! writer takes only answers that carry its own. iceoryx2 routes a response by the server's
//! connection slot, channel and request id; once a killed writer's slot passes to a new writer,
//! whose request ids and batch sequences also start from the beginning, an answer the ingest
//! still gives a request of the dead writer would otherwise be taken for the new one's batch of
//! the same number, and that batch would never be resent (seen once in the compose drill: three
//! batches acknowledged and never stored).
//!
//! # Dead writers and stale resources
//!
//! iceoryx2 keeps a liveness token per node; a process killed with SIGKILL leaves its node
//! "dead" and its shared memory behind. [`ShmIngest::spawn`] removes the resources of every
//! dead node before it opens the service (a killed server's port would otherwise occupy the
//! service's one server slot), force-removes the service if it is corrupted and no live node
//! uses it, and a janitor thread repeats the dead-node cleanup every `dead_node_scan_ms`. It is
//! the domain's only cleaner: no writer's node cleans implicitly ([`ShmConfig::iceoryx2_config`]),
//! so every cleanup is counted (`dead_nodes_cleaned`) and logged.
//! Cleaning removes the dead writer's ports from the service, so the ingest thread's
//! connection update skips them and keeps serving everyone else. The janitor has its own
//! thread so that an insert blocked by the rate limiter never delays it; the ingest thread
//! itself waits at most `insert_wait_ms` per attempt and then retries the same request (the
//! ack is delayed, never dropped).
//!
//! Bad input never stops the ingest: undecodable bytes, a header that disagrees with the
//! batch, or a batch that fails validation is counted against its actor
//! ([`Table::record_rejection`]) and answered with a rejection.
//!
//! Threading: [`ShmIngest`] owns two OS threads; [`ShmWriter`](mapless_net::shm::ShmWriter) is `Send` but not `Sync`
//! (use one per actor). Neither side allocates per row: the writer encodes a batch once and
//! copies it into shared memory, the server copies it out once and decodes it in place.

use std::collections::{HashMap, HashSet, VecDeque};
use std::sync::atomic::{AtomicBool, AtomicU64, Ordering};
use std::sync::{Arc, mpsc};
use std::thread::JoinHandle;
use std::time::{Duration, Instant};

use iceoryx2::active_request::ActiveRequest;
use iceoryx2::identifiers::UniqueClientId;
use iceoryx2::port::server::Server;
use iceoryx2::prelude::*;
use iceoryx2::service::builder::request_response::{RequestResponseCreateError, RequestResponseOpenError, RequestResponseOpenOrCreateError};
use iceoryx2::service::port_factory::request_response::PortFactory as RrFactory;
use iceoryx2::service::port_factory::server::ServerCreateError;
use mapless_net::shm::{Backoff, BatchHeader, CODE_ABORTED, CODE_INVALID, CODE_UNAVAILABLE, ShmConfig, WireAck, node_builder, rr_builder};
use mapless_proto::v1::TransitionBatch;
use prost::Message;
use prost::bytes::{Bytes, BytesMut};
use serde::Serialize;

use crate::error::ReplayError;
use crate::table::Table;

type ServerSvc = ipc::Service;
type InsertServer = Server<ServerSvc, [u8], BatchHeader, WireAck, ()>;
type InsertRequest = ActiveRequest<ServerSvc, [u8], BatchHeader, WireAck, ()>;

fn closed(service: &str, why: impl std::fmt::Display) -> ReplayError {
    ReplayError::Closed(format!("{service} (shared-memory ingest: {why})"))
}

#[derive(Debug, Default)]
struct Counters {
    batches_stored: AtomicU64,
    rows_stored: AtomicU64,
    duplicate_batches: AtomicU64,
    rejected_batches: AtomicU64,
    aborted_batches: AtomicU64,
    abandoned_batches: AtomicU64,
    insert_stalls: AtomicU64,
    dead_nodes_cleaned: AtomicU64,
    receive_errors: AtomicU64,
}

/// Counters of one [`ShmIngest`] since it started.
#[derive(Clone, Debug, Default, PartialEq, Eq, Serialize)]
pub struct ShmStats {
    pub batches_stored: u64,
    pub rows_stored: u64,
    /// Resends acknowledged as duplicates (nothing stored).
    pub duplicate_batches: u64,
    /// Undecodable or invalid batches (also counted per actor by the table).
    pub rejected_batches: u64,
    /// Batches refused because another connected writer owns the actor id.
    pub aborted_batches: u64,
    /// Batches not stored because their writer connection was gone or had ended ([`Ingest::handle`]):
    /// its writer went away (a batch waiting for the rate limiter counts too), or an earlier
    /// batch of it was refused (counted as aborted, or as a failed insert) or never arrived
    /// (the first out-of-turn batch counts too). The writer resends them on its next connection.
    pub abandoned_batches: u64,
    /// Insert attempts that hit `insert_wait_ms` on the rate limiter and were retried.
    pub insert_stalls: u64,
    /// Dead iceoryx2 nodes (killed writers or servers) whose resources were removed.
    pub dead_nodes_cleaned: u64,
    /// Receive calls that failed to update connections (e.g. a half-dead writer); retried.
    pub receive_errors: u64,
}

/// The shared-memory ingest service: an OS thread answering writers, plus a janitor thread.
/// Dropping it stops both (see [`ShmIngest::stop`]).
pub struct ShmIngest {
    service: String,
    stop: Arc<AtomicBool>,
    counters: Arc<Counters>,
    threads: Vec<JoinHandle<()>>,
}

impl ShmIngest {
    /// Cleans up dead nodes' resources, opens (or creates) the service, and starts serving
    /// `table`. Fails if another live ingest already serves the same service, or if the
    /// service exists with incompatible settings.
    pub fn spawn(table: Arc<Table>, cfg: ShmConfig) -> Result<ShmIngest, ReplayError> {
        cfg.validate()?;
        let service = cfg.service_name();
        let stop = Arc::new(AtomicBool::new(false));
        let counters = Arc::new(Counters::default());
        let (ready_tx, ready_rx) = mpsc::sync_channel(1);
        let ingest = {
            let (stop, counters, cfg) = (Arc::clone(&stop), Arc::clone(&counters), cfg.clone());
            std::thread::Builder::new()
                .name("shm-ingest".into())
                .spawn(move || {
                    let span = tracing::info_span!("shm_ingest", service = %cfg.service_name(), table = %table.config().name);
                    let _enter = span.enter();
                    match Ingest::open(table, cfg, counters) {
                        Ok(ingest) => {
                            let _ = ready_tx.send(Ok(()));
                            ingest.run(&stop);
                        }
                        Err(e) => {
                            let _ = ready_tx.send(Err(e));
                        }
                    }
                })
                .map_err(|e| closed(&service, format!("cannot start the ingest thread: {e}")))?
        };
        match ready_rx.recv() {
            Ok(Ok(())) => {}
            Ok(Err(e)) => {
                let _ = ingest.join();
                return Err(e);
            }
            Err(_) => {
                let _ = ingest.join();
                return Err(closed(&service, "the ingest thread died while starting"));
            }
        }
        let mut me = ShmIngest { service: service.clone(), stop: Arc::clone(&stop), counters: Arc::clone(&counters), threads: vec![ingest] };
        // The janitor's node is made here so that it exists when spawn returns.
        let node = server_node(&cfg, "mapless-replay-shm-janitor").map_err(|e| closed(&service, e))?; // `me` drops: stops ingest
        let scan = Duration::from_millis(cfg.dead_node_scan_ms);
        let janitor = std::thread::Builder::new().name("shm-janitor".into()).spawn(move || janitor(node, scan, &stop, &counters));
        match janitor {
            Ok(j) => me.threads.push(j),
            Err(e) => return Err(closed(&service, format!("cannot start the janitor thread: {e}"))),
        }
        tracing::info!(service = %service, "shared-memory ingest serving");
        Ok(me)
    }

    /// The iceoryx2 service name writers connect to.
    pub fn service_name(&self) -> &str {
        &self.service
    }

    pub fn stats(&self) -> ShmStats {
        let c = &self.counters;
        let g = |a: &AtomicU64| a.load(Ordering::Relaxed);
        ShmStats {
            batches_stored: g(&c.batches_stored),
            rows_stored: g(&c.rows_stored),
            duplicate_batches: g(&c.duplicate_batches),
            rejected_batches: g(&c.rejected_batches),
            aborted_batches: g(&c.aborted_batches),
            abandoned_batches: g(&c.abandoned_batches),
            insert_stalls: g(&c.insert_stalls),
            dead_nodes_cleaned: g(&c.dead_nodes_cleaned),
            receive_errors: g(&c.receive_errors),
        }
    }

    /// Stops serving and joins both threads (within about `insert_wait_ms`). A batch whose
    /// insert was waiting on the rate limiter is answered "unavailable"; batches not yet
    /// received stay unacknowledged, and their writers resend them to the next ingest.
    pub fn stop(mut self) {
        self.shutdown();
    }

    fn shutdown(&mut self) {
        self.stop.store(true, Ordering::Relaxed);
        for t in &self.threads {
            t.thread().unpark();
        }
        for t in self.threads.drain(..) {
            let _ = t.join();
        }
    }
}

impl Drop for ShmIngest {
    fn drop(&mut self) {
        self.shutdown();
    }
}

/// A server-side node. It cleans dead nodes explicitly (and counts them), never implicitly:
/// see [`ShmConfig::iceoryx2_config`].
fn server_node(cfg: &ShmConfig, name: &str) -> Result<Node<ServerSvc>, String> {
    node_builder(name).config(&cfg.iceoryx2_config()).create::<ServerSvc>().map_err(|e| format!("cannot create an iceoryx2 node: {e:?}"))
}

/// Reclaims dead nodes' resources every `scan` until stopped. Its own thread and node, so a
/// blocked insert on the ingest thread never delays it.
fn janitor(node: Node<ServerSvc>, scan: Duration, stop: &AtomicBool, counters: &Counters) {
    while !stop.load(Ordering::Relaxed) {
        std::thread::park_timeout(scan);
        if stop.load(Ordering::Relaxed) {
            break;
        }
        let s = node.try_cleanup_dead_nodes();
        if s.cleanups > 0 {
            counters.dead_nodes_cleaned.fetch_add(s.cleanups, Ordering::Relaxed);
            tracing::info!(cleaned = s.cleanups, failed = s.failed_cleanups, "removed the shared-memory resources of dead iceoryx2 nodes");
        }
    }
}

/// Requests taken from the port before any is handled (more than writers × window never wait).
const MAX_QUEUED: usize = 4096;

/// A request whose insert is waiting for the rate limiter; retried without decoding again.
struct Stalled {
    request: InsertRequest,
    batch: TransitionBatch,
    /// The payload `batch` was decoded from (and borrows its float columns from).
    payload: Bytes,
}

/// The ingest thread's state. Field order is drop order: requests before ports before node.
struct Ingest {
    stalled: Option<Stalled>,
    /// Requests received and not yet handled, in arrival order. Taking every waiting request
    /// before handling any serves writers in turn: `receive` alone favours the first client
    /// port with a request, so a writer that refills its window at once could starve others
    /// while the rate limiter lets one batch through at a time.
    queued: VecDeque<InsertRequest>,
    /// The payload buffer of the last batch, reused for the next one once nothing borrows it
    /// (no allocation and no page faults per batch).
    spare: BytesMut,
    server: InsertServer,
    service: RrFactory<ServerSvc, [u8], BatchHeader, WireAck, ()>,
    node: Node<ServerSvc>,
    table: Arc<Table>,
    cfg: ShmConfig,
    counters: Arc<Counters>,
    /// actor id → the client port that writes it (one connected writer per actor id).
    owners: HashMap<String, UniqueClientId>,
    /// Writer connections one of whose batches was not stored and must be resent (refused
    /// with ABORTED, a failed insert, or out of turn): nothing later from them is stored (see
    /// [`Ingest::handle`]). Pruned with `owners`.
    ended: HashSet<UniqueClientId>,
    /// Per writer connection, the [`BatchHeader::request`] its next request must carry.
    /// Pruned with `owners`.
    next_request: HashMap<UniqueClientId, u64>,
    next_prune: Instant,
    last_receive_warning: Option<Instant>,
}

impl Ingest {
    fn open(table: Arc<Table>, cfg: ShmConfig, counters: Arc<Counters>) -> Result<Ingest, ReplayError> {
        let svc = cfg.service_name();
        let node = server_node(&cfg, "mapless-replay-shm-ingest").map_err(|e| closed(&svc, e))?;
        // Stale resources first: a killed server's port would hold the one server slot, a
        // killed writer's segments would otherwise stay in /dev/shm.
        let s = node.blocking_cleanup_dead_nodes(Duration::from_secs(1));
        counters.dead_nodes_cleaned.fetch_add(s.cleanups, Ordering::Relaxed);
        if s.cleanups + s.failed_cleanups > 0 {
            tracing::info!(cleaned = s.cleanups, failed = s.failed_cleanups, "removed stale shared-memory resources of dead iceoryx2 nodes at start");
        }
        let name = ServiceName::new(&svc).map_err(|e| ReplayError::InvalidConfig(format!("shm service name `{svc}`: {e:?}")))?;
        let service = open_service(&node, &name, &cfg)?;
        // Never wait on a writer: a full response buffer (a writer that stopped reading) loses
        // that writer its ack, it does not stall everyone else.
        let server = service.server_builder().backpressure_strategy(BackpressureStrategy::DiscardData).create().map_err(|e| match e {
            ServerCreateError::ExceedsMaxSupportedServers => closed(&svc, "another live ShmIngest already serves this service"),
            e => closed(&svc, format!("cannot create the server port: {e:?}")),
        })?;
        let next_prune = Instant::now() + Duration::from_millis(cfg.dead_node_scan_ms);
        Ok(Ingest {
            stalled: None,
            queued: VecDeque::new(),
            spare: BytesMut::new(),
            server,
            service,
            node,
            table,
            cfg,
            counters,
            owners: HashMap::new(),
            ended: HashSet::new(),
            next_request: HashMap::new(),
            next_prune,
            last_receive_warning: None,
        })
    }

    fn run(mut self, stop: &AtomicBool) {
        let mut idle = Backoff::new(self.cfg.idle_sleep_us);
        while !stop.load(Ordering::Relaxed) {
            if self.turn() {
                idle.reset();
            } else {
                idle.snooze();
            }
        }
        if let Some(s) = self.stalled.take()
            && self.client_connected(s.request.origin())
        {
            respond(&s.request, WireAck::failed(s.batch.sequence, CODE_UNAVAILABLE, "ingest stopped while the batch waited for the rate limiter; resend after reconnecting"));
        }
        for r in std::mem::take(&mut self.queued) {
            // Not to a gone writer (see `handle`).
            if self.client_connected(r.origin()) {
                let sequence = r.user_header().sequence();
                respond(&r, WireAck::failed(sequence, CODE_UNAVAILABLE, "ingest stopped before handling the batch; resend after reconnecting"));
            }
        }
        tracing::info!("shared-memory ingest stopped");
    }

    /// One pass of the ingest loop: retries the insert waiting for the rate limiter, or else
    /// handles the next request (receiving every waiting one first when none is queued).
    /// False when there was nothing to do.
    fn turn(&mut self) -> bool {
        if Instant::now() >= self.next_prune {
            self.prune_owners();
            self.next_prune = Instant::now() + Duration::from_millis(self.cfg.dead_node_scan_ms);
        }
        if let Some(s) = self.stalled.take() {
            // By its client port, not `ActiveRequest::is_connected`: iceoryx2 may hand a gone
            // writer's connection slot to a new writer, and the request then reads as
            // connected again. A port that is gone never comes back.
            if !self.client_connected(s.request.origin()) {
                self.counters.abandoned_batches.fetch_add(1, Ordering::Relaxed);
                tracing::debug!(actor_id = %s.batch.actor_id, sequence = s.batch.sequence, "writer of a rate-limited batch went away; dropped with everything after it (it resends after reconnecting)");
                return true;
            }
            self.insert(s.request, s.batch, s.payload);
            return true; // stalled again or not, insert() already waited at most insert_wait_ms
        }
        if self.queued.is_empty() {
            loop {
                match self.server.receive() {
                    Ok(Some(request)) => {
                        self.queued.push_back(request);
                        if self.queued.len() >= MAX_QUEUED {
                            break;
                        }
                    }
                    Ok(None) => break,
                    Err(e) => {
                        // Usually a writer that died half-way; cleaning dead nodes drops its
                        // connection. Keep serving meanwhile.
                        self.counters.receive_errors.fetch_add(1, Ordering::Relaxed);
                        if self.last_receive_warning.is_none_or(|t| t.elapsed() > Duration::from_secs(5)) {
                            tracing::warn!(error = ?e, "shm receive failed; cleaning dead nodes and retrying");
                            self.last_receive_warning = Some(Instant::now());
                        }
                        self.cleanup_dead_nodes();
                        break;
                    }
                }
            }
        }
        match self.queued.pop_front() {
            Some(request) => {
                self.handle(request);
                true
            }
            None => false,
        }
    }

    fn cleanup_dead_nodes(&self) {
        let s = self.node.try_cleanup_dead_nodes();
        if s.cleanups > 0 {
            self.counters.dead_nodes_cleaned.fetch_add(s.cleanups, Ordering::Relaxed);
            tracing::info!(cleaned = s.cleanups, "removed the shared-memory resources of dead iceoryx2 nodes");
        }
    }

    /// Decodes, checks and inserts one request; answers it unless the insert stalls.
    ///
    /// A writer connection is a stream, as a gRPC `Insert` stream is: once one of its batches
    /// is not stored for a reason its writer must retry — its writer went away while the
    /// batch waited for the rate limiter, it was refused (another writer owns its actor id)
    /// or answered "resend after reconnecting" (a failed insert), or it
    /// never reached this ingest (the connection's request numbers jump, or begin past 0
    /// because the first ones went to an ingest that has since stopped) — nothing later from
    /// that connection is stored either, and its writer resends them all, in order, on its
    /// next connection. (A batch rejected as invalid is final: its writer moves on.) Storing a
    /// later one would leave a hole the table cannot see: it de-duplicates on the highest
    /// sequence stored, so the resend of the missing batch would be acknowledged as a
    /// duplicate and its rows never stored.
    fn handle(&mut self, request: InsertRequest) {
        let header = *request.user_header();
        let client = request.origin();
        if !self.client_connected(client) {
            // Not answered: nobody waits for it, and an answer could reach the writer's next
            // connection if iceoryx2 gave it the same slot (see `Conn::nonce` in mapless-net).
            self.counters.abandoned_batches.fetch_add(1, Ordering::Relaxed);
            return;
        }
        if self.ended.contains(&client) {
            self.counters.abandoned_batches.fetch_add(1, Ordering::Relaxed);
            return respond(&request, WireAck::failed(header.sequence(), CODE_UNAVAILABLE, "an earlier batch of this connection was not stored; resend after reconnecting"));
        }
        // A connection this ingest meets half-way (its first requests went to an earlier
        // ingest, which may have stopped before storing them) or whose requests jump is
        // ended the same way: what is missing may be a batch never stored.
        let expected = self.next_request.get(&client).copied().unwrap_or(0);
        if header.request() != expected {
            self.counters.abandoned_batches.fetch_add(1, Ordering::Relaxed);
            self.ended.insert(client);
            let why = format!("request {} of this connection arrived where {expected} was due (sent to an earlier ingest, or lost); resend after reconnecting", header.request());
            tracing::debug!(sequence = header.sequence(), "{why}");
            return respond(&request, WireAck::failed(header.sequence(), CODE_UNAVAILABLE, &why));
        }
        self.next_request.insert(client, expected + 1);
        let actor = match header.actor_id() {
            Ok(a) => a.to_string(),
            Err(why) => return self.reject(&request, "", header.sequence(), &why),
        };
        if let Err(why) = self.claim(&actor, client) {
            self.counters.aborted_batches.fetch_add(1, Ordering::Relaxed);
            tracing::warn!(actor_id = %actor, "{why}");
            self.ended.insert(client);
            return respond(&request, WireAck::failed(header.sequence(), CODE_ABORTED, &why));
        }
        let payload = request.payload();
        if payload.len() > self.cfg.max_payload_bytes {
            let why = format!("batch of {} bytes exceeds the shared-memory limit of {} bytes", payload.len(), self.cfg.max_payload_bytes);
            return self.reject(&request, &actor, header.sequence(), &why);
        }
        // Out of shared memory into our own buffer (one memcpy), then decoded in place: the
        // `bytes` float columns borrow from it.
        let mut buf = std::mem::take(&mut self.spare);
        buf.clear();
        buf.extend_from_slice(payload);
        let payload = buf.freeze();
        match decode_payload(&actor, header.sequence(), payload.clone()) {
            Ok(batch) => self.insert(request, batch, payload),
            Err(why) => {
                self.recycle(payload);
                self.reject(&request, &actor, header.sequence(), &why);
            }
        }
    }

    /// Keeps a payload buffer for the next batch when nothing else holds it any more.
    fn recycle(&mut self, payload: Bytes) {
        if let Ok(buf) = payload.try_into_mut() {
            self.spare = buf;
        }
    }

    fn reject(&self, request: &InsertRequest, actor: &str, sequence: u64, why: &str) {
        self.counters.rejected_batches.fetch_add(1, Ordering::Relaxed);
        self.table.record_rejection(actor, why);
        respond(request, WireAck::failed(sequence, CODE_INVALID, why));
    }

    /// Inserts with a deadline; on a rate-limiter timeout keeps the request in `stalled`.
    fn insert(&mut self, request: InsertRequest, mut batch: TransitionBatch, payload: Bytes) {
        let deadline = Instant::now() + Duration::from_millis(self.cfg.insert_wait_ms);
        let result = self.table.insert_encoded(&batch, Some(&payload), Some(deadline));
        if let Err(ReplayError::DeadlineExceeded { .. }) = result {
            self.counters.insert_stalls.fetch_add(1, Ordering::Relaxed);
            self.stalled = Some(Stalled { request, batch, payload });
            return;
        }
        let (sequence, actor_id) = (batch.sequence, std::mem::take(&mut batch.actor_id));
        drop(batch); // releases the borrowed float columns, so the buffer can be reused
        self.recycle(payload);
        match result {
            Ok(ack) => {
                let c = &self.counters;
                if ack.duplicate {
                    c.duplicate_batches.fetch_add(1, Ordering::Relaxed);
                } else {
                    c.batches_stored.fetch_add(1, Ordering::Relaxed);
                    c.rows_stored.fetch_add(u64::from(ack.accepted_rows), Ordering::Relaxed);
                }
                respond(&request, WireAck::stored(&ack));
            }
            Err(e @ (ReplayError::Invalid(_) | ReplayError::BadRequest(_))) => {
                // The table has already counted it against the actor.
                self.counters.rejected_batches.fetch_add(1, Ordering::Relaxed);
                respond(&request, WireAck::failed(sequence, CODE_INVALID, &e.to_string()));
            }
            // A full disk is reported once by the log and counted; the actor resends.
            Err(e @ ReplayError::DiskFull { .. }) => {
                tracing::debug!(actor_id = %actor_id, sequence, error = %e, "shm insert refused: disk full");
                self.ended.insert(request.origin());
                respond(&request, WireAck::failed(sequence, CODE_UNAVAILABLE, &e.to_string()));
            }
            Err(e) => {
                tracing::warn!(actor_id = %actor_id, sequence, error = %e, "shm insert failed");
                self.ended.insert(request.origin());
                respond(&request, WireAck::failed(sequence, CODE_UNAVAILABLE, &e.to_string()));
            }
        }
    }

    /// One connected writer per actor id, so that an actor's batches arrive in order. A new
    /// writer takes an actor id over once the previous one has disconnected or died.
    fn claim(&mut self, actor: &str, client: UniqueClientId) -> Result<(), String> {
        match self.owners.get(actor) {
            Some(owner) if *owner == client => Ok(()),
            Some(&owner) => {
                if self.client_connected(owner) {
                    // It may be dead but not yet cleaned up (killed a moment ago).
                    self.cleanup_dead_nodes();
                    if self.client_connected(owner) {
                        return Err(format!("actor id `{actor}` is already written by another connected ShmWriter; one writer per actor id at a time"));
                    }
                }
                tracing::info!(actor_id = %actor, "actor moved to a new shm writer connection");
                self.owners.insert(actor.to_string(), client);
                Ok(())
            }
            None => {
                if self.owners.len() >= 4 * self.cfg.max_writers {
                    self.prune_owners();
                }
                self.owners.insert(actor.to_string(), client);
                Ok(())
            }
        }
    }

    fn client_connected(&self, id: UniqueClientId) -> bool {
        let mut found = false;
        self.service.dynamic_config().list_clients(|c| {
            found = c.client_id == id;
            if found { CallbackProgression::Stop } else { CallbackProgression::Continue }
        });
        found
    }

    /// Forgets owners whose client port is gone (disconnected, or dead and cleaned up).
    fn prune_owners(&mut self) {
        let mut live = HashSet::new();
        self.service.dynamic_config().list_clients(|c| {
            live.insert(c.client_id);
            CallbackProgression::Continue
        });
        self.owners.retain(|actor, c| {
            let keep = live.contains(c);
            if !keep {
                tracing::info!(actor_id = %actor, "shm writer disconnected");
            }
            keep
        });
        // A port that is gone stays gone: `handle` drops what it still sent without these.
        self.ended.retain(|c| live.contains(c));
        self.next_request.retain(|c, _| live.contains(c));
    }
}

/// Decodes a request's payload (already copied out of shared memory) into the batch it
/// carries, borrowing the float columns from `payload`, and checks that the batch is the one
/// its header announces (`actor`, the header's checked actor id, and `sequence`). `Err` says
/// why the request is rejected. Validation against the table is the table's (`insert_encoded`).
pub(crate) fn decode_payload(actor: &str, sequence: u64, payload: Bytes) -> Result<TransitionBatch, String> {
    let len = payload.len();
    let batch = TransitionBatch::decode(payload).map_err(|e| format!("undecodable TransitionBatch ({len} bytes): {e}"))?;
    if batch.actor_id != actor || batch.sequence != sequence {
        return Err(format!("request header says actor `{actor}` sequence {sequence}, the batch says actor `{}` sequence {}", batch.actor_id, batch.sequence));
    }
    Ok(batch)
}

/// Answers `request`, echoing its writer's nonce: a writer takes only answers that carry its
/// own (see `mapless_net::shm::BatchHeader::writer`).
fn respond(request: &InsertRequest, ack: WireAck) {
    let ack = ack.for_writer(request.user_header().writer());
    if let Err(e) = request.send_copy(ack) {
        // The writer went away; it resends after reconnecting.
        tracing::debug!(error = ?e, sequence = ack.sequence(), "cannot deliver a shm ack");
    }
}

/// Opens or creates the service; if a dead creator left it corrupted and no live node uses
/// it, removes it and tries once more.
fn open_service(node: &Node<ServerSvc>, name: &ServiceName, cfg: &ShmConfig) -> Result<RrFactory<ServerSvc, [u8], BatchHeader, WireAck, ()>, ReplayError> {
    let svc = name.as_str();
    let attempt = || {
        rr_builder(node, name)
            .enable_safe_overflow_for_requests(false)
            .max_active_requests_per_client(cfg.max_in_flight)
            .max_servers(1)
            .max_clients(cfg.max_writers)
            // Writers, the ingest, and slack for reconnecting writers whose old node lingers.
            .max_nodes(cfg.max_writers + 8)
            .open_or_create()
    };
    let mut removed = false;
    for _ in 0..20 {
        match attempt() {
            Ok(s) => return Ok(s),
            Err(RequestResponseOpenOrCreateError::SystemInFlux) => std::thread::sleep(Duration::from_millis(10)),
            Err(e) if is_stale(&e) && !removed => {
                if live_nodes_using(node, name) > 0 {
                    return Err(closed(svc, format!("service is in a broken state ({e:?}) but live processes still use it")));
                }
                tracing::warn!(error = ?e, "removing a stale shared-memory service left by a dead process");
                // SAFETY: no live node is registered at the service (checked just above).
                match unsafe { node.force_remove_service(name, MessagingPattern::RequestResponse) } {
                    Ok(_) => removed = true,
                    Err(re) => return Err(closed(svc, format!("cannot remove the stale service ({e:?}): {re:?}"))),
                }
            }
            Err(e) => return Err(closed(svc, format!("cannot open the service: {e:?}"))),
        }
    }
    Err(closed(svc, "the service kept changing while opening it"))
}

fn is_stale(e: &RequestResponseOpenOrCreateError) -> bool {
    use RequestResponseCreateError as C;
    use RequestResponseOpenError as O;
    matches!(
        e,
        RequestResponseOpenOrCreateError::RequestResponseOpenError(O::HangsInCreation | O::InternalFailure)
            | RequestResponseOpenOrCreateError::RequestResponseCreateError(C::HangsInCreation | C::ServiceInCorruptedState | C::IsBeingCreatedByAnotherInstance)
    )
}

fn live_nodes_using(node: &Node<ServerSvc>, name: &ServiceName) -> usize {
    use iceoryx2::service::Service as _;
    match ServerSvc::details(name, node.config(), MessagingPattern::RequestResponse) {
        Ok(Some(d)) => d.dynamic_details.map_or(0, |dd| dd.nodes.iter().filter(|n| matches!(n, NodeState::Alive(_))).count()),
        Ok(None) => 0,
        Err(_) => usize::MAX, // cannot tell: do not remove anything
    }
}

#[cfg(test)]
mod tests {
    use mapless_net::shm::{Ack, ShmWriter, remove_private_domain_files};
    use mapless_proto::{Transition, TransitionBatchBuilder};

    use super::*;
    use crate::config::{RateLimiterConfig, TableConfig};

    /// `rows` rows of `actor`'s batch `seq`, 3 floats of observation.
    fn batch(actor: &str, seq: u64, rows: usize) -> TransitionBatch {
        let mut b = TransitionBatchBuilder::new(3, 2);
        for i in 0..rows {
            let r = (seq * 1000 + i as u64) as f32;
            b.push(Transition {
                obs: &[r, 0.0, 1.0],
                action: &[0.1, -0.1],
                reward: r,
                next_obs: &[r, 1.0, 0.0],
                terminal: false,
                truncated: false,
                episode_id: seq,
                step: i as u32,
                policy_version: 1,
            })
            .unwrap();
        }
        b.finish(actor, seq)
    }

    /// A service in an iceoryx2 domain of this test's own; its management file is removed
    /// when the guard drops, passed or failed.
    struct Domain(ShmConfig);

    impl Domain {
        fn new(tag: &str) -> Domain {
            let domain = format!("mlu{}{tag}_", std::process::id());
            Domain(ShmConfig { prefix: format!("mapless-unit/{tag}"), domain, insert_wait_ms: 1, dead_node_scan_ms: 100, ..ShmConfig::default() })
        }
    }

    impl Drop for Domain {
        fn drop(&mut self) {
            remove_private_domain_files(&self.0.domain);
        }
    }

    /// Inserts wait once more than 110 rows are unsampled: of 100-row batches, two pass and
    /// then one per 100 rows sampled.
    fn rate_limited_table() -> Arc<Table> {
        let limiter = RateLimiterConfig { min_size_to_sample: 10, samples_per_insert: Some(1.0), error_buffer: 100.0 };
        Arc::new(Table::new(TableConfig { capacity: 10_000, obs_dim: 3, rate_limiter: limiter, max_batch_rows: 100, max_sample_rows: 100, ..TableConfig::default() }, 1).unwrap())
    }

    /// A domain of this test's own, the rate-limited table, counters, and an ingest over them.
    fn rate_limited_ingest(tag: &str) -> (Domain, Arc<Table>, Arc<Counters>, Ingest) {
        let d = Domain::new(tag);
        let table = rate_limited_table();
        let counters = Arc::new(Counters::default());
        let ingest = Ingest::open(Arc::clone(&table), d.0.clone(), Arc::clone(&counters)).unwrap();
        (d, table, counters, ingest)
    }

    fn sample(table: &Table) {
        table.sample(100, None, Some(Instant::now() + Duration::from_secs(5))).unwrap();
    }

    /// Drives `ingest` by hand, as the actor's client drives `w` (reconnecting whenever the
    /// connection breaks), sampling whenever an insert waits for the rate limiter, until
    /// every batch is acknowledged; returns the sequences acknowledged, in order.
    fn deliver(ingest: &mut Ingest, w: &mut ShmWriter, table: &Table) -> Vec<u64> {
        let deadline = Instant::now() + Duration::from_secs(20);
        let mut acked = Vec::new();
        while w.unacked() > 0 {
            if !ingest.turn() && ingest.stalled.is_none() {
                std::thread::sleep(Duration::from_millis(1));
            }
            if ingest.stalled.is_some() {
                sample(table);
            }
            match w.poll_acks() {
                Ok(acks) => acked.extend(acks.iter().map(|a| match a {
                    Ack::Stored(s) => s.sequence,
                    Ack::Rejected { sequence, reason } => panic!("batch {sequence} rejected: {reason}"),
                })),
                Err(_) => w.reconnect().unwrap(),
            }
            assert!(Instant::now() < deadline, "{} batches never acknowledged; acknowledged {acked:?}", w.unacked());
        }
        acked
    }

    /// The ingest's loop, driven by hand, sees a writer reconnect while one of its batches
    /// waits for the rate limiter and the next is queued behind it, and the limiter opens
    /// just then. Before, the waiting batch was dropped (its writer had gone) and the queued
    /// one stored: the table held batch 4 without batch 3, and answered the resend of 3
    /// "duplicate", so the writer counted 3 delivered that no sample could ever draw.
    #[test]
    fn a_writer_that_reconnects_behind_the_rate_limiter_has_every_batch_stored_in_order() {
        let (d, table, counters, mut ingest) = rate_limited_ingest("stall");
        let mut w = ShmWriter::connect(&d.0, "a").unwrap();
        for seq in 1..=4 {
            w.send(&batch("a", seq, 100)).unwrap();
        }
        let deadline = Instant::now() + Duration::from_secs(20);
        while ingest.stalled.is_none() {
            ingest.turn();
            assert!(Instant::now() < deadline, "batch 3 never waited for the rate limiter");
        }
        assert_eq!((ingest.stalled.as_ref().map(|s| s.batch.sequence), ingest.queued.len()), (Some(3), 1), "batch 3 waits, batch 4 is queued behind it");
        // The old connection's port goes; all four are sent again (no ack was read yet).
        w.reconnect().unwrap();
        sample(&table); // room for one more batch, which must be batch 3
        assert_eq!(deliver(&mut ingest, &mut w, &table), [1, 2, 3, 4]);
        // What the writer was told is what the table holds: four batches, none missing.
        let a = &table.actors()["a"];
        assert_eq!((a.batches, a.rows, a.last_sequence), (4, 400, 4));
        assert!(counters.abandoned_batches.load(Ordering::Relaxed) >= 2, "the old connection's 3 and 4 were not stored");
    }

    /// A replay restarted under a live writer: batch 2 went to the ingest that stopped and
    /// was never stored; the writer, not yet aware, sends batch 3 on the same connection,
    /// which reaches the new ingest. Before, the new ingest stored 3, and the resend of 2
    /// was acknowledged as a duplicate. Now a connection met half-way is told to resend.
    #[test]
    fn a_connection_that_began_with_an_earlier_ingest_is_told_to_resend() {
        let (d, table, counters, mut first) = rate_limited_ingest("restart");
        let mut w = ShmWriter::connect(&d.0, "b").unwrap();
        w.send(&batch("b", 1, 100)).unwrap();
        assert_eq!(deliver(&mut first, &mut w, &table), [1]);
        w.send(&batch("b", 2, 100)).unwrap();
        drop(first); // stops before receiving batch 2
        let mut second = Ingest::open(Arc::clone(&table), d.0.clone(), Arc::clone(&counters)).unwrap();
        w.send(&batch("b", 3, 100)).unwrap();
        assert_eq!(deliver(&mut second, &mut w, &table), [2, 3]);
        let b = &table.actors()["b"];
        assert_eq!((b.batches, b.rows, b.last_sequence), (3, 300, 3));
    }
}
