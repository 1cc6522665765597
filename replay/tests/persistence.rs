//! Persistence: the write-ahead log and snapshots bring back every acknowledged change exactly
//! once, survive torn and corrupt files, and never stall traffic.
//!
//! A crash is simulated by copying the table's directory while the table is live and idle:
//! the copy holds exactly what a `kill -9` at that instant would leave (every acknowledged
//! record has been written to the OS; nothing else was flushed). The original table is then
//! dropped normally; only the copy is reopened.

use std::collections::BTreeMap;
use std::path::{Path, PathBuf};
use std::sync::Arc;
use std::sync::atomic::{AtomicBool, Ordering};
use std::time::{Duration, Instant};

use mapless_proto::v1::TransitionBatch;
use mapless_proto::{Transition, TransitionBatchBuilder};
use mapless_replay::{DurableTable, FsyncPolicy, PersistenceConfig, RateLimiterConfig, ReplayError, SamplerConfig, Table, TableConfig};

const D: usize = 3;

/// The latency test runs alone (write lock); the others share the machine (read lock).
static EXCLUSIVE: std::sync::RwLock<()> = std::sync::RwLock::new(());

fn shared() -> std::sync::RwLockReadGuard<'static, ()> {
    EXCLUSIVE.read().unwrap_or_else(|p| p.into_inner())
}

/// A directory under the system temp dir, removed on drop.
struct TempDir(PathBuf);

impl TempDir {
    fn new(tag: &str) -> TempDir {
        let nanos = std::time::SystemTime::now().duration_since(std::time::UNIX_EPOCH).unwrap().as_nanos();
        let p = std::env::temp_dir().join(format!("mapless-persist-{tag}-{}-{nanos}", std::process::id()));
        std::fs::create_dir_all(&p).unwrap();
        TempDir(p)
    }
    fn path(&self) -> &Path {
        &self.0
    }
}

impl Drop for TempDir {
    fn drop(&mut self) {
        let _ = std::fs::remove_dir_all(&self.0);
    }
}

/// What the disk holds right now, as a `kill -9` would leave it.
fn crash_image(dir: &Path, tag: &str) -> TempDir {
    fn copy(from: &Path, to: &Path) {
        std::fs::create_dir_all(to).unwrap();
        for e in std::fs::read_dir(from).unwrap() {
            let e = e.unwrap();
            if e.file_type().unwrap().is_dir() {
                copy(&e.path(), &to.join(e.file_name()));
            } else {
                std::fs::copy(e.path(), to.join(e.file_name())).unwrap();
            }
        }
    }
    let img = TempDir::new(tag);
    copy(dir, img.path());
    img
}

fn cfg(capacity: usize) -> TableConfig {
    TableConfig {
        capacity,
        obs_dim: D,
        act_dim: 2,
        rate_limiter: RateLimiterConfig { min_size_to_sample: 1, samples_per_insert: None, error_buffer: 0.0 },
        max_batch_rows: 1000,
        max_sample_rows: 1000,
        ..TableConfig::default()
    }
}

fn persist(dir: &Path) -> PersistenceConfig {
    PersistenceConfig { dir: Some(dir.to_path_buf()), segment_bytes: 4096, fsync: FsyncPolicy::IntervalMs(5), snapshot_interval_s: 0.0 }
}

fn open(c: TableConfig, dir: &Path) -> (DurableTable, mapless_replay::RecoveryReport) {
    DurableTable::open(c, persist(dir), 1).unwrap()
}

/// `rows` transitions whose reward (and obs[0]) is `first_reward + i`; every column varies.
fn batch(actor: &str, seq: u64, first_reward: f32, rows: usize) -> TransitionBatch {
    let mut b = TransitionBatchBuilder::new(D, 2);
    for i in 0..rows {
        let r = first_reward + i as f32;
        b.push(Transition {
            obs: &[r, 0.5, -r],
            action: &[0.1 * r, -0.1],
            reward: r,
            next_obs: &[r, 1.0, seq as f32],
            terminal: i % 7 == 6,
            truncated: i % 7 == 5,
            episode_id: seq,
            step: i as u32,
            policy_version: seq * 10 + i as u64,
        })
        .unwrap();
    }
    b.finish(actor, seq)
}

