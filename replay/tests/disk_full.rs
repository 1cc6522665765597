//! A full disk, for real: the replay's directory on a 1 MiB tmpfs that this test mounts
//! (`mount -t tmpfs`, so it needs root or CAP_SYS_ADMIN, and fails, saying so, without it)
//! and fills with a file. Inserts over gRPC are refused with RESOURCE_EXHAUSTED naming the
//! disk and counted, sampling goes on, nothing stored is damaged, and once the file is deleted
//! the same server accepts inserts again.

use std::net::SocketAddr;
use std::path::Path;
use std::sync::Arc;
use std::time::Duration;

use mapless_proto::v1::replay_service_client::ReplayServiceClient;
use mapless_proto::v1::{InsertAck, ProtocolVersion, SampleRequest, TransitionBatch};
use mapless_proto::{Transition, TransitionBatchBuilder};
use mapless_replay::{ActorRegistry, DurableTable, FsyncPolicy, PersistenceConfig, RateLimiterConfig, ReplayError, StorageRefusal, TableConfig, metrics};
use tonic::Code;
use tonic::transport::Channel;

const D: usize = 3;
const PATIENCE: Duration = Duration::from_secs(10);

#[path = "../../tests/common/tmpfs.rs"]
mod tmpfs;
use tmpfs::{Tmpfs, fill};

fn cfg() -> TableConfig {
    TableConfig {
        capacity: 10_000,
        obs_dim: D,
        act_dim: 2,
        rate_limiter: RateLimiterConfig { min_size_to_sample: 1, samples_per_insert: None, error_buffer: 0.0 },
        max_batch_rows: 200,
        max_sample_rows: 10_000,
        ..TableConfig::default()
    }
}

fn persist(dir: &Path) -> PersistenceConfig {
    PersistenceConfig { dir: Some(dir.to_path_buf()), segment_bytes: 64 << 10, fsync: FsyncPolicy::IntervalMs(20), snapshot_interval_s: 0.0 }
}

/// 100 rows (about 6 KB as a record) whose reward is `seq * 1000 + i`.
fn batch(seq: u64) -> TransitionBatch {
    batch_of("filler-actor", seq)
}

fn batch_of(actor: &str, seq: u64) -> TransitionBatch {
    let mut b = TransitionBatchBuilder::new(D, 2);
    for i in 0..100 {
        let r = (seq * 1000 + i) as f32;
        b.push(Transition { obs: &[r, 0.5, -r], action: &[0.1, -0.1], reward: r, next_obs: &[r, 1.0, 0.0], terminal: false, truncated: i == 99, episode_id: seq, step: i as u32, policy_version: 1 })
            .unwrap();
    }
    b.finish(actor, seq)
}

async fn client(addr: SocketAddr) -> ReplayServiceClient<Channel> {
    ReplayServiceClient::connect(format!("http://{addr}")).await.unwrap()
}

/// One batch on a fresh Insert stream: its ack or the status that ended the stream.
async fn insert(c: &mut ReplayServiceClient<Channel>, b: TransitionBatch) -> Result<InsertAck, tonic::Status> {
    let mut acks = c.insert(tokio_stream::iter([b])).await?.into_inner();
    match tokio::time::timeout(PATIENCE, acks.message()).await.expect("an answer in time")? {
        Some(ack) => Ok(ack),
        None => Err(tonic::Status::unknown("insert stream ended without an answer")),
    }
}

/// Rows of one minibatch of `rows` drawn over a Sample stream.
async fn sample(c: &mut ReplayServiceClient<Channel>, rows: u32) -> Result<usize, tonic::Status> {
    let req = SampleRequest {
        protocol_version: ProtocolVersion::V1 as i32,
        table: mapless_proto::DEFAULT_TABLE.into(),
        batch_size: rows,
        prefetch: 1,
        timeout_ms: 5_000,
        max_batches: 1,
        importance_beta: None,
        float_columns_as_bytes: false,
    };
    let mut s = c.sample(req).await?.into_inner();
    let got = tokio::time::timeout(PATIENCE, s.message()).await.expect("a minibatch in time")?;
    Ok(got.map_or(0, |b| b.keys.len()))
}

/// Every stored row (key → reward): one minibatch as large as the table draws each row once.
fn contents(t: &mapless_replay::Table) -> std::collections::BTreeMap<u64, f32> {
    let n = t.size() as usize;
    let s = t.sample(n, None, Some(std::time::Instant::now() + PATIENCE)).unwrap();
    s.keys.iter().copied().zip(s.reward.iter().copied()).collect()
}

fn metric(text: &str, series: &str) -> f64 {
    let line = text.lines().find(|l| l.starts_with(series)).unwrap_or_else(|| panic!("no {series} in\n{text}"));
    line.rsplit(' ').next().unwrap().parse().unwrap()
}

