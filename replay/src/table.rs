//! A table of transitions: columnar ring storage with FIFO eviction, a sum-tree sampler
//! (uniform or proportional prioritised), the rate limiter, and exactly-once inserts.
//!
//! ```text
//!   key k (u64, assigned in insert order) lives in slot k mod capacity while
//!   next_key − capacity ≤ k < next_key and it has not been removed (max_times_sampled)
//!
//!   columns (slot-major): obs[cap·obs_dim] next_obs[cap·obs_dim] action[cap·act_dim]
//!                         reward terminal truncated episode_id step policy_version actor key
//! ```
//!
//! Threading: one mutex guards everything; every method takes it once and holds it for
//! O(rows × dims) copying or O(rows × log capacity) tree work. Blocked callers park on a
//! condition variable that every insert, sample and close notifies. Memory is the raw payload
//! plus 16 bytes a slot for the sum tree and ~30 bytes of per-row metadata.
//!
//! Persistence ([`Table::open`]): inserts and priority updates append a record to the
//! write-ahead log (`wal.rs`) under the lock, before they change anything, so log order is
//! apply order and an acknowledged change is in the log. A background thread copies the
//! metadata under the lock (O(capacity) memcpy, a few ms at 1M rows) and writes the snapshot
//! (`snapshot.rs`) without it; another fsyncs the log on `FsyncPolicy::IntervalMs`.
//!
//! ```text
//!   open:  newest usable snapshot ──► replay log: LSN ≤ snapshot: row data only
//!                                                 LSN > snapshot: inserts, de-dup marks,
//!                                                                 priorities, counters
//!          stop at the first torn/corrupt record, move what follows to wal/corrupt/
//! ```

use std::collections::HashMap;
use std::path::{Path, PathBuf};
use std::sync::atomic::{AtomicBool, Ordering};
use std::sync::{Arc, Condvar, Mutex, MutexGuard};
use std::thread::JoinHandle;
use std::time::{Duration, Instant};

use mapless_proto::v1::{ActorInfo, InsertAck, ProtocolVersion, RateLimiterInfo, SampledBatch, ServerInfoResponse, TransitionBatch};
use mapless_proto::{FloatColumn, FloatEncoding, extend_f32le};
use prost::Message;
use prost::bytes::Bytes;
use rand::{Rng, SeedableRng};
use rand_pcg::Pcg64Mcg;

use crate::actors::ActorStats;
use crate::config::{FsyncPolicy, PersistenceConfig, SamplerConfig, TableConfig};
use crate::error::ReplayError;
use crate::rate_limiter::RateLimiter;
use crate::snapshot::{SnapshotData, SnapshotMeta, SnapshotStore};
use crate::sum_tree::SumTree;
use crate::wal::{self, StorageFault, Wal, WalSync, unix_ms};

/// Snapshots kept on disk. The log is kept back to the oldest, so a damaged newest snapshot
/// falls back to the previous one without losing anything.
const SNAPSHOTS_KEPT: usize = 2;

/// Insert and sample rates over the last few seconds.
#[derive(Debug)]
struct RateMeter {
    window: std::collections::VecDeque<(Instant, u64)>,
}

impl RateMeter {
    const SPAN_S: f64 = 10.0;
    fn new() -> Self {
        RateMeter { window: std::collections::VecDeque::new() }
    }
    fn add(&mut self, now: Instant, n: u64) {
        match self.window.back_mut() {
            // Coalesce into 100 ms buckets so the window stays small.
            Some((t, c)) if now.duration_since(*t).as_secs_f64() < 0.1 => *c += n,
            _ => self.window.push_back((now, n)),
        }
        while self.window.front().is_some_and(|(t, _)| now.duration_since(*t).as_secs_f64() > Self::SPAN_S) {
            self.window.pop_front();
        }
    }
    fn per_second(&self, now: Instant) -> f64 {
        let Some((first, _)) = self.window.front() else { return 0.0 };
        let span = now.duration_since(*first).as_secs_f64().clamp(1.0, Self::SPAN_S);
        self.window.iter().filter(|(t, _)| now.duration_since(*t).as_secs_f64() <= Self::SPAN_S).map(|(_, c)| *c).sum::<u64>() as f64 / span
    }
}

struct State {
    // Columns.
    obs: Vec<f32>,
    next_obs: Vec<f32>,
    action: Vec<f32>,
    reward: Vec<f32>,
    terminal: Vec<bool>,
    truncated: Vec<bool>,
    episode_id: Vec<u64>,
    step: Vec<u32>,
    policy_version: Vec<u64>,
    key: Vec<u64>,
    live: Vec<bool>,
    times_sampled: Vec<u32>,
    // Sampling.
    tree: SumTree,
    /// Largest priority^α seen; new items get it so each is sampled at least once soon.
    max_weight: f64,
    size: u64,
    next_key: u64,
    limiter: RateLimiter,
    actors: HashMap<String, ActorStats>,
    rng: Pcg64Mcg,
    insert_rate: RateMeter,
    sample_rate: RateMeter,
    closed: bool,
    /// The write-ahead log, when the table persists itself.
    wal: Option<Wal>,
}

impl State {
    /// Copies rows `r..r + n` of a validated `batch` into slots `slot..slot + n` (no wrap):
    /// one copy per column, whichever encoding its floats travelled in.
    fn write_rows(&mut self, slot: usize, batch: &TransitionBatch, r: usize, n: usize, d: usize, a: usize) {
        let (s0, s1, r1) = (slot, slot + n, r + n);
        copy_floats(batch.obs_column(), r * d, r1 * d, &mut self.obs[s0 * d..s1 * d]);
        copy_floats(batch.next_obs_column(), r * d, r1 * d, &mut self.next_obs[s0 * d..s1 * d]);
        copy_floats(batch.action_column(), r * a, r1 * a, &mut self.action[s0 * a..s1 * a]);
        copy_floats(batch.reward_column(), r, r1, &mut self.reward[s0..s1]);
        self.terminal[s0..s1].copy_from_slice(&batch.terminal[r..r1]);
        self.truncated[s0..s1].copy_from_slice(&batch.truncated[r..r1]);
        self.episode_id[s0..s1].copy_from_slice(&batch.episode_id[r..r1]);
        self.step[s0..s1].copy_from_slice(&batch.step[r..r1]);
        self.policy_version[s0..s1].copy_from_slice(&batch.policy_version[r..r1]);
    }

