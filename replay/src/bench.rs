//! Measurements behind `mapless bench replay`: ingest rate over gRPC with concurrent writers,
//! minibatch rate and latency of the sample stream, and resident memory of a full table.
//! Each function starts what it measures in-process on loopback and tears it down.
//!
//! Writers send their float columns as `bytes *_f32le` fields (the shm writer always does;
//! the gRPC writers' batches are built that way), and the sample stream asks for them
//! (`float_columns_as_bytes`): the fast encoding of transition.proto, "Two encodings".

use std::sync::Arc;
use std::sync::atomic::{AtomicBool, AtomicU64, Ordering};
use std::time::{Duration, Instant};

use mapless_proto::v1::replay_service_client::ReplayServiceClient;
use mapless_proto::v1::{ProtocolVersion, SampleRequest, TransitionBatch};
use mapless_proto::{FloatEncoding, MAX_MESSAGE_BYTES, Transition, TransitionBatchBuilder};
use tokio::sync::mpsc;
use tokio_stream::wrappers::ReceiverStream;

use crate::config::{RateLimiterConfig, TableConfig};
use crate::error::ReplayError;
use crate::table::Table;

/// Rows per insert batch in the benchmarks (an actor's typical flush).
pub const BATCH_ROWS: usize = 256;

/// A table sized for `obs_dim`, no rate limiting (the benches measure transport and storage).
pub fn bench_table(capacity: usize, obs_dim: usize) -> Result<Table, ReplayError> {
    let cfg = TableConfig { capacity, obs_dim, act_dim: 2, rate_limiter: RateLimiterConfig { min_size_to_sample: 1, samples_per_insert: None, error_buffer: 0.0 }, ..TableConfig::default() };
    Table::new(cfg, 1)
}

/// A batch of `rows` plausible transitions for `actor`, float columns as `*_f32le` bytes
/// (so clones share them, as an actor resending a batch would).
pub fn synthetic_batch(actor: &str, seq: u64, rows: usize, obs_dim: usize) -> TransitionBatch {
    let mut b = TransitionBatchBuilder::with_capacity(obs_dim, 2, rows);
    let obs: Vec<f32> = (0..obs_dim).map(|k| (k as f32 * 0.37).sin()).collect();
    for r in 0..rows {
        let t = Transition { obs: &obs, action: &[0.5, -0.25], reward: 0.3, next_obs: &obs, terminal: false, truncated: r == rows - 1, episode_id: seq, step: r as u32, policy_version: 1 };
        b.push(t).expect("synthetic rows are valid");
    }
    let mut batch = b.finish(actor, seq);
    batch.convert_float_columns(FloatEncoding::F32Le);
    batch
}

/// Inserts `rows` synthetic rows as actor "fill", `batch_rows` at a time.
fn fill(table: &Table, rows: usize, obs_dim: usize, batch_rows: usize) -> Result<(), ReplayError> {
    for (seq, start) in (0..rows).step_by(batch_rows).enumerate() {
        table.insert(&synthetic_batch("fill", seq as u64 + 1, batch_rows.min(rows - start), obs_dim), None)?;
    }
    Ok(())
}

fn runtime() -> tokio::runtime::Runtime {
    tokio::runtime::Builder::new_multi_thread().worker_threads(2).enable_all().build().expect("tokio runtime")
}

async fn client(addr: std::net::SocketAddr) -> ReplayServiceClient<tonic::transport::Channel> {
    ReplayServiceClient::connect(format!("http://{addr}")).await.expect("connect to the in-process server").max_decoding_message_size(MAX_MESSAGE_BYTES).max_encoding_message_size(MAX_MESSAGE_BYTES)
}

/// Rows of the ingest benchmarks' table (paper Table I).
pub const INGEST_TABLE_ROWS: usize = 1_000_000;

