//! Columnar transition batches: building, validating and reading rows back.
//!
//! [`TransitionBatch`] (actor -> replay) and [`SampledBatch`] (replay -> learner) share the
//! same nine columns. Both are checked by one function over a borrowed [`Columns`] view, so
//! the two messages can never disagree on what a valid row is.
//!
//! ```text
//!  row i of a batch with obs_dim = 3, act_dim = 2:
//!   obs      [ .. | o0 o1 o2 | .. ]   obs[3i .. 3i+3]
//!   action   [ .. |  a0 a1   | .. ]   action[2i .. 2i+2]
//!   reward   [ .. |    r     | .. ]   reward[i]
//!   next_obs [ .. | n0 n1 n2 | .. ]   next_obs[3i .. 3i+3]
//!   terminal, truncated, episode_id, step, policy_version: [i]
//! ```

use crate::error::ProtoError;
use crate::v1::{ProtocolVersion, SampledBatch, TransitionBatch};
use crate::{MAX_ACTOR_ID_BYTES, check_protocol_version};

/// One transition, borrowed from a batch (or handed to [`TransitionBatchBuilder::push`]).
///
/// The slices have length `obs_dim` / `act_dim` of their batch.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct Transition<'a> {
    /// s_t, the observation the policy acted on.
    pub obs: &'a [f32],
    /// a_t, the action applied (after exploration noise).
    pub action: &'a [f32],
    /// r_{t+1}, the reward for the step.
    pub reward: f32,
    /// s_{t+1}, the observation after the step (present also when `terminal`).
    pub next_obs: &'a [f32],
    /// The step ended the episode in a collision: no bootstrapping.
    pub terminal: bool,
    /// The episode hit its step limit after this step: bootstrapping continues.
    pub truncated: bool,
    /// Episode this transition belongs to (per actor).
    pub episode_id: u64,
    /// 0-based index of the step within its episode.
    pub step: u32,
    /// Weights version that chose the action (0: warm-up policy).
    pub policy_version: u64,
}

/// Borrowed view of the nine columns both batch messages carry.
///
/// Invariant established by [`Columns::check`]: every slice has exactly the length that
/// `num_rows` and the dims imply, so [`Columns::row`] succeeds for every `i < num_rows`.
#[derive(Clone, Copy)]
struct Columns<'a> {
    obs_dim: u32,
    act_dim: u32,
    num_rows: u32,
    obs: &'a [f32],
    action: &'a [f32],
    reward: &'a [f32],
    next_obs: &'a [f32],
    terminal: &'a [bool],
    truncated: &'a [bool],
    episode_id: &'a [u64],
    step: &'a [u32],
    policy_version: &'a [u64],
}

impl<'a> Columns<'a> {
    /// Checks dims, row count, column lengths, finiteness and flags, in that order, so that
    /// the first error reported is the most fundamental one. O(num_rows * (obs_dim + act_dim)).
    fn check(
        &self,
        message: &'static str,
        expected_obs_dim: usize,
        expected_act_dim: usize,
        max_rows: usize,
    ) -> Result<usize, ProtoError> {
        check_dim("obs_dim", self.obs_dim, expected_obs_dim)?;
        check_dim("act_dim", self.act_dim, expected_act_dim)?;
        if self.num_rows == 0 {
            return Err(ProtoError::Empty { message });
        }
        let rows = u64::from(self.num_rows);
        if rows > max_rows as u64 {
            return Err(ProtoError::TooManyRows {
                rows,
                max: max_rows as u64,
            });
        }
        // u32 * u32 always fits in u64, so these products cannot overflow.
        let obs_len = rows * u64::from(self.obs_dim);
        let act_len = rows * u64::from(self.act_dim);
        check_len("obs", self.obs.len(), obs_len)?;
        check_len("action", self.action.len(), act_len)?;
        check_len("reward", self.reward.len(), rows)?;
        check_len("next_obs", self.next_obs.len(), obs_len)?;
        check_len("terminal", self.terminal.len(), rows)?;
        check_len("truncated", self.truncated.len(), rows)?;
        check_len("episode_id", self.episode_id.len(), rows)?;
        check_len("step", self.step.len(), rows)?;
        check_len("policy_version", self.policy_version.len(), rows)?;

        // Lengths are now known to match, so the dims are non-zero and fit in usize.
        let obs_dim = self.obs_dim as usize;
        let act_dim = self.act_dim as usize;
        check_finite("obs", self.obs, obs_dim)?;
        check_finite("action", self.action, act_dim)?;
        check_finite("reward", self.reward, 1)?;
        check_finite("next_obs", self.next_obs, obs_dim)?;
        if let Some(row) = self
            .terminal
            .iter()
            .zip(self.truncated)
            .position(|(&terminal, &truncated)| terminal && truncated)
        {
            return Err(ProtoError::TerminalAndTruncated { row });
        }
        Ok(self.num_rows as usize)
    }