    /// Writes a validated batch's first `rows` rows at keys `first_key..`, in runs of
    /// consecutive slots (a run ends where the ring wraps), calling `placed(slot, n)` after
    /// each run.
    fn place_rows(&mut self, first_key: u64, batch: &TransitionBatch, rows: usize, cfg: &TableConfig, mut placed: impl FnMut(&mut State, usize, usize)) {
        let cap = cfg.capacity;
        let mut r = 0;
        while r < rows {
            let key = first_key + r as u64;
            let slot = (key % cap as u64) as usize;
            let n = (rows - r).min(cap - slot);
            self.write_rows(slot, batch, r, n, cfg.obs_dim, cfg.act_dim);
            for (i, k) in self.key[slot..slot + n].iter_mut().enumerate() {
                *k = key + i as u64;
            }
            placed(self, slot, n);
            r += n;
        }
    }

    /// Stores a validated batch's first `rows` rows under keys next_key.., evicting the oldest
    /// rows (FIFO); new rows are live with the largest weight seen.
    fn store_rows(&mut self, batch: &TransitionBatch, rows: usize, cfg: &TableConfig) {
        let first_key = self.next_key;
        self.place_rows(first_key, batch, rows, cfg, |st, slot, n| {
            // Live rows overwritten here leave (FIFO eviction); the run's rows become live.
            // A batch larger than the table evicts its own earlier runs the same way.
            let evicted = st.live[slot..slot + n].iter().filter(|&&l| l).count() as u64;
            st.size -= evicted;
            st.times_sampled[slot..slot + n].fill(0);
            st.live[slot..slot + n].fill(true);
            st.tree.set_range(slot, slot + n, st.max_weight);
            st.next_key += n as u64;
            st.size += n as u64;
        });
        self.limiter.inserted(rows as u64);
    }

    /// Updates the sending actor's de-duplication mark and statistics for a stored batch.
    fn note_insert(&mut self, batch: &TransitionBatch, rows: usize, unix_ms: u64) {
        let newest_version = batch.policy_version[..rows].iter().copied().max().unwrap_or(0);
        let actor = self.actors.entry(batch.actor_id.clone()).or_default();
        actor.last_sequence = batch.sequence;
        actor.batches += 1;
        actor.rows += rows as u64;
        actor.last_policy_version = actor.last_policy_version.max(newest_version);
        actor.last_insert_unix_ms = unix_ms;
    }

    /// The ack for a batch at or below its actor's last stored sequence (counted), if it is one.
    fn duplicate_ack(&mut self, batch: &TransitionBatch) -> Option<InsertAck> {
        let size = self.size;
        let a = self.actors.get_mut(&batch.actor_id)?;
        if batch.sequence > a.last_sequence {
            return None;
        }
        a.duplicate_batches += 1;
        Some(InsertAck { actor_id: batch.actor_id.clone(), sequence: batch.sequence, accepted_rows: 0, duplicate: true, table_size: size })
    }

    /// Is `key` stored now?
    fn holds(&self, key: u64, cap: u64) -> bool {
        let slot = (key % cap) as usize;
        key < self.next_key && self.live[slot] && self.key[slot] == key
    }

    /// Sets the priorities of keys still stored (weight (p + ε)^α); returns how many.
    fn apply_priorities(&mut self, pairs: &[(u64, f64)], alpha: f64, epsilon: f64, cap: u64) -> usize {
        let mut updated = 0;
        for &(k, p) in pairs {
            if self.holds(k, cap) {
                let w = (p + epsilon).powf(alpha);
                self.tree.set((k % cap) as usize, w);
                self.max_weight = self.max_weight.max(w);
                updated += 1;
            }
        }
        updated
    }
}

/// One replay table. Share it with `Arc`; every method takes `&self`.
pub struct Table {
    cfg: TableConfig,
    state: Arc<Mutex<State>>,
    changed: Condvar,
    started_unix_ms: u64,
    persist: Option<Persist>,
}

/// Asks the kernel to back a large, not yet touched column with transparent huge pages
/// (Linux, where THP is enabled as "madvise" or "always"; elsewhere nothing happens). A fresh
/// table is allocated zeroed and untouched, so its pages fault in as rows first land: with
/// 4 KiB pages a 203-float row costs about a page fault, with 2 MiB pages 512 times fewer
/// (the kernel still zeroes every page first, which keeps a fresh table's first fill memory
/// bound; in a probe the fill took 7–38% less CPU time). Random row reads while sampling miss
/// the TLB less, too. Resident memory still grows only as the table fills (in 2 MiB steps).
/// Advice only: failure changes nothing.
fn advise_huge_pages<T>(column: &mut [T]) {
    #[cfg(target_os = "linux")]
    {
        const HUGE: usize = 2 << 20;
        let bytes = std::mem::size_of_val(column);
        if bytes < 2 * HUGE {
            return;
        }
        // madvise needs a page-aligned start; round the range inwards to whole 4 KiB pages.
        let start = column.as_mut_ptr() as usize;
        let aligned = start.next_multiple_of(4096);
        let len = (start + bytes - aligned) / 4096 * 4096;
        // SAFETY: the range lies inside `column`'s allocation, which we borrow mutably;
        // MADV_HUGEPAGE changes how the kernel backs those pages, never their contents.
        let r = unsafe { libc::madvise(aligned as *mut libc::c_void, len, libc::MADV_HUGEPAGE) };
        if r != 0 {
            tracing::debug!(error = %std::io::Error::last_os_error(), "madvise(MADV_HUGEPAGE) refused; keeping 4 KiB pages");
        }
    }
    #[cfg(not(target_os = "linux"))]
    let _ = column;
}

