//! `mapless-actor --index auto` against a real `mapless-replay` process on loopback: replicas
//! that share one command line register under their names, get distinct slots, and deliver
//! under distinct actor ids; a name gets its slot back from a restarted actor and from a
//! restarted replay (its data directory keeps the slots).

#[path = "../../tests/common/workspace_build.rs"]
mod workspace_build;

use std::collections::BTreeMap;
use std::io::{BufRead, BufReader, Read as _};
use std::net::SocketAddr;
use std::path::{Path, PathBuf};
use std::process::{Child, Command, Stdio};
use std::time::{Duration, Instant};

use mapless_actor::run::{ActorConfig, ExplorationSettings, ReplayTarget};
use mapless_proto::v1::replay_service_client::ReplayServiceClient;
use mapless_proto::v1::{ProtocolVersion, ServerInfoRequest, ServerInfoResponse};
use mapless_sim::EnvConfig;

/// Upper bound on anything a test waits for, so a bug fails instead of hanging.
const PATIENCE: Duration = Duration::from_secs(60);
/// Vehicle-steps each actor process takes (2 vehicles, batches of 16 rows).
const STEPS: u64 = 96;

/// `mapless-replay`, beside this package's `mapless-actor` (the actor crate does not depend on
/// the replay). Brought up to date once per test binary, not only built when missing: a stale
/// replay left by an older checkout would answer the newer RPCs with UNIMPLEMENTED.
fn replay_bin() -> PathBuf {
    let actor = PathBuf::from(env!("CARGO_BIN_EXE_mapless-actor"));
    workspace_build::build_workspace_once(actor.parent().unwrap());
    actor.with_file_name("mapless-replay")
}

/// A replay process; killed when dropped (a failed assertion).
struct Replay {
    child: Child,
    addr: SocketAddr,
}

impl Replay {
    fn start(data_dir: &Path, obs_dim: usize) -> Replay {
        Replay::start_with(data_dir, obs_dim, &["--no-shm"])
    }

    fn start_with(data_dir: &Path, obs_dim: usize, extra: &[&str]) -> Replay {
        let mut child = Command::new(replay_bin())
            .args(["--listen", "127.0.0.1:0", "--no-metrics", "--capacity", "100000", "--min-size-to-sample", "1", "--obs-dim", &obs_dim.to_string()])
            .args(extra)
            .arg("--data-dir")
            .arg(data_dir)
            .env("RUST_LOG", "warn")
            .stdin(Stdio::null())
            .stdout(Stdio::piped())
            .stderr(Stdio::inherit())
            .spawn()
            .expect("start mapless-replay");
        let mut out = BufReader::new(child.stdout.take().expect("stdout"));
        let mut line = String::new();
        let addr = loop {
            line.clear();
            assert!(out.read_line(&mut line).expect("read stdout") > 0, "mapless-replay ended before it listened");
            if let Some(a) = line.trim().strip_prefix("listening on ") {
                break a.parse().expect("address");
            }
        };
        Replay { child, addr }
    }

    fn info(&self) -> ServerInfoResponse {
        let rt = tokio::runtime::Builder::new_current_thread().enable_all().build().unwrap();
        rt.block_on(async {
            let mut client = ReplayServiceClient::connect(format!("http://{}", self.addr)).await.expect("connect");
            client.server_info(ServerInfoRequest { protocol_version: ProtocolVersion::V1 as i32 }).await.expect("server info").into_inner()
        })
    }

    /// SIGTERM, then waits for a clean exit (the final snapshot).
    fn stop(mut self) {
        let kill = Command::new("kill").args(["-TERM", &self.child.id().to_string()]).status().expect("kill");
        assert!(kill.success());
        let status = wait(&mut self.child);
        assert!(status.success(), "mapless-replay exit {status:?}");
    }
}

impl Drop for Replay {
    fn drop(&mut self) {
        let _ = self.child.kill();
        let _ = self.child.wait();
    }
}

