//! Snapshots of a table's metadata: what the log alone cannot rebuild cheaply or at all.
//!
//! The rows themselves live only in the log (the table's content is the last `capacity`
//! inserted rows, a pure function of the log); a snapshot holds the rest, consistent with one
//! LSN, so recovery is "load the snapshot, replay the log after its LSN":
//!
//! ```text
//!   <dir>/snapshots/snap-<lsn:020>.snap   written as .tmp, fsynced, renamed, directory fsynced
//!                                         (mapless_proto::atomic_file)
//!
//!   "MPLSSNAP" | version u32 = 1 | meta_len u32 | meta (JSON, SnapshotMeta)
//!   | weight f64 × capacity | live u8 × capacity | times_sampled u32 × capacity
//!   | crc u32  (CRC-32 of every byte before it)                       (little-endian)
//! ```
//!
//! Meta: LSN, next key, rate-limiter counters, largest priority weight, per-actor statistics
//! (de-duplication marks), the sampler's random-number generator and the table's shape. Per slot: the sum-tree weight, whether the
//! slot is live, and how often it was sampled.
//!
//! What a crash costs: inserts and priority updates are logged, so they come back exactly.
//! Sampling is not logged (it is the hot path), so after a crash the rate limiter's sample
//! count, `times_sampled` and removals by `max_times_sampled` are those of the newest
//! snapshot: they may lag by one snapshot interval. Duplicate and rejected batch counts lag
//! the same way. A clean close writes a final snapshot, so nothing lags after it.

use std::collections::BTreeMap;
use std::fs::{self, File, OpenOptions};
use std::io::Write;
use std::path::{Path, PathBuf};

use mapless_proto::atomic_file::{Durability, is_temp_file_name, write_file_atomically_with};
use rand_pcg::Pcg64Mcg;
use serde::{Deserialize, Serialize};

use crate::actors::ActorStats;
use crate::clock::unix_ms;
use crate::config::SamplerConfig;
use crate::error::ReplayError;
use crate::wal::{atomic_write_storage, parse_numbered_name, storage, sync_dir};

const MAGIC: &[u8; 8] = b"MPLSSNAP";
const FORMAT_VERSION: u32 = 1;
/// magic 8 | version 4 | meta_len 4.
const PREFIX_BYTES: usize = 16;
/// Per slot: weight 8 | live 1 | times_sampled 4.
const SLOT_BYTES: usize = 13;
/// A meta block larger than this is corruption (actor ids are ≤ 128 bytes; a million actors
/// would still fit).
const MAX_META_BYTES: usize = 1 << 30;

/// Everything a snapshot holds besides the per-slot arrays.
#[derive(Clone, Debug, Serialize, Deserialize, PartialEq)]
#[serde(deny_unknown_fields)]
pub(crate) struct SnapshotMeta {
    pub table: String,
    /// The last log record whose effects the snapshot includes.
    pub lsn: u64,
    /// Key the next inserted row gets (= rows ever inserted).
    pub next_key: u64,
    pub capacity: u64,
    pub obs_dim: u64,
    pub act_dim: u64,
    /// The sampler the weights were computed with; another one means the weights are reset.
    pub sampler: SamplerConfig,
    /// Largest priority weight seen (what new rows get).
    pub max_weight: f64,
    /// Rate-limiter counters, in rows.
    pub inserts: u64,
    pub samples: u64,
    pub size: u64,
    pub created_unix_ms: u64,
    pub actors: BTreeMap<String, ActorStats>,
    /// The sampler's random-number generator, so that a restored table draws the minibatches
    /// the running one would have drawn next. Absent in snapshots of older builds (the
    /// stream then restarts from the table's seed).
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub sampler_rng: Option<Pcg64Mcg>,
}

/// A snapshot in memory: meta plus one entry per slot.
#[derive(Clone, Debug)]
pub(crate) struct SnapshotData {
    pub meta: SnapshotMeta,
    pub weights: Vec<f64>,
    pub live: Vec<bool>,
    pub times_sampled: Vec<u32>,
}

