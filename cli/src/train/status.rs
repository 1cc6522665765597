//! The run's status: what the supervisor knows of the run now (the run's clock, the learner's
//! newest status line, the replay's size and inserts, the environment rate), and the points of
//! it that `summary.json` keeps ([`Milestone`], [`Rates`]). The progress line, the stop rules
//! and the summary all read it.

use std::time::{Duration, Instant};

use mapless_learner_config::LearnerEvent;
use mapless_proto::v1::ServerInfoResponse;
use serde::{Deserialize, Serialize};

/// The learner's figures at the end of a session ([`Status::learner_end`]): from its
/// `stopped` event when it printed one, else from its newest status line.
#[derive(Debug, PartialEq)]
pub(crate) struct LearnerEnd {
    pub(crate) updates: u64,
    pub(crate) weights_version: u64,
}

/// The newest `LearnerEvent::Status` the learner printed.
#[derive(Default, Clone, Debug, PartialEq)]
pub(crate) struct LearnerStatus {
    pub(crate) updates: u64,
    pub(crate) updates_per_s: f64,
    pub(crate) weights_version: u64,
}

/// A point of the run: where the stop criteria were met.
#[derive(Serialize, Deserialize, Clone, Debug, PartialEq)]
pub struct Milestone {
    pub wall_s: f64,
    pub episode: u64,
    pub env_steps: u64,
    pub updates: u64,
}

/// Throughput between two moments of the run.
#[derive(Serialize, Deserialize, Debug, PartialEq)]
pub struct Rates {
    pub from_s: f64,
    pub seconds: f64,
    pub env_steps_per_s: f64,
    pub updates_per_s: f64,
}

/// The counters at one moment (for [`Rates`]).
#[derive(Clone, Copy, Debug, PartialEq)]
pub(crate) struct Counters {
    pub(crate) at: Instant,
    pub(crate) env_steps: u64,
    pub(crate) updates: u64,
}

/// Environment steps per second, measured over spans of at least 5 s.
#[derive(Clone, Copy, Debug)]
pub(crate) struct EnvRate {
    since: Instant,
    at: u64,
    pub(crate) per_s: f64,
}

impl EnvRate {
    fn new(now: Instant) -> EnvRate {
        EnvRate { since: now, at: 0, per_s: 0.0 }
    }

    /// Takes the replay's insert count at `now`: the rate moves once 5 s have passed since the
    /// last move (the first count seen starts the first span).
    fn update(&mut self, inserts: u64, now: Instant) {
        let dt = now.saturating_duration_since(self.since).as_secs_f64();
        if dt >= 5.0 {
            *self = EnvRate { since: now, at: inserts, per_s: inserts.saturating_sub(self.at) as f64 / dt };
        } else if self.at == 0 {
            self.at = inserts;
        }
    }
}

/// What the supervisor knows of the run now.
pub(crate) struct Status {
    /// When this session's supervision began.
    pub(crate) started: Instant,
    /// Wall seconds of the run's earlier sessions (a resumed run continues its clock).
    pub(crate) offset_s: f64,
    pub(crate) learner: LearnerStatus,
    /// Rows in the replay now.
    pub(crate) replay_size: u64,
    /// Rows inserted into the replay: the run's environment steps.
    pub(crate) env_steps: u64,
    pub(crate) env_rate: EnvRate,
    /// The steady rates are measured from this many seconds of the session on.
    steady_from_s: f64,
    /// The counters when that time was reached.
    pub(crate) steady_start: Option<Counters>,
}

impl Status {
    /// A session that starts now; steady throughput is measured from 20 s on, or from a third
    /// of a run limited to `minutes` when that is shorter.
    pub(crate) fn new(offset_s: f64, minutes: Option<f64>) -> Status {
        let now = Instant::now();
        Status {
            started: now,
            offset_s,
            learner: LearnerStatus::default(),
            replay_size: 0,
            env_steps: 0,
            env_rate: EnvRate::new(now),
            steady_from_s: minutes.map_or(20.0, |m| (m * 20.0).min(20.0)),
            steady_start: None,
        }
    }

    /// Seconds of the whole run (earlier sessions included).
    pub(crate) fn wall_s(&self) -> f64 {
        self.offset_s + self.started.elapsed().as_secs_f64()
    }

    /// Time since this session began.
    pub(crate) fn elapsed(&self) -> Duration {
        self.started.elapsed()
    }

    /// Takes a line the learner printed (its `status` events; other lines change nothing).
    pub(crate) fn learner_said(&mut self, event: &LearnerEvent) {
        if let LearnerEvent::Status { updates, updates_per_s, weights_version, .. } = *event {
            self.learner = LearnerStatus { updates, updates_per_s, weights_version };
        }
    }

    /// Takes what the replay said of itself (`None`: it did not answer), then moves the
    /// environment rate.
    pub(crate) fn replay_said(&mut self, info: Option<&ServerInfoResponse>) {
        let now = Instant::now();
        if let Some(i) = info {
            self.replay_size = i.size;
            self.env_steps = i.inserts_total;
            if self.steady_start.is_none() && now.duration_since(self.started).as_secs_f64() >= self.steady_from_s {
                self.steady_start = Some(Counters { at: now, env_steps: i.inserts_total, updates: self.learner.updates });
            }
        }
        self.env_rate.update(self.env_steps, now);
    }

