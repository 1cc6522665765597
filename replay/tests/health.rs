//! The replay's health in the standard gRPC health protocol (`grpc.health.v1.Health`), served
//! beside its own service on loopback, and `mapless-replay health`, the probe a container's
//! HEALTHCHECK runs: SERVING once it serves, NOT_SERVING from a graceful stop on, behind the
//! same token as the replay itself.

use std::net::SocketAddr;
use std::process::{Command, Output};
use std::sync::Arc;
use std::time::Duration;

use mapless_net::health::{Health, Phase, check};
use mapless_net::{GrpcEndpoint, Security};
use mapless_replay::server::{ServeOptions, ServerError, serve};
use mapless_replay::{Table, TableConfig};
use tokio::net::TcpListener;
use tokio::sync::oneshot;
use tokio::task::JoinHandle;
use tonic::Code;
use tonic_health::pb::HealthCheckRequest;
use tonic_health::pb::health_check_response::ServingStatus;
use tonic_health::pb::health_client::HealthClient;

/// Upper bound on anything a test waits for, so a bug fails instead of hanging.
const PATIENCE: Duration = Duration::from_secs(10);
const SERVING: i32 = ServingStatus::Serving as i32;
const NOT_SERVING: i32 = ServingStatus::NotServing as i32;
const TOKEN: &str = "open-sesame";

struct Replay {
    addr: SocketAddr,
    stop: oneshot::Sender<()>,
    server: JoinHandle<Result<(), ServerError>>,
}

async fn start(options: ServeOptions) -> Replay {
    let table = Arc::new(Table::new(TableConfig { capacity: 10_000, obs_dim: 3, ..TableConfig::default() }, 1).expect("table"));
    let listener = TcpListener::bind("127.0.0.1:0").await.expect("bind loopback");
    let addr = listener.local_addr().expect("address");
    let (stop, stopped) = oneshot::channel::<()>();
    let server = tokio::spawn(serve(listener, table, options, async {
        let _ = stopped.await;
    }));
    Replay { addr, stop, server }
}

fn endpoint(addr: SocketAddr) -> GrpcEndpoint {
    GrpcEndpoint::new(format!("http://{addr}"))
}

