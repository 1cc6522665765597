//! A durable table: a [`Table`] with a write-ahead log as its journal, snapshots of its
//! checkpoints, and recovery from both. Persistence depends on the table, never the reverse:
//! the table offers a [`Journal`] hook, a checkpoint value and a restore; this module wires
//! them to `wal.rs` and `snapshot.rs` (as Reverb's checkpointer drives `Table::Checkpoint`).
//!
//! ```text
//!   DurableTable::open ─► recovery.rs (snapshot + log ─► Table::restore)
//!                      ─► Table::set_journal(WalJournal)   inserts / priorities ─► wal.rs
//!                      ─► threads: snapshot-<table>   Table::checkpoint_into ─► snapshot.rs
//!                                  wal-flush-<table>  fsync on FsyncPolicy::IntervalMs
//! ```
//!
//! Write-ahead: the table hands every accepted insert and priority update to the journal
//! under its lock, before it changes anything, so log order is apply order and an acknowledged
//! change is in the log. A snapshot copies the checkpoint under the table lock (O(capacity)
//! memcpy into kept buffers, a few ms at 1M rows) with the log position it is consistent
//! with, then, without the lock, fsyncs the log up to there, writes the file, prunes old
//! snapshots and deletes log segments no recovery can need. Lock order: table, then log.

pub(crate) mod recovery;
#[cfg(test)]
mod tests;

use std::ops::Deref;
use std::path::PathBuf;
use std::sync::atomic::{AtomicBool, Ordering};
use std::sync::{Arc, Condvar, Mutex, MutexGuard};
use std::thread::JoinHandle;
use std::time::{Duration, Instant};

pub use recovery::RecoveryReport;

use crate::clock::unix_ms;
use crate::config::{FsyncPolicy, PersistenceConfig, TableConfig};
use crate::error::ReplayError;
use crate::snapshot::{SnapshotData, SnapshotMeta, SnapshotStore};
use crate::table::{CheckpointMark, Journal, Table, TableCheckpoint};
use crate::wal::{self, Wal, WalSync};

/// Snapshots kept on disk. The log is kept back to the oldest, so a damaged newest snapshot
/// falls back to the previous one without losing anything.
const SNAPSHOTS_KEPT: usize = 2;

/// A table that persists itself in a directory, or a memory-only one (no directory): opened
/// with [`DurableTable::open`], used as the [`Table`] it derefs to, shared as
/// [`DurableTable::table`]. Closing it (or dropping it) closes the table, stops the
/// background threads, writes a final snapshot and fsyncs the log.
pub struct DurableTable {
    table: Arc<Table>,
    persist: Option<Persist>,
}

/// One snapshot written by [`DurableTable::snapshot`] or the background thread.
#[derive(Clone, Debug)]
pub struct SnapshotInfo {
    pub path: PathBuf,
    /// The last log record it covers.
    pub lsn: u64,
    pub bytes: u64,
    pub rows: u64,
    /// How long the table's lock was held to copy the metadata: the longest any insert or
    /// sample waited for the snapshot.
    pub copy: Duration,
    /// Log fsync, file write, fsync and rename (no lock held).
    pub write: Duration,
    /// Log segments deleted because no recovery can need them any more.
    pub segments_deleted: usize,
}

