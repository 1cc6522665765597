//! The write-ahead log: every change to a table's content or priorities, in the order the
//! table applied it, as checksummed records in numbered segment files.
//!
//! ```text
//!   <dir>/wal/seg-<first_lsn:020>.log       rotated when the next record would pass segment_bytes
//!   <dir>/wal/corrupt/…                     what recovery cut off (kept for inspection, never read)
//!
//!   segment  = header record*
//!   header   = "MPLSWAL\0" | version u32 = 1 | reserved u32 = 0 | first_lsn u64      (24 bytes)
//!   record   = len u32 | crc u32 | body[len]                            (little-endian)
//!   body     = kind u8 | lsn u64 | payload                 crc = CRC-32 (IEEE) of the body
//!   Insert     (kind 1): first_key u64 | unix_ms u64 | TransitionBatch (prost bytes)
//!   Priorities (kind 2): count u32 | count × (key u64 | priority f64)        raw p, before α/ε
//! ```
//!
//! Invariants: LSNs start at 1 and increase by one per record with no gaps, across segments
//! (segment n+1 starts at segment n's last LSN + 1); a record is complete on disk or, after a
//! crash, the torn tail of the newest segment. Insert records carry the key of their first row
//! and the actor id and sequence of their batch, so row numbering and de-duplication are both
//! rebuilt from the log. Sampling is not logged (see `snapshot.rs` for what that costs).
//!
//! Guarantees: a record is acknowledged once `write(2)` returned for all of it, so it survives
//! the process dying (kill -9); `FsyncPolicy` decides what survives power loss (every record
//! under `always`, all but the last `interval_ms` under `interval_ms`). Under `always` the
//! fsync is a group commit ([`WalSync::commit`]): records are written under the table's lock,
//! the caller then waits without that lock for one fsync that covers its record and every
//! other record written before the fsync began. Recovery detects a torn record (cut short: a
//! crash mid-write) and a corrupt one (bad length, checksum, LSN, kind or payload), keeps
//! everything before the first such record and sets the rest aside.
//!
//! Faults of the disk (docs/reliability.md, "Faults of the disk"):
//! - A failed write (ENOSPC on a full disk, EIO) is rolled back: the file is truncated to the
//!   last whole record, the record's LSN is not used, the caller gets the error (`DiskFull`
//!   or `Storage`), and the next append simply tries again, so the log accepts records again
//!   as soon as space returns, without a restart. If the rollback itself fails the tail is
//!   unknown and the log refuses appends until it is reopened (recovery cuts the tail).
//! - A failed fsync is not retried: the log refuses every append, and every acknowledgement
//!   that would need the disk, until it is reopened. After a failed fsync Linux may already
//!   have marked the unwritten pages clean (and reports the error to one fsync caller only),
//!   so a second fsync that succeeds proves nothing about the records written before it:
//!   PostgreSQL's "fsyncgate" (2018) lesson. Rewriting those records into a new segment would
//!   need the old segment cut back, which is itself a write to the failing file. Reopening
//!   (a restart) recovers from what the disk really holds: everything acknowledged as durable
//!   is there; a record whose fsync failed was never acknowledged, and comes back or not.
//! - Each fault is logged once, when the log goes from accepting to refusing appends (and once
//!   more when it accepts again); every refused change is counted by the table
//!   (`replay_storage_refusals_total`), not logged.
//!
//! Threading: [`Wal`] is the table's journal (`persist/mod.rs`, behind its own mutex); the
//! table appends to it under the table's lock, so log order is apply order. Forcing data to
//! disk (fsync) happens through [`WalSync`], which background threads use without either lock.

use std::fs::{self, File, OpenOptions};
use std::os::unix::fs::FileExt;
use std::path::{Path, PathBuf};
use std::sync::atomic::{AtomicBool, AtomicU64, Ordering};
use std::sync::{Arc, Mutex, MutexGuard};

use mapless_proto::atomic_file::{AtomicWriteError, Durability, is_temp_file_name, write_file_atomically_with};

use crate::clock::unix_ms;
use crate::config::FsyncPolicy;
use crate::error::ReplayError;

pub(crate) const SEGMENT_MAGIC: &[u8; 8] = b"MPLSWAL\0";
pub(crate) const FORMAT_VERSION: u32 = 1;
/// magic 8 | version 4 | reserved 4 | first_lsn 8.
pub(crate) const SEGMENT_HEADER_BYTES: usize = 24;
/// len 4 | crc 4.
const RECORD_HEADER_BYTES: usize = 8;
/// kind 1 | lsn 8.
const BODY_FIXED_BYTES: usize = 9;
/// A length field above this is corruption, not a record (the largest legal record, a
/// 16 MiB message plus framing, is far below it).
pub(crate) const MAX_RECORD_BYTES: usize = 256 << 20;
pub(crate) const KIND_INSERT: u8 = 1;
pub(crate) const KIND_PRIORITIES: u8 = 2;

pub(crate) fn storage(path: &Path, problem: impl std::fmt::Display) -> ReplayError {
    ReplayError::Storage { path: path.to_path_buf(), problem: problem.to_string() }
}

pub(crate) fn segment_name(first_lsn: u64) -> String {
    format!("seg-{first_lsn:020}.log")
}

/// `seg-<20 digits>.log` → first LSN.
fn parse_segment_name(name: &str) -> Option<u64> {
    parse_numbered_name(name, "seg-", ".log")
}

