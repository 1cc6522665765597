//! Columnar transition batches: building, validating and reading rows back.
//!
//! [`TransitionBatch`] (actor -> replay) and [`SampledBatch`] (replay -> learner) share the
//! same nine columns. Both are checked by one function over a borrowed [`Columns`] view, so
//! the two messages can never disagree on what a valid row is.
//!
//! The four float columns travel either packed (`obs`) or as little-endian bytes
//! (`obs_f32le`); see [`FloatEncoding`]. Read them through the column accessors
//! (`obs_column()`, `obs_values()`, ...), which work for both; [`TransitionBatch::row`]
//! borrows `&[f32]` slices and therefore reads packed columns only.
//!
//! ```text
//!  row i of a batch with obs_dim = 3, act_dim = 2:
//!   obs      [ .. | o0 o1 o2 | .. ]   obs[3i .. 3i+3]
//!   action   [ .. |  a0 a1   | .. ]   action[2i .. 2i+2]
//!   reward   [ .. |    r     | .. ]   reward[i]
//!   next_obs [ .. | n0 n1 n2 | .. ]   next_obs[3i .. 3i+3]
//!   terminal, truncated, episode_id, step, policy_version: [i]
//! ```

use std::borrow::Cow;

use prost::Message;
use prost::bytes::Bytes;

use crate::error::ProtoError;
use crate::floats::{FloatColumn, FloatEncoding, f32le_bytes, length_delimited_overhead, put_length_delimited};
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

/// One float column as a message holds it: the packed field and its `_f32le` twin, at most
/// one of them set.
#[derive(Clone, Copy)]
struct FloatField<'a> {
    name: &'static str,
    le_name: &'static str,
    packed: &'a [f32],
    le: &'a [u8],
}

impl<'a> FloatField<'a> {
    /// The encoding that carries the column (the bytes when set, else the packed floats).
    fn column(&self) -> FloatColumn<'a> {
        FloatColumn::of(self.packed, self.le)
    }

    /// The field name of the encoding that carries the column.
    fn carrier(&self) -> &'static str {
        if self.le.is_empty() { self.name } else { self.le_name }
    }

    /// At most one encoding set, whole floats, `expected` values.
    fn check_len(&self, expected: u64) -> Result<(), ProtoError> {
        if !self.le.is_empty() {
            if !self.packed.is_empty() {
                return Err(ProtoError::InvalidField { field: self.le_name, reason: format!("is set together with `{}`; send exactly one encoding of a column", self.name) });
            }
            if !self.le.len().is_multiple_of(4) {
                return Err(ProtoError::InvalidField { field: self.le_name, reason: format!("is {} bytes long, not a whole number of 4-byte floats", self.le.len()) });
            }
        }
        check_len(self.carrier(), self.column().len(), expected)
    }

    /// The first non-finite value, reported in the carrying field's name.
    fn check_finite(&self, width: usize) -> Result<(), ProtoError> {
        match self.column().first_non_finite() {
            None => Ok(()),
            Some((index, value)) => Err(ProtoError::NonFinite { column: self.carrier(), row: index / width, element: index % width, value: f64::from(value) }),
        }
    }
}

/// Borrowed view of the nine columns both batch messages carry.
///
/// Invariant established by [`Columns::check`]: every column has exactly the length that
/// `num_rows` and the dims imply, in exactly one encoding, so [`Columns::row`] succeeds for
/// every `i < num_rows` when the float columns are packed.
#[derive(Clone, Copy)]
struct Columns<'a> {
    obs_dim: u32,
    act_dim: u32,
    num_rows: u32,
    obs: FloatField<'a>,
    action: FloatField<'a>,
    reward: FloatField<'a>,
    next_obs: FloatField<'a>,
    terminal: &'a [bool],
    truncated: &'a [bool],
    episode_id: &'a [u64],
    step: &'a [u32],
    policy_version: &'a [u64],
}

