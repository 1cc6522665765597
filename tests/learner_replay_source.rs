//! Replay sources against the real replay service, started in-process on loopback (port 0):
//! minibatches through the prefetching gRPC source, priorities back through it, surviving a
//! server restart, clear stops on errors retrying cannot fix, TLS + bearer token, and the
//! in-process source giving the same shapes.

mod common;
use common::in_process::InProcess;

use std::net::SocketAddr;
use std::sync::Arc;
use std::time::{Duration, Instant};

use mapless_learner::LearnerError;
use mapless_learner::source::{GrpcEndpoint, GrpcSource, ReplaySource, SampleConfig, sample_stream_window};
use mapless_net::{Security, TlsPem};
use mapless_proto::v1::{SampledBatch, TransitionBatch};
use mapless_proto::{Transition, TransitionBatchBuilder};
use mapless_replay::server::{ServeOptions, ServerError, serve};
use mapless_replay::{RateLimiterConfig, SamplerConfig, Table, TableConfig};
use prost::Message;
use tokio::net::TcpListener;
use tokio::runtime::Runtime;
use tokio::sync::oneshot;
use tokio::task::JoinHandle;

const OBS: usize = 3;
const ACT: usize = 2;
const BATCH: u32 = 8;
/// Upper bound on anything a test waits for, so a bug fails instead of hanging.
const PATIENCE: Duration = Duration::from_secs(15);

fn table_cfg(sampler: SamplerConfig) -> TableConfig {
    TableConfig {
        capacity: 1000,
        obs_dim: OBS,
        act_dim: ACT,
        sampler,
        rate_limiter: RateLimiterConfig { min_size_to_sample: 1, samples_per_insert: None, error_buffer: 0.0 },
        max_batch_rows: 100,
        max_sample_rows: 100,
        ..TableConfig::default()
    }
}

fn prioritized() -> SamplerConfig {
    SamplerConfig::Prioritized { alpha: 1.0, beta: 0.4, epsilon: 0.0 }
}

/// Row with reward `v`: every other column derived from it, so a sampled row can be checked.
fn row_of(v: f32) -> ([f32; OBS], [f32; ACT], [f32; OBS]) {
    ([v, v + 0.25, -v], [v / 1000.0, -v / 1000.0], [v + 1.0, v + 1.25, -v - 1.0])
}

/// `rows` transitions with rewards `first..first + rows`.
fn batch(actor: &str, seq: u64, first: f32, rows: usize) -> TransitionBatch {
    let mut b = TransitionBatchBuilder::new(OBS, ACT);
    for i in 0..rows {
        let v = first + i as f32;
        let (obs, action, next_obs) = row_of(v);
        b.push(Transition { obs: &obs, action: &action, reward: v, next_obs: &next_obs, terminal: i % 5 == 4, truncated: false, episode_id: first as u64, step: i as u32, policy_version: 1 })
            .expect("valid row");
    }
    b.finish(actor, seq)
}

fn filled_table(sampler: SamplerConfig, rows: usize) -> Arc<Table> {
    let table = Arc::new(Table::new(table_cfg(sampler), 7).expect("valid table config"));
    table.insert(&batch("actor-a", 1, 0.0, rows), None).expect("insert");
    table
}

/// Checks a minibatch's shape and that every row is one that was inserted.
fn check_batch(b: &SampledBatch) {
    assert_eq!(b.validate(OBS, ACT, BATCH as usize), Ok(BATCH as usize));
    assert_eq!((b.obs_dim as usize, b.act_dim as usize, b.num_rows), (OBS, ACT, BATCH));
    let obs = b.obs_values();
    let action = b.action_values();
    let reward = b.reward_values();
    let next_obs = b.next_obs_values();
    assert_eq!((obs.len(), action.len(), reward.len(), next_obs.len()), (BATCH as usize * OBS, BATCH as usize * ACT, BATCH as usize, BATCH as usize * OBS));
    assert_eq!((b.keys.len(), b.importance_weights.len(), b.probabilities.len()), (BATCH as usize, BATCH as usize, BATCH as usize));
    for i in 0..BATCH as usize {
        let (o, a, n) = row_of(reward[i]);
        assert_eq!(&obs[i * OBS..(i + 1) * OBS], &o, "row {i} obs belongs to its reward");
        assert_eq!(&action[i * ACT..(i + 1) * ACT], &a, "row {i} action");
        assert_eq!(&next_obs[i * OBS..(i + 1) * OBS], &n, "row {i} next_obs");
    }
}