/// A table of [`INGEST_TABLE_ROWS`] already filled to capacity, so every measured insert
/// evicts the oldest rows, as in a long run: the first fill of fresh memory is page-fault bound
/// and measured on its own by [`first_fill_rows_per_s`].
fn full_table(obs_dim: usize) -> Result<Table, ReplayError> {
    let table = bench_table(INGEST_TABLE_ROWS, obs_dim)?;
    fill(&table, INGEST_TABLE_ROWS, obs_dim, BATCH_ROWS)?;
    Ok(table)
}

/// Rows per second of the first fill of a fresh [`INGEST_TABLE_ROWS`]-row table, inserted
/// in-process (no transport) in batches of [`BATCH_ROWS`]: what a new replay's start costs.
pub fn first_fill_rows_per_s(obs_dim: usize) -> Result<f64, ReplayError> {
    let table = bench_table(INGEST_TABLE_ROWS, obs_dim)?;
    let t0 = Instant::now();
    fill(&table, INGEST_TABLE_ROWS, obs_dim, BATCH_ROWS)?;
    Ok(INGEST_TABLE_ROWS as f64 / t0.elapsed().as_secs_f64())
}

/// Rows per second acknowledged over gRPC with `writers` concurrent Insert streams, each
/// pipelining pre-encoded batches, for about `duration`, into a full table.
pub fn grpc_ingest_rows_per_s(writers: usize, obs_dim: usize, duration: Duration) -> f64 {
    let rt = runtime();
    rt.block_on(async move {
        let table = Arc::new(full_table(obs_dim).expect("valid table"));
        let listener = tokio::net::TcpListener::bind("127.0.0.1:0").await.expect("bind loopback");
        let addr = listener.local_addr().expect("address");
        let (stop_tx, stop_rx) = tokio::sync::oneshot::channel::<()>();
        let server = tokio::spawn(crate::server::run(listener, Arc::clone(&table), async {
            let _ = stop_rx.await;
        }));
        let acked = Arc::new(AtomicU64::new(0));
        let stop = Arc::new(AtomicBool::new(false));
        let mut tasks = Vec::new();
        for w in 0..writers {
            let (acked, stop) = (Arc::clone(&acked), Arc::clone(&stop));
            tasks.push(tokio::spawn(async move {
                let mut c = client(addr).await;
                let (tx, rx) = mpsc::channel::<TransitionBatch>(32);
                let actor = format!("bench-{w}");
                let template = synthetic_batch(&actor, 1, BATCH_ROWS, obs_dim);
                let feeder = tokio::spawn(async move {
                    for seq in 1.. {
                        if stop.load(Ordering::Relaxed) {
                            return;
                        }
                        let mut b = template.clone();
                        b.sequence = seq;
                        if tx.send(b).await.is_err() {
                            return;
                        }
                    }
                });
                let mut acks = c.insert(ReceiverStream::new(rx)).await.expect("insert stream").into_inner();
                while let Ok(Some(a)) = acks.message().await {
                    acked.fetch_add(a.accepted_rows as u64, Ordering::Relaxed);
                }
                feeder.abort();
            }));
        }
        // Measure after a short warm-up.
        tokio::time::sleep(Duration::from_millis(300)).await;
        let (a0, t0) = (acked.load(Ordering::Relaxed), Instant::now());
        tokio::time::sleep(duration).await;
        let rate = (acked.load(Ordering::Relaxed) - a0) as f64 / t0.elapsed().as_secs_f64();
        stop.store(true, Ordering::Relaxed);
        let _ = stop_tx.send(());
        for t in tasks {
            let _ = tokio::time::timeout(Duration::from_secs(10), t).await;
        }
        let _ = tokio::time::timeout(Duration::from_secs(10), server).await;
        table.close();
        rate
    })
}

/// Sample-stream figures: minibatches per second and the gaps between consecutive
/// minibatches at the client (what a learner waits), p50 and p99.
pub struct SampleFigures {
    pub minibatches_per_s: f64,
    pub p50_us: f64,
    pub p99_us: f64,
}