impl<'a> Columns<'a> {
    /// Checks dims, row count, column encodings and lengths, finiteness and flags, in that
    /// order, so that the first error reported is the most fundamental one.
    /// O(num_rows * (obs_dim + act_dim)).
    fn check(&self, message: &'static str, expected_obs_dim: usize, expected_act_dim: usize, max_rows: usize) -> Result<usize, ProtoError> {
        check_dim("obs_dim", self.obs_dim, expected_obs_dim)?;
        check_dim("act_dim", self.act_dim, expected_act_dim)?;
        if self.num_rows == 0 {
            return Err(ProtoError::Empty { message });
        }
        let rows = u64::from(self.num_rows);
        if rows > max_rows as u64 {
            return Err(ProtoError::TooManyRows { rows, max: max_rows as u64 });
        }
        // u32 * u32 always fits in u64, so these products cannot overflow.
        let obs_len = rows * u64::from(self.obs_dim);
        let act_len = rows * u64::from(self.act_dim);
        self.obs.check_len(obs_len)?;
        self.action.check_len(act_len)?;
        self.reward.check_len(rows)?;
        self.next_obs.check_len(obs_len)?;
        check_len("terminal", self.terminal.len(), rows)?;
        check_len("truncated", self.truncated.len(), rows)?;
        check_len("episode_id", self.episode_id.len(), rows)?;
        check_len("step", self.step.len(), rows)?;
        check_len("policy_version", self.policy_version.len(), rows)?;

        // Lengths are now known to match, so the dims are non-zero and fit in usize.
        let obs_dim = self.obs_dim as usize;
        let act_dim = self.act_dim as usize;
        self.obs.check_finite(obs_dim)?;
        self.action.check_finite(act_dim)?;
        self.reward.check_finite(1)?;
        self.next_obs.check_finite(obs_dim)?;
        if let Some(row) = self.terminal.iter().zip(self.truncated).position(|(&terminal, &truncated)| terminal && truncated) {
            return Err(ProtoError::TerminalAndTruncated { row });
        }
        Ok(self.num_rows as usize)
    }