    /// Row `i`, or `None` when `i >= num_rows` or a column is too short for it (only possible
    /// on a batch that has not passed [`Columns::check`]). Never panics.
    fn row(&self, i: usize) -> Option<Transition<'a>> {
        if i >= self.num_rows as usize {
            return None;
        }
        let obs_dim = self.obs_dim as usize;
        let act_dim = self.act_dim as usize;
        Some(Transition {
            obs: vector(self.obs, i, obs_dim)?,
            action: vector(self.action, i, act_dim)?,
            reward: *self.reward.get(i)?,
            next_obs: vector(self.next_obs, i, obs_dim)?,
            terminal: *self.terminal.get(i)?,
            truncated: *self.truncated.get(i)?,
            episode_id: *self.episode_id.get(i)?,
            step: *self.step.get(i)?,
            policy_version: *self.policy_version.get(i)?,
        })
    }
}

fn check_dim(field: &'static str, got: u32, expected: usize) -> Result<(), ProtoError> {
    // A receiver configured with dim 0 would accept empty vectors; refuse that outright.
    if got == 0 {
        return Err(ProtoError::InvalidField {
            field,
            reason: "is 0; vectors must have at least one element".to_owned(),
        });
    }
    if u64::from(got) != expected as u64 {
        return Err(ProtoError::DimensionMismatch {
            field,
            expected: expected as u64,
            got: u64::from(got),
        });
    }
    Ok(())
}

pub(crate) fn check_len(column: &'static str, got: usize, expected: u64) -> Result<(), ProtoError> {
    if got as u64 == expected {
        Ok(())
    } else {
        Err(ProtoError::ColumnLength {
            column,
            expected,
            got: got as u64,
        })
    }
}

/// Finds the first non-finite value of a row-major column with `width` values per row.
/// `width` must be > 0.
fn check_finite(column: &'static str, values: &[f32], width: usize) -> Result<(), ProtoError> {
    match values.iter().position(|v| !v.is_finite()) {
        None => Ok(()),
        Some(index) => Err(ProtoError::NonFinite {
            column,
            row: index / width,
            element: index % width,
            value: f64::from(values[index]),
        }),
    }
}

/// The `i`-th vector of length `width` in a row-major column, without panicking.
fn vector(values: &[f32], i: usize, width: usize) -> Option<&[f32]> {
    let start = i.checked_mul(width)?;
    values.get(start..start.checked_add(width)?)
}

fn check_actor_id(actor_id: &str) -> Result<(), ProtoError> {
    if actor_id.is_empty() {
        return Err(ProtoError::InvalidField {
            field: "actor_id",
            reason: "is empty".to_owned(),
        });
    }
    if actor_id.len() > MAX_ACTOR_ID_BYTES {
        return Err(ProtoError::InvalidField {
            field: "actor_id",
            reason: format!(
                "is {} bytes long, the limit is {MAX_ACTOR_ID_BYTES}",
                actor_id.len()
            ),
        });
    }
    Ok(())
}

impl TransitionBatch {
    fn columns(&self) -> Columns<'_> {
        Columns {
            obs_dim: self.obs_dim,
            act_dim: self.act_dim,
            num_rows: self.num_rows,
            obs: &self.obs,
            action: &self.action,
            reward: &self.reward,
            next_obs: &self.next_obs,
            terminal: &self.terminal,
            truncated: &self.truncated,
            episode_id: &self.episode_id,
            step: &self.step,
            policy_version: &self.policy_version,
        }
    }

    /// Checks every invariant documented on the message and returns the number of rows.
    ///
    /// `expected_obs_dim` / `expected_act_dim` are the dims the receiving table was created
    /// with; `max_rows` is the receiver's per-batch row limit. Checks, in order: protocol
    /// version, `actor_id`, `sequence`, dims, row count, every column's length, finiteness of
    /// every float (the error names column, row and element), and that no row is both
    /// terminal and truncated. O(num_rows * (obs_dim + act_dim)); allocates only on error.
    pub fn validate(
        &self,
        expected_obs_dim: usize,
        expected_act_dim: usize,
        max_rows: usize,
    ) -> Result<usize, ProtoError> {
        check_protocol_version(self.protocol_version)?;
        check_actor_id(&self.actor_id)?;
        if self.sequence == 0 {
            return Err(ProtoError::InvalidField {
                field: "sequence",
                reason: "is 0; sequences start at 1".to_owned(),
            });
        }
        self.columns().check(
            "TransitionBatch",
            expected_obs_dim,
            expected_act_dim,
            max_rows,
        )
    }

    /// Row `i`, borrowing from the batch; `None` if `i >= num_rows` or the batch is
    /// malformed at that row. Call [`TransitionBatch::validate`] first on received batches.
    pub fn row(&self, i: usize) -> Option<Transition<'_>> {
        self.columns().row(i)
    }

    /// All rows in order. On a batch that did not pass [`TransitionBatch::validate`] the
    /// iteration stops at the first malformed row.
    pub fn iter_rows(&self) -> impl Iterator<Item = Transition<'_>> + '_ {
        let columns = self.columns();
        (0..self.num_rows as usize).map_while(move |i| columns.row(i))
    }
}