impl DurableTable {
    /// A table that persists itself in `persistence.dir` (memory only when that is `None`):
    /// restores what the directory holds, then logs every insert and priority update and
    /// snapshots in the background. Every batch acknowledged before a crash comes back exactly
    /// once; a torn or corrupt log is cut at the first bad record, which the report names
    /// (everything before it is restored). Fails when another table holds the directory, or
    /// when the directory was written by a table of another capacity or dims.
    pub fn open(cfg: TableConfig, persistence: PersistenceConfig, seed: u64) -> Result<(DurableTable, RecoveryReport), ReplayError> {
        persistence.validate()?;
        let table = Table::new(cfg, seed)?;
        let Some(dir) = persistence.dir.clone() else {
            return Ok((DurableTable { table: Arc::new(table), persist: None }, RecoveryReport::default()));
        };
        let wal_dir = dir.join("wal");
        std::fs::create_dir_all(&wal_dir).map_err(|e| ReplayError::Storage { path: wal_dir.clone(), problem: format!("create: {e}") })?;
        let lock_file = crate::snapshot::lock_dir(&dir)?;
        let store = SnapshotStore::open(dir.join("snapshots"), SNAPSHOTS_KEPT)?;
        let cfg = table.config().clone();
        let (mut table, wal, report) = recovery::recover(table, || Table::new(cfg.clone(), seed), &store, &wal_dir, &persistence)?;
        let sync = wal.sync_handle();
        let acks_wait_for_fsync = wal.acks_wait_for_fsync();
        let journal = Arc::new(WalJournal { wal: Mutex::new(wal), sync: Arc::clone(&sync), acks_wait_for_fsync, _lock_file: lock_file });
        table.set_journal(Arc::clone(&journal) as Arc<dyn Journal>);
        let table = Arc::new(table);
        let shared =
            Arc::new(PersistShared { table: Arc::clone(&table), journal, store, sync, wal_dir, scratch: Mutex::new(SnapshotScratch::default()), stop: Mutex::new(false), stop_cv: Condvar::new() });
        let threads = match PersistShared::spawn(&shared, &persistence) {
            Ok(t) => t,
            Err((e, started)) => {
                *lock_plain(&shared.stop) = true;
                shared.stop_cv.notify_all();
                started.into_iter().for_each(|h| drop(h.join()));
                return Err(e);
            }
        };
        let persist = Persist { shared, threads: Mutex::new(threads), shut: AtomicBool::new(false) };
        Ok((DurableTable { table, persist: Some(persist) }, report))
    }

    /// The table, to share (the gRPC service, the shared-memory ingest and /metrics each hold
    /// one). It outlives this handle only closed: [`DurableTable::close`] closes it.
    pub fn table(&self) -> &Arc<Table> {
        &self.table
    }

    /// The log's fsync side (`None` for a memory-only table): its counters, and in test builds
    /// its fault seam.
    pub(crate) fn wal_sync(&self) -> Option<&Arc<WalSync>> {
        self.persist.as_ref().map(|p| &p.shared.sync)
    }

    /// Writes a snapshot now (waiting for one in progress); `None` for a memory-only table or
    /// when nothing changed since the last one. Inserts and samples wait only for the copy.
    pub fn snapshot(&self) -> Result<Option<SnapshotInfo>, ReplayError> {
        match &self.persist {
            Some(p) => p.shared.snapshot(),
            None => Ok(None),
        }
    }

    /// Closes the table (blocked callers get `Closed`, later calls fail the same way); a
    /// persistent one then stops its background threads, writes a final snapshot and fsyncs
    /// its log (problems are logged; the log alone still restores everything). Dropping it
    /// does the same.
    pub fn close(&self) {
        self.table.close();
        if let Some(p) = &self.persist {
            p.shutdown(&self.table.config().name);
        }
    }
}

impl Deref for DurableTable {
    type Target = Table;
    fn deref(&self) -> &Table {
        &self.table
    }
}

impl Drop for DurableTable {
    fn drop(&mut self) {
        if self.persist.is_some() {
            self.close();
        }
    }
}

/// The write-ahead log as the table's journal. The table calls it under its own lock; the
/// mutex here is only ever contended by a snapshot handing back obsolete segments.
struct WalJournal {
    wal: Mutex<Wal>,
    sync: Arc<WalSync>,
    /// `FsyncPolicy::Always`: [`Journal::commit`] waits for the group commit.
    acks_wait_for_fsync: bool,
    /// Held (flock) while the log is open, i.e. as long as the table or a background thread
    /// holds the journal: two writers would interleave their logs.
    _lock_file: std::fs::File,
}

impl Journal for WalJournal {
    fn insert(&self, first_key: u64, rows: u64, unix_ms: u64, batch_bytes: &[u8]) -> Result<(), ReplayError> {
        lock_plain(&self.wal).append_insert(first_key, rows, unix_ms, batch_bytes).map(drop)
    }

    fn priorities(&self, pairs: &[(u64, f64)]) -> Result<(), ReplayError> {
        lock_plain(&self.wal).append_priorities(pairs).map(drop)
    }

    fn position(&self) -> u64 {
        lock_plain(&self.wal).last_lsn()
    }

    fn commit(&self, position: u64) -> Result<(), ReplayError> {
        if self.acks_wait_for_fsync { self.sync.commit(position) } else { self.sync.check() }
    }
}