/// Fills a table with `rows` rows, then reads minibatches of `batch` rows from one Sample
/// stream with `prefetch` and `float_columns_as_bytes` for about `duration`.
pub fn grpc_sample(rows: usize, obs_dim: usize, batch: u32, prefetch: u32, duration: Duration) -> SampleFigures {
    let rt = runtime();
    rt.block_on(async move {
        let table = Arc::new(bench_table(rows.max(1), obs_dim).expect("valid table"));
        fill(&table, rows, obs_dim, BATCH_ROWS).expect("fill");
        let listener = tokio::net::TcpListener::bind("127.0.0.1:0").await.expect("bind loopback");
        let addr = listener.local_addr().expect("address");
        let (stop_tx, stop_rx) = tokio::sync::oneshot::channel::<()>();
        let server = tokio::spawn(crate::server::run(listener, Arc::clone(&table), async {
            let _ = stop_rx.await;
        }));
        let mut c = client(addr).await;
        let req = SampleRequest {
            protocol_version: ProtocolVersion::V1 as i32,
            table: table.config().name.clone(),
            batch_size: batch,
            prefetch,
            timeout_ms: 5_000,
            max_batches: 0,
            importance_beta: None,
            float_columns_as_bytes: true,
        };
        let mut stream = c.sample(req).await.expect("sample stream").into_inner();
        // Warm-up.
        let warm = Instant::now();
        while warm.elapsed() < Duration::from_millis(300) {
            stream.message().await.expect("minibatch").expect("stream open");
        }
        let mut gaps = Vec::new();
        let start = Instant::now();
        let mut last = start;
        while start.elapsed() < duration {
            stream.message().await.expect("minibatch").expect("stream open");
            let now = Instant::now();
            gaps.push(now.duration_since(last).as_secs_f64() * 1e6);
            last = now;
        }
        let n = gaps.len();
        let secs = start.elapsed().as_secs_f64();
        drop(stream);
        let _ = stop_tx.send(());
        let _ = tokio::time::timeout(Duration::from_secs(10), server).await;
        table.close();
        gaps.sort_by(|a, b| a.total_cmp(b));
        let pct = |p: f64| gaps[((n as f64 * p) as usize).min(n - 1)];
        SampleFigures { minibatches_per_s: n as f64 / secs, p50_us: pct(0.50), p99_us: pct(0.99) }
    })
}

/// Resident-memory growth of filling a table with `rows` rows, and the raw payload of those
/// rows (obs + next_obs + action + reward + the two flags + episode id, step, policy version).
pub fn memory(rows: usize, obs_dim: usize) -> (u64, u64) {
    let before = resident_bytes();
    let table = bench_table(rows, obs_dim).expect("valid table");
    fill(&table, rows, obs_dim, BATCH_ROWS).expect("fill");
    let after = resident_bytes();
    let raw_row = (2 * obs_dim + 2 + 1) * 4 + 2 + 8 + 4 + 8;
    drop(table);
    (after.saturating_sub(before), (rows * raw_row) as u64)
}

/// This process's resident set size (Linux /proc), 0 where unavailable.
pub fn resident_bytes() -> u64 {
    std::fs::read_to_string("/proc/self/statm").ok().and_then(|s| s.split_whitespace().nth(1).and_then(|p| p.parse::<u64>().ok())).map(|pages| pages * 4096).unwrap_or(0)
}