    /// Row `i`, or `None` when `i >= num_rows`, a column is too short for it (only possible
    /// on a batch that has not passed [`Columns::check`]) or a float column travels as bytes
    /// (which cannot be borrowed as `&[f32]`). Never panics.
    fn row(&self, i: usize) -> Option<Transition<'a>> {
        if i >= self.num_rows as usize {
            return None;
        }
        let obs_dim = self.obs_dim as usize;
        let act_dim = self.act_dim as usize;
        Some(Transition {
            obs: vector(self.obs, i, obs_dim)?,
            action: vector(self.action, i, act_dim)?,
            reward: *packed(self.reward)?.get(i)?,
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
        return Err(ProtoError::InvalidField { field, reason: "is 0; vectors must have at least one element".to_owned() });
    }
    if u64::from(got) != expected as u64 {
        return Err(ProtoError::DimensionMismatch { field, expected: expected as u64, got: u64::from(got) });
    }
    Ok(())
}

pub(crate) fn check_len(column: &'static str, got: usize, expected: u64) -> Result<(), ProtoError> {
    if got as u64 == expected { Ok(()) } else { Err(ProtoError::ColumnLength { column, expected, got: got as u64 }) }
}

/// The packed floats of a field, or `None` when the column travels as bytes.
fn packed(field: FloatField<'_>) -> Option<&[f32]> {
    field.le.is_empty().then_some(field.packed)
}

/// The `i`-th vector of length `width` in a packed row-major column, without panicking.
fn vector(field: FloatField<'_>, i: usize, width: usize) -> Option<&[f32]> {
    let values = packed(field)?;
    let start = i.checked_mul(width)?;
    values.get(start..start.checked_add(width)?)
}

/// Moves one float column into `to`, unless it is set in both encodings (left as it is, for
/// `validate` to report) or already there.
fn convert_column(packed: &mut Vec<f32>, le: &mut Bytes, to: FloatEncoding) {
    match to {
        FloatEncoding::F32Le if le.is_empty() && !packed.is_empty() => {
            *le = f32le_bytes(packed);
            *packed = Vec::new();
        }
        FloatEncoding::Packed if packed.is_empty() && !le.is_empty() => {
            *packed = FloatColumn::F32Le(le).to_vec();
            *le = Bytes::new();
        }
        _ => {}
    }
}

/// The float columns' (tag of the `_f32le` field, packed values, bytes) in field order.
type FloatFields<'a> = [(u32, &'a [f32], &'a [u8]); 4];

/// Appends `shell` (a message whose packed float fields are empty) followed by the float
/// columns as `bytes *_f32le` fields: the wire form of the message with every float column in
/// the F32Le encoding, without building it. A column set in both encodings keeps its packed
/// field (in `shell`) so that the receiver still sees, and rejects, both.
fn encode_with_f32le_fields(shell: &impl Message, fields: FloatFields<'_>, out: &mut Vec<u8>) {
    out.reserve(encoded_len_with_f32le_fields(shell, fields));
    shell.encode_raw(out);
    for (tag, packed, le) in fields {
        if !le.is_empty() {
            put_length_delimited(out, tag, le.len());
            out.extend_from_slice(le);
        } else if !packed.is_empty() {
            put_length_delimited(out, tag, packed.len() * 4);
            crate::floats::extend_f32le(out, packed);
        }
    }
}

fn encoded_len_with_f32le_fields(shell: &impl Message, fields: FloatFields<'_>) -> usize {
    let floats: usize = fields
        .iter()
        .map(|&(tag, packed, le)| {
            let n = if le.is_empty() { packed.len() * 4 } else { le.len() };
            if n == 0 { 0 } else { length_delimited_overhead(tag, n) + n }
        })
        .sum();
    shell.encoded_len() + floats
}

fn check_actor_id(actor_id: &str) -> Result<(), ProtoError> {
    if actor_id.is_empty() {
        return Err(ProtoError::InvalidField { field: "actor_id", reason: "is empty".to_owned() });
    }
    if actor_id.len() > MAX_ACTOR_ID_BYTES {
        return Err(ProtoError::InvalidField { field: "actor_id", reason: format!("is {} bytes long, the limit is {MAX_ACTOR_ID_BYTES}", actor_id.len()) });
    }
    Ok(())
}

impl TransitionBatch {
    fn columns(&self) -> Columns<'_> {
        Columns {
            obs_dim: self.obs_dim,
            act_dim: self.act_dim,
            num_rows: self.num_rows,
            obs: FloatField { name: "obs", le_name: "obs_f32le", packed: &self.obs, le: &self.obs_f32le },
            action: FloatField { name: "action", le_name: "action_f32le", packed: &self.action, le: &self.action_f32le },
            reward: FloatField { name: "reward", le_name: "reward_f32le", packed: &self.reward, le: &self.reward_f32le },
            next_obs: FloatField { name: "next_obs", le_name: "next_obs_f32le", packed: &self.next_obs, le: &self.next_obs_f32le },
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
    pub fn validate(&self, expected_obs_dim: usize, expected_act_dim: usize, max_rows: usize) -> Result<usize, ProtoError> {
        check_protocol_version(self.protocol_version)?;
        check_actor_id(&self.actor_id)?;
        if self.sequence == 0 {
            return Err(ProtoError::InvalidField { field: "sequence", reason: "is 0; sequences start at 1".to_owned() });
        }
        self.columns().check("TransitionBatch", expected_obs_dim, expected_act_dim, max_rows)
    }

    /// Row `i`, borrowing from the batch; `None` if `i >= num_rows` or the batch is
    /// malformed at that row. Call [`TransitionBatch::validate`] first on received batches.
    ///
    /// Rows borrow `&[f32]` from packed float columns, so a batch whose float columns travel
    /// as bytes has no rows here: convert it with
    /// `convert_float_columns(FloatEncoding::Packed)` first, or read the columns
    /// (`obs_column()`, ...).
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
            obs: FloatField { name: "obs", le_name: "obs_f32le", packed: &self.obs, le: &self.obs_f32le },
            action: FloatField { name: "action", le_name: "action_f32le", packed: &self.action, le: &self.action_f32le },
            reward: FloatField { name: "reward", le_name: "reward_f32le", packed: &self.reward, le: &self.reward_f32le },
            next_obs: FloatField { name: "next_obs", le_name: "next_obs_f32le", packed: &self.next_obs, le: &self.next_obs_f32le },
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
    pub fn validate(&self, expected_obs_dim: usize, expected_act_dim: usize, max_rows: usize) -> Result<usize, ProtoError> {
        check_protocol_version(self.protocol_version)?;
        let rows = self.columns().check("SampledBatch", expected_obs_dim, expected_act_dim, max_rows)?;
        if self.table_size == 0 {
            return Err(ProtoError::InvalidField { field: "table_size", reason: "is 0 although rows were sampled".to_owned() });
        }
        let rows_u64 = rows as u64;
        check_len("keys", self.keys.len(), rows_u64)?;
        check_len("probabilities", self.probabilities.len(), rows_u64)?;
        check_len("importance_weights", self.importance_weights.len(), rows_u64)?;
        for (row, &p) in self.probabilities.iter().enumerate() {
            // NaN fails this comparison too.
            if !(p > 0.0 && p <= 1.0) {
                return Err(ProtoError::OutOfRange { column: "probabilities", row, value: p, expected: "in (0, 1]" });
            }
        }
        for (row, &w) in self.importance_weights.iter().enumerate() {
            if !(w.is_finite() && w > 0.0) {
                return Err(ProtoError::OutOfRange { column: "importance_weights", row, value: f64::from(w), expected: "finite and > 0" });
            }
        }
        Ok(rows)
    }

    /// Row `i`, borrowing from the minibatch; `None` if `i >= num_rows` or the minibatch is
    /// malformed at that row. Keys and weights are `keys[i]`, `importance_weights[i]`.
    /// Packed float columns only, as [`TransitionBatch::row`].
    pub fn row(&self, i: usize) -> Option<Transition<'_>> {
        self.columns().row(i)
    }