/// A persistent table's background machinery.
struct Persist {
    shared: Arc<PersistShared>,
    threads: Mutex<Vec<JoinHandle<()>>>,
    shut: AtomicBool,
}

/// What the snapshot and flush threads share with the handle.
struct PersistShared {
    table: Arc<Table>,
    journal: Arc<WalJournal>,
    store: SnapshotStore,
    sync: Arc<WalSync>,
    wal_dir: PathBuf,
    /// Also serialises snapshot writers.
    scratch: Mutex<SnapshotScratch>,
    stop: Mutex<bool>,
    stop_cv: Condvar,
}

/// The last snapshot's mark and the checkpoint buffers, kept so that the copy under the table
/// lock writes into memory already paged in (see [`Table::checkpoint_into`]).
#[derive(Default)]
struct SnapshotScratch {
    mark: Option<CheckpointMark>,
    checkpoint: TableCheckpoint,
}

fn lock_plain<T>(m: &Mutex<T>) -> MutexGuard<'_, T> {
    m.lock().unwrap_or_else(|p| p.into_inner())
}

impl PersistShared {
    /// Starts the flush and snapshot threads; on failure, the error and the threads started.
    #[allow(clippy::type_complexity)]
    fn spawn(shared: &Arc<PersistShared>, p: &PersistenceConfig) -> Result<Vec<JoinHandle<()>>, (ReplayError, Vec<JoinHandle<()>>)> {
        let mut threads = Vec::new();
        let name = &shared.table.config().name;
        let spawn_err = |e: std::io::Error| ReplayError::Storage { path: shared.wal_dir.clone(), problem: format!("start background thread: {e}") };
        if let FsyncPolicy::IntervalMs(ms) = p.fsync {
            let sh = Arc::clone(shared);
            let every = Duration::from_millis(ms);
            let started = std::thread::Builder::new().name(format!("wal-flush-{name}")).spawn(move || {
                while !sh.wait_stop(every) {
                    // A failure is logged once by WalSync and refuses appends from then on.
                    let _ = sh.sync.sync_if_dirty();
                }
            });
            match started {
                Ok(h) => threads.push(h),
                Err(e) => return Err((spawn_err(e), threads)),
            }
        }
        if p.snapshot_interval_s > 0.0 {
            let sh = Arc::clone(shared);
            let every = Duration::from_secs_f64(p.snapshot_interval_s);
            let started = std::thread::Builder::new().name(format!("snapshot-{name}")).spawn(move || {
                // A failure that repeats (a full disk, a log refusing after a failed fsync) is
                // logged when it starts and when it ends, not every interval.
                let mut failing = false;
                while !sh.wait_stop(every) {
                    match sh.snapshot_if_changed() {
                        Ok(i) => {
                            if std::mem::take(&mut failing) {
                                tracing::info!(table = %sh.table.config().name, "snapshots succeed again");
                            }
                            if let Some(i) = i {
                                tracing::debug!(table = %sh.table.config().name, lsn = i.lsn, copy_us = i.copy.as_micros() as u64, write_ms = i.write.as_millis() as u64, segments_deleted = i.segments_deleted, "snapshot written");
                            }
                        }
                        Err(e) if !failing => {
                            failing = true;
                            tracing::warn!(table = %sh.table.config().name, error = %e, "snapshot failed; the log still holds everything (retried every interval, logged again once it succeeds)");
                        }
                        Err(_) => {}
                    }
                }
            });
            match started {
                Ok(h) => threads.push(h),
                Err(e) => return Err((spawn_err(e), threads)),
            }
        }
        Ok(threads)
    }

    /// Sleeps up to `d`; true when the table is shutting down.
    fn wait_stop(&self, d: Duration) -> bool {
        let stop = lock_plain(&self.stop);
        if *stop {
            return true;
        }
        *self.stop_cv.wait_timeout(stop, d).unwrap_or_else(|p| p.into_inner()).0
    }

    fn snapshot(&self) -> Result<Option<SnapshotInfo>, ReplayError> {
        self.write_snapshot(true)
    }

    fn snapshot_if_changed(&self) -> Result<Option<SnapshotInfo>, ReplayError> {
        self.write_snapshot(false)
    }

