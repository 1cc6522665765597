//! Delivery to the replay over gRPC: every batch arrives exactly once, in order, even when
//! the replay service goes away mid-stream and comes back on the same address.

use std::sync::Arc;
use std::sync::atomic::AtomicBool;
use std::time::{Duration, Instant};

use mapless_actor::sink::{InsertClient, Sink};
use mapless_net::GrpcEndpoint;
use mapless_proto::v1::TransitionBatch;
use mapless_proto::{Transition, TransitionBatchBuilder};
use mapless_replay::{Table, TableConfig};

fn batch(actor: &str, sequence: u64, rows: usize) -> TransitionBatch {
    let mut b = TransitionBatchBuilder::new(3, 2);
    for i in 0..rows {
        let v = (sequence * 1000 + i as u64) as f32;
        b.push(Transition {
            obs: &[v, 0.0, 1.0],
            action: &[0.1, -0.1],
            reward: v,
            next_obs: &[v + 1.0, 0.0, 1.0],
            terminal: false,
            truncated: false,
            episode_id: 1,
            step: i as u32,
            policy_version: sequence,
        })
        .unwrap();
    }
    b.finish(actor, sequence)
}

fn table() -> Arc<Table> {
    let cfg = TableConfig { obs_dim: 3, act_dim: 2, capacity: 100_000, ..TableConfig::default() };
    Arc::new(Table::new(cfg, 1).unwrap())
}

/// Serves `table` on `addr` on a runtime of its own; dropping the runtime is the replay
/// process dying: every connection is cut at once.
fn serve(table: Arc<Table>, addr: std::net::SocketAddr) -> tokio::runtime::Runtime {
    let rt = tokio::runtime::Builder::new_multi_thread().worker_threads(1).enable_all().build().unwrap();
    let listener = rt.block_on(async {
        // The dead server's port may take a moment to be free again.
        let end = Instant::now() + Duration::from_secs(10);
        loop {
            match tokio::net::TcpListener::bind(addr).await {
                Ok(l) => break l,
                Err(e) if Instant::now() < end => {
                    let _ = e;
                    tokio::time::sleep(Duration::from_millis(50)).await;
                }
                Err(e) => panic!("bind {addr}: {e}"),
            }
        }
    });
    rt.spawn(async move {
        let _ = mapless_replay::server::run(listener, table, std::future::pending()).await;
    });
    rt
}

#[test]
fn grpc_sink_delivers_every_batch_exactly_once_across_a_replay_restart() {
    let rt = tokio::runtime::Builder::new_multi_thread().worker_threads(1).enable_all().build().unwrap();
    let addr = std::net::TcpListener::bind("127.0.0.1:0").unwrap().local_addr().unwrap();
    let t = table();
    let server = serve(Arc::clone(&t), addr);
    let stop = AtomicBool::new(false);
    let mut sink = Sink::Grpc(InsertClient::new(rt.handle().clone(), GrpcEndpoint::new(format!("http://{addr}")), 4));

    for seq in 1..=30 {
        sink.send(batch("actor-test", seq, 10), &stop).unwrap();
    }
    // The replay dies with batches in flight, and comes back on the same address.
    server.shutdown_background();
    // Gone: nothing accepts on the address any more (the dropped runtime closed it).
    let end = Instant::now() + Duration::from_secs(10);
    while std::net::TcpStream::connect(addr).is_ok() {
        assert!(Instant::now() < end, "the dead replay still accepts connections");
        std::thread::sleep(Duration::from_millis(20));
    }
    // Batches sent now find the connection dead and the replay away; it comes back 0.5 s later.
    let t2 = Arc::clone(&t);
    let restarter = std::thread::spawn(move || {
        std::thread::sleep(Duration::from_millis(500));
        serve(t2, addr)
    });
    for seq in 31..=60 {
        sink.send(batch("actor-test", seq, 10), &stop).unwrap();
    }
    assert!(sink.flush(Instant::now() + Duration::from_secs(20)), "every batch acknowledged: {:?}", sink.stats());
    let _restarted = restarter.join().unwrap();

    let s = sink.stats();
    assert_eq!((s.batches, s.rows, s.acked, s.rejected), (60, 600, 60, 0), "{s:?}");
    assert!(s.reconnects >= 1, "the sink reconnected: {s:?}");
    // Exactly once: 600 rows, every (sequence, row) present once.
    assert_eq!(t.size(), 600);
    let info = t.info();
    let a = info.actors.iter().find(|a| a.actor_id == "actor-test").unwrap();
    assert_eq!((a.rows, a.last_sequence), (600, 60), "{a:?}");
}
