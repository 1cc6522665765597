//! Minibatches as the algorithms consume them: one tensor per column, on the learner's device.
//!
//! ```text
//!   SampledBatch (replay) ──► BatchColumns (borrowed slices) ──► Minibatch (tensors)
//!        Minibatch::from_sampled     │                 Minibatch::from_columns
//!   plain slices (tests, in-process) ┘                 (the one place that checks)
//! ```
//!
//! [`Minibatch::from_sampled`] is the only code that reads a `SampledBatch`'s fields; every
//! check (lengths against `num_rows × dims`, finiteness, importance weights ≥ 0) lives in
//! [`Minibatch::from_columns`], so a bad batch is an [`LearnerError::InvalidBatch`] naming the
//! column, never a libtorch panic inside an update.
//!
//! The terminal mask is 1.0 where the episode *ended* (a collision: no bootstrapping) and 0.0
//! otherwise. Truncation (the step limit) is deliberately not part of it: a truncated
//! transition still bootstraps from its next state, y = r + γ(1 − terminal)·V(s′).

use mapless_proto::v1::SampledBatch;
use tch::Tensor;

use crate::LearnerError;

/// One minibatch of B transitions.
#[derive(Debug)]
pub struct Minibatch {
    /// s, `[B, obs_dim]`.
    pub obs: Tensor,
    /// a, `[B, act_dim]`, in the normalised action space [−1, 1].
    pub action: Tensor,
    /// r, `[B, 1]`.
    pub reward: Tensor,
    /// s′, `[B, obs_dim]`.
    pub next_obs: Tensor,
    /// 1.0 for a terminal transition (no bootstrapping), else 0.0; `[B, 1]`.
    pub terminal: Tensor,
    /// Importance-sampling weights from prioritised replay (all 1.0 for uniform), `[B, 1]`.
    pub weights: Tensor,
    /// Replay keys of the rows, for priority updates (empty when the batch has none).
    pub keys: Vec<u64>,
    rows: usize,
    obs_dim: usize,
    act_dim: usize,
}

/// A [`Minibatch`]'s columns as host memory ([`Minibatch::host`]), row-major.
#[derive(Debug, Clone, Copy)]
pub struct HostBatch<'a> {
    /// s, `rows × obs_dim`.
    pub obs: &'a [f32],
    /// a, `rows × act_dim`.
    pub action: &'a [f32],
    /// r, `rows`.
    pub reward: &'a [f32],
    /// s′, `rows × obs_dim`.
    pub next_obs: &'a [f32],
    /// 1.0 for a terminal transition, `rows`.
    pub terminal: &'a [f32],
    /// Importance-sampling weights, `rows`.
    pub weights: &'a [f32],
    /// B.
    pub rows: usize,
}

/// A minibatch as borrowed row-major columns, before any check. `importance_weights` and
/// `keys` may be empty (weights then default to 1, keys to none).
#[derive(Debug, Clone, Copy)]
pub struct BatchColumns<'a> {
    /// Rows.
    pub rows: usize,
    /// Observation width.
    pub obs_dim: usize,
    /// Action width.
    pub act_dim: usize,
    /// `rows × obs_dim` values.
    pub obs: &'a [f32],
    /// `rows × act_dim` values.
    pub action: &'a [f32],
    /// `rows` values.
    pub reward: &'a [f32],
    /// `rows × obs_dim` values.
    pub next_obs: &'a [f32],
    /// `rows` flags: the episode ended here (no bootstrapping).
    pub terminal: &'a [bool],
    /// `rows` weights, or empty for all ones.
    pub importance_weights: &'a [f32],
    /// `rows` replay keys, or empty.
    pub keys: &'a [u64],
}

