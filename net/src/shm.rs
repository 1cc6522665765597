//! The shared-memory ingest's contract, and the writer actors use: settings ([`ShmConfig`]),
//! the wire types both sides map into shared memory ([`BatchHeader`], [`WireAck`]) and
//! [`ShmWriter`]. The replay's `shm` module serves the other end (`ShmIngest`), and its
//! module documentation describes the protocol: request-response over iceoryx2, one ack per
//! batch, at-least-once on the wire and exactly-once in the table, dead-node cleanup.
//!
//! ```text
//!   actor process                                   replay process
//!   ShmWriter (iceoryx2 client) ── request ───────► ShmIngest thread (iceoryx2 server)
//!     window of unacked batches    payload: [u8] =    decode once ─► Table::insert(deadline)
//!     (kept for resend)            prost TransitionBatch     │
//!                                  user header: actor id, sequence, writer nonce,
//!                                    request number on the connection
//!                 ◄── WireAck (per request, nonce echoed) ───┘
//! ```

use std::collections::VecDeque;
use std::time::{Duration, Instant};

use iceoryx2::pending_response::PendingResponse;
use iceoryx2::port::client::Client;
use iceoryx2::prelude::*;
use iceoryx2::service::builder::request_response::RequestResponseOpenError;
use iceoryx2::service::port_factory::request_response::PortFactory as RrFactory;
use mapless_proto::MAX_ACTOR_ID_BYTES;
use mapless_proto::v1::{InsertAck, TransitionBatch};
use serde::{Deserialize, Serialize};

/// What the shared-memory writer (and the settings' check) can fail with.
#[derive(Debug, thiserror::Error)]
pub enum ShmError {
    /// A batch or call this writer refuses (another actor's batch, a sequence not above the
    /// last, too large), or the actor id is held by another connected writer.
    #[error("{0}")]
    BadRequest(String),
    /// The window of unacknowledged batches stayed full (`send`), or acks did not all arrive
    /// (`wait_acks`), before the deadline.
    #[error("{op} waited {waited_ms} ms (deadline reached): {state}")]
    DeadlineExceeded { op: &'static str, waited_ms: u64, state: String },
    /// No ingest serves the service, or the connection broke: reconnect.
    #[error("{0} is closed")]
    Closed(String),
    /// Settings that cannot work.
    #[error("invalid config: {0}")]
    InvalidConfig(String),
}

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
    /// [`ShmError::BadRequest`] before anything is sent [inferred: the gRPC limit,
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
        ShmConfig::for_table(mapless_proto::DEFAULT_TABLE)
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

    /// The iceoryx2 configuration of this domain, for writers and the service alike.
    ///
    /// One janitor per domain: no node cleans dead nodes implicitly (on its creation or
    /// destruction, or on opening the service), as iceoryx2's defaults would. The replay's
    /// ingest does it, explicitly and counted: on start, every `dead_node_scan_ms`, and when a
    /// dead writer still claims an actor id. A restarted writer would otherwise race the
    /// janitor for its predecessor's resources, and the cleanup would go unseen.
    pub fn iceoryx2_config(&self) -> Config {
        let mut config = Config::global_config().clone();
        if let Ok(prefix) = FileName::new(self.domain.as_bytes()) {
            config.global.prefix = prefix;
        }
        config.global.node.cleanup_dead_nodes_on_creation = false;
        config.global.node.cleanup_dead_nodes_on_destruction = false;
        config.global.service.cleanup_dead_nodes_on_open = false;
        config
    }

