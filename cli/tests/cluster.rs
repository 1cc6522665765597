//! The local cluster end to end, as real processes: `mapless train` starts the replay, the
//! learner and two actors on a tiny budget. Checked: transitions from every actor reach the
//! replay; the learner's policy version advances at the actors (their rows carry newer
//! versions); `kill -9` of an actor leaves training running and the supervisor restarts it;
//! an interrupted run resumed with `--resume` continues from its checkpoint and its curve; the
//! best policy that the criterion's evaluations judged is kept, and the run keeps it or the
//! learner's last, as their scores on the same starts say.

#[path = "../../tests/common/workspace_build.rs"]
mod workspace_build;

use std::collections::BTreeSet;
use std::path::{Path, PathBuf};
use std::process::{Child, Command, Stdio};
use std::time::{Duration, Instant};

use mapless_proto::v1::replay_service_client::ReplayServiceClient;
use mapless_proto::v1::{ProtocolVersion, ServerInfoRequest, ServerInfoResponse};

/// `mapless`, with `mapless-actor`, `mapless-replay` and `mapless-learner` beside it, brought up
/// to date once per test binary.
fn mapless() -> PathBuf {
    let exe = PathBuf::from(env!("CARGO_BIN_EXE_mapless"));
    workspace_build::build_workspace_once(exe.parent().unwrap());
    exe
}

/// Settings that make a run small and quick: narrow networks, tiny batches, short episodes,
/// frequent publishing and checkpoints.
const TINY: &[&str] = &[
    "learner.hidden_width=16",
    "learner.batch_size=16",
    "replay.capacity=20000",
    "replay.rate_limiter.min_size_to_sample=100",
    // With a ratio, as the presets run: while the limiter blocks inserts every writer must
    // still get through (the shm ingest once starved all but one; replay/src/shm.rs).
    "replay.rate_limiter.samples_per_insert=4",
    "replay.rate_limiter.error_buffer=5000",
    "actors.warmup_steps=50",
    "actors.batch_rows=16",
    "max_steps=60",
    "driver.publish_every=5",
    "driver.checkpoint_every=100",
    "driver.metrics_every=50",
    "eval.episodes=1",
    "eval.every_minutes=0.1",
    "eval.progress_episodes=1",
    "stop.average_return=null",
    "stop.average_steps=null",
];

/// The `mapless train` process; dropping it (a failed assertion) stops it and its cluster.
struct Train(Child);

impl Drop for Train {
    fn drop(&mut self) {
        if let Ok(None) = self.0.try_wait() {
            let _ = Command::new("kill").args(["-TERM", &self.0.id().to_string()]).status();
            let end = Instant::now() + Duration::from_secs(90);
            while Instant::now() < end && matches!(self.0.try_wait(), Ok(None)) {
                std::thread::sleep(Duration::from_millis(100));
            }
            let _ = self.0.kill();
            let _ = self.0.wait();
        }
    }
}

impl std::ops::Deref for Train {
    type Target = Child;
    fn deref(&self) -> &Child {
        &self.0
    }
}

impl std::ops::DerefMut for Train {
    fn deref_mut(&mut self) -> &mut Child {
        &mut self.0
    }
}

fn train(run: &Path, extra: &[&str]) -> Train {
    let mut cmd = Command::new(mapless());
    cmd.arg("train");
    for s in TINY {
        cmd.args(["--set", s]);
    }
    // After TINY: a `--set` among `extra` overrides it.
    cmd.args(extra).env_remove("RUST_LOG").stdin(Stdio::null()).stdout(Stdio::null()).stderr(std::fs::File::create(run.with_extension("stderr")).unwrap());
    Train(cmd.spawn().expect("mapless train starts"))
}

fn wait_for<T>(what: &str, timeout: Duration, child: &mut Child, run: &Path, mut f: impl FnMut() -> Option<T>) -> T {
    let end = Instant::now() + timeout;
    loop {
        if let Some(v) = f() {
            return v;
        }
        if let Ok(Some(st)) = child.try_wait() {
            panic!("mapless train exited ({st}) while waiting for {what}; its output:\n{}", std::fs::read_to_string(run.with_extension("stderr")).unwrap_or_default());
        }
        assert!(Instant::now() < end, "timed out waiting for {what}; output:\n{}", std::fs::read_to_string(run.with_extension("stderr")).unwrap_or_default());
        std::thread::sleep(Duration::from_millis(250));
    }
}

fn wait_for_or_none<T>(timeout: Duration, child: &mut Child, mut f: impl FnMut() -> Option<T>) -> Option<T> {
    let end = Instant::now() + timeout;
    while Instant::now() < end {
        if let Some(v) = f() {
            return Some(v);
        }
        if let Ok(Some(_)) = child.try_wait() {
            return None;
        }
        std::thread::sleep(Duration::from_millis(250));
    }
    None
}

