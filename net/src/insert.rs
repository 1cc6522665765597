//! Delivering an actor's transitions to the replay service: [`InsertClient`] over its gRPC
//! `Insert` stream (any host) and [`ShmInsertClient`] over its shared-memory ingest (same host,
//! through [`ShmWriter`]). Either way delivery is at-least-once on the wire and exactly-once in
//! the table: every batch is kept until acknowledged, a broken connection is reopened with
//! exponential backoff (100 ms doubling to 5 s), and what was not acknowledged is resent,
//! oldest first, under the same (actor id, sequence), which the replay de-duplicates.
//!
//! `send` blocks only for backpressure (the window of unacknowledged batches is full, e.g.
//! while the replay's rate limiter holds inserts back) or while the replay is unreachable; it
//! gives up only when told to stop ([`Stopped`]). Both clients are synchronous (an actor's
//! loop is); the gRPC one drives its stream through a tokio runtime handle.

use std::collections::VecDeque;
use std::sync::Arc;
use std::sync::atomic::{AtomicBool, Ordering};
use std::time::{Duration, Instant};

use mapless_proto::MAX_MESSAGE_BYTES;
use mapless_proto::v1::replay_service_client::ReplayServiceClient;
use mapless_proto::v1::{InsertAck, TransitionBatch};
use tokio::runtime::Handle;
use tokio::sync::mpsc;
use tokio_stream::wrappers::ReceiverStream;

use crate::endpoint::{GrpcEndpoint, NetError};
use crate::shm::{Ack, ShmConfig, ShmError, ShmWriter};

/// Counters of one insert client since it was created.
#[derive(Clone, Debug, Default, PartialEq, serde::Serialize)]
pub struct InsertStats {
    /// Batches handed to `send`.
    pub batches: u64,
    /// Rows in them.
    pub rows: u64,
    /// Batches acknowledged (stored, or found already stored).
    pub acked: u64,
    /// Of those, acknowledged as duplicates (a resend whose first copy had arrived).
    pub duplicates: u64,
    /// Batches the replay refused as invalid (never resent; a bug on this side).
    pub rejected: u64,
    /// Connections reopened after a failure.
    pub reconnects: u64,
    /// The last connection error, for logs and status.
    pub last_error: Option<String>,
}

/// The client was told to stop while it waited (the batch may still be unacknowledged).
#[derive(Debug, thiserror::Error)]
#[error("stopped while {0}")]
pub struct Stopped(pub String);

const BACKOFF_START: Duration = Duration::from_millis(100);
const BACKOFF_MAX: Duration = Duration::from_secs(5);

/// Sleeps `d`, waking every 10 ms to return early once `stop` is set (blocking reconnect loops).
pub fn sleep_unless_stopped(d: Duration, stop: &AtomicBool) {
    let end = Instant::now() + d;
    while Instant::now() < end && !stop.load(Ordering::Relaxed) {
        std::thread::sleep(Duration::from_millis(10).min(end - Instant::now()));
    }
}

// ---------------------------------------------------------------------------------------------
// Shared memory
// ---------------------------------------------------------------------------------------------

/// [`ShmWriter`] with reconnection and backpressure handled: the shared-memory counterpart of
/// [`InsertClient`], with the same contract: a batch handed to `send` is held for delivery
/// even when `send` returns [`Stopped`], and `flush` delivers it.
pub struct ShmInsertClient {
    cfg: ShmConfig,
    actor_id: String,
    writer: Option<ShmWriter>,
    /// Batches handed to `send` and not yet taken by the writer (its window was full or the
    /// connection broken when `stop` came), oldest first; `flush` hands them over.
    held: VecDeque<TransitionBatch>,
    stats: InsertStats,
}

/// How long a blocking step of [`ShmInsertClient`] may go on: until the actor's stop flag
/// (`send`) or until a deadline (`flush`, which runs after the flag is set).
#[derive(Clone, Copy)]
enum Until<'a> {
    Stopped(&'a AtomicBool),
    Deadline(Instant),
}

impl Until<'_> {
    fn reached(self) -> bool {
        match self {
            Until::Stopped(stop) => stop.load(Ordering::Relaxed),
            Until::Deadline(d) => Instant::now() >= d,
        }
    }

    /// Sleeps `d`, or less when the limit comes first.
    fn sleep(self, d: Duration) {
        match self {
            Until::Stopped(stop) => sleep_unless_stopped(d, stop),
            Until::Deadline(end) => std::thread::sleep(d.min(end.saturating_duration_since(Instant::now()))),
        }
    }
}

