//! The learner process's settings: its cadence ([`DriverConfig`]) and everything the
//! `mapless-learner` binary reads from its `learner.yaml` ([`LearnerServiceConfig`]).

use std::net::SocketAddr;
use std::path::PathBuf;

use serde::{Deserialize, Serialize};

use crate::LearnerConfig;

/// How often the loop publishes, checkpoints and reports. The defaults are what `mapless train`
/// runs with; none is the paper's (its MATLAB agent acts, learns and keeps its state in one
/// process), each says why.
#[derive(Debug, Clone, Serialize, Deserialize, PartialEq)]
#[serde(default, deny_unknown_fields)]
pub struct DriverConfig {
    /// Publish the policy every K updates (K ≥ 1). Actors act with weights at most K updates old
    /// [ours: 50; the paper acts with the newest weights; at the ~400 updates/s of a 2-core
    /// machine a published policy is about 0.1 s old].
    pub publish_every: u64,
    /// Write a checkpoint every N updates; 0 = only when asked (and at the end of `run`)
    /// [ours: 20,000, under a minute of learning at ~400 updates/s is what a crash can lose].
    pub checkpoint_every: u64,
    /// Checkpoints kept on disk [`crate::DEFAULT_CHECKPOINT_KEEP`].
    pub checkpoint_keep: usize,
    /// Write TensorBoard scalars and a progress event every M updates (M ≥ 1) [ours: 200].
    pub metrics_every: u64,
    /// Send |TD error| back as new priorities (prioritised replay tables only) [paper: uniform
    /// replay, so off]. `mapless train` sets it from `replay.sampler.kind`: on for a
    /// prioritised table, which without it samples as a uniform one.
    pub send_priorities: bool,
}

impl Default for DriverConfig {
    fn default() -> Self {
        DriverConfig { publish_every: 50, checkpoint_every: 20_000, checkpoint_keep: crate::DEFAULT_CHECKPOINT_KEEP, metrics_every: 200, send_priorities: false }
    }
}

/// Everything the learner process needs (`mapless train` writes it as `learner.yaml`; the `mapless-learner` binary reads it).
#[derive(Clone, Debug, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct LearnerServiceConfig {
    /// Algorithm and hyperparameters.
    pub learner: LearnerConfig,
    /// Publishing, checkpoint and metrics cadence.
    #[serde(default)]
    pub driver: DriverConfig,
    /// Observation and action lengths (the replay table's).
    pub obs_dim: usize,
    pub act_dim: usize,
    /// The replay service, e.g. `http://127.0.0.1:50051`.
    pub replay: String,
    /// Where the weights service listens (`127.0.0.1:0`: any free port, printed on stdout).
    pub weights_listen: SocketAddr,
    /// Checkpoints go here; with `resume`, the newest one is loaded at start.
    pub checkpoint_dir: PathBuf,
    /// TensorBoard event files.
    pub tensorboard_dir: Option<PathBuf>,
    /// Newest published policy, for evaluation and deployment (`.safetensors`, written at
    /// start, every few seconds while the weights version advances, and at exit).
    pub policy_file: Option<PathBuf>,
    /// Continue from the newest checkpoint in `checkpoint_dir` when there is one.
    #[serde(default)]
    pub resume: bool,
    /// libtorch threads (intra-op); inter-op is 1.
    #[serde(default = "one")]
    pub threads: usize,
    /// The weights service's TLS certificate and key (required, with a token, on a
    /// non-loopback `weights_listen`).
    #[serde(default)]
    pub tls: Option<mapless_net::TlsFiles>,
    /// File holding a full-rights bearer token for the weights service (the one token of
    /// configs written before `auth_token_files`; prefer those).
    #[serde(default)]
    pub auth_token_file: Option<PathBuf>,
    /// Files holding one role's token each (`{actor: FILE, learner: FILE}`, distinct): the
    /// actor's may `Subscribe`; the learner's only ask the health service (useful for a health
    /// probe that holds the learner's token). Accepted beside `auth_token_file`.
    #[serde(default, skip_serializing_if = "mapless_net::RoleTokenFiles::is_empty")]
    pub auth_token_files: mapless_net::RoleTokenFiles,
    /// CA and token for reaching a replay service on another host.
    #[serde(default)]
    pub replay_security: mapless_net::ClientSecurity,
    /// Prometheus `/metrics` address (loopback, or any address with `metrics_token_file`);
    /// none: off.
    #[serde(default)]
    pub metrics_listen: Option<SocketAddr>,
    /// File holding the bearer token a scraper of `/metrics` must send; needed beyond loopback
    /// (plain HTTP: a private network, as compose's) [default: none, loopback only].
    #[serde(default)]
    pub metrics_token_file: Option<PathBuf>,
}