impl Minibatch {
    /// From a replay `SampledBatch` (what `mapless_replay::Table::sample` and the replay
    /// service's `Sample` RPC return), with its float columns in either wire encoding (packed
    /// floats or little-endian bytes; see `SampleRequest.float_columns_as_bytes`). `truncated`
    /// is read only to reject a row flagged both terminal and truncated.
    pub fn from_sampled(batch: &SampledBatch, device: tch::Device) -> Result<Self, LearnerError> {
        let len = |what: &str, got: usize, want: usize| {
            if got == want { Ok(()) } else { Err(LearnerError::InvalidBatch(format!("`{what}` has {got} values, num_rows says {want}"))) }
        };
        let rows = batch.num_rows as usize;
        len("truncated", batch.truncated.len(), rows)?;
        len("terminal", batch.terminal.len(), rows)?;
        if let Some(i) = (0..rows).find(|&i| batch.terminal[i] && batch.truncated[i]) {
            return Err(LearnerError::InvalidBatch(format!("row {i} is both terminal and truncated")));
        }
        let (obs, action, reward, next_obs) = (batch.obs_values(), batch.action_values(), batch.reward_values(), batch.next_obs_values());
        Self::from_columns(
            BatchColumns {
                rows,
                obs_dim: batch.obs_dim as usize,
                act_dim: batch.act_dim as usize,
                obs: &obs,
                action: &action,
                reward: &reward,
                next_obs: &next_obs,
                terminal: &batch.terminal,
                importance_weights: &batch.importance_weights,
                keys: &batch.keys,
            },
            device,
        )
    }

    /// From plain columns; checks every length and value.
    pub fn from_columns(c: BatchColumns<'_>, device: tch::Device) -> Result<Self, LearnerError> {
        let bad = |m: String| Err(LearnerError::InvalidBatch(m));
        if c.rows == 0 {
            return bad("no rows".into());
        }
        if c.obs_dim == 0 || c.act_dim == 0 {
            return bad(format!("obs_dim {} and act_dim {} must be ≥ 1", c.obs_dim, c.act_dim));
        }
        let (Some(n_obs), Some(n_act)) = (c.rows.checked_mul(c.obs_dim), c.rows.checked_mul(c.act_dim)) else {
            return bad("rows × dims overflows".into());
        };
        for (what, got, want) in
            [("obs", c.obs.len(), n_obs), ("next_obs", c.next_obs.len(), n_obs), ("action", c.action.len(), n_act), ("reward", c.reward.len(), c.rows), ("terminal", c.terminal.len(), c.rows)]
        {
            if got != want {
                return bad(format!("`{what}` has {got} values, {} rows × dims need {want}", c.rows));
            }
        }
        for (what, got) in [("importance_weights", c.importance_weights.len()), ("keys", c.keys.len())] {
            if got != 0 && got != c.rows {
                return bad(format!("`{what}` has {got} values, need 0 or {}", c.rows));
            }
        }
        for (what, col, width) in [("obs", c.obs, c.obs_dim), ("next_obs", c.next_obs, c.obs_dim), ("action", c.action, c.act_dim), ("reward", c.reward, 1)] {
            if let Some(i) = col.iter().position(|v| !v.is_finite()) {
                return bad(format!("`{what}` row {} holds {}", i / width, col[i]));
            }
        }
        if let Some(i) = c.importance_weights.iter().position(|w| !(w.is_finite() && *w >= 0.0)) {
            return bad(format!("`importance_weights` row {i} is {}; must be finite and ≥ 0", c.importance_weights[i]));
        }
        let (b, d, a) = (c.rows as i64, c.obs_dim as i64, c.act_dim as i64);
        let to = |v: &[f32], shape: [i64; 2]| Tensor::from_slice(v).view(shape).to_device(device);
        let terminal: Vec<f32> = c.terminal.iter().map(|&t| f32::from(u8::from(t))).collect();
        let weights = if c.importance_weights.is_empty() { Tensor::ones([b, 1], (tch::Kind::Float, device)) } else { to(c.importance_weights, [b, 1]) };
        Ok(Self {
            obs: to(c.obs, [b, d]),
            action: to(c.action, [b, a]),
            reward: to(c.reward, [b, 1]),
            next_obs: to(c.next_obs, [b, d]),
            terminal: to(&terminal, [b, 1]),
            weights,
            keys: c.keys.to_vec(),
            rows: c.rows,
            obs_dim: c.obs_dim,
            act_dim: c.act_dim,
        })
    }

