//! Faults of the disk injected through the log's test seam (`wal::InjectedFaults`): a failed
//! write or fsync is refused, reported once and counted, never acknowledged; group commit
//! shares one fsync among concurrent inserts. The full disk itself is `tests/disk_full.rs`.

use std::collections::BTreeMap;
use std::path::{Path, PathBuf};
use std::sync::Arc;
use std::time::{Duration, Instant};

use mapless_proto::v1::TransitionBatch;
use mapless_proto::{Transition, TransitionBatchBuilder};

use super::DurableTable;
use crate::config::{FsyncPolicy, PersistenceConfig, RateLimiterConfig, TableConfig};
use crate::error::ReplayError;
use crate::table::{StorageRefusal, Table};
use crate::wal::WalSync;

const D: usize = 3;
/// Linux errno values the seam returns.
const EIO: i32 = 5;
const ENOSPC: i32 = 28;

struct TempDir(PathBuf);

impl TempDir {
    fn new(tag: &str) -> TempDir {
        let nanos = std::time::SystemTime::now().duration_since(std::time::UNIX_EPOCH).unwrap().as_nanos();
        let p = std::env::temp_dir().join(format!("mapless-faults-{tag}-{}-{nanos}", std::process::id()));
        std::fs::create_dir_all(&p).unwrap();
        TempDir(p)
    }
}

impl Drop for TempDir {
    fn drop(&mut self) {
        let _ = std::fs::remove_dir_all(&self.0);
    }
}

fn cfg() -> TableConfig {
    TableConfig {
        capacity: 1000,
        obs_dim: D,
        act_dim: 2,
        rate_limiter: RateLimiterConfig { min_size_to_sample: 1, samples_per_insert: None, error_buffer: 0.0 },
        max_batch_rows: 100,
        max_sample_rows: 1000,
        ..TableConfig::default()
    }
}

fn open(dir: &Path, fsync: FsyncPolicy) -> DurableTable {
    let p = PersistenceConfig { dir: Some(dir.to_path_buf()), segment_bytes: 4096, fsync, snapshot_interval_s: 0.0 };
    let (t, report) = DurableTable::open(cfg(), p, 1).unwrap();
    assert!(report.fault.is_none(), "{:?}", report.fault);
    t
}

/// 10 rows whose reward is `seq * 100 + i`.
fn batch(actor: &str, seq: u64) -> TransitionBatch {
    let mut b = TransitionBatchBuilder::new(D, 2);
    for i in 0..10 {
        let r = (seq * 100 + i) as f32;
        let t = Transition { obs: &[r, 0.0, 1.0], action: &[0.1, -0.1], reward: r, next_obs: &[r, 1.0, 0.0], terminal: false, truncated: i == 9, episode_id: seq, step: i as u32, policy_version: 1 };
        b.push(t).unwrap();
    }
    b.finish(actor, seq)
}

/// Every stored row: key → reward (a minibatch as large as the table draws each row once).
fn contents(t: &Table) -> BTreeMap<u64, f32> {
    let n = t.size() as usize;
    if n == 0 {
        return BTreeMap::new();
    }
    let s = t.sample(n, None, Some(Instant::now() + Duration::from_secs(5))).unwrap();
    s.keys.iter().copied().zip(s.reward.iter().copied()).collect()
}

fn sync_of(t: &DurableTable) -> &Arc<WalSync> {
    t.wal_sync().expect("a persistent table")
}

fn refused(t: &Table, reason: StorageRefusal) -> u64 {
    t.storage_refusals(false, reason)
}

