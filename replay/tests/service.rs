//! The service binary end to end with both transports: a same-host writer over iceoryx2 and a
//! gRPC client feed one table, and each sees the other's rows.

use std::io::{BufRead, BufReader};
use std::net::SocketAddr;
use std::process::{Command, Stdio};
use std::time::{Duration, Instant};

use mapless_net::shm::{Ack, ShmConfig, ShmWriter};
use mapless_proto::v1::replay_service_client::ReplayServiceClient;
use mapless_proto::v1::{ProtocolVersion, ServerInfoRequest};
use mapless_proto::{Transition, TransitionBatchBuilder};

fn batch(actor: &str, seq: u64, rows: usize) -> mapless_proto::v1::TransitionBatch {
    let mut b = TransitionBatchBuilder::new(3, 2);
    for r in 0..rows {
        let o = [seq as f32, r as f32, 0.0];
        b.push(Transition { obs: &o, action: &[0.0, 0.0], reward: 0.0, next_obs: &o, terminal: false, truncated: false, episode_id: 1, step: r as u32, policy_version: 0 }).expect("valid");
    }
    b.finish(actor, seq)
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn shared_memory_and_grpc_writers_feed_one_table_in_the_service_process() {
    let id = std::process::id();
    let dir = std::env::temp_dir().join(format!("mapless-replay-service-{id}"));
    std::fs::create_dir_all(&dir).expect("temp dir");
    // A private iceoryx2 domain and prefix so parallel runs do not meet.
    let config = dir.join("replay.yaml");
    std::fs::write(
        &config,
        format!("table:\n  name: svc\n  capacity: 10000\n  obs_dim: 3\n  act_dim: 2\n  rate_limiter: {{min_size_to_sample: 1}}\nshm:\n  prefix: mapless/test/svc{id}\n  domain: svc{id}_\n"),
    )
    .expect("config");
    let mut child = Command::new(env!("CARGO_BIN_EXE_mapless-replay"))
        .args(["--config", config.to_str().expect("utf-8"), "--listen", "127.0.0.1:0", "--no-metrics"])
        .env("RUST_LOG", "warn")
        .stdout(Stdio::piped())
        .spawn()
        .expect("start mapless-replay");
    let mut out = BufReader::new(child.stdout.take().expect("stdout"));
    let (mut addr, mut shm_service): (Option<SocketAddr>, Option<String>) = (None, None);
    let mut line = String::new();
    while addr.is_none() || shm_service.is_none() {
        line.clear();
        assert!(out.read_line(&mut line).expect("stdout") > 0, "service exited early");
        if let Some(a) = line.trim().strip_prefix("listening on ") {
            addr = Some(a.parse().expect("address"));
        }
        if let Some(s) = line.trim().strip_prefix("shm ingest on ") {
            shm_service = Some(s.to_string());
        }
    }
    assert_eq!(shm_service.as_deref(), Some(format!("mapless/test/svc{id}/insert").as_str()));

    // 5 batches over shared memory…
    let shm_cfg = ShmConfig { prefix: format!("mapless/test/svc{id}"), domain: format!("svc{id}_"), ..ShmConfig::for_table("svc") };
    let writer = tokio::task::spawn_blocking(move || {
        let mut w = ShmWriter::connect(&shm_cfg, "shm-actor").expect("connect over shared memory");
        for seq in 1..=5 {
            w.send(&batch("shm-actor", seq, 10)).expect("send");
        }
        let mut stored = 0;
        let deadline = Instant::now() + Duration::from_secs(20);
        while stored < 5 {
            for a in w.wait_acks(deadline).expect("acks") {
                assert!(matches!(a, Ack::Stored(ref ack) if !ack.duplicate), "{a:?}");
                stored += 1;
            }
        }
    });
    tokio::time::timeout(Duration::from_secs(30), writer).await.expect("shm writer finishes").expect("shm writer");

    // …and 2 over gRPC, into the same table.
    let mut client = ReplayServiceClient::connect(format!("http://{}", addr.expect("address"))).await.expect("connect");
    let acks = client.insert(tokio_stream::iter(vec![batch("grpc-actor", 1, 10), batch("grpc-actor", 2, 10)])).await.expect("insert").into_inner();
    let acks: Vec<_> = tokio_stream::StreamExt::collect::<Vec<_>>(acks).await;
    assert_eq!(acks.len(), 2);
    let info = client.server_info(ServerInfoRequest { protocol_version: ProtocolVersion::V1 as i32 }).await.expect("info").into_inner();
    assert_eq!(info.size, 70);
    let ids: Vec<&str> = info.actors.iter().map(|a| a.actor_id.as_str()).collect();
    assert_eq!(ids, ["grpc-actor", "shm-actor"]);

    // SIGTERM: clean exit, shared memory released.
    assert!(Command::new("kill").args(["-TERM", &child.id().to_string()]).status().expect("kill").success());
    assert!(child.wait().expect("exit").success());
    let _ = std::fs::remove_dir_all(&dir);
    // iceoryx2 keeps one 16-byte management file per domain; ours is private, remove it.
    mapless_net::shm::remove_private_domain_files(&format!("svc{id}_"));
}
