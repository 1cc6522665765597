//! The stop rules: when a run stops by itself, and why. Whichever comes first: the order-W
//! moving averages reach the preset's goal (backed, when `stop.eval_*` is set, by an evaluation
//! of the newest policy that meets it), K episodes, a time limit; or Ctrl-C / SIGTERM.

use std::sync::Arc;
use std::sync::atomic::{AtomicBool, Ordering};

use super::config::StopCriteria;
use super::episodes::EpisodeRow;
use super::status::Milestone;
use crate::eval::EvalSummary;
use mapless_sim::stats::trailing_mean;

/// How `Summary::stopped_because` begins for a run that Ctrl-C or SIGTERM stopped.
pub const INTERRUPTED: &str = "interrupted";

/// Ctrl-C or SIGTERM, once either has come.
pub(crate) struct Interrupt(Arc<AtomicBool>);

impl Interrupt {
    /// Listens for the signals on `rt`.
    pub(crate) fn listen(rt: &tokio::runtime::Runtime) -> Interrupt {
        let flag = Arc::new(AtomicBool::new(false));
        let set = Arc::clone(&flag);
        rt.spawn(async move {
            crate::signals::termination().await;
            set.store(true, Ordering::Relaxed);
        });
        Interrupt(flag)
    }

    pub(crate) fn came(&self) -> bool {
        self.0.load(Ordering::Relaxed)
    }
}

/// Have the stop criteria on moving averages been met? Each episode's steps count up to
/// `steps_cap`, the training episodes' limit (`env.episode.max_steps`): a long training episode
/// (`actors.long_share`) counts as one that ran its limit once it has, so that the goal keeps
/// its meaning (episodes run their limit without a collision) whatever the share of long ones.
pub fn averages_met(rows: &[EpisodeRow], stop: &StopCriteria, steps_cap: u32) -> bool {
    if stop.average_return.is_none() && stop.average_steps.is_none() {
        return false;
    }
    if rows.len() < stop.window || stop.min_episodes.is_some_and(|m| (rows.len() as u64) < m) {
        return false;
    }
    let r = trailing_mean(rows.iter().map(|e| e.episode_return), stop.window);
    let s = trailing_mean(rows.iter().map(|e| f64::from(e.steps.min(steps_cap))), stop.window);
    stop.average_return.is_none_or(|g| r >= g) && stop.average_steps.is_none_or(|g| s >= g)
}

/// The limits, in this order: K training episodes, then minutes of the whole run (a resumed run
/// counts its earlier sessions, up to its last recorded episode). The reason, once one is reached.
pub(crate) fn limit_reached(stop: &StopCriteria, episodes: u64, wall_s: f64) -> Option<String> {
    if let Some(k) = stop.episodes
        && episodes >= k
    {
        return Some(format!("{k} episodes"));
    }
    if let Some(m) = stop.minutes
        && wall_s >= m * 60.0
    {
        return Some(format!("{m} minutes"));
    }
    None
}

/// What the moving averages say.
#[derive(Debug, PartialEq)]
pub(crate) enum Averages {
    /// Not (yet) at the goal, or already judged.
    Short,
    /// At the goal, and nothing else to ask: the run stops.
    Met,
    /// At the goal: an evaluation of the newest policy must now back them.
    Evaluate,
}

/// Why a run stopped, and where it met its criteria (what `summary.json` keeps).
#[derive(Debug)]
pub(crate) struct Outcome {
    pub(crate) stopped_because: String,
    pub(crate) criteria_met_at: Option<Milestone>,
    /// The evaluation that met `stop.eval_*`.
    pub(crate) criteria_evaluation: Option<EvalSummary>,
}

/// The stop rules of one session of a run, with what they have decided so far.
pub(crate) struct StopRules {
    criteria: StopCriteria,
    /// Episodes of earlier sessions: the averages are judged once this session has added one
    /// (a resumed run that had met them does not stop at once on the same episodes).
    before: usize,
    /// The training episodes' limit, up to which an episode's steps count ([`averages_met`]).
    steps_cap: u32,
    /// Why the run stops, once a rule has said so.
    reason: Option<String>,
    met_at: Option<Milestone>,
    criteria_evaluation: Option<EvalSummary>,
}