/// Copies floats `start..end` of a column into `dst`. The batch was validated, so the range
/// exists and fits; were it not, `dst` is left as it is (never a panic).
fn copy_floats(column: FloatColumn<'_>, start: usize, end: usize, dst: &mut [f32]) {
    let copied = column.slice(start, end).is_some_and(|c| c.copy_to_slice(dst));
    debug_assert!(copied, "validated column {start}..{end} did not fit {} slots", dst.len());
}

/// Rows `slots` of a row-major column of `width` floats, in the requested encoding.
fn gather(column: &[f32], width: usize, slots: &[usize], floats: FloatEncoding) -> (Vec<f32>, Bytes) {
    match floats {
        FloatEncoding::Packed => {
            let mut out = Vec::with_capacity(slots.len() * width);
            for &slot in slots {
                out.extend_from_slice(&column[slot * width..(slot + 1) * width]);
            }
            (out, Bytes::new())
        }
        FloatEncoding::F32Le => {
            let mut out = Vec::with_capacity(slots.len() * width * 4);
            for &slot in slots {
                extend_f32le(&mut out, &column[slot * width..(slot + 1) * width]);
            }
            (Vec::new(), Bytes::from(out))
        }
    }
}

impl Table {
    /// An empty table; `seed` fixes the sampler's random stream.
    pub fn new(cfg: TableConfig, seed: u64) -> Result<Table, ReplayError> {
        cfg.validate()?;
        let c = cfg.capacity;
        let state = State {
            obs: vec![0.0; c * cfg.obs_dim],
            next_obs: vec![0.0; c * cfg.obs_dim],
            action: vec![0.0; c * cfg.act_dim],
            reward: vec![0.0; c],
            terminal: vec![false; c],
            truncated: vec![false; c],
            episode_id: vec![0; c],
            step: vec![0; c],
            policy_version: vec![0; c],
            key: vec![0; c],
            live: vec![false; c],
            times_sampled: vec![0; c],
            tree: SumTree::new(c),
            max_weight: 1.0,
            size: 0,
            next_key: 0,
            limiter: RateLimiter::new(cfg.rate_limiter.clone()),
            actors: HashMap::new(),
            rng: Pcg64Mcg::seed_from_u64(seed),
            insert_rate: RateMeter::new(),
            sample_rate: RateMeter::new(),
            closed: false,
            wal: None,
        };
        let mut state = state;
        for column in [&mut state.obs, &mut state.next_obs, &mut state.action] {
            advise_huge_pages(column);
        }
        Ok(Table { cfg, state: Arc::new(Mutex::new(state)), changed: Condvar::new(), started_unix_ms: unix_ms(), persist: None })
    }

    /// A table that persists itself in `persistence.dir` (memory only when that is `None`):
    /// restores what the directory holds, then logs every insert and priority update and
    /// snapshots in the background. Every batch acknowledged before a crash comes back exactly
    /// once; a torn or corrupt log is cut at the first bad record, which the report names
    /// (everything before it is restored). Fails when another table holds the directory, or
    /// when the directory was written by a table of another capacity or dims.
    pub fn open(cfg: TableConfig, persistence: PersistenceConfig, seed: u64) -> Result<(Table, RecoveryReport), ReplayError> {
        persistence.validate()?;
        let mut table = Table::new(cfg, seed)?;
        let Some(dir) = persistence.dir.clone() else {
            return Ok((table, RecoveryReport::default()));
        };
        let wal_dir = dir.join("wal");
        std::fs::create_dir_all(&wal_dir).map_err(|e| ReplayError::Storage { path: wal_dir.clone(), problem: format!("create: {e}") })?;
        let lock_file = crate::snapshot::lock_dir(&dir)?;
        let store = SnapshotStore::open(dir.join("snapshots"), SNAPSHOTS_KEPT)?;
        let (wal, report) = table.recover(&store, &wal_dir, &persistence)?;
        let sync = wal.sync_handle();
        table.lock().wal = Some(wal);
        let shared = Arc::new(PersistShared {
            name: table.cfg.name.clone(),
            capacity: table.cfg.capacity,
            obs_dim: table.cfg.obs_dim,
            act_dim: table.cfg.act_dim,
            sampler: table.cfg.sampler.clone(),
            state: Arc::clone(&table.state),
            store,
            sync,
            wal_dir,
            scratch: Mutex::new(SnapshotScratch::default()),
            stop: Mutex::new(false),
            stop_cv: Condvar::new(),
        });
        let threads = match PersistShared::spawn(&shared, &persistence) {
            Ok(t) => t,
            Err((e, started)) => {
                *lock_plain(&shared.stop) = true;
                shared.stop_cv.notify_all();
                started.into_iter().for_each(|h| drop(h.join()));
                return Err(e);
            }
        };
        table.persist = Some(Persist { shared, threads: Mutex::new(threads), shut: AtomicBool::new(false), _lock_file: lock_file });
        Ok((table, report))
    }