    /// All rows in order; stops at the first malformed row of an unvalidated minibatch.
    pub fn iter_rows(&self) -> impl Iterator<Item = Transition<'_>> + '_ {
        let columns = self.columns();
        (0..self.num_rows as usize).map_while(move |i| columns.row(i))
    }
}

/// Column accessors and encoding conversion shared by both batch messages.
macro_rules! float_column_accessors {
    ($ty:ident) => {
        impl $ty {
            /// Observations s_t (row-major, `num_rows * obs_dim`), in whichever encoding
            /// carries them: `obs_f32le` when set, else `obs`.
            pub fn obs_column(&self) -> FloatColumn<'_> {
                FloatColumn::of(&self.obs, &self.obs_f32le)
            }

            /// Actions a_t (row-major, `num_rows * act_dim`): `action_f32le` when set, else
            /// `action`.
            pub fn action_column(&self) -> FloatColumn<'_> {
                FloatColumn::of(&self.action, &self.action_f32le)
            }

            /// Rewards (`num_rows`): `reward_f32le` when set, else `reward`.
            pub fn reward_column(&self) -> FloatColumn<'_> {
                FloatColumn::of(&self.reward, &self.reward_f32le)
            }

            /// Next observations s_{t+1} (row-major, `num_rows * obs_dim`):
            /// `next_obs_f32le` when set, else `next_obs`.
            pub fn next_obs_column(&self) -> FloatColumn<'_> {
                FloatColumn::of(&self.next_obs, &self.next_obs_f32le)
            }

            /// The observations as floats: borrowed when packed (or aligned bytes), else
            /// copied once. See [`FloatColumn::to_cow`].
            pub fn obs_values(&self) -> Cow<'_, [f32]> {
                self.obs_column().to_cow()
            }

            /// The actions as floats (borrowed or copied, as [`Self::obs_values`]).
            pub fn action_values(&self) -> Cow<'_, [f32]> {
                self.action_column().to_cow()
            }

            /// The rewards as floats (borrowed or copied, as [`Self::obs_values`]).
            pub fn reward_values(&self) -> Cow<'_, [f32]> {
                self.reward_column().to_cow()
            }

            /// The next observations as floats (borrowed or copied, as [`Self::obs_values`]).
            pub fn next_obs_values(&self) -> Cow<'_, [f32]> {
                self.next_obs_column().to_cow()
            }

            /// Moves every float column into the encoding `to` (one copy per column that
            /// changes). A column set in both encodings, which `validate` rejects, is left
            /// as it is. Use `FloatEncoding::Packed` before reading the fields `obs`, ...
            /// directly or through `row`, and `FloatEncoding::F32Le` before sending a wide
            /// batch to a receiver that decodes packed floats value by value.
            pub fn convert_float_columns(&mut self, to: FloatEncoding) {
                convert_column(&mut self.obs, &mut self.obs_f32le, to);
                convert_column(&mut self.action, &mut self.action_f32le, to);
                convert_column(&mut self.reward, &mut self.reward_f32le, to);
                convert_column(&mut self.next_obs, &mut self.next_obs_f32le, to);
            }

            /// The float columns' (tag of the `_f32le` field, packed floats, bytes).
            fn float_fields(&self) -> FloatFields<'_> {
                [
                    (Self::OBS_F32LE_TAG, &self.obs[..], &self.obs_f32le[..]),
                    (Self::OBS_F32LE_TAG + 1, &self.action[..], &self.action_f32le[..]),
                    (Self::OBS_F32LE_TAG + 2, &self.reward[..], &self.reward_f32le[..]),
                    (Self::OBS_F32LE_TAG + 3, &self.next_obs[..], &self.next_obs_f32le[..]),
                ]
            }

            /// Appends the message's protobuf encoding with every float column in the F32Le
            /// encoding (`bytes *_f32le` fields), whichever encoding it holds them in: what
            /// `convert_float_columns(FloatEncoding::F32Le)` followed by `encode` would
            /// write, without converting. Packed columns cost one `memcpy` each instead of
            /// an encode loop, and the receiver decodes them with one copy (or none).
            pub fn encode_f32le(&self, out: &mut Vec<u8>) {
                encode_with_f32le_fields(&self.without_packed_floats(), self.float_fields(), out);
            }

            /// Bytes [`Self::encode_f32le`] appends.
            pub fn encoded_len_f32le(&self) -> usize {
                encoded_len_with_f32le_fields(&self.without_packed_floats(), self.float_fields())
            }
        }
    };
}

