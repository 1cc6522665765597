//! `mapless monitor` as a process beside a cluster it did not start (what the compose cluster's
//! `monitor` service runs; deploy/smoke.sh drills it there with TLS and tokens): episodes
//! reported over `StatsService` land in `episodes.csv`, a malformed one is refused and not
//! stored, the replay's `/metrics` (behind a token) gives the env steps, a `/metrics` that
//! refuses the token is a warning once, the learner's published
//! policy is copied and evaluated while it runs, and SIGTERM ends it with curves, a final
//! evaluation and `summary.json`.

use std::io::{Read, Write};
use std::net::TcpListener;
use std::path::{Path, PathBuf};
use std::process::{Child, Command, Stdio};
use std::time::{Duration, Instant};

use mapless_proto::v1::stats_service_client::StatsServiceClient;
use mapless_proto::v1::{EpisodeStats, ProtocolVersion};

fn free_port() -> u16 {
    TcpListener::bind("127.0.0.1:0").unwrap().local_addr().unwrap().port()
}

/// A stand-in for a `/metrics` (the replay's two gauges): 401 without the token.
fn fake_metrics(token: &'static str) -> String {
    let l = TcpListener::bind("127.0.0.1:0").unwrap();
    let addr = l.local_addr().unwrap().to_string();
    std::thread::spawn(move || {
        for c in l.incoming() {
            let Ok(mut c) = c else { continue };
            let mut req = String::new();
            let mut buf = [0u8; 1024];
            while !req.ends_with("\r\n\r\n") {
                match c.read(&mut buf) {
                    Ok(0) | Err(_) => break,
                    Ok(n) => req.push_str(&String::from_utf8_lossy(&buf[..n])),
                }
            }
            let answer = if req.contains(&format!("Authorization: Bearer {token}\r\n")) {
                "HTTP/1.1 200 OK\r\n\r\n# TYPE replay_size gauge\nreplay_size{table=\"transitions\"} 4000\nreplay_inserts_total{table=\"transitions\"} 123456\n# EOF\n"
            } else {
                "HTTP/1.1 401 Unauthorized\r\ncontent-length: 0\r\n\r\n"
            };
            let _ = c.write_all(answer.as_bytes());
        }
    });
    addr
}

fn episode(actor: &str, id: u64, ret: f64) -> EpisodeStats {
    EpisodeStats {
        protocol_version: ProtocolVersion::V1 as i32,
        actor_id: actor.into(),
        episode_id: id,
        policy_version: 3,
        episode_return: ret,
        steps: 1000,
        truncated: true,
        eqs: 100.0,
        ees: 2.0,
        distance_m: 50.0,
        map: "env1".into(),
        ..EpisodeStats::default()
    }
}

fn wait_until(what: &str, limit: Duration, mut ok: impl FnMut() -> bool) {
    let t = Instant::now();
    while !ok() {
        assert!(t.elapsed() < limit, "timed out after {limit:?} waiting for {what}");
        std::thread::sleep(Duration::from_millis(100));
    }
}

fn rows(run: &Path) -> Vec<csv::StringRecord> {
    csv::Reader::from_path(run.join("episodes.csv")).map(|mut r| r.records().filter_map(Result::ok).collect()).unwrap_or_default()
}

struct Killed(Child);
impl Drop for Killed {
    fn drop(&mut self) {
        let _ = self.0.kill();
        let _ = self.0.wait();
    }
}

