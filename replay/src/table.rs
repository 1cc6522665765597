//! A table of transitions: columnar ring storage with FIFO eviction, a sum-tree sampler
//! (uniform or proportional prioritised), the rate limiter, and exactly-once inserts. Memory
//! only: what makes it durable (`persist/`) depends on it through three seams, never the
//! reverse (as Reverb's `Table::Checkpoint` and its checkpointer).
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
//! condition variable that every insert, sample and close notifies; async callers (the gRPC
//! Sample stream) instead try without waiting ([`Table::try_sample_as`]) and await
//! [`Table::changed`], which fires at the same moments. Memory is the raw payload
//! plus 16 bytes a slot for the sum tree and ~30 bytes of per-row metadata.
//!
//! The seams to persistence:
//!
//! ```text
//!   Journal (set_journal)   every accepted insert and priority update is handed to it under
//!                           the lock, before it changes anything: journal order is apply
//!                           order, and an acknowledged change is in the journal;
//!                           Journal::commit, without the lock, before the acknowledgement
//!                           (group commit under fsync: always)
//!   checkpoint[_into]       a value holding everything but the rows (priorities, live flags,
//!                           counters, de-dup marks, the sampler's random state) and the
//!                           journal position it is consistent with; an O(capacity) copy under
//!                           the lock into buffers the caller keeps
//!   restore (crate)         a checkpoint back, then the journaled rows and changes after it
//! ```

use std::collections::{BTreeMap, HashMap};
use std::sync::atomic::{AtomicU64, Ordering};
use std::sync::{Arc, Condvar, Mutex, MutexGuard};
use std::time::{Duration, Instant};

use mapless_proto::v1::{ActorInfo, InsertAck, ProtocolVersion, RateLimiterInfo, SampledBatch, ServerInfoResponse, TransitionBatch};
use mapless_proto::{FloatColumn, FloatEncoding, extend_f32le};
use prost::bytes::Bytes;
use rand::{Rng, SeedableRng};
use rand_pcg::Pcg64Mcg;

use crate::actors::ActorStats;
use crate::clock::unix_ms;
use crate::config::{SamplerConfig, TableConfig};
use crate::error::ReplayError;
use crate::rate_limiter::RateLimiter;
use crate::sum_tree::SumTree;

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
    /// Where every accepted change goes first, when the table is made durable.
    journal: Option<Arc<dyn Journal>>,
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
        // Actors number their batches 1, 2, 3, …: a jump means batches never stored (refused
        // as invalid, or lost on the way). Logged, naming the range, so that a count that does
        // not add up can be traced to its sequences (deploy/smoke.sh shows these lines).
        if batch.sequence > actor.last_sequence + 1 {
            tracing::warn!(actor_id = %batch.actor_id, missing_from = actor.last_sequence + 1, missing_to = batch.sequence - 1, "sequence gap: batches in this range were never stored");
        }
        actor.last_sequence = batch.sequence;
        actor.batches += 1;
        actor.rows += rows as u64;
        actor.last_policy_version = actor.last_policy_version.max(newest_version);
        actor.last_insert_unix_ms = unix_ms;
    }

    /// The ack for a batch at or below its actor's last stored sequence (counted), if it is one.
    /// The journal and its position now, for [`Journal::commit`] once the lock is released.
    fn commit_point(&self) -> Option<(Arc<dyn Journal>, u64)> {
        self.journal.as_ref().map(|j| (Arc::clone(j), j.position()))
    }

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

    /// Sets the priorities of keys still stored (weight (p + ε)^α, kept within
    /// [`MIN_PRIORITY_WEIGHT`, f64::MAX / 2·capacity]); returns how many.
    ///
    /// The bounds keep the sum tree's arithmetic finite and its mass positive: with α > 1 a
    /// large finite priority made (p + ε)^α infinite (1e200² in f64) and the total inf, so
    /// every probability was NaN; with ε = 0 and every stored priority 0 the total was 0 and
    /// the draws 0/0. A weight at the floor is drawn only when nothing else has mass, then
    /// uniformly.
    fn apply_priorities(&mut self, pairs: &[(u64, f64)], alpha: f64, epsilon: f64, cap: u64) -> usize {
        let ceiling = f64::MAX / (2.0 * cap as f64);
        let mut updated = 0;
        for &(k, p) in pairs {
            if self.holds(k, cap) {
                let w = (p + epsilon).powf(alpha).clamp(MIN_PRIORITY_WEIGHT, ceiling);
                self.tree.set((k % cap) as usize, w);
                self.max_weight = self.max_weight.max(w);
                updated += 1;
            }
        }
        updated
    }
}