/// Every key stored in the table (stratified draws over equal priorities reach every row).
fn all_keys(table: &Table) -> Vec<u64> {
    let mut keys: Vec<u64> = (0..5).flat_map(|_| table.sample(100, Some(0.0), None).expect("sample").keys).collect();
    keys.sort_unstable();
    keys.dedup();
    assert_eq!(keys.len() as u64, table.size(), "every stored row reached");
    keys
}

/// A replay server on its own runtime, restartable on the same port.
struct Replay {
    rt: Runtime,
    addr: SocketAddr,
    table: Arc<Table>,
    options: ServeOptions,
    stop: Option<oneshot::Sender<()>>,
    server: Option<JoinHandle<Result<(), ServerError>>>,
}

impl Replay {
    fn start(table: Arc<Table>, options: ServeOptions) -> Replay {
        let rt = tokio::runtime::Builder::new_multi_thread().worker_threads(2).enable_all().build().expect("runtime");
        let listener = rt.block_on(TcpListener::bind("127.0.0.1:0")).expect("bind loopback");
        let addr = listener.local_addr().expect("address");
        let mut replay = Replay { rt, addr, table, options, stop: None, server: None };
        replay.serve_on(listener);
        replay
    }

    fn serve_on(&mut self, listener: TcpListener) {
        let (stop, stopped) = oneshot::channel::<()>();
        let serving = serve(listener, Arc::clone(&self.table), self.options.clone(), async {
            let _ = stopped.await;
        });
        self.server = Some(self.rt.spawn(serving));
        self.stop = Some(stop);
    }

    fn endpoint(&self) -> GrpcEndpoint {
        GrpcEndpoint::new(format!("http://{}", self.addr))
    }

    /// Stops the server (open streams end UNAVAILABLE) and waits until it has returned.
    fn stop(&mut self) {
        if let Some(stop) = self.stop.take() {
            let _ = stop.send(());
        }
        if let Some(server) = self.server.take() {
            let result = self.rt.block_on(async { tokio::time::timeout(PATIENCE, server).await });
            result.expect("server stops in time").expect("no panic").expect("clean exit");
        }
    }

    /// Serves the same table on the same port again.
    fn restart(&mut self) {
        let deadline = Instant::now() + PATIENCE;
        let listener = loop {
            match self.rt.block_on(TcpListener::bind(self.addr)) {
                Ok(l) => break l,
                Err(e) if Instant::now() < deadline => {
                    eprintln!("rebinding {}: {e}; retrying", self.addr);
                    std::thread::sleep(Duration::from_millis(50));
                }
                Err(e) => panic!("cannot rebind {}: {e}", self.addr),
            }
        };
        self.serve_on(listener);
    }
}

impl Drop for Replay {
    fn drop(&mut self) {
        if let Some(stop) = self.stop.take() {
            let _ = stop.send(());
        }
    }
}

fn config(endpoint: GrpcEndpoint) -> SampleConfig {
    SampleConfig { backoff_initial: Duration::from_millis(20), backoff_max: Duration::from_millis(200), expected_dims: Some((OBS, ACT)), ..SampleConfig::new(endpoint, BATCH) }
}

fn next(source: &mut GrpcSource) -> SampledBatch {
    source.next_batch_timeout(PATIENCE).expect("source healthy").expect("a minibatch within the patience")
}