impl ShmInsertClient {
    /// Connects to the ingest at `cfg`, retrying (with backoff) until it is there or `stop`.
    pub fn connect(cfg: ShmConfig, actor_id: &str, stop: &AtomicBool) -> Result<ShmInsertClient, Stopped> {
        let mut s = ShmInsertClient { cfg, actor_id: actor_id.to_owned(), writer: None, held: VecDeque::new(), stats: InsertStats::default() };
        s.ensure_connected(Until::Stopped(stop)).map_err(|()| Stopped("connecting to the shared-memory ingest".into()))?;
        Ok(s)
    }

    /// `Err` when the limit came first.
    fn ensure_connected(&mut self, until: Until) -> Result<&mut ShmWriter, ()> {
        let mut backoff = BACKOFF_START;
        while self.writer.is_none() {
            match ShmWriter::connect(&self.cfg, &self.actor_id) {
                Ok(w) => {
                    self.writer = Some(w);
                    break;
                }
                Err(e) => self.note_error(e.to_string()),
            }
            if until.reached() {
                return Err(());
            }
            until.sleep(backoff);
            backoff = (backoff * 2).min(BACKOFF_MAX);
        }
        // A writer whose connection broke resends everything unacknowledged on `reconnect`.
        Ok(self.writer.as_mut().expect("connected"))
    }

    fn note_error(&mut self, e: String) {
        if self.stats.last_error.as_deref() != Some(e.as_str()) {
            tracing::warn!(error = %e, "replay (shared memory) unreachable; retrying");
        }
        self.stats.last_error = Some(e);
    }

    fn count(&mut self, acks: Vec<Ack>) {
        for a in acks {
            match a {
                Ack::Stored(a) => {
                    self.stats.acked += 1;
                    self.stats.duplicates += u64::from(a.duplicate);
                }
                Ack::Rejected { sequence, reason } => {
                    self.stats.rejected += 1;
                    tracing::error!(sequence, reason = %reason, "replay rejected a batch");
                }
            }
        }
    }

    /// Reopens the connection (resending the window) with backoff until it works or the limit.
    fn reconnect(&mut self, until: Until) -> Result<(), ()> {
        let mut backoff = BACKOFF_START;
        loop {
            let w = self.ensure_connected(until)?;
            match w.reconnect() {
                Ok(()) => {
                    self.stats.reconnects += 1;
                    return Ok(());
                }
                Err(e) => self.note_error(e.to_string()),
            }
            if until.reached() {
                return Err(());
            }
            until.sleep(backoff);
            backoff = (backoff * 2).min(BACKOFF_MAX);
        }
    }

    /// Counters.
    pub fn stats(&self) -> &InsertStats {
        &self.stats
    }

    /// Batches handed to `send` that the writer has not taken yet (see [`ShmInsertClient::flush`]).
    pub fn held(&self) -> usize {
        self.held.len()
    }

    /// Takes `batch` (its sequence must be above the previous one's) and sends it, waiting
    /// while the window is full or the replay is unreachable. Returns once the batch is taken
    /// by the writer; `Err` when `stop` turned true first, with the batch still held here for
    /// [`ShmInsertClient::flush`].
    pub fn send(&mut self, batch: TransitionBatch, stop: &AtomicBool) -> Result<(), Stopped> {
        self.stats.batches += 1;
        self.stats.rows += u64::from(batch.num_rows);
        // The one refusal that retrying cannot fix, checked before anything is sent; every
        // other refusal below is a connection state (closed, another writer still holds the
        // actor id, backpressure) and is retried.
        let len = batch.encoded_len_f32le();
        if len > self.cfg.max_payload_bytes {
            self.stats.rejected += 1;
            tracing::error!(sequence = batch.sequence, bytes = len, limit = self.cfg.max_payload_bytes, "batch larger than the shared-memory limit; dropped (send smaller batches)");
        } else {
            self.held.push_back(batch);
        }
        self.hand_over(Until::Stopped(stop)).map_err(|()| Stopped("waiting for the replay to take a batch".into()))
    }