impl StopRules {
    pub(crate) fn new(criteria: &StopCriteria, episodes_before: usize, steps_cap: u32) -> StopRules {
        StopRules { criteria: criteria.clone(), before: episodes_before, steps_cap, reason: None, met_at: None, criteria_evaluation: None }
    }

    /// `return ≥ G, steps ≥ H`: the goals of the moving averages.
    fn goals(&self) -> String {
        let goal = |name: &str, g: Option<f64>| g.map(|g| format!("{name} ≥ {g}"));
        [goal("return", self.criteria.average_return), goal("steps", self.criteria.average_steps)].into_iter().flatten().collect::<Vec<String>>().join(", ")
    }

    /// Looks at the moving averages of `rows` (`now`: this point of the run). Without an
    /// evaluation goal, their reaching the goal stops the run here; with one, the caller
    /// evaluates the newest policy and hands the result to [`StopRules::judge`].
    pub(crate) fn averages(&mut self, rows: &[EpisodeRow], now: impl FnOnce() -> Milestone) -> Averages {
        if self.met_at.is_some() || rows.len() <= self.before || !averages_met(rows, &self.criteria, self.steps_cap) {
            return Averages::Short;
        }
        if self.criteria.eval_goal().is_some() {
            return Averages::Evaluate;
        }
        self.met_at = Some(now());
        self.reason = Some(format!("order-{} moving averages reached the goal ({})", self.criteria.window, self.goals()));
        Averages::Met
    }

    /// An evaluation of the policy as it was `at`, made because the averages held: when it
    /// meets the goal (and nothing met it before), the criteria are met at `at` and the reason
    /// is returned.
    fn judged(&mut self, at: Milestone, s: EvalSummary) -> Option<String> {
        let gate = self.criteria.eval_goal().expect("an evaluation of the criterion is made only with a goal");
        if !gate.met_by(&s) {
            tracing::info!(policy_version = s.policy_version, "averages met, evaluation short of {}: {}", gate.describe(), s.one_line());
            return None;
        }
        if self.met_at.is_some() {
            return None;
        }
        let why =
            format!("order-{} moving averages reached the goal ({}) and an evaluation of policy v{} met {} ({})", self.criteria.window, self.goals(), s.policy_version, gate.describe(), s.one_line());
        self.met_at = Some(at);
        self.criteria_evaluation = Some(s);
        Some(why)
    }

    /// Takes an evaluation of the criterion that ended while the run goes on: one that meets
    /// the goal stops the run.
    pub(crate) fn judge(&mut self, at: Milestone, s: EvalSummary) {
        if let Some(why) = self.judged(at, s) {
            self.reason = Some(why);
        }
    }

    /// Takes an evaluation of the criterion that was still running when a limit or a signal
    /// stopped the run: if it met the goal, the run met its criteria after all.
    pub(crate) fn judge_after_stop(&mut self, at: Milestone, s: EvalSummary) {
        if let Some(why) = self.judged(at, s) {
            self.reason = Some(format!("{}; meanwhile {why}", self.stopped_because()));
        }
    }

    /// Does the run stop now? The criteria, once met, first; then a signal; then the limits.
    pub(crate) fn stops(&mut self, interrupted: bool, episodes: u64, wall_s: f64) -> bool {
        if self.reason.is_some() || interrupted {
            return true;
        }
        self.reason = limit_reached(&self.criteria, episodes, wall_s);
        self.reason.is_some()
    }

    /// Whether the criteria have been met (by the averages, and the evaluation they ask for).
    pub(crate) fn met(&self) -> bool {
        self.met_at.is_some()
    }

    /// Whether the criteria have been met, backed by an evaluation (its policy becomes the
    /// run's policy).
    pub(crate) fn met_by_evaluation(&self) -> bool {
        self.criteria_evaluation.is_some()
    }