/// `<prefix><20 digits><suffix>` → the number (log segments and snapshots are named so).
pub(crate) fn parse_numbered_name(name: &str, prefix: &str, suffix: &str) -> Option<u64> {
    let digits = name.strip_prefix(prefix)?.strip_suffix(suffix)?;
    if digits.len() != 20 || !digits.bytes().all(|b| b.is_ascii_digit()) {
        return None;
    }
    digits.parse().ok()
}

/// A failed atomic write (a snapshot, a new log segment) as a storage error: the path the
/// failed step acted on, the step and what the OS said.
pub(crate) fn atomic_write_storage(e: AtomicWriteError) -> ReplayError {
    ReplayError::io(&e.path, e.step, &e.error)
}

/// fsyncs a directory so that files created, renamed or removed in it survive power loss.
pub(crate) fn sync_dir(dir: &Path) -> Result<(), ReplayError> {
    File::open(dir).and_then(|d| d.sync_all()).map_err(|e| storage(dir, format!("fsync directory: {e}")))
}

/// Where and why the log stops being readable.
#[derive(Clone, Debug, PartialEq, Eq)]
pub struct StorageFault {
    /// The damaged file.
    pub path: PathBuf,
    /// Byte offset of the first byte that could not be used.
    pub offset: u64,
    /// What was wrong ("torn: …" for a record cut short, "corrupt: …" otherwise).
    pub reason: String,
}

impl std::fmt::Display for StorageFault {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        write!(f, "{} at byte {}: {}", self.path.display(), self.offset, self.reason)
    }
}

// ---------------------------------------------------------------------------------------------
// Payloads

/// Appends an Insert payload (first key, wall-clock time, prost-encoded batch).
pub(crate) fn put_insert_payload(buf: &mut Vec<u8>, first_key: u64, unix_ms: u64, batch_bytes: &[u8]) {
    buf.extend_from_slice(&first_key.to_le_bytes());
    buf.extend_from_slice(&unix_ms.to_le_bytes());
    buf.extend_from_slice(batch_bytes);
}

/// Splits an Insert payload into (first key, unix ms, prost bytes).
pub(crate) fn split_insert_payload(p: &[u8]) -> Result<(u64, u64, &[u8]), String> {
    if p.len() < 16 {
        return Err(format!("corrupt: insert payload of {} bytes is shorter than its 16-byte prefix", p.len()));
    }
    Ok((le_u64(&p[0..8]), le_u64(&p[8..16]), &p[16..]))
}

pub(crate) fn put_priorities_payload(buf: &mut Vec<u8>, pairs: &[(u64, f64)]) {
    buf.extend_from_slice(&(pairs.len() as u32).to_le_bytes());
    for (k, p) in pairs {
        buf.extend_from_slice(&k.to_le_bytes());
        buf.extend_from_slice(&p.to_le_bytes());
    }
}

pub(crate) fn parse_priorities_payload(p: &[u8]) -> Result<Vec<(u64, f64)>, String> {
    if p.len() < 4 {
        return Err("corrupt: priorities payload shorter than its count".into());
    }
    let n = le_u32(&p[0..4]) as usize;
    if p.len() != 4 + n * 16 {
        return Err(format!("corrupt: priorities payload of {} bytes does not hold {n} pairs", p.len()));
    }
    let pairs: Vec<(u64, f64)> = p[4..].chunks_exact(16).map(|c| (le_u64(&c[0..8]), f64::from_le_bytes(c[8..16].try_into().unwrap_or([0; 8])))).collect();
    // The table logs only priorities it accepted (finite, ≥ 0: `Table::update_priorities`);
    // any other value would enter the sampler's sum tree as a NaN or negative weight.
    if let Some((key, p)) = pairs.iter().find(|(_, p)| !(p.is_finite() && *p >= 0.0)) {
        return Err(format!("corrupt: priority of key {key} is {p}, never a logged value (finite and ≥ 0)"));
    }
    Ok(pairs)
}

fn le_u32(b: &[u8]) -> u32 {
    u32::from_le_bytes(b.try_into().unwrap_or([0; 4]))
}
fn le_u64(b: &[u8]) -> u64 {
    u64::from_le_bytes(b.try_into().unwrap_or([0; 8]))
}

// ---------------------------------------------------------------------------------------------
// Reading (recovery)

/// One record as read back: its LSN, kind and payload.
#[derive(Debug)]
pub(crate) struct RawRecord<'a> {
    pub lsn: u64,
    pub kind: u8,
    pub payload: &'a [u8],
}

/// A segment file found on disk, with what a framing scan made of it.
#[derive(Debug)]
pub(crate) struct ScannedSegment {
    pub path: PathBuf,
    pub first_lsn: u64,
    /// Bytes from the start that hold a valid header and whole, valid records.
    pub valid_len: u64,
    /// LSN of the last valid record (first_lsn − 1 when none).
    pub last_lsn: u64,
    /// The table's next key after this segment's last Insert record (set by [`replay`]).
    pub key_end: Option<u64>,
}

/// The framing-level view of the whole log: valid segments in order and the first fault.
#[derive(Debug)]
pub(crate) struct LogScan {
    pub dir: PathBuf,
    /// Segments up to and including the one holding the fault (whose `valid_len` stops there).
    pub segments: Vec<ScannedSegment>,
    /// Segments after the fault: unusable, moved to `corrupt/` when the log is reopened.
    pub after_fault: Vec<PathBuf>,
    pub fault: Option<StorageFault>,
}