async fn within<T>(what: &str, f: impl Future<Output = T>) -> T {
    tokio::time::timeout(PATIENCE, f).await.unwrap_or_else(|_| panic!("{what}: no answer within {PATIENCE:?}"))
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn serving_once_started_and_not_serving_from_a_graceful_stop_on() {
    let health = Health::new();
    let replay = start(ServeOptions { health: health.clone(), shutdown_grace: Duration::from_millis(300), ..ServeOptions::default() }).await;
    let e = endpoint(replay.addr);
    assert_eq!(within("check", check(&e, "")).await.expect("check the server"), SERVING);
    assert_eq!(within("check", check(&e, "mapless.v1.ReplayService")).await.expect("check the service"), SERVING);
    let unknown = within("check", check(&e, "mapless.v1.NoSuchService")).await.expect_err("an unknown name");
    assert_eq!(unknown.code(), Some(Code::NotFound), "{unknown}");
    assert_eq!(health.phase(), Phase::Serving, "the process's /healthz sees the same state");

    // A Watch stream sees the stop as it happens.
    let channel = e.connect("health").await.expect("connect");
    let mut watch = HealthClient::new(channel).watch(HealthCheckRequest { service: String::new() }).await.expect("watch").into_inner();
    assert_eq!(within("first status", watch.message()).await.expect("status").expect("open").status, SERVING);
    replay.stop.send(()).expect("server running");
    assert_eq!(within("status at stop", watch.message()).await.expect("status").expect("open").status, NOT_SERVING);
    assert_eq!(health.phase(), Phase::Draining);
    within("server stops", replay.server).await.expect("no panic").expect("clean exit");
    // Gone: a new check finds nobody. (The open Watch is not asserted on: tonic runs each
    // connection in a task of its own, which outlives the server future in this process; a
    // replay process exits there.)
    drop(watch);
    let gone = within("check", check(&e, "")).await.expect_err("stopped");
    assert_eq!(gone.code(), Some(Code::Unavailable), "{gone}");
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn health_needs_the_token_the_replay_needs() {
    let replay = start(ServeOptions { security: Security { tls: None, token: Some(TOKEN.into()), ..Security::default() }, ..ServeOptions::default() }).await;
    let refused = within("check", check(&endpoint(replay.addr), "")).await.expect_err("no token");
    assert_eq!(refused.code(), Some(Code::Unauthenticated), "{refused}");
    assert_eq!(within("check", check(&endpoint(replay.addr).with_token(TOKEN), "")).await.expect("with the token"), SERVING);
    replay.stop.send(()).expect("server running");
    within("server stops", replay.server).await.expect("no panic").expect("clean exit");
}

/// Health checks are open to any token the replay accepts, whatever its role.
#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn health_answers_every_role_token() {
    let role_tokens = mapless_net::RoleTokens { actor: Some("actor-tok".into()), learner: Some("learner-tok".into()) };
    let replay = start(ServeOptions { security: Security { role_tokens, ..Security::default() }, ..ServeOptions::default() }).await;
    for token in ["actor-tok", "learner-tok"] {
        let e = endpoint(replay.addr).with_token(token);
        assert_eq!(within("check", check(&e, "")).await.expect(token), SERVING);
        assert_eq!(within("check", check(&e, "mapless.v1.ReplayService")).await.expect(token), SERVING);
    }
    let refused = within("check", check(&endpoint(replay.addr).with_token("nobody"), "")).await.expect_err("unknown token");
    assert_eq!(refused.code(), Some(Code::Unauthenticated), "{refused}");
    replay.stop.send(()).expect("server running");
    within("server stops", replay.server).await.expect("no panic").expect("clean exit");
}

/// `mapless-replay health ARGS…`, with no `MAPLESS_HEALTH_*` from the environment.
fn probe(args: &[&str]) -> Output {
    let mut cmd = Command::new(env!("CARGO_BIN_EXE_mapless-replay"));
    cmd.arg("health").args(args);
    for (k, _) in std::env::vars() {
        if k.starts_with("MAPLESS_HEALTH_") {
            cmd.env_remove(k);
        }
    }
    cmd.output().expect("run mapless-replay health")
}

fn text(o: &Output) -> String {
    format!("{}{}", String::from_utf8_lossy(&o.stdout), String::from_utf8_lossy(&o.stderr))
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn the_probe_exits_0_only_when_serving() {
    let dir = tempfile::tempdir().expect("temp dir");
    let token_file = dir.path().join("token");
    std::fs::write(&token_file, format!("{TOKEN}\n")).expect("write token");
    let token_file = token_file.to_str().expect("utf-8 path").to_owned();
    let replay = start(ServeOptions { security: Security { tls: None, token: Some(TOKEN.into()), ..Security::default() }, ..ServeOptions::default() }).await;
    let addr = replay.addr.to_string();

    let serving = tokio::task::spawn_blocking({
        let addr = addr.clone();
        let token_file = token_file.clone();
        move || probe(&[&addr, "--token-file", &token_file])
    })
    .await
    .expect("probe");
    assert!(serving.status.success(), "{}", text(&serving));
    assert!(String::from_utf8_lossy(&serving.stdout).starts_with("SERVING"), "{}", text(&serving));

    let no_token = tokio::task::spawn_blocking({
        let addr = addr.clone();
        move || probe(&[&addr])
    })
    .await
    .expect("probe");
    assert_eq!(no_token.status.code(), Some(1), "{}", text(&no_token));
    assert!(text(&no_token).contains("Unauthenticated"), "{}", text(&no_token));

    replay.stop.send(()).expect("server running");
    within("server stops", replay.server).await.expect("no panic").expect("clean exit");
    let unreachable = tokio::task::spawn_blocking(move || probe(&[&addr, "--token-file", &token_file])).await.expect("probe");
    assert_eq!(unreachable.status.code(), Some(1), "{}", text(&unreachable));
    assert!(text(&unreachable).contains("unreachable"), "{}", text(&unreachable));

    // A replay whose process is already draining (its stop signal came) answers NOT_SERVING.
    let draining = Health::new();
    draining.drain();
    let replay = start(ServeOptions { health: draining, ..ServeOptions::default() }).await;
    let addr = replay.addr.to_string();
    let not_serving = tokio::task::spawn_blocking(move || probe(&[&addr])).await.expect("probe");
    assert_eq!(not_serving.status.code(), Some(1), "{}", text(&not_serving));
    assert!(text(&not_serving).contains("NOT_SERVING"), "{}", text(&not_serving));
    replay.stop.send(()).expect("server running");
    within("server stops", replay.server).await.expect("no panic").expect("clean exit");
}
