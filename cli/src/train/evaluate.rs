//! Evaluations of the run's policy: of the newest one every `eval.every_minutes` while training,
//! of a copy of it whenever the moving averages hold and the stop criterion asks for an
//! evaluation, and every `stop.choose_every_minutes` to choose from (the best of those copies
//! kept as `policy-best.safetensors`), of the final one at the end; each recorded as a line of
//! `evals.csv`.
//! Those made while training run on threads of their own: they must not hold up the
//! supervision.

use std::fs;
use std::path::{Path, PathBuf};
use std::thread::JoinHandle;
use std::time::{Duration, Instant};

use anyhow::{Context, Result};
use indicatif::ProgressBar;
use mapless_sim::EnvConfig;
use mapless_sim::worlds::Split;
use serde::{Deserialize, Serialize};

use super::config::{EvalSettings, KeepBestWhen, TrainConfig};
use super::episodes::truncate_torn_line;
use super::folder::write_atomic;
use super::status::{Milestone, Status};
use super::stop::Averages;
use crate::eval::{self, EvalSummary};

/// Shortest time between two evaluations of the stop criterion (they run while training goes
/// on; 10 episodes of 1000 steps take about a second).
pub(crate) const GATE_EVAL_COOLDOWN: Duration = Duration::from_secs(20);

/// An evaluation of the newest policy while training, on its own thread.
struct ProgressEval {
    wall_s: f64,
    handle: JoinHandle<Result<EvalSummary>>,
}

impl ProgressEval {
    /// Waits for it and records it in `evals.csv`; a failed or panicked evaluation is logged.
    fn finish(self, run: &Path) -> Result<()> {
        match self.handle.join() {
            Ok(Ok(s)) => {
                tracing::info!(policy_version = s.policy_version, "evaluation while training: {}", s.one_line());
                append_eval(run, self.wall_s, "progress", &s)?;
            }
            Ok(Err(e)) => tracing::warn!(error = %format!("{e:#}"), "evaluation while training failed"),
            Err(_) => tracing::warn!("evaluation while training panicked"),
        }
        Ok(())
    }
}

/// An evaluation of the stop criterion, on a copy of the policy it judges; `at` is the point of
/// training it judges (taken when the policy was copied). One made only to choose from
/// (`stop.choose_every_minutes`) is scored for the best policy as well, but judges nothing.
struct GateEval {
    at: Milestone,
    kind: GateKind,
    handle: JoinHandle<Result<EvalSummary>>,
}

/// Why a copy of the policy is evaluated on the criterion's starts.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
enum GateKind {
    /// The moving averages hold: the evaluation may stop the run (`criteria` in evals.csv).
    Criterion,
    /// `stop.choose_every_minutes` has passed: only scored for `policy-best` (`candidate`).
    Candidate,
}

impl GateKind {
    fn csv(self) -> &'static str {
        match self {
            GateKind::Criterion => "criteria",
            GateKind::Candidate => "candidate",
        }
    }
}

/// How an evaluation of the criterion scored a policy: what choosing the best one compares
/// (`policy-best.json` keeps that of `policy-best.safetensors`, so a resumed run goes on
/// comparing with it).
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
pub(crate) struct Score {
    pub(crate) policy_version: u64,
    /// When the evaluation ended (seconds of the whole run).
    pub(crate) wall_s: f64,
    pub(crate) episodes: usize,
    pub(crate) collisions: u32,
    pub(crate) mean_eqs: f64,
}

impl Score {
    fn of(s: &EvalSummary, wall_s: f64) -> Score {
        Score { policy_version: s.policy_version, wall_s, episodes: s.episodes.len(), collisions: s.collisions, mean_eqs: s.mean_eqs }
    }

    /// A lower share of episodes that collided, then (the same share) a higher mean EQS.
    fn beats(&self, other: &Score) -> bool {
        // Shares compared exactly: c₁/n₁ < c₂/n₂ ⇔ c₁·n₂ < c₂·n₁.
        let (mine, theirs) = (u64::from(self.collisions) * other.episodes as u64, u64::from(other.collisions) * self.episodes as u64);
        mine < theirs || (mine == theirs && self.mean_eqs > other.mean_eqs)
    }

    /// Whether its share of collisions is clearly below `other`'s: a one-sided Fisher exact test
    /// on the two counts rejects, at 5 %, that the two policies collide alike (of 20 episodes
    /// each: 0 against 5 or more, 1 against 6 or more; of 60: 0 against 5, 1 against 7). A
    /// collision or two is noise between two policies; 0 against 7 of 60 is not. [ours: the
    /// rule was once that the two 95 % Wilson intervals be apart, a test at about 0.5 %, which
    /// kept a last policy with 7 collisions of 60 over a best one with none, and the best one
    /// was the safer on 150 held-out worlds no evaluation had met, 142 against 114
    /// collision-free; docs/experiments.md, "A bonus on the EQS, and a stricter gate"]
    fn clearly_safer_than(&self, other: &Score) -> bool {
        fisher_one_sided(self.collisions, self.episodes, other.collisions, other.episodes) < 0.05
    }

    fn describe(&self) -> String {
        format!("v{}: {} of {} episodes collided, mean EQS {:.1}", self.policy_version, self.collisions, self.episodes, self.mean_eqs)
    }
}

/// The run's evaluations.
pub(crate) struct Evaluations {
    run: PathBuf,
    /// `eval.map`, or the training map.
    map: String,
    env: EnvConfig,
    /// `env` with the step limit of the evaluations that choose the run's policy
    /// (`stop.choose_max_steps`): those to choose from and `stop.keep_best`'s at the end.
    choose_env: EnvConfig,
    /// The seed of the evaluations while training and of the stop criterion (the run's,
    /// offset): they all meet the same starts, so their figures compare along the run.
    seed: u64,
    /// The final evaluation's seed: starts that no evaluation during training met. The stop
    /// criterion selects the first policy that passes on `seed`'s starts; judged again on those
    /// it would pass by construction, so the final figures come from fresh starts.
    final_seed: u64,
    /// The seed of the evaluations that choose the run's policy at the end (`stop.keep_best`):
    /// starts that neither the criterion's evaluations nor the final one meet.
    choice_seed: u64,
    settings: EvalSettings,
    /// Episodes of an evaluation of the stop criterion.
    gate_episodes: u32,
    /// Episodes each of the evaluations that choose between the best policy and the last at the
    /// end (`stop.choose_episodes`).
    choice_episodes: u32,
    /// The evaluation running now, if any, and when the last one ended.
    progress: Option<ProgressEval>,
    last_progress: Instant,
    gate: Option<GateEval>,
    last_gate: Option<Instant>,
    /// `stop.choose_every_minutes`, and when the last evaluation to choose from started.
    choose_every: Option<Duration>,
    last_candidate: Instant,
    /// The best score of an evaluation of the criterion so far (its policy in
    /// `policy-best.safetensors`).
    best: Option<Score>,
    /// `stop.average_last`: the run's policy at the end stands on the mean of this many of the
    /// newest snapshots instead of the learner's last.
    average_last: Option<usize>,
    /// `stop.keep_best_when`.
    keep_best_when: KeepBestWhen,
}

