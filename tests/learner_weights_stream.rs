//! The weights service over real HTTP/2 on loopback (port 0): the documented Subscribe
//! semantics (newest version at once, then strictly newer ones, min_version, slow subscribers
//! skip, UNAVAILABLE on shutdown), its gRPC health (SERVING from the first publication until
//! the learner drains), the publisher's checks, and the `.safetensors` round trip from tch
//! tensors to a file and back.

use std::collections::HashMap;
use std::future::Future;
use std::net::SocketAddr;
use std::time::Duration;

use mapless_learner::LearnerError;
use mapless_learner::source::GrpcEndpoint;
use mapless_learner::weights::{self, ServeOptions, WeightsPublisher, snapshot_from_tensors, tensors_from_snapshot};
use mapless_net::NetError;
use mapless_net::Security;
use mapless_net::health::Health;
use mapless_net::weights::{WeightsSubscription, subscribe};
use mapless_proto::v1::weights_service_client::WeightsServiceClient;
use mapless_proto::v1::{Algorithm, NamedTensor, ProtocolVersion, SubscribeRequest, WeightsSnapshot};
use mapless_proto::weights_file::{META_VERSION, WeightsFileError, read_safetensors_file, snapshot_from_safetensors, snapshot_to_safetensors, write_safetensors_file};
use tch::{Device, Kind, Tensor};
use tokio::net::TcpListener;
use tokio::sync::oneshot;
use tokio::task::JoinHandle;
use tonic::Code;

/// Upper bound on anything a test waits for, so a bug fails instead of hanging; generous, as
/// a test waits this long only when it fails (a slow subscriber's 40 snapshots of 1 MiB on a
/// loaded 2-core machine take seconds).
const PATIENCE: Duration = Duration::from_secs(60);

async fn within<T>(what: &str, f: impl Future<Output = T>) -> T {
    tokio::time::timeout(PATIENCE, f).await.unwrap_or_else(|_| panic!("{what}: nothing within {PATIENCE:?}"))
}

/// A snapshot of `version` with one small tensor whose values encode the version.
fn snapshot(version: u64) -> WeightsSnapshot {
    snapshot_with(version, 2)
}

fn snapshot_with(version: u64, values: usize) -> WeightsSnapshot {
    let data: Vec<f32> = (0..values).map(|i| version as f32 + i as f32 / 8.0).collect();
    let tensor = NamedTensor::from_f32("actor.out.bias", vec![values as u64], &data).expect("shape matches");
    WeightsSnapshot {
        protocol_version: ProtocolVersion::V1 as i32,
        version,
        algorithm: Algorithm::Sac as i32,
        created_unix_ms: 1_700_000_000_000 + version,
        obs_dim: 17,
        act_dim: 2,
        tensors: vec![tensor],
        metadata: [("learner_step".to_owned(), (version * 100).to_string())].into(),
    }
}

struct Harness {
    addr: SocketAddr,
    stop: Option<oneshot::Sender<()>>,
    server: Option<JoinHandle<Result<(), LearnerError>>>,
}

impl Harness {
    async fn start(publisher: &WeightsPublisher, options: ServeOptions) -> Harness {
        let listener = TcpListener::bind("127.0.0.1:0").await.expect("bind loopback");
        let addr = listener.local_addr().expect("bound address");
        let (stop, stopped) = oneshot::channel::<()>();
        let server = tokio::spawn(weights::serve(listener, publisher.clone(), options, async {
            let _ = stopped.await;
        }));
        Harness { addr, stop: Some(stop), server: Some(server) }
    }

    fn endpoint(&self) -> GrpcEndpoint {
        GrpcEndpoint::new(format!("http://{}", self.addr))
    }

    async fn subscribe(&self, min_version: u64) -> WeightsSubscription {
        within("subscribe", subscribe(&self.endpoint(), min_version, "actor-test")).await.expect("subscribe")
    }