/// Polls `done` until it holds, failing after PATIENCE.
fn eventually(what: &str, mut done: impl FnMut() -> bool) {
    let deadline = Instant::now() + PATIENCE;
    while !done() {
        assert!(Instant::now() < deadline, "{what}: not within {PATIENCE:?}");
        std::thread::sleep(Duration::from_millis(10));
    }
}

#[test]
fn grpc_source_delivers_minibatches_of_the_configured_shape() {
    let replay = Replay::start(filled_table(SamplerConfig::Uniform, 50), ServeOptions::default());
    let mut source = GrpcSource::start(config(replay.endpoint())).expect("start");
    for _ in 0..20 {
        check_batch(&source.next_batch().expect("minibatch"));
    }
    let stats = source.stats();
    assert_eq!(stats.batches, 20);
    assert_eq!((stats.reconnects, stats.invalid_batches), (0, 0));
    // A uniform table has no priorities: updates are accepted and ignored.
    source.update_priorities(&[1, 2], &[0.5, 1.0]).expect("ignored on a uniform table");
}

#[test]
fn priorities_sent_through_the_grpc_source_reach_the_table() {
    let table = filled_table(prioritized(), 50);
    let replay = Replay::start(Arc::clone(&table), ServeOptions::default());
    let cfg = config(replay.endpoint());
    let mut source = GrpcSource::start(cfg.clone()).expect("start");
    let first = next(&mut source);
    check_batch(&first);
    let favourite = first.keys[0];
    // Let the server push all it may: what it drew before the update is what flow control let
    // it get ahead of this reader.
    std::thread::sleep(Duration::from_millis(500));
    let keys = all_keys(&table);
    let priorities: Vec<f32> = keys.iter().map(|&k| if k == favourite { 1.0e6 } else { 1.0e-6 }).collect();
    source.update_priorities(&keys, &priorities).expect("queued");
    eventually("priority update acknowledged", || source.stats().priority_updates >= 1);

    // Every key is now ~1e12 times less likely than the favourite.
    let sampled = table.sample(50, Some(0.0), None).expect("sample");
    assert!(sampled.keys.iter().all(|&k| k == favourite), "only the favourite is drawn: {:?}", sampled.keys);
    // Minibatches drawn after the update, through the source, show it too, after at most what
    // was in flight. In bytes: the stream's HTTP/2 window (sized to the prefetch), two chunks
    // of up to 32 KiB (tonic's yield threshold, overshot by at most one message) that hyper may
    // hold past it (one handed to h2, one waiting for capacity) and one 16 KiB frame tonic's
    // decoder may hold. In minibatches: `prefetch` drawn and waiting at the server, one being
    // drawn, `queue_depth` decoded here and one the sample task holds. With the transport's
    // default 2 MiB window this was thousands of minibatches.
    let len = first.encoded_len();
    let window = sample_stream_window(&cfg, OBS, ACT) as usize;
    let bytes = window + 2 * (32 * 1024 + len) + 16 * 1024;
    let in_flight = bytes.div_ceil(len) + cfg.server_prefetch as usize + 1 + cfg.queue_depth + 1;
    let mut stale = 0;
    while !next(&mut source).keys.iter().all(|&k| k == favourite) {
        stale += 1;
        assert!(stale <= in_flight, "more than {in_flight} minibatches drawn before the update arrived after it");
    }
    eprintln!("{stale} minibatches drawn before the update (bound {in_flight})");
    assert_eq!(source.stats().priority_update_errors, 0);
}

#[test]
fn bad_priorities_are_refused_by_both_sources_without_panicking() {
    let table = filled_table(prioritized(), 20);
    let replay = Replay::start(Arc::clone(&table), ServeOptions::default());
    let mut grpc = GrpcSource::start(config(replay.endpoint())).expect("start");
    let mut local = InProcess::new(Arc::clone(&table), BATCH as usize).expect("in process");
    let sources: [&mut dyn ReplaySource; 2] = [&mut grpc, &mut local];
    for source in sources {
        for (keys, priorities) in [(&[1u64, 2][..], &[1.0f32][..]), (&[1], &[f32::NAN]), (&[1], &[-1.0]), (&[1], &[f32::INFINITY])] {
            match source.update_priorities(keys, priorities) {
                Err(LearnerError::InvalidPriorities { reason }) => assert!(!reason.is_empty()),
                other => panic!("expected InvalidPriorities for {keys:?} / {priorities:?}, got {other:?}"),
            }
        }
        source.update_priorities(&[], &[]).expect("an empty update is fine");
    }
}