    /// Copies the table's checkpoint under its lock, then (lock released) fsyncs the log up
    /// to the checkpoint's LSN, writes the snapshot, prunes old ones and deletes log segments
    /// that no kept snapshot needs and whose rows are all evicted.
    fn write_snapshot(&self, force: bool) -> Result<Option<SnapshotInfo>, ReplayError> {
        let mut scratch = lock_plain(&self.scratch);
        let scratch = &mut *scratch;
        let unless_at = if force { None } else { scratch.mark };
        let Some(copy) = self.table.checkpoint_into(&mut scratch.checkpoint, unless_at) else { return Ok(None) };
        let cp = &mut scratch.checkpoint;
        let mark = cp.mark();
        let cfg = self.table.config();
        // The per-slot buffers travel in the snapshot and come back to the scratch after it.
        let snap = SnapshotData {
            meta: SnapshotMeta {
                table: cfg.name.clone(),
                lsn: cp.journal_position,
                next_key: cp.next_key,
                capacity: cfg.capacity as u64,
                obs_dim: cfg.obs_dim as u64,
                act_dim: cfg.act_dim as u64,
                sampler: cfg.sampler.clone(),
                max_weight: cp.max_weight,
                inserts: cp.inserts,
                samples: cp.samples,
                size: cp.size,
                created_unix_ms: unix_ms(),
                actors: std::mem::take(&mut cp.actors),
                sampler_rng: cp.sampler_rng.clone(),
            },
            weights: std::mem::take(&mut cp.weights),
            live: std::mem::take(&mut cp.live),
            times_sampled: std::mem::take(&mut cp.times_sampled),
        };
        let write_start = Instant::now();
        let written = self.persist_snapshot(&snap);
        let rows = snap.meta.size;
        (cp.weights, cp.live, cp.times_sampled, cp.actors) = (snap.weights, snap.live, snap.times_sampled, snap.meta.actors);
        let (path, bytes, segments_deleted) = written?;
        scratch.mark = Some(mark);
        Ok(Some(SnapshotInfo { path, lsn: mark.journal_position, bytes, rows, copy, write: write_start.elapsed(), segments_deleted }))
    }

    /// The part of a snapshot done without the table lock: fsync the log up to the snapshot's
    /// LSN, write the file, prune old snapshots, delete log segments no recovery can need.
    /// Returns the path, its size and the number of segments deleted.
    fn persist_snapshot(&self, snap: &SnapshotData) -> Result<(PathBuf, u64, usize), ReplayError> {
        // Records the snapshot covers must be durable before it is, or a power loss could
        // leave a snapshot ahead of its log.
        self.sync.sync()?;
        let (path, bytes) = self.store.write(snap)?;
        let keep_from = self.store.prune()?.unwrap_or(0);
        // Rows below next_key − capacity stay evicted, so a next key read before the log's
        // lock is taken can only keep a segment one snapshot longer, never delete one early.
        let evicted_below = self.table.next_key().saturating_sub(self.table.config().capacity as u64);
        let doomed = lock_plain(&self.journal.wal).take_deletable(keep_from, evicted_below);
        let mut deleted = 0;
        for p in &doomed {
            match std::fs::remove_file(p) {
                Ok(()) => deleted += 1,
                Err(e) => tracing::warn!(table = %self.table.config().name, file = %p.display(), error = %e, "could not delete an obsolete log segment"),
            }
        }
        if let Err(e) = if deleted > 0 { wal::sync_dir(&self.wal_dir) } else { Ok(()) } {
            tracing::warn!(table = %self.table.config().name, error = %e, "fsync of the log directory failed");
        }
        Ok((path, bytes, deleted))
    }
}

impl Persist {
    /// Stops the threads, writes a final snapshot and fsyncs the log; once.
    fn shutdown(&self, name: &str) {
        if self.shut.swap(true, Ordering::SeqCst) {
            return;
        }
        *lock_plain(&self.shared.stop) = true;
        self.shared.stop_cv.notify_all();
        for h in lock_plain(&self.threads).drain(..) {
            let _ = h.join();
        }
        if let Err(e) = self.shared.snapshot_if_changed() {
            tracing::warn!(table = %name, error = %e, "final snapshot failed; the log still holds everything");
        }
        if let Err(e) = self.shared.sync.sync() {
            tracing::error!(table = %name, error = %e, "final log fsync failed");
        }
    }
}
