//! Same-host ingest over iceoryx2 shared memory: actors on the replay server's machine hand
//! batches over in shared memory instead of a socket, into the same [`Table`] the gRPC
//! `Insert` stream feeds.
//!
//! ```text
//!   actor process                                   replay process
//!   ShmWriter (iceoryx2 client) ── request ───────► ShmIngest thread (iceoryx2 server)
//!     window of unacked batches    payload: [u8] =    decode once ─► Table::insert(deadline)
//!     (kept for resend)            prost TransitionBatch     │
//!                                  user header: actor id, sequence
//!                 ◄── response: WireAck (one per request) ───┘
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
//! The payload is the same prost encoding as on the gRPC wire. [`ShmWriter`] always writes the
//! float columns in their `bytes *_f32le` encoding ([`TransitionBatch::encode_f32le`], one
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
//! A [`ShmWriter`] keeps every batch until its ack arrives. When the connection breaks
//! (server stopped or died, writer restarted) [`ShmWriter::reconnect`] opens a new one and
//! resends every unacknowledged batch, oldest first, unchanged. The table de-duplicates on
//! (actor id, sequence): a batch at or below the actor's highest stored sequence is acked
//! with `duplicate = true` and not stored again. Batches of one actor must therefore arrive in
//! increasing sequence order, so one actor id has at most one connected writer at a time; a
//! second one is refused ([`ShmWriter::poll_acks`] fails with [`ReplayError::BadRequest`])
//! until the first disconnects or dies.
//!
//! # Dead writers and stale resources
//!
//! iceoryx2 keeps a liveness token per node; a process killed with SIGKILL leaves its node
//! "dead" and its shared memory behind. [`ShmIngest::spawn`] removes the resources of every
//! dead node before it opens the service (a killed server's port would otherwise occupy the
//! service's one server slot), force-removes the service if it is corrupted and no live node
//! uses it, and a janitor thread repeats the dead-node cleanup every `dead_node_scan_ms`.
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
//! Threading: [`ShmIngest`] owns two OS threads; [`ShmWriter`] is `Send` but not `Sync`
//! (use one per actor). Neither side allocates per row: the writer encodes a batch once and
//! copies it into shared memory, the server copies it out once and decodes it in place.

use std::collections::{HashMap, HashSet, VecDeque};
use std::sync::atomic::{AtomicBool, AtomicU64, Ordering};
use std::sync::{Arc, mpsc};
use std::thread::JoinHandle;
use std::time::{Duration, Instant};

use iceoryx2::active_request::ActiveRequest;
use iceoryx2::identifiers::UniqueClientId;
use iceoryx2::pending_response::PendingResponse;
use iceoryx2::port::client::Client;
use iceoryx2::port::server::Server;
use iceoryx2::prelude::*;
use iceoryx2::service::builder::request_response::{RequestResponseCreateError, RequestResponseOpenError, RequestResponseOpenOrCreateError};
use iceoryx2::service::port_factory::request_response::PortFactory as RrFactory;
use iceoryx2::service::port_factory::server::ServerCreateError;
use mapless_proto::MAX_ACTOR_ID_BYTES;
use mapless_proto::v1::{InsertAck, TransitionBatch};
use prost::Message;
use prost::bytes::{Bytes, BytesMut};
use serde::{Deserialize, Serialize};

use crate::error::ReplayError;
use crate::table::Table;

/// Shared-memory ingest settings; the writer and the service must use the same `prefix`,
/// and the service's values of `max_in_flight` and `max_payload_bytes` bound every writer.
#[derive(Clone, Debug, Serialize, Deserialize, PartialEq)]
#[serde(default, deny_unknown_fields)]
pub struct ShmConfig {
    /// iceoryx2 service-name prefix; the ingest service is `<prefix>/insert` [inferred:
    /// `mapless/replay/<table name>`, see [`ShmConfig::for_table`]].
    pub prefix: String,
    /// iceoryx2 domain: the prefix of every shared-memory file and node record. Only nodes of
    /// the same domain see (and clean up) each other, so separate deployments or test runs
    /// on one host stay apart. Empty: iceoryx2's default domain (`iox2_`) [inferred].
    pub domain: String,
    /// Largest encoded batch accepted, in bytes. A writer refuses a larger batch with
    /// [`ReplayError::BadRequest`] before anything is sent [inferred: the gRPC limit,
    /// `mapless_proto::MAX_MESSAGE_BYTES` = 16 MiB, ~90,000 rows of 17-float observations].
    pub max_payload_bytes: usize,
    /// Shared memory a writer reserves per batch slot up front; a larger batch grows the
    /// writer's segment (power of two) up to `max_payload_bytes` [inferred: 256 KiB, ~1,500
    /// rows of 17-float observations; memory per writer ≈ (max_in_flight + 2) × this].
    pub initial_payload_bytes: usize,
    /// Batches one writer may have sent and not yet seen acknowledged; the service's
    /// request buffer per writer [inferred: 16, i.e. 4,096 rows in flight at 256 rows a batch].
    pub max_in_flight: usize,
    /// Writers connected at once [inferred: 64 actor processes on one host].
    pub max_writers: usize,
    /// How long one insert attempt waits for the rate limiter before the ingest thread checks
    /// for shutdown and retries the same batch [inferred: 50 ms].
    pub insert_wait_ms: u64,
    /// Period of the dead-node scan that reclaims killed writers' resources [inferred: 500 ms].
    pub dead_node_scan_ms: u64,
    /// How long [`ShmWriter::send`] waits for a free slot in its window [inferred: 10 s].
    pub send_timeout_ms: u64,
    /// Longest sleep of an idle ingest thread or of a writer waiting for acks; bounds the
    /// latency added by polling [inferred: 1 ms].
    pub idle_sleep_us: u64,
}