impl SnapshotData {
    fn encode(&self) -> Result<Vec<u8>, String> {
        let meta = serde_json::to_vec(&self.meta).map_err(|e| format!("encode meta: {e}"))?;
        let cap = self.weights.len();
        let mut out = Vec::with_capacity(PREFIX_BYTES + meta.len() + cap * SLOT_BYTES + 4);
        out.extend_from_slice(MAGIC);
        out.extend_from_slice(&FORMAT_VERSION.to_le_bytes());
        out.extend_from_slice(&(meta.len() as u32).to_le_bytes());
        out.extend_from_slice(&meta);
        for w in &self.weights {
            out.extend_from_slice(&w.to_le_bytes());
        }
        out.extend(self.live.iter().map(|&l| l as u8));
        for t in &self.times_sampled {
            out.extend_from_slice(&t.to_le_bytes());
        }
        let crc = crc32fast::hash(&out);
        out.extend_from_slice(&crc.to_le_bytes());
        Ok(out)
    }

    /// Parses and checks a snapshot file's bytes; the error says what is wrong.
    fn decode(data: &[u8]) -> Result<SnapshotData, String> {
        if data.len() < PREFIX_BYTES + 4 {
            return Err(format!("file of {} bytes is too short to be a snapshot", data.len()));
        }
        let (body, crc) = data.split_at(data.len() - 4);
        let stored = u32::from_le_bytes(crc.try_into().map_err(|_| "short checksum")?);
        let actual = crc32fast::hash(body);
        if stored != actual {
            return Err(format!("checksum mismatch (stored {stored:#010x}, computed {actual:#010x})"));
        }
        if &body[0..8] != MAGIC {
            return Err("not a mapless snapshot (bad magic)".into());
        }
        let version = u32::from_le_bytes(body[8..12].try_into().map_err(|_| "short version")?);
        if version != FORMAT_VERSION {
            return Err(format!("snapshot format version {version}, this build reads {FORMAT_VERSION}"));
        }
        let meta_len = u32::from_le_bytes(body[12..16].try_into().map_err(|_| "short length")?) as usize;
        if meta_len > MAX_META_BYTES || PREFIX_BYTES + meta_len > body.len() {
            return Err(format!("meta length {meta_len} does not fit the file"));
        }
        let meta: SnapshotMeta = serde_json::from_slice(&body[PREFIX_BYTES..PREFIX_BYTES + meta_len]).map_err(|e| format!("meta: {e}"))?;
        let slots = &body[PREFIX_BYTES + meta_len..];
        let cap = usize::try_from(meta.capacity).map_err(|_| "capacity does not fit this machine")?;
        if cap.checked_mul(SLOT_BYTES) != Some(slots.len()) {
            return Err(format!("{} bytes of slot data for capacity {cap}", slots.len()));
        }
        let (w, rest) = slots.split_at(cap * 8);
        let (l, t) = rest.split_at(cap);
        let weights: Vec<f64> = w.chunks_exact(8).map(|c| f64::from_le_bytes(c.try_into().unwrap_or([0; 8]))).collect();
        if let Some(i) = weights.iter().position(|w| !(w.is_finite() && *w >= 0.0)) {
            return Err(format!("slot {i} has weight {}", weights[i]));
        }
        if !(meta.max_weight.is_finite() && meta.max_weight > 0.0) {
            return Err(format!("max_weight is {}", meta.max_weight));
        }
        if let Some(i) = l.iter().position(|&b| b > 1) {
            return Err(format!("slot {i} has live flag {}", l[i]));
        }
        Ok(SnapshotData { weights, live: l.iter().map(|&b| b == 1).collect(), times_sampled: t.chunks_exact(4).map(|c| u32::from_le_bytes(c.try_into().unwrap_or([0; 4]))).collect(), meta })
    }
}

pub(crate) fn snapshot_name(lsn: u64) -> String {
    format!("snap-{lsn:020}.snap")
}

fn parse_snapshot_name(name: &str) -> Option<u64> {
    parse_numbered_name(name, "snap-", ".snap")
}

/// The snapshot directory: writes, lists, loads, sets aside and prunes snapshot files.
pub(crate) struct SnapshotStore {
    dir: PathBuf,
    /// Snapshots kept; the log is kept back to the oldest of them, so a damaged newest one
    /// can fall back to the one before.
    keep: usize,
}