/// The mean of the newest snapshots (`stop.average_last`), written as
/// `policy-average.safetensors`: what the run keeps at the end unless the best is clearly safer
/// (with `stop.keep_best_when: safer`, safer).
struct Averaged {
    path: PathBuf,
    name: String,
}

impl Evaluations {
    pub(crate) fn new(cfg: &TrainConfig, run: &Path) -> Evaluations {
        let mut evals = Evaluations {
            run: run.to_owned(),
            map: cfg.eval.map.clone().unwrap_or_else(|| cfg.map.clone()),
            env: cfg.env.clone(),
            choose_env: {
                let mut env = cfg.env.clone();
                env.episode.max_steps = cfg.stop.choose_max_steps.unwrap_or(env.episode.max_steps);
                env
            },
            seed: cfg.seed.wrapping_add(1_000_003),
            final_seed: cfg.seed.wrapping_add(2_000_003),
            choice_seed: cfg.seed.wrapping_add(3_000_003),
            settings: cfg.eval.clone(),
            gate_episodes: cfg.stop.eval_episodes,
            choice_episodes: cfg.stop.choose_episodes.unwrap_or(cfg.stop.eval_episodes),
            progress: None,
            last_progress: Instant::now(),
            gate: None,
            last_gate: None,
            choose_every: cfg.stop.choose_every_minutes.map(|m| Duration::from_secs_f64(m * 60.0)),
            last_candidate: Instant::now(),
            best: None,
            average_last: cfg.stop.average_last.map(|k| k as usize),
            keep_best_when: cfg.stop.keep_best_when,
        };
        evals.best = evals.read_best();
        evals
    }

    /// The policy the learner publishes (and replaces as it goes).
    fn policy(&self) -> PathBuf {
        self.run.join("policy.safetensors")
    }

    /// The copy of the policy that an evaluation of the stop criterion judges.
    fn gate_policy(&self) -> PathBuf {
        self.run.join("policy-criteria.safetensors")
    }

    /// The best policy an evaluation of the criterion judged, and its score.
    fn best_policy(&self) -> PathBuf {
        self.run.join("policy-best.safetensors")
    }

    fn best_score(&self) -> PathBuf {
        self.run.join("policy-best.json")
    }

    /// The score of `policy-best.safetensors` from an earlier session of the run, if both files
    /// are there and the score reads.
    fn read_best(&self) -> Option<Score> {
        if !self.best_policy().exists() {
            return None;
        }
        let text = fs::read_to_string(self.best_score()).ok()?;
        match serde_json::from_str(&text) {
            Ok(s) => Some(s),
            Err(e) => {
                tracing::warn!(error = %e, "policy-best.json does not read: the best policy is chosen afresh");
                None
            }
        }
    }

    /// The evaluation of the newest policy as the run goes: records one that ended, starts the
    /// next when `eval.every_minutes` have passed since (its trajectories drawn into eval/).
    /// What it logs goes `above` the progress line.
    pub(crate) fn progress_tick(&mut self, status: &Status, above: &ProgressBar) -> Result<()> {
        if self.progress.as_ref().is_some_and(|p| p.handle.is_finished()) {
            let p = self.progress.take().expect("checked");
            above.suspend(|| p.finish(&self.run))?;
            self.last_progress = Instant::now();
        }
        if let Some(every) = self.settings.every_minutes
            && self.settings.progress_episodes > 0
            && self.progress.is_none()
            && self.last_progress.elapsed().as_secs_f64() >= every * 60.0
            && self.policy().exists()
        {
            let (policy, map, env, n, seed, out) = (self.policy(), self.map.clone(), self.env.clone(), self.settings.progress_episodes, self.seed, self.run.join("eval"));
            let handle = std::thread::Builder::new().name("eval".into()).spawn(move || eval::evaluate(&policy, &map, Split::Validation, &env, n, seed, Some(&out)))?;
            self.progress = Some(ProgressEval { wall_s: status.wall_s(), handle });
        }
        Ok(())
    }

    /// An evaluation of the newest policy still running at the end: it ends first (a few
    /// episodes; it writes into eval/ too).
    pub(crate) fn finish_progress(&mut self) -> Result<()> {
        match self.progress.take() {
            Some(p) => p.finish(&self.run),
            None => Ok(()),
        }
    }

    /// Whether an evaluation of the stop criterion may start now: none running, the last one
    /// ended at least [`GATE_EVAL_COOLDOWN`] ago, and the learner has published a policy.
    fn gate_may_start(&self) -> bool {
        self.gate.is_none() && self.last_gate.is_none_or(|t| t.elapsed() >= GATE_EVAL_COOLDOWN) && self.policy().exists()
    }

    /// Whether an evaluation to choose from is due (`stop.choose_every_minutes` since the last
    /// one, or since the start) and may start ([`Evaluations::gate_may_start`]).
    fn candidate_due(&self) -> bool {
        self.choose_every.is_some_and(|every| self.last_candidate.elapsed() >= every) && self.gate_may_start()
    }

    /// Starts the evaluation now due, if any: one of the criterion when the moving averages ask
    /// for it and one may start, else one to choose from when that is due; `at` gives this
    /// point of training (asked only when one starts).
    pub(crate) fn start_due(&mut self, averages: Averages, at: impl FnOnce() -> Milestone) -> Result<()> {
        if averages == Averages::Evaluate && self.gate_may_start() {
            self.start_gate(at(), GateKind::Criterion)
        } else if self.candidate_due() {
            self.start_gate(at(), GateKind::Candidate)
        } else {
            Ok(())
        }
    }