/// Removes what iceoryx2 leaves of a domain once every node of it is gone: one small
/// management file in /dev/shm. Only for a domain this process owns alone (benchmarks, tests).
pub fn remove_private_domain_files(domain: &str) {
    for e in std::fs::read_dir("/dev/shm").into_iter().flatten().flatten() {
        if e.file_name().to_string_lossy().starts_with(domain) {
            let _ = std::fs::remove_file(e.path());
        }
    }
}

impl Default for ShmConfig {
    fn default() -> Self {
        ShmConfig::for_table(&crate::config::TableConfig::default().name)
    }
}

impl ShmConfig {
    /// Defaults, with the prefix `mapless/replay/<table>`.
    pub fn for_table(table: &str) -> ShmConfig {
        ShmConfig {
            prefix: format!("mapless/replay/{table}"),
            domain: String::new(),
            max_payload_bytes: mapless_proto::MAX_MESSAGE_BYTES,
            initial_payload_bytes: 256 * 1024,
            max_in_flight: 16,
            max_writers: 64,
            insert_wait_ms: 50,
            dead_node_scan_ms: 500,
            send_timeout_ms: 10_000,
            idle_sleep_us: 1_000,
        }
    }

    /// The iceoryx2 service batches go through.
    pub fn service_name(&self) -> String {
        format!("{}/insert", self.prefix)
    }

    /// The iceoryx2 configuration of this domain.
    fn iceoryx2_config(&self) -> Config {
        let mut config = Config::global_config().clone();
        if let Ok(prefix) = FileName::new(self.domain.as_bytes()) {
            config.global.prefix = prefix;
        }
        config
    }

    /// Checks every field's domain.
    pub fn validate(&self) -> Result<(), ReplayError> {
        let bad = |m: String| Err(ReplayError::InvalidConfig(format!("shm.{m}")));
        if self.prefix.is_empty() || ServiceName::new(&self.service_name()).is_err() {
            return bad(format!("prefix `{}` does not make a valid iceoryx2 service name (1..=248 bytes)", self.prefix));
        }
        if !self.domain.is_empty() && (self.domain.len() > 32 || FileName::new(self.domain.as_bytes()).is_err()) {
            return bad(format!("domain `{}` must be a file-name prefix of at most 32 bytes", self.domain));
        }
        if !(4096..=mapless_proto::MAX_MESSAGE_BYTES).contains(&self.max_payload_bytes) {
            return bad(format!("max_payload_bytes must be in 4096..={}, got {}", mapless_proto::MAX_MESSAGE_BYTES, self.max_payload_bytes));
        }
        if self.initial_payload_bytes == 0 || self.initial_payload_bytes > self.max_payload_bytes {
            return bad(format!("initial_payload_bytes must be in 1..=max_payload_bytes, got {}", self.initial_payload_bytes));
        }
        if !(1..=1024).contains(&self.max_in_flight) {
            return bad(format!("max_in_flight must be in 1..=1024, got {}", self.max_in_flight));
        }
        if !(1..=4096).contains(&self.max_writers) {
            return bad(format!("max_writers must be in 1..=4096, got {}", self.max_writers));
        }
        if self.insert_wait_ms == 0 || self.dead_node_scan_ms < 10 || self.send_timeout_ms == 0 {
            return bad("insert_wait_ms and send_timeout_ms must be ≥ 1, dead_node_scan_ms ≥ 10".into());
        }
        if !(1..=100_000).contains(&self.idle_sleep_us) {
            return bad(format!("idle_sleep_us must be in 1..=100000, got {}", self.idle_sleep_us));
        }
        Ok(())
    }
}