fn one() -> usize {
    1
}

impl LearnerServiceConfig {
    /// A learner on this host only, as `mapless train` and `mapless bench soak` start one:
    /// weights service and `/metrics` on loopback at any free port (each printed on stdout),
    /// no TLS, no tokens, one thread, no resume, no TensorBoard or policy file. Callers set
    /// what differs with struct update syntax.
    pub fn loopback(learner: LearnerConfig, driver: DriverConfig, obs_dim: usize, act_dim: usize, replay: String, checkpoint_dir: PathBuf) -> LearnerServiceConfig {
        let any_port = SocketAddr::from(([127, 0, 0, 1], 0));
        LearnerServiceConfig {
            learner,
            driver,
            obs_dim,
            act_dim,
            replay,
            weights_listen: any_port,
            checkpoint_dir,
            tensorboard_dir: None,
            policy_file: None,
            resume: false,
            threads: 1,
            tls: None,
            auth_token_file: None,
            auth_token_files: Default::default(),
            replay_security: Default::default(),
            metrics_listen: Some(any_port),
            metrics_token_file: None,
        }
    }
}

/// One line of the learner process's stdout, a JSON object tagged by `event` (what the
/// supervisor of `mapless train` reads). Other lines (`weights on ADDR`, `metrics on URL`) are
/// plain text.
#[derive(Clone, Debug, Serialize, Deserialize, PartialEq)]
#[serde(tag = "event", rename_all = "snake_case", deny_unknown_fields)]
pub enum LearnerEvent {
    /// Every second while learning.
    Status {
        /// Gradient updates done (the agent's counter; continues across resumes).
        updates: u64,
        /// Updates per second over the last second.
        updates_per_s: f64,
        /// Newest published weights version.
        weights_version: u64,
        /// Minibatches received from the replay.
        batches: u64,
        /// Replay sample streams reopened.
        reconnects: u64,
    },
    /// Once, after the final publication and checkpoint.
    Stopped {
        updates: u64,
        weights_version: u64,
        /// The final checkpoint's folder.
        checkpoint: PathBuf,
    },
}

impl LearnerEvent {
    /// Gradient updates done, whichever the event.
    pub fn updates(&self) -> u64 {
        match self {
            LearnerEvent::Status { updates, .. } | LearnerEvent::Stopped { updates, .. } => *updates,
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn learner_events_are_one_json_object_tagged_by_event() {
        let status = LearnerEvent::Status { updates: 7, updates_per_s: 2.5, weights_version: 3, batches: 9, reconnects: 0 };
        let line = serde_json::to_string(&status).unwrap();
        assert!(line.starts_with(r#"{"event":"status","updates":7,"#), "{line}");
        assert_eq!(serde_json::from_str::<LearnerEvent>(&line).unwrap(), status);
        let stopped: LearnerEvent = serde_json::from_str(r#"{"event":"stopped","updates":12,"weights_version":4,"checkpoint":"/r/checkpoints/ckpt-12"}"#).unwrap();
        assert_eq!(stopped.updates(), 12);
        // Not an event: a plain line, an unknown event, a missing field.
        for bad in ["weights on 127.0.0.1:5", r#"{"event":"paused"}"#, r#"{"event":"status","updates":1}"#] {
            assert!(serde_json::from_str::<LearnerEvent>(bad).is_err(), "{bad}");
        }
    }
}