    /// Starts an evaluation of a copy of the newest policy on the criterion's starts (the
    /// learner keeps replacing policy.safetensors); `at` is this point of training.
    fn start_gate(&mut self, at: Milestone, kind: GateKind) -> Result<()> {
        if kind == GateKind::Candidate {
            self.last_candidate = Instant::now();
        }
        let gate_policy = self.gate_policy();
        fs::copy(self.policy(), &gate_policy).with_context(|| format!("copying the policy to {}", gate_policy.display()))?;
        let env = match kind {
            GateKind::Criterion => self.env.clone(),
            GateKind::Candidate => self.choose_env.clone(),
        };
        let (map, n, seed) = (self.map.clone(), self.gate_episodes, self.seed);
        let handle = std::thread::Builder::new().name("eval-criteria".into()).spawn(move || eval::evaluate(&gate_policy, &map, Split::Validation, &env, n, seed, None))?;
        self.gate = Some(GateEval { at, kind, handle });
        Ok(())
    }

    /// An evaluation of the stop criterion that has ended, recorded (a `criteria` line of
    /// `evals.csv`, `candidate` for one made only to choose from), with the point of training it
    /// judged; one that failed, or was made only to choose from, yields nothing to judge. What
    /// it logs goes `above` the progress line.
    pub(crate) fn gate_ended(&mut self, status: &Status, above: &ProgressBar) -> Result<Option<(Milestone, EvalSummary)>> {
        let Some(g) = self.gate.take_if(|g| g.handle.is_finished()) else { return Ok(None) };
        self.last_gate = Some(Instant::now());
        above.suspend(|| self.record_gate(g, status))
    }

    /// An evaluation of the stop criterion still running when the run stopped: it ends first.
    pub(crate) fn gate_after_stop(&mut self, status: &Status) -> Result<Option<(Milestone, EvalSummary)>> {
        match self.gate.take() {
            Some(g) => self.record_gate(g, status),
            None => Ok(None),
        }
    }

    fn record_gate(&mut self, g: GateEval, status: &Status) -> Result<Option<(Milestone, EvalSummary)>> {
        match g.handle.join() {
            Ok(Ok(s)) => {
                append_eval(&self.run, status.wall_s(), g.kind.csv(), &s)?;
                if let Err(e) = self.keep_snapshot(s.policy_version) {
                    tracing::warn!(error = %format!("{e:#}"), "keeping a copy of the policy evaluated failed (the run goes on)");
                }
                if g.kind == GateKind::Candidate {
                    tracing::info!(policy_version = s.policy_version, "evaluation to choose from: {}", s.one_line());
                }
                // The criterion's evaluations are scored too when they run as long as those that
                // choose; scores of episodes of other lengths do not compare.
                let scored = g.kind == GateKind::Candidate || self.choose_env.episode.max_steps == self.env.episode.max_steps;
                if scored && let Err(e) = self.consider(Score::of(&s, status.wall_s())) {
                    tracing::warn!(error = %format!("{e:#}"), "keeping the best policy evaluated failed (the run goes on)");
                }
                Ok((g.kind == GateKind::Criterion).then_some((g.at, s)))
            }
            Ok(Err(e)) => {
                tracing::warn!(error = %format!("{e:#}"), "evaluation of the stop criterion failed");
                Ok(None)
            }
            Err(_) => {
                tracing::warn!("evaluation of the stop criterion panicked");
                Ok(None)
            }
        }
    }

    /// Every policy an evaluation of the criterion judged stays in `snapshots/` as
    /// `policy-v{version}.safetensors` (about 280 KB each for explore-sac; one every
    /// `stop.choose_every_minutes`, and one every 20 s or so while the moving averages hold and
    /// the criterion's evaluations run), so that any of them, not only the best and the last,
    /// can be evaluated, compared or shipped after the run (its scores are the `criteria` and
    /// `candidate` lines of `evals.csv`). A version already kept is never replaced: a run's
    /// final `policy.safetensors` may be the mean of several, carrying its newest one's
    /// version, and a resumed run could judge it before the learner publishes again.
    fn keep_snapshot(&self, version: u64) -> Result<()> {
        let dir = self.run.join("snapshots");
        fs::create_dir_all(&dir).with_context(|| format!("creating {}", dir.display()))?;
        let to = dir.join(format!("policy-v{version}.safetensors"));
        if to.exists() {
            return Ok(());
        }
        let bytes = fs::read(self.gate_policy()).with_context(|| format!("reading {}", self.gate_policy().display()))?;
        mapless_proto::atomic_file::write_file_atomically(&to, &bytes).with_context(|| format!("writing {}", to.display()))
    }

    /// The policy an evaluation of the criterion judged (`policy-criteria.safetensors`), scored:
    /// when it beats the best so far, it becomes `policy-best.safetensors` (whole or not at
    /// all, its score beside it).
    fn consider(&mut self, score: Score) -> Result<()> {
        if self.best.as_ref().is_some_and(|b| !score.beats(b)) {
            return Ok(());
        }
        let bytes = fs::read(self.gate_policy()).with_context(|| format!("reading {}", self.gate_policy().display()))?;
        mapless_proto::atomic_file::write_file_atomically(&self.best_policy(), &bytes).with_context(|| format!("writing {}", self.best_policy().display()))?;
        write_atomic(&self.best_score(), &serde_json::to_string_pretty(&score)?)?;
        tracing::info!(policy_version = score.policy_version, "the best policy evaluated so far: {}", score.describe());
        self.best = Some(score);
        Ok(())
    }

