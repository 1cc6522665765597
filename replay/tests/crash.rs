//! Crash consistency of the real service process: several writers stream over gRPC, the
//! server is killed with SIGKILL mid-stream, restarted on the same data directory, and must
//! hold every acknowledged batch; after the writers resend everything they sent, the table
//! holds every batch exactly once.

use std::io::{BufRead, BufReader};
use std::net::SocketAddr;
use std::process::{Child, Command, Stdio};
use std::sync::Arc;
use std::sync::atomic::{AtomicU64, Ordering};
use std::time::Duration;

use mapless_proto::v1::replay_service_client::ReplayServiceClient;
use mapless_proto::v1::{ProtocolVersion, SampleRequest, ServerInfoRequest, ServerInfoResponse, TransitionBatch};
use mapless_proto::{MAX_MESSAGE_BYTES, Transition, TransitionBatchBuilder};
use tokio::sync::mpsc;
use tokio_stream::wrappers::ReceiverStream;
use tonic::transport::Channel;

const WRITERS: u64 = 4;
const ROWS: usize = 50;
const OBS: usize = 3;

/// Rows carry their identity: obs = [writer, sequence, row].
fn batch(writer: u64, seq: u64) -> TransitionBatch {
    let mut b = TransitionBatchBuilder::new(OBS, 2);
    for r in 0..ROWS {
        let obs = [writer as f32, seq as f32, r as f32];
        b.push(Transition { obs: &obs, action: &[0.0, 0.0], reward: 1.0, next_obs: &obs, terminal: false, truncated: false, episode_id: seq, step: r as u32, policy_version: 0 }).expect("valid row");
    }
    b.finish(format!("writer-{writer}"), seq)
}

#[allow(clippy::zombie_processes)] // the caller owns the child and kills or waits for it
fn start(dir: &std::path::Path) -> (Child, SocketAddr) {
    let mut child = Command::new(env!("CARGO_BIN_EXE_mapless-replay"))
        .args(["--listen", "127.0.0.1:0", "--no-metrics", "--no-shm", "--capacity", "1000000", "--obs-dim", "3", "--act-dim", "2", "--min-size-to-sample", "1", "--data-dir"])
        .arg(dir)
        .env("RUST_LOG", "warn")
        .stdout(Stdio::piped())
        .stderr(Stdio::inherit())
        .spawn()
        .expect("start mapless-replay");
    let mut out = BufReader::new(child.stdout.take().expect("stdout"));
    let mut line = String::new();
    loop {
        line.clear();
        assert!(out.read_line(&mut line).expect("read stdout") > 0, "server exited before listening");
        if let Some(a) = line.trim().strip_prefix("listening on ") {
            return (child, a.parse().expect("address"));
        }
    }
}

async fn connect(addr: SocketAddr) -> ReplayServiceClient<Channel> {
    ReplayServiceClient::connect(format!("http://{addr}")).await.expect("connect").max_decoding_message_size(MAX_MESSAGE_BYTES)
}

async fn info(c: &mut ReplayServiceClient<Channel>) -> ServerInfoResponse {
    c.server_info(ServerInfoRequest { protocol_version: ProtocolVersion::V1 as i32 }).await.expect("info").into_inner()
}