impl SampledBatch {
    fn columns(&self) -> Columns<'_> {
        Columns {
            obs_dim: self.obs_dim,
            act_dim: self.act_dim,
            num_rows: self.num_rows,
            obs: &self.obs,
            action: &self.action,
            reward: &self.reward,
            next_obs: &self.next_obs,
            terminal: &self.terminal,
            truncated: &self.truncated,
            episode_id: &self.episode_id,
            step: &self.step,
            policy_version: &self.policy_version,
        }
    }

    /// Checks a minibatch received from the replay server and returns the number of rows.
    ///
    /// Same column checks as [`TransitionBatch::validate`], plus: `keys`, `probabilities`
    /// and `importance_weights` have one value per row, every probability is in (0, 1],
    /// every importance weight is finite and > 0, and `table_size` > 0.
    pub fn validate(
        &self,
        expected_obs_dim: usize,
        expected_act_dim: usize,
        max_rows: usize,
    ) -> Result<usize, ProtoError> {
        check_protocol_version(self.protocol_version)?;
        let rows =
            self.columns()
                .check("SampledBatch", expected_obs_dim, expected_act_dim, max_rows)?;
        if self.table_size == 0 {
            return Err(ProtoError::InvalidField {
                field: "table_size",
                reason: "is 0 although rows were sampled".to_owned(),
            });
        }
        let rows_u64 = rows as u64;
        check_len("keys", self.keys.len(), rows_u64)?;
        check_len("probabilities", self.probabilities.len(), rows_u64)?;
        check_len(
            "importance_weights",
            self.importance_weights.len(),
            rows_u64,
        )?;
        for (row, &p) in self.probabilities.iter().enumerate() {
            // NaN fails this comparison too.
            if !(p > 0.0 && p <= 1.0) {
                return Err(ProtoError::OutOfRange {
                    column: "probabilities",
                    row,
                    value: p,
                    expected: "in (0, 1]",
                });
            }
        }
        for (row, &w) in self.importance_weights.iter().enumerate() {
            if !(w.is_finite() && w > 0.0) {
                return Err(ProtoError::OutOfRange {
                    column: "importance_weights",
                    row,
                    value: f64::from(w),
                    expected: "finite and > 0",
                });
            }
        }
        Ok(rows)
    }

    /// Row `i`, borrowing from the minibatch; `None` if `i >= num_rows` or the minibatch is
    /// malformed at that row. Keys and weights are `keys[i]`, `importance_weights[i]`.
    pub fn row(&self, i: usize) -> Option<Transition<'_>> {
        self.columns().row(i)
    }

    /// All rows in order; stops at the first malformed row of an unvalidated minibatch.
    pub fn iter_rows(&self) -> impl Iterator<Item = Transition<'_>> + '_ {
        let columns = self.columns();
        (0..self.num_rows as usize).map_while(move |i| columns.row(i))
    }
}

/// Accumulates transitions one at a time into the columns of a [`TransitionBatch`].
///
/// Invariant: every column holds exactly `len()` rows, and every pushed row passed the same
/// checks as [`TransitionBatch::validate`] (lengths, finiteness, flags). A batch from
/// [`TransitionBatchBuilder::finish`] with a valid actor id and a sequence > 0 therefore
/// validates against the builder's dims, unless it is empty or exceeds the receiver's row
/// limit; the actor's own code finds its NaNs, not the replay server.
///
/// ```
/// use mapless_proto::{Transition, TransitionBatchBuilder};
///
/// let mut builder = TransitionBatchBuilder::new(2, 1);
/// builder.push(Transition {
///     obs: &[0.0, 1.0],
///     action: &[0.5],
///     reward: 1.0,
///     next_obs: &[0.1, 0.9],
///     terminal: false,
///     truncated: false,
///     episode_id: 1,
///     step: 0,
///     policy_version: 3,
/// })?;
/// let batch = builder.finish("actor-a", 1);
/// assert_eq!(batch.validate(2, 1, 1024)?, 1);
/// # Ok::<(), mapless_proto::ProtoError>(())
/// ```
#[derive(Debug, Clone)]
pub struct TransitionBatchBuilder {
    /// Columns filled so far; `actor_id`, `sequence` and `protocol_version` are set by
    /// `finish`.
    batch: TransitionBatch,
}