    /// A run that stopped without meeting its criteria (with `stop.keep_best`): the best policy
    /// evaluated while training and the learner's last one (with `stop.average_last`, the mean
    /// of the newest snapshots in its place) are evaluated again, on starts of their own (`best`
    /// and `last` or `average` lines of `evals.csv`), and the best one becomes the run's policy
    /// when it is clearly safer there ([`Score::clearly_safer_than`]): a guard against
    /// a run that collapsed, not a choice between two policies a collision apart; with
    /// `stop.keep_best_when: safer`, whenever it is the safer there ([`Score::beats`]). Its score
    /// while training was the best of many, and so flattered by chance; on fresh starts the two
    /// compare fairly. Says which policy the run keeps, and why.
    pub(crate) fn keep_the_best_policy(&self, status: &Status) -> Result<String> {
        if !self.policy().exists() {
            return Ok(LAST.to_owned());
        }
        let average = self.average();
        let Some(best) = &self.best else {
            return match average {
                Some(a) => self.make_the_runs_policy(&a.path).map(|()| a.name),
                None => Ok(LAST.to_owned()),
            };
        };
        let (other, other_kind, other_name) = match &average {
            Some(a) => (a.path.clone(), "average", a.name.as_str()),
            None => (self.policy(), "last", LAST),
        };
        eprintln!(
            "choosing the run's policy: the best one evaluated while training ({}, at {:.0} s) and {other_name}, {} episodes each on starts of their own ...",
            best.describe(),
            best.wall_s,
            self.choice_episodes
        );
        let score = |policy: PathBuf, kind: &str| match eval::evaluate(&policy, &self.map, Split::Validation, &self.choose_env, self.choice_episodes, self.choice_seed, None) {
            Ok(s) => append_eval(&self.run, status.wall_s(), kind, &s).map(|()| Some(Score::of(&s, status.wall_s()))),
            Err(e) => {
                tracing::warn!(error = %format!("{e:#}"), "evaluation of {} failed", policy.display());
                Ok(None)
            }
        };
        let (again, last) = (score(self.best_policy(), "best")?, score(other, other_kind)?);
        let kept = self.keep_best_over(again.as_ref(), last.as_ref(), average.as_ref())?;
        eprintln!("  the run's policy: {kept}");
        Ok(kept)
    }

    /// The best policy becomes the run's when, on the same starts, it (`best`) is clearly safer
    /// (with `stop.keep_best_when: safer`, safer: [`Score::beats`]) than the one the run keeps
    /// otherwise (`last`): the mean of the newest snapshots when
    /// there is one (`average`), else the learner's last; the learner's last stays beside the
    /// run's as `policy-last.safetensors`. None stands for an evaluation that failed: the other
    /// policy is kept (the default one when both did).
    fn keep_best_over(&self, best: Option<&Score>, last: Option<&Score>, average: Option<&Averaged>) -> Result<String> {
        let default = average.map_or(LAST, |a| a.name.as_str());
        let keep_default = || match average {
            Some(a) => self.make_the_runs_policy(&a.path),
            None => Ok(()),
        };
        let (Some(was), Some(b)) = (&self.best, best) else {
            keep_default()?;
            return Ok(match self.best.is_some() {
                true => format!("{default}: the best one evaluated while training could not be evaluated again"),
                false => default.to_owned(),
            });
        };
        let (better, not_better) = match self.keep_best_when {
            KeepBestWhen::ClearlySafer => (Score::clearly_safer_than as fn(&Score, &Score) -> bool, "is not clearly safer"),
            KeepBestWhen::Safer => (Score::beats as fn(&Score, &Score) -> bool, "is not the safer (fewer collisions, then a higher mean EQS)"),
        };
        if let Some(l) = last
            && !better(b, l)
        {
            keep_default()?;
            return Ok(format!("{default} ({}); the best one evaluated while training (at {:.0} s, then {}; now {}) {not_better}", l.describe(), was.wall_s, was.describe(), b.describe()));
        }
        self.make_the_runs_policy(&self.best_policy())?;
        Ok(match last {
            Some(l) => format!("the best one evaluated while training (at {:.0} s, then {}; now {}), over {default} ({})", was.wall_s, was.describe(), b.describe(), l.describe()),
            None => format!("the best one evaluated while training (at {:.0} s, then {}; now {}): {default} could not be evaluated", was.wall_s, was.describe(), b.describe()),
        })
    }

    /// With `stop.average_last` = k: the mean of the newest k snapshots, written as
    /// `policy-average.safetensors`; none without the knob, with fewer than two snapshots, or
    /// when averaging failed (logged: the run then keeps what it would without the knob).
    fn average(&self) -> Option<Averaged> {
        let k = self.average_last?;
        let path = self.run.join("policy-average.safetensors");
        match super::average::average_newest(&self.run.join("snapshots"), k, &path) {
            Ok(Some(versions)) => {
                let name = format!("the mean of the newest {} policies judged (v{}–v{})", versions.len(), versions[0], versions[versions.len() - 1]);
                Some(Averaged { path, name })
            }
            Ok(None) => None,
            Err(e) => {
                tracing::warn!(error = %format!("{e:#}"), "averaging the newest policies failed: the run keeps what it would without stop.average_last");
                None
            }
        }
    }

    /// A run stopped by its criteria keeps the policy that met them as its policy; the
    /// learner's last one (a few seconds of training later) stays beside it as
    /// `policy-last.safetensors`.
    pub(crate) fn keep_the_policy_that_met_the_criteria(&self) -> Result<()> {
        self.make_the_runs_policy(&self.gate_policy())
    }

    /// `chosen` becomes `policy.safetensors`; the learner's last policy, if there is one, is
    /// kept beside it as `policy-last.safetensors`.
    fn make_the_runs_policy(&self, chosen: &Path) -> Result<()> {
        let (policy, last) = (self.policy(), self.run.join("policy-last.safetensors"));
        if policy.exists() {
            fs::rename(&policy, &last).with_context(|| format!("renaming {}", policy.display()))?;
        }
        fs::copy(chosen, &policy).with_context(|| format!("copying {} to {}", chosen.display(), policy.display()))?;
        Ok(())
    }

    /// The evaluation of the final policy (`eval.episodes`, deterministic; none with 0 or
    /// without a policy); its pictures replace those in eval/. A failed one is logged.
    pub(crate) fn final_evaluation(&self, status: &Status) -> Result<Option<EvalSummary>> {
        if self.settings.episodes == 0 || !self.policy().exists() {
            return Ok(None);
        }
        // Only this evaluation's pictures remain.
        if let Ok(dir) = fs::read_dir(self.run.join("eval")) {
            for f in dir.flatten() {
                if f.file_name().to_string_lossy().starts_with("episode-") {
                    let _ = fs::remove_file(f.path());
                }
            }
        }
        let map = &self.map;
        eprintln!("evaluating the final policy: {} episodes on {map} (deterministic, starts that no evaluation during training met) ...", self.settings.episodes);
        match eval::evaluate(&self.policy(), map, Split::HeldOut, &self.env, self.settings.episodes, self.final_seed, Some(&self.run.join("eval"))) {
            Ok(s) => {
                eprintln!("  {}", s.one_line());
                append_eval(&self.run, status.wall_s(), "final", &s)?;
                Ok(Some(s))
            }
            Err(e) => {
                tracing::warn!(error = %format!("{e:#}"), "evaluation failed");
                Ok(None)
            }
        }
    }
}

