//! A replay source on a table in this process, for the tests that drive the learner without a
//! replay service: the learner's [`ReplaySource`] implemented on the replay's [`Table`]. It
//! lives here, in the integration crate, because the learner must not depend on the replay
//! (dependencies follow the data: the learner receives minibatches, over gRPC in a cluster).

use std::sync::Arc;
use std::time::{Duration, Instant};

use mapless_learner::LearnerError;
use mapless_learner::source::{ReplaySource, SampleStats, checked_priorities};
use mapless_proto::v1::SampledBatch;
use mapless_replay::Table;

/// Samples straight from a replay [`Table`] in this process: the learner's update loop on a
/// table it shares with the test (the learner crate itself never depends on the replay).
pub struct InProcess {
    table: Arc<Table>,
    batch_size: usize,
    importance_beta: Option<f64>,
    timeout: Option<Duration>,
    stats: SampleStats,
}

impl std::fmt::Debug for InProcess {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.debug_struct("InProcess")
            .field("table", &self.table.config().name)
            .field("batch_size", &self.batch_size)
            .field("importance_beta", &self.importance_beta)
            .field("timeout", &self.timeout)
            .finish()
    }
}

impl InProcess {
    /// Minibatches of `batch_size` rows from `table`; `batch_size` must be in
    /// `1..=table.config().max_sample_rows`.
    pub fn new(table: Arc<Table>, batch_size: usize) -> Result<Self, LearnerError> {
        let max = table.config().max_sample_rows;
        if batch_size == 0 || batch_size > max {
            return Err(LearnerError::ReplaySourceConfig { reason: format!("batch_size is {batch_size}, must be in 1..={max} (the table's max_sample_rows)") });
        }
        Ok(Self { table, batch_size, importance_beta: None, timeout: None, stats: SampleStats::default() })
    }

    /// Importance-sampling exponent β (finite, >= 0); without it the table's configured β is
    /// used (0 for uniform tables).
    pub fn with_importance_beta(mut self, beta: f64) -> Result<Self, LearnerError> {
        if !(beta.is_finite() && beta >= 0.0) {
            return Err(LearnerError::ReplaySourceConfig { reason: format!("importance_beta is {beta}, must be finite and >= 0") });
        }
        self.importance_beta = Some(beta);
        Ok(self)
    }

    /// Longest `next_batch` waits on the rate limiter before failing with the table's
    /// deadline error; without it, it waits as long as it takes.
    pub fn with_timeout(mut self, timeout: Duration) -> Self {
        self.timeout = Some(timeout);
        self
    }

    /// The table sampled from.
    pub fn table(&self) -> &Arc<Table> {
        &self.table
    }
}

impl ReplaySource for InProcess {
    fn next_batch(&mut self) -> Result<SampledBatch, LearnerError> {
        let deadline = self.timeout.map(|t| Instant::now() + t);
        match self.table.sample(self.batch_size, self.importance_beta, deadline) {
            Ok(batch) => {
                self.stats.batches += 1;
                Ok(batch)
            }
            Err(e) => {
                self.stats.last_error = Some(e.to_string());
                Err(LearnerError::Replay(e.to_string()))
            }
        }
    }

    fn update_priorities(&mut self, keys: &[u64], priorities: &[f32]) -> Result<(), LearnerError> {
        let priorities = checked_priorities(keys, priorities)?;
        match self.table.update_priorities(keys, &priorities) {
            Ok(_) => {
                self.stats.priority_updates += 1;
                Ok(())
            }
            Err(e) => {
                self.stats.priority_update_errors += 1;
                self.stats.last_error = Some(e.to_string());
                Err(LearnerError::Replay(e.to_string()))
            }
        }
    }

    fn stats(&self) -> SampleStats {
        self.stats.clone()
    }
}
