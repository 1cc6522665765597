//! The replay service over real HTTP/2 on loopback (port 0): message order and exactly-once
//! on Insert, prefetching Sample streams, precise statuses for bad input, one stream per actor,
//! clients that vanish, ServerInfo, /metrics, security, and the binary itself.

use std::future::Future;
use std::io::{BufRead, BufReader, Read as _, Write as _};
use std::net::SocketAddr;
use std::process::{Command, Stdio};
use std::sync::Arc;
use std::time::{Duration, Instant};

use mapless_net::{Security, TlsPem};
use mapless_proto::v1::replay_service_client::ReplayServiceClient;
use mapless_proto::v1::{
    InsertAck, PriorityUpdate, ProtocolVersion, RegisterActorRequest, RegisterActorResponse, SampleRequest, SampledBatch, Selector, ServerInfoRequest, ServerInfoResponse, TransitionBatch,
};
use mapless_proto::{FloatEncoding, MAX_MESSAGE_BYTES, Transition, TransitionBatchBuilder};
use mapless_replay::server::{ServeOptions, ServerError, run, serve};
use mapless_replay::{ActorRegistry, RateLimiterConfig, SamplerConfig, Table, TableConfig, metrics};
use tokio::net::TcpListener;
use tokio::sync::{mpsc, oneshot};
use tokio::task::JoinHandle;
use tokio_stream::wrappers::ReceiverStream;
use tonic::transport::Channel;
use tonic::{Code, Request, Status, Streaming};

const OBS: usize = 3;
const ACT: usize = 2;
const V1: i32 = ProtocolVersion::V1 as i32;
/// Upper bound on anything a test waits for, so a bug fails instead of hanging.
const PATIENCE: Duration = Duration::from_secs(10);

fn table_cfg(capacity: usize) -> TableConfig {
    TableConfig {
        capacity,
        obs_dim: OBS,
        act_dim: ACT,
        rate_limiter: RateLimiterConfig { min_size_to_sample: 1, samples_per_insert: None, error_buffer: 0.0 },
        max_batch_rows: 100,
        max_sample_rows: 100,
        ..TableConfig::default()
    }
}

/// Inserts stall once 20 rows are stored and nothing sampled (diff 20 > max_diff 11); sampling
/// 10 rows lets the next insert through.
fn throttled_cfg() -> TableConfig {
    TableConfig { rate_limiter: RateLimiterConfig { min_size_to_sample: 1, samples_per_insert: Some(1.0), error_buffer: 10.0 }, max_batch_rows: 10, max_sample_rows: 10, ..table_cfg(1000) }
}

/// Row `i` of the test data: every column derived from `value`, so a sampled row can be
/// checked against what was inserted.
fn row_of(value: f32) -> ([f32; OBS], [f32; ACT], [f32; OBS]) {
    ([value, value + 0.25, -value], [value / 1000.0, -value / 1000.0], [value + 1.0, value + 1.25, -value - 1.0])
}

/// `rows` transitions whose reward is `first + i` (episode = first, step = i).
fn batch_v(actor: &str, seq: u64, first: f32, rows: usize, policy_version: u64) -> TransitionBatch {
    let mut b = TransitionBatchBuilder::new(OBS, ACT);
    for i in 0..rows {
        let v = first + i as f32;
        let (obs, action, next_obs) = row_of(v);
        b.push(Transition { obs: &obs, action: &action, reward: v, next_obs: &next_obs, terminal: i % 5 == 4, truncated: false, episode_id: first as u64, step: i as u32, policy_version })
            .expect("valid row");
    }
    b.finish(actor, seq)
}

fn batch(actor: &str, seq: u64, first: f32, rows: usize) -> TransitionBatch {
    batch_v(actor, seq, first, rows, 1)
}

struct Harness {
    addr: SocketAddr,
    table: Arc<Table>,
    stop: Option<oneshot::Sender<()>>,
    server: Option<JoinHandle<Result<(), ServerError>>>,
}

impl Harness {
    async fn start(cfg: TableConfig) -> Harness {
        Harness::start_with(cfg, ServeOptions::default()).await
    }

    async fn start_with(cfg: TableConfig, options: ServeOptions) -> Harness {
        let table = Arc::new(Table::new(cfg, 7).expect("valid table config"));
        let listener = TcpListener::bind("127.0.0.1:0").await.expect("bind loopback");
        let addr = listener.local_addr().expect("bound address");
        let (stop, stopped) = oneshot::channel::<()>();
        let server = tokio::spawn(serve(listener, Arc::clone(&table), options, async {
            let _ = stopped.await;
        }));
        Harness { addr, table, stop: Some(stop), server: Some(server) }
    }

    async fn client(&self) -> ReplayServiceClient<Channel> {
        connect(self.addr).await
    }

    /// Stops the server and checks that it returns cleanly and promptly.
    async fn shutdown(mut self) {
        self.stop.take().expect("running").send(()).expect("server still running");
        let server = self.server.take().expect("running");
        tokio::time::timeout(PATIENCE, server).await.expect("server stops in time").expect("no panic").expect("clean exit");
    }
}

async fn connect(addr: SocketAddr) -> ReplayServiceClient<Channel> {
    ReplayServiceClient::connect(format!("http://{addr}")).await.expect("connect").max_decoding_message_size(MAX_MESSAGE_BYTES).max_encoding_message_size(MAX_MESSAGE_BYTES)
}

async fn within<T>(what: &str, f: impl Future<Output = T>) -> T {
    tokio::time::timeout(PATIENCE, f).await.unwrap_or_else(|_| panic!("{what}: no answer within {PATIENCE:?}"))
}

/// Sends `batches` on one Insert stream, half-closes, and collects the acks and how the stream
/// ended (None = OK).
async fn insert_all(client: &mut ReplayServiceClient<Channel>, batches: Vec<TransitionBatch>) -> (Vec<InsertAck>, Option<Status>) {
    let response = within("insert", client.insert(tokio_stream::iter(batches))).await;
    let mut acks_stream = match response {
        Ok(r) => r.into_inner(),
        Err(status) => return (Vec::new(), Some(status)),
    };
    let mut acks = Vec::new();
    loop {
        match within("ack", acks_stream.message()).await {
            Ok(Some(ack)) => acks.push(ack),
            Ok(None) => return (acks, None),
            Err(status) => return (acks, Some(status)),
        }
    }
}

/// An Insert stream the test feeds by hand.
struct OpenStream {
    tx: mpsc::Sender<TransitionBatch>,
    acks: Streaming<InsertAck>,
}

impl OpenStream {
    async fn open(client: &mut ReplayServiceClient<Channel>) -> OpenStream {
        let (tx, rx) = mpsc::channel(16);
        let acks = within("open insert", client.insert(ReceiverStream::new(rx))).await.expect("stream opens").into_inner();
        OpenStream { tx, acks }
    }

    async fn send(&self, b: TransitionBatch) {
        self.tx.send(b).await.expect("request stream open");
    }

    async fn next(&mut self) -> Result<Option<InsertAck>, Status> {
        within("ack", self.acks.message()).await
    }
}

async fn info(client: &mut ReplayServiceClient<Channel>) -> ServerInfoResponse {
    within("server info", client.server_info(ServerInfoRequest { protocol_version: V1 })).await.expect("server info").into_inner()
}

/// What ServerInfo says about one actor's health: (rejected_batches, last_rejection,
/// policy_version_lag).
fn health(info: &ServerInfoResponse, _table: &Table, actor: &str) -> (u64, String, u64) {
    let a = info.actors.iter().find(|a| a.actor_id == actor).unwrap_or_else(|| panic!("{actor} not listed"));
    (a.rejected_batches, a.last_rejection.clone(), a.policy_version_lag)
}

fn sample_request(batch_size: u32) -> SampleRequest {
    SampleRequest { protocol_version: V1, table: String::new(), batch_size, prefetch: 1, timeout_ms: 5_000, max_batches: 1, importance_beta: None, float_columns_as_bytes: false }
}