    /// Hands the held batches to the writer, oldest first; `Err` when the limit came first
    /// (what is left stays held).
    fn hand_over(&mut self, until: Until) -> Result<(), ()> {
        let mut backoff = BACKOFF_START;
        let send_timeout = Duration::from_millis(self.cfg.send_timeout_ms);
        while let Some(batch) = self.held.pop_front() {
            let w = match self.ensure_connected(until) {
                Ok(w) => w,
                Err(()) => {
                    self.held.push_front(batch);
                    return Err(());
                }
            };
            let sent = match until {
                // A flush waits for a free slot in the window no longer than its deadline.
                Until::Deadline(d) => w.send_by(&batch, d.min(Instant::now() + send_timeout)),
                Until::Stopped(_) => w.send(&batch),
            };
            let acks = w.poll_acks();
            match acks {
                Ok(a) => self.count(a),
                Err(e) if sent.is_ok() => {
                    // Taken; the connection broke afterwards: the window is resent on a new
                    // one (now, or by a later call when the limit comes first).
                    self.note_error(e.to_string());
                    self.reconnect(until)?;
                    backoff = BACKOFF_START;
                    continue;
                }
                Err(_) => {}
            }
            match sent {
                Ok(()) => {
                    backoff = BACKOFF_START;
                    continue;
                }
                Err(ShmError::DeadlineExceeded { .. }) => {
                    // Backpressure: the replay holds inserts back (rate limiter). Try again.
                }
                Err(e) => {
                    // Not taken: the connection is closed or another writer still holds the
                    // actor id (a predecessor's connection not yet reaped). Reconnect later.
                    self.note_error(e.to_string());
                    until.sleep(backoff);
                    backoff = (backoff * 2).min(BACKOFF_MAX);
                    if !until.reached() {
                        let _ = self.reconnect(until);
                    }
                }
            }
            self.held.push_front(batch);
            if until.reached() {
                return Err(());
            }
        }
        Ok(())
    }

    /// Hands over the held batches and waits until every batch is acknowledged, at most
    /// until `deadline`; true when none is left held or unacknowledged.
    pub fn flush(&mut self, deadline: Instant) -> bool {
        if self.hand_over(Until::Deadline(deadline)).is_err() {
            return false;
        }
        loop {
            let Some(w) = self.writer.as_mut() else { return true };
            match w.wait_acks(deadline) {
                Ok(acks) => {
                    self.count(acks);
                    return true;
                }
                Err(e) => {
                    self.note_error(e.to_string());
                    if Instant::now() >= deadline {
                        return false;
                    }
                    // The replay went away (or is restarting): resend the window on a new
                    // connection while the deadline allows.
                    std::thread::sleep(Duration::from_millis(100));
                    if let Some(w) = self.writer.as_mut()
                        && w.reconnect().is_ok()
                    {
                        self.stats.reconnects += 1;
                    }
                }
            }
        }
    }
}

// ---------------------------------------------------------------------------------------------
// gRPC
// ---------------------------------------------------------------------------------------------

/// One open `Insert` stream.
struct Stream {
    tx: mpsc::Sender<TransitionBatch>,
    acks: tonic::Streaming<InsertAck>,
}

/// The replay's gRPC `Insert` stream (TLS and bearer token from the [`GrpcEndpoint`]), driven
/// from a synchronous actor loop through a tokio runtime handle.
pub struct InsertClient {
    rt: Handle,
    endpoint: GrpcEndpoint,
    /// Sent and not yet acknowledged, oldest first (resent after a reconnect).
    window: VecDeque<Arc<TransitionBatch>>,
    /// How many of the window's newest batches are not on the current stream yet: its
    /// channel was full when they came (a stream opened later carries the whole window).
    unsent: usize,
    max_in_flight: usize,
    stream: Option<Stream>,
    stats: InsertStats,
    /// Wait before the next connection attempt; reset only by an ack, so a stream the server
    /// accepts and then refuses (ABORTED: the actor id's previous stream is still open) does
    /// not make a tight reconnect loop.
    backoff: Duration,
}

impl InsertClient {
    /// A client that connects on first use; at most `max_in_flight` batches unacknowledged.
    /// `rt` must drive its own IO (a multi-thread runtime: `Handle::block_on` on a
    /// current-thread runtime cannot), and `send`/`flush` must not be called from inside it.
    pub fn new(rt: Handle, endpoint: GrpcEndpoint, max_in_flight: usize) -> InsertClient {
        InsertClient { rt, endpoint, window: VecDeque::new(), unsent: 0, max_in_flight: max_in_flight.max(1), stream: None, stats: InsertStats::default(), backoff: Duration::ZERO }
    }

    async fn open(endpoint: &GrpcEndpoint, window: &VecDeque<Arc<TransitionBatch>>, depth: usize) -> Result<Stream, NetError> {
        let channel = endpoint.connect("replay").await?;
        let mut client = ReplayServiceClient::new(channel).max_decoding_message_size(MAX_MESSAGE_BYTES).max_encoding_message_size(MAX_MESSAGE_BYTES);
        let (tx, rx) = mpsc::channel(depth + window.len());
        // Unacknowledged batches first, unchanged and in order.
        for b in window {
            let _ = tx.try_send((**b).clone());
        }
        let request = endpoint.request("replay", ReceiverStream::new(rx))?;
        let acks = client.insert(request).await.map_err(|s| endpoint.status_error("replay", &s))?.into_inner();
        Ok(Stream { tx, acks })
    }