// ---------------------------------------------------------------------------------------
// Wire types. Both live in shared memory, so they are plain `repr(C)` values; the explicit
// type names make iceoryx2 refuse to connect peers built with a different layout.

/// Request user header: who sent the batch, readable even when the payload is garbage.
#[derive(Debug, Clone, Copy, ZeroCopySend)]
#[repr(C)]
#[type_name("mapless.shm.v1.BatchHeader")]
pub struct BatchHeader {
    sequence: u64,
    actor_id_len: u32,
    _reserved: u32,
    actor_id: [u8; MAX_ACTOR_ID_BYTES],
}

impl Default for BatchHeader {
    fn default() -> Self {
        BatchHeader { sequence: 0, actor_id_len: 0, _reserved: 0, actor_id: [0; MAX_ACTOR_ID_BYTES] }
    }
}

impl BatchHeader {
    fn new(actor_id: &str, sequence: u64) -> BatchHeader {
        let mut h = BatchHeader { sequence, actor_id_len: actor_id.len() as u32, ..BatchHeader::default() };
        h.actor_id[..actor_id.len()].copy_from_slice(actor_id.as_bytes());
        h
    }

    fn actor_id(&self) -> Result<&str, String> {
        let n = self.actor_id_len as usize;
        if n == 0 || n > MAX_ACTOR_ID_BYTES {
            return Err(format!("request header: actor id length {n} is not in 1..={MAX_ACTOR_ID_BYTES}"));
        }
        std::str::from_utf8(&self.actor_id[..n]).map_err(|_| "request header: actor id is not UTF-8".to_string())
    }
}

const ACK_MESSAGE_BYTES: usize = 244;

/// What the service answered; `code` is one of the `CODE_*` values.
#[derive(Debug, Clone, Copy, ZeroCopySend)]
#[repr(C)]
#[type_name("mapless.shm.v1.Ack")]
pub struct WireAck {
    sequence: u64,
    table_size: u64,
    accepted_rows: u32,
    code: u32,
    message_len: u32,
    message: [u8; ACK_MESSAGE_BYTES],
}

/// Stored now.
const CODE_STORED: u32 = 0;
/// Stored before (a resend); nothing stored now.
const CODE_DUPLICATE: u32 = 1;
/// Undecodable or invalid; never stored as sent. Counted against the actor.
const CODE_INVALID: u32 = 2;
/// Another connected writer owns this actor id; not stored, resend after reconnecting.
const CODE_ABORTED: u32 = 3;
/// The table is closed or failed to store; not stored, resend after reconnecting.
const CODE_UNAVAILABLE: u32 = 4;

impl WireAck {
    fn stored(ack: &InsertAck) -> WireAck {
        let code = if ack.duplicate { CODE_DUPLICATE } else { CODE_STORED };
        WireAck { sequence: ack.sequence, table_size: ack.table_size, accepted_rows: ack.accepted_rows, code, message_len: 0, message: [0; ACK_MESSAGE_BYTES] }
    }

    fn failed(sequence: u64, code: u32, why: &str) -> WireAck {
        // Truncate on a char boundary so the message stays UTF-8.
        let mut n = why.len().min(ACK_MESSAGE_BYTES);
        while !why.is_char_boundary(n) {
            n -= 1;
        }
        let mut message = [0; ACK_MESSAGE_BYTES];
        message[..n].copy_from_slice(&why.as_bytes()[..n]);
        WireAck { sequence, table_size: 0, accepted_rows: 0, code, message_len: n as u32, message }
    }

    fn message(&self) -> String {
        let n = (self.message_len as usize).min(ACK_MESSAGE_BYTES);
        String::from_utf8_lossy(&self.message[..n]).into_owned()
    }
}

type ServerSvc = ipc::Service;
type ClientSvc = ipc_threadsafe::Service;
type InsertServer = Server<ServerSvc, [u8], BatchHeader, WireAck, ()>;
type InsertRequest = ActiveRequest<ServerSvc, [u8], BatchHeader, WireAck, ()>;
type InsertClient = Client<ClientSvc, [u8], BatchHeader, WireAck, ()>;
type PendingAck = PendingResponse<ClientSvc, [u8], BatchHeader, WireAck, ()>;

fn closed(service: &str, why: impl std::fmt::Display) -> ReplayError {
    ReplayError::Closed(format!("{service} (shared-memory ingest: {why})"))
}

