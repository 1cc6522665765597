//! The paper's protocol as stated rules: when a run has converged (Table III's "convergence
//! episode") and when an evaluation meets the paper's exploration figures (the stop criterion).

use mapless_sim::stats::moving_average;

use crate::eval::EvalSummary;
use crate::train::episodes::EpisodeRow;

/// The order-`window` moving averages of `values` over full windows only: entry k averages
/// `values[k..k + window]` (`mapless_sim::stats::moving_average` from index `window − 1` on;
/// non-finite values are left out of their windows). Empty with fewer than `window` values.
fn full_window_averages(values: &[f64], window: usize) -> Vec<f64> {
    if window == 0 || values.len() < window {
        return Vec::new();
    }
    moving_average(values, window).split_off(window - 1)
}

/// The convergence episode: the first episode from which the order-`window` moving averages of
/// return *and* steps stay within `tolerance` (a fraction) of their values at the end of the
/// run, through to its end. `None` with fewer than `window` episodes. Episodes count from 1.
///
/// The paper does not state its rule; this one reads its Table III (DDPG "converged" at 170
/// with 865 average steps, so the rule cannot ask for the step limit, only for the curves to
/// have settled) and its Figs. 8–9.
pub fn convergence_episode(rows: &[EpisodeRow], window: usize, tolerance: f64) -> Option<u64> {
    let ret: Vec<f64> = rows.iter().map(|r| r.episode_return).collect();
    let steps: Vec<f64> = rows.iter().map(|r| f64::from(r.steps)).collect();
    let (ma_r, ma_s) = (full_window_averages(&ret, window), full_window_averages(&steps, window));
    let (fr, fs) = (*ma_r.last()?, *ma_s.last()?);
    let within = |v: f64, f: f64| (v - f).abs() <= tolerance * f.abs();
    // ma_*[k] is the average ending at episode k + window (1-based).
    let last_outside = (0..ma_r.len()).rev().find(|&k| !(within(ma_r[k], fr) && within(ma_s[k], fs)));
    let k = last_outside.map_or(0, |k| k + 1);
    Some((k + window) as u64)
}

/// What an evaluation must reach for a run to stop on its own (with the moving averages).
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct EvalGoal {
    pub eqs: Option<f64>,
    pub ees: Option<f64>,
    pub max_collisions: u32,
}

impl EvalGoal {
    /// Does `s` meet the goal? Means over its episodes.
    pub fn met_by(&self, s: &EvalSummary) -> bool {
        self.eqs.is_none_or(|g| s.mean_eqs >= g) && self.ees.is_none_or(|g| s.mean_ees >= g) && s.collisions <= self.max_collisions
    }

    pub fn describe(&self) -> String {
        let mut parts = Vec::new();
        if let Some(g) = self.eqs {
            parts.push(format!("EQS ≥ {g}"));
        }
        if let Some(g) = self.ees {
            parts.push(format!("EES ≥ {g}"));
        }
        parts.push(format!("≤ {} collisions", self.max_collisions));
        parts.join(", ")
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    fn rows(values: &[(f64, u32)]) -> Vec<EpisodeRow> {
        values
            .iter()
            .enumerate()
            .map(|(i, &(r, s))| EpisodeRow {
                episode: i as u64 + 1,
                wall_s: 0.0,
                actor_id: String::new(),
                policy_version: 0,
                episode_return: r,
                steps: s,
                terminal: false,
                eqs: 0.0,
                ees: 0.0,
                distance_m: 0.0,
                shaded_time_s: 0.0,
            })
            .collect()
    }

    #[test]
    fn full_window_averages_start_at_the_first_full_window() {
        assert_eq!(full_window_averages(&[1.0, 2.0, 3.0, 4.0, 5.0, 6.0], 3), vec![2.0, 3.0, 4.0, 5.0]);
        assert_eq!(full_window_averages(&[1.0, 2.0], 3), Vec::<f64>::new(), "fewer values than the window");
        assert_eq!(full_window_averages(&[1.0, 2.0], 0), Vec::<f64>::new(), "window 0");
        // Each entry is the plain mean of its window, as the running sum this replaced gave.
        let v: Vec<f64> = (0..5000).map(|i| ((i * 7919) % 1000) as f64 * 0.37 - 100.0).collect();
        let ma = full_window_averages(&v, 50);
        assert_eq!(ma.len(), v.len() - 49);
        for (k, a) in ma.iter().enumerate() {
            let direct = v[k..k + 50].iter().sum::<f64>() / 50.0;
            assert!((a - direct).abs() < 1e-9, "entry {k}: {a} vs {direct}");
        }
    }

    #[test]
    fn convergence_is_where_both_curves_settle_for_good() {
        // Window 2. Returns 0, 0, 100, 100, 50, 100, 100, 100, 100: the averages reach 100 at
        // episode 4, dip at 5–6 (75), and stay at 100 from episode 7 on.
        let r = rows(&[(0.0, 10), (0.0, 10), (100.0, 1000), (100.0, 1000), (50.0, 1000), (100.0, 1000), (100.0, 1000), (100.0, 1000), (100.0, 1000)]);
        assert_eq!(convergence_episode(&r, 2, 0.1), Some(7));
        // A looser tolerance forgives the dip (75 is within 30 % of 100).
        assert_eq!(convergence_episode(&r, 2, 0.3), Some(4));
        // Steps must settle too: the same returns with the steps still climbing at the end.
        let mut r2 = r.clone();
        r2[8].steps = 500;
        assert_eq!(convergence_episode(&r2, 2, 0.1), Some(9));
        assert_eq!(convergence_episode(&r[..1], 2, 0.1), None);
    }
}
