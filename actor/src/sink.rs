//! Where an actor's transitions go: the replay service's shared-memory ingest (same host) or
//! its gRPC `Insert` stream (any host). The two clients — exactly-once delivery, backoff, stop
//! handling — live in `mapless-net` ([`mapless_net::insert`]); [`Sink`] picks one per actor.
//!
//! [`Sink::send`] blocks only for backpressure (the window of unacknowledged batches is
//! full, e.g. while the replay's rate limiter holds inserts back) or while the replay is
//! unreachable; it gives up only when told to stop.

use std::sync::atomic::AtomicBool;
use std::time::Instant;

pub use mapless_net::insert::{InsertClient, InsertStats, ShmInsertClient, Stopped};
use mapless_proto::v1::TransitionBatch;

/// The replay service an actor writes to.
pub enum Sink {
    /// Shared memory (iceoryx2), for an actor on the replay's host.
    Shm(ShmInsertClient),
    /// gRPC `Insert` stream.
    Grpc(InsertClient),
}

impl Sink {
    /// Takes `batch` (its sequence must be above the previous one's) and sends it, waiting
    /// while the window is full or the replay is unreachable. Returns once the batch is held
    /// for delivery; `Err` only when `stop` turned true first, and the batch is then still held
    /// for [`Sink::flush`] (both clients: the rows an actor hands over are the rows it owes).
    pub fn send(&mut self, batch: TransitionBatch, stop: &AtomicBool) -> Result<(), Stopped> {
        match self {
            Sink::Shm(s) => s.send(batch, stop),
            Sink::Grpc(s) => s.send(batch, stop),
        }
    }

    /// Waits until every batch is acknowledged, at most until `deadline`; true when none is
    /// left unacknowledged.
    pub fn flush(&mut self, deadline: Instant) -> bool {
        match self {
            Sink::Shm(s) => s.flush(deadline),
            Sink::Grpc(s) => s.flush(deadline),
        }
    }

    /// Counters.
    pub fn stats(&self) -> &InsertStats {
        match self {
            Sink::Shm(s) => s.stats(),
            Sink::Grpc(s) => s.stats(),
        }
    }
}
