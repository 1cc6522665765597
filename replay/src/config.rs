//! Table configuration. Defaults reproduce the paper (capacity 1,000,000, Table I) or are
//! marked [inferred] with their source.

use serde::{Deserialize, Serialize};

use crate::error::ReplayError;

/// How items are chosen for a minibatch.
#[derive(Clone, Debug, Serialize, Deserialize, PartialEq)]
#[serde(rename_all = "snake_case", tag = "kind", deny_unknown_fields)]
pub enum SamplerConfig {
    /// Every live item equally likely [paper: the MATLAB toolbox samples uniformly].
    Uniform,
    /// Proportional prioritisation (Schaul et al. 2016): P(i) = p_i^α / Σ p_k^α, importance
    /// weight w_i = (N·P(i))^−β / max_k w_k. New items get the largest priority seen so far.
    Prioritized {
        /// α, how much prioritisation is used [inferred, Schaul et al.: 0.6].
        #[serde(default = "default_alpha")]
        alpha: f64,
        /// β, importance-sampling correction used when a request does not set one, as
        /// `mapless-learner`'s Sample stream does not [inferred, Schaul et al.: 0.4, which
        /// they anneal towards 1; here it stays fixed, as Acme's DQN keeps its exponent].
        #[serde(default = "default_beta")]
        beta: f64,
        /// Added to every |TD error| update so no item becomes unsampleable [inferred: 1e-6].
        #[serde(default = "default_epsilon")]
        epsilon: f64,
    },
}

impl SamplerConfig {
    /// Proportional prioritisation with the defaults above (α 0.6, β 0.4, ε 1e-6).
    pub fn prioritized() -> Self {
        SamplerConfig::Prioritized { alpha: default_alpha(), beta: default_beta(), epsilon: default_epsilon() }
    }
}

fn default_alpha() -> f64 {
    0.6
}
fn default_beta() -> f64 {
    0.4
}
fn default_epsilon() -> f64 {
    1e-6
}

/// The one throttle between actors and learner (Reverb's `SampleToInsertRatio` limiter).
///
/// With `inserts` and `samples` counted in rows, let diff = inserts × samples_per_insert −
/// samples. Sampling waits until the table holds `min_size_to_sample` rows and a minibatch of
/// B rows keeps diff − B ≥ min_diff; inserting waits while diff > max_diff, where
/// min_diff = samples_per_insert × min_size_to_sample − error_buffer and
/// max_diff = samples_per_insert × min_size_to_sample + error_buffer.
/// `samples_per_insert = None` disables the ratio: only the minimum size gates sampling.
#[derive(Clone, Debug, Serialize, Deserialize, PartialEq)]
#[serde(default, deny_unknown_fields)]
pub struct RateLimiterConfig {
    /// Rows stored before the first sample [inferred: 1,000 — a few minibatches of warm-up].
    pub min_size_to_sample: u64,
    /// Sampled rows per inserted row (e.g. one 128-row minibatch per environment step = 128),
    /// or none for no ratio [inferred: none; the paper's toolbox updates once per step].
    pub samples_per_insert: Option<f64>,
    /// Slack around the ratio, in sampled rows; must cover the largest minibatch and insert
    /// batch (× samples_per_insert) or callers could wait forever [inferred: 100,000].
    pub error_buffer: f64,
}

impl Default for RateLimiterConfig {
    fn default() -> Self {
        RateLimiterConfig { min_size_to_sample: 1_000, samples_per_insert: None, error_buffer: 100_000.0 }
    }
}

/// One table of transitions.
#[derive(Clone, Debug, Serialize, Deserialize, PartialEq)]
#[serde(default, deny_unknown_fields)]
pub struct TableConfig {
    /// Name used in requests, logs and metrics.
    pub name: String,
    /// Rows kept; the oldest is evicted first (FIFO) [paper Table I: 1,000,000].
    pub capacity: usize,
    /// Observation length [paper: 17 = 2 × 7 beams + 3].
    pub obs_dim: usize,
    /// Action length [paper: 2, (v, ω)].
    pub act_dim: usize,
    pub sampler: SamplerConfig,
    /// Remove an item after it has been sampled this many times; 0 = never [Reverb's
    /// max_times_sampled; inferred: 0].
    pub max_times_sampled: u32,
    pub rate_limiter: RateLimiterConfig,
    /// Largest insert batch accepted, in rows [inferred: 65,536].
    pub max_batch_rows: usize,
    /// Largest minibatch served, in rows [inferred: 8,192].
    pub max_sample_rows: usize,
}

impl Default for TableConfig {
    fn default() -> Self {
        TableConfig {
            name: mapless_proto::DEFAULT_TABLE.into(),
            capacity: 1_000_000,
            obs_dim: 17,
            act_dim: 2,
            sampler: SamplerConfig::Uniform,
            max_times_sampled: 0,
            rate_limiter: RateLimiterConfig::default(),
            max_batch_rows: 65_536,
            max_sample_rows: 8_192,
        }
    }
}