impl LogScan {
    /// LSN of the last valid record, or `None` when the log holds no segment.
    pub fn end_lsn(&self) -> Option<u64> {
        self.segments.iter().rev().find(|s| s.valid_len >= SEGMENT_HEADER_BYTES as u64).map(|s| s.last_lsn)
    }

    /// First LSN the log can replay (that of the first segment with a valid header).
    pub fn start_lsn(&self) -> Option<u64> {
        self.segments.iter().find(|s| s.valid_len >= SEGMENT_HEADER_BYTES as u64).map(|s| s.first_lsn)
    }
}

/// Lists `seg-*.log` files in LSN order.
fn list_segments(dir: &Path) -> Result<Vec<(u64, PathBuf)>, ReplayError> {
    let mut out = Vec::new();
    let entries = fs::read_dir(dir).map_err(|e| storage(dir, format!("list: {e}")))?;
    for entry in entries {
        let entry = entry.map_err(|e| storage(dir, format!("list: {e}")))?;
        let name = entry.file_name();
        let Some(name) = name.to_str() else { continue };
        match parse_segment_name(name) {
            Some(lsn) if entry.file_type().is_ok_and(|t| t.is_file()) => out.push((lsn, entry.path())),
            _ => {}
        }
    }
    out.sort();
    Ok(out)
}

/// Checks a segment header; returns its first LSN.
fn check_header(data: &[u8], named_lsn: u64) -> Result<u64, String> {
    if data.len() < SEGMENT_HEADER_BYTES {
        return Err(format!("torn: segment header is {} of {SEGMENT_HEADER_BYTES} bytes", data.len()));
    }
    if &data[0..8] != SEGMENT_MAGIC {
        return Err("corrupt: not a mapless log segment (bad magic)".into());
    }
    let version = le_u32(&data[8..12]);
    if version != FORMAT_VERSION {
        return Err(format!("corrupt: segment format version {version}, this build reads {FORMAT_VERSION}"));
    }
    let first = le_u64(&data[16..24]);
    if first != named_lsn {
        return Err(format!("corrupt: header says first LSN {first}, file name says {named_lsn}"));
    }
    Ok(first)
}

/// Reads the record at `pos`: `Ok(None)` at the clean end of the data, `Err(reason)` for a
/// torn or corrupt record.
fn read_record(data: &[u8], pos: usize, expected_lsn: u64) -> Result<Option<(RawRecord<'_>, usize)>, String> {
    let rest = &data[pos..];
    if rest.is_empty() {
        return Ok(None);
    }
    if rest.len() < RECORD_HEADER_BYTES {
        return Err(format!("torn: record header cut short ({} of {RECORD_HEADER_BYTES} bytes)", rest.len()));
    }
    let len = le_u32(&rest[0..4]) as usize;
    let crc = le_u32(&rest[4..8]);
    if !(BODY_FIXED_BYTES..=MAX_RECORD_BYTES).contains(&len) {
        return Err(format!("corrupt: record length {len} outside {BODY_FIXED_BYTES}..={MAX_RECORD_BYTES}"));
    }
    if rest.len() - RECORD_HEADER_BYTES < len {
        return Err(format!("torn: record of {len} bytes cut short ({} present)", rest.len() - RECORD_HEADER_BYTES));
    }
    let body = &rest[RECORD_HEADER_BYTES..RECORD_HEADER_BYTES + len];
    let actual = crc32fast::hash(body);
    if actual != crc {
        return Err(format!("corrupt: checksum mismatch (stored {crc:#010x}, computed {actual:#010x})"));
    }
    let kind = body[0];
    let lsn = le_u64(&body[1..9]);
    if lsn != expected_lsn {
        return Err(format!("corrupt: LSN {lsn} where {expected_lsn} was expected"));
    }
    if kind != KIND_INSERT && kind != KIND_PRIORITIES {
        return Err(format!("corrupt: unknown record kind {kind}"));
    }
    Ok(Some((RawRecord { lsn, kind, payload: &body[BODY_FIXED_BYTES..] }, pos + RECORD_HEADER_BYTES + len)))
}

/// Scans every segment's framing (headers, lengths, checksums, LSN order) and finds the first
/// fault. Reads each file once; changes nothing on disk.
pub(crate) fn scan(dir: &Path) -> Result<LogScan, ReplayError> {
    let mut scan = LogScan { dir: dir.to_path_buf(), segments: Vec::new(), after_fault: Vec::new(), fault: None };
    let mut expected: Option<u64> = None;
    for (named_lsn, path) in list_segments(dir)? {
        if scan.fault.is_some() {
            scan.after_fault.push(path);
            continue;
        }
        let data = fs::read(&path).map_err(|e| storage(&path, format!("read: {e}")))?;
        let mut seg = ScannedSegment { path: path.clone(), first_lsn: named_lsn, valid_len: 0, last_lsn: named_lsn.saturating_sub(1), key_end: None };
        let header = check_header(&data, named_lsn).and_then(|first| match expected {
            Some(e) if first != e => Err(format!("corrupt: segment starts at LSN {first} but the previous one ends at {}", e - 1)),
            _ if first == 0 => Err("corrupt: LSN 0 is never used".into()),
            _ => Ok(first),
        });
        match header {
            Err(reason) => scan.fault = Some(StorageFault { path: path.clone(), offset: 0, reason }),
            Ok(first) => {
                let mut pos = SEGMENT_HEADER_BYTES;
                let mut next = first;
                loop {
                    match read_record(&data, pos, next) {
                        Ok(Some((_, end))) => {
                            pos = end;
                            next += 1;
                        }
                        Ok(None) => break,
                        Err(reason) => {
                            scan.fault = Some(StorageFault { path: path.clone(), offset: pos as u64, reason });
                            break;
                        }
                    }
                }
                seg.valid_len = pos as u64;
                seg.last_lsn = next - 1;
                expected = Some(next);
            }
        }
        scan.segments.push(seg);
    }
    Ok(scan)
}