    /// Stops the server and checks that it returns cleanly.
    async fn shutdown(mut self) {
        self.stop.take().expect("running").send(()).expect("server still running");
        within("server stop", self.server.take().expect("running")).await.expect("no panic").expect("clean exit");
    }
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn health_is_serving_from_the_first_publication_until_the_learner_drains() {
    use tonic_health::pb::HealthCheckRequest;
    use tonic_health::pb::health_check_response::ServingStatus;
    use tonic_health::pb::health_client::HealthClient;
    let (serving, not_serving) = (ServingStatus::Serving as i32, ServingStatus::NotServing as i32);
    let publisher = WeightsPublisher::new();
    let health = Health::new();
    let h = Harness::start(&publisher, ServeOptions { health: health.clone(), ..ServeOptions::default() }).await;
    assert_eq!(within("check", mapless_net::health::check(&h.endpoint(), "")).await.expect("check"), not_serving, "nothing published yet");
    let channel = h.endpoint().connect("health").await.expect("connect");
    let request = HealthCheckRequest { service: "mapless.v1.WeightsService".into() };
    let mut watch = HealthClient::new(channel).watch(request).await.expect("watch").into_inner();
    let mut status = async || within("health status", watch.message()).await.expect("status").expect("open").status;
    assert_eq!(status().await, not_serving);
    publisher.publish(snapshot(1)).expect("v1");
    assert_eq!(status().await, serving, "an actor that subscribes now gets weights at once");
    health.drain();
    assert_eq!(status().await, not_serving, "the learner's stop signal: draining");
    assert_eq!(within("check", mapless_net::health::check(&h.endpoint(), "")).await.expect("check"), not_serving);
    h.shutdown().await;
}

async fn next(subscription: &mut WeightsSubscription) -> WeightsSnapshot {
    within("next snapshot", subscription.next()).await.expect("healthy stream").expect("stream open")
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn late_subscriber_gets_the_newest_version_at_once_then_each_newer_one() {
    let publisher = WeightsPublisher::new();
    publisher.publish(snapshot(1)).expect("v1");
    publisher.publish(snapshot(2)).expect("v2");
    let h = Harness::start(&publisher, ServeOptions::default()).await;

    let mut stream = h.subscribe(0).await;
    let first = next(&mut stream).await;
    assert_eq!(first.version, 2, "a late subscriber starts at the newest version, no history");
    assert_eq!(first, snapshot(2), "every field survives the wire");

    let mut last = first.version;
    for version in 3..=6 {
        publisher.publish(snapshot(version)).expect("publish");
        let got = next(&mut stream).await;
        assert!(got.version > last, "versions strictly increase: {} after {last}", got.version);
        assert_eq!(got.version, version, "a subscriber that keeps up sees every version");
        last = got.version;
    }
    assert_eq!(stream.last_version(), 6);
    drop(stream);
    h.shutdown().await;
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn subscriber_before_the_first_publication_gets_it_when_it_appears() {
    let publisher = WeightsPublisher::new();
    let h = Harness::start(&publisher, ServeOptions::default()).await;
    let mut stream = h.subscribe(1).await;
    let waiting = tokio::spawn(async move { next(&mut stream).await });
    publisher.publish(snapshot(1)).expect("v1");
    assert_eq!(within("first", waiting).await.expect("no panic").version, 1);
    h.shutdown().await;
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn min_version_is_respected() {
    let publisher = WeightsPublisher::new();
    publisher.publish(snapshot(5)).expect("v5");
    let h = Harness::start(&publisher, ServeOptions::default()).await;

    // Wants at least 3, newest is 5: gets 5 at once.
    let mut behind = h.subscribe(3).await;
    assert_eq!(next(&mut behind).await.version, 5);

    // Reconnecting after version 5 (min_version = 6): 5 is not sent again; 6 is the first.
    let mut caught_up = h.subscribe(6).await;
    let waiting = tokio::spawn(async move { next(&mut caught_up).await });
    publisher.publish(snapshot(6)).expect("v6");
    let first = within("first after reconnect", waiting).await.expect("no panic");
    assert_eq!(first.version, 6, "min_version 6 skips the already-received version 5");
    assert_eq!(next(&mut behind).await.version, 6);
    h.shutdown().await;
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn slow_subscriber_skips_versions_but_ends_at_the_newest() {
    let publisher = WeightsPublisher::new();
    // 1 MiB snapshots: far more than HTTP/2 and the per-stream slot can buffer in total.
    const VALUES: usize = 256 * 1024;
    const LAST: u64 = 40;
    publisher.publish(snapshot_with(1, VALUES)).expect("v1");
    let h = Harness::start(&publisher, ServeOptions::default()).await;
    let mut stream = h.subscribe(0).await;
    assert_eq!(next(&mut stream).await.version, 1);

    // The learner races ahead while the subscriber reads nothing; publish never blocks.
    for version in 2..=LAST {
        publisher.publish(snapshot_with(version, VALUES)).expect("publish");
    }
    let mut received = vec![1];
    while *received.last().expect("non-empty") < LAST {
        let got = next(&mut stream).await;
        assert!(got.version > *received.last().expect("non-empty"), "strictly increasing");
        assert_eq!(got, snapshot_with(got.version, VALUES), "a skipped-to snapshot is intact");
        received.push(got.version);
    }
    assert_eq!(*received.last().expect("non-empty"), LAST, "ends at the newest version");
    assert!((received.len() as u64) < LAST, "a slow subscriber skips intermediate versions instead of queueing them all: got {received:?}");
    h.shutdown().await;
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn unknown_protocol_version_is_refused_with_failed_precondition() {
    let publisher = WeightsPublisher::new();
    publisher.publish(snapshot(1)).expect("v1");
    let h = Harness::start(&publisher, ServeOptions::default()).await;
    let mut client = WeightsServiceClient::connect(format!("http://{}", h.addr)).await.expect("connect");
    let refused = client.subscribe(SubscribeRequest { protocol_version: 7, ..SubscribeRequest::default() }).await.expect_err("unknown protocol version");
    assert_eq!(refused.code(), Code::FailedPrecondition);
    assert!(refused.message().contains("protocol_version"), "{}", refused.message());
    h.shutdown().await;
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn shutdown_ends_open_streams_with_unavailable() {
    let publisher = WeightsPublisher::new();
    publisher.publish(snapshot(1)).expect("v1");
    let mut h = Harness::start(&publisher, ServeOptions::default()).await;
    let mut stream = h.subscribe(0).await;
    assert_eq!(next(&mut stream).await.version, 1);

    h.stop.take().expect("running").send(()).expect("server running");
    match within("end of stream", stream.next()).await {
        Err(NetError::Grpc { code, message, .. }) => {
            assert_eq!(code, Code::Unavailable, "{message}");
            assert!(message.contains("shutting down"), "{message}");
        }
        other => panic!("expected UNAVAILABLE, got {other:?}"),
    }
    within("server stop", h.server.take().expect("running")).await.expect("no panic").expect("clean exit");
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn bearer_token_is_required_when_configured() {
    let publisher = WeightsPublisher::new();
    publisher.publish(snapshot(1)).expect("v1");
    let options = ServeOptions { security: Security { tls: None, token: Some("open-sesame".into()), ..Security::default() }, ..ServeOptions::default() };
    let h = Harness::start(&publisher, options).await;
    match within("subscribe without token", subscribe(&h.endpoint(), 0, "")).await {
        Err(NetError::Grpc { code, .. }) => assert_eq!(code, Code::Unauthenticated),
        other => panic!("expected UNAUTHENTICATED, got {other:?}"),
    }
    let endpoint = h.endpoint().with_token("open-sesame");
    let mut stream = within("subscribe", subscribe(&endpoint, 0, "")).await.expect("right token");
    assert_eq!(next(&mut stream).await.version, 1);
    h.shutdown().await;
}

/// Tokens with a role each (issue 17): the actor's subscribes; the learner's may not (it
/// publishes in its own process; no RPC publishes); no or a wrong token is UNAUTHENTICATED;
/// refusals are counted.
#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn only_the_actor_role_subscribes() {
    let publisher = WeightsPublisher::new();
    publisher.publish(snapshot(1)).expect("v1");
    let role_tokens = mapless_net::RoleTokens { actor: Some("actor-tok".into()), learner: Some("learner-tok".into()) };
    let security = Security { role_tokens, ..Security::default() };
    let refusals = security.refusals.clone();
    let h = Harness::start(&publisher, ServeOptions { security, ..ServeOptions::default() }).await;
    let mut stream = within("subscribe", subscribe(&h.endpoint().with_token("actor-tok"), 0, "")).await.expect("the actor token subscribes");
    assert_eq!(next(&mut stream).await.version, 1);
    match within("subscribe with the learner token", subscribe(&h.endpoint().with_token("learner-tok"), 0, "")).await {
        Err(NetError::Grpc { code, message, .. }) => {
            assert_eq!(code, Code::PermissionDenied, "{message}");
            assert!(message.contains("/mapless.v1.WeightsService/Subscribe") && message.contains("the actor role") && message.contains("the learner role"), "{message}");
        }
        other => panic!("expected PERMISSION_DENIED, got {other:?}"),
    }
    for (endpoint, reason) in [(h.endpoint(), "missing_token"), (h.endpoint().with_token("actor-to"), "wrong_token")] {
        match within("subscribe", subscribe(&endpoint, 0, "")).await {
            Err(NetError::Grpc { code, .. }) => assert_eq!(code, Code::Unauthenticated, "{reason}"),
            other => panic!("{reason}: expected UNAUTHENTICATED, got {other:?}"),
        }
        assert_eq!(refusals.count("mapless.v1.WeightsService", "Subscribe", reason), 1, "{reason}");
    }
    assert_eq!(refusals.count("mapless.v1.WeightsService", "Subscribe", "forbidden"), 1);
    h.shutdown().await;
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn non_loopback_listener_without_tls_and_token_is_refused() {
    let listener = TcpListener::bind("0.0.0.0:0").await.expect("bind");
    let refused = weights::run(listener, WeightsPublisher::new(), std::future::pending()).await;
    let err = refused.expect_err("insecure non-loopback listener");
    assert!(err.to_string().contains("TLS") && err.to_string().contains("token"), "{err}");
}

#[test]
fn publish_refuses_stale_invalid_and_oversized_snapshots_and_keeps_the_newest() {
    let publisher = WeightsPublisher::new();
    assert_eq!(publisher.latest_version(), 0);
    assert_eq!(publisher.publish(snapshot(3)).expect("v3"), 3);

    for stale in [3, 2] {
        let err = publisher.publish(snapshot(stale)).expect_err("not newer");
        assert!(err.to_string().contains("not newer"), "{err}");
    }
    let mut unversioned = snapshot(4);
    unversioned.version = 0;
    assert!(publisher.publish(unversioned).is_err(), "version 0 is never published");
    let mut no_algorithm = snapshot(4);
    no_algorithm.algorithm = Algorithm::Unspecified as i32;
    assert!(publisher.publish(no_algorithm).expect_err("algorithm").to_string().contains("algorithm"));
    let mut torn = snapshot(4);
    torn.tensors[0].data.pop();
    assert!(publisher.publish(torn).expect_err("torn tensor").to_string().contains("actor.out.bias"));
    let huge = snapshot_with(4, mapless_proto::MAX_MESSAGE_BYTES / 4 + 1);
    assert!(publisher.publish(huge).expect_err("too big").to_string().contains("message limit"));

    assert_eq!(publisher.latest_version(), 3, "refused snapshots leave the newest in place");
    assert_eq!(*publisher.latest().expect("published"), snapshot(3));
    // Clones share the one slot.
    let clone = publisher.clone();
    clone.publish(snapshot(4)).expect("v4");
    assert_eq!(publisher.latest_version(), 4);
}

/// A snapshot with awkward values and names given out of alphabetical order.
fn awkward_snapshot() -> WeightsSnapshot {
    let special = [0.0, -0.0, f32::MIN_POSITIVE / 2.0, f32::MAX, f32::MIN, 1.0e-38, std::f32::consts::PI, -1.5];
    let tensors = vec![
        NamedTensor::from_f32("policy.z_last.weight", vec![2, 4], &special).expect("2x4"),
        NamedTensor::from_f32("policy.a_first.bias", vec![3], &[1.0, 2.0, 3.0]).expect("3"),
        NamedTensor::from_f32("policy.log_std_scale", vec![], &[0.25]).expect("scalar"),
        NamedTensor::from_f32("policy.empty", vec![0, 5], &[]).expect("empty"),
    ];
    WeightsSnapshot {
        protocol_version: ProtocolVersion::V1 as i32,
        version: 42,
        algorithm: Algorithm::Td3 as i32,
        created_unix_ms: 1_700_000_123_456,
        obs_dim: 17,
        act_dim: 2,
        tensors,
        metadata: [("learner_step".to_owned(), "4200".to_owned()), ("config_hash".to_owned(), "abc123".to_owned())].into(),
    }
}

#[test]
fn snapshot_round_trips_through_a_safetensors_file_bit_exactly() {
    let dir = tempfile::tempdir().expect("temp dir");
    let path = dir.path().join("policy-42.safetensors");
    let original = awkward_snapshot();
    write_safetensors_file(&path, &original).expect("write");
    let back = read_safetensors_file(&path).expect("read");
    assert_eq!(back, original, "every field, tensor order and byte survive");
    for (a, b) in original.tensors.iter().zip(&back.tensors) {
        assert_eq!(a.data, b.data, "tensor `{}` bytes", a.name);
    }
    // Overwriting is atomic and leaves no temporary file behind.
    let mut newer = original.clone();
    newer.version = 43;
    write_safetensors_file(&path, &newer).expect("overwrite");
    assert_eq!(read_safetensors_file(&path).expect("read").version, 43);
    let names: Vec<_> = std::fs::read_dir(dir.path()).expect("list").map(|e| e.expect("entry").file_name()).collect();
    assert_eq!(names, vec![std::ffi::OsString::from("policy-42.safetensors")]);

    // A plain safetensors reader sees the tensors and the metadata.
    let bytes = std::fs::read(&path).expect("read bytes");
    let (_, header) = safetensors::SafeTensors::read_metadata(&bytes).expect("valid safetensors");
    let meta = header.metadata().as_ref().expect("__metadata__");
    assert_eq!(meta.get(META_VERSION).map(String::as_str), Some("43"));
    assert_eq!(meta.get("learner_step").map(String::as_str), Some("4200"));
    let file = safetensors::SafeTensors::deserialize(&bytes).expect("valid safetensors");
    let view = file.tensor("policy.z_last.weight").expect("tensor");
    assert_eq!(view.dtype(), safetensors::Dtype::F32);
    assert_eq!(view.shape(), &[2, 4]);
}

fn expect_invalid(result: Result<WeightsSnapshot, WeightsFileError>, needle: &str) {
    match result {
        Err(e @ WeightsFileError::Invalid { .. }) => {
            assert!(e.to_string().contains(needle), "error should mention `{needle}`: {e}");
        }
        other => panic!("expected InvalidWeights mentioning `{needle}`, got {other:?}"),
    }
}

#[test]
fn corrupt_safetensors_files_are_clear_errors() {
    let dir = tempfile::tempdir().expect("temp dir");
    let good = snapshot_to_safetensors(&awkward_snapshot()).expect("encode");

    // Truncated: the header's offsets run past the end.
    let path = dir.path().join("truncated.safetensors");
    std::fs::write(&path, &good[..good.len() - 3]).expect("write");
    expect_invalid(read_safetensors_file(&path), "not a valid .safetensors file");

    // A flipped bit in the tensor data: only the checksum can tell.
    let mut flipped = good.clone();
    let last = flipped.len() - 1;
    flipped[last] ^= 0x01;
    expect_invalid(snapshot_from_safetensors(&flipped, "flipped"), "corrupt");

    // Garbage, empty, and a header length pointing nowhere.
    expect_invalid(snapshot_from_safetensors(b"definitely not safetensors", "garbage"), "not a valid");
    expect_invalid(snapshot_from_safetensors(&[], "empty"), "not a valid");
    expect_invalid(snapshot_from_safetensors(&u64::MAX.to_le_bytes(), "huge header"), "not a valid");

    // A valid safetensors file that is not a mapless snapshot.
    let plain_data = [0u8; 8];
    let view = safetensors::tensor::TensorView::new(safetensors::Dtype::F32, vec![2], &plain_data).expect("view");
    let plain = safetensors::serialize([("w", view)], None).expect("serialize");
    expect_invalid(snapshot_from_safetensors(&plain, "plain"), "mapless.version");

    // A missing file names the path.
    let missing = dir.path().join("missing.safetensors");
    let err = read_safetensors_file(&missing).expect_err("missing file");
    assert!(matches!(err, WeightsFileError::Io { .. }) && err.to_string().contains("missing.safetensors"), "{err}");

    // Writing refuses invalid snapshots and reserved metadata keys.
    let mut reserved = awkward_snapshot();
    reserved.metadata.insert("mapless.version".into(), "7".into());
    assert!(snapshot_to_safetensors(&reserved).expect_err("reserved").to_string().contains("reserved"));
    let mut duplicate = awkward_snapshot();
    duplicate.tensors.push(duplicate.tensors[0].clone());
    assert!(snapshot_to_safetensors(&duplicate).is_err(), "duplicate names refused");
}

#[test]
fn tensor_values_from_tch_survive_exactly() {
    tch::manual_seed(7);
    let weight = Tensor::randn([4, 3], (Kind::Float, Device::Cpu)) * 1.0e3;
    let bias = Tensor::randn([3], (Kind::Float, Device::Cpu));
    // Non-contiguous (a transpose) and a trainable parameter: both must come out row-major.
    let transposed = Tensor::randn([3, 5], (Kind::Float, Device::Cpu)).transpose(0, 1);
    assert!(!transposed.is_contiguous());
    let trainable = Tensor::randn([2, 2], (Kind::Float, Device::Cpu)).set_requires_grad(true);
    let scalar = Tensor::from(-0.0f32);
    let tensors = vec![
        ("actor.fc2.weight".to_owned(), weight.shallow_clone()),
        ("actor.fc1.bias".to_owned(), bias.shallow_clone()),
        ("actor.t".to_owned(), transposed.shallow_clone()),
        ("actor.p".to_owned(), trainable.shallow_clone()),
        ("actor.s".to_owned(), scalar.shallow_clone()),
    ];
    let metadata = HashMap::from([("learner_step".to_owned(), "17".to_owned())]);
    let snap = snapshot_from_tensors(9, Algorithm::Sac, 17, 2, &tensors, metadata).expect("snapshot");
    assert_eq!(snap.validate(), Ok(()));
    let names: Vec<_> = snap.tensors.iter().map(|t| t.name.as_str()).collect();
    assert_eq!(names, ["actor.fc2.weight", "actor.fc1.bias", "actor.t", "actor.p", "actor.s"], "names and order as given");
    assert_eq!(snap.tensor("actor.t").expect("t").shape, vec![5, 3]);
    assert_eq!(snap.tensor("actor.s").expect("s").shape, Vec::<u64>::new());

    let back = snapshot_from_safetensors(&snapshot_to_safetensors(&snap).expect("encode"), "memory").expect("decode");
    assert_eq!(back, snap);
    let restored = tensors_from_snapshot(&back).expect("tensors");
    for ((name, original), (restored_name, restored)) in tensors.iter().zip(&restored) {
        assert_eq!(name, restored_name);
        assert_eq!(original.size(), restored.size(), "{name} shape");
        let a = Vec::<f32>::try_from(original.detach().contiguous().flatten(0, -1)).expect("f32 values");
        let b = Vec::<f32>::try_from(restored.flatten(0, -1)).expect("f32 values");
        let bits = |v: &[f32]| v.iter().map(|x| x.to_bits()).collect::<Vec<_>>();
        assert_eq!(bits(&a), bits(&b), "{name}: every bit survives");
    }

    // Values the learner must never publish, and kinds that are not weights.
    let nan = vec![("actor.nan".to_owned(), Tensor::from_slice(&[1.0f32, f32::NAN]))];
    let err = snapshot_from_tensors(10, Algorithm::Sac, 17, 2, &nan, HashMap::new()).expect_err("NaN");
    assert!(err.to_string().contains("actor.nan") && err.to_string().contains("element 1"), "{err}");
    let ints = vec![("actor.steps".to_owned(), Tensor::from_slice(&[1i64, 2]))];
    let err = snapshot_from_tensors(10, Algorithm::Sac, 17, 2, &ints, HashMap::new()).expect_err("int64");
    assert!(err.to_string().contains("actor.steps"), "{err}");
    // f64 parameters are converted to f32.
    let doubles = vec![("actor.d".to_owned(), Tensor::from_slice(&[0.5f64, -2.0]))];
    let snap = snapshot_from_tensors(10, Algorithm::Ddpg, 3, 1, &doubles, HashMap::new()).expect("f64 converted");
    assert_eq!(snap.tensors[0].to_f32_vec(), Ok(vec![0.5, -2.0]));
}