    fn note_error(&mut self, e: &NetError) {
        let text = e.to_string();
        if self.stats.last_error.as_deref() != Some(text.as_str()) {
            tracing::warn!(error = %text, "replay (gRPC) stream broken; reconnecting");
        }
        self.stats.last_error = Some(text);
        self.stream = None;
    }

    /// Records one ack; errors if it does not match the oldest batch in the window.
    fn on_ack(&mut self, ack: InsertAck) -> Result<(), NetError> {
        match self.window.front() {
            Some(b) if b.sequence == ack.sequence => {
                self.window.pop_front();
                self.backoff = Duration::ZERO;
                self.stats.acked += 1;
                self.stats.duplicates += u64::from(ack.duplicate);
                Ok(())
            }
            other => Err(NetError::Invalid {
                origin: self.endpoint.uri().to_owned(),
                reason: format!("ack for sequence {} while the oldest unacknowledged is {:?}", ack.sequence, other.map(|b| b.sequence)),
            }),
        }
    }

    /// Makes `s` the current stream. [`InsertClient::open`] put the whole window on it, so no
    /// batch is left unsent.
    fn attach(&mut self, s: Stream) {
        self.stream = Some(s);
        self.unsent = 0;
    }

    /// Opens a stream if there is none (resending the window), with backoff until `stop`.
    fn ensure_stream(&mut self, stop: &AtomicBool) -> Result<(), Stopped> {
        while self.stream.is_none() {
            if !self.backoff.is_zero() {
                sleep_unless_stopped(self.backoff, stop);
            }
            self.backoff = (self.backoff * 2).clamp(BACKOFF_START, BACKOFF_MAX);
            if stop.load(Ordering::Relaxed) {
                return Err(Stopped("connecting to the replay over gRPC".into()));
            }
            match self.rt.block_on(Self::open(&self.endpoint, &self.window, self.max_in_flight)) {
                Ok(s) => {
                    if self.stats.last_error.is_some() {
                        self.stats.reconnects += 1;
                    }
                    self.attach(s);
                }
                Err(e) => self.note_error(&e),
            }
        }
        Ok(())
    }

    /// Waits for the next ack (up to `wait`); Ok(false) on timeout.
    fn next_ack(&mut self, wait: Duration) -> Result<bool, NetError> {
        let Some(s) = self.stream.as_mut() else { return Ok(false) };
        let endpoint = &self.endpoint;
        let got = self.rt.block_on(async { tokio::time::timeout(wait, s.acks.message()).await });
        match got {
            Err(_) => Ok(false),
            Ok(Ok(Some(ack))) => self.on_ack(ack).map(|()| true),
            Ok(Ok(None)) => Err(NetError::Grpc { service: "replay", endpoint: endpoint.uri().to_owned(), code: tonic::Code::Unavailable, message: "insert stream ended".into() }),
            Ok(Err(status)) => {
                // RESOURCE_EXHAUSTED is the replay's disk being full: the batch stays in the
                // window and is resent, with backoff, until the replay can store it again.
                if matches!(status.code(), tonic::Code::InvalidArgument | tonic::Code::FailedPrecondition) {
                    // The oldest unacknowledged batch was refused; resending it cannot help.
                    if let Some(b) = self.window.pop_front() {
                        self.stats.rejected += 1;
                        tracing::error!(sequence = b.sequence, status = %status.message(), "replay rejected a batch; dropped");
                    }
                }
                Err(endpoint.status_error("replay", &status))
            }
        }
    }

    /// Counters.
    pub fn stats(&self) -> &InsertStats {
        &self.stats
    }

    /// Batches handed to `send` that are not on the stream yet (its channel was full); the
    /// next `send` or [`InsertClient::flush`] puts them on it, in order.
    pub fn held(&self) -> usize {
        self.unsent
    }

    /// Puts the window's unsent batches on the open stream, oldest first, as far as its
    /// channel takes them; a closed channel drops the stream (a new one carries the window).
    fn push_unsent(&mut self) {
        // Acks and refusals take the oldest batches, which are on the stream; never more.
        self.unsent = self.unsent.min(self.window.len());
        while self.unsent > 0 {
            let Some(s) = self.stream.as_ref() else { return };
            let b = &self.window[self.window.len() - self.unsent];
            match s.tx.try_send((**b).clone()) {
                Ok(()) => self.unsent -= 1,
                Err(mpsc::error::TrySendError::Full(_)) => return,
                Err(mpsc::error::TrySendError::Closed(_)) => {
                    self.stream = None;
                    return;
                }
            }
        }
    }