/// The smallest sum-tree weight a prioritized row gets ([`State::apply_priorities`]): far below
/// any weight (p + ε)^α of a row with a positive priority that the learner sends, so such a row
/// is drawn only when no row has more.
const MIN_PRIORITY_WEIGHT: f64 = 1e-300;

/// Index of [`Table::storage_refusals`]' first dimension.
const INSERT: usize = 0;
const PRIORITIES: usize = 1;

/// One replay table. Share it with `Arc`; every method takes `&self`.
pub struct Table {
    cfg: TableConfig,
    state: Mutex<State>,
    changed: Condvar,
    /// Fired with `changed`, for callers that wait asynchronously (see [`Table::changed`]).
    changed_async: tokio::sync::Notify,
    /// Sample streams the transport refused because too many were open (see
    /// [`Table::record_sample_stream_refused`]).
    sample_streams_refused: AtomicU64,
    /// Changes the journal refused: [insert batches, priority updates] × [`StorageRefusal`].
    storage_refusals: [[AtomicU64; 2]; 2],
    started_unix_ms: u64,
    /// A journal is set: inserts encode their batch (outside the lock) for it.
    journaled: bool,
}

/// Where a table hands every accepted change before applying it: a write-ahead log, for
/// instance (`persist/`). The table calls it under its lock, so the journal sees changes in
/// exactly the order they are applied, and nothing else reaches the table in between.
///
/// A call that returns `Err` changes nothing in the table and its error goes back to the
/// caller of [`Table::insert`] or [`Table::update_priorities`] (which therefore never
/// acknowledges a change the journal did not take). A journal must never take the table's lock
/// (it is held) and should be quick: every insert and sample waits while it runs.
pub trait Journal: Send + Sync {
    /// Rows `first_key..first_key + rows` of the batch whose protobuf encoding is
    /// `batch_bytes`, stored at wall-clock `unix_ms`.
    fn insert(&self, first_key: u64, rows: u64, unix_ms: u64, batch_bytes: &[u8]) -> Result<(), ReplayError>;
    /// New raw priorities (before α and ε) of keys stored at the time.
    fn priorities(&self, pairs: &[(u64, f64)]) -> Result<(), ReplayError>;
    /// How far the journal got (e.g. the last log sequence number); a checkpoint records it,
    /// read under the same lock as everything it copies.
    fn position(&self) -> u64;
    /// Returns once every change journaled up to `position` is as durable as the journal
    /// promises before an acknowledgement (the write-ahead log under `fsync: always`: on
    /// disk). Called without the table's lock, after the change is applied, so that callers
    /// arriving together share one flush (group commit); the change is visible to samplers
    /// meanwhile, but its caller hears nothing until this returns. An `Err` reaches that
    /// caller instead of the acknowledgement. Default: nothing to wait for.
    fn commit(&self, position: u64) -> Result<(), ReplayError> {
        let _ = position;
        Ok(())
    }
}

/// What a journal refused, for [`Table::storage_refusals`] (`replay_storage_refusals_total`).
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum StorageRefusal {
    /// The file system is full (or out of quota): `ReplayError::DiskFull`.
    DiskFull,
    /// Any other storage error (EIO, a failed fsync, a log refusing after one).
    IoError,
}

impl StorageRefusal {
    pub const ALL: [StorageRefusal; 2] = [StorageRefusal::DiskFull, StorageRefusal::IoError];

    /// The metric label.
    pub fn label(self) -> &'static str {
        match self {
            StorageRefusal::DiskFull => "disk_full",
            StorageRefusal::IoError => "io_error",
        }
    }

    fn of(e: &ReplayError) -> Option<StorageRefusal> {
        match e {
            ReplayError::DiskFull { .. } => Some(StorageRefusal::DiskFull),
            ReplayError::Storage { .. } => Some(StorageRefusal::IoError),
            _ => None,
        }
    }
}