/// Polling with a growing sleep: a few yields, then 10 µs doubling up to `max`.
struct Backoff {
    spins: u32,
    sleep_us: u64,
    max_us: u64,
}

impl Backoff {
    fn new(max_us: u64) -> Backoff {
        Backoff { spins: 0, sleep_us: 10, max_us }
    }
    fn reset(&mut self) {
        self.spins = 0;
        self.sleep_us = 10;
    }
    fn snooze(&mut self) {
        if self.spins < 8 {
            self.spins += 1;
            std::thread::yield_now();
        } else {
            std::thread::sleep(Duration::from_micros(self.sleep_us.min(self.max_us)));
            self.sleep_us = (self.sleep_us * 2).min(self.max_us);
        }
    }
}

// ---------------------------------------------------------------------------------------
// Server side.

#[derive(Debug, Default)]
struct Counters {
    batches_stored: AtomicU64,
    rows_stored: AtomicU64,
    duplicate_batches: AtomicU64,
    rejected_batches: AtomicU64,
    aborted_batches: AtomicU64,
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

fn node_builder(name: &str) -> NodeBuilder {
    let b = NodeBuilder::new().signal_handling_mode(SignalHandlingMode::Disabled); // the host process owns SIGINT/SIGTERM
    match NodeName::new(name) {
        Ok(n) => b.name(&n),
        Err(_) => b,
    }
}

/// The server side's nodes clean dead nodes explicitly (and count them), not implicitly on
/// node creation, destruction or service open as iceoryx2's defaults do.
fn server_node(cfg: &ShmConfig, name: &str) -> Result<Node<ServerSvc>, String> {
    let mut config = cfg.iceoryx2_config();
    config.global.node.cleanup_dead_nodes_on_creation = false;
    config.global.node.cleanup_dead_nodes_on_destruction = false;
    config.global.service.cleanup_dead_nodes_on_open = false;
    node_builder(name).config(&config).create::<ServerSvc>().map_err(|e| format!("cannot create an iceoryx2 node: {e:?}"))
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

/// A request whose insert is waiting for the rate limiter; retried without decoding again.
/// Requests taken from the port before any is handled (more than writers × window never wait).
const MAX_QUEUED: usize = 4096;

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
        Ok(Ingest { stalled: None, queued: VecDeque::new(), spare: BytesMut::new(), server, service, node, table, cfg, counters, owners: HashMap::new() })
    }

    fn run(mut self, stop: &AtomicBool) {
        let mut idle = Backoff::new(self.cfg.idle_sleep_us);
        let scan = Duration::from_millis(self.cfg.dead_node_scan_ms);
        let mut next_prune = Instant::now() + scan;
        let mut last_receive_warning: Option<Instant> = None;
        while !stop.load(Ordering::Relaxed) {
            if Instant::now() >= next_prune {
                self.prune_owners();
                next_prune = Instant::now() + scan;
            }
            if let Some(s) = self.stalled.take() {
                if !s.request.is_connected() {
                    tracing::debug!(actor_id = %s.batch.actor_id, sequence = s.batch.sequence, "writer of a rate-limited batch went away; dropped (it resends after reconnecting)");
                    continue;
                }
                self.insert(s.request, s.batch, s.payload);
                if self.stalled.is_some() {
                    continue; // still blocked; insert() already waited insert_wait_ms
                }
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
                            if last_receive_warning.is_none_or(|t| t.elapsed() > Duration::from_secs(5)) {
                                tracing::warn!(error = ?e, "shm receive failed; cleaning dead nodes and retrying");
                                last_receive_warning = Some(Instant::now());
                            }
                            self.cleanup_dead_nodes();
                            break;
                        }
                    }
                }
            }
            match self.queued.pop_front() {
                Some(request) => {
                    idle.reset();
                    self.handle(request);
                }
                None => idle.snooze(),
            }
        }
        if let Some(s) = self.stalled.take() {
            respond(&s.request, WireAck::failed(s.batch.sequence, CODE_UNAVAILABLE, "ingest stopped while the batch waited for the rate limiter; resend after reconnecting"));
        }
        for r in self.queued.drain(..) {
            let sequence = r.user_header().sequence;
            respond(&r, WireAck::failed(sequence, CODE_UNAVAILABLE, "ingest stopped before handling the batch; resend after reconnecting"));
        }
        tracing::info!("shared-memory ingest stopped");
    }

    fn cleanup_dead_nodes(&self) {
        let s = self.node.try_cleanup_dead_nodes();
        if s.cleanups > 0 {
            self.counters.dead_nodes_cleaned.fetch_add(s.cleanups, Ordering::Relaxed);
            tracing::info!(cleaned = s.cleanups, "removed the shared-memory resources of dead iceoryx2 nodes");
        }
    }

    /// Decodes, checks and inserts one request; answers it unless the insert stalls.
    fn handle(&mut self, request: InsertRequest) {
        let header = *request.user_header();
        let actor = match header.actor_id() {
            Ok(a) => a.to_string(),
            Err(why) => return self.reject(&request, "", header.sequence, &why),
        };
        if let Err(why) = self.claim(&actor, request.origin()) {
            self.counters.aborted_batches.fetch_add(1, Ordering::Relaxed);
            tracing::warn!(actor_id = %actor, "{why}");
            return respond(&request, WireAck::failed(header.sequence, CODE_ABORTED, &why));
        }
        let payload = request.payload();
        if payload.len() > self.cfg.max_payload_bytes {
            let why = format!("batch of {} bytes exceeds the shared-memory limit of {} bytes", payload.len(), self.cfg.max_payload_bytes);
            return self.reject(&request, &actor, header.sequence, &why);
        }
        // Out of shared memory into our own buffer (one memcpy), then decoded in place: the
        // `bytes` float columns borrow from it.
        let mut buf = std::mem::take(&mut self.spare);
        buf.clear();
        buf.extend_from_slice(payload);
        let payload = buf.freeze();
        let batch = match TransitionBatch::decode(payload.clone()) {
            Ok(b) => b,
            Err(e) => {
                let why = format!("undecodable TransitionBatch ({} bytes): {e}", payload.len());
                self.recycle(payload);
                return self.reject(&request, &actor, header.sequence, &why);
            }
        };
        if batch.actor_id != actor || batch.sequence != header.sequence {
            let why = format!("request header says actor `{actor}` sequence {}, the batch says actor `{}` sequence {}", header.sequence, batch.actor_id, batch.sequence);
            drop(batch);
            self.recycle(payload);
            return self.reject(&request, &actor, header.sequence, &why);
        }
        self.insert(request, batch, payload);
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
            Err(e) => {
                tracing::warn!(actor_id = %actor_id, sequence, error = %e, "shm insert failed");
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
    }
}