    /// Why the run stopped (a signal, when no rule said so).
    pub(crate) fn stopped_because(&self) -> String {
        self.reason.clone().unwrap_or_else(|| format!("{INTERRUPTED} (Ctrl-C or SIGTERM)"))
    }

    pub(crate) fn outcome(self) -> Outcome {
        Outcome { stopped_because: self.stopped_because(), criteria_met_at: self.met_at, criteria_evaluation: self.criteria_evaluation }
    }
}

#[cfg(test)]
mod tests {
    use super::super::config::preset_config;
    use super::super::episodes::row;
    use super::*;

    fn at(episode: u64) -> Milestone {
        Milestone { wall_s: episode as f64, episode, env_steps: 1000 * episode, updates: 10 * episode }
    }

    fn evaluation(version: u64, eqs: f64, ees: f64, collisions: u32) -> EvalSummary {
        EvalSummary {
            map: "env1".into(),
            policy_version: version,
            episodes: Vec::new(),
            mean_steps: 1000.0,
            mean_return: 400.0,
            mean_eqs: eqs,
            mean_ees: ees,
            mean_distance_m: 49.0,
            mean_shaded_time_s: 0.0,
            collisions,
            parked: 0,
        }
    }

    #[test]
    fn stop_on_moving_averages_needs_a_full_window_and_both_goals() {
        let stop = StopCriteria { window: 3, average_return: Some(300.0), average_steps: Some(990.0), ..StopCriteria::default() };
        let mut rows = vec![row(1, 400.0, 1000), row(2, 400.0, 1000)];
        assert!(!averages_met(&rows, &stop, 1000), "fewer episodes than the window");
        rows.push(row(3, 400.0, 1000));
        assert!(averages_met(&rows, &stop, 1000));
        rows.push(row(4, 400.0, 900)); // steps average (1000+1000+900)/3 = 966.7 < 990
        assert!(!averages_met(&rows, &stop, 1000));
        let only_return = StopCriteria { average_steps: None, ..stop.clone() };
        assert!(averages_met(&rows, &only_return, 1000));
        let none = StopCriteria { average_return: None, average_steps: None, ..stop };
        assert!(!averages_met(&rows, &none, 1000), "no goals: never stops on averages");
    }

    /// Long training episodes (`actors.long_share`) count up to the ordinary limit: a window
    /// of long episodes that collided after it meets the steps goal, one whose long episodes
    /// make up for short ones does not.
    #[test]
    fn steps_count_up_to_the_training_episodes_limit() {
        let stop = StopCriteria { window: 3, average_steps: Some(990.0), ..StopCriteria::default() };
        let rows = [row(1, 400.0, 3000), row(2, 400.0, 1700), row(3, 400.0, 1000)];
        assert!(averages_met(&rows, &stop, 1000));
        let rows = [row(1, 400.0, 3000), row(2, 400.0, 3000), row(3, 400.0, 400)];
        assert!(averages_met(&rows, &stop, 3000), "uncapped: (3000 + 3000 + 400) / 3 ≥ 990");
        assert!(!averages_met(&rows, &stop, 1000), "(1000 + 1000 + 400) / 3 = 800 < 990");
    }

    #[test]
    fn no_average_is_judged_before_the_episode_floor() {
        let stop = StopCriteria { window: 2, average_return: Some(300.0), min_episodes: Some(4), ..StopCriteria::default() };
        let mut rows = vec![row(1, 400.0, 1000), row(2, 400.0, 1000), row(3, 400.0, 1000)];
        assert!(!averages_met(&rows, &stop, 1000), "3 episodes, the floor is 4");
        rows.push(row(4, 400.0, 1000));
        assert!(averages_met(&rows, &stop, 1000));
        let mut rules = StopRules::new(&stop, 0, 1000);
        assert_eq!(rules.averages(&rows[..3], || at(3)), Averages::Short);
        assert_eq!(rules.averages(&rows, || at(4)), Averages::Met);
    }

