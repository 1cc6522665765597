//! The learner's main loop: sample → update → (priorities) → publish every K → checkpoint.
//!
//! ```text
//!   ReplaySource ──SampledBatch──► Minibatch ──► Agent::update ──► |TD error| ──► priorities
//!                                                     │
//!                     every `publish_every` updates   ├──► WeightsPublisher (version v+1)
//!                     every `checkpoint_every`        ├──► checkpoint::save (+ version, in `extra`)
//!                     every `metrics_every`           └──► TensorBoard scalars + a tracing event
//! ```
//!
//! The weights version counts publications, not updates: it starts at 1 and is stored in every
//! checkpoint, so a resumed learner continues the count and actors never see it go back.
//! The update counter (`learner_step` in the published metadata) is the agent's own.

use std::path::{Path, PathBuf};
use std::sync::atomic::{AtomicBool, Ordering};
use std::time::{Duration, Instant};

use mapless_proto::v1::WeightsSnapshot;

use crate::LearnerError;
use crate::algo::{Agent, UpdateStats};
use crate::batch::Minibatch;
use crate::checkpoint;
use crate::source::ReplaySource;
use crate::tensorboard::SummaryWriter;
use crate::weights::{WeightsPublisher, snapshot_from_tensors, unix_ms_now};

/// Key of the weights version in a checkpoint's `extra` JSON.
pub const EXTRA_WEIGHTS_VERSION: &str = "weights_version";

pub use mapless_learner_config::DriverConfig;

/// What [`Driver::run`] did.
#[derive(Debug, Clone, PartialEq)]
pub struct RunReport {
    /// Updates done in this call.
    pub updates: u64,
    /// The agent's update counter at the end.
    pub total_updates: u64,
    /// Newest published weights version.
    pub weights_version: u64,
    /// Updates per second over the call.
    pub updates_per_s: f64,
    /// The last checkpoint written, if any.
    pub checkpoint: Option<PathBuf>,
}

/// Ties an [`Agent`] to a replay source, a weights publisher, checkpoints and metrics.
pub struct Driver {
    agent: Agent,
    source: Box<dyn ReplaySource>,
    publisher: WeightsPublisher,
    cfg: DriverConfig,
    checkpoint_root: Option<PathBuf>,
    metrics: Option<SummaryWriter>,
    version: u64,
    last_stats: UpdateStats,
    window: (Instant, u64),
    checkpoint_failures: u64,
}

impl Driver {
    /// A driver around `agent`. `weights_version` is the last version published before (0 for a
    /// fresh run; [`Driver::resume`] reads it from the checkpoint).
    pub fn new(agent: Agent, source: Box<dyn ReplaySource>, publisher: WeightsPublisher, cfg: DriverConfig, weights_version: u64) -> Result<Self, LearnerError> {
        if cfg.publish_every == 0 || cfg.metrics_every == 0 || cfg.checkpoint_keep == 0 {
            return Err(LearnerError::InvalidConfig { field: "driver", reason: "publish_every, metrics_every and checkpoint_keep must be ≥ 1".into() });
        }
        let start = agent.updates();
        Ok(Driver {
            agent,
            source,
            publisher,
            cfg,
            checkpoint_root: None,
            metrics: None,
            version: weights_version,
            last_stats: UpdateStats::default(),
            window: (Instant::now(), start),
            checkpoint_failures: 0,
        })
    }

    /// Loads the newest checkpoint under (or at) `path`, with its weights version; `device`
    /// overrides the stored one.
    pub fn resume(path: &Path, device: Option<&str>, source: Box<dyn ReplaySource>, publisher: WeightsPublisher, cfg: DriverConfig) -> Result<Self, LearnerError> {
        let (agent, extra) = checkpoint::load(path, device)?;
        let version = extra.get(EXTRA_WEIGHTS_VERSION).and_then(serde_json::Value::as_u64).unwrap_or(0);
        Driver::new(agent, source, publisher, cfg, version)
    }

    /// Writes checkpoints under `root` (periodically and at the end of [`Driver::run`]).
    pub fn with_checkpoints(mut self, root: impl Into<PathBuf>) -> Self {
        self.checkpoint_root = Some(root.into());
        self
    }

    /// Writes TensorBoard event files into `dir`.
    pub fn with_tensorboard(mut self, dir: &Path) -> Result<Self, LearnerError> {
        self.metrics = Some(SummaryWriter::create(dir)?);
        Ok(self)
    }

    /// The agent.
    pub fn agent(&self) -> &Agent {
        &self.agent
    }

    /// The agent, mutably (acting in-process, tests).
    pub fn agent_mut(&mut self) -> &mut Agent {
        &mut self.agent
    }

    /// Newest published weights version (0 before the first).
    pub fn weights_version(&self) -> u64 {
        self.version
    }

    /// Continues the version count from at least `version`: a learner restarted after a crash
    /// may have published more versions than its newest checkpoint records, and subscribers
    /// wait for a version above the last they saw (they must never see a number reused).
    pub fn continue_versions_from(&mut self, version: u64) {
        self.version = self.version.max(version);
    }

    /// The replay source (for its counters).
    pub fn source(&self) -> &dyn ReplaySource {
        self.source.as_ref()
    }

    /// Periodic checkpoints that could not be written (each one logged as a warning).
    pub fn checkpoint_failures(&self) -> u64 {
        self.checkpoint_failures
    }

    /// Scalars of the most recent update.
    pub fn last_stats(&self) -> &UpdateStats {
        &self.last_stats
    }