#[test]
fn grpc_source_survives_a_server_restart() {
    let table = filled_table(prioritized(), 50);
    let mut replay = Replay::start(Arc::clone(&table), ServeOptions::default());
    let mut source = GrpcSource::start(config(replay.endpoint())).expect("start");
    for _ in 0..3 {
        check_batch(&next(&mut source));
    }

    replay.stop();
    // The update loop keeps calling while the service is down: nothing panics or fails.
    source.update_priorities(&[0], &[2.0]).expect("queued while down");
    // The queue holds minibatches drawn before the stop; consuming them lets the source see
    // the broken stream.
    eventually("the broken stream is noticed", || {
        let _ = source.next_batch_timeout(Duration::from_millis(20)).expect("retrying, not stopped");
        source.stats().stream_errors >= 1
    });

    replay.restart();
    eventually("the source reconnects and keeps delivering", || {
        check_batch(&next(&mut source));
        source.stats().reconnects >= 1
    });
    for _ in 0..5 {
        check_batch(&next(&mut source));
    }
    let stats = source.stats();
    assert!(stats.reconnects >= 1 && stats.stream_errors >= 1, "{stats:?}");
    assert!(stats.last_error.is_some());
}

#[test]
fn grpc_source_waits_for_a_service_that_is_not_up_yet_and_for_warm_up() {
    // Reserve a port, then free it: the source starts against nothing.
    let addr = std::net::TcpListener::bind("127.0.0.1:0").expect("bind").local_addr().expect("addr");
    let mut source = GrpcSource::start(config(GrpcEndpoint::new(format!("http://{addr}")))).expect("starts without a server");
    assert!(source.next_batch_timeout(Duration::from_millis(300)).expect("still retrying").is_none());

    // An empty table: the rate limiter holds sampling back until rows arrive.
    let table = Arc::new(Table::new(table_cfg(SamplerConfig::Uniform), 7).expect("table"));
    let mut replay = Replay::start(Arc::clone(&table), ServeOptions::default());
    replay.stop();
    replay.addr = addr;
    replay.restart();
    assert!(source.next_batch_timeout(Duration::from_millis(300)).expect("waiting, not failing").is_none());
    table.insert(&batch("actor-a", 1, 0.0, 20), None).expect("insert");
    check_batch(&next(&mut source));
}

#[test]
fn errors_retrying_cannot_fix_stop_the_source_with_a_clear_message() {
    let options = ServeOptions { security: Security { tls: None, token: Some("open-sesame".into()), ..Security::default() }, ..ServeOptions::default() };
    let replay = Replay::start(filled_table(SamplerConfig::Uniform, 20), options);
    let stopped = |config: SampleConfig, needle: &str| {
        let mut source = GrpcSource::start(config).expect("start");
        match source.next_batch_timeout(PATIENCE) {
            Err(e @ LearnerError::ReplaySourceStopped { .. }) => {
                assert!(e.to_string().contains(needle), "`{needle}` in {e}")
            }
            other => panic!("expected the source to stop with `{needle}`, got {other:?}"),
        }
        // And it stays stopped.
        assert!(matches!(source.next_batch(), Err(LearnerError::ReplaySourceStopped { .. })));
    };
    stopped(config(replay.endpoint()), "Unauthenticated");
    stopped(config(replay.endpoint().with_token("wrong")), "wrong bearer token");
    let token = || replay.endpoint().with_token("open-sesame");
    stopped(SampleConfig { table: "elsewhere".into(), ..config(token()) }, "elsewhere");
    stopped(SampleConfig { expected_dims: Some((17, 2)), ..config(token()) }, "obs_dim 17");
    stopped(SampleConfig { batch_size: 1000, ..config(token()) }, "batch_size");

    // Configs that can never work are refused up front.
    for bad in [
        SampleConfig { batch_size: 0, ..config(token()) },
        SampleConfig { queue_depth: 0, ..config(token()) },
        SampleConfig { importance_beta: Some(1.5), ..config(token()) },
        config(GrpcEndpoint::new("http://[not a uri")),
        config(GrpcEndpoint::new("https://127.0.0.1:1")),
        config(replay.endpoint().with_token("new\nline")),
    ] {
        assert!(matches!(GrpcSource::start(bad), Err(LearnerError::ReplaySourceConfig { .. })));
    }
}