/// Every stored row, by key, with all its columns as bits. With the uniform sampler and a
/// minibatch as large as the table, stratified sampling draws each live row exactly once.
fn contents(t: &Table) -> BTreeMap<u64, Vec<u64>> {
    let n = t.size() as usize;
    if n == 0 {
        return BTreeMap::new();
    }
    let s = t.sample(n, None, Some(Instant::now() + Duration::from_secs(5))).unwrap();
    let mut out = BTreeMap::new();
    for i in 0..n {
        let mut cols: Vec<u64> = Vec::new();
        cols.extend(s.obs[i * D..(i + 1) * D].iter().map(|x| x.to_bits() as u64));
        cols.extend(s.next_obs[i * D..(i + 1) * D].iter().map(|x| x.to_bits() as u64));
        cols.extend(s.action[i * 2..(i + 1) * 2].iter().map(|x| x.to_bits() as u64));
        cols.extend([s.reward[i].to_bits() as u64, s.terminal[i] as u64, s.truncated[i] as u64, s.episode_id[i], s.step[i] as u64, s.policy_version[i]]);
        assert!(out.insert(s.keys[i], cols).is_none(), "key {} drawn twice", s.keys[i]);
    }
    out
}

/// (last_sequence, batches, rows) per actor.
fn marks(t: &Table) -> BTreeMap<String, (u64, u64, u64)> {
    t.actors().into_iter().filter(|(_, a)| a.batches > 0).map(|(id, a)| (id, (a.last_sequence, a.batches, a.rows))).collect()
}

fn segments(dir: &Path) -> Vec<PathBuf> {
    let mut v: Vec<PathBuf> = std::fs::read_dir(dir.join("wal")).unwrap().map(|e| e.unwrap().path()).filter(|p| p.file_name().unwrap().to_str().unwrap().ends_with(".log")).collect();
    v.sort();
    v
}

#[test]
fn restart_restores_every_acknowledged_row_exactly_once() {
    let _shared = shared();
    let dir = TempDir::new("restart");
    let (t, report) = open(cfg(200), dir.path());
    assert_eq!((report.rows, report.records_replayed, report.fault.clone()), (0, 0, None));
    let t = Arc::new(t);
    // Three actors insert concurrently; batches of 1..=7 rows; 600+ rows through 200 slots.
    let run = |from: u64, to: u64| {
        let hs: Vec<_> = ["a", "b", "c"]
            .into_iter()
            .map(|actor| {
                let t = Arc::clone(&t);
                std::thread::spawn(move || {
                    for seq in from..to {
                        let ack = t.insert(&batch(actor, seq, seq as f32 * 100.0, 1 + (seq as usize % 7)), None).unwrap();
                        assert!(!ack.duplicate);
                    }
                })
            })
            .collect();
        hs.into_iter().for_each(|h| h.join().unwrap());
    };
    run(1, 21);
    let before_snapshot = (contents(&t), marks(&t), crash_image(dir.path(), "restart-early"));
    let snap = t.snapshot().unwrap().expect("a persistent table writes snapshots");
    run(21, 41);
    t.update_priorities(&[1, 2], &[5.0, 6.0]).unwrap(); // uniform table: accepted, nothing logged
    let expected = (contents(&t), marks(&t), t.info().inserts_total);
    let image = crash_image(dir.path(), "restart-late");
    assert!(segments(image.path()).len() > 3, "the 4 KiB segments rotated");
    drop(t);

    // Log only (the crash came before any snapshot).
    let (early_contents, early_marks, early_image) = before_snapshot;
    let (t1, r1) = open(cfg(200), early_image.path());
    assert_eq!((r1.snapshot.clone(), r1.fault.clone(), r1.rows_lost), (None, None, 0));
    assert_eq!(contents(&t1), early_contents);
    assert_eq!(marks(&t1), early_marks);

    // Snapshot plus the log after it.
    let (t2, r2) = open(cfg(200), image.path());
    assert_eq!(r2.snapshot_lsn, snap.lsn);
    assert!(r2.records_after_snapshot > 0 && r2.fault.is_none() && r2.rows_lost == 0, "{r2:?}");
    assert_eq!(contents(&t2), expected.0, "same rows, same keys, same columns");
    assert_eq!(t2.size(), 200);
    assert_eq!(marks(&t2), expected.1, "de-duplication marks restored");
    assert_eq!(t2.info().inserts_total, expected.2, "insert counter is exact");
    // Every batch sent before the crash is a duplicate now; the next one is not.
    for actor in ["a", "b", "c"] {
        for seq in [1, 20, 21, 40] {
            assert!(t2.insert(&batch(actor, seq, 0.0, 1), None).unwrap().duplicate, "{actor}/{seq} resent after restart");
        }
        assert!(!t2.insert(&batch(actor, 41, 0.0, 1), None).unwrap().duplicate);
    }
    assert_eq!(t2.size(), 200);
}

