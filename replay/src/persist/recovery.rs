//! Recovery: a new table rebuilt from what a directory holds — the newest usable snapshot,
//! then the write-ahead log — through the table's restore seam (`Table::restore`).
//!
//! ```text
//!   newest usable snapshot ──► replay log: LSN ≤ snapshot: row data only
//!                                          LSN > snapshot: inserts, de-dup marks,
//!                                                          priorities, counters
//!   stop at the first torn/corrupt record, move what follows to wal/corrupt/
//! ```
//!
//! A snapshot is passed over (and renamed, never read again) when it is corrupt or covers
//! records the log no longer holds; one before a gap in the log is passed over too. A snapshot
//! and a log that disagree about keys, or files written by a table of another shape, stop
//! recovery with an error that says what to move away: nothing on disk is cut for those.

use std::path::{Path, PathBuf};
use std::time::{Duration, Instant};

use mapless_proto::v1::TransitionBatch;
use prost::Message;

use crate::config::PersistenceConfig;
use crate::error::ReplayError;
use crate::snapshot::{SnapshotData, SnapshotStore};
use crate::table::{Table, TableCheckpoint};
use crate::wal::{self, StorageFault, Wal};

/// What [`DurableTable::open`](super::DurableTable::open) found on disk and did about it.
#[derive(Clone, Debug, Default)]
pub struct RecoveryReport {
    /// The snapshot recovery started from; `None` means the log alone (or an empty directory).
    pub snapshot: Option<PathBuf>,
    /// The last log record that snapshot covers.
    pub snapshot_lsn: u64,
    /// Snapshots passed over, newest first, and why. Corrupt ones, and ones covering records the
    /// log no longer holds, are renamed (`*.corrupt.<ms>`, `*.ahead.<ms>`) and never read again.
    pub skipped_snapshots: Vec<StorageFault>,
    /// Log segments read.
    pub segments: usize,
    /// Valid log records read (before and after the snapshot).
    pub records_replayed: u64,
    /// Of those, records newer than the snapshot, re-applied in full.
    pub records_after_snapshot: u64,
    /// Rows stored after recovery.
    pub rows: u64,
    /// Rows ever inserted (the next key).
    pub next_key: u64,
    /// LSN of the last valid record; new records continue from it.
    pub last_lsn: u64,
    /// The first torn or corrupt spot in the log: the file, the byte offset and why. Nothing
    /// from it on was restored; those bytes (and any later segments) are in `wal/corrupt/`.
    pub fault: Option<StorageFault>,
    /// Rows a snapshot listed as stored whose data the log no longer held (dropped).
    pub rows_lost: u64,
    /// Anything else a person should know (e.g. the sampler changed).
    pub warnings: Vec<String>,
    pub elapsed: Duration,
}

/// A snapshot as the table's checkpoint value.
fn checkpoint_of(snap: SnapshotData) -> TableCheckpoint {
    let m = snap.meta;
    TableCheckpoint {
        journal_position: m.lsn,
        next_key: m.next_key,
        size: m.size,
        max_weight: m.max_weight,
        inserts: m.inserts,
        samples: m.samples,
        actors: m.actors,
        sampler_rng: m.sampler_rng,
        weights: snap.weights,
        live: snap.live,
        times_sampled: snap.times_sampled,
    }
}

/// Rebuilds `table` (new and empty) from the newest usable snapshot and the log in `wal_dir`;
/// returns it with the log reopened for appending after the last valid record.
///
/// A record that passes its checksum but will not replay (it does not decode, or its keys do
/// not follow on) cuts the log there; when that cut falls before the chosen snapshot's LSN, the
/// snapshot covers records the log no longer holds, so it is set aside ("ahead", as the scan
/// would have) and recovery starts over on `fresh()` without it. Otherwise the reopened log
/// would hand out again LSNs the snapshot claims to cover, and the next recovery would pass
/// the snapshot over (or find it disagreeing with the new records) and restore another table.
pub(crate) fn recover(table: Table, fresh: impl Fn() -> Result<Table, ReplayError>, store: &SnapshotStore, wal_dir: &Path, p: &PersistenceConfig) -> Result<(Table, Wal, RecoveryReport), ReplayError> {
    let t0 = Instant::now();
    let mut skipped = Vec::new();
    let mut table = table;
    loop {
        // Each retry has set one more snapshot aside, so this ends.
        if let Some((wal, mut report)) = recover_once(&table, store, wal_dir, p, &mut skipped)? {
            report.elapsed = t0.elapsed();
            // A snapshot passed over without being renamed (before a gap) is listed once.
            let mut seen = std::collections::HashSet::new();
            report.skipped_snapshots.retain(|f| seen.insert(f.path.clone()));
            return Ok((table, wal, report));
        }
        table = fresh()?;
    }
}