    /// Rebuilds the (empty) state from the newest usable snapshot and the log; returns the log
    /// reopened for appending after the last valid record.
    fn recover(&self, store: &SnapshotStore, wal_dir: &Path, p: &PersistenceConfig) -> Result<(Wal, RecoveryReport), ReplayError> {
        let t0 = Instant::now();
        let cfg = &self.cfg;
        let (cap, d, a) = (cfg.capacity, cfg.obs_dim, cfg.act_dim);
        let mut report = RecoveryReport::default();
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
        for f in &report.skipped_snapshots {
            tracing::warn!(table = %cfg.name, file = %f.path.display(), reason = %f.reason, "snapshot skipped");
        }

        let mut st = self.lock();
        let s = &mut *st;
        let mut snap_lsn = 0;
        let mut samples = 0;
        let snapshot_path = base.as_ref().map(|(p, _)| p.clone());
        if let Some((path, snap)) = base {
            let m = snap.meta;
            let same_sampler = m.sampler == cfg.sampler;
            if !same_sampler {
                report.warnings.push(format!("sampler changed since {} was written: stored priorities reset to 1", path.display()));
            }
            s.max_weight = if same_sampler { m.max_weight } else { 1.0 };
            for slot in 0..cap {
                s.live[slot] = snap.live[slot];
                s.times_sampled[slot] = snap.times_sampled[slot];
                if snap.live[slot] {
                    s.tree.set(slot, if same_sampler { snap.weights[slot] } else { 1.0 });
                }
            }
            s.size = s.live.iter().filter(|&&l| l).count() as u64;
            s.next_key = m.next_key;
            s.actors = m.actors.into_iter().collect();
            // The sampler continues its random stream where the snapshot left it, so the
            // minibatches drawn after a restart are those the table would have drawn anyway
            // (older snapshots lack it: the stream restarts from `seed`).
            if let Some(rng) = m.sampler_rng {
                s.rng = rng;
            }
            samples = m.samples;
            snap_lsn = m.lsn;
            report.snapshot = Some(path);
            report.snapshot_lsn = m.lsn;
        } else if let Some(start) = log_start.filter(|&start| start > 1) {
            report.warnings.push(format!("no usable snapshot and the log starts at LSN {start}: de-duplication marks and counters from before it are lost"));
        }

        let mut filled = vec![false; cap];
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
                    if key_end > s.next_key {
                        return Err(Err(mismatch(snapshot_path.as_ref(), format!("LSN {} holds keys up to {key_end}, the snapshot's next key is {}", rec.lsn, s.next_key))));
                    }
                    s.place_rows(first_key, &batch, rows, cfg, |_, slot, n| filled[slot..slot + n].fill(true));
                } else {
                    if s.next_key != first_key {
                        if snapshot_path.is_none() && inserts_applied == 0 {
                            s.next_key = first_key; // the log's history before its start is gone (warned above)
                        } else {
                            return Err(Err(mismatch(snapshot_path.as_ref(), format!("LSN {} inserts at key {first_key}, the table is at {}", rec.lsn, s.next_key))));
                        }
                    }
                    for r in 0..rows {
                        filled[((first_key + r as u64) % cap as u64) as usize] = true;
                    }
                    s.store_rows(&batch, rows, cfg);
                    s.note_insert(&batch, rows, unix_ms);
                    after_snapshot += 1;
                    inserts_applied += 1;
                }
                Ok(Some(key_end))
            }
            wal::KIND_PRIORITIES => {
                let pairs = wal::parse_priorities_payload(rec.payload).map_err(Ok)?;
                if rec.lsn > snap_lsn {
                    if let SamplerConfig::Prioritized { alpha, epsilon, .. } = cfg.sampler {
                        s.apply_priorities(&pairs, alpha, epsilon, cap as u64);
                    }
                    after_snapshot += 1;
                }
                Ok(None)
            }
            kind => Err(Ok(format!("corrupt: unknown record kind {kind}"))),
        })?;

        // A live row whose data the log no longer holds cannot be served: drop it, loudly.
        let window = s.next_key.saturating_sub(cap as u64);
        let mut lost = 0u64;
        for (slot, &has_data) in filled.iter().enumerate() {
            if s.live[slot] && !(has_data && s.key[slot] >= window && s.key[slot] < s.next_key) {
                s.live[slot] = false;
                s.tree.set(slot, 0.0);
                lost += 1;
            }
        }
        s.size = s.live.iter().filter(|&&l| l).count() as u64;
        s.limiter.restore(s.next_key, samples);

        let end = scan.end_lsn().unwrap_or(0).max(snap_lsn);
        let wal = Wal::reopen(&scan, p.fsync, p.segment_bytes, end + 1, s.next_key)?;
        report.segments = scan.segments.iter().filter(|g| g.valid_len > 0).count();
        report.records_replayed = replayed;
        report.records_after_snapshot = after_snapshot;
        report.rows = s.size;
        report.next_key = s.next_key;
        report.last_lsn = wal.last_lsn();
        report.fault = scan.fault.clone();
        report.rows_lost = lost;
        if lost > 0 {
            report.warnings.push(format!("{lost} rows the snapshot lists as stored are missing from the log and were dropped"));
        }
        if let Some(f) = &report.fault {
            tracing::warn!(table = %cfg.name, file = %f.path.display(), offset = f.offset, reason = %f.reason, records_restored = replayed, "log cut at a torn or corrupt record; everything before it restored, the rest moved to wal/corrupt/");
        }
        for w in &report.warnings {
            tracing::warn!(table = %cfg.name, "{w}");
        }
        report.elapsed = t0.elapsed();
        tracing::info!(table = %cfg.name, rows = report.rows, records = replayed, after_snapshot, snapshot_lsn = snap_lsn, ms = report.elapsed.as_millis() as u64, "table restored");
        Ok((wal, report))
    }

    /// Writes a snapshot now (waiting for one in progress); `None` for a memory-only table or
    /// when nothing changed since the last one. Inserts and samples wait only for the copy.
    pub fn snapshot(&self) -> Result<Option<SnapshotInfo>, ReplayError> {
        match &self.persist {
            Some(p) => p.shared.snapshot(),
            None => Ok(None),
        }
    }

    pub fn config(&self) -> &TableConfig {
        &self.cfg
    }

    fn lock(&self) -> MutexGuard<'_, State> {
        // A panic while holding the lock cannot leave columns half-written in a way later
        // calls trip over (each row is written before it becomes live), so keep serving.
        self.state.lock().unwrap_or_else(|p| p.into_inner())
    }

    /// Rows currently stored (live).
    pub fn size(&self) -> u64 {
        self.lock().size
    }

    /// Validates, de-duplicates on (actor_id, sequence), waits for the rate limiter until
    /// `deadline` (None: wait indefinitely), and stores the batch. A duplicate (sequence at or
    /// below the actor's last stored one) is acknowledged with `duplicate = true` and changes
    /// nothing. A rejected batch changes nothing and is counted against its actor. On a
    /// persistent table the batch is in the log (written to the OS; fsynced too under
    /// `FsyncPolicy::Always`) before it is stored and acknowledged; if the log cannot be
    /// written, nothing is stored and the error is `Storage`.
    ///
    /// The batch's float columns may travel in either encoding (packed or `*_f32le` bytes);
    /// each column is copied into the table with one copy.
    pub fn insert(&self, batch: &TransitionBatch, deadline: Option<Instant>) -> Result<InsertAck, ReplayError> {
        self.insert_encoded(batch, None, deadline)
    }

    /// [`Table::insert`] for a batch whose protobuf encoding the caller already holds
    /// (`encoded`, exactly the bytes `batch` was decoded from): a persistent table logs those
    /// bytes instead of encoding the batch again.
    pub(crate) fn insert_encoded(&self, batch: &TransitionBatch, encoded: Option<&[u8]>, deadline: Option<Instant>) -> Result<InsertAck, ReplayError> {
        let rows = match batch.validate(self.cfg.obs_dim, self.cfg.act_dim, self.cfg.max_batch_rows) {
            Ok(r) => r,
            Err(e) => {
                self.record_rejection(&batch.actor_id, &e.to_string());
                return Err(e.into());
            }
        };
        // Encoded outside the lock (float columns as bytes: a memcpy each); the record is
        // written under it, before anything changes.
        let owned;
        let encoded = match (self.persist.as_ref(), encoded) {
            (None, _) => None,
            (Some(_), Some(bytes)) => Some(bytes),
            (Some(_), None) => {
                let mut buf = Vec::with_capacity(batch.encoded_len_f32le());
                batch.encode_f32le(&mut buf);
                owned = buf;
                Some(owned.as_slice())
            }
        };
        let mut st = self.lock();
        if let Some(ack) = st.duplicate_ack(batch) {
            return Ok(ack);
        }
        st = self.wait(st, deadline, "insert", |s| s.limiter.can_insert())?;
        // Another caller may have stored the same batch while this one waited.
        if let Some(ack) = st.duplicate_ack(batch) {
            return Ok(ack);
        }
        let now_ms = unix_ms();
        let s = &mut *st;
        if let (Some(wal), Some(bytes)) = (s.wal.as_mut(), encoded) {
            wal.append_insert(s.next_key, rows as u64, now_ms, bytes)?;
        }
        s.store_rows(batch, rows, &self.cfg);
        s.insert_rate.add(Instant::now(), rows as u64);
        s.note_insert(batch, rows, now_ms);
        let ack = InsertAck { actor_id: batch.actor_id.clone(), sequence: batch.sequence, accepted_rows: rows as u32, duplicate: false, table_size: s.size };
        drop(st);
        self.changed.notify_all();
        Ok(ack)
    }

    /// Counts a rejected batch against its actor (any ingest path calls this for input it
    /// could not even decode). Nothing stored is touched.
    pub fn record_rejection(&self, actor_id: &str, why: &str) {
        let id = if actor_id.is_empty() || actor_id.len() > mapless_proto::MAX_ACTOR_ID_BYTES { "<invalid actor id>" } else { actor_id };
        let mut st = self.lock();
        let a = st.actors.entry(id.to_string()).or_default();
        a.rejected_batches += 1;
        a.last_rejection = why.chars().take(200).collect();
        tracing::warn!(table = %self.cfg.name, actor_id = id, reason = why, "batch rejected");
    }

    /// Draws a minibatch of `rows`, waiting for the rate limiter until `deadline`. `beta`
    /// overrides the configured importance-sampling exponent (prioritised sampler only).
    /// The float columns are packed (`obs`, ...); see [`Table::sample_as`].
    pub fn sample(&self, rows: usize, beta: Option<f64>, deadline: Option<Instant>) -> Result<SampledBatch, ReplayError> {
        self.sample_as(rows, beta, deadline, FloatEncoding::Packed)
    }

    /// [`Table::sample`] with the float columns in `floats`: `F32Le` fills `obs_f32le`, ...
    /// (what a Sample stream sends when `SampleRequest.float_columns_as_bytes` is set). The
    /// rows drawn do not depend on the encoding.
    ///
    /// Uniform tables without `max_times_sampled` whose every key since the oldest stored one
    /// is live (the normal case) draw keys directly, without walking the sum tree.
    pub fn sample_as(&self, rows: usize, beta: Option<f64>, deadline: Option<Instant>, floats: FloatEncoding) -> Result<SampledBatch, ReplayError> {
        if rows == 0 || rows > self.cfg.max_sample_rows {
            return Err(ReplayError::BadRequest(format!("batch_size must be in 1..={}, got {rows}", self.cfg.max_sample_rows)));
        }
        let beta = match (&self.cfg.sampler, beta) {
            (SamplerConfig::Prioritized { beta, .. }, None) => *beta,
            (_, Some(b)) if b.is_finite() && b >= 0.0 => b,
            (_, Some(b)) => return Err(ReplayError::BadRequest(format!("importance beta must be finite and ≥ 0, got {b}"))),
            (SamplerConfig::Uniform, None) => 0.0,
        };
        let st = self.lock();
        let mut st = self.wait(st, deadline, "sample", |s| s.limiter.can_sample(s.size, rows as u64))?;
        let (d, a) = (self.cfg.obs_dim, self.cfg.act_dim);
        let cap = self.cfg.capacity as u64;
        let s = &mut *st;
        let table_size = s.size;
        let n = s.size as f64;
        let mut slots = Vec::with_capacity(rows);
        let mut keys = Vec::with_capacity(rows);
        let mut probabilities = Vec::with_capacity(rows);
        let mut importance_weights = Vec::with_capacity(rows);
        let mut max_w = 0.0f64;
        if let Some((first_key, len)) = self.uniform_window(s) {
            // Every key in first_key..first_key + len is live with weight 1: draw keys
            // stratified over that range, as the tree walk would over the slots.
            let segment = len as f64 / rows as f64;
            let p = 1.0 / len as f64;
            let w = (n * p).powf(-beta);
            for i in 0..rows {
                let u = (i as f64 + s.rng.random::<f64>()) * segment;
                let key = first_key + (u as u64).min(len - 1);
                let slot = (key % cap) as usize;
                slots.push(slot);
                keys.push(key);
                probabilities.push(p);
                importance_weights.push(w as f32);
                s.times_sampled[slot] = s.times_sampled[slot].saturating_add(1);
            }
            max_w = w;
        } else {
            let total = s.tree.total();
            let segment = total / rows as f64;
            for i in 0..rows {
                // Stratified: one draw from each of `rows` equal slices of the total mass.
                let u = (i as f64 + s.rng.random::<f64>()) * segment;
                let slot = s.tree.find(u.min(total));
                let p = s.tree.get(slot) / total;
                let w = (n * p).powf(-beta);
                max_w = max_w.max(w);
                slots.push(slot);
                keys.push(s.key[slot]);
                probabilities.push(p);
                importance_weights.push(w as f32);
                s.times_sampled[slot] = s.times_sampled[slot].saturating_add(1);
                if self.cfg.max_times_sampled > 0 && s.times_sampled[slot] >= self.cfg.max_times_sampled && s.live[slot] {
                    s.live[slot] = false;
                    s.tree.set(slot, 0.0);
                    s.size -= 1;
                }
            }
        }
        // Normalise by the minibatch's largest weight (as Acme and Dopamine do), so weights
        // only ever scale updates down.
        for w in &mut importance_weights {
            *w = (*w as f64 / max_w) as f32;
        }
        // Gathered after drawing: a row removed by max_times_sampled still has its data.
        let (obs, obs_f32le) = gather(&s.obs, d, &slots, floats);
        let (next_obs, next_obs_f32le) = gather(&s.next_obs, d, &slots, floats);
        let (action, action_f32le) = gather(&s.action, a, &slots, floats);
        let (reward, reward_f32le) = gather(&s.reward, 1, &slots, floats);
        let out = SampledBatch {
            protocol_version: ProtocolVersion::V1 as i32,
            table: self.cfg.name.clone(),
            obs_dim: d as u32,
            act_dim: a as u32,
            num_rows: rows as u32,
            table_size,
            keys,
            probabilities,
            importance_weights,
            obs,
            action,
            reward,
            next_obs,
            terminal: slots.iter().map(|&slot| s.terminal[slot]).collect(),
            truncated: slots.iter().map(|&slot| s.truncated[slot]).collect(),
            episode_id: slots.iter().map(|&slot| s.episode_id[slot]).collect(),
            step: slots.iter().map(|&slot| s.step[slot]).collect(),
            policy_version: slots.iter().map(|&slot| s.policy_version[slot]).collect(),
            obs_f32le,
            action_f32le,
            reward_f32le,
            next_obs_f32le,
        };
        s.limiter.sampled(rows as u64);
        s.sample_rate.add(Instant::now(), rows as u64);
        drop(st);
        self.changed.notify_all();
        Ok(out)
    }

    /// `Some((oldest key, rows))` when uniform draws may skip the sum tree: a uniform sampler
    /// that never removes rows, and every key from the oldest stored one to the newest is
    /// live (not so after a recovery that dropped rows, for instance).
    fn uniform_window(&self, s: &State) -> Option<(u64, u64)> {
        if self.cfg.sampler != SamplerConfig::Uniform || self.cfg.max_times_sampled > 0 {
            return None;
        }
        let len = s.next_key.min(self.cfg.capacity as u64);
        // Live rows only ever hold keys among the newest `len`; as many live rows as keys
        // there means each of those keys is live.
        (len > 0 && s.size == len).then_some((s.next_key - len, len))
    }

    /// Sets new priorities (e.g. |TD error|) for keys still stored; returns (updated,
    /// unknown) counts. Keys evicted or removed since they were sampled are skipped. On a
    /// persistent table the updates to stored keys are logged first, as for `insert`.
    pub fn update_priorities(&self, keys: &[u64], priorities: &[f64]) -> Result<(u32, u32), ReplayError> {
        if keys.len() != priorities.len() {
            return Err(ReplayError::BadRequest(format!("{} keys but {} priorities", keys.len(), priorities.len())));
        }
        if let Some(i) = priorities.iter().position(|p| !(p.is_finite() && *p >= 0.0)) {
            return Err(ReplayError::BadRequest(format!("priority {i} is {}, must be finite and ≥ 0", priorities[i])));
        }
        let SamplerConfig::Prioritized { alpha, epsilon, .. } = self.cfg.sampler else {
            // Uniform tables accept and ignore updates, so a learner can run either way.
            return Ok((0, 0));
        };
        let cap = self.cfg.capacity as u64;
        let mut st = self.lock();
        let s = &mut *st;
        let known: Vec<(u64, f64)> = keys.iter().zip(priorities).filter(|(k, _)| s.holds(**k, cap)).map(|(&k, &p)| (k, p)).collect();
        if let Some(wal) = s.wal.as_mut().filter(|_| !known.is_empty()) {
            wal.append_priorities(&known)?;
        }
        let updated = s.apply_priorities(&known, alpha, epsilon, cap);
        Ok((updated as u32, (keys.len() - updated) as u32))
    }

    /// Waits on the condition variable until `ready` or the deadline; accounts blocked time.
    fn wait<'a>(&self, mut st: MutexGuard<'a, State>, deadline: Option<Instant>, op: &'static str, ready: impl Fn(&State) -> bool) -> Result<MutexGuard<'a, State>, ReplayError> {
        let start = Instant::now();
        let account_blocked = |st: &mut State| {
            let ns = start.elapsed().as_nanos() as u64;
            if op == "insert" { st.limiter.insert_blocked(ns) } else { st.limiter.sample_blocked(ns) }
        };
        let mut blocked = false;
        loop {
            if st.closed {
                return Err(ReplayError::Closed(self.cfg.name.clone()));
            }
            if ready(&st) {
                if blocked {
                    account_blocked(&mut st);
                }
                return Ok(st);
            }
            blocked = true;
            let now = Instant::now();
            match deadline {
                Some(d) if now >= d => {
                    account_blocked(&mut st);
                    let state = serde_json::to_string(&st.limiter.state()).unwrap_or_default();
                    return Err(ReplayError::DeadlineExceeded { op, waited_ms: start.elapsed().as_millis() as u64, state: format!("size {}, {state}", st.size) });
                }
                Some(d) => st = self.changed.wait_timeout(st, d - now).unwrap_or_else(|p| p.into_inner()).0,
                None => st = self.changed.wait(st).unwrap_or_else(|p| p.into_inner()),
            }
        }
    }

    /// Wakes every blocked caller with `Closed`; later calls fail the same way. A persistent
    /// table then stops its background threads, writes a final snapshot and fsyncs its log
    /// (problems are logged; the log alone still restores everything). Dropping a table does
    /// the same.
    pub fn close(&self) {
        self.lock().closed = true;
        self.changed.notify_all();
        if let Some(p) = &self.persist {
            p.shutdown(&self.cfg.name);
        }
    }

    /// Per-actor statistics (clone).
    pub fn actors(&self) -> HashMap<String, ActorStats> {
        self.lock().actors.clone()
    }

    /// Everything `ServerInfo` reports.
    pub fn info(&self) -> ServerInfoResponse {
        use mapless_proto::v1::{RateLimiterState as Rls, Selector};
        let st = self.lock();
        let now = Instant::now();
        let rl = st.limiter.state();
        let batch = self.cfg.max_sample_rows.min(128) as u64;
        let state = if st.size < rl.min_size_to_sample {
            Rls::WarmingUp
        } else if !st.limiter.can_insert() {
            Rls::InsertsBlocked
        } else if !st.limiter.can_sample(st.size, batch) {
            Rls::SamplesBlocked
        } else {
            Rls::Open
        };
        let mut actors: Vec<ActorInfo> = st
            .actors
            .iter()
            .map(|(id, a)| ActorInfo {
                actor_id: id.clone(),
                batches: a.batches,
                rows: a.rows,
                duplicate_batches: a.duplicate_batches,
                last_sequence: a.last_sequence,
                last_policy_version: a.last_policy_version,
                last_insert_unix_ms: a.last_insert_unix_ms,
                // Rejections and policy-version lag are filled by the gRPC layer (grpc::server_info).
                ..ActorInfo::default()
            })
            .collect();
        actors.sort_by(|a, b| a.actor_id.cmp(&b.actor_id));
        ServerInfoResponse {
            protocol_version: ProtocolVersion::V1 as i32,
            table: self.cfg.name.clone(),
            selector: match self.cfg.sampler {
                SamplerConfig::Uniform => Selector::Uniform as i32,
                SamplerConfig::Prioritized { .. } => Selector::Prioritized as i32,
            },
            obs_dim: self.cfg.obs_dim as u32,
            act_dim: self.cfg.act_dim as u32,
            size: st.size,
            capacity: self.cfg.capacity as u64,
            inserts_total: rl.inserts,
            samples_total: rl.samples,
            inserts_per_s: st.insert_rate.per_second(now),
            samples_per_s: st.sample_rate.per_second(now),
            rate_limiter: Some(RateLimiterInfo {
                state: state as i32,
                min_size_to_sample: rl.min_size_to_sample,
                samples_per_insert: rl.samples_per_insert.unwrap_or(0.0),
                error_buffer: self.cfg.rate_limiter.error_buffer,
                inserts_blocked_ms: (rl.insert_blocked_s * 1e3) as u64,
                samples_blocked_ms: (rl.sample_blocked_s * 1e3) as u64,
            }),
            actors,
            max_rows_per_batch: self.cfg.max_batch_rows as u32,
            started_unix_ms: self.started_unix_ms,
        }
    }

    /// Bytes held by the table's columns and sampler (what the memory target measures).
    pub fn memory_bytes(&self) -> usize {
        let st = self.lock();
        let f = std::mem::size_of::<f32>();
        (st.obs.len() + st.next_obs.len() + st.action.len() + st.reward.len()) * f
            + st.terminal.len() * 3 // terminal, truncated, live
            + (st.episode_id.len() + st.policy_version.len() + st.key.len()) * 8
            + (st.step.len() + st.times_sampled.len()) * 4
            + st.tree.memory_bytes()
    }
}