#[test]
fn priorities_survive_restart() {
    let _shared = shared();
    let dir = TempDir::new("prio");
    let mut c = cfg(8);
    c.sampler = SamplerConfig::Prioritized { alpha: 1.0, beta: 1.0, epsilon: 0.0 };
    let (t, _) = open(c.clone(), dir.path());
    t.insert(&batch("a", 1, 0.0, 4), None).unwrap();
    t.update_priorities(&[0, 1, 2, 3], &[1.0, 2.0, 3.0, 4.0]).unwrap();
    t.snapshot().unwrap();
    // After the snapshot: an update, then rows that get the largest weight seen (8).
    assert_eq!(t.update_priorities(&[3, 77], &[8.0, 1.0]).unwrap(), (1, 1));
    t.insert(&batch("a", 2, 4.0, 2), None).unwrap();
    t.update_priorities(&[5], &[0.5]).unwrap();
    let image = crash_image(dir.path(), "prio-img");
    drop(t);

    let (t, r) = open(c, image.path());
    assert!(r.snapshot.is_some() && r.records_after_snapshot == 3, "{r:?}");
    // Weights 1, 2, 3, 8, 8, 0.5 → total 22.5.
    let expected = [1.0, 2.0, 3.0, 8.0, 8.0, 0.5].map(|w| w / 22.5);
    let s = t.sample(500, None, None).unwrap();
    for (k, p) in s.keys.iter().zip(&s.probabilities) {
        assert!((p - expected[*k as usize]).abs() < 1e-12, "key {k}: p {p}, expected {}", expected[*k as usize]);
    }
    // The largest weight seen is restored too: a new row gets 8.
    t.insert(&batch("a", 3, 6.0, 1), None).unwrap();
    let s = t.sample(500, None, None).unwrap();
    let p6 = s.keys.iter().zip(&s.probabilities).find(|(k, _)| **k == 6).map(|(_, p)| *p).unwrap();
    assert!((p6 - 8.0 / 30.5).abs() < 1e-12, "{p6}");
}

#[test]
fn minibatches_sampled_after_snapshot_and_reopen_are_those_of_the_uninterrupted_table() {
    let _shared = shared();
    for sampler in [SamplerConfig::Uniform, SamplerConfig::Prioritized { alpha: 0.6, beta: 0.4, epsilon: 0.01 }] {
        let dir = TempDir::new("rng");
        let c = cfg(40);
        let c = TableConfig { sampler: sampler.clone(), ..c };
        // The same history on a persistent table and on one that is never interrupted.
        let (persistent, _) = open(c.clone(), dir.path());
        let uninterrupted = Table::new(c.clone(), 1).unwrap();
        for t in [&persistent, &uninterrupted] {
            for seq in 1..=6 {
                t.insert(&batch("a", seq, seq as f32 * 10.0, 9), None).unwrap(); // 54 rows, ring of 40
            }
            for _ in 0..3 {
                let s = t.sample(16, None, None).unwrap();
                if sampler != SamplerConfig::Uniform {
                    let p: Vec<f64> = s.keys.iter().map(|k| 1.0 + (*k % 5) as f64).collect();
                    t.update_priorities(&s.keys, &p).unwrap();
                }
            }
        }
        persistent.snapshot().unwrap().expect("a snapshot was written");
        drop(persistent);

        let (restored, report) = open(c, dir.path());
        assert!(report.snapshot.is_some(), "{report:?}");
        for round in 0..4 {
            if round == 2 {
                // Inserts after the restart keep both tables in step too.
                restored.insert(&batch("a", 7, 70.0, 9), None).unwrap();
                uninterrupted.insert(&batch("a", 7, 70.0, 9), None).unwrap();
            }
            let a = restored.sample(16, None, None).unwrap();
            let b = uninterrupted.sample(16, None, None).unwrap();
            assert_eq!(a, b, "{sampler:?}: minibatch {round} after the restart differs");
        }
    }
}