    #[test]
    fn the_averages_stop_the_run_exactly_when_the_window_fills_above_the_goal() {
        let criteria = StopCriteria { window: 4, average_return: Some(300.0), average_steps: Some(990.0), ..StopCriteria::default() };
        let mut rules = StopRules::new(&criteria, 0, 1000);
        let mut rows = Vec::new();
        for k in 1..=3 {
            rows.push(row(k, 400.0, 1000));
            assert_eq!(rules.averages(&rows, || at(k)), Averages::Short, "episode {k}: the window is not full");
            assert!(!rules.stops(false, k, k as f64), "episode {k}");
        }
        rows.push(row(4, 400.0, 1000));
        assert_eq!(rules.averages(&rows, || at(4)), Averages::Met);
        assert!(rules.stops(false, 4, 4.0));
        assert_eq!(rules.averages(&rows, || at(5)), Averages::Short, "met once: the first point stays");
        let o = rules.outcome();
        assert_eq!(o.stopped_because, "order-4 moving averages reached the goal (return ≥ 300, steps ≥ 990)");
        assert_eq!(o.criteria_met_at, Some(at(4)));
        assert!(o.criteria_evaluation.is_none());

        // A window whose last value pulls the average under the goal does not stop the run.
        let mut rules = StopRules::new(&criteria, 0, 1000);
        let rows = [row(1, 400.0, 1000), row(2, 400.0, 1000), row(3, 400.0, 1000), row(4, -200.0, 1000)];
        assert_eq!(rules.averages(&rows, || at(4)), Averages::Short, "return average 250 < 300");
        assert!(!rules.stops(false, 4, 4.0));
    }

    #[test]
    fn a_resumed_run_judges_the_averages_only_after_an_episode_of_its_own() {
        let criteria = StopCriteria { window: 2, average_return: Some(300.0), ..StopCriteria::default() };
        let mut rows = vec![row(1, 400.0, 1000), row(2, 400.0, 1000)];
        let mut rules = StopRules::new(&criteria, 2, 1000);
        assert_eq!(rules.averages(&rows, || at(2)), Averages::Short, "the earlier session's episodes only");
        rows.push(row(3, 400.0, 1000));
        assert_eq!(rules.averages(&rows, || at(3)), Averages::Met);
    }

    #[test]
    fn with_an_evaluation_goal_the_averages_ask_for_an_evaluation_that_must_meet_it() {
        let criteria = StopCriteria { window: 2, average_return: Some(300.0), eval_eqs: Some(91.0), eval_ees: Some(2.63), ..StopCriteria::default() };
        let rows = [row(1, 400.0, 1000), row(2, 400.0, 1000)];
        let mut rules = StopRules::new(&criteria, 0, 1000);
        assert_eq!(rules.averages(&rows, || at(2)), Averages::Evaluate);
        assert!(!rules.stops(false, 2, 2.0), "the averages alone do not stop it");
        // Short of the goal: EES, then a collision.
        rules.judge(at(2), evaluation(5, 120.0, 2.5, 0));
        rules.judge(at(2), evaluation(6, 120.0, 3.0, 1));
        assert!(!rules.stops(false, 2, 2.0) && !rules.met_by_evaluation());
        assert_eq!(rules.averages(&rows, || at(3)), Averages::Evaluate, "asked again while unmet");
        rules.judge(at(3), evaluation(7, 91.0, 2.63, 0));
        assert!(rules.stops(false, 3, 3.0) && rules.met_by_evaluation());
        assert_eq!(rules.averages(&rows, || at(4)), Averages::Short);
        rules.judge(at(4), evaluation(8, 200.0, 3.0, 0));
        let o = rules.outcome();
        assert_eq!(o.criteria_met_at, Some(at(3)), "the point of training that the evaluation judged");
        assert_eq!(o.criteria_evaluation.map(|s| s.policy_version), Some(7), "the first that met it");
        assert!(
            o.stopped_because.starts_with("order-2 moving averages reached the goal (return ≥ 300) and an evaluation of policy v7 met EQS ≥ 91, EES ≥ 2.63, ≤ 0 collisions (env1: "),
            "{}",
            o.stopped_because
        );
    }