/// One-sided Fisher exact test: were `k1` of `n1` and `k2` of `n2` collisions drawn from one
/// policy, the chance that the first count would be `k1` or fewer (the hypergeometric tail, given
/// the `k1 + k2` collisions in all). 1 when either side has no episode.
fn fisher_one_sided(k1: u32, n1: usize, k2: u32, n2: usize) -> f64 {
    let (k1, k2, n1, n2) = (u64::from(k1), u64::from(k2), n1 as u64, n2 as u64);
    if n1 == 0 || n2 == 0 || k1 > n1 || k2 > n2 {
        return 1.0;
    }
    // ln C(n, r), as a sum: the counts are episodes, a few hundred at most.
    let ln_choose = |n: u64, r: u64| -> f64 { (0..r).map(|i| ((n - i) as f64).ln() - ((i + 1) as f64).ln()).sum() };
    let k = k1 + k2;
    let total = ln_choose(n1 + n2, k);
    (k.saturating_sub(n2)..=k1).map(|x| (ln_choose(n1, x) + ln_choose(n2, k - x) - total).exp()).sum::<f64>().min(1.0)
}

/// What a run keeps when nothing else is chosen.
pub(crate) const LAST: &str = "the learner's last";

/// A row of `evals.csv`: one per evaluation (while training, of the criterion, and final).
#[derive(Serialize)]
struct EvalLine<'a> {
    wall_s: f64,
    kind: &'a str,
    policy_version: u64,
    map: &'a str,
    episodes: usize,
    mean_steps: f64,
    mean_return: f64,
    mean_eqs: f64,
    mean_ees: f64,
    mean_distance_m: f64,
    collisions: u32,
}