/// Inserts `n` batches of 5 rows from actor "a" and returns the last segment and its length
/// before the last batch (where the last record starts).
fn fill(t: &Table, dir: &Path, n: u64) -> (PathBuf, u64) {
    for seq in 1..n {
        t.insert(&batch("a", seq, seq as f32, 5), None).unwrap();
    }
    let last = segments(dir).pop().unwrap();
    let start = std::fs::metadata(&last).unwrap().len();
    t.insert(&batch("a", n, n as f32, 5), None).unwrap();
    assert_eq!(segments(dir).pop().unwrap(), last, "the last record shares the segment");
    (last, start)
}

fn big_segments(dir: &Path) -> PersistenceConfig {
    PersistenceConfig { segment_bytes: 1 << 20, fsync: FsyncPolicy::Always, ..persist(dir) }
}

#[test]
fn a_corrupt_byte_in_the_tail_is_reported_with_file_and_offset_and_everything_before_restored() {
    let _shared = shared();
    let dir = TempDir::new("corrupt");
    let (t, _) = DurableTable::open(cfg(1000), big_segments(dir.path()), 1).unwrap();
    let (_, start) = fill(&t, dir.path(), 10);
    let image = crash_image(dir.path(), "corrupt-img");
    drop(t);
    let seg = segments(image.path()).pop().unwrap();
    let mut bytes = std::fs::read(&seg).unwrap();
    bytes[start as usize + 40] ^= 0x01;
    std::fs::write(&seg, &bytes).unwrap();

    let (t, r) = DurableTable::open(cfg(1000), big_segments(image.path()), 1).unwrap();
    let fault = r.fault.clone().expect("corruption reported");
    assert_eq!((fault.path.clone(), fault.offset), (seg.clone(), start), "{fault}");
    assert!(fault.reason.contains("checksum"), "{fault}");
    assert_eq!((r.records_replayed, r.rows, t.size()), (9, 45, 45), "the nine batches before it are back");
    assert_eq!(t.actors()["a"].last_sequence, 9);
    // The cut bytes are kept for inspection; the segment ends where the bad record began.
    assert_eq!(std::fs::metadata(&seg).unwrap().len(), start);
    assert_eq!(std::fs::read_dir(image.path().join("wal/corrupt")).unwrap().count(), 1);
    // The lost batch can be sent again, and the log is clean afterwards.
    assert!(!t.insert(&batch("a", 10, 10.0, 5), None).unwrap().duplicate);
    let before = contents(&t);
    drop(t);
    let (t, r) = DurableTable::open(cfg(1000), big_segments(image.path()), 1).unwrap();
    assert_eq!((r.fault, contents(&t)), (None, before));
}

#[test]
fn a_torn_tail_is_cut_and_appends_continue_after_it() {
    let _shared = shared();
    for cut in [3u64, 30] {
        let dir = TempDir::new("torn");
        let (t, _) = DurableTable::open(cfg(1000), big_segments(dir.path()), 1).unwrap();
        let (_, start) = fill(&t, dir.path(), 6);
        let image = crash_image(dir.path(), "torn-img");
        drop(t);
        let seg = segments(image.path()).pop().unwrap();
        std::fs::OpenOptions::new().write(true).open(&seg).unwrap().set_len(start + cut).unwrap();

        let (t, r) = DurableTable::open(cfg(1000), big_segments(image.path()), 1).unwrap();
        let fault = r.fault.clone().expect("torn record reported");
        assert_eq!((fault.path.clone(), fault.offset), (seg.clone(), start), "{fault}");
        assert!(fault.reason.starts_with("torn"), "{fault}");
        assert_eq!(t.size(), 25);
        for seq in 6..=8 {
            t.insert(&batch("a", seq, seq as f32, 5), None).unwrap();
        }
        let before = contents(&t);
        assert_eq!(before.len(), 40);
        t.close();
        drop(t);
        let (t, r) = DurableTable::open(cfg(1000), big_segments(image.path()), 1).unwrap();
        assert!(r.fault.is_none(), "{r:?}");
        assert_eq!(contents(&t), before);
        assert_eq!(t.actors()["a"].last_sequence, 8);
    }
}