fn respond(request: &InsertRequest, ack: WireAck) {
    if let Err(e) = request.send_copy(ack) {
        // The writer went away; it resends after reconnecting.
        tracing::debug!(error = ?e, sequence = ack.sequence, "cannot deliver a shm ack");
    }
}

fn rr_builder<S: iceoryx2::service::Service>(node: &Node<S>, name: &ServiceName) -> iceoryx2::service::builder::request_response::Builder<[u8], BatchHeader, WireAck, (), S> {
    node.service_builder(name).request_response::<[u8], WireAck>().request_user_header::<BatchHeader>()
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

// ---------------------------------------------------------------------------------------
// Client side.

/// The service's answer to one batch.
#[derive(Clone, Debug, PartialEq)]
pub enum Ack {
    /// The batch is in the table exactly once: stored now, or (`duplicate = true`) by an
    /// earlier send whose ack was lost.
    Stored(InsertAck),
    /// Undecodable or invalid (the reason says which); it will never be stored as sent.
    /// The service counted it against the actor.
    Rejected { sequence: u64, reason: String },
}

impl Ack {
    pub fn sequence(&self) -> u64 {
        match self {
            Ack::Stored(a) => a.sequence,
            Ack::Rejected { sequence, .. } => *sequence,
        }
    }
}

/// One batch between send and ack. `pending` is None until it is (re)sent on the current
/// connection.
struct InFlight {
    sequence: u64,
    bytes: Vec<u8>,
    pending: Option<PendingAck>,
    answer: Option<Ack>,
}

/// Why the connection cannot be used until [`ShmWriter::reconnect`].
#[derive(Clone, Debug)]
enum Broken {
    Unavailable(String),
    Aborted(String),
}

/// Field order is drop order: the client port before the service before the node.
struct Conn {
    client: InsertClient,
    service: RrFactory<ClientSvc, [u8], BatchHeader, WireAck, ()>,
    node: Node<ClientSvc>,
    /// Batches this connection may have in flight: min(config, service).
    window: usize,
}

impl Conn {
    fn open(cfg: &ShmConfig, actor_id: &str) -> Result<Conn, ReplayError> {
        let svc = cfg.service_name();
        // Creating a node also removes dead nodes' resources (iceoryx2's default), which is
        // what a restarted actor wants after its predecessor was killed.
        let node = node_builder(actor_id).config(&cfg.iceoryx2_config()).create::<ClientSvc>().map_err(|e| closed(&svc, format!("cannot create an iceoryx2 node: {e:?}")))?;
        let name = ServiceName::new(&svc).map_err(|e| ReplayError::InvalidConfig(format!("shm service name `{svc}`: {e:?}")))?;
        let service = rr_builder(&node, &name).open().map_err(|e| match e {
            RequestResponseOpenError::DoesNotExist => closed(&svc, "no ShmIngest serves it (service does not exist)"),
            e => closed(&svc, format!("cannot open the service: {e:?}")),
        })?;
        let window = cfg.max_in_flight.min(service.static_config().max_active_requests_per_client()).max(1);
        let client = service
            .client_builder()
            // The window never exceeds the server's buffer for this writer; should it be full
            // anyway (a wedged server), the send reports no delivery instead of spinning.
            .backpressure_strategy(BackpressureStrategy::DiscardData)
            .max_active_requests(window)
            .initial_max_slice_len(cfg.initial_payload_bytes)
            .allocation_strategy(AllocationStrategy::PowerOfTwo)
            .create()
            .map_err(|e| closed(&svc, format!("cannot create the client port: {e:?}")))?;
        Ok(Conn { client, service, node, window })
    }

    /// Are the servers the service lists alive? (A killed server stays listed until someone
    /// cleans dead nodes; its requests would never be answered.)
    fn server_alive(&self) -> bool {
        let mut servers = Vec::new();
        self.service.dynamic_config().list_servers(|s| {
            servers.push(s.node_id);
            CallbackProgression::Continue
        });
        servers.iter().any(|id| matches!(Node::<ClientSvc>::state_of(self.node.config(), *id), Ok(Some(NodeState::Alive(_))) | Err(_)))
    }
}

/// An actor's connection to the shared-memory ingest of a replay service on the same host.
///
/// Delivery is at-least-once on the wire and exactly-once in the table: every batch is kept
/// until acknowledged, [`ShmWriter::reconnect`] resends what is unacknowledged, and the
/// table drops resends by (actor id, sequence). Sequences are the caller's and must increase
/// strictly from batch to batch. Connection trouble is reported by `send`, `poll_acks` and
/// `wait_acks` as [`ReplayError::Closed`] (or [`ReplayError::BadRequest`] while another
/// writer holds the actor id); answer it with `reconnect`, which loses nothing.
pub struct ShmWriter {
    window: VecDeque<InFlight>,
    conn: Option<Conn>,
    cfg: ShmConfig,
    actor_id: String,
    service: String,
    ready: VecDeque<Ack>,
    broken: Option<Broken>,
    last_sequence: u64,
    last_liveness_check: Instant,
}

impl ShmWriter {
    /// Connects to the ingest serving `cfg.prefix`. Fails with [`ReplayError::Closed`] when no
    /// ingest serves it.
    pub fn connect(cfg: &ShmConfig, actor_id: &str) -> Result<ShmWriter, ReplayError> {
        cfg.validate()?;
        if actor_id.is_empty() || actor_id.len() > MAX_ACTOR_ID_BYTES {
            return Err(ReplayError::BadRequest(format!("actor id must be 1..={MAX_ACTOR_ID_BYTES} bytes, got {}", actor_id.len())));
        }
        let conn = Conn::open(cfg, actor_id)?;
        Ok(ShmWriter {
            window: VecDeque::new(),
            conn: Some(conn),
            cfg: cfg.clone(),
            actor_id: actor_id.to_string(),
            service: cfg.service_name(),
            ready: VecDeque::new(),
            broken: None,
            last_sequence: 0,
            last_liveness_check: Instant::now(),
        })
    }

    pub fn actor_id(&self) -> &str {
        &self.actor_id
    }

    /// Batches sent (or queued for resend) and not yet acknowledged.
    pub fn unacked(&self) -> usize {
        self.window.len()
    }

    /// Queues `batch` and sends it. Waits (up to `send_timeout_ms`) only while the window of
    /// `max_in_flight` unacknowledged batches is full; acks that arrive meanwhile are kept
    /// for [`ShmWriter::poll_acks`].
    ///
    /// `Ok` means the batch is taken: it will be delivered at least once, if need be after
    /// `reconnect`. `Err` means it was not taken: a batch for another actor, a sequence not
    /// above the previous one, a batch larger than `max_payload_bytes` (`BadRequest`), a
    /// full window (`DeadlineExceeded`), or a broken connection (`Closed`: reconnect, then
    /// send it again).
    pub fn send(&mut self, batch: &TransitionBatch) -> Result<(), ReplayError> {
        if batch.actor_id != self.actor_id {
            return Err(ReplayError::BadRequest(format!("batch is for actor `{}`, this writer writes `{}`", batch.actor_id, self.actor_id)));
        }
        // Float columns as `bytes *_f32le` fields: a memcpy each here, and decoded in place
        // by the ingest, whichever encoding `batch` holds them in.
        let len = batch.encoded_len_f32le();
        if len > self.cfg.max_payload_bytes {
            return Err(ReplayError::BadRequest(format!(
                "batch of {} rows encodes to {len} bytes, above the shared-memory limit shm.max_payload_bytes = {}; send smaller batches",
                batch.num_rows, self.cfg.max_payload_bytes
            )));
        }
        let mut bytes = Vec::with_capacity(len);
        batch.encode_f32le(&mut bytes);
        self.send_encoded(batch.sequence, bytes)
    }

    /// Sends bytes that claim to be the prost encoding of this actor's batch `sequence`,
    /// unchecked (test and tooling hook: the service must survive garbage).
    #[doc(hidden)]
    pub fn send_encoded(&mut self, sequence: u64, bytes: Vec<u8>) -> Result<(), ReplayError> {
        if sequence <= self.last_sequence {
            return Err(ReplayError::BadRequest(format!("sequence {sequence} is not above the last sent {}; unacknowledged batches are resent by reconnect()", self.last_sequence)));
        }
        if bytes.len() > self.cfg.max_payload_bytes {
            return Err(ReplayError::BadRequest(format!("{} bytes exceed shm.max_payload_bytes = {}", bytes.len(), self.cfg.max_payload_bytes)));
        }
        self.check_broken()?;
        let window = self.conn.as_ref().map_or(1, |c| c.window);
        if self.window.len() >= window {
            let start = Instant::now();
            let deadline = start + Duration::from_millis(self.cfg.send_timeout_ms);
            let mut backoff = Backoff::new(self.cfg.idle_sleep_us);
            loop {
                self.collect();
                self.check_broken()?;
                if self.window.len() < window {
                    break;
                }
                if Instant::now() >= deadline {
                    return Err(ReplayError::DeadlineExceeded {
                        op: "shm send",
                        waited_ms: start.elapsed().as_millis() as u64,
                        state: format!("{} batches unacknowledged by {}", self.window.len(), self.service),
                    });
                }
                self.check_server_alive();
                backoff.snooze();
            }
        }
        self.window.push_back(InFlight { sequence, bytes, pending: None, answer: None });
        self.last_sequence = sequence;
        self.transmit_unsent();
        Ok(())
    }

    /// Acks that arrived since the last call, oldest first. Fails (`Closed`, or `BadRequest`
    /// while another writer holds the actor id) once the connection is broken and every ack
    /// received before has been returned; then call [`ShmWriter::reconnect`].
    pub fn poll_acks(&mut self) -> Result<Vec<Ack>, ReplayError> {
        self.collect();
        if self.ready.is_empty() {
            self.check_broken()?;
        }
        Ok(self.ready.drain(..).collect())
    }

    /// Waits until every sent batch is acknowledged and returns the acks not yet returned.
    /// Fails with `DeadlineExceeded` at `deadline` and with `Closed` when the connection
    /// breaks (server stopped or died); acks received so far are kept for the next call.
    pub fn wait_acks(&mut self, deadline: Instant) -> Result<Vec<Ack>, ReplayError> {
        let start = Instant::now();
        let mut backoff = Backoff::new(self.cfg.idle_sleep_us);
        loop {
            self.collect();
            if self.window.is_empty() {
                return Ok(self.ready.drain(..).collect());
            }
            self.check_broken()?;
            if Instant::now() >= deadline {
                return Err(ReplayError::DeadlineExceeded {
                    op: "shm wait_acks",
                    waited_ms: start.elapsed().as_millis() as u64,
                    state: format!("{} batches unacknowledged by {}", self.window.len(), self.service),
                });
            }
            self.check_server_alive();
            backoff.snooze();
        }
    }

    /// Drops the connection, opens a new one (cleaning up dead nodes on the way) and resends
    /// every unacknowledged batch, oldest first. Batches the service had already stored are
    /// acknowledged as duplicates. On failure the batches stay queued; call it again later.
    pub fn reconnect(&mut self) -> Result<(), ReplayError> {
        for e in &mut self.window {
            e.pending = None;
        }
        self.conn = None;
        match Conn::open(&self.cfg, &self.actor_id) {
            Ok(c) => {
                self.conn = Some(c);
                self.broken = None;
                self.transmit_unsent();
                self.check_broken()
            }
            Err(e) => {
                self.broken = Some(Broken::Unavailable(e.to_string()));
                Err(e)
            }
        }
    }

    fn check_broken(&self) -> Result<(), ReplayError> {
        match &self.broken {
            None => Ok(()),
            Some(Broken::Unavailable(why)) => Err(closed(&self.service, why)),
            Some(Broken::Aborted(why)) => Err(ReplayError::BadRequest(why.clone())),
        }
    }

    fn set_broken(&mut self, b: Broken) {
        if self.broken.is_none() {
            tracing::debug!(actor_id = %self.actor_id, service = %self.service, reason = ?b, "shm writer connection broken");
            self.broken = Some(b);
        }
    }

    /// Sends every queued batch not yet sent on this connection, in order.
    fn transmit_unsent(&mut self) {
        if self.broken.is_some() {
            return;
        }
        let Some(conn) = self.conn.as_ref() else {
            return self.set_broken(Broken::Unavailable("not connected".into()));
        };
        let mut failure = None;
        for e in self.window.iter_mut().filter(|e| e.pending.is_none() && e.answer.is_none()) {
            let request = match conn.client.loan_slice_uninit(e.bytes.len()) {
                Ok(mut r) => {
                    *r.user_header_mut() = BatchHeader::new(&self.actor_id, e.sequence);
                    r.write_from_slice(&e.bytes)
                }
                Err(err) => {
                    failure = Some(format!("cannot loan {} bytes of shared memory: {err:?}", e.bytes.len()));
                    break;
                }
            };
            match request.send() {
                Ok(p) if p.number_of_server_connections() == 0 => {
                    failure = Some("no ShmIngest serves it".to_string());
                    break;
                }
                Ok(p) => e.pending = Some(p),
                Err(err) => {
                    failure = Some(format!("cannot send: {err:?}"));
                    break;
                }
            }
        }
        if let Some(why) = failure {
            self.set_broken(Broken::Unavailable(why));
        }
    }

    /// Moves answered batches out of the window into `ready`, in window order.
    fn collect(&mut self) {
        let mut broken = None;
        for e in self.window.iter_mut() {
            let Some(p) = e.pending.as_ref() else { continue };
            // Read the connection state before receiving: an answer sent just before the
            // server dropped the request is still received.
            let connected = p.is_connected();
            match p.receive() {
                Ok(Some(r)) => {
                    let a = *r.payload();
                    drop(r);
                    e.pending = None;
                    if a.sequence != e.sequence {
                        broken = Some(Broken::Unavailable(format!("protocol error: ack for sequence {} answers batch {}", a.sequence, e.sequence)));
                        continue;
                    }
                    match a.code {
                        CODE_STORED | CODE_DUPLICATE => {
                            e.answer = Some(Ack::Stored(InsertAck {
                                actor_id: self.actor_id.clone(),
                                sequence: a.sequence,
                                accepted_rows: a.accepted_rows,
                                duplicate: a.code == CODE_DUPLICATE,
                                table_size: a.table_size,
                            }))
                        }
                        CODE_INVALID => e.answer = Some(Ack::Rejected { sequence: a.sequence, reason: a.message() }),
                        CODE_ABORTED => broken = Some(Broken::Aborted(a.message())),
                        CODE_UNAVAILABLE => broken = Some(Broken::Unavailable(a.message())),
                        c => broken = Some(Broken::Unavailable(format!("unknown ack code {c}"))),
                    }
                }
                Ok(None) if !connected => {
                    e.pending = None;
                    broken = Some(Broken::Unavailable(format!("the ingest dropped batch {} without answering (stopped or died)", e.sequence)));
                }
                Ok(None) => {}
                Err(err) => {
                    e.pending = None;
                    broken = Some(Broken::Unavailable(format!("cannot receive acks: {err:?}")));
                }
            }
        }
        while let Some(pos) = self.window.iter().position(|e| e.answer.is_some()) {
            if let Some(Some(a)) = self.window.remove(pos).map(|e| e.answer) {
                self.ready.push_back(a);
            }
        }
        if let Some(b) = broken {
            self.set_broken(b);
        }
    }

    /// While waiting: every `dead_node_scan_ms`, checks that the server is alive, so that a
    /// killed server is noticed without waiting for someone to clean it up.
    fn check_server_alive(&mut self) {
        if self.last_liveness_check.elapsed() < Duration::from_millis(self.cfg.dead_node_scan_ms) {
            return;
        }
        self.last_liveness_check = Instant::now();
        if self.conn.as_ref().is_some_and(|c| !c.server_alive()) {
            self.set_broken(Broken::Unavailable("the ingest server is gone (stopped or died)".into()));
        }
    }
}