fn append_eval(run: &Path, wall_s: f64, kind: &str, s: &EvalSummary) -> Result<()> {
    let path = run.join("evals.csv");
    // As episodes.csv: a line a crash tore is cut, the header goes into an empty file only.
    truncate_torn_line(&path)?;
    let empty = fs::metadata(&path).map_or(true, |m| m.len() == 0);
    let f = fs::OpenOptions::new().create(true).append(true).open(&path).with_context(|| format!("opening {}", path.display()))?;
    let mut w = csv::WriterBuilder::new().has_headers(empty).from_writer(f);
    w.serialize(EvalLine {
        wall_s,
        kind,
        policy_version: s.policy_version,
        map: &s.map,
        episodes: s.episodes.len(),
        mean_steps: s.mean_steps,
        mean_return: s.mean_return,
        mean_eqs: s.mean_eqs,
        mean_ees: s.mean_ees,
        mean_distance_m: s.mean_distance_m,
        collisions: s.collisions,
    })?;
    w.flush()?;
    Ok(())
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn evals_csv_gets_one_header_and_loses_only_a_torn_line() {
        let dir = tempfile::tempdir().unwrap();
        let s = EvalSummary {
            map: "maps/a,b.yaml".into(),
            policy_version: 7,
            episodes: Vec::new(),
            mean_steps: 1000.0,
            mean_return: 400.0,
            mean_eqs: 120.0,
            mean_ees: 2.5,
            mean_distance_m: 49.0,
            mean_shaded_time_s: 0.0,
            collisions: 0,
            parked: 0,
        };
        append_eval(dir.path(), 10.0, "progress", &s).unwrap();
        let p = dir.path().join("evals.csv");
        let torn = format!("{}20.0,progr", std::fs::read_to_string(&p).unwrap());
        std::fs::write(&p, torn).unwrap();
        append_eval(dir.path(), 30.0, "final", &s).unwrap();
        let mut r = csv::Reader::from_path(&p).unwrap();
        assert_eq!(r.headers().unwrap().iter().next(), Some("wall_s"));
        let rows: Vec<csv::StringRecord> = r.records().map(|x| x.unwrap()).collect();
        let kinds: Vec<(&str, &str)> = rows.iter().map(|x| (&x[1], &x[3])).collect();
        assert_eq!(kinds, [("progress", "maps/a,b.yaml"), ("final", "maps/a,b.yaml")], "a map path with a comma stays one field");
    }

    #[test]
    fn the_criteria_policy_becomes_the_runs_and_the_last_one_stays_beside_it() {
        let dir = tempfile::tempdir().unwrap();
        let cfg = super::super::config::preset_config("env1-sac").unwrap();
        let evals = Evaluations::new(&cfg, dir.path());
        assert!(!evals.gate_may_start(), "no policy published yet");
        std::fs::write(dir.path().join("policy.safetensors"), "last").unwrap();
        assert!(evals.gate_may_start());
        std::fs::write(dir.path().join("policy-criteria.safetensors"), "met").unwrap();
        evals.keep_the_policy_that_met_the_criteria().unwrap();
        let read = |f: &str| std::fs::read_to_string(dir.path().join(f)).unwrap();
        assert_eq!((read("policy.safetensors"), read("policy-last.safetensors")), ("met".to_owned(), "last".to_owned()));
    }

    #[test]
    fn every_policy_judged_stays_in_snapshots_under_its_version() {
        let dir = tempfile::tempdir().unwrap();
        let evals = Evaluations::new(&super::super::config::preset_config("explore-sac").unwrap(), dir.path());
        for (version, bytes) in [(7, "seven"), (12, "twelve")] {
            std::fs::write(dir.path().join("policy-criteria.safetensors"), bytes).unwrap();
            evals.keep_snapshot(version).unwrap();
        }
        let read = |v: u64| std::fs::read_to_string(dir.path().join(format!("snapshots/policy-v{v}.safetensors"))).unwrap();
        assert_eq!((read(7), read(12)), ("seven".to_owned(), "twelve".to_owned()));
        std::fs::write(dir.path().join("policy-criteria.safetensors"), "not seven").unwrap();
        evals.keep_snapshot(7).unwrap();
        assert_eq!(read(7), "seven", "a version kept is not replaced");
        std::fs::remove_file(dir.path().join("policy-criteria.safetensors")).unwrap();
        assert!(evals.keep_snapshot(13).is_err(), "no policy judged: an error (logged by the caller), no empty file");
        assert!(!dir.path().join("snapshots/policy-v13.safetensors").exists());
    }

    fn score(version: u64, episodes: usize, collisions: u32, mean_eqs: f64) -> Score {
        Score { policy_version: version, wall_s: version as f64, episodes, collisions, mean_eqs }
    }

    #[test]
    fn a_policy_is_better_for_a_lower_share_of_collisions_then_a_higher_eqs() {
        assert!(score(1, 20, 1, 50.0).beats(&score(2, 10, 1, 500.0)), "1 of 20 beats 1 of 10 whatever the EQS");
        assert!(!score(1, 10, 1, 500.0).beats(&score(2, 20, 1, 50.0)));
        assert!(score(1, 20, 2, 90.0).beats(&score(2, 10, 1, 80.0)) && !score(2, 10, 1, 80.0).beats(&score(1, 20, 2, 90.0)), "the same share: the EQS decides");
        assert!(!score(1, 10, 0, 80.0).beats(&score(2, 10, 0, 80.0)), "a tie keeps the one before");
    }

    #[test]
    fn clearly_safer_means_a_one_sided_exact_test_rejects_alike_at_five_percent() {
        // By hand: 0 of 20 against 6 of 20: C(20,6)/C(40,6) = 38760/3838380; 0 of 60 against 7 of
        // 60: C(60,7)/C(120,7) = 0.00649; 1 of 20 against 4 of 20: (C(20,5) + 20·C(20,4))/C(40,5).
        assert!((fisher_one_sided(0, 20, 6, 20) - 38760.0 / 3838380.0).abs() < 1e-12);
        assert!((fisher_one_sided(0, 60, 7, 60) - 0.006492).abs() < 1e-5);
        assert!((fisher_one_sided(1, 20, 4, 20) - (15504.0 + 20.0 * 4845.0) / 658008.0).abs() < 1e-12);
        assert!((fisher_one_sided(3, 20, 2, 20) - (1.0 - (20.0 * 4845.0 + 15504.0) / 658008.0)).abs() < 1e-12, "3 against 2: more likely than not");
        assert_eq!((fisher_one_sided(0, 20, 0, 20), fisher_one_sided(0, 0, 5, 20)), (1.0, 1.0));
        assert!(fisher_one_sided(20, 20, 0, 20) > 0.999 && fisher_one_sided(0, 20, 20, 20) < 1e-10);
        let first_clearly_worse = |best, n| (0..=n).find(|&l| score(1, n as usize, best, 0.0).clearly_safer_than(&score(2, n as usize, l, 0.0)));
        assert_eq!((first_clearly_worse(0, 20), first_clearly_worse(1, 20), first_clearly_worse(20, 20)), (Some(5), Some(6), None));
        assert_eq!((first_clearly_worse(0, 60), first_clearly_worse(1, 60)), (Some(5), Some(7)));
        assert!(score(1, 60, 0, 0.0).clearly_safer_than(&score(2, 60, 7, 0.0)), "the run of 2026-12-02");
        assert!(!score(1, 20, 2, 0.0).clearly_safer_than(&score(2, 20, 2, 0.0)) && !score(1, 20, 4, 0.0).clearly_safer_than(&score(2, 20, 2, 0.0)));
    }

    /// An evaluation of the criterion of the policy `content`, scored.
    fn judged(evals: &mut Evaluations, content: &str, s: Score) {
        std::fs::write(evals.gate_policy(), content).unwrap();
        evals.consider(s).unwrap();
    }

    #[test]
    fn the_best_policy_evaluated_is_kept_as_the_run_goes_and_across_a_resume() {
        let dir = tempfile::tempdir().unwrap();
        let cfg = super::super::config::preset_config("explore-sac").unwrap();
        let read = |f: &str| std::fs::read_to_string(dir.path().join(f)).unwrap();
        let mut evals = Evaluations::new(&cfg, dir.path());
        judged(&mut evals, "v1", score(1, 20, 3, 200.0));
        judged(&mut evals, "v2", score(2, 20, 1, 100.0));
        judged(&mut evals, "v3", score(3, 20, 1, 90.0));
        judged(&mut evals, "v4", score(4, 20, 9, 400.0));
        assert_eq!(read("policy-best.safetensors"), "v2");
        let mut resumed = Evaluations::new(&cfg, dir.path());
        assert_eq!(resumed.best, Some(score(2, 20, 1, 100.0)), "a resumed run compares with the best of its earlier sessions");
        judged(&mut resumed, "v5", score(5, 20, 2, 300.0));
        assert_eq!(read("policy-best.safetensors"), "v2");
        judged(&mut resumed, "v6", score(6, 20, 0, 10.0));
        assert_eq!(read("policy-best.safetensors"), "v6");
        std::fs::write(dir.path().join("policy-best.json"), "{ torn").unwrap();
        assert_eq!(Evaluations::new(&cfg, dir.path()).best, None, "a score that does not read is chosen afresh");
    }

    #[test]
    fn evaluations_to_choose_from_come_every_choose_every_minutes_are_scored_and_judge_nothing() {
        let dir = tempfile::tempdir().unwrap();
        let mut cfg = super::super::config::preset_config("explore-sac").unwrap();
        cfg.stop.eval_episodes = 2;
        cfg.env.episode.max_steps = 40;
        (cfg.stop.choose_every_minutes, cfg.stop.choose_max_steps) = (None, None);
        let shipped = Path::new(env!("CARGO_MANIFEST_DIR")).join("../policies/explore-sac/policy.safetensors");
        let evals = Evaluations::new(&cfg, dir.path());
        fs::copy(&shipped, evals.policy()).unwrap();
        assert!(evals.choose_every.is_none() && !evals.candidate_due(), "off unless the config asks");

        cfg.stop.choose_every_minutes = Some(0.5);
        cfg.stop.choose_max_steps = Some(60);
        let mut evals = Evaluations::new(&cfg, dir.path());
        assert!(!evals.candidate_due(), "not before the first half minute has passed");
        evals.last_candidate -= Duration::from_secs(31);
        assert!(evals.candidate_due());
        let (status, above) = (Status::new(0.0, None), ProgressBar::hidden());
        let ended = |evals: &mut Evaluations, averages| {
            evals.start_due(averages, || status.milestone(0)).unwrap();
            let g = evals.gate.as_ref().expect("an evaluation is due");
            while !g.handle.is_finished() {
                std::thread::sleep(Duration::from_millis(10));
            }
            evals.gate_ended(&status, &above).unwrap()
        };
        // One to choose from is due, but averages that hold come first. The criterion's
        // evaluations run the training episodes' 40 steps: not scored against the 60-step ones
        // that choose.
        assert!(ended(&mut evals, Averages::Evaluate).is_some() && evals.best.is_none());
        evals.last_gate = evals.last_gate.map(|t| t - GATE_EVAL_COOLDOWN);
        evals.last_candidate -= Duration::from_secs(31);
        assert!(ended(&mut evals, Averages::Short).is_none(), "an evaluation to choose from stops nothing");
        assert!(!evals.candidate_due(), "the clock starts again");
        let best = evals.best.clone().expect("scored for the best policy");
        assert_eq!((best.episodes, fs::read(evals.best_policy()).unwrap()), (2, fs::read(&shipped).unwrap()));
        let rows: Vec<csv::StringRecord> = csv::Reader::from_path(dir.path().join("evals.csv")).unwrap().records().map(|r| r.unwrap()).collect();
        let kinds: Vec<(&str, f64)> = rows.iter().map(|r| (&r[1], r[5].parse().unwrap())).collect();
        assert_eq!(kinds.iter().map(|k| k.0).collect::<Vec<_>>(), ["criteria", "candidate"]);
        assert!(kinds[0].1 <= 40.0 && kinds[1].1 > 40.0, "episodes of stop.choose_max_steps: {kinds:?}");
        // The next due one waits for the cooldown after the last evaluation, then the period.
        evals.last_candidate -= Duration::from_secs(31);
        assert!(!evals.candidate_due(), "the cooldown after an evaluation holds");
        evals.last_gate = evals.last_gate.map(|t| t - GATE_EVAL_COOLDOWN);
        assert!(evals.candidate_due());
        evals.last_candidate = Instant::now();
        evals.start_due(Averages::Short, || unreachable!("nothing is due")).unwrap();
        assert!(evals.gate.is_none());
    }

    #[test]
    fn at_the_end_the_best_policy_replaces_the_last_only_when_clearly_safer_on_the_same_fresh_starts() {
        let dir = tempfile::tempdir().unwrap();
        let cfg = super::super::config::preset_config("explore-sac").unwrap();
        let read = |f: &str| std::fs::read_to_string(dir.path().join(f)).unwrap();
        let mut evals = Evaluations::new(&cfg, dir.path());
        // The preset chooses on more episodes than a gate has: there 5 against 9 collisions
        // (of 60 each) is noise, and the same shares of 240 each are not.
        assert_eq!((evals.gate_episodes, evals.choice_episodes), (60, 240));
        assert!(!score(2, 60, 5, 0.0).clearly_safer_than(&score(9, 60, 9, 0.0)));
        assert!(score(2, 240, 20, 0.0).clearly_safer_than(&score(9, 240, 36, 0.0)));
        std::fs::write(evals.policy(), "last").unwrap();
        let kept = evals.keep_best_over(Some(&score(2, 20, 0, 90.0)), Some(&score(9, 20, 20, 0.0)), None).unwrap();
        assert_eq!(kept, LAST, "nothing evaluated while training: the last stays");
        judged(&mut evals, "best", score(2, 20, 0, 100.0));

        // Its score while training was the best of many; evaluated again it does worse than the
        // last on the same starts, or better by a collision or three: the last stays.
        for (best, last) in [(3, 2), (1, 4), (0, 3), (2, 6)] {
            let kept = evals.keep_best_over(Some(&score(2, 20, best, 100.0)), Some(&score(9, 20, last, 50.0)), None).unwrap();
            assert!(kept.starts_with("the learner's last (v9") && kept.ends_with(") is not clearly safer"), "{best} against {last}: {kept}");
        }
        assert_eq!(read("policy.safetensors"), "last");
        assert!(!dir.path().join("policy-last.safetensors").exists());
        let kept = evals.keep_best_over(None, Some(&score(9, 20, 20, 0.0)), None).unwrap();
        assert!(kept.contains("could not be evaluated again") && read("policy.safetensors") == "last", "{kept}");

        let kept = evals.keep_best_over(Some(&score(2, 20, 1, 100.0)), Some(&score(9, 20, 9, 500.0)), None).unwrap();
        assert!(kept.starts_with("the best one evaluated while training (at 2 s"), "{kept}");
        assert_eq!((read("policy.safetensors"), read("policy-last.safetensors")), ("best".to_owned(), "last".to_owned()));

        std::fs::write(evals.policy(), "another last").unwrap();
        let kept = evals.keep_best_over(Some(&score(2, 20, 1, 100.0)), None, None).unwrap();
        assert!(kept.contains("could not be evaluated"), "{kept}");
        assert_eq!((read("policy.safetensors"), read("policy-last.safetensors")), ("best".to_owned(), "another last".to_owned()));
    }

    #[test]
    fn with_average_last_the_mean_stands_where_the_last_would_and_the_last_stays_beside_it() {
        let dir = tempfile::tempdir().unwrap();
        let mut cfg = super::super::config::preset_config("explore-sac").unwrap();
        cfg.stop.average_last = Some(2);
        let read = |f: &str| std::fs::read_to_string(dir.path().join(f)).unwrap();
        let mut evals = Evaluations::new(&cfg, dir.path());
        assert!(evals.average().is_none(), "no snapshots: nothing to average");
        let mean = Averaged { path: dir.path().join("policy-average.safetensors"), name: "the mean".into() };
        std::fs::write(&mean.path, "mean").unwrap();
        judged(&mut evals, "best", score(2, 20, 0, 100.0));
        std::fs::write(evals.policy(), "last").unwrap();
        let kept = evals.keep_best_over(Some(&score(2, 20, 2, 100.0)), Some(&score(9, 20, 3, 50.0)), Some(&mean)).unwrap();
        assert!(kept.starts_with("the mean (v9"), "{kept}");
        assert_eq!((read("policy.safetensors"), read("policy-last.safetensors")), ("mean".to_owned(), "last".to_owned()));

        std::fs::write(evals.policy(), "last").unwrap();
        let kept = evals.keep_best_over(Some(&score(2, 20, 1, 100.0)), Some(&score(9, 20, 9, 500.0)), Some(&mean)).unwrap();
        assert!(kept.starts_with("the best one evaluated while training") && kept.contains("over the mean"), "{kept}");
        assert_eq!((read("policy.safetensors"), read("policy-last.safetensors")), ("best".to_owned(), "last".to_owned()));

        std::fs::write(evals.policy(), "last").unwrap();
        let kept = evals.keep_best_over(None, Some(&score(9, 20, 9, 500.0)), Some(&mean)).unwrap();
        assert!(kept.starts_with("the mean: the best one evaluated while training could not be evaluated again"), "{kept}");
        assert_eq!(read("policy.safetensors"), "mean");
    }

    #[test]
    fn with_keep_best_when_safer_the_one_that_collided_less_on_the_same_starts_is_kept() {
        let dir = tempfile::tempdir().unwrap();
        let mut cfg = super::super::config::preset_config("explore-sac").unwrap();
        cfg.stop.average_last = Some(16);
        cfg.stop.keep_best_when = KeepBestWhen::Safer;
        let read = |f: &str| std::fs::read_to_string(dir.path().join(f)).unwrap();
        let mut evals = Evaluations::new(&cfg, dir.path());
        let mean = Averaged { path: dir.path().join("policy-average.safetensors"), name: "the mean".into() };
        std::fs::write(&mean.path, "mean").unwrap();
        judged(&mut evals, "best", score(2, 60, 4, 100.0));
        // The counts of the run of 2026-12-07 (seed 0, hard starts within 3 m): 19 against 30
        // of 240 is not clearly fewer (p ≈ 0.07), but fewer.
        assert!(!score(2, 240, 19, 0.0).clearly_safer_than(&score(9, 240, 30, 0.0)));
        std::fs::write(evals.policy(), "last").unwrap();
        let kept = evals.keep_best_over(Some(&score(2, 240, 19, 384.0)), Some(&score(9, 240, 30, 371.0)), Some(&mean)).unwrap();
        assert!(kept.starts_with("the best one evaluated while training") && kept.contains("over the mean"), "{kept}");
        assert_eq!((read("policy.safetensors"), read("policy-last.safetensors")), ("best".to_owned(), "last".to_owned()));
        // More collisions, or as many at a lower or the same mean EQS: the mean stays.
        for (best, best_eqs) in [(33, 500.0), (32, 400.0), (32, 450.0)] {
            std::fs::write(evals.policy(), "last").unwrap();
            let kept = evals.keep_best_over(Some(&score(2, 240, best, best_eqs)), Some(&score(9, 240, 32, 450.0)), Some(&mean)).unwrap();
            assert!(kept.starts_with("the mean (v9") && kept.ends_with("is not the safer (fewer collisions, then a higher mean EQS)"), "{best} at {best_eqs}: {kept}");
            assert_eq!(read("policy.safetensors"), "mean");
        }
        // As many collisions at a higher mean EQS: the best.
        std::fs::write(evals.policy(), "last").unwrap();
        let kept = evals.keep_best_over(Some(&score(2, 240, 32, 451.0)), Some(&score(9, 240, 32, 450.0)), Some(&mean)).unwrap();
        assert!(kept.starts_with("the best one evaluated while training"), "{kept}");
        assert_eq!(read("policy.safetensors"), "best");
        // Without the knob the same counts keep the mean.
        cfg.stop.keep_best_when = KeepBestWhen::ClearlySafer;
        let mut evals = Evaluations::new(&cfg, dir.path());
        judged(&mut evals, "best", score(2, 60, 4, 100.0));
        std::fs::write(evals.policy(), "last").unwrap();
        let kept = evals.keep_best_over(Some(&score(2, 240, 19, 384.0)), Some(&score(9, 240, 30, 371.0)), Some(&mean)).unwrap();
        assert!(kept.starts_with("the mean (v9") && kept.ends_with("is not clearly safer"), "{kept}");
    }

    #[test]
    fn a_run_that_judged_no_policy_keeps_the_mean_of_its_newest_snapshots_unevaluated() {
        use mapless_proto::v1::{Algorithm, NamedTensor, ProtocolVersion, WeightsSnapshot};
        use mapless_proto::weights_file::{read_safetensors_file, write_safetensors_file};
        let dir = tempfile::tempdir().unwrap();
        let mut cfg = super::super::config::preset_config("explore-sac").unwrap();
        cfg.stop.average_last = Some(2);
        let evals = Evaluations::new(&cfg, dir.path());
        let policy = |version: u64, w: f32| WeightsSnapshot {
            protocol_version: ProtocolVersion::V1 as i32,
            version,
            algorithm: Algorithm::Sac as i32,
            created_unix_ms: 1,
            obs_dim: 1,
            act_dim: 1,
            tensors: vec![NamedTensor::from_f32("actor.out.bias", vec![1], &[w]).unwrap()],
            metadata: Default::default(),
        };
        std::fs::create_dir(dir.path().join("snapshots")).unwrap();
        for (v, w) in [(3, 100.0), (5, 1.0), (8, 3.0)] {
            write_safetensors_file(&dir.path().join(format!("snapshots/policy-v{v}.safetensors")), &policy(v, w)).unwrap();
        }
        write_safetensors_file(&evals.policy(), &policy(9, -7.0)).unwrap();
        let kept = evals.keep_the_best_policy(&Status::new(0.0, None)).unwrap();
        assert_eq!(kept, "the mean of the newest 2 policies judged (v5–v8)");
        let bias = |f: &str| read_safetensors_file(&dir.path().join(f)).unwrap().tensors[0].to_f32_vec().unwrap();
        assert_eq!((bias("policy.safetensors"), bias("policy-last.safetensors")), (vec![2.0], vec![-7.0]));
    }
}