float_column_accessors!(TransitionBatch);
float_column_accessors!(SampledBatch);

impl TransitionBatch {
    /// Field number of `obs_f32le`; action, reward and next_obs follow it (transition.proto).
    const OBS_F32LE_TAG: u32 = 16;

    /// The message without its packed float columns (those set in both encodings kept, for
    /// the receiver to reject), and without the `_f32le` fields, which `encode_f32le` writes
    /// itself. Every field is listed, so a field added to the message fails to compile here
    /// instead of being dropped from `encode_f32le`.
    fn without_packed_floats(&self) -> TransitionBatch {
        let keep = |packed: &Vec<f32>, le: &Bytes| if le.is_empty() { Vec::new() } else { packed.clone() };
        TransitionBatch {
            protocol_version: self.protocol_version,
            actor_id: self.actor_id.clone(),
            sequence: self.sequence,
            obs_dim: self.obs_dim,
            act_dim: self.act_dim,
            num_rows: self.num_rows,
            obs: keep(&self.obs, &self.obs_f32le),
            action: keep(&self.action, &self.action_f32le),
            reward: keep(&self.reward, &self.reward_f32le),
            next_obs: keep(&self.next_obs, &self.next_obs_f32le),
            terminal: self.terminal.clone(),
            truncated: self.truncated.clone(),
            episode_id: self.episode_id.clone(),
            step: self.step.clone(),
            policy_version: self.policy_version.clone(),
            obs_f32le: Bytes::new(),
            action_f32le: Bytes::new(),
            reward_f32le: Bytes::new(),
            next_obs_f32le: Bytes::new(),
        }
    }
}

impl SampledBatch {
    /// Field number of `obs_f32le`; action, reward and next_obs follow it (replay.proto).
    const OBS_F32LE_TAG: u32 = 19;

    /// As [`TransitionBatch`]'s: every field listed, packed floats and `_f32le` left out.
    fn without_packed_floats(&self) -> SampledBatch {
        let keep = |packed: &Vec<f32>, le: &Bytes| if le.is_empty() { Vec::new() } else { packed.clone() };
        SampledBatch {
            protocol_version: self.protocol_version,
            table: self.table.clone(),
            obs_dim: self.obs_dim,
            act_dim: self.act_dim,
            num_rows: self.num_rows,
            table_size: self.table_size,
            keys: self.keys.clone(),
            probabilities: self.probabilities.clone(),
            importance_weights: self.importance_weights.clone(),
            obs: keep(&self.obs, &self.obs_f32le),
            action: keep(&self.action, &self.action_f32le),
            reward: keep(&self.reward, &self.reward_f32le),
            next_obs: keep(&self.next_obs, &self.next_obs_f32le),
            terminal: self.terminal.clone(),
            truncated: self.truncated.clone(),
            episode_id: self.episode_id.clone(),
            step: self.step.clone(),
            policy_version: self.policy_version.clone(),
            obs_f32le: Bytes::new(),
            action_f32le: Bytes::new(),
            reward_f32le: Bytes::new(),
            next_obs_f32le: Bytes::new(),
        }
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
            return Err(ProtoError::TooManyRows { rows: u64::from(u32::MAX) + 1, max: u64::from(u32::MAX) });
        }
        let obs_dim = self.batch.obs_dim as usize;
        let act_dim = self.batch.act_dim as usize;
        check_len("obs", t.obs.len(), obs_dim as u64)?;
        check_len("action", t.action.len(), act_dim as u64)?;
        check_len("next_obs", t.next_obs.len(), obs_dim as u64)?;
        for (column, values) in [("obs", t.obs), ("action", t.action), ("reward", std::slice::from_ref(&t.reward)), ("next_obs", t.next_obs)] {
            if let Some(element) = values.iter().position(|v| !v.is_finite()) {
                return Err(ProtoError::NonFinite { column, row, element, value: f64::from(values[element]) });
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
        TransitionBatch { protocol_version: ProtocolVersion::V1 as i32, actor_id: actor_id.into(), sequence, ..self.batch }
    }
}