impl TableConfig {
    /// Checks every field's domain, including that the rate limiter cannot deadlock.
    pub fn validate(&self) -> Result<(), ReplayError> {
        let bad = |m: String| Err(ReplayError::InvalidConfig(m));
        if self.name.is_empty() {
            return bad("table name must not be empty".into());
        }
        if self.capacity == 0 || self.capacity > u32::MAX as usize {
            return bad(format!("capacity must be in 1..=2^32-1, got {}", self.capacity));
        }
        if self.obs_dim == 0 || self.act_dim == 0 {
            return bad("obs_dim and act_dim must be ≥ 1".into());
        }
        if self.max_batch_rows == 0 || self.max_sample_rows == 0 {
            return bad("max_batch_rows and max_sample_rows must be ≥ 1".into());
        }
        if let SamplerConfig::Prioritized { alpha, beta, epsilon } = self.sampler
            && (!(alpha.is_finite() && alpha >= 0.0) || !(beta.is_finite() && beta >= 0.0) || !(epsilon.is_finite() && epsilon >= 0.0))
        {
            return bad("prioritized sampler needs finite alpha, beta, epsilon ≥ 0".into());
        }
        let rl = &self.rate_limiter;
        if rl.min_size_to_sample as usize > self.capacity {
            return bad(format!("rate_limiter.min_size_to_sample {} exceeds capacity {}", rl.min_size_to_sample, self.capacity));
        }
        if let Some(spi) = rl.samples_per_insert {
            if !(spi.is_finite() && spi > 0.0) {
                return bad(format!("rate_limiter.samples_per_insert must be > 0, got {spi}"));
            }
            let need = (self.max_sample_rows as f64).max(self.max_batch_rows as f64 * spi);
            if !(rl.error_buffer.is_finite() && rl.error_buffer >= need) {
                return bad(format!("rate_limiter.error_buffer {} must be ≥ max(max_sample_rows, max_batch_rows × samples_per_insert) = {need}, or callers can wait forever", rl.error_buffer));
            }
        }
        Ok(())
    }
}

/// When the log is forced to stable storage. Under every policy a batch is acknowledged only
/// after its record has been written to the OS (write(2)), so it survives the process being
/// killed (kill -9, OOM, panic); the policy decides what a power loss or kernel crash may take.
///
/// In YAML: `fsync: never`, `fsync: always` or `fsync: {interval_ms: 100}`.
#[derive(Clone, Copy, Debug, Serialize, Deserialize, PartialEq, Eq)]
#[serde(from = "FsyncRepr", into = "FsyncRepr")]
pub enum FsyncPolicy {
    /// Leave write-back to the OS: a power loss may take the last ~30 s (the kernel's
    /// dirty-page expiry). For throwaway runs and tmpfs.
    Never,
    /// A background thread fsyncs this often when anything was written: a power loss may
    /// take the last N ms of acknowledged batches. Inserts never wait for the disk.
    IntervalMs(u64),
    /// fsync before every acknowledgement: nothing acknowledged is lost even on power loss;
    /// every insert and priority update waits for the disk, without the table's lock, and
    /// concurrent ones share one fsync (group commit, `wal.rs`). Cost: docs/reliability.md.
    Always,
}

/// [`FsyncPolicy`] as written in config files (serde's own enum forms read badly in YAML).
#[derive(Clone, Copy, Serialize, Deserialize)]
#[serde(untagged)]
enum FsyncRepr {
    Word(FsyncWord),
    Interval { interval_ms: u64 },
}

#[derive(Clone, Copy, Serialize, Deserialize)]
#[serde(rename_all = "snake_case")]
enum FsyncWord {
    Never,
    Always,
}

impl From<FsyncRepr> for FsyncPolicy {
    fn from(r: FsyncRepr) -> Self {
        match r {
            FsyncRepr::Word(FsyncWord::Never) => FsyncPolicy::Never,
            FsyncRepr::Word(FsyncWord::Always) => FsyncPolicy::Always,
            FsyncRepr::Interval { interval_ms } => FsyncPolicy::IntervalMs(interval_ms),
        }
    }
}

impl From<FsyncPolicy> for FsyncRepr {
    fn from(p: FsyncPolicy) -> Self {
        match p {
            FsyncPolicy::Never => FsyncRepr::Word(FsyncWord::Never),
            FsyncPolicy::Always => FsyncRepr::Word(FsyncWord::Always),
            FsyncPolicy::IntervalMs(interval_ms) => FsyncRepr::Interval { interval_ms },
        }
    }
}

/// Where and how a table persists itself (write-ahead log plus periodic snapshots).
#[derive(Clone, Debug, Serialize, Deserialize, PartialEq)]
#[serde(default, deny_unknown_fields)]
pub struct PersistenceConfig {
    /// Directory holding `wal/`, `snapshots/`, a `LOCK` file and the actor slots
    /// (`actor-slots.json`, see `registry.rs`); none = memory only.
    pub dir: Option<std::path::PathBuf>,
    /// A log segment is closed once the next record would take it past this size
    /// [inferred: 64 MiB — ~350,000 default-size rows; deletion works a segment at a time].
    pub segment_bytes: u64,
    /// Durability of acknowledged records [inferred: every 100 ms, as a database's group
    /// commit would].
    pub fsync: FsyncPolicy,
    /// Seconds between background snapshots, 0 = only on close or when asked [inferred: 30].
    /// It bounds how far the sample counter can lag after a crash and how much log is kept.
    pub snapshot_interval_s: f64,
}

impl Default for PersistenceConfig {
    fn default() -> Self {
        PersistenceConfig { dir: None, segment_bytes: 64 << 20, fsync: FsyncPolicy::IntervalMs(100), snapshot_interval_s: 30.0 }
    }
}

impl PersistenceConfig {
    pub fn validate(&self) -> Result<(), ReplayError> {
        let bad = |m: String| Err(ReplayError::InvalidConfig(m));
        if self.segment_bytes < 4096 {
            return bad(format!("persistence.segment_bytes must be ≥ 4096, got {}", self.segment_bytes));
        }
        if self.fsync == FsyncPolicy::IntervalMs(0) {
            return bad("persistence.fsync interval_ms must be ≥ 1 (use `always` to sync every record)".into());
        }
        if !(self.snapshot_interval_s.is_finite() && self.snapshot_interval_s >= 0.0) {
            return bad(format!("persistence.snapshot_interval_s must be finite and ≥ 0, got {}", self.snapshot_interval_s));
        }
        Ok(())
    }
}