impl SnapshotStore {
    /// Opens (creating) the directory and removes half-written temporary files (the atomic
    /// write's, and `snap-<lsn>.snap.tmp` of older builds).
    pub fn open(dir: PathBuf, keep: usize) -> Result<SnapshotStore, ReplayError> {
        fs::create_dir_all(&dir).map_err(|e| storage(&dir, format!("create: {e}")))?;
        for entry in fs::read_dir(&dir).map_err(|e| storage(&dir, format!("list: {e}")))? {
            let entry = entry.map_err(|e| storage(&dir, format!("list: {e}")))?;
            if entry.file_name().to_str().is_some_and(|n| n.ends_with(".snap.tmp") || is_temp_file_name(n)) {
                let p = entry.path();
                fs::remove_file(&p).map_err(|e| storage(&p, format!("remove stale temporary file: {e}")))?;
            }
        }
        Ok(SnapshotStore { dir, keep: keep.max(1) })
    }

    /// Snapshot files, oldest first.
    pub fn list(&self) -> Result<Vec<(u64, PathBuf)>, ReplayError> {
        let mut out = Vec::new();
        for entry in fs::read_dir(&self.dir).map_err(|e| storage(&self.dir, format!("list: {e}")))? {
            let entry = entry.map_err(|e| storage(&self.dir, format!("list: {e}")))?;
            if let Some(lsn) = entry.file_name().to_str().and_then(parse_snapshot_name) {
                out.push((lsn, entry.path()));
            }
        }
        out.sort();
        Ok(out)
    }

    /// Reads and checks one snapshot; `Err` says why it cannot be used.
    pub fn load(path: &Path) -> Result<SnapshotData, String> {
        let data = fs::read(path).map_err(|e| format!("read: {e}"))?;
        let snap = SnapshotData::decode(&data)?;
        let named = path.file_name().and_then(|n| n.to_str()).and_then(parse_snapshot_name);
        if named != Some(snap.meta.lsn) {
            return Err(format!("holds LSN {} but is named for {named:?}", snap.meta.lsn));
        }
        Ok(snap)
    }

    /// Writes a snapshot durably (`mapless_proto::atomic_file`, [`Durability::Synced`]):
    /// temporary file, fsync, rename over `snap-<lsn>.snap`, directory fsync. Returns its path
    /// and size in bytes.
    pub fn write(&self, snap: &SnapshotData) -> Result<(PathBuf, u64), ReplayError> {
        let path = self.dir.join(snapshot_name(snap.meta.lsn));
        let bytes = snap.encode().map_err(|e| storage(&path, e))?;
        write_file_atomically_with(&path, Durability::Synced, |f| f.write_all(&bytes)).map_err(atomic_write_storage)?;
        Ok((path, bytes.len() as u64))
    }

    /// Renames an unusable snapshot to `<name>.<why>.<unix_ms>` so it is never loaded again
    /// (a snapshot ahead of a damaged log must not be picked up once new records reuse its
    /// LSNs) but stays for inspection.
    pub fn set_aside(&self, path: &Path, why: &str) -> Result<(), ReplayError> {
        let name = path.file_name().map(|n| n.to_string_lossy().into_owned()).unwrap_or_default();
        let to = self.dir.join(format!("{name}.{why}.{}", unix_ms()));
        fs::rename(path, &to).map_err(|e| storage(path, format!("move to {}: {e}", to.display())))?;
        sync_dir(&self.dir)
    }

    /// Deletes all but the newest `keep` snapshots. Returns the LSN the log must be kept back
    /// to: that of the oldest snapshot kept once there are `keep` of them, else `None` (keep
    /// the whole log, so that a damaged only snapshot can fall back to the log alone).
    pub fn prune(&self) -> Result<Option<u64>, ReplayError> {
        let list = self.list()?;
        let excess = list.len().saturating_sub(self.keep);
        for (_, path) in &list[..excess] {
            fs::remove_file(path).map_err(|e| storage(path, format!("remove: {e}")))?;
        }
        if excess > 0 {
            sync_dir(&self.dir)?;
        }
        Ok(if list.len() - excess >= self.keep { list.get(excess).map(|(lsn, _)| *lsn) } else { None })
    }
}