impl Drop for Table {
    fn drop(&mut self) {
        if self.persist.is_some() {
            self.close();
        }
    }
}

/// What [`Table::open`] found on disk and did about it.
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

/// One snapshot written by [`Table::snapshot`] or the background thread.
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

/// A persistent table's background machinery.
struct Persist {
    shared: Arc<PersistShared>,
    threads: Mutex<Vec<JoinHandle<()>>>,
    shut: AtomicBool,
    /// Held (flock) while the table is open: two writers would interleave their logs.
    _lock_file: std::fs::File,
}

/// What the snapshot and flush threads share with the table.
struct PersistShared {
    name: String,
    capacity: usize,
    obs_dim: usize,
    act_dim: usize,
    sampler: SamplerConfig,
    state: Arc<Mutex<State>>,
    store: SnapshotStore,
    sync: Arc<WalSync>,
    wal_dir: PathBuf,
    /// Also serialises snapshot writers.
    scratch: Mutex<SnapshotScratch>,
    stop: Mutex<bool>,
    stop_cv: Condvar,
}

/// The last snapshot's (LSN, samples) and its per-slot buffers, kept so that the copy under
/// the table lock writes into memory already paged in (at 1M slots the first touch of the
/// 13 MB costs more than the copy itself).
#[derive(Default)]
struct SnapshotScratch {
    mark: Option<(u64, u64)>,
    weights: Vec<f64>,
    live: Vec<bool>,
    times_sampled: Vec<u32>,
}