fn wait(child: &mut Child) -> std::process::ExitStatus {
    let until = Instant::now() + PATIENCE;
    loop {
        if let Some(s) = child.try_wait().expect("wait") {
            return s;
        }
        if Instant::now() > until {
            let _ = child.kill();
            panic!("process {} did not exit within {PATIENCE:?}", child.id());
        }
        std::thread::sleep(Duration::from_millis(20));
    }
}

/// One actor config for every replica: the same file, the same command line.
fn actor_config(dir: &Path, replay: SocketAddr) -> PathBuf {
    let env = EnvConfig::default();
    let cfg = ActorConfig {
        map: "env1".into(),
        worlds_per_family: 32,
        env,
        vehicles: 2,
        // Random actions throughout: no learner in this test (the weights address refuses).
        exploration: ExplorationSettings { warmup_steps: u64::MAX, noise: None, mirror_share: 0.0 },
        n_step: None,
        batch_rows: 16,
        max_in_flight: 8,
        replay: ReplayTarget::Grpc { uri: format!("http://{replay}") },
        weights: "http://127.0.0.1:9".into(),
        stats: None,
        security: Default::default(),
        seed: 5,
        metrics_listen: None,
        metrics_token_file: None,
    };
    let path = dir.join("actor.yaml");
    std::fs::write(&path, serde_yaml::to_string(&cfg).unwrap()).unwrap();
    path
}

/// Starts `mapless-actor --index auto` naming itself `name` (by flag, or by the environment).
fn spawn_actor(config: &Path, name: &str, by_env: bool) -> Child {
    let mut cmd = Command::new(env!("CARGO_BIN_EXE_mapless-actor"));
    cmd.arg("--config").arg(config).args(["--index", "auto", "--max-steps", &STEPS.to_string()]);
    if by_env {
        cmd.env("MAPLESS_ACTOR_NAME", name);
    } else {
        cmd.env_remove("MAPLESS_ACTOR_NAME").args(["--name", name]);
    }
    cmd.env("RUST_LOG", "info").stdin(Stdio::null()).stdout(Stdio::piped()).stderr(Stdio::piped()).spawn().expect("start mapless-actor")
}

/// What an actor process said: its final report (stdout's JSON line) and its log.
struct Finished {
    actor_id: String,
    rows_acked: u64,
    log: String,
    report: serde_json::Value,
}

fn finish(mut child: Child) -> Finished {
    let status = wait(&mut child);
    let (mut out, mut log) = (String::new(), String::new());
    child.stdout.take().unwrap().read_to_string(&mut out).unwrap();
    child.stderr.take().unwrap().read_to_string(&mut log).unwrap();
    assert!(status.success(), "mapless-actor exit {status:?}\n{log}");
    let report: serde_json::Value = serde_json::from_str(out.lines().last().expect("a report line")).expect("JSON report");
    let sink = &report["sink"];
    assert_eq!(sink["acked"], sink["batches"], "every batch acknowledged: {report}");
    assert_eq!(report["unacked_at_exit"], false, "{report}");
    Finished { actor_id: report["actor_id"].as_str().unwrap().to_owned(), rows_acked: sink["rows"].as_u64().unwrap(), log, report }
}

/// The slot in an actor id `actor-<slot>-<pid>-<ms>`.
fn slot_of(actor_id: &str) -> u32 {
    actor_id.split('-').nth(1).and_then(|s| s.parse().ok()).unwrap_or_else(|| panic!("no slot in {actor_id}"))
}

fn rows_by_actor(info: &ServerInfoResponse) -> BTreeMap<String, u64> {
    info.actors.iter().map(|a| (a.actor_id.clone(), a.rows)).collect()
}