/// Calls `visit` on every valid record, in order; `visit` returns the table's next key after
/// an Insert record (`None` for other kinds). `visit` may refuse a record (`Err(Ok(reason))`),
/// e.g. one that will not decode: that record becomes the fault and the scan's valid region is
/// cut back to it. `Err(Err(e))` aborts recovery altogether (a configuration mismatch: nothing
/// on disk is wrong, so nothing may be cut). Returns the number of records visited.
pub(crate) fn replay(scan: &mut LogScan, mut visit: impl FnMut(&RawRecord<'_>) -> Result<Option<u64>, Result<String, ReplayError>>) -> Result<u64, ReplayError> {
    let mut count = 0u64;
    for i in 0..scan.segments.len() {
        let seg = &scan.segments[i];
        if seg.valid_len < SEGMENT_HEADER_BYTES as u64 {
            continue;
        }
        let path = seg.path.clone();
        let mut data = fs::read(&path).map_err(|e| storage(&path, format!("read: {e}")))?;
        data.truncate(seg.valid_len as usize);
        let mut pos = SEGMENT_HEADER_BYTES;
        let mut next = seg.first_lsn;
        loop {
            let (rec, end) = match read_record(&data, pos, next) {
                Ok(Some(r)) => r,
                Ok(None) => break,
                // The file changed since the scan (another writer?): give up rather than guess.
                Err(reason) => return Err(storage(&path, format!("changed during recovery at byte {pos}: {reason}"))),
            };
            match visit(&rec) {
                Ok(None) => {}
                Ok(Some(key_end)) => scan.segments[i].key_end = Some(key_end),
                Err(Ok(reason)) => {
                    // Cut here: this segment ends at the bad record, later ones are unusable.
                    let later: Vec<PathBuf> = scan.segments.drain(i + 1..).map(|s| s.path).collect();
                    scan.after_fault.splice(0..0, later);
                    let seg = &mut scan.segments[i];
                    seg.valid_len = pos as u64;
                    seg.last_lsn = next - 1;
                    scan.fault = Some(StorageFault { path, offset: pos as u64, reason });
                    return Ok(count);
                }
                Err(Err(fatal)) => return Err(fatal),
            }
            count += 1;
            pos = end;
            next += 1;
        }
    }
    Ok(count)
}

// ---------------------------------------------------------------------------------------------
// Writing

/// The fsync side of the log, shared with the background flusher, the snapshot writer and
/// (under `always`) every caller waiting for its acknowledgement.
///
/// Group commit: `written_lsn` is raised after each record is written; a sync reads it
/// *before* it fsyncs, and afterwards raises `durable_lsn` to what it read. A caller waiting
/// for LSN n takes `sync_lock` only while `durable_lsn < n`, and rechecks it once it holds the
/// lock: callers that queued behind one fsync find their records covered by it and leave
/// without another. Cost: one fsync per group, whatever the number of concurrent writers.
pub(crate) struct WalSync {
    dir: PathBuf,
    files: Mutex<SyncFiles>,
    /// Set after every write, cleared by the flusher before it syncs.
    dirty: AtomicBool,
    /// One sync at a time, so "sync returned" means everything written before the call is on disk.
    sync_lock: Mutex<()>,
    /// Set when an fsync failed: what was acknowledged may not be on disk, so appends stop.
    failed: Mutex<Option<String>>,
    /// LSN of the last record written to the OS (0 before the first).
    written_lsn: AtomicU64,
    /// LSN up to which every record is known to be on stable storage.
    durable_lsn: AtomicU64,
    /// fsync rounds that succeeded (each may cover many records).
    fsyncs: AtomicU64,
    /// Faults logged: one per change from accepting to refusing appends.
    faults_reported: AtomicU64,
    #[cfg(test)]
    pub(crate) inject: InjectedFaults,
}

/// The test seam of the log's file layer: errors (as errno values) that the next writes and
/// fsyncs return instead of touching the disk, and a hook run inside a sync round before it
/// decides what the round covers. Test builds only.
#[cfg(test)]
#[derive(Default)]
pub(crate) struct InjectedFaults {
    /// The next writes fail with these errnos, in order; each first writes half its record,
    /// as a disk that fills mid-record does.
    pub writes: Mutex<std::collections::VecDeque<i32>>,
    /// The next fsyncs of the current segment fail with these errnos, in order.
    pub fsyncs: Mutex<std::collections::VecDeque<i32>>,
    #[allow(clippy::type_complexity)]
    pub before_sync: Mutex<Option<Box<dyn Fn(&WalSync) + Send + Sync>>>,
}

#[cfg(test)]
impl InjectedFaults {
    fn next(q: &Mutex<std::collections::VecDeque<i32>>) -> Option<std::io::Error> {
        lock(q).pop_front().map(std::io::Error::from_raw_os_error)
    }
}

struct SyncFiles {
    current: (PathBuf, Arc<File>),
    /// Segments closed since the last sync, by path: fsync through a fresh descriptor flushes
    /// the file's pages all the same, and no descriptor is held per segment.
    retired: Vec<PathBuf>,
    /// A segment was created since the last sync (its directory entry needs an fsync).
    dir_dirty: bool,
}

fn lock<T>(m: &Mutex<T>) -> MutexGuard<'_, T> {
    m.lock().unwrap_or_else(|p| p.into_inner())
}