#[test]
fn the_monitor_writes_the_run_folder_of_a_cluster_it_did_not_start() {
    let root = tempfile::tempdir().unwrap();
    let (dir, run) = (root.path(), root.path().join("run"));
    let policy = PathBuf::from(env!("CARGO_MANIFEST_DIR")).join("../policies/env1-sac/policy.safetensors");
    std::fs::create_dir_all(dir.join("train")).unwrap();
    std::fs::copy(&policy, dir.join("train/policy.safetensors")).unwrap();
    std::fs::write(dir.join("metrics-token"), "m3trics\n").unwrap();
    let config = dir.join("monitor.yaml");
    // The learner's: a /metrics that wants another token, refused on every scrape, told once.
    let (replay_metrics, learner_metrics) = (fake_metrics("m3trics"), fake_metrics("another"));
    let exe = env!("CARGO_BIN_EXE_mapless");
    // A port free a moment ago may be taken before the monitor binds it (by another test's
    // listener): the monitor then exits, saying so, and the test tries another port.
    let (mut monitor, addr) = 'started: {
        for _ in 0..5 {
            let port = free_port();
            std::fs::write(
                &config,
                format!(
                    "preset: env1-sac\nset: [eval.episodes=3, eval.every_minutes=0.005, eval.progress_episodes=1]\nrun: {}\nstats_listen: 127.0.0.1:{port}\n\
                     policy_file: {}\nreplay_metrics: {replay_metrics}\nlearner_metrics: {learner_metrics}\nmetrics_token_file: {}\n",
                    run.display(),
                    dir.join("train/policy.safetensors").display(),
                    dir.join("metrics-token").display()
                ),
            )
            .unwrap();
            let mut monitor = Killed(Command::new(exe).args(["monitor", "--config"]).arg(&config).env("RUST_LOG", "info").stdout(Stdio::null()).stderr(Stdio::piped()).spawn().unwrap());
            let addr = format!("127.0.0.1:{port}");
            let exited = |m: &mut Killed| m.0.try_wait().unwrap().is_some();
            let mut serving = false;
            wait_until("the monitor's health probe says SERVING (or the monitor exits)", Duration::from_secs(90), || {
                serving = Command::new(exe).args(["monitor", "health", &addr]).stdout(Stdio::null()).stderr(Stdio::null()).status().is_ok_and(|s| s.success());
                serving || exited(&mut monitor)
            });
            // The one that answered may be whoever took the port: the monitor must still run.
            std::thread::sleep(Duration::from_millis(500));
            if serving && !exited(&mut monitor) {
                break 'started (monitor, addr);
            }
            let mut log = String::new();
            monitor.0.stderr.take().unwrap().read_to_string(&mut log).unwrap();
            assert!(log.to_lowercase().contains("address already in use"), "the monitor exited on start:\n{log}");
        }
        panic!("five ports in a row were taken before the monitor bound them");
    };

    let rt = tokio::runtime::Builder::new_current_thread().enable_all().build().unwrap();
    rt.block_on(async {
        // Three actors, 20 episodes each, over one Report stream each (as an actor's reporter).
        for a in 0..3u64 {
            let (tx, rx) = tokio::sync::mpsc::channel(64);
            let reporter = tokio::spawn(mapless_net::stats::report(format!("http://{addr}").into(), rx));
            for k in 1..=20 {
                tx.send(episode(&format!("actor-{a}-1-1"), k, 300.0 + k as f64)).await.unwrap();
            }
            drop(tx);
            reporter.await.unwrap();
        }
        // A malformed record is refused (INVALID_ARGUMENT) and nothing of it is stored.
        let mut client = StatsServiceClient::connect(format!("http://{addr}")).await.unwrap();
        let bad = episode("actor-9-1-1", 1, f64::NAN);
        let status = client.report(tokio_stream::iter(vec![bad])).await.expect_err("a NaN return is refused");
        assert_eq!(status.code(), tonic::Code::InvalidArgument, "{status:?}");
    });
    wait_until("60 episodes in episodes.csv", Duration::from_secs(120), || rows(&run).len() >= 60);
    let stored = rows(&run);
    assert_eq!(stored.len(), 60, "exactly the valid episodes");
    assert!(stored.iter().all(|r| &r[2] != "actor-9-1-1"), "nothing of the refused record");
    assert!(run.join("policy.safetensors").exists(), "the learner's policy copied into the run folder");
    wait_until("an evaluation while it runs (evals.csv)", Duration::from_secs(180), || std::fs::read_to_string(run.join("evals.csv")).is_ok_and(|t| t.contains("progress")));

    nix::sys::signal::kill(nix::unistd::Pid::from_raw(monitor.0.id() as i32), nix::sys::signal::Signal::SIGTERM).unwrap();
    let t = Instant::now();
    let status = loop {
        if let Some(s) = monitor.0.try_wait().unwrap() {
            break s;
        }
        assert!(t.elapsed() < Duration::from_secs(60), "the monitor did not stop on SIGTERM");
        std::thread::sleep(Duration::from_millis(100));
    };
    let mut log = String::new();
    monitor.0.stderr.take().unwrap().read_to_string(&mut log).unwrap();
    assert!(status.success(), "{status:?}\n{log}");
    assert!(log.contains("invalid episode record"), "the refusal is logged:\n{log}");
    assert_eq!(log.matches("cannot read /metrics").count(), 1, "a refused scrape is a warning once, not every second:\n{log}");
    assert!(log.contains("401"), "the warning says why:\n{log}");

    let summary: serde_json::Value = serde_json::from_str(&std::fs::read_to_string(run.join("summary.json")).unwrap()).unwrap();
    assert_eq!(summary["episodes"], 60);
    assert_eq!(summary["env_steps"], 123_456, "env steps from the replay's /metrics, read with the token");
    assert_eq!(summary["updates"], 0, "the learner's /metrics refused the token: no figures from it");
    assert_eq!(summary["preset"], "env1-sac");
    assert!(summary["stopped_because"].as_str().unwrap().starts_with("interrupted"), "{}", summary["stopped_because"]);
    let eval = &summary["evaluation"];
    assert_eq!(eval["episodes"].as_array().map(Vec::len), Some(3), "the final evaluation: eval.episodes");
    assert_eq!(eval["map"], "env1");
    assert!((summary["average_return"].as_f64().unwrap() - 311.5).abs() < 1e-9, "order-50 average of the last 50 returns (311..320, then 301..320 twice): {}", summary["average_return"]);
    for f in ["curves.png", "eval/episode-1.png", "config.yaml"] {
        assert!(run.join(f).exists(), "{f}");
    }
    assert_eq!(std::fs::read(run.join("policy.safetensors")).unwrap(), std::fs::read(&policy).unwrap());
}