    /// Checks every field's domain.
    pub fn validate(&self) -> Result<(), ShmError> {
        let bad = |m: String| Err(ShmError::InvalidConfig(format!("shm.{m}")));
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
#[type_name("mapless.shm.v3.BatchHeader")]
pub struct BatchHeader {
    sequence: u64,
    /// The sending connection's random nonce, echoed in its answer ([`WireAck`]).
    writer: u64,
    /// The request's place on its connection: 0 for the first request the connection sends,
    /// then 1, 2, … An ingest that sees a connection's requests jump, or begin anywhere but
    /// at 0 (the first ones went to an earlier ingest), stores nothing more from it.
    request: u64,
    actor_id_len: u32,
    _reserved: u32,
    actor_id: [u8; MAX_ACTOR_ID_BYTES],
}

impl Default for BatchHeader {
    fn default() -> Self {
        BatchHeader { sequence: 0, writer: 0, request: 0, actor_id_len: 0, _reserved: 0, actor_id: [0; MAX_ACTOR_ID_BYTES] }
    }
}

impl BatchHeader {
    /// The header of `actor_id`'s batch `sequence`, the connection's request number `request`
    /// (from 0), sent on the connection whose nonce is `writer`.
    pub fn new(actor_id: &str, sequence: u64, writer: u64, request: u64) -> BatchHeader {
        let mut h = BatchHeader { sequence, writer, request, actor_id_len: actor_id.len() as u32, ..BatchHeader::default() };
        h.actor_id[..actor_id.len()].copy_from_slice(actor_id.as_bytes());
        h
    }

    /// A header exactly as raw shared memory could hold it, unchecked (a writer never makes
    /// one: [`BatchHeader::new`]); for the replay's fuzzing harness, which feeds the ingest
    /// the headers a buggy or hostile writer could send.
    #[doc(hidden)]
    pub fn from_raw_parts(sequence: u64, actor_id_len: u32, actor_id: [u8; MAX_ACTOR_ID_BYTES]) -> BatchHeader {
        BatchHeader { sequence, writer: 0, request: 0, actor_id_len, _reserved: 0, actor_id }
    }

    /// The sender's batch sequence.
    pub fn sequence(&self) -> u64 {
        self.sequence
    }

    /// The sending connection's nonce, which every answer to this batch must echo.
    pub fn writer(&self) -> u64 {
        self.writer
    }

    /// The request's number on its connection, from 0 ([`BatchHeader::new`]).
    pub fn request(&self) -> u64 {
        self.request
    }

    /// The sender's actor id, checked.
    pub fn actor_id(&self) -> Result<&str, String> {
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
#[type_name("mapless.shm.v2.Ack")]
pub struct WireAck {
    sequence: u64,
    /// The nonce of the connection whose batch this answers ([`BatchHeader::writer`]).
    writer: u64,
    table_size: u64,
    accepted_rows: u32,
    code: u32,
    message_len: u32,
    message: [u8; ACK_MESSAGE_BYTES],
}

/// Stored now.
pub const CODE_STORED: u32 = 0;
/// Stored before (a resend); nothing stored now.
pub const CODE_DUPLICATE: u32 = 1;
/// Undecodable or invalid; never stored as sent. Counted against the actor.
pub const CODE_INVALID: u32 = 2;
/// Another connected writer owns this actor id; not stored, resend after reconnecting.
pub const CODE_ABORTED: u32 = 3;
/// The table is closed or failed to store; not stored, resend after reconnecting.
pub const CODE_UNAVAILABLE: u32 = 4;

impl WireAck {
    pub fn stored(ack: &InsertAck) -> WireAck {
        let code = if ack.duplicate { CODE_DUPLICATE } else { CODE_STORED };
        WireAck { sequence: ack.sequence, writer: 0, table_size: ack.table_size, accepted_rows: ack.accepted_rows, code, message_len: 0, message: [0; ACK_MESSAGE_BYTES] }
    }

    pub fn failed(sequence: u64, code: u32, why: &str) -> WireAck {
        // Truncate on a char boundary so the message stays UTF-8.
        let mut n = why.len().min(ACK_MESSAGE_BYTES);
        while !why.is_char_boundary(n) {
            n -= 1;
        }
        let mut message = [0; ACK_MESSAGE_BYTES];
        message[..n].copy_from_slice(&why.as_bytes()[..n]);
        WireAck { sequence, writer: 0, table_size: 0, accepted_rows: 0, code, message_len: n as u32, message }
    }

    /// This answer, addressed to the connection whose nonce is `writer`: the service answers
    /// every request with the nonce of its header ([`BatchHeader::writer`]).
    pub fn for_writer(mut self, writer: u64) -> WireAck {
        self.writer = writer;
        self
    }

    /// The batch this answers.
    pub fn sequence(&self) -> u64 {
        self.sequence
    }

    fn message(&self) -> String {
        let n = (self.message_len as usize).min(ACK_MESSAGE_BYTES);
        String::from_utf8_lossy(&self.message[..n]).into_owned()
    }
}

type ClientSvc = ipc_threadsafe::Service;
type InsertClient = Client<ClientSvc, [u8], BatchHeader, WireAck, ()>;
type PendingAck = PendingResponse<ClientSvc, [u8], BatchHeader, WireAck, ()>;

fn closed(service: &str, why: impl std::fmt::Display) -> ShmError {
    ShmError::Closed(format!("{service} (shared-memory ingest: {why})"))
}

/// Polling with a growing sleep: a few yields, then 10 µs doubling up to `max`.
pub struct Backoff {
    spins: u32,
    sleep_us: u64,
    max_us: u64,
}

impl Backoff {
    pub fn new(max_us: u64) -> Backoff {
        Backoff { spins: 0, sleep_us: 10, max_us }
    }
    pub fn reset(&mut self) {
        self.spins = 0;
        self.sleep_us = 10;
    }
    pub fn snooze(&mut self) {
        if self.spins < 8 {
            self.spins += 1;
            std::thread::yield_now();
        } else {
            std::thread::sleep(Duration::from_micros(self.sleep_us.min(self.max_us)));
            self.sleep_us = (self.sleep_us * 2).min(self.max_us);
        }
    }
}

/// A node builder named `name` (when it is a valid node name) that leaves signals to the host.
pub fn node_builder(name: &str) -> NodeBuilder {
    let b = NodeBuilder::new().signal_handling_mode(SignalHandlingMode::Disabled); // the host process owns SIGINT/SIGTERM
    match NodeName::new(name) {
        Ok(n) => b.name(&n),
        Err(_) => b,
    }
}

/// The ingest service's request-response builder: payload, user header and response types.
pub fn rr_builder<S: iceoryx2::service::Service>(node: &Node<S>, name: &ServiceName) -> iceoryx2::service::builder::request_response::Builder<[u8], BatchHeader, WireAck, (), S> {
    node.service_builder(name).request_response::<[u8], WireAck>().request_user_header::<BatchHeader>()
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

/// Moves the answered batches at the front of the window into `ready`, so that acks come out
/// in the order the batches were sent. The ingest answers one writer's batches in order, but
/// one pass of [`ShmWriter::collect`] can find batch 4 answered after it found batch 1 not yet
/// answered; batch 4 then waits in the window until batch 1's answer is read.
fn hand_over_answered(window: &mut VecDeque<InFlight>, ready: &mut VecDeque<Ack>) {
    while window.front().is_some_and(|e| e.answer.is_some()) {
        if let Some(a) = window.pop_front().and_then(|e| e.answer) {
            ready.push_back(a);
        }
    }
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
    /// Random, per connection: every request carries it and every answer must echo it.
    /// iceoryx2 routes a response by the server's connection slot, channel and request id;
    /// a killed writer's slot may pass to a new client whose request ids and sequences also
    /// start from the beginning, so an answer the ingest still sends to a request of the dead
    /// writer can reach the new one's pending request of the same number. Without the nonce
    /// that stranger's "stored" would be taken for a batch the ingest never received.
    nonce: u64,
    /// Requests sent on this connection (the next one's [`BatchHeader::request`]).
    sent: u64,
}

/// A random nonce, never 0 (the value of a header made by `BatchHeader::from_raw_parts`).
fn connection_nonce() -> u64 {
    use std::hash::BuildHasher;
    static OPENED: std::sync::atomic::AtomicU64 = std::sync::atomic::AtomicU64::new(0);
    let n = OPENED.fetch_add(1, std::sync::atomic::Ordering::Relaxed);
    let now = std::time::SystemTime::now().duration_since(std::time::UNIX_EPOCH).map_or(0, |d| d.as_nanos());
    // RandomState's keys are random per process (and vary per call within one).
    std::collections::hash_map::RandomState::new().hash_one((std::process::id(), now, n)).max(1)
}

impl Conn {
    fn open(cfg: &ShmConfig, actor_id: &str) -> Result<Conn, ShmError> {
        let svc = cfg.service_name();
        // A killed predecessor's resources are the service's to remove (see `iceoryx2_config`).
        let node = node_builder(actor_id).config(&cfg.iceoryx2_config()).create::<ClientSvc>().map_err(|e| closed(&svc, format!("cannot create an iceoryx2 node: {e:?}")))?;
        let name = ServiceName::new(&svc).map_err(|e| ShmError::InvalidConfig(format!("shm service name `{svc}`: {e:?}")))?;
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
        Ok(Conn { client, service, node, window, nonce: connection_nonce(), sent: 0 })
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
/// `wait_acks` as [`ShmError::Closed`] (or [`ShmError::BadRequest`] while another
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
    /// Connects to the ingest serving `cfg.prefix`. Fails with [`ShmError::Closed`] when no
    /// ingest serves it.
    pub fn connect(cfg: &ShmConfig, actor_id: &str) -> Result<ShmWriter, ShmError> {
        cfg.validate()?;
        if actor_id.is_empty() || actor_id.len() > MAX_ACTOR_ID_BYTES {
            return Err(ShmError::BadRequest(format!("actor id must be 1..={MAX_ACTOR_ID_BYTES} bytes, got {}", actor_id.len())));
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
    pub fn send(&mut self, batch: &TransitionBatch) -> Result<(), ShmError> {
        self.send_by(batch, Instant::now() + Duration::from_millis(self.cfg.send_timeout_ms))
    }

    /// [`ShmWriter::send`], waiting for a free slot in the window until `deadline` instead of
    /// `send_timeout_ms` (a caller with a deadline of its own, such as a flush at shutdown).
    pub fn send_by(&mut self, batch: &TransitionBatch, deadline: Instant) -> Result<(), ShmError> {
        if batch.actor_id != self.actor_id {
            return Err(ShmError::BadRequest(format!("batch is for actor `{}`, this writer writes `{}`", batch.actor_id, self.actor_id)));
        }
        // Float columns as `bytes *_f32le` fields: a memcpy each here, and decoded in place
        // by the ingest, whichever encoding `batch` holds them in.
        let len = batch.encoded_len_f32le();
        if len > self.cfg.max_payload_bytes {
            return Err(ShmError::BadRequest(format!(
                "batch of {} rows encodes to {len} bytes, above the shared-memory limit shm.max_payload_bytes = {}; send smaller batches",
                batch.num_rows, self.cfg.max_payload_bytes
            )));
        }
        let mut bytes = Vec::with_capacity(len);
        batch.encode_f32le(&mut bytes);
        self.send_encoded_by(batch.sequence, bytes, deadline)
    }

    /// Sends bytes that claim to be the prost encoding of this actor's batch `sequence`,
    /// unchecked (test and tooling hook: the service must survive garbage).
    #[doc(hidden)]
    pub fn send_encoded(&mut self, sequence: u64, bytes: Vec<u8>) -> Result<(), ShmError> {
        self.send_encoded_by(sequence, bytes, Instant::now() + Duration::from_millis(self.cfg.send_timeout_ms))
    }

    fn send_encoded_by(&mut self, sequence: u64, bytes: Vec<u8>, deadline: Instant) -> Result<(), ShmError> {
        if sequence <= self.last_sequence {
            return Err(ShmError::BadRequest(format!("sequence {sequence} is not above the last sent {}; unacknowledged batches are resent by reconnect()", self.last_sequence)));
        }
        if bytes.len() > self.cfg.max_payload_bytes {
            return Err(ShmError::BadRequest(format!("{} bytes exceed shm.max_payload_bytes = {}", bytes.len(), self.cfg.max_payload_bytes)));
        }
        self.check_broken()?;
        let window = self.conn.as_ref().map_or(1, |c| c.window);
        if self.window.len() >= window {
            let start = Instant::now();
            let mut backoff = Backoff::new(self.cfg.idle_sleep_us);
            loop {
                self.collect();
                self.check_broken()?;
                if self.window.len() < window {
                    break;
                }
                if Instant::now() >= deadline {
                    return Err(ShmError::DeadlineExceeded {
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
    pub fn poll_acks(&mut self) -> Result<Vec<Ack>, ShmError> {
        self.collect();
        if self.ready.is_empty() {
            self.check_broken()?;
        }
        Ok(self.ready.drain(..).collect())
    }

    /// Waits until every sent batch is acknowledged and returns the acks not yet returned.
    /// Fails with `DeadlineExceeded` at `deadline` and with `Closed` when the connection
    /// breaks (server stopped or died); acks received so far are kept for the next call.
    pub fn wait_acks(&mut self, deadline: Instant) -> Result<Vec<Ack>, ShmError> {
        let start = Instant::now();
        let mut backoff = Backoff::new(self.cfg.idle_sleep_us);
        loop {
            self.collect();
            if self.window.is_empty() {
                return Ok(self.ready.drain(..).collect());
            }
            self.check_broken()?;
            if Instant::now() >= deadline {
                return Err(ShmError::DeadlineExceeded {
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
    pub fn reconnect(&mut self) -> Result<(), ShmError> {
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

    fn check_broken(&self) -> Result<(), ShmError> {
        match &self.broken {
            None => Ok(()),
            Some(Broken::Unavailable(why)) => Err(closed(&self.service, why)),
            Some(Broken::Aborted(why)) => Err(ShmError::BadRequest(why.clone())),
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
        let Some(conn) = self.conn.as_mut() else {
            return self.set_broken(Broken::Unavailable("not connected".into()));
        };
        let mut failure = None;
        for e in self.window.iter_mut().filter(|e| e.pending.is_none() && e.answer.is_none()) {
            let request = match conn.client.loan_slice_uninit(e.bytes.len()) {
                Ok(mut r) => {
                    *r.user_header_mut() = BatchHeader::new(&self.actor_id, e.sequence, conn.nonce, conn.sent);
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
                Ok(p) => {
                    conn.sent += 1;
                    e.pending = Some(p);
                }
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

    /// Receives the answers that arrived and moves answered batches out of the window into
    /// `ready`, in window order (see [`hand_over_answered`]).
    fn collect(&mut self) {
        // The first failure of the pass (`get_or_insert` below): the oldest batch's answer says
        // why; later ones may only say that an earlier batch was not stored.
        let mut broken = None;
        let nonce = self.conn.as_ref().map_or(0, |c| c.nonce);
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
                    if a.writer != nonce {
                        // Another connection's answer (see `Conn::nonce`): says nothing of this
                        // batch. Reconnecting resends it; the table drops it if it was stored.
                        broken.get_or_insert(Broken::Unavailable(format!("protocol error: the answer for batch {} was addressed to another shm writer connection", e.sequence)));
                        continue;
                    }
                    if a.sequence != e.sequence {
                        broken.get_or_insert(Broken::Unavailable(format!("protocol error: ack for sequence {} answers batch {}", a.sequence, e.sequence)));
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
                        CODE_ABORTED => {
                            broken.get_or_insert(Broken::Aborted(a.message()));
                        }
                        CODE_UNAVAILABLE => {
                            broken.get_or_insert(Broken::Unavailable(a.message()));
                        }
                        c => {
                            broken.get_or_insert(Broken::Unavailable(format!("unknown ack code {c}")));
                        }
                    }
                }
                Ok(None) if !connected => {
                    e.pending = None;
                    broken.get_or_insert(Broken::Unavailable(format!("the ingest dropped batch {} without answering (stopped or died)", e.sequence)));
                }
                Ok(None) => {}
                Err(err) => {
                    e.pending = None;
                    broken.get_or_insert(Broken::Unavailable(format!("cannot receive acks: {err:?}")));
                }
            }
        }
        hand_over_answered(&mut self.window, &mut self.ready);
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

#[cfg(test)]
mod tests {
    use super::*;

    fn in_flight(sequence: u64, answered: bool) -> InFlight {
        let answer = answered.then(|| Ack::Stored(InsertAck { actor_id: "a".into(), sequence, accepted_rows: 1, duplicate: false, table_size: sequence }));
        InFlight { sequence, bytes: Vec::new(), pending: None, answer }
    }

    fn sequences(ready: &VecDeque<Ack>) -> Vec<u64> {
        ready
            .iter()
            .map(|a| match a {
                Ack::Stored(s) => s.sequence,
                Ack::Rejected { sequence, .. } => *sequence,
            })
            .collect()
    }

    #[test]
    fn acks_are_handed_over_in_the_order_the_batches_were_sent() {
        // Batches 4 and 5 were seen answered in a pass that found 1..=3 not yet answered.
        let mut window: VecDeque<InFlight> = (1..=5).map(|s| in_flight(s, s >= 4)).collect();
        let mut ready = VecDeque::new();
        hand_over_answered(&mut window, &mut ready);
        assert!(ready.is_empty());
        assert_eq!(window.len(), 5);
        // The next pass reads 1 and 3; 2 still holds 3, 4 and 5 back.
        for e in window.iter_mut().filter(|e| e.sequence == 1 || e.sequence == 3) {
            *e = in_flight(e.sequence, true);
        }
        hand_over_answered(&mut window, &mut ready);
        assert_eq!(sequences(&ready), [1]);
        window[0] = in_flight(2, true);
        hand_over_answered(&mut window, &mut ready);
        assert_eq!(sequences(&ready), [1, 2, 3, 4, 5]);
        assert!(window.is_empty());
    }
}
