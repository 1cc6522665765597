//! Where the learner's minibatches come from: any [`ReplaySource`] — the replay service over
//! gRPC ([`GrpcSource`]), or, in tests, a table in the same process (the workspace's `tests`
//! crate implements one; the learner does not depend on the replay crate). Every source hands
//! out `mapless.v1.SampledBatch`es and takes priority updates.
//!
//! [`GrpcSource`] is a thin adapter over `mapless-net`'s [`SampleClient`], which does the
//! transport: a background thread keeps a queue of decoded minibatches full from the `Sample`
//! stream (its HTTP/2 window sized to the prefetch), reconnects with exponential backoff, and
//! sends priority updates asynchronously; see [`mapless_net::sample`]. Errors that retrying
//! cannot fix (wrong table, wrong token, a protocol or dims mismatch) stop the source:
//! `next_batch` returns [`LearnerError::ReplaySourceStopped`] from then on.
//!
//! Everything here is libtorch-free.

use std::time::Duration;

pub use mapless_net::sample::{SampleClient, SampleConfig, SampleStats, minibatch_wire_bytes, sample_stream_window};
use mapless_proto::v1::SampledBatch;

use crate::error::LearnerError;
/// Where a gRPC service is and how to reach it (`mapless-net`, shared with the actors).
pub use mapless_net::GrpcEndpoint;

// ---------------------------------------------------------------------------------------------
// The trait
// ---------------------------------------------------------------------------------------------

/// A stream of minibatches for the update loop, and the way back for new priorities.
///
/// Threading: owned by the update thread (`Send`, used through `&mut self`).
pub trait ReplaySource: Send {
    /// The next minibatch of the configured batch size. Blocks until one is available (the
    /// replay rate limiter may hold it back, e.g. during warm-up).
    fn next_batch(&mut self) -> Result<SampledBatch, LearnerError>;

    /// New priorities (typically |TD error| + ε) for keys of sampled rows. Fails at once on
    /// bad input (lengths differ, NaN, infinite or negative values); otherwise may be applied
    /// later. Tables that sample uniformly ignore updates.
    fn update_priorities(&mut self, keys: &[u64], priorities: &[f32]) -> Result<(), LearnerError>;

    /// Counters since the source was created (`mapless-net`'s [`SampleStats`], which every
    /// source reports: an in-process one counts priority updates it applied as acknowledged).
    fn stats(&self) -> SampleStats;

    /// Like [`ReplaySource::next_batch`], but waits at most about `timeout`: `Ok(None)` when no
    /// minibatch came in time (so a caller can look at its stop flag). The default waits as
    /// long as `next_batch` does.
    fn next_batch_timeout(&mut self, timeout: Duration) -> Result<Option<SampledBatch>, LearnerError> {
        let _ = timeout;
        self.next_batch().map(Some)
    }
}

/// Checks priorities before they leave the update thread; returns them as f64. Every
/// [`ReplaySource`] calls it first in `update_priorities`.
pub fn checked_priorities(keys: &[u64], priorities: &[f32]) -> Result<Vec<f64>, LearnerError> {
    if keys.len() != priorities.len() {
        return Err(LearnerError::InvalidPriorities { reason: format!("{} keys but {} priorities", keys.len(), priorities.len()) });
    }
    if let Some(i) = priorities.iter().position(|p| !(p.is_finite() && *p >= 0.0)) {
        return Err(LearnerError::InvalidPriorities { reason: format!("priority {i} (key {}) is {}; priorities must be finite and >= 0", keys[i], priorities[i]) });
    }
    Ok(priorities.iter().map(|&p| f64::from(p)).collect())
}

// ---------------------------------------------------------------------------------------------
// gRPC source
// ---------------------------------------------------------------------------------------------

/// Samples from the replay service over gRPC: a [`ReplaySource`] over a [`SampleClient`]
/// (prefetching on its background thread; see the module doc), whose errors it reports as
/// [`LearnerError`]s.
///
/// Dropping it stops the background thread (and waits for it, at most a moment).
#[derive(Debug)]
pub struct GrpcSource {
    client: SampleClient,
}

impl GrpcSource {
    /// Starts the client's background thread, which connects (and keeps reconnecting) on its
    /// own: this returns at once, even when the service is not up yet. Fails only on a config
    /// that can never work ([`LearnerError::ReplaySourceConfig`]).
    pub fn start(config: SampleConfig) -> Result<Self, LearnerError> {
        Ok(Self { client: SampleClient::start(config)? })
    }

    /// Like [`ReplaySource::next_batch`], but gives up after `timeout` with `Ok(None)` (for
    /// an update loop that wants to log that it is waiting).
    pub fn next_batch_timeout(&mut self, timeout: Duration) -> Result<Option<SampledBatch>, LearnerError> {
        Ok(self.client.next_batch_timeout(timeout)?)
    }
}

impl ReplaySource for GrpcSource {
    fn next_batch_timeout(&mut self, timeout: Duration) -> Result<Option<SampledBatch>, LearnerError> {
        GrpcSource::next_batch_timeout(self, timeout)
    }

    fn next_batch(&mut self) -> Result<SampledBatch, LearnerError> {
        Ok(self.client.next_batch()?)
    }

    fn update_priorities(&mut self, keys: &[u64], priorities: &[f32]) -> Result<(), LearnerError> {
        let priorities = checked_priorities(keys, priorities)?;
        Ok(self.client.update_priorities(keys, priorities)?)
    }

    fn stats(&self) -> SampleStats {
        self.client.stats()
    }
}
