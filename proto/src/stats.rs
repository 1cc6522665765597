//! Checks on per-episode statistics records.

use crate::error::ProtoError;
use crate::v1::EpisodeStats;
use crate::{MAX_ACTOR_ID_BYTES, check_protocol_version};

impl EpisodeStats {
    /// Checks a received record: protocol version, `actor_id` non-empty and at most
    /// [`MAX_ACTOR_ID_BYTES`], `episode_id` >= 1, exactly one of `terminal` / `truncated`,
    /// and every float finite (`distance_m` and `shaded_time_s` also >= 0).
    pub fn validate(&self) -> Result<(), ProtoError> {
        check_protocol_version(self.protocol_version)?;
        if self.actor_id.is_empty() || self.actor_id.len() > MAX_ACTOR_ID_BYTES {
            return Err(ProtoError::InvalidField { field: "actor_id", reason: format!("is {} bytes long, must be 1..={MAX_ACTOR_ID_BYTES}", self.actor_id.len()) });
        }
        if self.episode_id == 0 {
            return Err(ProtoError::InvalidField { field: "episode_id", reason: "is 0; episodes are numbered from 1".to_owned() });
        }
        match (self.terminal, self.truncated) {
            (true, false) | (false, true) => {}
            (true, true) => return Err(ProtoError::TerminalAndTruncated { row: 0 }),
            (false, false) => {
                return Err(ProtoError::EpisodeNotEnded { episode_id: self.episode_id });
            }
        }
        for (column, value, non_negative) in
            [("episode_return", self.episode_return, false), ("eqs", self.eqs, true), ("ees", self.ees, true), ("distance_m", self.distance_m, true), ("shaded_time_s", self.shaded_time_s, true)]
        {
            if !value.is_finite() {
                return Err(ProtoError::NonFinite { column, row: 0, element: 0, value });
            }
            if non_negative && value < 0.0 {
                return Err(ProtoError::OutOfRange { column, row: 0, value, expected: ">= 0" });
            }
        }
        Ok(())
    }
}