/// Rows per second stored over iceoryx2 shared memory with `writers` writer threads (each an
/// [`ShmWriter`](mapless_net::shm::ShmWriter) with its own window of unacknowledged batches), for
/// about `duration`, into a full table. Uses a private iceoryx2 domain and removes it afterwards.
pub fn shm_ingest_rows_per_s(writers: usize, obs_dim: usize, duration: Duration) -> Result<f64, ReplayError> {
    use crate::shm::ShmIngest;
    use mapless_net::shm::{ShmConfig, ShmWriter};
    let table = Arc::new(full_table(obs_dim)?);
    let id = std::process::id();
    let domain = format!("mlbench{id}_");
    let cfg = ShmConfig { prefix: format!("mapless-bench/{id}"), domain: domain.clone(), ..ShmConfig::for_table("bench") };
    let ingest = ShmIngest::spawn(Arc::clone(&table), cfg.clone())?;
    let stop = Arc::new(AtomicBool::new(false));
    let threads: Vec<_> = (0..writers)
        .map(|w| {
            let (cfg, stop) = (cfg.clone(), Arc::clone(&stop));
            std::thread::spawn(move || -> Result<(), ReplayError> {
                let actor = format!("bench-{w}");
                let mut writer = ShmWriter::connect(&cfg, &actor)?;
                let mut batch = synthetic_batch(&actor, 1, BATCH_ROWS, obs_dim);
                let mut seq = 0;
                while !stop.load(Ordering::Relaxed) {
                    seq += 1;
                    batch.sequence = seq;
                    writer.send(&batch)?; // waits while the window is full
                    writer.poll_acks()?;
                }
                Ok(())
            })
        })
        .collect();
    std::thread::sleep(Duration::from_millis(300));
    let (r0, t0) = (ingest.stats().rows_stored, Instant::now());
    std::thread::sleep(duration);
    let rate = (ingest.stats().rows_stored - r0) as f64 / t0.elapsed().as_secs_f64();
    stop.store(true, Ordering::Relaxed);
    let mut result = Ok(rate);
    for t in threads {
        if let Ok(Err(e)) = t.join() {
            result = Err(e);
        }
    }
    ingest.stop();
    table.close();
    mapless_net::shm::remove_private_domain_files(&domain);
    result
}

/// Snapshot cost at `rows` rows of 17-float observations with persistence on (temp dir):
/// (longest time a snapshot held the table lock, worst latency of a 100-row insert while three
/// snapshots ran back to back), in milliseconds.
pub fn snapshot_stall_ms(rows: usize) -> Result<(f64, f64), ReplayError> {
    use crate::config::PersistenceConfig;
    use crate::persist::DurableTable;
    let dir = std::env::temp_dir().join(format!("mapless-bench-snapshot-{}", std::process::id()));
    let _ = std::fs::remove_dir_all(&dir);
    let cfg = TableConfig { capacity: rows, max_batch_rows: 10_000, ..bench_table(1, 17)?.config().clone() };
    let persist = PersistenceConfig { dir: Some(dir.clone()), snapshot_interval_s: 0.0, ..PersistenceConfig::default() };
    let (table, _) = DurableTable::open(cfg, persist, 1)?;
    let table = Arc::new(table);
    fill(&table, rows, 17, 10_000)?;
    let stop = Arc::new(AtomicBool::new(false));
    let inserter = {
        let (t, stop) = (Arc::clone(&table), Arc::clone(&stop));
        std::thread::spawn(move || -> Result<Duration, ReplayError> {
            let mut b = synthetic_batch("w", 0, 100, 17);
            let mut worst = Duration::ZERO;
            while !stop.load(Ordering::Relaxed) {
                b.sequence += 1;
                let t0 = Instant::now();
                t.insert(&b, None)?;
                worst = worst.max(t0.elapsed());
            }
            Ok(worst)
        })
    };
    std::thread::sleep(Duration::from_millis(50));
    let mut lock = Duration::ZERO;
    for _ in 0..3 {
        if let Some(info) = table.snapshot()? {
            lock = lock.max(info.copy);
        }
    }
    stop.store(true, Ordering::Relaxed);
    let worst = inserter.join().map_err(|_| ReplayError::BadRequest("inserter panicked".into()))??;
    table.close();
    drop(table);
    let _ = std::fs::remove_dir_all(&dir);
    Ok((lock.as_secs_f64() * 1e3, worst.as_secs_f64() * 1e3))
}