/// One attempt of [`recover`]: `None` when the chosen snapshot turned out to lie past the end
/// of the replayable log (then set aside and added to `skipped`, which carries the snapshots
/// passed over into the next attempt's report).
fn recover_once(table: &Table, store: &SnapshotStore, wal_dir: &Path, p: &PersistenceConfig, skipped: &mut Vec<StorageFault>) -> Result<Option<(Wal, RecoveryReport)>, ReplayError> {
    let t0 = Instant::now();
    let cfg = table.config();
    let (cap, d, a) = (cfg.capacity, cfg.obs_dim, cfg.act_dim);
    let mut report = RecoveryReport { skipped_snapshots: std::mem::take(skipped), ..RecoveryReport::default() };
    let carried = report.skipped_snapshots.len();
    let mut scan = wal::scan(wal_dir)?;
    let (log_start, log_end) = (scan.start_lsn(), scan.end_lsn());

    // The newest snapshot that checks out and that the log can continue: not past the
    // log's end (records it covers were lost) and not before a gap in the log.
    let mut base: Option<(PathBuf, SnapshotData)> = None;
    for (lsn, path) in store.list()?.into_iter().rev() {
        let unusable = |reason: String| StorageFault { path: path.clone(), offset: 0, reason };
        if let Some(end) = log_end.filter(|&end| lsn > end) {
            report.skipped_snapshots.push(unusable(format!("covers the log up to LSN {lsn} but its valid records end at {end}")));
            store.set_aside(&path, "ahead")?;
            continue;
        }
        if let Some(start) = log_start.filter(|&start| start > lsn + 1) {
            report.skipped_snapshots.push(unusable(format!("the log now starts at LSN {start}, records {} onwards are gone", lsn + 1)));
            continue;
        }
        match SnapshotStore::load(&path) {
            Err(reason) => {
                report.skipped_snapshots.push(unusable(format!("corrupt: {reason}")));
                store.set_aside(&path, "corrupt")?;
            }
            Ok(snap) => {
                let m = &snap.meta;
                if (m.capacity, m.obs_dim, m.act_dim) != (cap as u64, d as u64, a as u64) {
                    return Err(ReplayError::InvalidConfig(format!(
                        "{} was written by a table of capacity {}, obs_dim {}, act_dim {}; this one has {cap}, {d}, {a}. Use the same shape or move the directory away",
                        path.display(),
                        m.capacity,
                        m.obs_dim,
                        m.act_dim
                    )));
                }
                base = Some((path, snap));
                break;
            }
        }
    }
    for f in &report.skipped_snapshots[carried..] {
        tracing::warn!(table = %cfg.name, file = %f.path.display(), reason = %f.reason, "snapshot skipped");
    }

    let mut restore = table.restore();
    let mut snap_lsn = 0;
    let snapshot_path = base.as_ref().map(|(p, _)| p.clone());
    if let Some((path, snap)) = base {
        let same_sampler = snap.meta.sampler == cfg.sampler;
        if !same_sampler {
            report.warnings.push(format!("sampler changed since {} was written: stored priorities reset to 1", path.display()));
        }
        snap_lsn = snap.meta.lsn;
        restore.load(checkpoint_of(snap), same_sampler);
        report.snapshot = Some(path);
        report.snapshot_lsn = snap_lsn;
    } else if let Some(start) = log_start.filter(|&start| start > 1) {
        report.warnings.push(format!("no usable snapshot and the log starts at LSN {start}: de-duplication marks and counters from before it are lost"));
    }

    let mut expected_key: Option<u64> = None;
    let mut after_snapshot = 0u64;
    let mut inserts_applied = 0u64;
    let mismatch = |path: Option<&PathBuf>, what: String| ReplayError::Storage {
        path: path.cloned().unwrap_or_else(|| wal_dir.to_path_buf()),
        problem: format!("snapshot and log disagree: {what}; move the snapshot aside to recover from the log alone"),
    };
    let replayed = wal::replay(&mut scan, |rec| match rec.kind {
        wal::KIND_INSERT => {
            let (first_key, unix_ms, bytes) = wal::split_insert_payload(rec.payload).map_err(Ok)?;
            let batch = TransitionBatch::decode(bytes).map_err(|e| Ok(format!("corrupt: logged batch does not decode: {e}")))?;
            if (batch.obs_dim as usize, batch.act_dim as usize) != (d, a) {
                return Err(Err(ReplayError::InvalidConfig(format!(
                    "the log in {} holds rows of obs_dim {}, act_dim {}; this table has {d}, {a}. Use the same dims or move the directory away",
                    wal_dir.display(),
                    batch.obs_dim,
                    batch.act_dim
                ))));
            }
            let rows = batch.validate(d, a, usize::MAX).map_err(|e| Ok(format!("corrupt: logged batch is invalid: {e}")))?;
            let key_end = first_key.checked_add(rows as u64).ok_or_else(|| Ok(format!("corrupt: first key {first_key} overflows")))?;
            if let Some(k) = expected_key.filter(|&k| k != first_key) {
                return Err(Ok(format!("corrupt: rows start at key {first_key}, {k} expected")));
            }
            expected_key = Some(key_end);
            if rec.lsn <= snap_lsn {
                // The snapshot already counts these rows; only their data lives here.
                if key_end > restore.next_key() {
                    return Err(Err(mismatch(snapshot_path.as_ref(), format!("LSN {} holds keys up to {key_end}, the snapshot's next key is {}", rec.lsn, restore.next_key()))));
                }
                restore.fill_rows(first_key, &batch, rows);
            } else {
                if restore.next_key() != first_key {
                    if snapshot_path.is_none() && inserts_applied == 0 {
                        restore.start_at_key(first_key); // the log's history before its start is gone (warned above)
                    } else {
                        return Err(Err(mismatch(snapshot_path.as_ref(), format!("LSN {} inserts at key {first_key}, the table is at {}", rec.lsn, restore.next_key()))));
                    }
                }
                restore.insert(&batch, rows, unix_ms);
                after_snapshot += 1;
                inserts_applied += 1;
            }
            Ok(Some(key_end))
        }
        wal::KIND_PRIORITIES => {
            let pairs = wal::parse_priorities_payload(rec.payload).map_err(Ok)?;
            if rec.lsn > snap_lsn {
                restore.priorities(&pairs);
                after_snapshot += 1;
            }
            Ok(None)
        }
        kind => Err(Ok(format!("corrupt: unknown record kind {kind}"))),
    })?;

    // A record at or below the snapshot's LSN would not replay: the log now ends before what
    // the snapshot covers. Set the snapshot aside and start over without it (see `recover`).
    let replay_end = scan.end_lsn().unwrap_or(0);
    if let Some(path) = snapshot_path.as_ref().filter(|_| scan.fault.is_some() && replay_end < snap_lsn) {
        drop(restore);
        let why = scan.fault.as_ref().map(|f| f.to_string()).unwrap_or_default();
        let fault = StorageFault { path: path.clone(), offset: 0, reason: format!("covers the log up to LSN {snap_lsn} but its replayable records end at {replay_end} ({why})") };
        tracing::warn!(table = %cfg.name, file = %path.display(), reason = %fault.reason, "snapshot set aside; recovering again without it");
        report.skipped_snapshots.push(fault);
        store.set_aside(path, "ahead")?;
        *skipped = report.skipped_snapshots;
        return Ok(None);
    }

    // A live row whose data the log no longer holds cannot be served: finish drops it, loudly.
    let restored = restore.finish();
    let end = scan.end_lsn().unwrap_or(0).max(snap_lsn);
    let wal = Wal::reopen(&scan, p.fsync, p.segment_bytes, end + 1, restored.next_key)?;
    report.segments = scan.segments.iter().filter(|g| g.valid_len > 0).count();
    report.records_replayed = replayed;
    report.records_after_snapshot = after_snapshot;
    report.rows = restored.rows;
    report.next_key = restored.next_key;
    report.last_lsn = wal.last_lsn();
    report.fault = scan.fault.clone();
    report.rows_lost = restored.rows_lost;
    if restored.rows_lost > 0 {
        report.warnings.push(format!("{} rows the snapshot lists as stored are missing from the log and were dropped", restored.rows_lost));
    }
    if let Some(f) = &report.fault {
        tracing::warn!(table = %cfg.name, file = %f.path.display(), offset = f.offset, reason = %f.reason, records_restored = replayed, "log cut at a torn or corrupt record; everything before it restored, the rest moved to wal/corrupt/");
    }
    for w in &report.warnings {
        tracing::warn!(table = %cfg.name, "{w}");
    }
    report.elapsed = t0.elapsed();
    tracing::info!(table = %cfg.name, rows = report.rows, records = replayed, after_snapshot, snapshot_lsn = snap_lsn, ms = report.elapsed.as_millis() as u64, "table restored");
    Ok(Some((wal, report)))
}