    #[test]
    fn an_evaluation_that_ends_after_the_stop_still_counts() {
        let criteria = StopCriteria { window: 1, average_return: Some(300.0), eval_eqs: Some(91.0), minutes: Some(5.0), ..StopCriteria::default() };
        let mut rules = StopRules::new(&criteria, 0, 1000);
        assert!(rules.stops(false, 1, 300.0));
        rules.judge_after_stop(at(1), evaluation(3, 95.0, 0.0, 0));
        let o = rules.outcome();
        assert!(o.stopped_because.starts_with("5 minutes; meanwhile order-1 moving averages reached the goal (return ≥ 300) and an evaluation of policy v3"), "{}", o.stopped_because);
        assert_eq!(o.criteria_met_at, Some(at(1)));
        // One short of the goal leaves the reason alone.
        let mut rules = StopRules::new(&criteria, 0, 1000);
        assert!(rules.stops(true, 1, 1.0));
        rules.judge_after_stop(at(1), evaluation(3, 90.0, 0.0, 0));
        assert_eq!(rules.outcome().stopped_because, "interrupted (Ctrl-C or SIGTERM)");
    }

    #[test]
    fn limits_fire_when_reached_and_not_before() {
        let c = StopCriteria { episodes: Some(10), minutes: Some(0.5), ..StopCriteria::default() };
        assert_eq!(limit_reached(&c, 9, 29.9), None);
        assert_eq!(limit_reached(&c, 10, 0.0).as_deref(), Some("10 episodes"));
        assert_eq!(limit_reached(&c, 3, 30.0).as_deref(), Some("0.5 minutes"));
        assert_eq!(limit_reached(&c, 10, 30.0).as_deref(), Some("10 episodes"), "episodes are looked at first");
        assert_eq!(limit_reached(&StopCriteria::default(), u64::MAX, 1e12), None, "no limits: never");
        let mut rules = StopRules::new(&c, 0, 1000);
        assert!(!rules.stops(false, 9, 1.0));
        assert!(rules.stops(false, 10, 1.0));
        assert_eq!(rules.stopped_because(), "10 episodes");
    }

    #[test]
    fn a_signal_stops_the_run_and_only_met_criteria_name_another_reason() {
        let c = StopCriteria { episodes: Some(1), window: 1, average_return: Some(0.0), ..StopCriteria::default() };
        let mut rules = StopRules::new(&c, 0, 1000);
        assert!(rules.stops(true, 5, 1.0));
        assert!(rules.stopped_because().starts_with(INTERRUPTED), "a limit reached too does not name itself");
        let mut rules = StopRules::new(&c, 0, 1000);
        assert_eq!(rules.averages(&[row(1, 1.0, 10)], || at(1)), Averages::Met);
        assert!(rules.stops(true, 1, 1.0));
        assert!(rules.stopped_because().starts_with("order-1 moving averages"), "the criteria met in the same look win");
    }

    #[test]
    fn an_evaluation_goal_backs_the_averages_and_is_in_the_env1_presets() {
        let mut cfg = preset_config("env1-sac").unwrap();
        let goal = cfg.stop.eval_goal().expect("env1-sac stops on an evaluation too");
        assert_eq!((goal.eqs, goal.ees, goal.max_collisions), (Some(91.0), Some(2.63), 0), "Table III SAC");
        // Without averages to back, the goal does not stop a run (`averages_met` is false).
        cfg.stop.average_return = None;
        cfg.stop.average_steps = None;
        cfg.stop.window = 1;
        assert!(!averages_met(&[row(1, 500.0, 1000)], &cfg.stop, 1000));
        cfg.resolve().unwrap();
        for (p, eqs, ees) in [("env1-td3", 113.0, 2.40), ("env1-ddpg", 81.0, 1.82)] {
            let cfg = preset_config(p).unwrap();
            let g = cfg.stop.eval_goal().unwrap();
            assert_eq!((g.eqs, g.ees), (Some(eqs), Some(ees)), "{p}");
        }
    }
}