fn json(path: &Path) -> Option<serde_json::Value> {
    serde_json::from_str(&std::fs::read_to_string(path).ok()?).ok()
}

fn server_info(rt: &tokio::runtime::Runtime, uri: &str) -> Option<ServerInfoResponse> {
    rt.block_on(async {
        let mut c = ReplayServiceClient::connect(uri.to_owned()).await.ok()?;
        c.server_info(ServerInfoRequest { protocol_version: ProtocolVersion::V1 as i32 }).await.ok().map(|r| r.into_inner())
    })
}

fn sigterm(pid: u32) {
    assert!(Command::new("kill").args(["-TERM", &pid.to_string()]).status().unwrap().success());
}

fn wait_exit(child: &mut Child, timeout: Duration) -> std::process::ExitStatus {
    let end = Instant::now() + timeout;
    loop {
        if let Some(st) = child.try_wait().unwrap() {
            return st;
        }
        if Instant::now() > end {
            let _ = child.kill();
            panic!("mapless train did not stop within {timeout:?}");
        }
        std::thread::sleep(Duration::from_millis(100));
    }
}

#[test]
fn local_cluster_trains_survives_an_actor_kill_and_resumes() {
    let dir = tempfile::tempdir().unwrap();
    let run = dir.path().join("tiny");
    let rt = tokio::runtime::Builder::new_current_thread().enable_all().build().unwrap();
    let run_arg = run.to_string_lossy().into_owned();
    // The test stops the run itself: a tiny run can reach the preset's 10,000 episodes in
    // half a minute, before the kill-and-restart and a progress evaluation have been seen.
    // The criterion is evaluated whenever its averages hold (here: always) and is never met,
    // so the run keeps the best policy those evaluations judged (`stop.keep_best`).
    let never_met = ["stop.average_steps=1", "stop.min_episodes=null", "stop.eval_eqs=1e9", "stop.eval_episodes=3"].map(|s| ["--set", s]).concat();
    let args = [&["--preset", "env1-sac", "--actors", "2", "--vehicles", "2", "--episodes", "10000000", "--run", &run_arg][..], &never_met].concat();
    let mut child = train(&run, &args);

    let endpoints = wait_for("endpoints.json", Duration::from_secs(400), &mut child, &run, || json(&run.join("endpoints.json")));
    let replay_uri = endpoints["replay"].as_str().unwrap().to_owned();

    // Every actor's transitions reach the replay, and their rows carry advancing policy
    // versions (the learner publishes; the actors follow).
    let mut last = None;
    let info = wait_for_or_none(Duration::from_secs(480), &mut child, || {
        let i = server_info(&rt, &replay_uri);
        let ok = i.as_ref().is_some_and(|i| i.actors.iter().filter(|a| a.rows > 0 && a.last_policy_version >= 3).count() >= 2);
        last = Some(i.clone());
        if ok { i } else { None }
    });
    let info = info
        .unwrap_or_else(|| panic!("no rows from 2 actors with policy version >= 3; last server info: {last:?}; output: {}", std::fs::read_to_string(run.with_extension("stderr")).unwrap_or_default()));
    let first_ids: BTreeSet<String> = info.actors.iter().map(|a| a.actor_id.clone()).collect();
    assert!(first_ids.len() >= 2, "at least two actor incarnations wrote: {first_ids:?}");

    // kill -9 one actor: the supervisor restarts it (a new incarnation writes rows), and the
    // learner keeps updating.
    let pids = json(&run.join("pids.json")).unwrap();
    let victim = pids["actors"][0].as_u64().unwrap();
    let updates_before = server_info(&rt, &replay_uri).unwrap().samples_total;
    assert!(Command::new("kill").args(["-9", &victim.to_string()]).status().unwrap().success());
    let mut last = None;
    let found = wait_for_or_none(Duration::from_secs(400), &mut child, || {
        let i = server_info(&rt, &replay_uri)?;
        let new_writer = i.actors.iter().any(|a| !first_ids.contains(&a.actor_id) && a.rows > 0);
        let done = new_writer && i.samples_total > updates_before;
        last = Some(i);
        done.then_some(())
    });
    assert!(found.is_some(), "no restarted actor wrote rows (first: {first_ids:?}); last server info: {last:?}; pids: {:?}", json(&run.join("pids.json")));
    let pids = json(&run.join("pids.json")).unwrap();
    assert!(pids["restarts"].as_u64().unwrap() >= 1, "{pids}");
    assert_ne!(pids["actors"][0].as_u64().unwrap(), victim);

    // The newest policy is evaluated as the run goes.
    wait_for("a progress evaluation in evals.csv", Duration::from_secs(300), &mut child, &run, || {
        let text = std::fs::read_to_string(run.join("evals.csv")).ok()?;
        text.lines().any(|l| l.split(',').nth(1) == Some("progress") && l.split(',').nth(2).and_then(|v| v.parse::<u64>().ok()).is_some_and(|v| v >= 3)).then_some(())
    });

    // ... and the criterion's: the best policy it judged so far is kept beside the newest.
    wait_for("a criteria evaluation in evals.csv", Duration::from_secs(300), &mut child, &run, || {
        let text = std::fs::read_to_string(run.join("evals.csv")).ok()?;
        text.lines().any(|l| l.split(',').nth(1) == Some("criteria")).then_some(())
    });
    let best = json(&run.join("policy-best.json")).expect("policy-best.json");
    assert_eq!(best["episodes"].as_u64(), Some(3), "{best}");
    assert!(run.join("policy-best.safetensors").exists());

    // Stop (as Ctrl-C would): a final checkpoint, the curve, a summary.
    std::thread::sleep(Duration::from_secs(3));
    sigterm(child.id());
    let st = wait_exit(&mut child, Duration::from_secs(400));
    assert!(st.success(), "train exited with {st}: {}", std::fs::read_to_string(run.with_extension("stderr")).unwrap_or_default());
    let first = json(&run.join("summary.json")).expect("summary.json");
    let first_updates = first["updates"].as_u64().unwrap();
    let first_episodes = first["episodes"].as_u64().unwrap();
    assert!(first_updates > 0 && first_episodes > 0, "{first}");
    assert!(first["actor_restarts"].as_u64().unwrap() >= 1);
    assert!(run.join("checkpoints").join("LATEST").exists(), "a checkpoint was written");
    assert!(run.join("curves.png").exists() && run.join("policy.safetensors").exists());
    assert!(run.join("eval").join("episode-1.png").exists(), "evaluation trajectory drawn");
    let evals = std::fs::read_to_string(run.join("evals.csv")).unwrap();
    let kinds: Vec<&str> = evals.lines().filter_map(|l| l.split(',').nth(1)).collect();
    assert_eq!(kinds[kinds.len() - 3..], ["best", "last", "final"], "the best policy and the learner's last are scored on the same starts, then the kept one is evaluated: {evals}");
    // The run's policy is the best one evaluated or the learner's last, as summary.json says.
    let kept = first["kept_policy"].as_str().expect("summary.json says which policy the run kept");
    let read = |f: &str| std::fs::read(run.join(f)).unwrap();
    if kept.starts_with("the best one evaluated while training") {
        assert_eq!(read("policy.safetensors"), read("policy-best.safetensors"), "{kept}");
        assert!(run.join("policy-last.safetensors").exists(), "{kept}");
    } else {
        assert!(kept.starts_with("the learner's last (v"), "{kept}");
        assert!(!run.join("policy-last.safetensors").exists(), "{kept}");
    }
    // Every log line of every process names the run, the role and (actors) the actor id.
    for (file, role) in [("replay.log", "replay"), ("learner.log", "learner"), ("actor-0.log", "actor"), ("actor-1.log", "actor")] {
        let text = std::fs::read_to_string(run.join("logs").join(file)).unwrap();
        let lines: Vec<&str> = text.lines().filter(|l| l.starts_with("20")).collect();
        assert!(!lines.is_empty(), "{file} has log lines");
        for l in lines {
            assert!(l.contains(" run=tiny") && l.contains(&format!(" role={role}")), "{file}: {l}");
            assert!(role != "actor" || l.contains(" actor_id=actor-"), "{file}: {l}");
        }
    }

    // Resume: the learner continues from its checkpoint (updates keep counting up), episodes
    // continue the same curve.
    let mut child = train(&run, &["--resume", &run_arg, "--episodes", &(first_episodes + 20).to_string()]);
    let st = wait_exit(&mut child, Duration::from_secs(900));
    assert!(st.success(), "resumed train exited with {st}: {}", std::fs::read_to_string(run.with_extension("stderr")).unwrap_or_default());
    let second = json(&run.join("summary.json")).unwrap();
    assert!(second["updates"].as_u64().unwrap() > first_updates, "updates continue from the checkpoint: {first} then {second}");
    assert!(second["episodes"].as_u64().unwrap() >= first_episodes + 20, "{second}");
    let learner_log = std::fs::read_to_string(run.join("logs").join("learner.log")).unwrap();
    assert!(learner_log.contains("resumed from checkpoint"), "learner log: {learner_log}");
    let csv = std::fs::read_to_string(run.join("episodes.csv")).unwrap();
    let numbers: Vec<u64> = csv.lines().skip(1).map(|l| l.split(',').next().unwrap().parse().unwrap()).collect();
    assert_eq!(numbers, (1..=numbers.len() as u64).collect::<Vec<_>>(), "one curve, numbered without gaps");
}