impl WalSync {
    fn new(dir: PathBuf, current: (PathBuf, Arc<File>), last_lsn: u64) -> WalSync {
        WalSync {
            dir,
            files: Mutex::new(SyncFiles { current, retired: Vec::new(), dir_dirty: false }),
            dirty: AtomicBool::new(false),
            sync_lock: Mutex::new(()),
            failed: Mutex::new(None),
            written_lsn: AtomicU64::new(last_lsn),
            durable_lsn: AtomicU64::new(0),
            fsyncs: AtomicU64::new(0),
            faults_reported: AtomicU64::new(0),
            #[cfg(test)]
            inject: InjectedFaults::default(),
        }
    }

    /// Forces everything written so far (records, new segment files) to stable storage.
    /// Fails at once, touching nothing, after an earlier fsync failed (see the module doc).
    pub fn sync(&self) -> Result<(), ReplayError> {
        let _one = lock(&self.sync_lock);
        self.sync_locked()
    }

    /// Returns once the record at `lsn` and all before it are on stable storage, syncing if
    /// no other caller's fsync covered them (group commit; see the type's doc). Fails, and
    /// the caller must not acknowledge, when the log is refusing after a failed fsync.
    pub fn commit(&self, lsn: u64) -> Result<(), ReplayError> {
        self.check()?;
        if self.durable_lsn.load(Ordering::SeqCst) >= lsn {
            return Ok(());
        }
        let _one = lock(&self.sync_lock);
        if self.durable_lsn.load(Ordering::SeqCst) >= lsn {
            return self.check();
        }
        self.sync_locked()
    }

    /// `Err` while the log refuses appends after a failed fsync.
    pub fn check(&self) -> Result<(), ReplayError> {
        match lock(&self.failed).as_ref() {
            Some(why) => Err(storage(&self.dir, format!("log is read-only after a failed fsync (reopen the replay to recover from what the disk holds): {why}"))),
            None => Ok(()),
        }
    }

    /// One sync round; `sync_lock` is held.
    fn sync_locked(&self) -> Result<(), ReplayError> {
        self.check()?;
        #[cfg(test)]
        if let Some(hook) = lock(&self.inject.before_sync).as_ref() {
            hook(self);
        }
        // Read before the fsync: every record up to here is in a file this round syncs.
        let covers = self.written_lsn.load(Ordering::SeqCst);
        self.dirty.store(false, Ordering::SeqCst);
        let (retired, current, dir_dirty) = {
            let mut f = lock(&self.files);
            let dir_dirty = std::mem::replace(&mut f.dir_dirty, false);
            (std::mem::take(&mut f.retired), f.current.clone(), dir_dirty)
        };
        let result: Result<(), ReplayError> = (|| {
            for path in &retired {
                match File::open(path) {
                    Ok(f) => f.sync_data().map_err(|e| ReplayError::io(path, "fsync", &e))?,
                    // Deleted after a snapshot that had already synced it.
                    Err(e) if e.kind() == std::io::ErrorKind::NotFound => {}
                    Err(e) => return Err(ReplayError::io(path, "open to fsync", &e)),
                }
            }
            #[cfg(test)]
            if let Some(e) = InjectedFaults::next(&self.inject.fsyncs) {
                return Err(ReplayError::io(&current.0, "fsync", &e));
            }
            current.1.sync_data().map_err(|e| ReplayError::io(&current.0, "fsync", &e))?;
            if dir_dirty {
                sync_dir(&self.dir)?;
            }
            Ok(())
        })();
        match &result {
            Ok(()) => {
                self.durable_lsn.fetch_max(covers, Ordering::SeqCst);
                self.fsyncs.fetch_add(1, Ordering::Relaxed);
            }
            Err(e) => {
                let mut failed = lock(&self.failed);
                if failed.is_none() {
                    *failed = Some(e.to_string());
                    self.faults_reported.fetch_add(1, Ordering::Relaxed);
                    tracing::error!(log = %self.dir.display(), error = %e, "log fsync failed: records written since the last fsync may be lost; inserts are refused until the replay is reopened");
                }
            }
        }
        result
    }

    /// Syncs if anything was written since the last sync (the interval flusher's tick).
    pub fn sync_if_dirty(&self) -> Result<(), ReplayError> {
        if self.dirty.load(Ordering::SeqCst) { self.sync() } else { Ok(()) }
    }

    /// LSN of the last record written to the OS.
    #[cfg(test)]
    pub fn written_lsn(&self) -> u64 {
        self.written_lsn.load(Ordering::SeqCst)
    }

    /// LSN up to which every record is known to be on stable storage.
    #[cfg(test)]
    pub fn durable_lsn(&self) -> u64 {
        self.durable_lsn.load(Ordering::SeqCst)
    }

    /// fsync rounds that succeeded since the log was opened.
    pub fn fsyncs(&self) -> u64 {
        self.fsyncs.load(Ordering::Relaxed)
    }

    /// Faults logged since the log was opened (one per change from accepting to refusing).
    #[cfg(test)]
    pub fn faults_reported(&self) -> u64 {
        self.faults_reported.load(Ordering::Relaxed)
    }
}