#[test]
fn a_corrupt_newest_snapshot_falls_back_to_the_previous_one() {
    let _shared = shared();
    let dir = TempDir::new("snapfall");
    let (t, _) = open(cfg(50), dir.path());
    let mut seq = 0;
    let mut more = |t: &Table, n: u64| {
        for _ in 0..n {
            seq += 1;
            t.insert(&batch("a", seq, seq as f32, 4), None).unwrap();
        }
    };
    more(&t, 10);
    let s1 = t.snapshot().unwrap().unwrap();
    more(&t, 10);
    let s2 = t.snapshot().unwrap().unwrap();
    more(&t, 10);
    let expected = (contents(&t), marks(&t));
    let image = crash_image(dir.path(), "snapfall-img");
    drop(t);
    let newest = image.path().join("snapshots").join(s2.path.file_name().unwrap());
    let mut bytes = std::fs::read(&newest).unwrap();
    let mid = bytes.len() / 2;
    bytes[mid] ^= 0x40;
    std::fs::write(&newest, &bytes).unwrap();

    let (t, r) = open(cfg(50), image.path());
    assert_eq!(r.skipped_snapshots.len(), 1, "{r:?}");
    assert_eq!(r.skipped_snapshots[0].path, newest);
    assert!(r.skipped_snapshots[0].reason.contains("checksum"), "{r:?}");
    assert_eq!(r.snapshot.as_deref(), Some(image.path().join("snapshots").join(s1.path.file_name().unwrap()).as_path()));
    assert_eq!((contents(&t), marks(&t)), expected);
    assert!(!newest.exists(), "the corrupt snapshot was set aside");
}

#[test]
fn a_snapshot_ahead_of_a_damaged_log_is_set_aside_and_the_log_alone_restores_its_rows() {
    let _shared = shared();
    let dir = TempDir::new("ahead");
    let (t, _) = DurableTable::open(cfg(1000), big_segments(dir.path()), 1).unwrap();
    let (_, start) = fill(&t, dir.path(), 4);
    t.snapshot().unwrap();
    let image = crash_image(dir.path(), "ahead-img");
    drop(t);
    let seg = segments(image.path()).pop().unwrap();
    std::fs::OpenOptions::new().write(true).open(&seg).unwrap().set_len(start + 10).unwrap();

    let (t, r) = DurableTable::open(cfg(1000), big_segments(image.path()), 1).unwrap();
    assert_eq!(r.snapshot, None);
    assert!(r.skipped_snapshots[0].reason.contains("valid records end at 3"), "{r:?}");
    assert_eq!((t.size(), t.actors()["a"].last_sequence), (15, 3));
    // New records reuse LSN 4 onwards: the old snapshot must never be read again.
    t.insert(&batch("a", 4, 0.0, 1), None).unwrap();
    drop(t);
    let (t, r) = DurableTable::open(cfg(1000), big_segments(image.path()), 1).unwrap();
    assert!(r.skipped_snapshots.is_empty() && r.fault.is_none(), "{r:?}");
    assert_eq!(t.size(), 16);
}

#[test]
fn old_segments_are_deleted_once_their_rows_are_evicted() {
    let _shared = shared();
    let dir = TempDir::new("gc");
    let (t, _) = open(cfg(100), dir.path());
    for seq in 1..=200 {
        t.insert(&batch("a", seq, seq as f32, 10), None).unwrap();
    }
    let written = segments(dir.path()).len();
    assert!(written > 20, "{written} segments");
    let first = t.snapshot().unwrap().unwrap();
    assert_eq!(first.segments_deleted, 0, "the log is kept back to the oldest snapshot kept (none before)");
    t.insert(&batch("a", 201, 0.0, 10), None).unwrap();
    let second = t.snapshot().unwrap().unwrap();
    let left = segments(dir.path()).len();
    assert!(second.segments_deleted > 0 && left <= 4, "deleted {}, {left} of {written} left", second.segments_deleted);
    assert_eq!(std::fs::read_dir(dir.path().join("snapshots")).unwrap().count(), 2, "two snapshots kept");
    // What is left still restores the table.
    let expected = (contents(&t), marks(&t));
    let image = crash_image(dir.path(), "gc-img");
    drop(t);
    let (t, r) = open(cfg(100), image.path());
    assert!(r.fault.is_none() && r.rows_lost == 0, "{r:?}");
    assert_eq!((contents(&t), marks(&t)), expected);
}