#[test]
fn grpc_source_speaks_tls_with_a_bearer_token() {
    let cert = rcgen::generate_simple_self_signed(vec!["localhost".to_owned()]).expect("self-signed certificate");
    let (cert_pem, key_pem) = (cert.cert.pem(), cert.signing_key.serialize_pem());
    let security = Security { tls: Some(TlsPem { cert: cert_pem.clone().into_bytes(), key: key_pem.into_bytes() }), token: Some("tok".into()), ..Security::default() };
    let replay = Replay::start(filled_table(SamplerConfig::Uniform, 20), ServeOptions { security, ..ServeOptions::default() });
    let endpoint = replay.endpoint().with_tls(cert_pem.into_bytes(), Some("localhost".into())).with_token("tok");
    assert!(endpoint.uri().starts_with("https://"));
    assert!(!format!("{endpoint:?}").contains("tok\""), "Debug never prints the token");
    let mut source = GrpcSource::start(config(endpoint)).expect("start");
    check_batch(&next(&mut source));
}

#[test]
fn in_process_source_returns_the_same_shapes_as_the_grpc_source() {
    let table = filled_table(prioritized(), 50);
    let replay = Replay::start(Arc::clone(&table), ServeOptions::default());
    let mut grpc = GrpcSource::start(config(replay.endpoint())).expect("start");
    let mut local = InProcess::new(Arc::clone(&table), BATCH as usize).expect("in process");
    let remote = next(&mut grpc);
    let here = local.next_batch().expect("minibatch");
    check_batch(&remote);
    check_batch(&here);
    let shape = |b: &SampledBatch| {
        (
            b.obs_dim,
            b.act_dim,
            b.num_rows,
            b.table.clone(),
            b.keys.len(),
            b.obs_values().len(),
            b.action_values().len(),
            b.reward_values().len(),
            b.next_obs_values().len(),
            b.terminal.len(),
            b.truncated.len(),
        )
    };
    assert_eq!(shape(&remote), shape(&here));

    // In process, priorities apply at once.
    let favourite = here.keys[0];
    let keys = all_keys(&table);
    let priorities: Vec<f32> = keys.iter().map(|&k| if k == favourite { 1.0e6 } else { 1.0e-6 }).collect();
    local.update_priorities(&keys, &priorities).expect("update");
    assert!(local.next_batch().expect("minibatch").keys.iter().all(|&k| k == favourite));
    assert_eq!(local.stats().batches, 2);
    assert_eq!(local.stats().priority_updates, 1);

    assert!(matches!(InProcess::new(Arc::clone(&table), 0), Err(LearnerError::ReplaySourceConfig { .. })));
    assert!(matches!(InProcess::new(Arc::clone(&table), 101), Err(LearnerError::ReplaySourceConfig { .. })));
    assert!(InProcess::new(Arc::clone(&table), 8).expect("ok").with_importance_beta(f64::NAN).is_err());

    // A closed table is an error, not a hang or a panic.
    table.close();
    assert!(matches!(local.next_batch(), Err(LearnerError::Replay(_))));
}
