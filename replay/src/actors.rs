//! What the replay keeps per actor: the de-duplication watermark and the counts server info
//! and `/metrics` report. The table updates it; snapshots persist it.

use serde::{Deserialize, Serialize};

/// Per-actor bookkeeping: de-duplication and what server info reports.
#[derive(Clone, Debug, Default, PartialEq, Serialize, Deserialize)]
#[serde(default)]
pub struct ActorStats {
    /// Highest sequence stored; batches at or below it are duplicates.
    pub last_sequence: u64,
    pub batches: u64,
    pub rows: u64,
    pub duplicate_batches: u64,
    pub rejected_batches: u64,
    pub last_rejection: String,
    pub last_policy_version: u64,
    pub last_insert_unix_ms: u64,
}