/// Everything of a table but its rows, consistent with one journal position: what a
/// checkpoint (a snapshot on disk) holds. The rows themselves are the journal's; restoring
/// means this value plus the rows and changes the journal holds (see `persist/recovery.rs`).
#[derive(Clone, Debug, Default)]
pub struct TableCheckpoint {
    /// [`Journal::position`] when the copy was taken (0 without a journal): every journaled
    /// change up to it is included, none after it.
    pub journal_position: u64,
    /// Key the next inserted row gets (= rows ever inserted).
    pub next_key: u64,
    /// Rows stored (live).
    pub size: u64,
    /// Largest priority weight seen (what new rows get).
    pub max_weight: f64,
    /// Rate-limiter counters, in rows.
    pub inserts: u64,
    pub samples: u64,
    /// Per-actor statistics, de-duplication marks among them.
    pub actors: BTreeMap<String, ActorStats>,
    /// The sampler's random-number generator (`None` on restore: keep the seeded stream).
    pub sampler_rng: Option<Pcg64Mcg>,
    /// Per slot: sum-tree weight, whether the slot is live, how often it was sampled.
    pub weights: Vec<f64>,
    pub live: Vec<bool>,
    pub times_sampled: Vec<u32>,
}

/// What tells two checkpoints of one table apart: the journal position and the samples drawn
/// (sampling is not journaled but moves the counters, `times_sampled` and the sampler's state).
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub struct CheckpointMark {
    pub journal_position: u64,
    pub samples: u64,
}