fn lock_plain<T>(m: &Mutex<T>) -> MutexGuard<'_, T> {
    m.lock().unwrap_or_else(|p| p.into_inner())
}

impl PersistShared {
    /// Starts the flush and snapshot threads; on failure, the error and the threads started.
    #[allow(clippy::type_complexity)]
    fn spawn(shared: &Arc<PersistShared>, p: &PersistenceConfig) -> Result<Vec<JoinHandle<()>>, (ReplayError, Vec<JoinHandle<()>>)> {
        let mut threads = Vec::new();
        let spawn_err = |e: std::io::Error| ReplayError::Storage { path: shared.wal_dir.clone(), problem: format!("start background thread: {e}") };
        if let FsyncPolicy::IntervalMs(ms) = p.fsync {
            let sh = Arc::clone(shared);
            let every = Duration::from_millis(ms);
            let started = std::thread::Builder::new().name(format!("wal-flush-{}", shared.name)).spawn(move || {
                while !sh.wait_stop(every) {
                    if let Err(e) = sh.sync.sync_if_dirty() {
                        tracing::error!(table = %sh.name, error = %e, "log fsync failed; further inserts are refused");
                    }
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
            let started = std::thread::Builder::new()
                .name(format!("snapshot-{}", shared.name))
                .spawn(move || {
                    while !sh.wait_stop(every) {
                        match sh.snapshot_if_changed() {
                            Ok(Some(i)) => tracing::debug!(table = %sh.name, lsn = i.lsn, copy_us = i.copy.as_micros() as u64, write_ms = i.write.as_millis() as u64, segments_deleted = i.segments_deleted, "snapshot written"),
                            Ok(None) => {}
                            Err(e) => tracing::warn!(table = %sh.name, error = %e, "snapshot failed; the log still holds everything"),
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

    /// Copies the metadata under the table lock, then (lock released) fsyncs the log up to
    /// the copy's LSN, writes the snapshot, prunes old ones and deletes log segments that no
    /// kept snapshot needs and whose rows are all evicted.
    fn write_snapshot(&self, force: bool) -> Result<Option<SnapshotInfo>, ReplayError> {
        let mut scratch = lock_plain(&self.scratch);
        let cap = self.capacity;
        scratch.weights.resize(cap, 0.0);
        scratch.live.resize(cap, false);
        scratch.times_sampled.resize(cap, 0);
        let st = lock_plain(&self.state);
        let copy_start = Instant::now();
        let Some(wal) = st.wal.as_ref() else { return Ok(None) };
        let lsn = wal.last_lsn();
        let (inserts, samples) = st.limiter.counts();
        if !force && scratch.mark == Some((lsn, samples)) {
            return Ok(None);
        }
        for (slot, w) in scratch.weights.iter_mut().enumerate() {
            *w = st.tree.get(slot);
        }
        scratch.live.copy_from_slice(&st.live);
        scratch.times_sampled.copy_from_slice(&st.times_sampled);
        let snap = SnapshotData {
            meta: SnapshotMeta {
                table: self.name.clone(),
                lsn,
                next_key: st.next_key,
                capacity: cap as u64,
                obs_dim: self.obs_dim as u64,
                act_dim: self.act_dim as u64,
                sampler: self.sampler.clone(),
                max_weight: st.max_weight,
                inserts,
                samples,
                size: st.size,
                created_unix_ms: unix_ms(),
                actors: st.actors.iter().map(|(k, v)| (k.clone(), v.clone())).collect(),
                sampler_rng: Some(st.rng.clone()),
            },
            weights: std::mem::take(&mut scratch.weights),
            live: std::mem::take(&mut scratch.live),
            times_sampled: std::mem::take(&mut scratch.times_sampled),
        };
        drop(st);
        let copy = copy_start.elapsed();
        let write_start = Instant::now();
        let written = self.persist_snapshot(&snap);
        let rows = snap.meta.size;
        (scratch.weights, scratch.live, scratch.times_sampled) = (snap.weights, snap.live, snap.times_sampled);
        let (path, bytes, segments_deleted) = written?;
        scratch.mark = Some((lsn, samples));
        Ok(Some(SnapshotInfo { path, lsn, bytes, rows, copy, write: write_start.elapsed(), segments_deleted }))
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
        let doomed = {
            let mut st = lock_plain(&self.state);
            let evicted_below = st.next_key.saturating_sub(self.capacity as u64);
            st.wal.as_mut().map(|w| w.take_deletable(keep_from, evicted_below)).unwrap_or_default()
        };
        let mut deleted = 0;
        for p in &doomed {
            match std::fs::remove_file(p) {
                Ok(()) => deleted += 1,
                Err(e) => tracing::warn!(table = %self.name, file = %p.display(), error = %e, "could not delete an obsolete log segment"),
            }
        }
        if let Err(e) = if deleted > 0 { wal::sync_dir(&self.wal_dir) } else { Ok(()) } {
            tracing::warn!(table = %self.name, error = %e, "fsync of the log directory failed");
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
