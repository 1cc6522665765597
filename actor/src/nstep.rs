//! n-step transitions: each stored row carries the discounted sum of n rewards and the
//! observation n steps later, so that one TD target looks n steps ahead (Sutton 1988; Mnih et
//! al. 2016; Hessel et al. 2018, "Rainbow"; Acme's `NStepTransitionAdder`).
//!
//! ```text
//!   vehicle i:  s_t a_t r_t+1 | s_t+1 a_t+1 r_t+2 | … | s_t+n
//!   row:        (s_t, a_t, Σ_{j<n} γ^j r_t+j+1, s_t+n, terminal, truncated)
//! ```
//!
//! The learner bootstraps such a row with γⁿ (`learner.n_step`). At the end of an episode the
//! rows still waiting have fewer than n rewards: after a collision (terminal) they need no
//! bootstrap and are stored with their shorter sums, marked terminal; after the step limit
//! (truncated) they would need γᵏ with k < n, which a row does not carry, so they are dropped
//! and counted (at most n − 1 of every truncated episode). With n = 1 every step is one row,
//! exactly as without this adder.

use mapless_proto::Transition;
use serde::{Deserialize, Serialize};

pub use mapless_proto::{MAX_N_STEP, META_GAMMA, META_N_STEP};

/// How an actor builds its rows when the learner bootstraps n steps ahead.
#[derive(Clone, Copy, Debug, Serialize, Deserialize, PartialEq)]
#[serde(deny_unknown_fields)]
pub struct NStepReturns {
    /// n, rewards summed per row (≥ 1); handed over from `learner.n_step`.
    pub n: usize,
    /// γ of the sum; handed over from `learner.gamma`.
    pub gamma: f64,
}

impl NStepReturns {
    /// n in 1..=[`MAX_N_STEP`] and γ in [0, 1].
    pub fn validate(&self) -> Result<(), String> {
        if self.n == 0 || self.n > MAX_N_STEP {
            return Err(format!("n_step.n must be in 1..={MAX_N_STEP}, got {}", self.n));
        }
        if !(0.0..=1.0).contains(&self.gamma) {
            return Err(format!("n_step.gamma must be in [0, 1], got {}", self.gamma));
        }
        Ok(())
    }
}

/// Whether published weights come from a learner whose targets bootstrap over the rewards
/// this actor sums per row: the same n (their metadata's [`META_N_STEP`]; absent: 1) and, for
/// n > 1, the same γ ([`META_GAMMA`]); the error names both sides.
pub fn check_snapshot(metadata: &std::collections::HashMap<String, String>, returns: Option<NStepReturns>) -> Result<(), String> {
    let n = returns.map_or(1, |r| r.n);
    let theirs = metadata.get(META_N_STEP);
    if theirs.map_or(Ok(1), |v| v.parse::<usize>()) != Ok(n) {
        return Err(format!("the learner's targets bootstrap over n = {} rewards, this actor's rows sum {n} (learner.n_step; the actors' n_step follows it)", theirs.map_or("1", |v| v.as_str())));
    }
    if let Some(r) = returns
        && n > 1
    {
        let gamma = metadata.get(META_GAMMA);
        if gamma.and_then(|v| v.parse::<f64>().ok()) != Some(r.gamma) {
            return Err(format!("the learner's γ is {}, this actor's rows sum with γ = {} (learner.gamma; the actors' n_step.gamma follows it)", gamma.map_or("not stated", |v| v.as_str()), r.gamma));
        }
    }
    Ok(())
}

/// Where a step's row came from, carried unchanged onto the row.
#[derive(Clone, Copy, Debug, Default)]
struct RowMeta {
    episode_id: u64,
    step: u32,
    policy_version: u64,
}

/// One vehicle's steps still waiting for their n rewards (a ring of at most n).
struct Lane {
    obs: Vec<f32>,
    action: Vec<f32>,
    reward: Vec<f32>,
    meta: Vec<RowMeta>,
    head: usize,
    len: usize,
}

/// Turns every vehicle's steps into n-step rows.
pub struct NStepAdder {
    n: usize,
    /// γ^0 .. γ^(n−1).
    discounts: Vec<f64>,
    obs_dim: usize,
    act_dim: usize,
    lanes: Vec<Lane>,
    dropped: u64,
}