/// A closed segment's extent, for deciding when it may be deleted.
#[derive(Debug)]
struct ClosedSegment {
    path: PathBuf,
    last_lsn: u64,
    /// The table's next key after the last row this or any earlier segment inserted: every
    /// row of the segment has a key below it.
    key_end: u64,
}

/// The appending side of the log (the table's journal: appended to under the table lock).
pub(crate) struct Wal {
    dir: PathBuf,
    policy: FsyncPolicy,
    segment_bytes: u64,
    current: File,
    current_path: PathBuf,
    current_len: u64,
    closed: Vec<ClosedSegment>,
    next_lsn: u64,
    key_end: u64,
    buf: Vec<u8>,
    /// Set when a failed write could not be rolled back: the segment's tail is unknown, so
    /// nothing more may be appended (recovery will cut the tail on the next open).
    poisoned: Option<String>,
    /// Appends refused in a row by failed writes (0 while writes succeed): the first is
    /// logged, the rest only counted, and the first success after them logged once.
    refused_in_a_row: u64,
    sync: Arc<WalSync>,
}

impl Wal {
    /// Reopens the log after recovery: moves everything past the scan's fault into
    /// `corrupt/` (the damaged segment's cut-off tail is copied there before it is truncated),
    /// and appends after the last valid record. `next_lsn_if_empty` starts the log when no
    /// segment survives; `key_end` is the table's next key after recovery.
    pub fn reopen(scan: &LogScan, policy: FsyncPolicy, segment_bytes: u64, next_lsn_if_empty: u64, key_end: u64) -> Result<Wal, ReplayError> {
        let dir = scan.dir.clone();
        // A segment whose creation a crash interrupted (never renamed, so never written to):
        // the atomic write's temporary file, or `seg-<lsn>.log.tmp` of older builds.
        for entry in fs::read_dir(&dir).map_err(|e| storage(&dir, format!("list: {e}")))?.flatten() {
            let name = entry.file_name();
            if name.to_str().is_some_and(|n| (n.starts_with("seg-") && n.ends_with(".log.tmp")) || is_temp_file_name(n)) {
                let p = entry.path();
                fs::remove_file(&p).map_err(|e| storage(&p, format!("remove: {e}")))?;
            }
        }
        let quarantine = dir.join("corrupt");
        let stamp = unix_ms();
        let mut moved_any = false;
        let quarantine_dir = || -> Result<(), ReplayError> { fs::create_dir_all(&quarantine).map_err(|e| storage(&quarantine, format!("create: {e}"))) };
        // Whole segments past the fault.
        for path in &scan.after_fault {
            quarantine_dir()?;
            let name = path.file_name().map(|n| n.to_string_lossy().into_owned()).unwrap_or_default();
            let to = quarantine.join(format!("{name}.{stamp}"));
            fs::rename(path, &to).map_err(|e| storage(path, format!("move to {}: {e}", to.display())))?;
            moved_any = true;
        }
        // The damaged segment: keep its valid prefix; a segment without a valid header goes whole.
        let mut kept: Vec<&ScannedSegment> = Vec::new();
        for seg in &scan.segments {
            let len = fs::metadata(&seg.path).map_err(|e| storage(&seg.path, format!("stat: {e}")))?.len();
            if seg.valid_len < SEGMENT_HEADER_BYTES as u64 {
                quarantine_dir()?;
                let name = seg.path.file_name().map(|n| n.to_string_lossy().into_owned()).unwrap_or_default();
                let to = quarantine.join(format!("{name}.{stamp}"));
                fs::rename(&seg.path, &to).map_err(|e| storage(&seg.path, format!("move to {}: {e}", to.display())))?;
                moved_any = true;
                continue;
            }
            if len > seg.valid_len {
                quarantine_dir()?;
                let data = fs::read(&seg.path).map_err(|e| storage(&seg.path, format!("read: {e}")))?;
                let name = seg.path.file_name().map(|n| n.to_string_lossy().into_owned()).unwrap_or_default();
                let to = quarantine.join(format!("{name}.from-{}.{stamp}", seg.valid_len));
                let tail = data.get(seg.valid_len as usize..).unwrap_or(&[]);
                fs::write(&to, tail).map_err(|e| storage(&to, format!("write: {e}")))?;
                let f = OpenOptions::new().write(true).open(&seg.path).map_err(|e| storage(&seg.path, format!("open: {e}")))?;
                f.set_len(seg.valid_len).map_err(|e| storage(&seg.path, format!("truncate to {}: {e}", seg.valid_len)))?;
                f.sync_all().map_err(|e| storage(&seg.path, format!("fsync: {e}")))?;
                moved_any = true;
            }
            kept.push(seg);
        }
        if moved_any {
            sync_dir(&dir)?;
        }
        let mut closed = Vec::new();
        let mut running_key_end = 0;
        for seg in kept.iter().take(kept.len().saturating_sub(1)) {
            running_key_end = seg.key_end.unwrap_or(running_key_end);
            closed.push(ClosedSegment { path: seg.path.clone(), last_lsn: seg.last_lsn, key_end: running_key_end });
        }
        let (current, current_path, current_len, next_lsn, fresh) = match kept.last() {
            Some(seg) => {
                let f = OpenOptions::new().write(true).open(&seg.path).map_err(|e| storage(&seg.path, format!("open for append: {e}")))?;
                (f, seg.path.clone(), seg.valid_len, seg.last_lsn + 1, false)
            }
            None => {
                let (f, path) = create_segment(&dir, next_lsn_if_empty)?;
                (f, path, SEGMENT_HEADER_BYTES as u64, next_lsn_if_empty, true)
            }
        };
        if fresh {
            sync_dir(&dir)?;
        }
        let shared = Arc::new(current.try_clone().map_err(|e| storage(&current_path, format!("dup: {e}")))?);
        let sync = Arc::new(WalSync::new(dir.clone(), (current_path.clone(), shared), next_lsn - 1));
        Ok(Wal { dir, policy, segment_bytes, current, current_path, current_len, closed, next_lsn, key_end, buf: Vec::new(), poisoned: None, refused_in_a_row: 0, sync })
    }

