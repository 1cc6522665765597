//! The run's summary: what `summary.json` holds at the end of a session (`mapless reproduce`
//! reads it back), made from the run's status, its episodes and why it stopped.

use std::path::Path;

use anyhow::Result;
use serde::{Deserialize, Serialize};

use super::config::TrainConfig;
use super::episodes::Episodes;
use super::folder::write_atomic;
use super::status::{LearnerEnd, Milestone, Rates};
use super::stop::Outcome;
use crate::eval::EvalSummary;
use crate::protocol;

/// What `summary.json` holds (`mapless reproduce` reads it back).
#[derive(Serialize, Deserialize, Debug)]
pub struct Summary {
    pub run: String,
    pub preset: String,
    /// Starts with [`INTERRUPTED`](super::stop::INTERRUPTED) when Ctrl-C or SIGTERM stopped the run.
    pub stopped_because: String,
    pub wall_s: f64,
    pub episodes: u64,
    pub env_steps: u64,
    pub updates: u64,
    /// The learner's last published weights version: that of its `stopped` event (after the
    /// final publication), else of its newest status line.
    pub weights_version: u64,
    /// NaN (written as null) before the first episode.
    #[serde(deserialize_with = "nan_if_null")]
    pub average_return: f64,
    #[serde(deserialize_with = "nan_if_null")]
    pub average_steps: f64,
    pub window: usize,
    pub criteria_met_at: Option<Milestone>,
    /// The evaluation that met `stop.eval_*` (its policy is the run's `policy.safetensors`).
    pub criteria_evaluation: Option<EvalSummary>,
    /// First episode from which the moving averages stayed within `stop.convergence_tolerance`
    /// of their final values (`protocol::convergence_episode`).
    pub convergence_episode: Option<u64>,
    pub actor_restarts: u32,
    /// Throughput after start-up (from 20 s, or a third of a time-limited run, to the stop).
    pub steady: Option<Rates>,
    /// Which policy is the run's `policy.safetensors`, and why (`stop.keep_best`); none from
    /// `mapless monitor` (the cluster's policy is not its to choose) and in older summaries.
    #[serde(default)]
    pub kept_policy: Option<String>,
    pub evaluation: Option<EvalSummary>,
}

/// serde_json writes a non-finite f64 as null; read it back as NaN.
fn nan_if_null<'de, D: serde::Deserializer<'de>>(d: D) -> std::result::Result<f64, D::Error> {
    Ok(Option::<f64>::deserialize(d)?.unwrap_or(f64::NAN))
}

/// What a session ended with, besides the episodes.
pub(crate) struct End {
    /// Seconds of the whole run.
    pub(crate) wall_s: f64,
    pub(crate) env_steps: u64,
    pub(crate) learner: LearnerEnd,
    pub(crate) actor_restarts: u32,
    pub(crate) steady: Option<Rates>,
    pub(crate) evaluation: Option<EvalSummary>,
    pub(crate) kept_policy: Option<String>,
}

impl Summary {
    pub(crate) fn new(run: &Path, cfg: &TrainConfig, episodes: &Episodes, outcome: Outcome, end: End) -> Summary {
        let w = cfg.stop.window;
        let (average_return, average_steps) = episodes.averages(w);
        Summary {
            run: run.display().to_string(),
            preset: cfg.name.clone(),
            stopped_because: outcome.stopped_because,
            wall_s: end.wall_s,
            episodes: episodes.count(),
            env_steps: end.env_steps,
            updates: end.learner.updates,
            weights_version: end.learner.weights_version,
            average_return,
            average_steps,
            window: w,
            criteria_met_at: outcome.criteria_met_at,
            criteria_evaluation: outcome.criteria_evaluation,
            convergence_episode: protocol::convergence_episode(&episodes.rows, w, cfg.stop.convergence_tolerance),
            actor_restarts: end.actor_restarts,
            steady: end.steady,
            kept_policy: end.kept_policy,
            evaluation: end.evaluation,
        }
    }

    /// Writes `run/summary.json` (whole or not at all).
    pub(crate) fn write(&self, run: &Path) -> Result<()> {
        write_atomic(&run.join("summary.json"), &serde_json::to_string_pretty(self)?)
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn a_summary_before_the_first_episode_reads_back_with_nan_averages() {
        let dir = tempfile::tempdir().unwrap();
        let cfg = super::super::config::preset_config("env1-sac").unwrap();
        let episodes = Episodes::open(dir.path()).unwrap();
        let outcome = Outcome { stopped_because: "0.1 minutes".into(), criteria_met_at: None, criteria_evaluation: None };
        let end = End { wall_s: 6.5, env_steps: 10, learner: LearnerEnd { updates: 3, weights_version: 2 }, actor_restarts: 1, steady: None, evaluation: None, kept_policy: None };
        let s = Summary::new(dir.path(), &cfg, &episodes, outcome, end);
        s.write(dir.path()).unwrap();
        let text = std::fs::read_to_string(dir.path().join("summary.json")).unwrap();
        assert!(text.contains("\"average_return\": null") && text.contains("\"window\": 50"), "{text}");
        let back: Summary = serde_json::from_str(&text).unwrap();
        assert!(back.average_return.is_nan() && back.average_steps.is_nan());
        assert_eq!((back.episodes, back.updates, back.weights_version, back.actor_restarts, back.stopped_because.as_str()), (0, 3, 2, 1, "0.1 minutes"));
        assert_eq!(back.convergence_episode, None);
    }
}