    /// The columns as host slices for the fused CPU updates, or `None` when one is not a
    /// contiguous CPU f32 tensor (then the libtorch path runs). The slices borrow the batch:
    /// a batch's columns are never written after it is built, and replacing one needs the
    /// batch mutably.
    pub fn host(&self) -> Option<HostBatch<'_>> {
        fn col(t: &Tensor) -> Option<&[f32]> {
            // SAFETY: see above.
            unsafe { crate::cpu::host_slice(t) }
        }
        Some(HostBatch {
            obs: col(&self.obs)?,
            action: col(&self.action)?,
            reward: col(&self.reward)?,
            next_obs: col(&self.next_obs)?,
            terminal: col(&self.terminal)?,
            weights: col(&self.weights)?,
            rows: self.rows,
        })
    }

    /// B.
    pub fn rows(&self) -> usize {
        self.rows
    }

    /// Observation width.
    pub fn obs_dim(&self) -> usize {
        self.obs_dim
    }

    /// Action width.
    pub fn act_dim(&self) -> usize {
        self.act_dim
    }

    /// A minibatch of `rows` random transitions (uniform values in [−1, 1], about 5%
    /// terminal), drawn from `rng`: for benchmarks and smoke tests.
    pub fn random(rows: usize, obs_dim: usize, act_dim: usize, rng: &mut impl rand::Rng, device: tch::Device) -> Result<Self, LearnerError> {
        let mut u = |n: usize| -> Vec<f32> { (0..n).map(|_| rng.random_range(-1.0f32..1.0)).collect() };
        let (obs, next_obs, action, reward) = (u(rows * obs_dim), u(rows * obs_dim), u(rows * act_dim), u(rows));
        let terminal: Vec<bool> = reward.iter().map(|r| *r > 0.9).collect();
        Self::from_columns(BatchColumns { rows, obs_dim, act_dim, obs: &obs, action: &action, reward: &reward, next_obs: &next_obs, terminal: &terminal, importance_weights: &[], keys: &[] }, device)
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    fn sampled() -> SampledBatch {
        SampledBatch {
            obs_dim: 2,
            act_dim: 1,
            num_rows: 2,
            obs: vec![1.0, 2.0, 3.0, 4.0],
            next_obs: vec![5.0, 6.0, 7.0, 8.0],
            action: vec![0.5, -0.5],
            reward: vec![1.0, -1.0],
            terminal: vec![true, false],
            truncated: vec![false, true],
            importance_weights: vec![1.0, 0.25],
            keys: vec![7, 9],
            ..SampledBatch::default()
        }
    }

    #[test]
    fn sampled_batches_become_column_tensors_with_a_terminal_mask_ignoring_truncation() {
        let mb = Minibatch::from_sampled(&sampled(), tch::Device::Cpu).unwrap();
        assert_eq!(mb.obs.size(), vec![2, 2]);
        assert_eq!(mb.action.size(), vec![2, 1]);
        assert_eq!(Vec::<f32>::try_from(&mb.terminal.view([-1])).unwrap(), vec![1.0, 0.0]);
        assert_eq!(Vec::<f32>::try_from(&mb.weights.view([-1])).unwrap(), vec![1.0, 0.25]);
        assert_eq!(mb.next_obs.double_value(&[1, 0]), 7.0);
        assert_eq!(mb.keys, vec![7, 9]);
    }

    #[test]
    fn wrong_lengths_nan_and_negative_weights_are_errors_naming_the_column() {
        let mut b = sampled();
        b.obs.pop();
        let e = Minibatch::from_sampled(&b, tch::Device::Cpu).unwrap_err();
        assert!(e.to_string().contains("`obs` has 3 values"), "{e}");

        let mut b = sampled();
        b.obs_dim = 3;
        assert!(Minibatch::from_sampled(&b, tch::Device::Cpu).is_err());

        let mut b = sampled();
        b.reward[1] = f32::NAN;
        let e = Minibatch::from_sampled(&b, tch::Device::Cpu).unwrap_err();
        assert!(e.to_string().contains("`reward` row 1 holds NaN"), "{e}");

        let mut b = sampled();
        b.importance_weights[0] = -1.0;
        assert!(Minibatch::from_sampled(&b, tch::Device::Cpu).unwrap_err().to_string().contains("importance_weights"));

        let mut b = sampled();
        b.truncated[0] = true;
        assert!(Minibatch::from_sampled(&b, tch::Device::Cpu).unwrap_err().to_string().contains("both terminal and truncated"));

        let mut b = sampled();
        b.num_rows = 0;
        b.terminal.clear();
        b.truncated.clear();
        assert!(Minibatch::from_sampled(&b, tch::Device::Cpu).is_err());
    }
}
