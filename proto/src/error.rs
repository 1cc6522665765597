//! Why a message from a peer was refused, and which gRPC status says so.

use crate::PROTOCOL_VERSION;

/// A message breaks the wire contract.
///
/// Every variant names what is wrong precisely enough to fix the sender (the column, the row,
/// the element), because the message text travels back to the peer inside the gRPC status.
/// [`ProtoError::to_status`] gives the status code:
///
/// | variant                        | gRPC code           |
/// |--------------------------------|---------------------|
/// | `UnsupportedProtocolVersion`   | FAILED_PRECONDITION |
/// | `TooManyRows`                  | RESOURCE_EXHAUSTED  |
/// | every other variant            | INVALID_ARGUMENT    |
#[derive(Debug, Clone, PartialEq, thiserror::Error)]
#[non_exhaustive]
pub enum ProtoError {
    /// `protocol_version` is not one this crate speaks (0 means the field was never set).
    #[error("unsupported protocol_version {got}: this peer speaks only {PROTOCOL_VERSION} (mapless.v1)")]
    UnsupportedProtocolVersion {
        /// The raw value received.
        got: i32,
    },

    /// A dimension field differs from what the receiver was configured with.
    #[error("{field} is {got}, expected {expected}")]
    DimensionMismatch {
        /// `obs_dim` or `act_dim`.
        field: &'static str,
        /// What the receiver expects.
        expected: u64,
        /// What the message says.
        got: u64,
    },

    /// A batch with no rows.
    #[error("{message} has num_rows = 0; an empty batch carries nothing")]
    Empty {
        /// Message type, e.g. `TransitionBatch`.
        message: &'static str,
    },

    /// More rows than the receiver accepts in one message.
    #[error("{rows} rows in one message, the limit is {max}; send smaller batches")]
    TooManyRows {
        /// Rows in the message.
        rows: u64,
        /// The receiver's limit.
        max: u64,
    },

    /// A column (repeated field) has a length other than its rows and dimensions imply.
    #[error("column `{column}` has {got} values, expected {expected}")]
    ColumnLength {
        /// Field name, e.g. `next_obs`.
        column: &'static str,
        /// Required length, e.g. `num_rows * obs_dim`.
        expected: u64,
        /// Actual length.
        got: u64,
    },

    /// A float that must be finite is NaN or infinite.
    #[error("column `{column}` row {row} element {element} is {value}; values must be finite")]
    NonFinite {
        /// Field name, e.g. `reward`.
        column: &'static str,
        /// 0-based row.
        row: usize,
        /// 0-based position within the row's vector (0 for scalar columns).
        element: usize,
        /// The offending value (widened to f64).
        value: f64,
    },

    /// A value is outside its documented range (e.g. a negative priority).
    #[error("column `{column}` row {row} is {value}, expected {expected}")]
    OutOfRange {
        /// Field name, e.g. `priorities`.
        column: &'static str,
        /// 0-based row.
        row: usize,
        /// The offending value (widened to f64).
        value: f64,
        /// The allowed range, in words.
        expected: &'static str,
    },

    /// Both `terminal` and `truncated` are set on one row; an episode ends for one reason.
    #[error(
        "row {row} has both terminal and truncated set; a collision on the last step is \
         terminal only"
    )]
    TerminalAndTruncated {
        /// 0-based row.
        row: usize,
    },

    /// An episode record with neither `terminal` nor `truncated` set.
    #[error("episode {episode_id} has neither terminal nor truncated set; it has not ended")]
    EpisodeNotEnded {
        /// The record's episode id.
        episode_id: u64,
    },

    /// A scalar field breaks its documented rule (empty id, zero sequence, ...).
    #[error("field `{field}` {reason}")]
    InvalidField {
        /// Field name.
        field: &'static str,
        /// What is wrong, completing "field `x` ...".
        reason: String,
    },

    /// A tensor's data, shape or dtype are inconsistent, or not what the reader supports.
    #[error("tensor `{name}`: {reason}")]
    InvalidTensor {
        /// The tensor's name.
        name: String,
        /// What is wrong.
        reason: String,
    },
}

impl ProtoError {
    /// The gRPC status a server answers with; the message is this error's text.
    ///
    /// Unknown protocol versions are FAILED_PRECONDITION (the peer must be upgraded, retrying
    /// cannot help), oversized batches RESOURCE_EXHAUSTED (the same data fits in smaller
    /// batches), everything else INVALID_ARGUMENT (the message itself is malformed).
    pub fn to_status(&self) -> tonic::Status {
        let message = self.to_string();
        match self {
            Self::UnsupportedProtocolVersion { .. } => tonic::Status::failed_precondition(message),
            Self::TooManyRows { .. } => tonic::Status::resource_exhausted(message),
            Self::DimensionMismatch { .. }
            | Self::Empty { .. }
            | Self::ColumnLength { .. }
            | Self::NonFinite { .. }
            | Self::OutOfRange { .. }
            | Self::TerminalAndTruncated { .. }
            | Self::EpisodeNotEnded { .. }
            | Self::InvalidField { .. }
            | Self::InvalidTensor { .. } => tonic::Status::invalid_argument(message),
        }
    }
}

impl From<ProtoError> for tonic::Status {
    fn from(error: ProtoError) -> Self {
        error.to_status()
    }
}