    /// The counters now.
    pub(crate) fn counters(&self) -> Counters {
        Counters { at: Instant::now(), env_steps: self.env_steps, updates: self.learner.updates }
    }

    /// This point of the run, `episodes` in.
    pub(crate) fn milestone(&self, episodes: u64) -> Milestone {
        Milestone { wall_s: self.wall_s(), episode: episodes, env_steps: self.env_steps, updates: self.learner.updates }
    }

    /// Throughput after start-up: from the steady start to `end` (the stop).
    pub(crate) fn steady_rates(&self, end: Counters) -> Option<Rates> {
        self.steady_start.map(|s| {
            let secs = end.at.saturating_duration_since(s.at).as_secs_f64().max(1e-9);
            Rates {
                from_s: s.at.saturating_duration_since(self.started).as_secs_f64(),
                seconds: secs,
                env_steps_per_s: end.env_steps.saturating_sub(s.env_steps) as f64 / secs,
                updates_per_s: end.updates.saturating_sub(s.updates) as f64 / secs,
            }
        })
    }

    /// The learner's figures at the end, `late` being what it printed while it stopped: those
    /// of its `stopped` event (printed after the final publication and checkpoint), else those
    /// of its newest status line.
    pub(crate) fn learner_end(&self, late: &[LearnerEvent]) -> LearnerEnd {
        let mut end = LearnerEnd { updates: self.learner.updates, weights_version: self.learner.weights_version };
        for e in late {
            match *e {
                LearnerEvent::Status { updates, weights_version, .. } => end = LearnerEnd { updates, weights_version },
                LearnerEvent::Stopped { updates, weights_version, .. } => return LearnerEnd { updates, weights_version },
            }
        }
        end
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn the_env_rate_moves_over_spans_of_five_seconds() {
        let t0 = Instant::now();
        let mut r = EnvRate::new(t0);
        r.update(100, t0 + Duration::from_secs(1));
        assert_eq!((r.at, r.per_s), (100, 0.0), "the first count starts the span");
        r.update(300, t0 + Duration::from_secs(4));
        assert_eq!((r.at, r.per_s), (100, 0.0), "under 5 s: no move");
        r.update(1100, t0 + Duration::from_secs(5));
        assert_eq!((r.at, r.per_s), (1100, 200.0), "1000 steps over 5 s");
        r.update(1600, t0 + Duration::from_secs(15));
        assert_eq!(r.per_s, 50.0);
    }

    #[test]
    fn learner_status_lines_and_late_events() {
        let mut s = Status::new(30.0, None);
        s.learner_said(&LearnerEvent::Status { updates: 7, updates_per_s: 2.5, weights_version: 3, batches: 9, reconnects: 0 });
        assert_eq!(s.learner, LearnerStatus { updates: 7, updates_per_s: 2.5, weights_version: 3 });
        let stopped = LearnerEvent::Stopped { updates: 9, weights_version: 4, checkpoint: "c".into() };
        s.learner_said(&stopped);
        assert_eq!(s.learner.updates, 7, "only status lines move the status");
        let late_status = LearnerEvent::Status { updates: 8, updates_per_s: 1.0, weights_version: 3, batches: 10, reconnects: 0 };
        let end = |updates, weights_version| LearnerEnd { updates, weights_version };
        assert_eq!(s.learner_end(&[]), end(7, 3), "nothing printed late: the last status line");
        assert_eq!(s.learner_end(std::slice::from_ref(&late_status)), end(8, 3), "a status line printed late");
        assert_eq!(s.learner_end(&[late_status, stopped.clone()]), end(9, 4), "the stopped event: the version of the final publication");
        assert_eq!(s.learner_end(&[stopped]), end(9, 4));
        assert!(s.wall_s() >= 30.0, "the clock continues the earlier sessions'");
        let m = s.milestone(12);
        assert_eq!((m.episode, m.updates, m.env_steps), (12, 7, 0));
    }

    #[test]
    fn steady_rates_start_when_the_session_is_old_enough() {
        // A 0.0-minute limit: steady from 0 s, so the first answer of the replay starts it.
        let mut s = Status::new(0.0, Some(0.0));
        assert_eq!(s.steady_rates(s.counters()), None);
        s.replay_said(Some(&ServerInfoResponse { size: 5, inserts_total: 100, ..Default::default() }));
        let start = s.steady_start.expect("started");
        assert_eq!((s.replay_size, s.env_steps, start.env_steps), (5, 100, 100));
        s.replay_said(None);
        assert_eq!(s.env_steps, 100, "no answer keeps the last counts");
        let end = Counters { at: start.at + Duration::from_secs(2), env_steps: 300, updates: 50 };
        let r = s.steady_rates(end).unwrap();
        assert_eq!((r.seconds, r.env_steps_per_s, r.updates_per_s), (2.0, 100.0, 25.0));
        // 20 s by default: not yet.
        let mut s = Status::new(0.0, None);
        s.replay_said(Some(&ServerInfoResponse { inserts_total: 100, ..Default::default() }));
        assert!(s.steady_start.is_none());
    }
}