#[test]
fn replicas_with_index_auto_get_distinct_slots_and_keep_them_across_restarts() {
    let dir = std::env::temp_dir().join(format!("mapless-actor-register-{}", std::process::id()));
    let _ = std::fs::remove_dir_all(&dir);
    std::fs::create_dir_all(&dir).unwrap();
    let data = dir.join("replay");
    let obs_dim = EnvConfig::default().obs_dim();
    let replay = Replay::start(&data, obs_dim);
    let config = actor_config(&dir, replay.addr);

    // Two replicas at once, one command line, two names.
    let (a, b) = (spawn_actor(&config, "host-a", false), spawn_actor(&config, "host-b", true));
    let (a, b) = (finish(a), finish(b));
    assert_ne!(a.actor_id, b.actor_id);
    let mut slots = [slot_of(&a.actor_id), slot_of(&b.actor_id)];
    slots.sort();
    assert_eq!(slots, [0, 1], "{} {}", a.actor_id, b.actor_id);
    assert!(a.log.contains("registered with the replay") && a.log.contains("known=false"), "{}", a.log);
    let info = replay.info();
    let rows = rows_by_actor(&info);
    assert_eq!(rows, BTreeMap::from([(a.actor_id.clone(), STEPS), (b.actor_id.clone(), STEPS)]), "both ids deliver every row once");
    assert_eq!((a.rows_acked, b.rows_acked), (STEPS, STEPS));

    // A restarted replica gets its slot back, under a new incarnation id.
    let a2 = finish(spawn_actor(&config, "host-a", false));
    assert_eq!(slot_of(&a2.actor_id), slot_of(&a.actor_id));
    assert_ne!(a2.actor_id, a.actor_id, "a new incarnation never reuses its predecessor's sequence numbers");
    assert!(a2.log.contains("known=true"), "{}", a2.log);

    // The replay restarts from its data directory: the names keep their slots, a new name
    // takes the next one, and nothing was lost or duplicated.
    replay.stop();
    let replay = Replay::start(&data, obs_dim);
    let config = actor_config(&dir, replay.addr);
    let (b2, c) = (spawn_actor(&config, "host-b", false), spawn_actor(&config, "host-c", false));
    let (b2, c) = (finish(b2), finish(c));
    assert_eq!(slot_of(&b2.actor_id), slot_of(&b.actor_id));
    assert_eq!(slot_of(&c.actor_id), 2);
    let rows = rows_by_actor(&replay.info());
    let expected: BTreeMap<String, u64> = [&a, &b, &a2, &b2, &c].iter().map(|f| (f.actor_id.clone(), STEPS)).collect();
    assert_eq!(rows, expected);
    replay.stop();
    let _ = std::fs::remove_dir_all(&dir);
}

/// An actor that writes over shared memory (a container sharing the replay's IPC namespace and
/// iceoryx2 folder, deploy/compose.yaml's `actor-shm`) registers over gRPC (`replay.register`)
/// and delivers its rows through shared memory, once each; without the address, `--index auto`
/// is refused with a clear error.
#[test]
fn an_actor_on_shared_memory_takes_its_slot_over_grpc() {
    let dir = std::env::temp_dir().join(format!("mapless-actor-register-shm-{}", std::process::id()));
    let _ = std::fs::remove_dir_all(&dir);
    std::fs::create_dir_all(&dir).unwrap();
    let (prefix, domain) = (format!("mapless-test/register-{}", std::process::id()), format!("mreg{}", std::process::id()));
    let shm = dir.join("replay-shm.yaml");
    std::fs::write(&shm, format!("shm:\n  prefix: {prefix}\n  domain: {domain}\n")).unwrap();
    let replay = Replay::start_with(&dir.join("replay"), EnvConfig::default().obs_dim(), &["--config", shm.to_str().unwrap()]);
    let grpc = actor_config(&dir, replay.addr);
    let mut cfg: ActorConfig = serde_yaml::from_str(&std::fs::read_to_string(&grpc).unwrap()).unwrap();
    cfg.replay = ReplayTarget::Shm { prefix: prefix.clone(), domain: domain.clone(), register: Some(format!("http://{}", replay.addr)) };
    let config = dir.join("actor-shm.yaml");
    std::fs::write(&config, serde_yaml::to_string(&cfg).unwrap()).unwrap();

    let a = finish(spawn_actor(&config, "shm-host", false));
    assert_eq!(slot_of(&a.actor_id), 0, "{}", a.actor_id);
    assert!(a.log.contains("registered with the replay"), "{}", a.log);
    assert_eq!(rows_by_actor(&replay.info()), BTreeMap::from([(a.actor_id.clone(), STEPS)]), "every row once, over shared memory");

    cfg.replay = ReplayTarget::Shm { prefix, domain: domain.clone(), register: None };
    std::fs::write(&config, serde_yaml::to_string(&cfg).unwrap()).unwrap();
    let out = spawn_actor(&config, "shm-host", false).wait_with_output().unwrap();
    let log = String::from_utf8_lossy(&out.stderr);
    assert!(!out.status.success() && log.contains("replay.register") && !log.contains("panicked"), "{log}");
    replay.stop();
    mapless_net::shm::remove_private_domain_files(&domain);
    let _ = std::fs::remove_dir_all(&dir);
}