#[test]
fn a_directory_is_opened_by_one_table_at_a_time() {
    let _shared = shared();
    let dir = TempDir::new("lock");
    let (t, _) = open(cfg(10), dir.path());
    let e = DurableTable::open(cfg(10), persist(dir.path()), 1).err().expect("second open refused");
    assert!(matches!(&e, ReplayError::Storage { path, .. } if path.ends_with("LOCK")), "{e}");
    drop(t);
    let other = cfg(20);
    open(cfg(10), dir.path()).0.insert(&batch("a", 1, 0.0, 1), None).unwrap();
    let e = DurableTable::open(other, persist(dir.path()), 1).err().expect("another shape refused");
    assert!(matches!(e, ReplayError::InvalidConfig(_)), "{e}");
}

#[test]
fn snapshots_do_not_stall_inserts() {
    let _alone = EXCLUSIVE.write().unwrap_or_else(|p| p.into_inner());
    let dir = TempDir::new("stall");
    let mut c = cfg(1_000_000);
    c.max_batch_rows = 10_000;
    let p = PersistenceConfig { fsync: FsyncPolicy::IntervalMs(100), segment_bytes: 64 << 20, ..persist(dir.path()) };
    let (t, _) = DurableTable::open(c.clone(), p.clone(), 1).unwrap();
    let t = Arc::new(t);
    let fill_start = Instant::now();
    for seq in 1..=100 {
        t.insert(&batch("fill", seq, 0.0, 10_000), None).unwrap();
    }
    let fill = fill_start.elapsed();
    assert_eq!(t.size(), 1_000_000);

    // An inserter runs throughout; its latencies are split into a quiet phase (no snapshot)
    // and a phase with back-to-back snapshots.
    let stop = Arc::new(AtomicBool::new(false));
    let inserter = {
        let (t, stop) = (Arc::clone(&t), Arc::clone(&stop));
        std::thread::spawn(move || {
            let mut lat = Vec::new();
            let mut b = batch("w", 0, 0.0, 100);
            while !stop.load(Ordering::Relaxed) {
                b.sequence += 1;
                let t0 = Instant::now();
                t.insert(&b, None).unwrap();
                lat.push((t0, t0.elapsed()));
            }
            lat
        })
    };
    std::thread::sleep(Duration::from_millis(50));
    let quiet_start = Instant::now();
    std::thread::sleep(Duration::from_millis(300));
    let snap_start = Instant::now();
    let mut copies = Vec::new();
    for _ in 0..3 {
        let info = t.snapshot().unwrap().unwrap();
        copies.push((info.copy, info.write, info.bytes));
    }
    let snap_end = Instant::now();
    stop.store(true, Ordering::Relaxed);
    let lat = inserter.join().unwrap();
    let worst_in = |from: Instant, to: Instant| lat.iter().filter(|(at, _)| *at >= from && *at < to).fold((Duration::ZERO, 0), |(w, n), (_, l)| (w.max(*l), n + 1));
    let (quiet, n_quiet) = worst_in(quiet_start, snap_start);
    let (worst, n) = worst_in(snap_start, snap_end);
    let worst_copy = copies.iter().map(|c| c.0).max().unwrap();
    println!(
        "1M rows: fill {fill:?}; 3 snapshots in {:?}: lock held for the copy {:?}, written in {:?}, {} bytes each; \
         inserts of 100 rows: worst {worst:?} of {n} during snapshots, worst {quiet:?} of {n_quiet} in 300 ms without",
        snap_end - snap_start,
        copies.iter().map(|c| c.0).collect::<Vec<_>>(),
        copies.iter().map(|c| c.1).collect::<Vec<_>>(),
        copies[0].2
    );
    // No timing thresholds here (figures belong to `mapless bench replay`); the structural
    // property: inserts keep completing while snapshots are written. Had a snapshot held the
    // lock while writing its ~13 MB file, at most a couple of inserts would slip in between
    // the three back-to-back snapshots; without a stall there are hundreds.
    let _ = (worst, worst_copy);
    assert!(n >= 50, "only {n} inserts completed during 3 snapshots: snapshots stall inserts");

    // Recovery of a full table from its final snapshot and ~1M logged rows.
    let size = t.size();
    drop(Arc::try_unwrap(t).ok().expect("inserter joined"));
    let (t, r) = DurableTable::open(c, p, 1).unwrap();
    println!("1M rows: reopened in {:?} ({} records, {} segments)", r.elapsed, r.records_replayed, r.segments);
    assert_eq!((t.size(), r.rows_lost, r.fault), (size, 0, None));
}