    /// The current policy as the next weights version (not yet published).
    pub fn snapshot(&self) -> Result<WeightsSnapshot, LearnerError> {
        let mut metadata: std::collections::HashMap<String, String> = self.agent.policy_metadata().into_iter().collect();
        // The agent's `version` key is its update counter; on the wire that is `learner_step`.
        if let Some(step) = metadata.remove("version") {
            metadata.insert("learner_step".into(), step);
        }
        let mut s = snapshot_from_tensors(self.version + 1, self.agent.algorithm(), self.agent.obs_dim(), self.agent.act_dim(), &self.agent.policy_tensors(), metadata)?;
        s.created_unix_ms = unix_ms_now();
        Ok(s)
    }

    /// Publishes the current policy as the next version; returns it.
    pub fn publish(&mut self) -> Result<u64, LearnerError> {
        let snapshot = self.snapshot()?;
        self.version = self.publisher.publish(snapshot)?;
        Ok(self.version)
    }

    /// Writes a checkpoint now (needs [`Driver::with_checkpoints`]).
    pub fn checkpoint(&mut self) -> Result<PathBuf, LearnerError> {
        let root = self.checkpoint_root.clone().ok_or_else(|| LearnerError::InvalidConfig { field: "driver", reason: "no checkpoint directory configured".into() })?;
        let extra = serde_json::json!({ EXTRA_WEIGHTS_VERSION: self.version });
        checkpoint::save(&root, &self.agent, &extra, self.cfg.checkpoint_keep)
    }

    /// One update on the next minibatch, with everything that is due after it.
    pub fn step(&mut self) -> Result<(), LearnerError> {
        self.step_within(None).map(|_| ())
    }

    /// Like [`Driver::step`], but waits at most about `wait` for the minibatch (the replay's
    /// rate limiter may hold it back); `Ok(false)` when none came and nothing was done.
    pub fn try_step(&mut self, wait: Duration) -> Result<bool, LearnerError> {
        self.step_within(Some(wait))
    }

    fn step_within(&mut self, wait: Option<Duration>) -> Result<bool, LearnerError> {
        if self.version == 0 {
            // Actors wait for weights: give them the initial policy before the first update.
            self.publish()?;
        }
        let sampled = match wait {
            None => self.source.next_batch()?,
            Some(w) => match self.source.next_batch_timeout(w)? {
                Some(b) => b,
                None => return Ok(false),
            },
        };
        let batch = Minibatch::from_sampled(&sampled, self.agent.device())?;
        let stats = self.agent.update(&batch)?;
        if self.cfg.send_priorities && !stats.td_errors.is_empty() {
            // A lost priority update only delays re-weighting; the source counts it.
            if let Err(e) = self.source.update_priorities(&sampled.keys, &stats.td_errors) {
                tracing::warn!(error = %e, "priority update failed");
            }
        }
        self.last_stats = stats;
        let n = self.agent.updates();
        if n.is_multiple_of(self.cfg.publish_every) {
            self.publish()?;
        }
        if self.cfg.checkpoint_every > 0 && n.is_multiple_of(self.cfg.checkpoint_every) && self.checkpoint_root.is_some() {
            // A periodic checkpoint that cannot be written (a full disk, an I/O error) costs
            // only its own save: the previous one stays whole and named, training goes on, and
            // the next period tries again. The final one, in `run`, is an error.
            if let Err(e) = self.checkpoint() {
                self.checkpoint_failures += 1;
                tracing::warn!(error = %e, updates = n, failures = self.checkpoint_failures, "checkpoint not written; the previous one stays the newest and training goes on");
            }
        }
        if n.is_multiple_of(self.cfg.metrics_every) {
            self.report_metrics(n);
        }
        Ok(true)
    }

    fn report_metrics(&mut self, n: u64) {
        let (since, at) = self.window;
        let rate = (n - at) as f64 / since.elapsed().as_secs_f64().max(1e-9);
        self.window = (Instant::now(), n);
        let s = &self.last_stats;
        tracing::info!(
            updates = n,
            weights_version = self.version,
            updates_per_s = rate.round(),
            critic_loss = s.get(crate::algo::metric::CRITIC_LOSS),
            q_mean = s.get(crate::algo::metric::Q_MEAN),
            alpha = s.get(crate::algo::metric::ALPHA),
            "learner progress"
        );
        if let Some(w) = self.metrics.as_mut() {
            let step = n as i64;
            let mut write = |tag: &str, v: f64| {
                if let Err(e) = w.add_scalar(tag, step, v as f32) {
                    tracing::warn!(error = %e, tag, "tensorboard write failed");
                }
            };
            for (name, v) in &s.scalars {
                write(name, *v);
            }
            write("charts/updates_per_s", rate);
            write("charts/weights_version", self.version as f64);
        }
    }

    /// Updates until `stop` is set or `max_updates` more are done, then checkpoints (when a
    /// checkpoint directory is set) and publishes the final policy.
    pub fn run(&mut self, stop: &AtomicBool, max_updates: Option<u64>) -> Result<RunReport, LearnerError> {
        let start = Instant::now();
        let first = self.agent.updates();
        while !stop.load(Ordering::Relaxed) && max_updates.is_none_or(|m| self.agent.updates() - first < m) {
            // Short waits, so a stop request is seen while the replay holds sampling back.
            self.try_step(Duration::from_millis(200))?;
        }
        let updates = self.agent.updates() - first;
        if updates > 0 && !self.agent.updates().is_multiple_of(self.cfg.publish_every) {
            self.publish()?;
        }
        let checkpoint = if self.checkpoint_root.is_some() { Some(self.checkpoint()?) } else { None };
        if let Some(w) = self.metrics.as_mut() {
            w.flush()?;
        }
        Ok(RunReport { updates, total_updates: self.agent.updates(), weights_version: self.version, updates_per_s: updates as f64 / start.elapsed().as_secs_f64().max(1e-9), checkpoint })
    }
}