/// Streams batches 1.. until the server goes away; records how many were sent and the highest
/// acknowledged sequence.
async fn stream_until_gone(addr: SocketAddr, writer: u64, sent: Arc<AtomicU64>, acked: Arc<AtomicU64>) {
    let mut client = connect(addr).await;
    let (tx, rx) = mpsc::channel(8);
    let Ok(resp) = client.insert(ReceiverStream::new(rx)).await else { return };
    let mut acks = resp.into_inner();
    let feeder = tokio::spawn(async move {
        for seq in 1.. {
            if tx.send(batch(writer, seq)).await.is_err() {
                return;
            }
            sent.store(seq, Ordering::SeqCst);
        }
    });
    while let Ok(Some(a)) = acks.message().await {
        assert!(!a.duplicate);
        acked.store(a.sequence, Ordering::SeqCst);
    }
    feeder.abort();
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn kill_9_mid_stream_loses_no_acknowledged_batch_and_resends_insert_nothing_twice() {
    let dir = std::env::temp_dir().join(format!("mapless-replay-crash-{}", std::process::id()));
    let _ = std::fs::remove_dir_all(&dir);
    let (mut child, addr) = start(&dir);
    let sent: Vec<Arc<AtomicU64>> = (0..WRITERS).map(|_| Arc::new(AtomicU64::new(0))).collect();
    let acked: Vec<Arc<AtomicU64>> = (0..WRITERS).map(|_| Arc::new(AtomicU64::new(0))).collect();
    let writers: Vec<_> = (0..WRITERS).map(|w| tokio::spawn(stream_until_gone(addr, w, Arc::clone(&sent[w as usize]), Arc::clone(&acked[w as usize])))).collect();
    // Let every writer get well into its stream, then pull the plug.
    let deadline = tokio::time::Instant::now() + Duration::from_secs(30);
    while acked.iter().any(|a| a.load(Ordering::SeqCst) < 20) {
        assert!(tokio::time::Instant::now() < deadline, "writers made no progress");
        tokio::time::sleep(Duration::from_millis(10)).await;
    }
    child.kill().expect("SIGKILL"); // std's kill is SIGKILL on Unix
    child.wait().expect("reaped");
    for w in writers {
        tokio::time::timeout(Duration::from_secs(10), w).await.expect("writer notices the dead server").expect("writer task");
    }
    let sent: Vec<u64> = sent.iter().map(|s| s.load(Ordering::SeqCst)).collect();
    let acked: Vec<u64> = acked.iter().map(|a| a.load(Ordering::SeqCst)).collect();

    let (mut child, addr) = start(&dir);
    let mut client = connect(addr).await;
    let before = info(&mut client).await;
    let mut stored_rows = 0;
    for w in 0..WRITERS as usize {
        let a = before.actors.iter().find(|a| a.actor_id == format!("writer-{w}")).expect("writer known after restart");
        assert!(a.last_sequence >= acked[w], "writer {w}: acknowledged {} but only {} restored", acked[w], a.last_sequence);
        assert!(a.last_sequence <= sent[w], "writer {w}: restored {} of {} sent", a.last_sequence, sent[w]);
        assert_eq!(a.rows, a.last_sequence * ROWS as u64, "writer {w}: every stored batch once");
        stored_rows += a.rows;
    }
    assert_eq!(before.size, stored_rows, "no extra rows");
    let restored: Vec<u64> = (0..WRITERS).map(|w| before.actors.iter().find(|a| a.actor_id == format!("writer-{w}")).map(|a| a.last_sequence).unwrap_or(0)).collect();
    eprintln!("sent {sent:?}, acknowledged {acked:?}, restored {restored:?}");

    // Each writer resends everything it sent: stored ones are duplicates, the rest go in.
    for w in 0..WRITERS {
        let (tx, rx) = mpsc::channel(8);
        let mut acks = client.insert(ReceiverStream::new(rx)).await.expect("insert").into_inner();
        let n = sent[w as usize];
        let feeder = tokio::spawn(async move {
            for seq in 1..=n {
                tx.send(batch(w, seq)).await.expect("send");
            }
        });
        let restored = before.actors.iter().find(|a| a.actor_id == format!("writer-{w}")).map(|a| a.last_sequence).unwrap_or(0);
        for seq in 1..=n {
            let a = acks.message().await.expect("ack").expect("ack");
            assert_eq!((a.sequence, a.duplicate), (seq, seq <= restored));
        }
        feeder.await.expect("feeder");
    }
    let after = info(&mut client).await;
    assert_eq!(after.size, sent.iter().sum::<u64>() * ROWS as u64, "every batch exactly once");

    // And the rows are the ones sent: sample the table and check identities.
    let mut s = client
        .sample(SampleRequest {
            protocol_version: ProtocolVersion::V1 as i32,
            table: after.table.clone(),
            batch_size: 1000,
            prefetch: 2,
            timeout_ms: 5000,
            max_batches: 5,
            importance_beta: None,
            float_columns_as_bytes: false,
        })
        .await
        .expect("sample")
        .into_inner();
    while let Some(b) = s.message().await.expect("minibatch") {
        for r in 0..b.num_rows as usize {
            let (w, seq, row) = (b.obs[r * OBS] as u64, b.obs[r * OBS + 1] as u64, b.obs[r * OBS + 2] as usize);
            assert!(w < WRITERS && seq >= 1 && seq <= sent[w as usize] && row < ROWS, "garbage row {:?}", &b.obs[r * OBS..(r + 1) * OBS]);
        }
    }
    child.kill().expect("stop");
    child.wait().expect("reaped");
    let _ = std::fs::remove_dir_all(&dir);
}