#[test]
fn a_failed_write_is_refused_reported_once_counted_and_the_next_insert_succeeds() {
    let dir = TempDir::new("write");
    let t = open(&dir.0, FsyncPolicy::IntervalMs(5));
    t.insert(&batch("a", 1), None).unwrap();
    let sync = sync_of(&t);
    sync.inject.writes.lock().unwrap().extend([EIO, EIO]);

    for _ in 0..2 {
        let e = t.insert(&batch("a", 2), None).unwrap_err();
        assert!(matches!(&e, ReplayError::Storage { path, problem } if path.ends_with("seg-00000000000000000001.log") && problem.starts_with("write ")), "{e}");
        assert_eq!(e.to_status().code(), tonic::Code::Internal);
    }
    assert_eq!((sync.faults_reported(), refused(&t, StorageRefusal::IoError)), (1, 2), "one report for two refusals in a row");
    assert_eq!(t.actors()["a"].last_sequence, 1, "a refused batch is not stored");
    assert!(!t.insert(&batch("a", 2), None).unwrap().duplicate, "the resend is stored");

    // The disk fills mid-record: half the record was written, then rolled back.
    sync.inject.writes.lock().unwrap().push_back(ENOSPC);
    let e = t.insert(&batch("a", 3), None).unwrap_err();
    assert!(matches!(e, ReplayError::DiskFull { .. }), "{e}");
    let status = e.to_status();
    assert_eq!(status.code(), tonic::Code::ResourceExhausted);
    assert!(status.message().starts_with("disk full: ") && status.message().contains("seg-"), "{}", status.message());
    assert_eq!((sync.faults_reported(), refused(&t, StorageRefusal::DiskFull)), (2, 1), "a new fault after a success is reported again");
    t.insert(&batch("a", 3), None).unwrap();

    let before = contents(&t);
    assert_eq!(before.len(), 30);
    t.close();
    drop(t);
    let t = open(&dir.0, FsyncPolicy::IntervalMs(5));
    assert_eq!(contents(&t), before, "the log holds every stored row once and nothing of the refused writes");
    assert_eq!((t.actors()["a"].last_sequence, t.actors()["a"].batches), (3, 3));
}

#[test]
fn a_failed_fsync_is_never_acknowledged_and_the_log_refuses_until_reopened() {
    let dir = TempDir::new("fsync");
    let t = open(&dir.0, FsyncPolicy::Always);
    t.insert(&batch("a", 1), None).unwrap();
    let sync = sync_of(&t);
    assert!(sync.durable_lsn() >= 1, "an acknowledged insert under `always` is on disk");
    sync.inject.fsyncs.lock().unwrap().push_back(EIO);

    let e = t.insert(&batch("a", 2), None).unwrap_err();
    assert!(matches!(&e, ReplayError::Storage { problem, .. } if problem.starts_with("fsync: ")), "{e}");
    // Everything that would need the disk is refused now, resends of stored batches too:
    // a#2 reached the table before its fsync failed, but must not be acknowledged as a
    // duplicate.
    for seq in [3, 2, 1] {
        let e = t.insert(&batch("a", seq), None).unwrap_err();
        assert!(e.to_string().contains("read-only after a failed fsync"), "{e}");
    }
    assert!(t.snapshot().is_err(), "no snapshot may claim records whose fsync failed");
    assert_eq!((sync.faults_reported(), refused(&t, StorageRefusal::IoError)), (1, 4), "reported once, every refusal counted");
    t.close();
    drop(t);

    // Reopened: what the disk holds. a#1 was acknowledged and is there; a#2 was refused (it
    // may come back, its client was told it failed); a#3 never reached the log.
    let t = open(&dir.0, FsyncPolicy::Always);
    let last = t.actors()["a"].last_sequence;
    assert!(last == 1 || last == 2, "last sequence {last}");
    assert!(contents(&t).values().any(|&r| r == 100.0), "the acknowledged batch survives");
    assert!(!t.insert(&batch("a", 3), None).unwrap().duplicate, "the reopened log accepts inserts");
}

#[test]
fn concurrent_inserts_under_fsync_always_share_one_fsync() {
    const WRITERS: u64 = 8;
    let dir = TempDir::new("group");
    let t = Arc::new(open(&dir.0, FsyncPolicy::Always));
    // The first sync round starts only once every writer's record is written, as happens
    // whenever records arrive faster than an fsync takes.
    *sync_of(&t).inject.before_sync.lock().unwrap() = Some(Box::new(|s: &WalSync| {
        let give_up = Instant::now() + Duration::from_secs(10);
        while s.written_lsn() < WRITERS && Instant::now() < give_up {
            std::thread::sleep(Duration::from_millis(1));
        }
    }));
    let threads: Vec<_> = (0..WRITERS)
        .map(|w| {
            let t = Arc::clone(&t);
            std::thread::spawn(move || t.insert(&batch(&format!("w{w}"), 1), None))
        })
        .collect();
    for h in threads {
        assert!(!h.join().unwrap().unwrap().duplicate);
    }
    let sync = sync_of(&t);
    assert_eq!((sync.fsyncs(), sync.durable_lsn()), (1, WRITERS), "one fsync covered all {WRITERS} records");
    assert_eq!(t.size(), 10 * WRITERS);
}