    /// Takes `batch` (its sequence must be above the previous one's) and sends it, waiting
    /// while the window is full or the replay is unreachable. Returns once the batch is on the
    /// stream; `Err` only when `stop` turned true first, with the batch kept for
    /// [`InsertClient::flush`] (in the window, and [`InsertClient::held`] if it is not on the
    /// stream yet).
    pub fn send(&mut self, batch: TransitionBatch, stop: &AtomicBool) -> Result<(), Stopped> {
        self.stats.batches += 1;
        self.stats.rows += u64::from(batch.num_rows);
        self.window.push_back(Arc::new(batch));
        self.unsent += 1;
        loop {
            if self.stream.is_none() {
                // A freshly opened stream carries the whole window, this batch included.
                self.ensure_stream(stop)?;
            }
            self.push_unsent();
            if self.stream.is_none() {
                continue;
            }
            // Take the acks that are there; wait only while the window is over its bound.
            let must_wait = self.unsent > 0 || self.window.len() > self.max_in_flight;
            match self.next_ack(if must_wait { Duration::from_millis(50) } else { Duration::ZERO }) {
                Ok(true) => continue,
                Ok(false) if !must_wait => return Ok(()),
                Ok(false) => {}
                Err(e) => self.note_error(&e),
            }
            if stop.load(Ordering::Relaxed) {
                return Err(Stopped("waiting for the replay to acknowledge".into()));
            }
        }
    }

    /// Waits until every batch is acknowledged, at most until `deadline`; true when none is
    /// left unacknowledged.
    pub fn flush(&mut self, deadline: Instant) -> bool {
        while !self.window.is_empty() && Instant::now() < deadline {
            if self.stream.is_none() {
                // Short attempts only: this runs at shutdown.
                match self.rt.block_on(Self::open(&self.endpoint, &self.window, self.max_in_flight)) {
                    Ok(s) => self.attach(s),
                    Err(e) => {
                        self.note_error(&e);
                        std::thread::sleep(Duration::from_millis(100));
                        continue;
                    }
                }
            }
            // Batches that `send` could not put on the stream before it was stopped.
            self.push_unsent();
            if self.stream.is_none() {
                continue;
            }
            let left = deadline.saturating_duration_since(Instant::now());
            if let Err(e) = self.next_ack(left.min(Duration::from_millis(200))) {
                self.note_error(&e);
                std::thread::sleep(Duration::from_millis(100).min(deadline.saturating_duration_since(Instant::now())));
            }
        }
        self.window.is_empty()
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    fn batch(sequence: u64) -> TransitionBatch {
        TransitionBatch { actor_id: "a".into(), sequence, num_rows: 1, ..TransitionBatch::default() }
    }

    #[test]
    fn a_grpc_send_gives_up_only_when_told_to_stop() {
        // A worker thread drives the IO: `Handle::block_on` on a current-thread runtime cannot.
        let rt = tokio::runtime::Builder::new_multi_thread().worker_threads(1).enable_all().build().unwrap();
        // Nothing listens on loopback port 1: every connection attempt fails.
        let mut client = InsertClient::new(rt.handle().clone(), GrpcEndpoint::new("http://127.0.0.1:1"), 2);
        let stop = AtomicBool::new(false);
        let err = std::thread::scope(|s| {
            s.spawn(|| {
                // Long enough for a first connection attempt to fail on a loaded machine.
                std::thread::sleep(Duration::from_secs(2));
                stop.store(true, Ordering::Relaxed);
            });
            client.send(batch(1), &stop).expect_err("stopped")
        });
        assert!(err.to_string().starts_with("stopped while "), "{err}");
        let stats = client.stats();
        assert_eq!((stats.batches, stats.rows, stats.acked), (1, 1, 0));
        assert!(stats.last_error.as_deref().is_some_and(|e| e.contains("replay at http://127.0.0.1:1")), "{stats:?}");
        // Still unacknowledged: a flush cannot finish.
        assert!(!client.flush(Instant::now() + Duration::from_millis(100)));
    }

    #[test]
    fn backoff_sleeps_end_early_on_stop() {
        let stop = AtomicBool::new(true);
        let t = Instant::now();
        sleep_unless_stopped(Duration::from_secs(5), &stop);
        assert!(t.elapsed() < Duration::from_millis(100));
    }
}