impl TransitionBatchBuilder {
    /// An empty builder for vectors of `obs_dim` and `act_dim` floats.
    ///
    /// Dims above `u32::MAX` cannot be expressed on the wire; they are saturated, so every
    /// push then fails with a length error instead of building a batch no peer accepts.
    pub fn new(obs_dim: usize, act_dim: usize) -> Self {
        Self::with_capacity(obs_dim, act_dim, 0)
    }

    /// Like [`TransitionBatchBuilder::new`], with room for `rows` transitions reserved.
    pub fn with_capacity(obs_dim: usize, act_dim: usize, rows: usize) -> Self {
        let obs_dim_u32 = u32::try_from(obs_dim).unwrap_or(u32::MAX);
        let act_dim_u32 = u32::try_from(act_dim).unwrap_or(u32::MAX);
        let obs_len = rows.saturating_mul(obs_dim);
        let act_len = rows.saturating_mul(act_dim);
        Self {
            batch: TransitionBatch {
                obs_dim: obs_dim_u32,
                act_dim: act_dim_u32,
                obs: Vec::with_capacity(obs_len),
                action: Vec::with_capacity(act_len),
                reward: Vec::with_capacity(rows),
                next_obs: Vec::with_capacity(obs_len),
                terminal: Vec::with_capacity(rows),
                truncated: Vec::with_capacity(rows),
                episode_id: Vec::with_capacity(rows),
                step: Vec::with_capacity(rows),
                policy_version: Vec::with_capacity(rows),
                ..TransitionBatch::default()
            },
        }
    }

    /// Rows pushed so far.
    pub fn len(&self) -> usize {
        self.batch.num_rows as usize
    }

    /// No rows pushed yet.
    pub fn is_empty(&self) -> bool {
        self.batch.num_rows == 0
    }

    /// Appends one transition after checking it: vector lengths against the builder's dims,
    /// every float finite, not both terminal and truncated. On error nothing is appended and
    /// the error names the row index the transition would have had.
    pub fn push(&mut self, t: Transition<'_>) -> Result<(), ProtoError> {
        let row = self.len();
        if self.batch.num_rows == u32::MAX {
            return Err(ProtoError::TooManyRows {
                rows: u64::from(u32::MAX) + 1,
                max: u64::from(u32::MAX),
            });
        }
        let obs_dim = self.batch.obs_dim as usize;
        let act_dim = self.batch.act_dim as usize;
        check_len("obs", t.obs.len(), obs_dim as u64)?;
        check_len("action", t.action.len(), act_dim as u64)?;
        check_len("next_obs", t.next_obs.len(), obs_dim as u64)?;
        for (column, values) in [
            ("obs", t.obs),
            ("action", t.action),
            ("reward", std::slice::from_ref(&t.reward)),
            ("next_obs", t.next_obs),
        ] {
            if let Some(element) = values.iter().position(|v| !v.is_finite()) {
                return Err(ProtoError::NonFinite {
                    column,
                    row,
                    element,
                    value: f64::from(values[element]),
                });
            }
        }
        if t.terminal && t.truncated {
            return Err(ProtoError::TerminalAndTruncated { row });
        }

        let b = &mut self.batch;
        b.obs.extend_from_slice(t.obs);
        b.action.extend_from_slice(t.action);
        b.reward.push(t.reward);
        b.next_obs.extend_from_slice(t.next_obs);
        b.terminal.push(t.terminal);
        b.truncated.push(t.truncated);
        b.episode_id.push(t.episode_id);
        b.step.push(t.step);
        b.policy_version.push(t.policy_version);
        b.num_rows += 1;
        Ok(())
    }

    /// The finished batch, stamped with this contract's protocol version, the sending
    /// actor's id and the batch's sequence number (>= 1, strictly increasing per actor; see
    /// `TransitionBatch.sequence` in `transition.proto`).
    pub fn finish(self, actor_id: impl Into<String>, sequence: u64) -> TransitionBatch {
        TransitionBatch {
            protocol_version: ProtocolVersion::V1 as i32,
            actor_id: actor_id.into(),
            sequence,
            ..self.batch
        }
    }
}