impl TableCheckpoint {
    pub fn mark(&self) -> CheckpointMark {
        CheckpointMark { journal_position: self.journal_position, samples: self.samples }
    }
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
            journal: None,
        };
        let mut state = state;
        for column in [&mut state.obs, &mut state.next_obs, &mut state.action] {
            advise_huge_pages(column);
        }
        Ok(Table {
            cfg,
            state: Mutex::new(state),
            changed: Condvar::new(),
            changed_async: tokio::sync::Notify::new(),
            sample_streams_refused: AtomicU64::new(0),
            storage_refusals: Default::default(),
            started_unix_ms: unix_ms(),
            journaled: false,
        })
    }

    /// Hands every insert and priority update from now on to `journal` first (see
    /// [`Journal`]). Set once, before the table is shared (a durable table sets it after
    /// recovery, so replayed changes are not journaled again).
    pub fn set_journal(&mut self, journal: Arc<dyn Journal>) {
        self.lock().journal = Some(journal);
        self.journaled = true;
    }

    /// A checkpoint of the table as it is now (allocates; see [`Table::checkpoint_into`]).
    pub fn checkpoint(&self) -> TableCheckpoint {
        let mut out = TableCheckpoint::default();
        self.checkpoint_into(&mut out, None);
        out
    }

    /// Copies a checkpoint into `out`, reusing its buffers, unless the table's
    /// [`CheckpointMark`] is still `unless_at` (then `out` is left as it was and the result is
    /// `None`). Returns how long the table's lock was held for the copy: the longest any insert
    /// or sample waited for it. The per-slot buffers are sized before the lock is taken, so a
    /// caller that keeps `out` between checkpoints copies into memory already paged in (at 1M
    /// slots the first touch of the 13 MB costs more than the copy itself).
    pub fn checkpoint_into(&self, out: &mut TableCheckpoint, unless_at: Option<CheckpointMark>) -> Option<Duration> {
        let cap = self.cfg.capacity;
        out.weights.resize(cap, 0.0);
        out.live.resize(cap, false);
        out.times_sampled.resize(cap, 0);
        let st = self.lock();
        let copy_start = Instant::now();
        let journal_position = st.journal.as_ref().map_or(0, |j| j.position());
        let (inserts, samples) = st.limiter.counts();
        if unless_at == Some(CheckpointMark { journal_position, samples }) {
            return None;
        }
        for (slot, w) in out.weights.iter_mut().enumerate() {
            *w = st.tree.get(slot);
        }
        out.live.copy_from_slice(&st.live);
        out.times_sampled.copy_from_slice(&st.times_sampled);
        out.journal_position = journal_position;
        out.next_key = st.next_key;
        out.size = st.size;
        out.max_weight = st.max_weight;
        (out.inserts, out.samples) = (inserts, samples);
        out.actors.clear();
        out.actors.extend(st.actors.iter().map(|(k, v)| (k.clone(), v.clone())));
        out.sampler_rng = Some(st.rng.clone());
        drop(st);
        Some(copy_start.elapsed())
    }

    /// Restores this (new, empty, not yet shared) table: the lock is held until the returned
    /// [`Restore`] is finished.
    pub(crate) fn restore(&self) -> Restore<'_> {
        Restore { cfg: &self.cfg, st: self.lock(), filled: vec![false; self.cfg.capacity], samples: 0 }
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

    /// Rows ever inserted: the key the next row gets.
    pub fn next_key(&self) -> u64 {
        self.lock().next_key
    }

    /// Validates, de-duplicates on (actor_id, sequence), waits for the rate limiter until
    /// `deadline` (None: wait indefinitely), and stores the batch. A duplicate (sequence at or
    /// below the actor's last stored one) is acknowledged with `duplicate = true` and changes
    /// nothing. A rejected batch changes nothing and is counted against its actor. With a
    /// [`Journal`] the batch is in the journal before it is stored and acknowledged (for the
    /// write-ahead log: written to the OS, and under `FsyncPolicy::Always` fsynced before the
    /// acknowledgement, see [`Journal::commit`]); if the journal refuses it, nothing is stored
    /// and its error (`Storage`, `DiskFull`) is returned and counted.
    ///
    /// The batch's float columns may travel in either encoding (packed or `*_f32le` bytes);
    /// each column is copied into the table with one copy.
    pub fn insert(&self, batch: &TransitionBatch, deadline: Option<Instant>) -> Result<InsertAck, ReplayError> {
        self.insert_encoded(batch, None, deadline)
    }

    /// [`Table::insert`] for a batch whose protobuf encoding the caller already holds
    /// (`encoded`, exactly the bytes `batch` was decoded from): a journaled table journals those
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
        let encoded = match (self.journaled, encoded) {
            (false, _) => None,
            (true, Some(bytes)) => Some(bytes),
            (true, None) => {
                let mut buf = Vec::with_capacity(batch.encoded_len_f32le());
                batch.encode_f32le(&mut buf);
                owned = buf;
                Some(owned.as_slice())
            }
        };
        let mut st = self.lock();
        if let Some(ack) = st.duplicate_ack(batch) {
            // A resend of a batch stored but perhaps not yet durable: the same wait as its
            // first acknowledgement (and the same refusal while the log refuses).
            let pending = st.commit_point();
            drop(st);
            return self.commit(pending, INSERT).map(|()| ack);
        }
        st = self.wait(st, deadline, "insert", |s| s.limiter.can_insert())?;
        // Another caller may have stored the same batch while this one waited.
        if let Some(ack) = st.duplicate_ack(batch) {
            let pending = st.commit_point();
            drop(st);
            return self.commit(pending, INSERT).map(|()| ack);
        }
        let now_ms = unix_ms();
        let s = &mut *st;
        if let (Some(journal), Some(bytes)) = (s.journal.as_ref(), encoded)
            && let Err(e) = journal.insert(s.next_key, rows as u64, now_ms, bytes)
        {
            drop(st);
            self.count_refusal(INSERT, &e);
            return Err(e);
        }
        s.store_rows(batch, rows, &self.cfg);
        s.insert_rate.add(Instant::now(), rows as u64);
        s.note_insert(batch, rows, now_ms);
        let ack = InsertAck { actor_id: batch.actor_id.clone(), sequence: batch.sequence, accepted_rows: rows as u32, duplicate: false, table_size: s.size };
        let pending = st.commit_point();
        drop(st);
        self.wake();
        self.commit(pending, INSERT)?;
        Ok(ack)
    }

    /// Waits for the journal's [`Journal::commit`] of `pending` (no lock held); counts a refusal.
    fn commit(&self, pending: Option<(Arc<dyn Journal>, u64)>, op: usize) -> Result<(), ReplayError> {
        let Some((journal, position)) = pending else { return Ok(()) };
        journal.commit(position).inspect_err(|e| self.count_refusal(op, e))
    }

    fn count_refusal(&self, op: usize, e: &ReplayError) {
        if let Some(r) = StorageRefusal::of(e) {
            self.storage_refusals[op][r as usize].fetch_add(1, Ordering::Relaxed);
        }
    }

    /// Insert batches (`priorities` false) or priority updates (true) that the journal refused
    /// for `reason`: never stored, or stored but never acknowledged.
    pub fn storage_refusals(&self, priorities: bool, reason: StorageRefusal) -> u64 {
        self.storage_refusals[priorities as usize][reason as usize].load(Ordering::Relaxed)
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
        let beta = self.sample_beta(rows, beta)?;
        let st = self.lock();
        let st = self.wait(st, deadline, "sample", |s| s.limiter.can_sample(s.size, rows as u64))?;
        Ok(self.draw(st, rows, beta, floats))
    }

    /// [`Table::sample_as`] without waiting: `Ok(None)` when the rate limiter does not allow
    /// the minibatch now. It still takes the table's lock (which an insert may hold while its
    /// journal writes), so async callers run it on a blocking thread. Pair it with
    /// [`Table::changed`] to wait, and with [`Table::record_sample_blocked`] /
    /// [`Table::sample_deadline_exceeded`] to account the wait as `sample_as` would.
    pub fn try_sample_as(&self, rows: usize, beta: Option<f64>, floats: FloatEncoding) -> Result<Option<SampledBatch>, ReplayError> {
        let beta = self.sample_beta(rows, beta)?;
        let st = self.lock();
        if st.closed {
            return Err(ReplayError::Closed(self.cfg.name.clone()));
        }
        if !st.limiter.can_sample(st.size, rows as u64) {
            return Ok(None);
        }
        Ok(Some(self.draw(st, rows, beta, floats)))
    }

    /// A future that resolves at the next insert, sample or close: whenever a caller blocked
    /// on the rate limiter could proceed. Create it and `enable()` it *before* checking (e.g.
    /// with [`Table::try_sample_as`]), or a change between the check and the await is missed.
    pub fn changed(&self) -> tokio::sync::futures::Notified<'_> {
        self.changed_async.notified()
    }

    /// Adds `waited` to the rate limiter's sample-side blocked time (for callers that waited
    /// outside [`Table::sample_as`]).
    pub fn record_sample_blocked(&self, waited: Duration) {
        self.lock().limiter.sample_blocked(waited.as_nanos() as u64);
    }

    /// The DeadlineExceeded a sampler gets after waiting `waited` in vain, worded as
    /// [`Table::sample_as`] words it (with the limiter's state). Does not account the wait.
    pub fn sample_deadline_exceeded(&self, waited: Duration) -> ReplayError {
        let st = self.lock();
        let state = serde_json::to_string(&st.limiter.state()).unwrap_or_default();
        ReplayError::DeadlineExceeded { op: "sample", waited_ms: waited.as_millis() as u64, state: format!("size {}, {state}", st.size) }
    }

    /// Counts a Sample stream the transport refused because its limit of open streams was
    /// reached (`replay_sample_streams_refused_total` in /metrics).
    pub fn record_sample_stream_refused(&self) {
        self.sample_streams_refused.fetch_add(1, Ordering::Relaxed);
    }

    /// Sample streams refused so far (see [`Table::record_sample_stream_refused`]).
    pub fn sample_streams_refused(&self) -> u64 {
        self.sample_streams_refused.load(Ordering::Relaxed)
    }

    /// Wakes every caller waiting for a change: blocked threads and async waiters alike.
    fn wake(&self) {
        self.changed.notify_all();
        self.changed_async.notify_waiters();
    }

    /// Checks a sample request; returns the importance-sampling exponent in effect.
    fn sample_beta(&self, rows: usize, beta: Option<f64>) -> Result<f64, ReplayError> {
        if rows == 0 || rows > self.cfg.max_sample_rows {
            return Err(ReplayError::BadRequest(format!("batch_size must be in 1..={}, got {rows}", self.cfg.max_sample_rows)));
        }
        let beta = match (&self.cfg.sampler, beta) {
            (SamplerConfig::Prioritized { beta, .. }, None) => *beta,
            (_, Some(b)) if b.is_finite() && b >= 0.0 => b,
            (_, Some(b)) => return Err(ReplayError::BadRequest(format!("importance beta must be finite and ≥ 0, got {b}"))),
            (SamplerConfig::Uniform, None) => 0.0,
        };
        Ok(beta)
    }

    /// Draws a minibatch of `rows` the rate limiter allows (checked by the caller, under `st`).
    fn draw(&self, mut st: MutexGuard<'_, State>, rows: usize, beta: f64, floats: FloatEncoding) -> SampledBatch {
        let (d, a) = (self.cfg.obs_dim, self.cfg.act_dim);
        let cap = self.cfg.capacity as u64;
        let s = &mut *st;
        let table_size = s.size;
        let mut slots = Vec::with_capacity(rows);
        let mut keys = Vec::with_capacity(rows);
        let mut probabilities = Vec::with_capacity(rows);
        let mut importance_weights = Vec::with_capacity(rows);
        if let Some((first_key, len)) = self.uniform_window(s) {
            // Every key in first_key..first_key + len is live with weight 1: draw keys
            // stratified over that range, as the tree walk would over the slots.
            let segment = len as f64 / rows as f64;
            let p = 1.0 / len as f64;
            for i in 0..rows {
                let u = (i as f64 + s.rng.random::<f64>()) * segment;
                let key = first_key + (u as u64).min(len - 1);
                let slot = (key % cap) as usize;
                slots.push(slot);
                keys.push(key);
                probabilities.push(p);
                s.times_sampled[slot] = s.times_sampled[slot].saturating_add(1);
            }
        } else {
            let total = s.tree.total();
            let segment = total / rows as f64;
            for i in 0..rows {
                // Stratified: one draw from each of `rows` equal slices of the total mass.
                let u = (i as f64 + s.rng.random::<f64>()) * segment;
                let slot = s.tree.find(u.min(total));
                let p = s.tree.get(slot) / total;
                slots.push(slot);
                keys.push(s.key[slot]);
                probabilities.push(p);
                s.times_sampled[slot] = s.times_sampled[slot].saturating_add(1);
            }
            // Rows that reached max_times_sampled leave once the whole minibatch is drawn: every
            // draw is from the distribution its probability describes. Removed as they were
            // drawn, the later draws of the same minibatch walked a tree that had lost mass
            // under their stale `total` (biased), and once it had lost all of it returned a
            // never-live slot with probability 0 (a table of one row with max_times_sampled 1,
            // asked for 2 rows). A row may so appear more often than max_times_sampled within
            // one minibatch, never in a later one.
            if self.cfg.max_times_sampled > 0 {
                for &slot in &slots {
                    if s.times_sampled[slot] >= self.cfg.max_times_sampled && s.live[slot] {
                        s.live[slot] = false;
                        s.tree.set(slot, 0.0);
                        s.size -= 1;
                    }
                }
            }
        }
        // w_i = (N·P(i))^−β, normalised by the minibatch's largest weight (as Acme and Dopamine
        // do), so weights only ever scale updates down: w_i / max w = (P_min / P(i))^β. Computed
        // from the ratio, N cancels and nothing overflows: priorities many orders of magnitude
        // apart (|TD error| 1e200 beside 1) made (N·P)^−β infinite in f32 and the weights
        // inf/inf or 0, which `SampledBatch::validate` refuses. A weight below f32's range is
        // kept at its smallest positive value.
        let p_min = probabilities.iter().copied().fold(f64::INFINITY, f64::min);
        importance_weights.extend(probabilities.iter().map(|&p| ((p_min / p).powf(beta) as f32).max(f32::MIN_POSITIVE)));
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
        self.wake();
        out
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
    /// unknown) counts. Keys evicted or removed since they were sampled are skipped. With a
    /// [`Journal`] the updates to stored keys are journaled first, as for `insert`.
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
        if let Some(journal) = s.journal.as_ref().filter(|_| !known.is_empty())
            && let Err(e) = journal.priorities(&known)
        {
            drop(st);
            self.count_refusal(PRIORITIES, &e);
            return Err(e);
        }
        let updated = s.apply_priorities(&known, alpha, epsilon, cap);
        let pending = if known.is_empty() { None } else { st.commit_point() };
        drop(st);
        self.commit(pending, PRIORITIES)?;
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

    /// Wakes every blocked caller with `Closed`; later calls fail the same way. (A
    /// `DurableTable`'s close does this, then writes its final snapshot.)
    pub fn close(&self) {
        self.lock().closed = true;
        self.wake();
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

    /// Every live row with its key, oldest key first, after checking the table's own
    /// bookkeeping (the count of live rows is `size`, each live key lies in the window of the
    /// newest `capacity` keys and sits in its slot, each live weight is finite and ≥ 0).
    /// O(capacity): for the fuzzing harnesses (`crate::fuzzing`) and tests, never a hot path.
    pub(crate) fn stored_rows(&self) -> Result<Vec<StoredRow>, String> {
        let st = self.lock();
        let (d, a, cap) = (self.cfg.obs_dim, self.cfg.act_dim, self.cfg.capacity as u64);
        let live = st.live.iter().filter(|&&l| l).count() as u64;
        if live != st.size {
            return Err(format!("size {} but {live} live slots", st.size));
        }
        if st.size > cap {
            return Err(format!("size {} above capacity {cap}", st.size));
        }
        let window = st.next_key.saturating_sub(cap)..st.next_key;
        let mut rows = Vec::with_capacity(live as usize);
        for slot in (0..self.cfg.capacity).filter(|&s| st.live[s]) {
            let key = st.key[slot];
            if !window.contains(&key) || key % cap != slot as u64 {
                return Err(format!("live slot {slot} holds key {key}; the window is {window:?}"));
            }
            let w = st.tree.get(slot);
            if !(w.is_finite() && w >= 0.0) {
                return Err(format!("live slot {slot} has weight {w}"));
            }
            rows.push(StoredRow {
                key,
                obs: st.obs[slot * d..(slot + 1) * d].to_vec(),
                action: st.action[slot * a..(slot + 1) * a].to_vec(),
                reward: st.reward[slot],
                next_obs: st.next_obs[slot * d..(slot + 1) * d].to_vec(),
                terminal: st.terminal[slot],
                truncated: st.truncated[slot],
                episode_id: st.episode_id[slot],
                step: st.step[slot],
                policy_version: st.policy_version[slot],
            });
        }
        rows.sort_by_key(|r| r.key);
        Ok(rows)
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

/// One stored row as [`Table::stored_rows`] copies it out.
#[derive(Clone, Debug, PartialEq)]
pub(crate) struct StoredRow {
    pub key: u64,
    pub obs: Vec<f32>,
    pub action: Vec<f32>,
    pub reward: f32,
    pub next_obs: Vec<f32>,
    pub terminal: bool,
    pub truncated: bool,
    pub episode_id: u64,
    pub step: u32,
    pub policy_version: u64,
}

/// A restore in progress: a new table's lock, held from [`Table::restore`] until
/// [`Restore::finish`], while a checkpoint and then the journal are fed in (recovery in
/// `persist/recovery.rs` reads them from disk). Nothing is journaled again. The batches handed
/// in must have passed `validate` for this table's dims, `rows` being what it returned.
pub(crate) struct Restore<'a> {
    cfg: &'a TableConfig,
    st: MutexGuard<'a, State>,
    /// Slots whose row data came in (a live slot without it cannot be served).
    filled: Vec<bool>,
    /// The checkpoint's sample count (the rate limiter's, restored at the end).
    samples: u64,
}

/// What a finished [`Restore`] left.
#[derive(Clone, Copy, Debug)]
pub(crate) struct Restored {
    /// Rows stored.
    pub rows: u64,
    /// Rows ever inserted (the next key).
    pub next_key: u64,
    /// Rows the checkpoint listed as stored whose data never came (dropped).
    pub rows_lost: u64,
}

impl Restore<'_> {
    /// Loads a checkpoint of a table of this capacity. `keep_priorities` false (it was taken
    /// under another sampler) resets every stored row's weight, and the largest, to 1.
    pub fn load(&mut self, cp: TableCheckpoint, keep_priorities: bool) {
        debug_assert_eq!((cp.weights.len(), cp.live.len(), cp.times_sampled.len()), (self.cfg.capacity, self.cfg.capacity, self.cfg.capacity));
        let s = &mut *self.st;
        s.max_weight = if keep_priorities { cp.max_weight } else { 1.0 };
        for (slot, ((&live, &times), &weight)) in cp.live.iter().zip(&cp.times_sampled).zip(&cp.weights).enumerate().take(self.cfg.capacity) {
            s.live[slot] = live;
            s.times_sampled[slot] = times;
            if live {
                s.tree.set(slot, if keep_priorities { weight } else { 1.0 });
            }
        }
        s.size = s.live.iter().filter(|&&l| l).count() as u64;
        s.next_key = cp.next_key;
        s.actors = cp.actors.into_iter().collect();
        // The sampler continues its random stream where the checkpoint left it, so the
        // minibatches drawn after a restart are those the table would have drawn anyway
        // (without it the stream restarts from the table's seed).
        if let Some(rng) = cp.sampler_rng {
            s.rng = rng;
        }
        self.samples = cp.samples;
    }

    /// Key the next re-applied insert gets.
    pub fn next_key(&self) -> u64 {
        self.st.next_key
    }

    /// Numbers rows from `key` on: the journal's history before it is gone (no checkpoint).
    pub fn start_at_key(&mut self, key: u64) {
        self.st.next_key = key;
    }

    /// The data of rows `first_key..first_key + rows` that the checkpoint already counts:
    /// written to their slots; nothing else changes.
    pub fn fill_rows(&mut self, first_key: u64, batch: &TransitionBatch, rows: usize) {
        let filled = &mut self.filled;
        self.st.place_rows(first_key, batch, rows, self.cfg, |_, slot, n| filled[slot..slot + n].fill(true));
    }

    /// A journaled insert after the checkpoint, applied as [`Table::insert`] applied it (at
    /// the next key, evicting, with its actor's de-duplication mark and counts), without the
    /// rate limiter's wait.
    pub fn insert(&mut self, batch: &TransitionBatch, rows: usize, unix_ms: u64) {
        let (first_key, cap) = (self.st.next_key, self.cfg.capacity as u64);
        for r in 0..rows {
            self.filled[((first_key + r as u64) % cap) as usize] = true;
        }
        self.st.store_rows(batch, rows, self.cfg);
        self.st.note_insert(batch, rows, unix_ms);
    }

    /// A journaled priority update after the checkpoint (nothing on a uniform table).
    pub fn priorities(&mut self, pairs: &[(u64, f64)]) {
        if let SamplerConfig::Prioritized { alpha, epsilon, .. } = self.cfg.sampler {
            self.st.apply_priorities(pairs, alpha, epsilon, self.cfg.capacity as u64);
        }
    }

    /// Drops every live row whose data did not come (loudly: the count is returned), recounts
    /// and restores the rate limiter's counters; releases the lock.
    pub fn finish(mut self) -> Restored {
        let cap = self.cfg.capacity as u64;
        let s = &mut *self.st;
        let window = s.next_key.saturating_sub(cap);
        let mut lost = 0u64;
        for (slot, &has_data) in self.filled.iter().enumerate() {
            if s.live[slot] && !(has_data && s.key[slot] >= window && s.key[slot] < s.next_key) {
                s.live[slot] = false;
                s.tree.set(slot, 0.0);
                lost += 1;
            }
        }
        s.size = s.live.iter().filter(|&&l| l).count() as u64;
        s.limiter.restore(s.next_key, self.samples);
        Restored { rows: s.size, next_key: s.next_key, rows_lost: lost }
    }
}

#[cfg(test)]
mod tests {
    use mapless_proto::{Transition, TransitionBatchBuilder};

    use super::*;
    use crate::config::RateLimiterConfig;

    fn cfg() -> TableConfig {
        TableConfig {
            capacity: 16,
            obs_dim: 2,
            act_dim: 1,
            sampler: SamplerConfig::Prioritized { alpha: 0.5, beta: 0.4, epsilon: 0.01 },
            rate_limiter: RateLimiterConfig { min_size_to_sample: 1, samples_per_insert: None, error_buffer: 0.0 },
            ..TableConfig::default()
        }
    }

    fn batch(seq: u64, rows: usize) -> TransitionBatch {
        let mut b = TransitionBatchBuilder::new(2, 1);
        for i in 0..rows {
            let r = (seq * 100 + i as u64) as f32;
            b.push(Transition { obs: &[r, 1.0], action: &[0.5], reward: r, next_obs: &[r, 2.0], terminal: false, truncated: false, episode_id: seq, step: i as u32, policy_version: 1 }).unwrap();
        }
        b.finish("a", seq)
    }

    #[test]
    fn a_checkpoint_and_the_rows_restore_a_table_that_samples_as_the_original() {
        let original = Table::new(cfg(), 1).unwrap();
        let batches: Vec<TransitionBatch> = (1..=4).map(|s| batch(s, 6)).collect(); // 24 rows, ring of 16
        for b in &batches {
            original.insert(b, None).unwrap();
        }
        let s = original.sample(8, None, None).unwrap();
        original.update_priorities(&s.keys, &s.keys.iter().map(|k| (k % 3) as f64).collect::<Vec<_>>()).unwrap();
        let cp = original.checkpoint();

        // The checkpoint, then the rows it counts; batch 4's rows left out are dropped.
        let restored = Table::new(cfg(), 99).unwrap();
        let mut r = restored.restore();
        r.load(cp.clone(), true);
        for (i, b) in batches.iter().enumerate().take(3) {
            r.fill_rows(i as u64 * 6, b, 6);
        }
        let done = r.finish();
        assert_eq!((done.next_key, done.rows_lost, done.rows), (24, 6, 10));

        // With every row back, and an insert journaled after the checkpoint re-applied as the
        // live insert applied it, the restored table is the original: same minibatches.
        original.insert(&batch(5, 6), None).unwrap();
        let restored = Table::new(cfg(), 99).unwrap();
        let mut r = restored.restore();
        r.load(cp, true);
        for (i, b) in batches.iter().enumerate() {
            r.fill_rows(i as u64 * 6, b, 6);
        }
        assert_eq!(r.next_key(), 24);
        r.insert(&batch(5, 6), 6, 0);
        assert_eq!(r.finish().rows_lost, 0);
        assert_eq!((original.size(), original.next_key(), original.actors()["a"].last_sequence), (restored.size(), restored.next_key(), restored.actors()["a"].last_sequence));
        for _ in 0..2 {
            assert_eq!(original.sample(8, None, None).unwrap(), restored.sample(8, None, None).unwrap());
        }
        assert_eq!(original.sample(8, None, None).unwrap(), restored.sample(8, None, None).unwrap());
    }
}