/// Opens a file only to hold it (the directory lock).
pub(crate) fn lock_dir(dir: &Path) -> Result<File, ReplayError> {
    let path = dir.join("LOCK");
    let f = OpenOptions::new().read(true).write(true).create(true).truncate(false).open(&path).map_err(|e| storage(&path, format!("open: {e}")))?;
    match f.try_lock() {
        Ok(()) => Ok(f),
        Err(std::fs::TryLockError::WouldBlock) => Err(storage(&path, "another table (in this or another process) has this directory open")),
        Err(std::fs::TryLockError::Error(e)) => Err(storage(&path, format!("lock: {e}"))),
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    fn sample() -> SnapshotData {
        let mut actors = BTreeMap::new();
        actors.insert("a".to_string(), ActorStats { last_sequence: 7, batches: 3, rows: 30, ..ActorStats::default() });
        SnapshotData {
            meta: SnapshotMeta {
                table: "t".into(),
                lsn: 12,
                next_key: 30,
                capacity: 3,
                obs_dim: 2,
                act_dim: 1,
                sampler: SamplerConfig::Uniform,
                max_weight: 1.5,
                inserts: 30,
                samples: 4,
                size: 3,
                created_unix_ms: 1,
                actors,
                sampler_rng: Some(rand::SeedableRng::seed_from_u64(3)),
            },
            weights: vec![1.0, 0.0, 1.5],
            live: vec![true, false, true],
            times_sampled: vec![0, 9, 1],
        }
    }

    #[test]
    fn snapshot_bytes_round_trip_and_any_flipped_bit_is_caught() {
        let s = sample();
        let bytes = s.encode().unwrap();
        let back = SnapshotData::decode(&bytes).unwrap();
        assert_eq!((back.meta, back.weights, back.live, back.times_sampled), (s.meta, s.weights, s.live, s.times_sampled));
        for i in [0, 9, 20, bytes.len() / 2, bytes.len() - 1] {
            let mut bad = bytes.clone();
            bad[i] ^= 0x10;
            assert!(SnapshotData::decode(&bad).is_err(), "flip at {i} went unnoticed");
        }
        assert!(SnapshotData::decode(&bytes[..bytes.len() - 1]).is_err());
    }

    #[test]
    fn snapshots_are_written_whole_and_a_crash_s_temporary_files_removed_on_open() {
        let dir = std::env::temp_dir().join(format!("mapless-snapshot-store-{}", std::process::id()));
        let _ = fs::remove_dir_all(&dir);
        let store = SnapshotStore::open(dir.clone(), 2).unwrap();
        let (path, bytes) = store.write(&sample()).unwrap();
        assert_eq!((path.file_name().unwrap().to_str().unwrap(), bytes), (snapshot_name(12).as_str(), fs::metadata(&path).unwrap().len()));
        assert_eq!(SnapshotStore::load(&path).unwrap().meta, sample().meta);
        // What a crash before the rename leaves: the atomic write's temporary file, and an
        // older build's `snap-<lsn>.snap.tmp`.
        fs::write(dir.join(".a1B2c3.tmp"), b"half").unwrap();
        fs::write(dir.join(format!("{}.tmp", snapshot_name(13))), b"half").unwrap();
        SnapshotStore::open(dir.clone(), 2).unwrap();
        let mut left: Vec<String> = fs::read_dir(&dir).unwrap().map(|e| e.unwrap().file_name().into_string().unwrap()).collect();
        left.sort();
        assert_eq!(left, [snapshot_name(12)]);
        fs::remove_dir_all(&dir).unwrap();
    }

    #[test]
    fn snapshot_names_round_trip() {
        assert_eq!(parse_snapshot_name(&snapshot_name(5)), Some(5));
        assert_eq!(parse_snapshot_name("snap-5.snap"), None);
        assert_eq!(parse_snapshot_name(&format!("{}.tmp", snapshot_name(5))), None);
    }
}