/// `mapless reproduce` on a slice of the matrix (one experiment, two seeds, two at once): each
/// seed trains and is evaluated on env3; the page's cells are the means of what the runs
/// wrote; a second call finds nothing to do; an interrupted run is resumed, not restarted.
#[test]
fn reproduce_trains_evaluates_on_env3_resumes_and_writes_the_page() {
    let dir = tempfile::tempdir().unwrap();
    let (runs, out) = (dir.path().join("runs"), dir.path().join("results"));
    let reproduce = || {
        let mut cmd = Command::new(mapless());
        cmd.args(["reproduce", "--only", "env1-td3", "--seeds", "2", "--minutes", "0.15", "--jobs", "2"]).arg("--runs").arg(&runs).arg("--out").arg(&out);
        for s in TINY {
            cmd.args(["--set", s]);
        }
        let o = cmd.env_remove("RUST_LOG").stdin(Stdio::null()).output().expect("mapless reproduce runs");
        let stderr = String::from_utf8_lossy(&o.stderr).into_owned();
        assert!(o.status.success(), "mapless reproduce failed:\n{stderr}");
        stderr
    };
    let first = reproduce();
    assert!(first.contains("2 to do (0 done)"), "{first}");
    let mut eqs = Vec::new();
    for k in 1..=2u64 {
        let run = runs.join("env1-td3").join(format!("seed-{k}"));
        let s = json(&run.join("summary.json")).expect("a finished run");
        assert!(s["stopped_because"].as_str().unwrap().contains("minutes"), "{s}");
        let cfg: serde_yaml::Value = serde_yaml::from_str(&std::fs::read_to_string(run.join("config.yaml")).unwrap()).unwrap();
        assert_eq!(cfg["seed"].as_u64(), Some(k), "each seed is its own run");
        assert_eq!(cfg["learner"]["hidden_width"].as_u64(), Some(16), "--set reaches the runs");
        let e3 = json(&run.join("reproduce-env3").join("eval.json")).expect("an env3 evaluation");
        assert_eq!(e3["map"], "env3");
        let eps = e3["episodes"].as_array().unwrap();
        assert_eq!(eps.len(), 10);
        assert!(eps.iter().all(|e| e["steps"].as_u64().unwrap() <= 3000 && (e["collided"] == true || e["steps"] == 3000)), "env3 runs to a collision or 3,000 steps");
        eqs.push(s["evaluation"]["mean_eqs"].as_f64().unwrap());
    }
    let page = std::fs::read_to_string(out.join("README.md")).unwrap();
    let (m, sd) = ((eqs[0] + eqs[1]) / 2.0, (eqs[0] - eqs[1]).abs() / 2f64.sqrt());
    let cell = format!("| 113 / {m:.1} ± {sd:.1} |");
    assert!(page.contains("## Table III") && page.contains(&cell), "the EQS cell {cell} is the mean ± std of the runs' evaluations:\n{page}");
    assert!(page.contains("| TD3-env1 | 1533 / ") && !page.contains("## Table IV"), "{page}");
    for f in ["fig08-09-env1-td3.png", "fig10-env1-td3.png", "fig14-env3-env1-td3.png", "results.json"] {
        assert!(out.join(f).exists(), "{f}");
    }
    assert!(reproduce().contains("0 to do (2 done)"), "a second call trains nothing");
    let o = Command::new(mapless()).args(["reproduce", "--report-only", "--set", "seed=3"]).arg("--runs").arg(&runs).arg("--out").arg(&out).output().unwrap();
    assert!(!o.status.success() && String::from_utf8_lossy(&o.stderr).contains("--seeds"), "a seed override would make every seed the same run");

    // A run that was interrupted is resumed (its log gets a second session).
    let run2 = runs.join("env1-td3").join("seed-2");
    let mut s2 = json(&run2.join("summary.json")).unwrap();
    s2["stopped_because"] = serde_json::json!("interrupted (Ctrl-C or SIGTERM)");
    std::fs::write(run2.join("summary.json"), s2.to_string()).unwrap();
    let third = reproduce();
    assert!(third.contains("1 to do (1 done)"), "{third}");
    assert!(!json(&run2.join("summary.json")).unwrap()["stopped_because"].as_str().unwrap().starts_with("interrupted"));
    let log = std::fs::read_to_string(runs.join("env1-td3").join("seed-2.log")).unwrap();
    assert!(log.contains("=== mapless reproduce: resuming"), "the second session resumed the run:\n{log}");
}