#[test]
fn index_auto_with_a_bad_name_fails_with_a_clear_error() {
    let dir = std::env::temp_dir().join(format!("mapless-actor-badname-{}", std::process::id()));
    let _ = std::fs::remove_dir_all(&dir);
    std::fs::create_dir_all(&dir).unwrap();
    // Checked before dialling: no replay needed.
    let config = actor_config(&dir, "127.0.0.1:9".parse().unwrap());
    let child = spawn_actor(&config, &"n".repeat(200), false);
    let output = child.wait_with_output().unwrap();
    let log = String::from_utf8_lossy(&output.stderr);
    assert!(!output.status.success());
    assert!(log.contains("200 bytes long") && log.contains("registering actor name"), "{log}");
    assert!(!log.contains("panicked"), "{log}");
    let _ = std::fs::remove_dir_all(&dir);
}

/// `exploration.mirror_share` (`actors.mirror_share` of a run): that share of the rows goes to
/// the replay as its mirror image (what a mirror image is: sim/tests/mirror.rs), every row
/// still delivered once; a share outside [0, 1] is refused before anything runs.
#[test]
fn an_actor_stores_its_share_of_rows_mirrored() {
    let dir = std::env::temp_dir().join(format!("mapless-actor-mirror-{}", std::process::id()));
    let _ = std::fs::remove_dir_all(&dir);
    std::fs::create_dir_all(&dir).unwrap();
    let replay = Replay::start(&dir.join("replay"), EnvConfig::default().obs_dim());
    let plain = actor_config(&dir, replay.addr);
    let mut cfg: ActorConfig = serde_yaml::from_str(&std::fs::read_to_string(&plain).unwrap()).unwrap();
    let config = dir.join("actor-mirror.yaml");
    let mut delivered = BTreeMap::new();
    for (share, name) in [(0.0, "m-none"), (0.5, "m-half"), (1.0, "m-all")] {
        cfg.exploration.mirror_share = share;
        std::fs::write(&config, serde_yaml::to_string(&cfg).unwrap()).unwrap();
        let f = finish(spawn_actor(&config, name, false));
        let mirrored = f.report["mirrored_rows"].as_u64().expect("mirrored_rows in the report");
        match share {
            0.0 => assert_eq!(mirrored, 0),
            1.0 => assert_eq!(mirrored, STEPS),
            // 96 draws at one half: all or none has odds of 2⁻⁹⁵.
            _ => assert!(0 < mirrored && mirrored < STEPS, "{mirrored} of {STEPS}"),
        }
        delivered.insert(f.actor_id, STEPS);
    }
    assert_eq!(rows_by_actor(&replay.info()), delivered, "every row once, mirrored or not");
    cfg.exploration.mirror_share = 1.5;
    std::fs::write(&config, serde_yaml::to_string(&cfg).unwrap()).unwrap();
    let out = spawn_actor(&config, "m-bad", false).wait_with_output().unwrap();
    let log = String::from_utf8_lossy(&out.stderr);
    assert!(!out.status.success() && log.contains("mirror_share") && !log.contains("panicked"), "{log}");
    replay.stop();
    let _ = std::fs::remove_dir_all(&dir);
}