#[test]
fn corruption_in_an_older_segment_cuts_the_log_there_and_sets_later_segments_aside() {
    let _shared = shared();
    let dir = TempDir::new("midcorrupt");
    let (t, _) = open(cfg(1000), dir.path());
    for seq in 1..=60 {
        t.insert(&batch("a", seq, seq as f32, 5), None).unwrap();
    }
    let image = crash_image(dir.path(), "midcorrupt-img");
    drop(t);
    let segs = segments(image.path());
    assert!(segs.len() >= 4, "{segs:?}");
    let second_first_lsn: u64 = segs[1].file_name().unwrap().to_str().unwrap()[4..24].parse().unwrap();
    let mut bytes = std::fs::read(&segs[1]).unwrap();
    bytes[24 + 50] ^= 0xff;
    std::fs::write(&segs[1], &bytes).unwrap();

    let (t, r) = open(cfg(1000), image.path());
    let fault = r.fault.clone().unwrap();
    assert_eq!((fault.path.as_path(), fault.offset), (segs[1].as_path(), 24), "{fault}");
    let kept = second_first_lsn - 1;
    assert_eq!((r.records_replayed, t.size(), t.actors()["a"].last_sequence), (kept, 5 * kept, kept));
    assert_eq!(segments(image.path()), segs[..2].to_vec(), "later segments moved to wal/corrupt/");
    assert_eq!(std::fs::read_dir(image.path().join("wal/corrupt")).unwrap().count(), segs.len() - 1);
    t.insert(&batch("a", kept + 1, 0.0, 5), None).unwrap();
    drop(t);
    let (t, r) = open(cfg(1000), image.path());
    assert!(r.fault.is_none(), "{r:?}");
    assert_eq!(t.size(), 5 * (kept + 1));
}

#[test]
fn every_fsync_policy_restores_acknowledged_rows_and_background_snapshots_run() {
    let _shared = shared();
    for fsync in [FsyncPolicy::Never, FsyncPolicy::IntervalMs(1), FsyncPolicy::Always] {
        let dir = TempDir::new("policy");
        let p = PersistenceConfig { fsync, snapshot_interval_s: 0.02, ..persist(dir.path()) };
        let (t, _) = DurableTable::open(cfg(300), p.clone(), 1).unwrap();
        for seq in 1..=40 {
            t.insert(&batch("a", seq, seq as f32, 9), None).unwrap();
        }
        let deadline = Instant::now() + Duration::from_secs(10);
        while std::fs::read_dir(dir.path().join("snapshots")).unwrap().count() == 0 {
            assert!(Instant::now() < deadline, "{fsync:?}: no background snapshot");
            std::thread::sleep(Duration::from_millis(10));
        }
        for seq in 41..=50 {
            t.insert(&batch("a", seq, seq as f32, 9), None).unwrap();
        }
        let expected = (contents(&t), marks(&t));
        let image = crash_image(dir.path(), "policy-img");
        drop(t);
        let (t, r) = DurableTable::open(cfg(300), PersistenceConfig { dir: Some(image.path().to_path_buf()), ..p }, 1).unwrap();
        assert!(r.fault.is_none() && r.rows_lost == 0, "{fsync:?}: {r:?}");
        assert_eq!((contents(&t), marks(&t)), expected, "{fsync:?}");
    }
}

#[test]
fn persistence_config_reads_from_yaml_with_defaults() {
    let _shared = shared();
    let p: PersistenceConfig = serde_yaml::from_str("dir: /var/lib/mapless\nfsync: {interval_ms: 250}\n").unwrap();
    assert_eq!(p.dir.as_deref(), Some(Path::new("/var/lib/mapless")));
    assert_eq!((p.fsync, p.segment_bytes, p.snapshot_interval_s), (FsyncPolicy::IntervalMs(250), 64 << 20, 30.0));
    let p: PersistenceConfig = serde_yaml::from_str("fsync: always").unwrap();
    assert_eq!((p.dir, p.fsync), (None, FsyncPolicy::Always));
    assert!(serde_yaml::from_str::<PersistenceConfig>("fsync: sometimes").is_err());
    let back: PersistenceConfig = serde_yaml::from_str(&serde_yaml::to_string(&PersistenceConfig::default()).unwrap()).unwrap();
    assert_eq!(back, PersistenceConfig::default());
    let bad = PersistenceConfig { segment_bytes: 10, ..PersistenceConfig::default() };
    assert!(matches!(DurableTable::open(cfg(10), bad, 1), Err(ReplayError::InvalidConfig(_))));
}