#[test]
fn a_full_disk_refuses_inserts_with_resource_exhausted_keeps_sampling_and_accepts_again_once_space_returns() {
    let disk = Tmpfs::mount("1m");
    let dir = disk.path().join("replay");
    let (table, _) = DurableTable::open(cfg(), persist(&dir), 1).unwrap();
    let table = Arc::new(table);
    let registry = Arc::new(ActorRegistry::in_memory(16));
    let rt = tokio::runtime::Builder::new_multi_thread().worker_threads(2).enable_all().build().unwrap();
    let (stop_tx, stop_rx) = tokio::sync::oneshot::channel::<()>();
    let listener = rt.block_on(tokio::net::TcpListener::bind("127.0.0.1:0")).unwrap();
    let addr = listener.local_addr().unwrap();
    let server = rt.spawn(mapless_replay::server::run(listener, Arc::clone(table.table()), async {
        let _ = stop_rx.await;
    }));
    let mut c = rt.block_on(client(addr));

    for seq in 1..=5 {
        assert!(!rt.block_on(insert(&mut c, batch(seq))).unwrap().duplicate);
    }
    let filler = disk.path().join("filler");
    let filled = fill(&filler);
    assert!(filled > 0, "the tmpfs had room for the filler");

    // Full: each insert is refused (the record's partial write into the log's last page is
    // rolled back), with a status that names the disk; nothing is stored.
    for _ in 0..3 {
        let status = rt.block_on(insert(&mut c, batch(6))).unwrap_err();
        assert_eq!(status.code(), Code::ResourceExhausted, "{status:?}");
        assert!(status.message().starts_with("disk full: ") && status.message().contains(&dir.join("wal").display().to_string()), "{}", status.message());
    }
    assert_eq!(table.size(), 500);
    assert_eq!(table.storage_refusals(false, StorageRefusal::DiskFull), 3);
    let text = metrics::render(table.table(), &registry, &Default::default());
    assert_eq!(metric(&text, r#"replay_storage_refusals_total{table="transitions",op="insert",reason="disk_full"}"#), 3.0);
    assert_eq!(metric(&text, r#"replay_storage_refusals_total{table="transitions",op="insert",reason="io_error"}"#), 0.0);

    // An actor's insert client (mapless-net) keeps a refused batch and resends it: nothing is
    // dropped while the disk is full, and the batch is stored once space returns (below).
    let mut actor = mapless_net::insert::InsertClient::new(rt.handle().clone(), mapless_net::GrpcEndpoint::new(format!("http://{addr}")), 4);
    let never = std::sync::atomic::AtomicBool::new(false);
    actor.send(batch_of("net-actor", 1), &never).unwrap();
    assert!(!actor.flush(std::time::Instant::now() + Duration::from_millis(1500)), "not acknowledged while the disk is full");
    assert_eq!((actor.stats().acked, actor.stats().rejected), (0, 0), "kept, not dropped: {:?}", actor.stats());
    assert!(table.storage_refusals(false, StorageRefusal::DiskFull) > 3, "the client resent it");
    assert_eq!(table.size(), 500);

    // Sampling goes on; a snapshot cannot be written, and leaves nothing behind.
    assert_eq!(rt.block_on(sample(&mut c, 64)).unwrap(), 64);
    let e = table.snapshot().unwrap_err();
    assert!(matches!(e, ReplayError::DiskFull { .. }), "{e}");
    let snapshots: Vec<_> = std::fs::read_dir(dir.join("snapshots")).unwrap().collect();
    assert!(snapshots.is_empty(), "no snapshot or temporary file left: {snapshots:?}");

    // Space returns: the same server takes the refused batch, as new.
    std::fs::remove_file(&filler).unwrap();
    let ack = rt.block_on(insert(&mut c, batch(6))).unwrap();
    assert!(!ack.duplicate && ack.accepted_rows == 100, "{ack:?}");
    assert!(table.snapshot().unwrap().is_some(), "snapshots work again");
    rt.block_on(insert(&mut c, batch(7))).unwrap();
    assert!(actor.flush(std::time::Instant::now() + PATIENCE), "the kept batch is stored once space returns");
    assert_eq!((actor.stats().acked, actor.stats().rejected), (1, 0), "{:?}", actor.stats());
    drop(actor);
    let stored = contents(table.table());
    assert_eq!(stored.len(), 800);

    let _ = stop_tx.send(());
    rt.block_on(async { tokio::time::timeout(PATIENCE, server).await }).unwrap().unwrap().unwrap();
    drop(c);
    table.close();
    drop(table);

    // Nothing stored was damaged: the log and snapshot bring back exactly those rows.
    let (again, report) = DurableTable::open(cfg(), persist(&dir), 1).unwrap();
    assert!(report.fault.is_none(), "{:?}", report.fault);
    assert_eq!(contents(&again), stored);
    assert_eq!(again.actors()["filler-actor"].last_sequence, 7);
    assert_eq!(again.actors()["net-actor"].last_sequence, 1);
    drop(again);
    drop(disk);
}
