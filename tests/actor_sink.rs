//! Delivery to the replay over gRPC: every batch arrives exactly once, in order, even when
//! the replay service goes away mid-stream and comes back on the same address, or holds
//! inserts back as the actor is told to stop.

use std::sync::Arc;
use std::sync::atomic::{AtomicBool, Ordering};
use std::time::{Duration, Instant};

use mapless_actor::sink::{InsertClient, Sink};
use mapless_net::GrpcEndpoint;
use mapless_proto::v1::TransitionBatch;
use mapless_proto::{Transition, TransitionBatchBuilder};
use mapless_replay::{RateLimiterConfig, Table, TableConfig};

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

/// A batch handed to the gRPC client when its stream cannot take it and the actor is told to
/// stop is not lost: the replay's rate limiter holds inserts back, so the replay stops reading
/// the stream, the transport's buffers and then the stream's channel fill, and `send` returns
/// `Stopped` with the batch held; `flush` puts it on the stream once the channel has room and
/// waits for every ack. (Before, such a batch stayed in the window but never reached the
/// stream: the flush ran out its deadline and the actor reported it unacknowledged.)
#[test]
fn a_grpc_batch_the_stream_could_not_take_as_the_actor_stops_is_flushed_not_lost() {
    const ROWS: usize = 10_000;
    let rt = tokio::runtime::Builder::new_multi_thread().worker_threads(1).enable_all().build().unwrap();
    let addr = std::net::TcpListener::bind("127.0.0.1:0").unwrap().local_addr().unwrap();
    // One sampled row per inserted row, with one batch of slack: inserts wait until sampled.
    let t = Arc::new(
        Table::new(
            TableConfig {
                obs_dim: 3,
                act_dim: 2,
                capacity: 1_000_000,
                max_batch_rows: ROWS,
                max_sample_rows: ROWS,
                rate_limiter: RateLimiterConfig { min_size_to_sample: 10, samples_per_insert: Some(1.0), error_buffer: ROWS as f64 },
                ..TableConfig::default()
            },
            1,
        )
        .unwrap(),
    );
    let _server = serve(Arc::clone(&t), addr);
    let mut client = InsertClient::new(rt.handle().clone(), GrpcEndpoint::new(format!("http://{addr}")), 1);
    let stop = AtomicBool::new(false);
    let mut seq = 0;
    // Sends return while the replay stores what they bring; one then waits for an ack that the
    // limiter holds back, until the actor is told to stop.
    std::thread::scope(|s| {
        s.spawn(|| {
            std::thread::sleep(Duration::from_secs(2));
            stop.store(true, Ordering::Relaxed);
        });
        loop {
            seq += 1;
            assert!(seq < 50, "the limiter never held an insert back: {:?}", client.stats());
            if client.send(batch("held", seq, ROWS), &stop).is_err() {
                break;
            }
        }
    });
    // Stopping, the actor hands over what it has left, until one batch finds no room.
    while client.held() == 0 {
        seq += 1;
        assert!(seq <= 80, "the stream never filled: {:?}", client.stats());
        let e = client.send(batch("held", seq, ROWS), &stop).unwrap_err();
        assert!(e.to_string().contains("acknowledge"), "{e}");
    }
    assert!(t.actors()["held"].batches < seq, "all stored before the flush");
    // Sampling lets inserts through again; the flush delivers every batch, in order.
    let sampled = AtomicBool::new(false);
    let flushed = std::thread::scope(|s| {
        s.spawn(|| {
            while !sampled.load(Ordering::Relaxed) {
                let _ = t.sample(ROWS, None, Some(Instant::now() + Duration::from_millis(200)));
            }
        });
        let ok = client.flush(Instant::now() + Duration::from_secs(30));
        sampled.store(true, Ordering::Relaxed);
        ok
    });
    assert!(flushed, "every batch acknowledged: {:?}", client.stats());
    assert_eq!(client.held(), 0);
    let s = client.stats();
    assert_eq!((s.batches, s.rows, s.acked, s.rejected, s.duplicates), (seq, seq * ROWS as u64, seq, 0, 0), "{s:?}");
    let info = t.info();
    let a = info.actors.iter().find(|a| a.actor_id == "held").unwrap();
    assert_eq!((a.rows, a.last_sequence), (seq * ROWS as u64, seq), "{a:?}");
}