    pub fn sync_handle(&self) -> Arc<WalSync> {
        Arc::clone(&self.sync)
    }

    /// LSN of the last record appended (0 before the first).
    pub fn last_lsn(&self) -> u64 {
        self.next_lsn - 1
    }

    /// Whether an acknowledgement must wait for [`WalSync::commit`] (`FsyncPolicy::Always`).
    pub fn acks_wait_for_fsync(&self) -> bool {
        self.policy == FsyncPolicy::Always
    }

    /// Appends an Insert record for rows `first_key..first_key + rows`; returns its LSN once
    /// the record has been written to the OS (under `FsyncPolicy::Always` the caller then
    /// waits for [`WalSync::commit`] of that LSN before acknowledging).
    pub fn append_insert(&mut self, first_key: u64, rows: u64, unix_ms: u64, batch_bytes: &[u8]) -> Result<u64, ReplayError> {
        let lsn = self.append_with(KIND_INSERT, |buf| put_insert_payload(buf, first_key, unix_ms, batch_bytes))?;
        self.key_end = first_key + rows;
        Ok(lsn)
    }

    /// Appends a Priorities record (raw priorities of keys that were live when it was written).
    pub fn append_priorities(&mut self, pairs: &[(u64, f64)]) -> Result<u64, ReplayError> {
        self.append_with(KIND_PRIORITIES, |buf| put_priorities_payload(buf, pairs))
    }

    fn append_with(&mut self, kind: u8, payload: impl FnOnce(&mut Vec<u8>)) -> Result<u64, ReplayError> {
        if let Some(why) = &self.poisoned {
            return Err(storage(&self.current_path, format!("log is read-only after a write that could not be rolled back (reopen the replay to recover): {why}")));
        }
        self.sync.check()?;
        let lsn = self.next_lsn;
        let mut buf = std::mem::take(&mut self.buf);
        buf.clear();
        buf.extend_from_slice(&[0u8; RECORD_HEADER_BYTES]);
        buf.push(kind);
        buf.extend_from_slice(&lsn.to_le_bytes());
        payload(&mut buf);
        let len = buf.len() - RECORD_HEADER_BYTES;
        if len > MAX_RECORD_BYTES {
            self.buf = buf;
            return Err(storage(&self.current_path, format!("record of {len} bytes exceeds the {MAX_RECORD_BYTES}-byte limit")));
        }
        let crc = crc32fast::hash(&buf[RECORD_HEADER_BYTES..]);
        buf[0..4].copy_from_slice(&(len as u32).to_le_bytes());
        buf[4..8].copy_from_slice(&crc.to_le_bytes());
        let result = self.write_record(lsn, &buf);
        // Keep the buffer for the next record unless it grew huge (a one-off giant batch).
        if buf.capacity() <= 32 << 20 {
            self.buf = buf;
        }
        match &result {
            Ok(()) if self.refused_in_a_row > 0 => {
                tracing::warn!(log = %self.dir.display(), refused = self.refused_in_a_row, "log appends succeed again");
                self.refused_in_a_row = 0;
            }
            Ok(()) => {}
            Err(e) => {
                if self.refused_in_a_row == 0 {
                    self.sync.faults_reported.fetch_add(1, Ordering::Relaxed);
                    tracing::error!(log = %self.dir.display(), error = %e, "log append failed; changes are refused (and counted) until an append succeeds");
                }
                self.refused_in_a_row += 1;
            }
        }
        result.map(|()| lsn)
    }

    fn write_record(&mut self, lsn: u64, record: &[u8]) -> Result<(), ReplayError> {
        let has_records = self.current_len > SEGMENT_HEADER_BYTES as u64;
        if has_records && self.current_len + record.len() as u64 > self.segment_bytes {
            self.rotate(lsn)?;
        }
        let at = self.current_len;
        if let Err(e) = self.write_at(record, at) {
            // Take the partial record back out, or nothing after it could ever be read. The
            // record's LSN stays unused, so the next append writes the same LSN at `at`.
            let what = format!("write {} bytes at {at}", record.len());
            if let Err(e2) = self.current.set_len(at) {
                self.poisoned = Some(format!("{what}: {e}; rollback failed: {e2}"));
            }
            return Err(ReplayError::io(&self.current_path, what, &e));
        }
        self.current_len += record.len() as u64;
        self.next_lsn = lsn + 1;
        self.sync.written_lsn.store(lsn, Ordering::SeqCst);
        self.sync.dirty.store(true, Ordering::SeqCst);
        Ok(())
    }

    /// `write_all_at` on the current segment (the test build's fault seam sits here).
    fn write_at(&self, record: &[u8], at: u64) -> std::io::Result<()> {
        #[cfg(test)]
        if let Some(e) = InjectedFaults::next(&self.sync.inject.writes) {
            self.current.write_all_at(&record[..record.len() / 2], at)?;
            return Err(e);
        }
        self.current.write_all_at(record, at)
    }