/// Write-ahead log figures under one fsync policy: acknowledged rows per second, the latency
/// of one insert (call to acknowledgement) at p50 and p99, and rows per fsync round.
pub struct DurabilityFigures {
    pub rows_per_s: f64,
    pub p50_us: f64,
    pub p99_us: f64,
    /// Rows acknowledged per fsync the log made (infinite when it made none).
    pub rows_per_fsync: f64,
}

/// Inserts into a persistent table whose directory is a fresh folder under `base` (the disk
/// measured) with `policy`, from `writers` threads, each inserting [`BATCH_ROWS`]-row batches
/// of 17-float rows one at a time (the next after the previous one's acknowledgement), for
/// about `duration` after a 300 ms warm-up. In-process, no transport: the cost of the log.
/// The table holds 100,000 rows, so inserts evict once it is full; no snapshots run.
pub fn durable_insert(policy: crate::config::FsyncPolicy, writers: usize, base: &std::path::Path, duration: Duration) -> Result<DurabilityFigures, ReplayError> {
    use crate::config::PersistenceConfig;
    use crate::persist::DurableTable;
    let dir = base.join(format!("mapless-bench-durability-{}-{}", std::process::id(), crate::clock::unix_ms()));
    let cfg = TableConfig { capacity: 100_000, max_batch_rows: BATCH_ROWS, ..bench_table(1, 17)?.config().clone() };
    let persist = PersistenceConfig { dir: Some(dir.clone()), fsync: policy, snapshot_interval_s: 0.0, ..PersistenceConfig::default() };
    let (table, _) = DurableTable::open(cfg, persist, 1)?;
    let table = Arc::new(table);
    let measuring = Arc::new(AtomicBool::new(false));
    let stop = Arc::new(AtomicBool::new(false));
    let threads: Vec<_> = (0..writers)
        .map(|w| {
            let (t, measuring, stop) = (Arc::clone(&table), Arc::clone(&measuring), Arc::clone(&stop));
            std::thread::spawn(move || -> Result<(Vec<f64>, u64), ReplayError> {
                let mut b = synthetic_batch(&format!("w{w}"), 0, BATCH_ROWS, 17);
                let (mut lat_us, mut rows) = (Vec::new(), 0u64);
                while !stop.load(Ordering::Relaxed) {
                    b.sequence += 1;
                    let t0 = Instant::now();
                    t.insert(&b, None)?;
                    if measuring.load(Ordering::Relaxed) {
                        lat_us.push(t0.elapsed().as_secs_f64() * 1e6);
                        rows += BATCH_ROWS as u64;
                    }
                }
                Ok((lat_us, rows))
            })
        })
        .collect();
    std::thread::sleep(Duration::from_millis(300));
    let fsyncs = || table.wal_sync().map_or(0, |s| s.fsyncs());
    let (f0, t0) = (fsyncs(), Instant::now());
    measuring.store(true, Ordering::Relaxed);
    std::thread::sleep(duration);
    measuring.store(false, Ordering::Relaxed);
    let (secs, f1) = (t0.elapsed().as_secs_f64(), fsyncs());
    stop.store(true, Ordering::Relaxed);
    let (mut lat, mut rows, mut failed) = (Vec::new(), 0u64, None);
    for h in threads {
        match h.join() {
            Ok(Ok((l, r))) => {
                lat.extend(l);
                rows += r;
            }
            Ok(Err(e)) => failed = Some(e),
            Err(_) => failed = Some(ReplayError::BadRequest("a bench writer panicked".into())),
        }
    }
    table.close();
    drop(table);
    let _ = std::fs::remove_dir_all(&dir);
    if let Some(e) = failed {
        return Err(e);
    }
    lat.sort_by(|a, b| a.total_cmp(b));
    let pct = |p: f64| lat.get(((lat.len() as f64 * p) as usize).min(lat.len().saturating_sub(1))).copied().unwrap_or(f64::NAN);
    Ok(DurabilityFigures { rows_per_s: rows as f64 / secs, p50_us: pct(0.50), p99_us: pct(0.99), rows_per_fsync: rows as f64 / (f1 - f0) as f64 })
}