impl NStepAdder {
    /// For `vehicles` vehicles with observations of `obs_dim` and actions of `act_dim` floats;
    /// `None` is n = 1.
    pub fn new(returns: Option<NStepReturns>, vehicles: usize, obs_dim: usize, act_dim: usize) -> Self {
        let (n, gamma) = returns.map_or((1, 1.0), |r| (r.n.max(1), r.gamma));
        let lane = || Lane { obs: vec![0.0; n * obs_dim], action: vec![0.0; n * act_dim], reward: vec![0.0; n], meta: vec![RowMeta::default(); n], head: 0, len: 0 };
        NStepAdder { n, discounts: (0..n).map(|j| gamma.powi(j as i32)).collect(), obs_dim, act_dim, lanes: (0..vehicles).map(|_| lane()).collect(), dropped: 0 }
    }

    /// n.
    pub fn n(&self) -> usize {
        self.n
    }

    /// Rows dropped at truncated episode ends (fewer than n rewards, no γᵏ to carry).
    pub fn dropped(&self) -> u64 {
        self.dropped
    }

    /// Vehicle `i` took the one-step transition `t` (s_t, a_t, r_t+1, s_t+1; `terminal` and
    /// `truncated` end its episode); hands every row this completes to `emit`, oldest first.
    pub fn step<E>(&mut self, i: usize, t: Transition<'_>, mut emit: impl FnMut(Transition<'_>) -> Result<(), E>) -> Result<(), E> {
        let (n, d, k_a) = (self.n, self.obs_dim, self.act_dim);
        let lane = &mut self.lanes[i];
        let slot = (lane.head + lane.len) % n;
        lane.obs[slot * d..(slot + 1) * d].copy_from_slice(t.obs);
        lane.action[slot * k_a..(slot + 1) * k_a].copy_from_slice(t.action);
        lane.reward[slot] = t.reward;
        lane.meta[slot] = RowMeta { episode_id: t.episode_id, step: t.step, policy_version: t.policy_version };
        lane.len += 1;
        // Full: the oldest step has its n rewards. At an episode's end after a collision,
        // every waiting step is a row too (no bootstrap, so the shorter sum is its target).
        while lane.len == n || (t.terminal && lane.len > 0) {
            let k = lane.head;
            let sum: f64 = (0..lane.len).map(|j| self.discounts[j] * f64::from(lane.reward[(k + j) % n])).sum();
            let m = lane.meta[k];
            let row = Transition {
                obs: &lane.obs[k * d..(k + 1) * d],
                action: &lane.action[k * k_a..(k + 1) * k_a],
                reward: sum as f32,
                next_obs: t.next_obs,
                terminal: t.terminal,
                truncated: t.truncated && !t.terminal,
                episode_id: m.episode_id,
                step: m.step,
                policy_version: m.policy_version,
            };
            emit(row)?;
            lane.head = (lane.head + 1) % n;
            lane.len -= 1;
        }
        if t.terminal || t.truncated {
            self.dropped += lane.len as u64;
            lane.head = 0;
            lane.len = 0;
        }
        Ok(())
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[derive(Debug, Clone, PartialEq)]
    struct Row {
        obs: f32,
        reward: f32,
        next: f32,
        terminal: bool,
        truncated: bool,
        step: u32,
    }

    /// Runs one vehicle through `rewards` (obs of step t is t, next obs t+1) ending as given.
    fn rows(n: usize, gamma: f64, rewards: &[f32], end: (bool, bool)) -> (Vec<Row>, u64) {
        let mut adder = NStepAdder::new(Some(NStepReturns { n, gamma }), 1, 1, 2);
        let mut out = Vec::new();
        for (t, &r) in rewards.iter().enumerate() {
            let last = t + 1 == rewards.len();
            let (term, trunc) = if last { end } else { (false, false) };
            let step =
                Transition { obs: &[t as f32], action: &[0.5, -0.5], reward: r, next_obs: &[t as f32 + 1.0], terminal: term, truncated: trunc, episode_id: 1, step: t as u32, policy_version: 3 };
            adder
                .step(0, step, |row| {
                    assert_eq!((row.action, row.episode_id, row.policy_version), (&[0.5, -0.5][..], 1, 3));
                    out.push(Row { obs: row.obs[0], reward: row.reward, next: row.next_obs[0], terminal: row.terminal, truncated: row.truncated, step: row.step });
                    Ok::<(), ()>(())
                })
                .unwrap();
        }
        (out, adder.dropped())
    }

    fn row(obs: f32, reward: f32, next: f32, terminal: bool, truncated: bool) -> Row {
        Row { obs, reward, next, terminal, truncated, step: obs as u32 }
    }

    #[test]
    fn one_step_is_every_step_unchanged() {
        let (out, dropped) = rows(1, 0.9, &[1.0, 2.0, 3.0], (false, true));
        assert_eq!(out, vec![row(0.0, 1.0, 1.0, false, false), row(1.0, 2.0, 2.0, false, false), row(2.0, 3.0, 3.0, false, true)]);
        assert_eq!(dropped, 0);
    }

    #[test]
    fn rows_sum_n_discounted_rewards_and_look_n_ahead() {
        let (out, _) = rows(3, 0.5, &[1.0, 2.0, 4.0, 8.0, 16.0], (false, false));
        // 1 + 0.5·2 + 0.25·4 = 3; 2 + 0.5·4 + 0.25·8 = 6; 4 + 4 + 4 = 12.
        assert_eq!(out, vec![row(0.0, 3.0, 3.0, false, false), row(1.0, 6.0, 4.0, false, false), row(2.0, 12.0, 5.0, false, false)]);
    }

    #[test]
    fn a_collision_stores_every_waiting_step_as_terminal() {
        let (out, dropped) = rows(3, 0.5, &[1.0, 2.0, 4.0, -8.0], (true, false));
        // The full row of step 1 ends in the collision too: 2 + 2 − 2 = 2, terminal.
        assert_eq!(out, vec![row(0.0, 3.0, 3.0, false, false), row(1.0, 2.0, 4.0, true, false), row(2.0, 0.0, 4.0, true, false), row(3.0, -8.0, 4.0, true, false)]);
        assert_eq!(dropped, 0);
        // A collision on the first step: one row of one reward.
        let (out, _) = rows(4, 0.5, &[-1.0], (true, false));
        assert_eq!(out, vec![row(0.0, -1.0, 1.0, true, false)]);
    }

    #[test]
    fn the_step_limit_drops_the_rows_that_lack_n_rewards() {
        let (out, dropped) = rows(3, 0.5, &[1.0, 2.0, 4.0, 8.0], (false, true));
        assert_eq!(out, vec![row(0.0, 3.0, 3.0, false, false), row(1.0, 6.0, 4.0, false, true)]);
        assert_eq!(dropped, 2);
    }

    #[test]
    fn vehicles_and_episodes_do_not_mix() {
        let mut adder = NStepAdder::new(Some(NStepReturns { n: 2, gamma: 1.0 }), 2, 1, 1);
        let mut out = Vec::new();
        let mut push = |adder: &mut NStepAdder, i: usize, t: f32, r: f32, term: bool| {
            adder
                .step(i, Transition { obs: &[t], action: &[0.0], reward: r, next_obs: &[t + 1.0], terminal: term, truncated: false, episode_id: i as u64, step: 0, policy_version: 0 }, |row| {
                    out.push((row.episode_id, row.obs[0], row.reward, row.next_obs[0], row.terminal));
                    Ok::<(), ()>(())
                })
                .unwrap()
        };
        push(&mut adder, 0, 0.0, 1.0, false);
        push(&mut adder, 1, 10.0, 100.0, true);
        push(&mut adder, 1, 20.0, 200.0, false); // vehicle 1's next episode
        push(&mut adder, 0, 1.0, 2.0, false);
        push(&mut adder, 1, 21.0, 300.0, false);
        assert_eq!(out, vec![(1, 10.0, 100.0, 11.0, true), (0, 0.0, 3.0, 2.0, false), (1, 20.0, 500.0, 22.0, false)]);
    }

    #[test]
    fn weights_must_say_the_same_n_and_gamma() {
        let three = Some(NStepReturns { n: 3, gamma: 0.995 });
        let mut meta = std::collections::HashMap::new();
        assert!(check_snapshot(&meta, None).is_ok());
        assert!(check_snapshot(&meta, Some(NStepReturns { n: 1, gamma: 0.9 })).is_ok());
        assert!(check_snapshot(&meta, three).unwrap_err().contains("n = 1"));
        meta.insert(META_N_STEP.to_owned(), "3".to_owned());
        assert!(check_snapshot(&meta, None).unwrap_err().contains("n = 3"));
        assert!(check_snapshot(&meta, three).unwrap_err().contains("not stated"));
        meta.insert(META_GAMMA.to_owned(), "0.99".to_owned());
        assert!(check_snapshot(&meta, three).unwrap_err().contains("γ is 0.99"));
        meta.insert(META_GAMMA.to_owned(), 0.995f64.to_string());
        assert!(check_snapshot(&meta, three).is_ok());
        meta.insert(META_N_STEP.to_owned(), "three".to_owned());
        assert!(check_snapshot(&meta, three).is_err());
    }

    #[test]
    fn settings_are_checked() {
        assert!(NStepReturns { n: 0, gamma: 0.9 }.validate().is_err());
        assert!(NStepReturns { n: MAX_N_STEP + 1, gamma: 0.9 }.validate().is_err());
        assert!(NStepReturns { n: 3, gamma: 1.5 }.validate().is_err());
        assert!(NStepReturns { n: 3, gamma: 0.995 }.validate().is_ok());
    }
}
