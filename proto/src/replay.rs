//! Checks on the replay requests that are not transition batches.

use crate::MAX_ACTOR_NAME_BYTES;
use crate::check_protocol_version;
use crate::error::ProtoError;
use crate::transition::check_len;
use crate::v1::{PriorityUpdate, RegisterActorRequest, SampleRequest};

impl SampleRequest {
    /// Checks a request that opens a Sample stream: protocol version, `batch_size` in
    /// `1..=max_rows`, `importance_beta` unset or in [0, 1]. `table`, `prefetch` (clamped, never
    /// rejected), `timeout_ms` and `max_batches` need the server's configuration and are left
    /// to it. Returns `batch_size`.
    pub fn validate(&self, max_rows: usize) -> Result<usize, ProtoError> {
        check_protocol_version(self.protocol_version)?;
        if self.batch_size == 0 {
            return Err(ProtoError::InvalidField { field: "batch_size", reason: "is 0".to_owned() });
        }
        if u64::from(self.batch_size) > max_rows as u64 {
            return Err(ProtoError::InvalidField { field: "batch_size", reason: format!("is {}, the limit is {max_rows}", self.batch_size) });
        }
        // NaN fails the range test too. Unset: the table's own beta.
        if let Some(beta) = self.importance_beta
            && !(0.0..=1.0).contains(&beta)
        {
            return Err(ProtoError::InvalidField { field: "importance_beta", reason: format!("is {beta}, must be in [0, 1]") });
        }
        Ok(self.batch_size as usize)
    }
}

impl PriorityUpdate {
    /// Checks an update before it touches the sum tree: protocol version, at most
    /// `max_keys` keys, one priority per key, every priority finite and >= 0.
    /// Returns the number of keys (0 is allowed: an empty update changes nothing).
    pub fn validate(&self, max_keys: usize) -> Result<usize, ProtoError> {
        check_protocol_version(self.protocol_version)?;
        let keys = self.keys.len();
        if keys > max_keys {
            return Err(ProtoError::TooManyRows { rows: keys as u64, max: max_keys as u64 });
        }
        check_len("priorities", self.priorities.len(), keys as u64)?;
        for (row, &p) in self.priorities.iter().enumerate() {
            if !p.is_finite() {
                return Err(ProtoError::NonFinite { column: "priorities", row, element: 0, value: p });
            }
            if p < 0.0 {
                return Err(ProtoError::OutOfRange { column: "priorities", row, value: p, expected: ">= 0" });
            }
        }
        Ok(keys)
    }
}

impl RegisterActorRequest {
    /// Checks a registration: protocol version, and a `name` of 1 to
    /// [`MAX_ACTOR_NAME_BYTES`] bytes without control characters (it is a key in the
    /// server's slot file and appears in its logs). Returns the name.
    pub fn validate(&self) -> Result<&str, ProtoError> {
        check_protocol_version(self.protocol_version)?;
        check_actor_name(&self.name)?;
        Ok(&self.name)
    }
}

/// The rule on actor names (see [`RegisterActorRequest::validate`]), for servers that read
/// names from elsewhere (the replay's slot file) and clients that check before dialling.
pub fn check_actor_name(name: &str) -> Result<(), ProtoError> {
    if name.is_empty() {
        return Err(ProtoError::InvalidField { field: "name", reason: "is empty".to_owned() });
    }
    if name.len() > MAX_ACTOR_NAME_BYTES {
        return Err(ProtoError::InvalidField { field: "name", reason: format!("is {} bytes long, the limit is {MAX_ACTOR_NAME_BYTES}", name.len()) });
    }
    if let Some(c) = name.chars().find(|c| c.is_control()) {
        return Err(ProtoError::InvalidField { field: "name", reason: format!("contains the control character {c:?}") });
    }
    Ok(())
}