    /// Closes the current segment and starts `seg-<first_lsn>.log`. The old segment joins
    /// the segments the next sync round fsyncs, with the directory (under every policy: with
    /// group commit the old segment's last records may not be synced yet).
    fn rotate(&mut self, first_lsn: u64) -> Result<(), ReplayError> {
        let (file, path) = create_segment(&self.dir, first_lsn)?;
        let shared = match file.try_clone() {
            Ok(f) => Arc::new(f),
            Err(e) => {
                // Still empty: remove it so the next append can try again.
                let _ = fs::remove_file(&path);
                return Err(ReplayError::io(&path, "dup", &e));
            }
        };
        {
            let mut f = lock(&self.sync.files);
            let (old, _) = std::mem::replace(&mut f.current, (path.clone(), shared));
            f.retired.push(old);
            f.dir_dirty = true;
        }
        let old_path = std::mem::replace(&mut self.current_path, path);
        self.closed.push(ClosedSegment { path: old_path, last_lsn: first_lsn - 1, key_end: self.key_end });
        self.current = file;
        self.current_len = SEGMENT_HEADER_BYTES as u64;
        Ok(())
    }

    /// Removes from the log's bookkeeping, and returns, the oldest closed segments that no
    /// recovery can need: every record at or below `covered_lsn` (the oldest snapshot kept)
    /// and every row already evicted (key below `evicted_below` = next_key − capacity).
    /// The caller deletes the files outside the log's lock.
    pub fn take_deletable(&mut self, covered_lsn: u64, evicted_below: u64) -> Vec<PathBuf> {
        let n = self.closed.iter().take_while(|s| s.last_lsn <= covered_lsn && s.key_end <= evicted_below).count();
        self.closed.drain(..n).map(|s| s.path).collect()
    }
}

/// Creates `seg-<first_lsn>.log` with its header, open for appending: written as a temporary
/// file and renamed (`mapless_proto::atomic_file`), so a crash never leaves a segment without a
/// whole header. Not fsynced here: appends sync the segment by the log's policy, and the
/// directory is synced by the caller (at once under `always`, else by the sync thread).
fn create_segment(dir: &Path, first_lsn: u64) -> Result<(File, PathBuf), ReplayError> {
    let path = dir.join(segment_name(first_lsn));
    if path.exists() {
        return Err(storage(&path, "already exists"));
    }
    let mut header = [0u8; SEGMENT_HEADER_BYTES];
    header[0..8].copy_from_slice(SEGMENT_MAGIC);
    header[8..12].copy_from_slice(&FORMAT_VERSION.to_le_bytes());
    header[16..24].copy_from_slice(&first_lsn.to_le_bytes());
    let file = write_file_atomically_with(&path, Durability::Unsynced, |f| f.write_all_at(&header, 0)).map_err(atomic_write_storage)?;
    Ok((file, path))
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn segment_names_round_trip_and_reject_lookalikes() {
        assert_eq!(segment_name(42), "seg-00000000000000000042.log");
        assert_eq!(parse_segment_name(&segment_name(42)), Some(42));
        assert_eq!(parse_segment_name("seg-42.log"), None);
        assert_eq!(parse_segment_name("seg-0000000000000000004x.log"), None);
        assert_eq!(parse_segment_name("seg-00000000000000000042.log.123"), None);
    }

    #[test]
    fn priorities_payload_round_trips_and_rejects_a_wrong_length() {
        let mut b = Vec::new();
        put_priorities_payload(&mut b, &[(3, 0.5), (u64::MAX, 1e300)]);
        assert_eq!(parse_priorities_payload(&b).unwrap(), vec![(3, 0.5), (u64::MAX, 1e300)]);
        b.pop();
        assert!(parse_priorities_payload(&b).is_err());
        for bad in [f64::NAN, f64::INFINITY, -0.5] {
            let mut b = Vec::new();
            put_priorities_payload(&mut b, &[(3, 0.5), (4, bad)]);
            assert!(parse_priorities_payload(&b).unwrap_err().contains("priority of key 4"), "{bad} accepted");
        }
    }

    #[test]
    fn records_report_torn_and_corrupt_tails() {
        let mut rec = vec![0u8; RECORD_HEADER_BYTES];
        rec.push(KIND_PRIORITIES);
        rec.extend_from_slice(&7u64.to_le_bytes());
        put_priorities_payload(&mut rec, &[(1, 2.0)]);
        let len = (rec.len() - RECORD_HEADER_BYTES) as u32;
        let crc = crc32fast::hash(&rec[RECORD_HEADER_BYTES..]);
        rec[0..4].copy_from_slice(&len.to_le_bytes());
        rec[4..8].copy_from_slice(&crc.to_le_bytes());
        let (r, end) = read_record(&rec, 0, 7).unwrap().unwrap();
        assert_eq!((r.lsn, r.kind, end), (7, KIND_PRIORITIES, rec.len()));
        assert!(read_record(&rec, 0, 8).unwrap_err().contains("LSN 7 where 8"));
        assert!(read_record(&rec[..rec.len() - 1], 0, 7).unwrap_err().starts_with("torn"));
        assert!(read_record(&rec[..5], 0, 7).unwrap_err().starts_with("torn"));
        let mut bad = rec.clone();
        *bad.last_mut().unwrap() ^= 1;
        assert!(read_record(&bad, 0, 7).unwrap_err().contains("checksum"));
    }
}