async fn sample_all(client: &mut ReplayServiceClient<Channel>, req: impl tonic::IntoRequest<SampleRequest>) -> (Vec<SampledBatch>, Option<Status>) {
    let mut stream = match within("sample", client.sample(req)).await {
        Ok(r) => r.into_inner(),
        Err(status) => return (Vec::new(), Some(status)),
    };
    let mut out = Vec::new();
    loop {
        match within("minibatch", stream.message()).await {
            Ok(Some(b)) => out.push(b),
            Ok(None) => return (out, None),
            Err(status) => return (out, Some(status)),
        }
    }
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn insert_stream_acks_every_batch_once_in_order() {
    let h = Harness::start(table_cfg(1000)).await;
    let mut client = h.client().await;
    let batches: Vec<_> = (1..=6u64).map(|s| batch("actor-a", s, s as f32 * 100.0, s as usize)).collect();
    let (acks, end) = insert_all(&mut client, batches).await;
    assert!(end.is_none(), "stream ends OK after half-close: {end:?}");
    assert_eq!(acks.iter().map(|a| a.sequence).collect::<Vec<_>>(), vec![1, 2, 3, 4, 5, 6], "one ack per batch, in order");
    let mut stored = 0;
    for (i, ack) in acks.iter().enumerate() {
        stored += i as u64 + 1;
        assert_eq!((ack.actor_id.as_str(), ack.accepted_rows, ack.duplicate, ack.table_size), ("actor-a", i as u32 + 1, false, stored));
    }
    assert_eq!(h.table.size(), 21);
    h.shutdown().await;
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn reconnecting_client_resending_its_last_batches_gets_duplicate_acks_and_nothing_twice() {
    let h = Harness::start(table_cfg(1000)).await;
    let mut client = h.client().await;
    let b = |s: u64| batch("actor-r", s, s as f32 * 10.0, 4);
    let (acks, end) = insert_all(&mut client, (1..=4).map(b).collect()).await;
    assert!(end.is_none());
    assert_eq!(acks.len(), 4);
    // The client lost the acks of 3 and 4 (say), reconnects and resends them, oldest first.
    let (acks, end) = insert_all(&mut client, (3..=6).map(b).collect()).await;
    assert!(end.is_none(), "{end:?}");
    let seen: Vec<_> = acks.iter().map(|a| (a.sequence, a.duplicate, a.accepted_rows)).collect();
    assert_eq!(seen, vec![(3, true, 0), (4, true, 0), (5, false, 4), (6, false, 4)]);
    assert_eq!(h.table.size(), 24, "six batches of four rows, each stored once");
    let info = info(&mut client).await;
    let actor = info.actors.iter().find(|a| a.actor_id == "actor-r").expect("actor listed");
    assert_eq!((actor.batches, actor.rows, actor.duplicate_batches, actor.last_sequence), (6, 24, 2, 6));
    h.shutdown().await;
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn sample_stream_with_prefetch_delivers_columnar_minibatches_of_inserted_rows() {
    let h = Harness::start(table_cfg(1000)).await;
    let mut client = h.client().await;
    let (_, end) = insert_all(&mut client, vec![batch("actor-s", 1, 0.0, 50), batch("actor-s", 2, 50.0, 50)]).await;
    assert!(end.is_none());
    let req = SampleRequest { batch_size: 16, prefetch: 4, max_batches: 5, ..sample_request(16) };
    let (batches, end) = sample_all(&mut client, req).await;
    assert!(end.is_none(), "stream ends OK after max_batches: {end:?}");
    assert_eq!(batches.len(), 5, "exactly max_batches minibatches");
    for b in &batches {
        assert_eq!(b.validate(OBS, ACT, 100), Ok(16), "a well-formed columnar minibatch");
        assert_eq!((b.table.as_str(), b.table_size), ("transitions", 100));
        for i in 0..16 {
            let r = b.row(i).expect("row");
            let v = r.reward;
            assert!((0.0..100.0).contains(&v) && v.fract() == 0.0, "reward {v} was inserted");
            let (obs, action, next_obs) = row_of(v);
            assert_eq!((r.obs, r.action, r.next_obs), (&obs[..], &action[..], &next_obs[..]), "row {v} intact");
            let step = v as u32 % 50;
            assert_eq!((r.episode_id, r.step, r.terminal, r.truncated, r.policy_version), ((v as u64 / 50) * 50, step, step % 5 == 4, false, 1));
            assert!((b.probabilities[i] - 0.01).abs() < 1e-12, "uniform: 1 / table_size");
            assert_eq!(b.importance_weights[i], 1.0);
        }
    }
    assert_eq!(h.table.info().samples_total, 80);
    h.shutdown().await;
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn float_columns_as_bytes_are_accepted_on_insert_and_sent_on_request() {
    let h = Harness::start(table_cfg(1000)).await;
    let mut client = h.client().await;
    let mut bytes_batch = batch("actor-b", 1, 0.0, 30);
    bytes_batch.convert_float_columns(FloatEncoding::F32Le);
    // An old-style packed batch and a bytes one on the same stream.
    let (acks, end) = insert_all(&mut client, vec![bytes_batch, batch("actor-b", 2, 30.0, 30)]).await;
    assert!(end.is_none(), "{end:?}");
    assert_eq!(acks.iter().map(|a| a.accepted_rows).collect::<Vec<_>>(), vec![30, 30]);

    for as_bytes in [false, true] {
        let req = SampleRequest { batch_size: 20, max_batches: 3, float_columns_as_bytes: as_bytes, ..sample_request(20) };
        let (batches, end) = sample_all(&mut client, req).await;
        assert!(end.is_none(), "{end:?}");
        assert_eq!(batches.len(), 3);
        for b in batches {
            assert_eq!(b.validate(OBS, ACT, 100), Ok(20));
            let want = if as_bytes { FloatEncoding::F32Le } else { FloatEncoding::Packed };
            for column in [b.obs_column(), b.action_column(), b.reward_column(), b.next_obs_column()] {
                assert_eq!(column.encoding(), want);
            }
            let (obs, action, reward, next_obs) = (b.obs_values(), b.action_values(), b.reward_values(), b.next_obs_values());
            for (i, &v) in reward.iter().enumerate() {
                assert!((0.0..60.0).contains(&v) && v.fract() == 0.0, "reward {v} was inserted");
                let (o, a, n) = row_of(v);
                assert_eq!((&obs[i * OBS..(i + 1) * OBS], &action[i * ACT..(i + 1) * ACT], &next_obs[i * OBS..(i + 1) * OBS]), (&o[..], &a[..], &n[..]));
            }
        }
    }

    // Malformed bytes columns end the stream with INVALID_ARGUMENT naming the field, and are
    // counted against the actor.
    let mut ragged = batch("actor-b", 3, 0.0, 3);
    ragged.convert_float_columns(FloatEncoding::F32Le);
    ragged.obs_f32le = ragged.obs_f32le.slice(..ragged.obs_f32le.len() - 3);
    let mut doubled = batch("actor-b", 3, 0.0, 3);
    doubled.next_obs_f32le = mapless_proto::f32le_bytes(&doubled.next_obs); // and next_obs
    for (bad, field) in [(ragged, "obs_f32le"), (doubled, "next_obs_f32le")] {
        let (acks, end) = insert_all(&mut client, vec![bad]).await;
        assert!(acks.is_empty());
        let status = end.expect("refused");
        assert_eq!(status.code(), Code::InvalidArgument, "{status:?}");
        assert!(status.message().contains(field), "{}", status.message());
    }
    let info = info(&mut client).await;
    assert_eq!(health(&info, &h.table, "actor-b").0, 2);
    assert_eq!(info.size, 60);
    h.shutdown().await;
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn sample_blocked_by_the_rate_limiter_ends_with_deadline_exceeded_after_timeout_ms() {
    let mut cfg = table_cfg(1000);
    cfg.rate_limiter.min_size_to_sample = 100;
    let h = Harness::start(cfg).await;
    let mut client = h.client().await;
    insert_all(&mut client, vec![batch("actor-w", 1, 0.0, 10)]).await;
    let started = Instant::now();
    let (batches, end) = sample_all(&mut client, SampleRequest { timeout_ms: 400, max_batches: 0, ..sample_request(8) }).await;
    let waited = started.elapsed();
    assert!(batches.is_empty());
    let status = end.expect("stream fails");
    assert_eq!(status.code(), Code::DeadlineExceeded, "{status:?}");
    assert!(waited >= Duration::from_millis(400) && waited < Duration::from_secs(5), "waited {waited:?}");
    assert!(status.message().contains("rate limiter"), "{}", status.message());
    h.shutdown().await;
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn rate_limited_insert_fails_with_deadline_exceeded_at_the_grpc_timeout() {
    let h = Harness::start(throttled_cfg()).await;
    let mut client = h.client().await;
    let mut request = Request::new(tokio_stream::iter((1..=3).map(|s| batch("actor-t", s, s as f32 * 10.0, 10)).collect::<Vec<_>>()));
    request.set_timeout(Duration::from_millis(400));
    let started = Instant::now();
    let mut acks = within("insert", client.insert(request)).await.expect("stream opens").into_inner();
    assert_eq!(acks.message().await.expect("ack").expect("ack").sequence, 1);
    assert_eq!(acks.message().await.expect("ack").expect("ack").sequence, 2);
    let status = within("third ack", acks.message()).await.expect_err("third batch is held by the limiter");
    assert_eq!(status.code(), Code::DeadlineExceeded, "{status:?}");
    assert!(started.elapsed() >= Duration::from_millis(350), "{:?}", started.elapsed());
    assert_eq!(h.table.size(), 20, "the timed-out batch was not inserted");
    h.shutdown().await;
}

/// A client that speaks raw bytes on the Insert method, to send what no prost client would.
mod raw {
    use mapless_proto::v1::InsertAck;
    use prost::Message as _;
    use prost::bytes::BufMut as _;
    use tonic::Status;
    use tonic::codec::{Codec, DecodeBuf, Decoder, EncodeBuf, Encoder};

    pub struct RawCodec;
    pub struct RawEncoder;
    pub struct AckDecoder;

    impl Encoder for RawEncoder {
        type Item = Vec<u8>;
        type Error = Status;
        fn encode(&mut self, item: Vec<u8>, dst: &mut EncodeBuf<'_>) -> Result<(), Status> {
            dst.put_slice(&item);
            Ok(())
        }
    }

    impl Decoder for AckDecoder {
        type Item = InsertAck;
        type Error = Status;
        fn decode(&mut self, src: &mut DecodeBuf<'_>) -> Result<Option<InsertAck>, Status> {
            InsertAck::decode(src).map(Some).map_err(|e| Status::internal(e.to_string()))
        }
    }

    impl Codec for RawCodec {
        type Encode = Vec<u8>;
        type Decode = InsertAck;
        type Encoder = RawEncoder;
        type Decoder = AckDecoder;
        fn encoder(&mut self) -> RawEncoder {
            RawEncoder
        }
        fn decoder(&mut self) -> AckDecoder {
            AckDecoder
        }
    }
}

async fn insert_raw(addr: SocketAddr, messages: Vec<Vec<u8>>) -> Status {
    let channel = Channel::from_shared(format!("http://{addr}")).expect("uri").connect().await.expect("connect");
    let mut grpc = tonic::client::Grpc::new(channel);
    grpc.ready().await.expect("ready");
    let path = tonic::codegen::http::uri::PathAndQuery::from_static("/mapless.v1.ReplayService/Insert");
    let response = within("raw insert", grpc.streaming(Request::new(tokio_stream::iter(messages)), path, raw::RawCodec)).await;
    match response {
        Err(status) => status,
        Ok(r) => {
            let mut acks = r.into_inner();
            match within("raw ack", acks.message()).await {
                Ok(Some(ack)) => panic!("malformed input was acked: {ack:?}"),
                Ok(None) => panic!("malformed input ended the stream with OK"),
                Err(status) => status,
            }
        }
    }
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn each_bad_input_gets_its_precise_status_and_leaves_the_table_untouched() {
    let h = Harness::start(table_cfg(1000)).await;
    let mut client = h.client().await;
    insert_all(&mut client, vec![batch("bad", 1, 0.0, 5)]).await;
    let before = h.table.info();

    let mut wrong_dims = batch("bad", 2, 0.0, 3);
    wrong_dims.obs_dim = 4;
    let mut nan = batch("bad", 2, 0.0, 3);
    nan.reward[1] = f32::NAN;
    let mut future_version = batch("bad", 2, 0.0, 3);
    future_version.protocol_version = 2;
    let too_many_rows = batch("bad", 2, 0.0, 101);
    let mut both_flags = batch("bad", 2, 0.0, 3);
    both_flags.truncated[1] = true;
    both_flags.terminal[1] = true;
    let cases = [
        ("obs_dim 4", wrong_dims, Code::InvalidArgument, "obs_dim"),
        ("NaN reward", nan, Code::InvalidArgument, "reward"),
        ("protocol_version 2", future_version, Code::FailedPrecondition, "protocol_version"),
        ("101 rows", too_many_rows, Code::ResourceExhausted, "101 rows"),
        ("terminal and truncated", both_flags, Code::InvalidArgument, "terminal"),
    ];
    let n_cases = cases.len() as u64;
    for (what, bad, code, needle) in cases {
        let (acks, end) = insert_all(&mut client, vec![bad, batch("bad", 3, 0.0, 3)]).await;
        assert!(acks.is_empty(), "{what}: nothing acked");
        let status = end.unwrap_or_else(|| panic!("{what}: stream must fail"));
        assert_eq!(status.code(), code, "{what}: {status:?}");
        assert!(status.message().contains(needle), "{what}: {}", status.message());
    }

    // A second actor on the stream of the first.
    let (acks, end) = insert_all(&mut client, vec![batch("bad", 2, 0.0, 3), batch("intruder", 1, 0.0, 3)]).await;
    assert_eq!(acks.len(), 1, "the first actor's batch is acked");
    let status = end.expect("stream fails on the second actor");
    assert_eq!(status.code(), Code::InvalidArgument, "{status:?}");
    let after_good = 3;

    // Larger than MAX_MESSAGE_BYTES: tonic stops at the length prefix. The client must be
    // allowed to send it, so it gets no encoding limit.
    let mut huge = batch("bad", 9, 0.0, 1);
    huge.obs = vec![0.5; MAX_MESSAGE_BYTES / 4 + 1024];
    let mut unlimited = ReplayServiceClient::connect(format!("http://{}", h.addr)).await.expect("connect");
    let (acks, end) = insert_all(&mut unlimited, vec![huge]).await;
    assert!(acks.is_empty());
    let status = end.expect("oversized message refused");
    assert_eq!(status.code(), Code::OutOfRange, "{status:?}");

    // Bytes that are not a TransitionBatch at all.
    let status = insert_raw(h.addr, vec![vec![0xff; 16]]).await;
    assert_eq!(status.code(), Code::InvalidArgument, "{status:?}");
    assert!(status.message().contains("malformed TransitionBatch"), "{}", status.message());

    // The table holds exactly what it held plus the one good batch.
    let after = h.table.info();
    assert_eq!(after.size, before.size + after_good);
    assert_eq!(after.inserts_total, before.inserts_total + after_good);
    let info = info(&mut client).await;
    let (rejected, last, _) = health(&info, &h.table, "bad");
    assert_eq!(rejected, n_cases + 1, "five invalid batches and one foreign batch");
    assert!(last.contains("intruder"), "last rejection names the cause: {last}");
    assert_eq!(info.actors.iter().find(|a| a.actor_id == "bad").map(|a| a.batches), Some(2));
    assert!(info.actors.iter().all(|a| a.actor_id != "intruder"), "the intruder's batch never reached the table");
    let (rejected, last, _) = health(&info, &h.table, "<invalid actor id>");
    assert_eq!(rejected, 2, "oversized and malformed, counted though no actor_id could be read");
    assert!(last.contains("malformed"), "{last}");

    // Bad Sample, UpdatePriorities and ServerInfo requests.
    let bad_samples = [
        (SampleRequest { protocol_version: 0, ..sample_request(4) }, Code::FailedPrecondition),
        (SampleRequest { table: "other".into(), ..sample_request(4) }, Code::NotFound),
        (sample_request(0), Code::InvalidArgument),
        (sample_request(101), Code::InvalidArgument),
        (SampleRequest { importance_beta: Some(1.5), ..sample_request(4) }, Code::InvalidArgument),
    ];
    for (req, code) in bad_samples {
        let (batches, end) = sample_all(&mut client, req.clone()).await;
        assert!(batches.is_empty());
        assert_eq!(end.map(|s| s.code()), Some(code), "{req:?}");
    }
    let status = client.server_info(ServerInfoRequest { protocol_version: 3 }).await.expect_err("unknown version");
    assert_eq!(status.code(), Code::FailedPrecondition);
    let update = PriorityUpdate { protocol_version: V1, table: String::new(), keys: vec![1], priorities: vec![1.0] };
    let status = client.update_priorities(update.clone()).await.expect_err("uniform table has no priorities");
    assert_eq!(status.code(), Code::FailedPrecondition);
    let status = client.update_priorities(PriorityUpdate { table: "nope".into(), ..update }).await.expect_err("unknown table");
    assert_eq!(status.code(), Code::NotFound);
    assert_eq!(h.table.info().samples_total, 0, "no bad request sampled anything");
    h.shutdown().await;
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn second_concurrent_stream_for_the_same_actor_is_aborted() {
    let h = Harness::start(table_cfg(1000)).await;
    let mut client = h.client().await;
    let mut first = OpenStream::open(&mut client).await;
    first.send(batch("actor-x", 1, 0.0, 2)).await;
    assert_eq!(first.next().await.expect("ack").expect("ack").sequence, 1);

    let mut second = OpenStream::open(&mut client).await;
    second.send(batch("actor-x", 2, 10.0, 2)).await;
    let status = second.next().await.expect_err("second stream refused");
    assert_eq!(status.code(), Code::Aborted, "{status:?}");

    // Another actor is unaffected, and the first stream goes on.
    let (acks, end) = insert_all(&mut client, vec![batch("actor-y", 1, 0.0, 2)]).await;
    assert!(end.is_none() && acks.len() == 1);
    first.send(batch("actor-x", 2, 20.0, 2)).await;
    let ack = first.next().await.expect("ack").expect("ack");
    assert_eq!((ack.sequence, ack.duplicate), (2, false));
    assert_eq!(h.table.size(), 6, "the refused batch was not inserted");
    drop(first);
    h.shutdown().await;
}

/// Retries on ABORTED: the server may not yet have noticed that the previous stream died.
async fn reconnect_and_send(client: &mut ReplayServiceClient<Channel>, batches: Vec<TransitionBatch>) -> Vec<InsertAck> {
    let until = Instant::now() + Duration::from_secs(3);
    loop {
        let (acks, end) = insert_all(client, batches.clone()).await;
        match end {
            None => return acks,
            Some(s) if s.code() == Code::Aborted && Instant::now() < until => tokio::time::sleep(Duration::from_millis(50)).await,
            Some(s) => panic!("reconnect failed: {s:?}"),
        }
    }
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn client_dropping_a_blocked_stream_does_not_wedge_the_server_or_its_actor() {
    let h = Harness::start(throttled_cfg()).await;
    let mut client = h.client().await;
    let b = |s: u64| batch("actor-d", s, s as f32 * 10.0, 10);
    let mut doomed = OpenStream::open(&mut client).await;
    for s in 1..=3 {
        doomed.send(b(s)).await;
    }
    assert_eq!(doomed.next().await.expect("ack").expect("ack").sequence, 1);
    assert_eq!(doomed.next().await.expect("ack").expect("ack").sequence, 2);
    // Batch 3 is now held by the rate limiter. The server still answers others meanwhile.
    let started = Instant::now();
    let info_now = info(&mut client).await;
    assert!(started.elapsed() < Duration::from_secs(5), "{:?}", started.elapsed());
    assert_eq!(info_now.size, 20);
    drop(doomed); // the actor process dies mid-stream

    // Give the blocked insert time to notice (it looks every 100 ms; 2 s leaves room for a
    // loaded machine), then open the limiter: a zombie insert would now store batch 3 on its own.
    tokio::time::sleep(Duration::from_secs(2)).await;
    let (batches, end) = sample_all(&mut client, sample_request(10)).await;
    assert!(end.is_none() && batches.len() == 1, "{end:?}");
    tokio::time::sleep(Duration::from_secs(1)).await;
    assert_eq!(h.table.size(), 20, "the abandoned batch was not inserted behind the client's back");

    // The restarted actor gets its stream slot and resends its unacknowledged batch.
    let acks = reconnect_and_send(&mut client, vec![b(3)]).await;
    assert_eq!(acks.iter().map(|a| (a.sequence, a.duplicate)).collect::<Vec<_>>(), vec![(3, false)]);
    assert_eq!(h.table.size(), 30);

    // A Sample stream abandoned while blocked releases its producer too: it draws nothing later.
    let samples_before = h.table.info().samples_total;
    let mut blocked = within("sample", client.sample(SampleRequest { batch_size: 10, timeout_ms: 0, max_batches: 0, ..sample_request(10) })).await.expect("stream opens").into_inner();
    // With 30 rows in and 10 out the limiter allows two more minibatches of 10; drain them,
    // after which the producer is blocked.
    let mut drawn = 0;
    while let Ok(Ok(Some(_))) = tokio::time::timeout(Duration::from_secs(2), blocked.message()).await {
        drawn += 1;
    }
    drop(blocked);
    tokio::time::sleep(Duration::from_millis(1500)).await;
    let settled = h.table.info().samples_total;
    // Inserts now open the limiter again; a zombie producer would draw from it.
    let acks = reconnect_and_send(&mut client, vec![b(4)]).await;
    assert_eq!(acks.len(), 1);
    tokio::time::sleep(Duration::from_millis(1500)).await;
    assert_eq!(h.table.info().samples_total, settled, "no sampling after the client left ({drawn} drawn before, from {samples_before})");
    h.shutdown().await;
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn server_info_reports_table_limiter_and_per_actor_counters() {
    let mut cfg = table_cfg(50);
    cfg.rate_limiter.min_size_to_sample = 10;
    let h = Harness::start(cfg).await;
    let mut client = h.client().await;
    insert_all(&mut client, vec![batch_v("actor-new", 1, 0.0, 30, 7)]).await;
    insert_all(&mut client, vec![batch_v("actor-old", 1, 100.0, 30, 4)]).await;
    let mut bad = batch("actor-old", 2, 0.0, 2);
    bad.action.pop();
    insert_all(&mut client, vec![bad]).await;
    sample_all(&mut client, sample_request(8)).await;

    let info = info(&mut client).await;
    assert_eq!(info.protocol_version, V1);
    assert_eq!(info.table, "transitions");
    assert_eq!(info.selector, Selector::Uniform as i32);
    assert_eq!((info.obs_dim, info.act_dim, info.capacity, info.max_rows_per_batch), (3, 2, 50, 100));
    assert_eq!(info.size, 50, "60 rows into 50 slots: the oldest evicted");
    assert_eq!((info.inserts_total, info.samples_total), (60, 8));
    assert!(info.inserts_per_s > 0.0 && info.samples_per_s > 0.0);
    assert!(info.started_unix_ms > 1_600_000_000_000);
    let rl = info.rate_limiter.expect("rate limiter");
    assert_eq!(rl.min_size_to_sample, 10);
    let names: Vec<_> = info.actors.iter().map(|a| a.actor_id.as_str()).collect();
    assert_eq!(names, vec!["actor-new", "actor-old"], "sorted by actor_id");
    let (new, old) = (&info.actors[0], &info.actors[1]);
    assert_eq!((new.batches, new.rows, new.last_policy_version), (1, 30, 7));
    assert_eq!((old.batches, old.rows, old.last_policy_version), (1, 30, 4));
    assert_eq!(health(&info, &h.table, "actor-new"), (0, String::new(), 0), "newest policy, nothing rejected");
    let (rejected, last, lag) = health(&info, &h.table, "actor-old");
    assert_eq!((rejected, lag), (1, 3), "one bad batch; policy 4 against the newest 7");
    assert!(last.contains("action"), "{last}");
    assert!(old.last_insert_unix_ms >= new.last_insert_unix_ms && new.last_insert_unix_ms > 0);
    h.shutdown().await;
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn update_priorities_sets_known_keys_and_counts_evicted_ones() {
    let cfg = TableConfig { sampler: SamplerConfig::Prioritized { alpha: 1.0, beta: 0.4, epsilon: 0.0 }, ..table_cfg(20) };
    let h = Harness::start(cfg).await;
    let mut client = h.client().await;
    insert_all(&mut client, vec![batch("actor-p", 1, 0.0, 20)]).await;
    let (batches, _) = sample_all(&mut client, sample_request(20)).await;
    let mut keys = batches[0].keys.clone();
    keys.sort_unstable();
    keys.dedup();
    let known = keys.len() as u32;
    keys.push(1_000_000);
    let priorities = vec![2.0; keys.len()];
    let r = client.update_priorities(PriorityUpdate { protocol_version: V1, table: "transitions".into(), keys, priorities }).await.expect("update").into_inner();
    assert_eq!((r.updated, r.unknown_keys), (known, 1));
    let status = client.update_priorities(PriorityUpdate { protocol_version: V1, table: String::new(), keys: vec![1], priorities: vec![-1.0] }).await.expect_err("negative priority");
    assert_eq!(status.code(), Code::InvalidArgument);
    let (batches, _) = sample_all(&mut client, SampleRequest { importance_beta: Some(1.0), ..sample_request(8) }).await;
    assert!(batches[0].importance_weights.iter().all(|w| *w > 0.0 && *w <= 1.0));
    h.shutdown().await;
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn a_request_without_beta_gets_the_tables_beta_and_one_with_beta_gets_its_own() {
    let cfg = TableConfig { sampler: SamplerConfig::Prioritized { alpha: 1.0, beta: 0.4, epsilon: 0.0 }, ..table_cfg(20) };
    let h = Harness::start(cfg).await;
    let mut client = h.client().await;
    insert_all(&mut client, vec![batch("actor-b", 1, 0.0, 20)]).await;
    let (batches, _) = sample_all(&mut client, sample_request(20)).await;
    // Priorities 1..=20 over the sampled keys, so that rows are drawn unevenly.
    let mut keys = batches[0].keys.clone();
    keys.sort_unstable();
    keys.dedup();
    let priorities: Vec<f64> = (1..=keys.len()).map(|p| p as f64).collect();
    client.update_priorities(PriorityUpdate { protocol_version: V1, table: String::new(), keys, priorities }).await.expect("update");
    // w_i = (N·P(i))^−β / max_j w_j, from the batch's own probabilities.
    let expected = |b: &SampledBatch, beta: f64| -> Vec<f32> {
        let raw: Vec<f64> = b.probabilities.iter().map(|p| (b.table_size as f64 * p).powf(-beta)).collect();
        let max = raw.iter().cloned().fold(0.0, f64::max);
        raw.iter().map(|w| (w / max) as f32).collect()
    };
    for (request, beta) in [(None, 0.4), (Some(0.0), 0.0), (Some(1.0), 1.0)] {
        let (batches, _) = sample_all(&mut client, SampleRequest { importance_beta: request, ..sample_request(20) }).await;
        let b = &batches[0];
        assert!(b.probabilities.iter().any(|p| (p - b.probabilities[0]).abs() > 1e-9), "rows drawn evenly");
        for (got, want) in b.importance_weights.iter().zip(expected(b, beta)) {
            assert!((got - want).abs() < 1e-5, "request {request:?}: weight {got}, expected {want} for β = {beta}");
        }
        assert_eq!(b.importance_weights.iter().all(|w| *w == 1.0), beta == 0.0, "request {request:?}");
    }
    h.shutdown().await;
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn shutdown_ends_open_streams_with_unavailable() {
    let mut cfg = table_cfg(100);
    cfg.rate_limiter.min_size_to_sample = 50;
    let h = Harness::start(cfg).await;
    let mut client = h.client().await;
    let mut idle_insert = OpenStream::open(&mut client).await;
    idle_insert.send(batch("actor-i", 1, 0.0, 1)).await;
    idle_insert.next().await.expect("ack").expect("ack");
    let mut blocked_sample = client.sample(SampleRequest { timeout_ms: 0, max_batches: 0, ..sample_request(4) }).await.expect("opens").into_inner();
    let started = Instant::now();
    let table = Arc::clone(&h.table);
    let stopping = tokio::spawn(h.shutdown());
    let s = idle_insert.next().await.expect_err("insert stream ends");
    assert_eq!(s.code(), Code::Unavailable, "{s:?}");
    let s = within("sample end", blocked_sample.message()).await.expect_err("sample stream ends");
    assert_eq!(s.code(), Code::Unavailable, "{s:?}");
    within("shutdown", stopping).await.expect("clean");
    assert!(started.elapsed() < Duration::from_secs(4), "streams did not hold up shutdown: {:?}", started.elapsed());
    assert_eq!(table.size(), 1);
}

/// More Sample streams than `max_sample_streams` are refused at once with RESOURCE_EXHAUSTED,
/// and counted; the admitted ones wait on the rate limiter without holding a blocking thread.
/// 600 admitted streams all waiting is more than tokio's 512 blocking threads, so with a
/// thread per waiting stream the insert and the priority update below would stall.
#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn a_thousand_sample_streams_are_each_served_or_refused_and_inserts_and_updates_go_on() {
    const STREAMS: usize = 1000;
    const LIMIT: usize = 600;
    // hyper serves at most 200 concurrent streams per connection: spread them over ten.
    const CONNECTIONS: usize = 10;
    let mut cfg = TableConfig { sampler: SamplerConfig::Prioritized { alpha: 1.0, beta: 0.4, epsilon: 0.0 }, ..table_cfg(1000) };
    cfg.rate_limiter.min_size_to_sample = 50;
    let h = Harness::start_with(cfg, ServeOptions { max_sample_streams: LIMIT as u32, ..ServeOptions::default() }).await;
    let mut client = h.client().await;
    let mut connections = Vec::new();
    for _ in 0..CONNECTIONS {
        connections.push(h.client().await);
    }

    // The table is empty, so every admitted stream waits: none can end before all are open.
    let req = SampleRequest { timeout_ms: 0, max_batches: 1, ..sample_request(4) };
    let mut opening = tokio::task::JoinSet::new();
    for i in 0..STREAMS {
        let (mut c, req) = (connections[i % CONNECTIONS].clone(), req.clone());
        opening.spawn(async move { c.sample(req).await.map(|r| r.into_inner()) });
    }
    let (mut open, mut refused) = (Vec::new(), 0);
    within("every Sample call answered", async {
        while let Some(answer) = opening.join_next().await {
            match answer.expect("no panic") {
                Ok(stream) => open.push(stream),
                Err(status) => {
                    assert_eq!(status.code(), Code::ResourceExhausted, "{status:?}");
                    assert!(status.message().contains("600 Sample streams") && status.message().contains("max_sample_streams"), "{}", status.message());
                    refused += 1;
                }
            }
        }
    })
    .await;
    assert_eq!((open.len(), refused), (LIMIT, STREAMS - LIMIT));

    // While those 600 wait: an insert is acknowledged and a priority update applies.
    let (acks, end) = insert_all(&mut client, vec![batch("actor-c", 1, 0.0, 10)]).await;
    assert!(end.is_none() && acks.len() == 1, "{end:?}");
    let update = PriorityUpdate { protocol_version: V1, table: String::new(), keys: vec![0, 1, 2], priorities: vec![3.0; 3] };
    let r = within("priority update", client.update_priorities(update)).await.expect("update").into_inner();
    assert_eq!((r.updated, r.unknown_keys), (3, 0));

    // Filling the table to min_size_to_sample serves each admitted stream its minibatch.
    let (acks, end) = insert_all(&mut client, vec![batch("actor-c", 2, 10.0, 40)]).await;
    assert!(end.is_none() && acks.len() == 1, "{end:?}");
    let mut reading = tokio::task::JoinSet::new();
    for mut stream in open {
        reading.spawn(async move { (stream.message().await, stream.message().await) });
    }
    within("every admitted stream served", async {
        while let Some(read) = reading.join_next().await {
            let (first, end) = read.expect("no panic");
            assert_eq!(first.expect("a minibatch").expect("not the end").num_rows, 4);
            assert!(matches!(end, Ok(None)), "ends OK after max_batches: {end:?}");
        }
    })
    .await;
    assert_eq!(h.table.info().samples_total, (LIMIT * 4) as u64);

    // Refusals are counted, in /metrics too.
    assert_eq!(h.table.sample_streams_refused(), refused as u64);
    let samples = parse_exposition(&metrics::render(&h.table, &ActorRegistry::default(), &Default::default()));
    let counted = samples.iter().find(|(s, _)| s == r#"replay_sample_streams_refused_total{table="transitions"}"#).expect("refusal counter exported");
    assert_eq!(counted.1, refused as f64);

    // The ended streams gave their places back.
    let (batches, end) = sample_all(&mut client, sample_request(4)).await;
    assert!(end.is_none() && batches.len() == 1, "{end:?}");
    assert_eq!(h.table.sample_streams_refused(), refused as u64);
    h.shutdown().await;
}

/// One HTTP/1.0 GET; returns (status line, headers, body).
fn http_get(addr: SocketAddr, path: &str) -> (String, String, String) {
    let mut s = std::net::TcpStream::connect(addr).expect("connect metrics");
    s.set_read_timeout(Some(PATIENCE)).expect("timeout");
    write!(s, "GET {path} HTTP/1.0\r\nHost: {addr}\r\n\r\n").expect("send");
    let mut raw = String::new();
    s.read_to_string(&mut raw).expect("read");
    let (head, body) = raw.split_once("\r\n\r\n").expect("header/body split");
    let (status, headers) = head.split_once("\r\n").unwrap_or((head, ""));
    (status.to_owned(), headers.to_ascii_lowercase(), body.to_owned())
}

/// Checks the text format: each family's HELP and TYPE come once, before its samples, and
/// every sample line is `name{labels} number`. Returns (name with labels, value) pairs.
fn parse_exposition(body: &str) -> Vec<(String, f64)> {
    let mut typed = std::collections::HashMap::new();
    let mut helped = std::collections::HashSet::new();
    let mut samples = Vec::new();
    // OpenMetrics: a counter family `x` has samples `x_total`; the text ends with `# EOF`.
    let family = |name: &str, typed: &std::collections::HashMap<String, String>| match name.strip_suffix("_total") {
        Some(base) if typed.get(base).is_some_and(|k| k == "counter") => base.to_owned(),
        _ => name.to_owned(),
    };
    let mut ended = false;
    for line in body.lines() {
        assert!(!ended, "a line after # EOF: {line}");
        if line == "# EOF" {
            ended = true;
        } else if let Some(rest) = line.strip_prefix("# HELP ") {
            let name = rest.split(' ').next().expect("name");
            assert!(helped.insert(name.to_owned()), "HELP twice for {name}");
        } else if let Some(rest) = line.strip_prefix("# TYPE ") {
            let mut it = rest.split(' ');
            let (name, kind) = (it.next().expect("name"), it.next().expect("type"));
            assert!(matches!(kind, "counter" | "gauge"), "{line}");
            assert!(typed.insert(name.to_owned(), kind.to_owned()).is_none(), "TYPE twice for {name}");
        } else {
            let (series, value) = line.rsplit_once(' ').unwrap_or_else(|| panic!("bad line {line:?}"));
            let name = series.split('{').next().expect("name");
            assert!(name.chars().all(|c| c.is_ascii_alphanumeric() || c == '_'), "{name}");
            let fam = family(name, &typed);
            assert!(typed.contains_key(&fam) && helped.contains(&fam), "{name} sampled before its HELP/TYPE");
            if typed[&fam] == "counter" {
                assert!(name.ends_with("_total"), "counter {name} ends in _total");
            }
            assert!(series.ends_with('}') || !series.contains('{'), "{line}");
            samples.push((series.to_owned(), value.parse::<f64>().unwrap_or_else(|_| panic!("value in {line:?}"))));
        }
    }
    assert!(ended, "no # EOF at the end:\n{body}");
    samples
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn metrics_endpoint_serves_prometheus_text() {
    let h = Harness::start(table_cfg(1000)).await;
    let mut client = h.client().await;
    insert_all(&mut client, vec![batch("actor-m\"1", 1, 0.0, 12), batch("actor-m\"1", 2, 0.0, 3)]).await;
    let mut bad = batch("actor-m\"1", 3, 0.0, 1);
    bad.obs_dim = 9;
    insert_all(&mut client, vec![bad]).await;
    sample_all(&mut client, sample_request(5)).await;

    let listener = TcpListener::bind("127.0.0.1:0").await.expect("bind");
    let addr = listener.local_addr().expect("addr");
    let (stop, stopped) = oneshot::channel::<()>();
    let server = tokio::spawn(metrics::serve(listener, Arc::clone(&h.table), Arc::default(), Default::default(), Default::default(), Default::default(), async {
        let _ = stopped.await;
    }));
    let (status, headers, body) = tokio::task::spawn_blocking(move || http_get(addr, "/metrics")).await.expect("get");
    assert!(status.contains(" 200 "), "{status}");
    assert!(headers.contains("content-type: application/openmetrics-text; version=1.0.0"), "{headers}");
    let samples = parse_exposition(&body);
    let value = |series: &str| samples.iter().find(|(s, _)| s == series).map(|(_, v)| *v).unwrap_or_else(|| panic!("{series} missing:\n{body}"));
    assert_eq!(value(r#"replay_up{table="transitions"}"#), 1.0);
    assert_eq!(value(r#"replay_size{table="transitions"}"#), 15.0);
    assert_eq!(value(r#"replay_capacity{table="transitions"}"#), 1000.0);
    assert_eq!(value(r#"replay_inserts_total{table="transitions"}"#), 15.0);
    assert_eq!(value(r#"replay_samples_total{table="transitions"}"#), 5.0);
    assert!(value(r#"replay_insert_rows_per_s{table="transitions"}"#) > 0.0);
    assert!(value(r#"replay_sample_rows_per_s{table="transitions"}"#) > 0.0);
    assert!(value(r#"replay_rate_limiter_blocked_seconds_total{table="transitions",side="sample"}"#) >= 0.0);
    let actor = r#"table="transitions",actor="actor-m\"1""#;
    assert_eq!(value(&format!("replay_actor_rows_total{{{actor}}}")), 15.0);
    assert_eq!(value(&format!("replay_actor_batches_total{{{actor}}}")), 2.0);
    assert_eq!(value(&format!("replay_actor_duplicate_batches_total{{{actor}}}")), 0.0);
    assert_eq!(value(&format!("replay_actor_rejected_batches_total{{{actor}}}")), 1.0);
    assert_eq!(value(&format!("replay_actor_policy_version_lag{{{actor}}}")), 0.0);
    // Just inserted: its last insert is now, to within the test's run time.
    let now_s = std::time::SystemTime::now().duration_since(std::time::UNIX_EPOCH).unwrap().as_secs_f64();
    let last = value(&format!("replay_actor_last_insert_timestamp_seconds{{{actor}}}"));
    assert!((now_s - 60.0..=now_s + 1.0).contains(&last), "{last} vs now {now_s}");
    let (status, _, _) = tokio::task::spawn_blocking(move || http_get(addr, "/nope")).await.expect("get");
    assert!(status.contains(" 404 "), "{status}");
    stop.send(()).expect("running");
    within("metrics stop", server).await.expect("no panic").expect("clean");
    h.shutdown().await;
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn non_loopback_listener_without_tls_and_token_is_refused() {
    let table = Arc::new(Table::new(table_cfg(10), 1).expect("table"));
    let listener = TcpListener::bind("0.0.0.0:0").await.expect("bind all interfaces");
    let err = run(listener, Arc::clone(&table), std::future::pending()).await.expect_err("refused");
    assert!(matches!(err, ServerError::Insecure { .. }), "{err}");
    assert!(err.to_string().contains("TLS") && err.to_string().contains("token"), "{err}");
    let listener = TcpListener::bind("0.0.0.0:0").await.expect("bind all interfaces");
    let token_only = ServeOptions { security: Security { tls: None, token: Some("t".into()), ..Security::default() }, ..ServeOptions::default() };
    assert!(matches!(serve(listener, table, token_only, std::future::pending()).await, Err(ServerError::Insecure { .. })));
}

async fn register(client: &mut ReplayServiceClient<Channel>, name: &str) -> Result<RegisterActorResponse, Status> {
    within("register", client.register_actor(RegisterActorRequest { protocol_version: V1, name: name.to_owned() })).await.map(tonic::Response::into_inner)
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn register_actor_gives_each_name_its_own_slot_and_refuses_bad_input_with_precise_statuses() {
    let registry = Arc::new(ActorRegistry::in_memory(3));
    let h = Harness::start_with(table_cfg(100), ServeOptions { registry: Arc::clone(&registry), ..ServeOptions::default() }).await;
    let mut client = h.client().await;
    let slot = |r: RegisterActorResponse| (r.slot, r.known, r.registered);
    assert_eq!(slot(register(&mut client, "3f9a1c2b7d4e").await.expect("first name")), (0, false, 1));
    assert_eq!(slot(register(&mut client, "8e7d6c5b4a39").await.expect("second name")), (1, false, 2));
    assert_eq!(slot(register(&mut client, "3f9a1c2b7d4e").await.expect("same name again")), (0, true, 2));

    let refused = |r: Result<RegisterActorResponse, Status>| r.expect_err("refused");
    let empty = refused(register(&mut client, "").await);
    assert!(empty.code() == Code::InvalidArgument && empty.message().contains("is empty"), "{empty:?}");
    let long = refused(register(&mut client, &"h".repeat(129)).await);
    assert!(long.code() == Code::InvalidArgument && long.message().contains("129 bytes"), "{long:?}");
    let control = refused(register(&mut client, "a\nb").await);
    assert_eq!(control.code(), Code::InvalidArgument, "{control:?}");
    let old = refused(within("register", client.register_actor(RegisterActorRequest { protocol_version: 0, name: "x".into() })).await.map(tonic::Response::into_inner));
    assert_eq!(old.code(), Code::FailedPrecondition, "{old:?}");
    assert_eq!(slot(register(&mut client, "third").await.expect("the last slot")), (2, false, 3));
    let full = refused(register(&mut client, "fourth").await);
    assert!(full.code() == Code::ResourceExhausted && full.message().contains("max_actor_slots"), "{full:?}");
    assert_eq!(slot(register(&mut client, "8e7d6c5b4a39").await.expect("known names still answered")), (1, true, 3));

    // Every outcome is counted in /metrics.
    let samples = parse_exposition(&metrics::render(&h.table, &registry, &Default::default()));
    let value = |series: &str| samples.iter().find(|(s, _)| s == series).map(|(_, v)| *v).unwrap_or_else(|| panic!("{series} missing: {samples:?}"));
    assert_eq!(value(r#"replay_actor_slots{table="transitions"}"#), 3.0);
    assert_eq!(value(r#"replay_actor_registrations_total{table="transitions",outcome="new"}"#), 3.0);
    assert_eq!(value(r#"replay_actor_registrations_total{table="transitions",outcome="known"}"#), 2.0);
    assert_eq!(value(r#"replay_actor_registrations_total{table="transitions",outcome="refused"}"#), 5.0);
    h.shutdown().await;
}

fn with_token<T>(msg: T, token: &str) -> Request<T> {
    let mut r = Request::new(msg);
    r.metadata_mut().insert("authorization", format!("Bearer {token}").parse().expect("ascii"));
    r
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn bearer_token_is_checked_on_every_call() {
    let options = ServeOptions { security: Security { tls: None, token: Some("open-sesame".into()), ..Security::default() }, ..ServeOptions::default() };
    let h = Harness::start_with(table_cfg(100), options).await;
    let mut client = h.client().await;
    let ask = ServerInfoRequest { protocol_version: V1 };
    assert_eq!(client.server_info(ask).await.expect_err("no token").code(), Code::Unauthenticated);
    assert_eq!(client.server_info(with_token(ask, "open-sesam")).await.expect_err("wrong token").code(), Code::Unauthenticated);
    let (acks, end) = insert_all(&mut client, vec![batch("actor-z", 1, 0.0, 1)]).await;
    assert!(acks.is_empty());
    assert_eq!(end.map(|s| s.code()), Some(Code::Unauthenticated));
    client.server_info(with_token(ask, "open-sesame")).await.expect("right token");
    let reg = RegisterActorRequest { protocol_version: V1, name: "host-z".into() };
    assert_eq!(client.register_actor(reg.clone()).await.expect_err("no token").code(), Code::Unauthenticated);
    assert_eq!(client.register_actor(with_token(reg.clone(), "open-sesam")).await.expect_err("wrong token").code(), Code::Unauthenticated);
    assert_eq!(client.register_actor(with_token(reg, "open-sesame")).await.expect("right token").into_inner().slot, 0);
    let acks = client.insert(with_token(tokio_stream::iter(vec![batch("actor-z", 1, 0.0, 1)]), "open-sesame")).await;
    let ack = acks.expect("insert").into_inner().message().await.expect("ack").expect("ack");
    assert_eq!(ack.sequence, 1);
    // The single token of configs without roles keeps every right, sampling included.
    let (batches, end) = sample_all(&mut client, with_token(sample_request(1), "open-sesame")).await;
    assert!(end.is_none() && batches.len() == 1, "{end:?}");
    let update = PriorityUpdate { protocol_version: V1, table: String::new(), keys: vec![1], priorities: vec![1.0] };
    let refused = client.update_priorities(with_token(update, "open-sesame")).await.expect_err("uniform table");
    assert_eq!(refused.code(), Code::FailedPrecondition, "past the token check: {refused}");
    h.shutdown().await;
}

/// One batch on an Insert stream carrying `token`: its ack, or how the call or stream ended.
async fn insert_one(client: &mut ReplayServiceClient<Channel>, token: Option<&str>, b: TransitionBatch) -> Result<InsertAck, Status> {
    let stream = tokio_stream::iter(vec![b]);
    let request = match token {
        Some(t) => with_token(stream, t),
        None => Request::new(stream),
    };
    let mut acks = within("insert", client.insert(request)).await?.into_inner();
    within("ack", acks.message()).await?.ok_or_else(|| Status::internal("stream ended without an ack"))
}

/// Tokens with a role each (issue 17): an actor's token inserts and registers but cannot read
/// the table; the learner's samples but cannot write; either asks the health service; no or a
/// wrong token is UNAUTHENTICATED; every refusal is counted in /metrics.
#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn each_role_token_calls_only_its_methods() {
    use mapless_net::RoleTokens;
    let security = Security { role_tokens: RoleTokens { actor: Some("actor-tok".into()), learner: Some("learner-tok".into()) }, ..Security::default() };
    let refusals = security.refusals.clone();
    let registry = Arc::new(ActorRegistry::default());
    let h = Harness::start_with(table_cfg(100), ServeOptions { security, registry: Arc::clone(&registry), ..ServeOptions::default() }).await;
    let mut client = h.client().await;
    let denied = |status: Status, method: &str, role: &str| {
        assert_eq!(status.code(), Code::PermissionDenied, "{status}");
        let m = status.message();
        assert!(m.contains(&format!("/mapless.v1.ReplayService/{method}")) && m.contains(&format!("the {role} role")), "{m}");
    };

    // The actor's token: Insert and RegisterActor.
    let ack = insert_one(&mut client, Some("actor-tok"), batch("actor-r", 1, 0.0, 3)).await.expect("the actor token inserts");
    assert_eq!(ack.sequence, 1);
    let reg = RegisterActorRequest { protocol_version: V1, name: "host-r".into() };
    assert_eq!(client.register_actor(with_token(reg.clone(), "actor-tok")).await.expect("the actor token registers").into_inner().slot, 0);
    // ... but not the learner's methods.
    let (batches, end) = sample_all(&mut client, with_token(sample_request(1), "actor-tok")).await;
    assert!(batches.is_empty());
    denied(end.expect("refused"), "Sample", "learner");
    denied(client.server_info(with_token(ServerInfoRequest { protocol_version: V1 }, "actor-tok")).await.expect_err("refused"), "ServerInfo", "learner");
    let update = PriorityUpdate { protocol_version: V1, table: String::new(), keys: vec![1], priorities: vec![1.0] };
    denied(client.update_priorities(with_token(update.clone(), "actor-tok")).await.expect_err("refused"), "UpdatePriorities", "learner");

    // The learner's token: Sample, ServerInfo, UpdatePriorities.
    let (batches, end) = sample_all(&mut client, with_token(sample_request(2), "learner-tok")).await;
    assert!(end.is_none(), "{end:?}");
    assert_eq!(batches.len(), 1);
    assert_eq!(client.server_info(with_token(ServerInfoRequest { protocol_version: V1 }, "learner-tok")).await.expect("info").into_inner().size, 3);
    let past_auth = client.update_priorities(with_token(update, "learner-tok")).await.expect_err("uniform table");
    assert_eq!(past_auth.code(), Code::FailedPrecondition, "past the token check: {past_auth}");
    // ... but not the actor's.
    denied(insert_one(&mut client, Some("learner-tok"), batch("actor-l", 1, 0.0, 1)).await.expect_err("refused"), "Insert", "actor");
    denied(client.register_actor(with_token(reg, "learner-tok")).await.expect_err("refused"), "RegisterActor", "actor");

    // No token or an unknown one: UNAUTHENTICATED, whatever the method.
    assert_eq!(insert_one(&mut client, None, batch("actor-n", 1, 0.0, 1)).await.expect_err("no token").code(), Code::Unauthenticated);
    assert_eq!(insert_one(&mut client, Some("actor-to"), batch("actor-n", 1, 0.0, 1)).await.expect_err("wrong token").code(), Code::Unauthenticated);
    let (_, end) = sample_all(&mut client, sample_request(1)).await;
    assert_eq!(end.map(|s| s.code()), Some(Code::Unauthenticated));
    let (_, end) = sample_all(&mut client, with_token(sample_request(1), "learner-to")).await;
    assert_eq!(end.map(|s| s.code()), Some(Code::Unauthenticated));
    assert_eq!(h.table.info().size, 3, "no refused insert reached the table");

    let samples = parse_exposition(&metrics::render(&h.table, &registry, &refusals));
    let value = |series: &str| samples.iter().find(|(s, _)| s == series).map(|(_, v)| *v).unwrap_or_else(|| panic!("{series} missing from {samples:?}"));
    let series = |method: &str, reason: &str| format!(r#"replay_auth_refusals_total{{service="mapless.v1.ReplayService",method="{method}",reason="{reason}"}}"#);
    assert_eq!(value(&series("Sample", "forbidden")), 1.0);
    assert_eq!(value(&series("ServerInfo", "forbidden")), 1.0);
    assert_eq!(value(&series("UpdatePriorities", "forbidden")), 1.0);
    assert_eq!(value(&series("Insert", "forbidden")), 1.0);
    assert_eq!(value(&series("RegisterActor", "forbidden")), 1.0);
    assert_eq!(value(&series("Insert", "missing_token")), 1.0);
    assert_eq!(value(&series("Insert", "wrong_token")), 1.0);
    assert_eq!(value(&series("Sample", "missing_token")), 1.0);
    assert_eq!(value(&series("Sample", "wrong_token")), 1.0);
    h.shutdown().await;
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn tls_with_token_serves_a_client_that_trusts_the_certificate() {
    let cert = rcgen::generate_simple_self_signed(vec!["localhost".to_owned()]).expect("self-signed certificate");
    let (cert_pem, key_pem) = (cert.cert.pem(), cert.signing_key.serialize_pem());
    let security = Security { tls: Some(TlsPem { cert: cert_pem.clone().into_bytes(), key: key_pem.into_bytes() }), token: Some("tok".into()), ..Security::default() };
    let h = Harness::start_with(table_cfg(100), ServeOptions { security, ..ServeOptions::default() }).await;
    let tls = tonic::transport::ClientTlsConfig::new().ca_certificate(tonic::transport::Certificate::from_pem(cert_pem)).domain_name("localhost");
    let channel = Channel::from_shared(format!("https://localhost:{}", h.addr.port())).expect("uri").tls_config(tls).expect("tls config").connect().await.expect("TLS handshake");
    let mut client = ReplayServiceClient::new(channel);
    let info = client.server_info(with_token(ServerInfoRequest { protocol_version: V1 }, "tok")).await.expect("info over TLS");
    assert_eq!(info.into_inner().capacity, 100);
    // Plain HTTP/2 to a TLS port gets nowhere.
    let plain = tokio::time::timeout(Duration::from_secs(3), ReplayServiceClient::connect(format!("http://{}", h.addr))).await;
    if let Ok(Ok(mut plain)) = plain {
        assert!(tokio::time::timeout(Duration::from_secs(3), plain.server_info(ServerInfoRequest { protocol_version: V1 })).await.map_or(true, |r| r.is_err()));
    }
    h.shutdown().await;
}

/// The binary, started with flags only.
fn spawn_binary(args: &[&str]) -> std::process::Child {
    Command::new(env!("CARGO_BIN_EXE_mapless-replay"))
        .args(args)
        // gRPC only: parallel servers would contend for one shared-memory service name.
        .arg("--no-shm")
        .env("RUST_LOG", "info")
        .stdin(Stdio::null())
        .stdout(Stdio::piped())
        .stderr(Stdio::piped())
        .spawn()
        .expect("start mapless-replay")
}

/// Reads stdout until `prefix` and returns the rest of that line.
fn read_line_starting(out: &mut impl BufRead, prefix: &str) -> String {
    let mut line = String::new();
    loop {
        line.clear();
        let n = out.read_line(&mut line).expect("read stdout");
        assert!(n > 0, "stdout closed before `{prefix}`");
        if let Some(rest) = line.trim_end().strip_prefix(prefix) {
            return rest.to_owned();
        }
    }
}

fn wait_exit(child: &mut std::process::Child, within: Duration) -> std::process::ExitStatus {
    let until = Instant::now() + within;
    loop {
        if let Some(status) = child.try_wait().expect("wait") {
            return status;
        }
        if Instant::now() > until {
            let _ = child.kill();
            panic!("mapless-replay did not exit within {within:?}");
        }
        std::thread::sleep(Duration::from_millis(20));
    }
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn binary_serves_on_port_zero_and_exits_cleanly_on_sigterm() {
    let mut child = spawn_binary(&[
        "--listen",
        "127.0.0.1:0",
        "--metrics",
        "127.0.0.1:0",
        "--capacity",
        "500",
        "--obs-dim",
        "3",
        "--act-dim",
        "2",
        "--min-size-to-sample",
        "1",
        "--sampler",
        "prioritized",
        "--log-json",
    ]);
    let mut out = BufReader::new(child.stdout.take().expect("stdout"));
    let metrics_url = read_line_starting(&mut out, "metrics on ");
    let addr: SocketAddr = read_line_starting(&mut out, "listening on ").parse().expect("address");
    assert_ne!(addr.port(), 0);

    let mut client = connect(addr).await;
    let (acks, end) = insert_all(&mut client, vec![batch("actor-bin", 1, 0.0, 8)]).await;
    assert!(end.is_none() && acks.len() == 1, "{end:?}");
    let info = info(&mut client).await;
    assert_eq!((info.size, info.capacity, info.obs_dim, info.selector), (8, 500, 3, Selector::Prioritized as i32));
    let (batches, end) = sample_all(&mut client, sample_request(4)).await;
    assert!(end.is_none() && batches.len() == 1);
    let metrics_addr: SocketAddr = metrics_url.trim_start_matches("http://").trim_end_matches("/metrics").parse().expect("metrics addr");
    let (_, _, body) = tokio::task::spawn_blocking(move || http_get(metrics_addr, "/metrics")).await.expect("get");
    assert!(body.contains("replay_size{table=\"transitions\"} 8"), "{body}");

    // An idle open stream must not hold up the shutdown.
    let mut idle = OpenStream::open(&mut client).await;
    let kill = Command::new("kill").args(["-TERM", &child.id().to_string()]).status().expect("kill");
    assert!(kill.success());
    let status = tokio::task::spawn_blocking(move || {
        let s = wait_exit(&mut child, PATIENCE);
        let mut err = String::new();
        child.stderr.take().expect("stderr").read_to_string(&mut err).expect("stderr");
        (s, err)
    })
    .await
    .expect("wait");
    let (exit, stderr) = status;
    assert!(exit.success(), "exit {exit:?}; stderr:\n{stderr}");
    assert!(stderr.contains("SIGTERM received"), "{stderr}");
    assert!(stderr.contains("\"table\":\"transitions\""), "JSON lines carry the table:\n{stderr}");
    assert!(idle.next().await.is_err(), "the open stream was ended");
}

#[test]
fn binary_refuses_a_non_loopback_address_without_tls_and_token() {
    let mut child = spawn_binary(&["--listen", "0.0.0.0:0", "--no-metrics"]);
    let status = wait_exit(&mut child, PATIENCE);
    let mut err = String::new();
    child.stderr.take().expect("stderr").read_to_string(&mut err).expect("stderr");
    assert!(!status.success());
    assert!(err.contains("refusing to serve on 0.0.0.0:0") && err.contains("TLS") && err.contains("token"), "{err}");
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn binary_with_a_data_dir_restores_acknowledged_rows_after_a_restart() {
    let dir = std::env::temp_dir().join(format!("mapless-replay-grpc-{}", std::process::id()));
    let _ = std::fs::remove_dir_all(&dir);
    let args = ["--listen", "127.0.0.1:0", "--no-metrics", "--capacity", "100", "--obs-dim", "3", "--min-size-to-sample", "1", "--data-dir"];
    let start = |dir: &std::path::Path| {
        let mut all: Vec<&str> = args.to_vec();
        all.push(dir.to_str().expect("utf-8 temp dir"));
        let mut child = spawn_binary(&all);
        let mut out = BufReader::new(child.stdout.take().expect("stdout"));
        let addr: SocketAddr = read_line_starting(&mut out, "listening on ").parse().expect("address");
        (child, addr)
    };
    let stop = |mut child: std::process::Child| {
        let kill = Command::new("kill").args(["-TERM", &child.id().to_string()]).status().expect("kill");
        assert!(kill.success());
        let exit = wait_exit(&mut child, PATIENCE);
        let mut err = String::new();
        child.stderr.take().expect("stderr").read_to_string(&mut err).expect("stderr");
        assert!(exit.success(), "exit {exit:?}; stderr:\n{err}");
    };

    let (child, addr) = start(&dir);
    let mut client = connect(addr).await;
    let (acks, end) = insert_all(&mut client, (1..=3).map(|s| batch("actor-p", s, s as f32 * 10.0, 5)).collect()).await;
    assert!(end.is_none() && acks.len() == 3, "{end:?}");
    for (name, slot) in [("host-a", 0), ("host-b", 1)] {
        assert_eq!(register(&mut client, name).await.expect("register").slot, slot);
    }
    drop(client);
    tokio::task::spawn_blocking(move || stop(child)).await.expect("stopped");

    let (child, addr) = start(&dir);
    let mut client = connect(addr).await;
    assert_eq!(info(&mut client).await.size, 15, "every acknowledged row is back");
    let (acks, end) = insert_all(&mut client, vec![batch("actor-p", 3, 30.0, 5), batch("actor-p", 4, 40.0, 5)]).await;
    assert!(end.is_none(), "{end:?}");
    assert_eq!(acks.iter().map(|a| (a.sequence, a.duplicate)).collect::<Vec<_>>(), vec![(3, true), (4, false)], "de-duplication survives the restart");
    // The actor slots came back from the data directory too.
    let b = register(&mut client, "host-b").await.expect("register");
    assert_eq!((b.slot, b.known, b.registered), (1, true, 2));
    assert_eq!(register(&mut client, "host-c").await.expect("register").slot, 2);
    drop(client);
    tokio::task::spawn_blocking(move || stop(child)).await.expect("stopped");

    // A slot file that is not one stops the replay with a message naming it, not a panic and
    // not a fresh table (which would hand the same slots out again).
    std::fs::write(dir.join("actor-slots.json"), b"{\"version\": 1, \"slots\": {\"host-a\": 0, \"host-b\": 0}}").expect("write");
    let mut all: Vec<&str> = args.to_vec();
    all.push(dir.to_str().expect("utf-8 temp dir"));
    let mut child = spawn_binary(&all);
    let exit = wait_exit(&mut child, PATIENCE);
    let mut err = String::new();
    child.stderr.take().expect("stderr").read_to_string(&mut err).expect("stderr");
    assert!(!exit.success(), "{err}");
    assert!(err.contains("actor-slots.json") && err.contains("not a valid actor-slot file") && err.contains("slot 0 is held by both"), "{err}");
    assert!(!err.contains("panicked"), "{err}");
    let _ = std::fs::remove_dir_all(&dir);
}
