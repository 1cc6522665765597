//! `mapless train`: a whole actor–learner cluster on this machine, supervised.
//!
//! ```text
//!   mapless train ─┬─ mapless-replay  (run/replay.yaml; persists to run/replay/)
//!   (supervisor,   ├─ mapless-learner (run/learner.yaml; checkpoints, TensorBoard, policy file)
//!    stats         └─ mapless-actor × N (run/actor.yaml) ──iceoryx2──► replay
//!    collector)         ▲ weights (gRPC) ── learner        └─ episodes (gRPC) ──► supervisor
//! ```
//!
//! The supervisor restarts a child that dies (actors at once; the learner from its newest
//! checkpoint; the replay from its log), prints a progress line, writes `episodes.csv` and
//! `curves.png` as the run goes, stops on the preset's criteria (order-W moving averages of
//! return and steps, or K episodes, or a time limit) or Ctrl-C, then stops the children in
//! order (actors, learner with a final checkpoint, replay), evaluates the final policy and
//! writes `summary.json`.

use std::fs;
use std::io::IsTerminal;
use std::net::SocketAddr;
use std::path::Path;
use std::sync::atomic::{AtomicBool, Ordering};
use std::sync::mpsc as std_mpsc;
use std::sync::{Arc, Mutex};
use std::time::{Duration, Instant};

use anyhow::{Context, Result, bail};
use mapless_actor::run::{ActorConfig, ExplorationSettings, ReplayTarget};
use mapless_learner_config::{LearnerConfig, LearnerEvent, LearnerServiceConfig};
use mapless_net::shm::ShmConfig;
use mapless_plots::{CurvePoint, CurveStyle, training_curves_png};
use mapless_proto::v1::replay_service_client::ReplayServiceClient;
use mapless_proto::v1::{EpisodeStats, ProtocolVersion, ServerInfoRequest};
use mapless_replay::server::ServerConfig;
use serde::{Deserialize, Serialize};

use crate::eval;
use crate::protocol;

mod children;
mod config;
pub(crate) mod episodes;

pub(crate) use children::*;
pub(crate) use config::*;
pub(crate) use episodes::*;

/// An evaluation of the newest policy while training, on its own thread.
struct ProgressEval {
    wall_s: f64,
    handle: std::thread::JoinHandle<Result<eval::EvalSummary>>,
}

impl ProgressEval {
    /// Waits for it and records it in `evals.csv`; a failed or panicked evaluation is logged.
    fn finish(self, run: &Path) -> Result<()> {
        match self.handle.join() {
            Ok(Ok(s)) => {
                tracing::info!(policy_version = s.policy_version, "evaluation while training: {}", s.one_line());
                append_eval(run, self.wall_s, "progress", &s)?;
            }
            Ok(Err(e)) => tracing::warn!(error = %format!("{e:#}"), "evaluation while training failed"),
            Err(_) => tracing::warn!("evaluation while training panicked"),
        }
        Ok(())
    }
}

/// A row of `evals.csv`: one per evaluation (while training and final).
#[derive(Serialize)]
struct EvalLine<'a> {
    wall_s: f64,
    kind: &'a str,
    policy_version: u64,
    map: &'a str,
    episodes: usize,
    mean_steps: f64,
    mean_return: f64,
    mean_eqs: f64,
    mean_ees: f64,
    mean_distance_m: f64,
    collisions: u32,
}

fn append_eval(run: &Path, wall_s: f64, kind: &str, s: &eval::EvalSummary) -> Result<()> {
    let path = run.join("evals.csv");
    // As episodes.csv: a line a crash tore is cut, the header goes into an empty file only.
    truncate_torn_line(&path)?;
    let empty = fs::metadata(&path).map_or(true, |m| m.len() == 0);
    let f = fs::OpenOptions::new().create(true).append(true).open(&path).with_context(|| format!("opening {}", path.display()))?;
    let mut w = csv::WriterBuilder::new().has_headers(empty).from_writer(f);
    w.serialize(EvalLine {
        wall_s,
        kind,
        policy_version: s.policy_version,
        map: &s.map,
        episodes: s.episodes.len(),
        mean_steps: s.mean_steps,
        mean_return: s.mean_return,
        mean_eqs: s.mean_eqs,
        mean_ees: s.mean_ees,
        mean_distance_m: s.mean_distance_m,
        collisions: s.collisions,
    })?;
    w.flush()?;
    Ok(())
}

// ---------------------------------------------------------------------------------------------
// The run
// ---------------------------------------------------------------------------------------------

/// The newest `LearnerEvent::Status` the learner printed (what the progress line shows).
#[derive(Default, Clone, Debug)]
struct LearnerStatus {
    updates: u64,
    updates_per_s: f64,
    weights_version: u64,
}

/// What `summary.json` holds (`mapless reproduce` reads it back).
#[derive(Serialize, Deserialize, Debug)]
pub struct Summary {
    pub run: String,
    pub preset: String,
    /// Starts with [`INTERRUPTED`] when Ctrl-C or SIGTERM stopped the run.
    pub stopped_because: String,
    pub wall_s: f64,
    pub episodes: u64,
    pub env_steps: u64,
    pub updates: u64,
    pub weights_version: u64,
    /// NaN (written as null) before the first episode.
    #[serde(deserialize_with = "nan_if_null")]
    pub average_return: f64,
    #[serde(deserialize_with = "nan_if_null")]
    pub average_steps: f64,
    pub window: usize,
    pub criteria_met_at: Option<Milestone>,
    /// The evaluation that met `stop.eval_*` (its policy is the run's `policy.safetensors`).
    pub criteria_evaluation: Option<eval::EvalSummary>,
    /// First episode from which the moving averages stayed within `stop.convergence_tolerance`
    /// of their final values (`protocol::convergence_episode`).
    pub convergence_episode: Option<u64>,
    pub actor_restarts: u32,
    /// Throughput after start-up (from 20 s, or a third of a time-limited run, to the stop).
    pub steady: Option<Rates>,
    pub evaluation: Option<eval::EvalSummary>,
}

/// serde_json writes a non-finite f64 as null; read it back as NaN.
fn nan_if_null<'de, D: serde::Deserializer<'de>>(d: D) -> std::result::Result<f64, D::Error> {
    Ok(Option::<f64>::deserialize(d)?.unwrap_or(f64::NAN))
}

/// Writes `path` whole or not at all (a temporary file beside it, then a rename), so a run
/// killed mid-write leaves the old file, never a torn one.
pub fn write_atomic(path: &Path, contents: &str) -> Result<()> {
    mapless_proto::weights_file::write_file_atomically(path, contents.as_bytes()).with_context(|| format!("writing {}", path.display()))
}

/// How `Summary::stopped_because` begins for a run that Ctrl-C or SIGTERM stopped.
pub const INTERRUPTED: &str = "interrupted";

#[derive(Serialize, Deserialize, Debug)]
pub struct Rates {
    pub from_s: f64,
    pub seconds: f64,
    pub env_steps_per_s: f64,
    pub updates_per_s: f64,
}

#[derive(Serialize, Deserialize, Clone, Debug)]
pub struct Milestone {
    pub wall_s: f64,
    pub episode: u64,
    pub env_steps: u64,
    pub updates: u64,
}

fn fmt_int(n: u64) -> String {
    let s = n.to_string();
    let mut out = String::new();
    for (i, c) in s.chars().enumerate() {
        if i > 0 && (s.len() - i).is_multiple_of(3) {
            out.push(',');
        }
        out.push(c);
    }
    out
}

/// Runs `mapless train`.
pub fn train(args: &TrainArgs, log_json: bool) -> Result<()> {
    let (cfg, run, resuming) = load_config(args)?;
    if args.print_config {
        print!("{}", serde_yaml::to_string(&cfg)?);
        return Ok(());
    }
    if !resuming && run.join("config.yaml").exists() {
        if !args.force {
            bail!("{} already holds a run; continue it with `--resume {}`, pick another `--run`, or pass --force to start over", run.display(), run.display());
        }
        fs::remove_dir_all(&run).with_context(|| format!("removing {}", run.display()))?;
    }
    let logs = run.join("logs");
    fs::create_dir_all(&logs)?;
    write_atomic(&run.join("config.yaml"), &serde_yaml::to_string(&cfg)?)?;
    let run_name = run.file_name().map(|s| s.to_string_lossy().into_owned()).unwrap_or_else(|| "run".into());
    mapless_net::logging::identify(&[("run", &run_name), ("role", "supervisor")]);
    let run_abs = fs::canonicalize(&run)?;

    // Stop flag: Ctrl-C / SIGTERM.
    let stop = Arc::new(AtomicBool::new(false));
    let rt = tokio::runtime::Builder::new_multi_thread().worker_threads(1).thread_name("train-io").enable_all().build()?;
    {
        let stop = Arc::clone(&stop);
        rt.spawn(async move {
            crate::signals::termination().await;
            stop.store(true, Ordering::Relaxed);
        });
    }

    // Ports: each service binds port 0 and says what it got (no bind-and-release race); the
    // configs are then rewritten with those ports so that a restarted child comes back on the
    // same addresses.
    let any_port = SocketAddr::from(([127, 0, 0, 1], 0));
    // One iceoryx2 domain per run folder: runs on one host stay apart, and a restarted
    // replay or actor cleans what a killed predecessor of *this* run left.
    let domain = format!("mpl{:08x}_", crc32fast::hash(run_abs.to_string_lossy().as_bytes()));
    let shm = ShmConfig { domain: domain.clone(), ..ShmConfig::for_table(&cfg.replay.name) };

    let learner_bin = sibling("mapless-learner")?.to_string_lossy().into_owned();
    let replay_bin = sibling("mapless-replay")?.to_string_lossy().into_owned();
    let actor_bin = sibling("mapless-actor")?.to_string_lossy().into_owned();
    let p = |x: &Path| x.to_string_lossy().into_owned();
    let (line_tx, line_rx) = std_mpsc::channel::<(String, String)>();

    eprintln!("mapless train: {} — {} ({} actors × {} vehicles); run folder {}", cfg.name, cfg.description, cfg.actors.count, cfg.actors.vehicles, run.display());
    eprintln!("  logs: {}/  TensorBoard: tensorboard --logdir {}/tensorboard", logs.display(), run.display());
    // `mapless --log-json train` makes every process log JSON lines.
    let json_flag = |mut v: Vec<String>| {
        if log_json {
            v.push("--log-json".into());
        }
        v
    };

    let mut server = ServerConfig { listen: any_port, metrics_listen: Some(any_port), table: cfg.replay.clone(), shm: Some(shm.clone()), seed: cfg.seed, ..ServerConfig::default() };
    if cfg.replay_persistence {
        server.persistence.dir = Some(run_abs.join("replay"));
    }
    fs::write(run.join("replay.yaml"), serde_yaml::to_string(&server)?)?;
    let replay_cmd = json_flag(vec![replay_bin, "--config".into(), p(&run_abs.join("replay.yaml"))]);
    let (mut replay, replay_addr, replay_metrics) = start_service("replay", replay_cmd, logs.join("replay.log"), "listening on ", &line_rx, &line_tx)?;
    // A restarted replay comes back on the same ports.
    server.listen = replay_addr;
    server.metrics_listen = Some(replay_metrics);
    fs::write(run.join("replay.yaml"), serde_yaml::to_string(&server)?)?;

    let mut learner_cfg = LearnerServiceConfig {
        learner: LearnerConfig { seed: cfg.seed, ..cfg.learner.clone() },
        driver: cfg.driver.clone(),
        obs_dim: cfg.env.obs_dim(),
        act_dim: 2,
        replay: format!("http://{replay_addr}"),
        weights_listen: any_port,
        checkpoint_dir: run_abs.join("checkpoints"),
        tensorboard_dir: Some(run_abs.join("tensorboard")),
        policy_file: Some(run_abs.join("policy.safetensors")),
        resume: true,
        threads: cfg.threads.learner,
        tls: None,
        auth_token_file: None,
        replay_security: Default::default(),
        metrics_listen: Some(any_port),
    };
    fs::write(run.join("learner.yaml"), serde_yaml::to_string(&learner_cfg)?)?;
    let learner_cmd = json_flag(vec![learner_bin, "--config".into(), p(&run_abs.join("learner.yaml")), "--run".into(), run_name.clone()]);
    let (mut learner, weights_addr, learner_metrics) = start_service("learner", learner_cmd, logs.join("learner.log"), "weights on ", &line_rx, &line_tx)?;
    // A restarted learner comes back on the same ports.
    learner_cfg.weights_listen = weights_addr;
    learner_cfg.metrics_listen = Some(learner_metrics);
    fs::write(run.join("learner.yaml"), serde_yaml::to_string(&learner_cfg)?)?;

    // Stats collector (in this process).
    let stats_listener = rt.block_on(tokio::net::TcpListener::bind("127.0.0.1:0"))?;
    let stats_addr = stats_listener.local_addr()?;
    let (ep_tx, mut ep_rx) = tokio::sync::mpsc::channel::<EpisodeStats>(8192);
    let (collector_stop_tx, collector_stop_rx) = tokio::sync::watch::channel(false);
    rt.spawn(async move {
        if let Err(e) = mapless_net::stats::serve_collector(stats_listener, ep_tx, collector_stop_rx).await {
            tracing::error!(error = %e, "stats collector stopped");
        }
    });

    let actor_cfg = ActorConfig {
        map: cfg.map.clone(),
        env: cfg.env.clone(),
        vehicles: cfg.actors.vehicles,
        exploration: ExplorationSettings { warmup_steps: if resuming { 0 } else { cfg.actors.warmup_steps }, noise: cfg.noise() },
        batch_rows: cfg.actors.batch_rows,
        max_in_flight: 8,
        replay: ReplayTarget::Shm { prefix: shm.prefix.clone(), domain: shm.domain.clone() },
        weights: format!("http://{weights_addr}"),
        stats: Some(format!("http://{stats_addr}")),
        security: Default::default(),
        seed: cfg.seed,
        // Each actor process logs the port it got.
        metrics_listen: Some(SocketAddr::from(([127, 0, 0, 1], 0))),
    };
    fs::write(run.join("actor.yaml"), serde_yaml::to_string(&actor_cfg)?)?;

    let actor_cmd = |i: usize| json_flag(vec![actor_bin.clone(), "--config".into(), p(&run_abs.join("actor.yaml")), "--index".into(), i.to_string(), "--run".into(), run_name.clone()]);
    let mut actors: Vec<Proc> = Vec::new();
    for i in 0..cfg.actors.count {
        actors.push(Proc::spawn(&format!("actor-{i}"), actor_cmd(i), logs.join(format!("actor-{i}.log")), Some(line_tx.clone())).with_context(|| format!("actor {i}"))?);
    }
    fs::write(
        run.join("endpoints.json"),
        serde_json::to_string_pretty(&serde_json::json!({
            "replay": format!("http://{replay_addr}"), "replay_metrics": format!("http://{replay_metrics}/metrics"),
            "weights": format!("http://{weights_addr}"), "learner_metrics": format!("http://{learner_metrics}/metrics"), "stats": format!("http://{stats_addr}"),
            "shm_prefix": shm.prefix, "shm_domain": shm.domain,
        }))?,
    )?;
    write_pids(&run, &replay, &learner, &actors)?;

    // Episodes so far (a resumed run continues its curve).
    let csv_path = run.join("episodes.csv");
    // A crash may have torn the last line: cut it before reading, so what is read is what stays.
    truncate_torn_line(&csv_path)?;
    let (mut rows, bad) = read_episodes(&csv_path);
    if bad > 0 {
        tracing::warn!(bad, "skipped unreadable lines of episodes.csv");
    }
    let offset_s = rows.last().map_or(0.0, |r| r.wall_s);
    let empty = fs::metadata(&csv_path).map_or(true, |m| m.len() == 0);
    let mut csv = episodes_writer(fs::OpenOptions::new().create(true).append(true).open(&csv_path)?, empty);
    let first_episode_this_session = rows.len();

    let learner_status = Arc::new(Mutex::new(LearnerStatus::default()));
    let mut replay_client: Option<ReplayServiceClient<tonic::transport::Channel>> = None;
    let (mut replay_size, mut inserts_total) = (0u64, 0u64);
    let mut env_rate = (Instant::now(), 0u64, 0.0f64);
    let started = Instant::now();
    let mut last_progress = Instant::now() - Duration::from_secs(10);
    let mut last_printed = Instant::now() - Duration::from_secs(10);
    let mut last_picture = Instant::now();
    let mut pictured = rows.len();
    let mut milestone: Option<Milestone> = None;
    let mut stopped_because = format!("{INTERRUPTED} (Ctrl-C or SIGTERM)");
    let tty = std::io::stderr().is_terminal();
    let steady_from = cfg.stop.minutes.map_or(20.0, |m| (m * 20.0).min(20.0));
    let eval_map = cfg.eval.map.clone().unwrap_or_else(|| cfg.map.clone());
    let eval_seed = cfg.seed.wrapping_add(1_000_003);
    // The evaluation running now, if any, and when the last one ended.
    let mut progress_eval: Option<ProgressEval> = None;
    let mut last_progress_eval = Instant::now();
    let mut steady_start: Option<(Instant, u64, u64)> = None;
    // The evaluation of the stop criterion running now (on a copy of the policy it judges).
    // Its milestone is taken when the policy is copied: the point of training it judges.
    let gate_policy = run.join("policy-criteria.safetensors");
    let mut gate_eval: Option<(Milestone, std::thread::JoinHandle<Result<eval::EvalSummary>>)> = None;
    let mut last_gate_eval: Option<Instant> = None;
    let mut criteria_evaluation: Option<eval::EvalSummary> = None;
    let goal = |name: &str, g: Option<f64>| g.map(|g| format!("{name} ≥ {g}"));
    let averages = || [goal("return", cfg.stop.average_return), goal("steps", cfg.stop.average_steps)].into_iter().flatten().collect::<Vec<String>>().join(", ");
    // Records a finished evaluation of the stop criterion; `Some(reason)` when it met the goal.
    let judge = |at: Milestone, joined: std::thread::Result<Result<eval::EvalSummary>>, wall_s: f64| -> Result<Option<(Milestone, String, eval::EvalSummary)>> {
        match joined {
            Ok(Ok(s)) => {
                let gate = cfg.stop.eval_goal().expect("a gate evaluation runs only with a goal");
                append_eval(&run, wall_s, "criteria", &s)?;
                if gate.met_by(&s) {
                    let why = format!(
                        "order-{} moving averages reached the goal ({}) and an evaluation of policy v{} met {} ({})",
                        cfg.stop.window,
                        averages(),
                        s.policy_version,
                        gate.describe(),
                        s.one_line()
                    );
                    return Ok(Some((at, why, s)));
                }
                tracing::info!(policy_version = s.policy_version, "averages met, evaluation short of {}: {}", gate.describe(), s.one_line());
            }
            Ok(Err(e)) => tracing::warn!(error = %format!("{e:#}"), "evaluation of the stop criterion failed"),
            Err(_) => tracing::warn!("evaluation of the stop criterion panicked"),
        }
        Ok(None)
    };

    loop {
        // Lines from children (the learner's status, actors' final reports).
        while let Ok((role, line)) = line_rx.try_recv() {
            if role == "learner"
                && let Ok(LearnerEvent::Status { updates, updates_per_s, weights_version, .. }) = serde_json::from_str(&line)
            {
                *learner_status.lock().unwrap_or_else(|e| e.into_inner()) = LearnerStatus { updates, updates_per_s, weights_version };
            }
        }
        // Episodes.
        while let Ok(e) = ep_rx.try_recv() {
            record_episode(e, offset_s + started.elapsed().as_secs_f64(), &mut rows, &mut csv)?;
        }
        let ls = learner_status.lock().unwrap_or_else(|e| e.into_inner()).clone();
        // Replay info, once a second.
        if last_progress.elapsed() >= Duration::from_secs(1) {
            // Bounded: the supervisor's loop must never hang on the replay.
            let info = rt.block_on(async {
                let fetch = async {
                    if replay_client.is_none() {
                        replay_client = ReplayServiceClient::connect(format!("http://{replay_addr}")).await.ok();
                    }
                    let c = replay_client.as_mut()?;
                    c.server_info(ServerInfoRequest { protocol_version: ProtocolVersion::V1 as i32 }).await.ok().map(tonic::Response::into_inner)
                };
                tokio::time::timeout(Duration::from_secs(1), fetch).await.ok().flatten()
            });
            match info {
                Some(i) => {
                    replay_size = i.size;
                    inserts_total = i.inserts_total;
                    if steady_start.is_none() && started.elapsed().as_secs_f64() >= steady_from {
                        steady_start = Some((Instant::now(), i.inserts_total, ls.updates));
                    }
                }
                None => replay_client = None,
            }
            let dt = env_rate.0.elapsed().as_secs_f64();
            if dt >= 5.0 {
                env_rate = (Instant::now(), inserts_total, (inserts_total.saturating_sub(env_rate.1)) as f64 / dt);
            } else if env_rate.1 == 0 {
                env_rate.1 = inserts_total;
            }
            let w = cfg.stop.window;
            let avg_r = trailing_mean(rows.iter().map(|e| e.episode_return), w);
            let avg_s = trailing_mean(rows.iter().map(|e| f64::from(e.steps)), w);
            let el = started.elapsed().as_secs();
            let alive = actors.iter_mut().filter_map(|a| a.exited().is_none().then_some(())).count();
            let restarts = total_restarts(&replay, &learner, &actors);
            let line = format!(
                "[{:02}:{:02}:{:02}] ep {} | avg{} return {:.1} steps {:.0} | updates {} ({:.0}/s) | env {:.0} steps/s | replay {} | policy v{} | actors {}/{}{}",
                el / 3600,
                el / 60 % 60,
                el % 60,
                fmt_int(rows.len() as u64),
                w,
                avg_r,
                avg_s,
                fmt_int(ls.updates),
                ls.updates_per_s,
                env_rate.2,
                fmt_int(replay_size),
                ls.weights_version,
                alive,
                actors.len(),
                if restarts > 0 { format!(" ({restarts} restarts)") } else { String::new() }
            );
            if tty {
                eprint!("\r{line}\x1b[K");
            } else if last_printed.elapsed() >= Duration::from_secs(10) {
                // Logs and pipes get a line every 10 s instead of a line rewritten in place.
                eprintln!("{line}");
                last_printed = Instant::now();
            }
            last_progress = Instant::now();
        }
        // Evaluation of the newest policy as the run goes (a thread: it must not hold up the
        // supervision), its trajectories drawn into eval/.
        if progress_eval.as_ref().is_some_and(|p| p.handle.is_finished()) {
            progress_eval.take().expect("checked").finish(&run)?;
            last_progress_eval = Instant::now();
        }
        if let Some(every) = cfg.eval.every_minutes
            && cfg.eval.progress_episodes > 0
            && progress_eval.is_none()
            && last_progress_eval.elapsed().as_secs_f64() >= every * 60.0
            && run.join("policy.safetensors").exists()
        {
            let (policy, map, env, n, seed, out) = (run.join("policy.safetensors"), eval_map.clone(), cfg.env.clone(), cfg.eval.progress_episodes, eval_seed, run.join("eval"));
            let handle = std::thread::Builder::new().name("eval".into()).spawn(move || eval::evaluate(&policy, &map, &env, n, seed, Some(&out)))?;
            progress_eval = Some(ProgressEval { wall_s: offset_s + started.elapsed().as_secs_f64(), handle });
        }
        // Pictures as the run goes.
        if rows.len() > pictured && (rows.len() - pictured >= 50 || last_picture.elapsed() >= Duration::from_secs(30)) {
            draw_curves(&run, &cfg, &rows);
            pictured = rows.len();
            last_picture = Instant::now();
        }
        // Stop criteria: the moving averages, backed (when the preset asks) by an evaluation of
        // the newest policy that reaches the paper's exploration figures.
        let now = |rows: &[EpisodeRow]| Milestone { wall_s: offset_s + started.elapsed().as_secs_f64(), episode: rows.len() as u64, env_steps: inserts_total, updates: ls.updates };
        if let Some((at, h)) = gate_eval.take_if(|(_, h)| h.is_finished()) {
            last_gate_eval = Some(Instant::now());
            if let Some((at, why, s)) = judge(at, h.join(), offset_s + started.elapsed().as_secs_f64())?
                && milestone.is_none()
            {
                milestone = Some(at);
                stopped_because = why;
                criteria_evaluation = Some(s);
                stop.store(true, Ordering::Relaxed);
            }
        }
        if milestone.is_none() && rows.len() > first_episode_this_session && averages_met(&rows, &cfg.stop) {
            if cfg.stop.eval_goal().is_none() {
                milestone = Some(now(&rows));
                stopped_because = format!("order-{} moving averages reached the goal ({})", cfg.stop.window, averages());
                stop.store(true, Ordering::Relaxed);
            } else if gate_eval.is_none() && last_gate_eval.is_none_or(|t| t.elapsed() >= GATE_EVAL_COOLDOWN) && run.join("policy.safetensors").exists() {
                // Judge a copy: the learner keeps replacing policy.safetensors.
                fs::copy(run.join("policy.safetensors"), &gate_policy).with_context(|| format!("copying the policy to {}", gate_policy.display()))?;
                let (policy, map, env, n, seed) = (gate_policy.clone(), eval_map.clone(), cfg.env.clone(), cfg.stop.eval_episodes, eval_seed);
                let handle = std::thread::Builder::new().name("eval-criteria".into()).spawn(move || eval::evaluate(&policy, &map, &env, n, seed, None))?;
                gate_eval = Some((now(&rows), handle));
            }
        }
        if let Some(k) = cfg.stop.episodes
            && !stop.load(Ordering::Relaxed)
            && rows.len() as u64 >= k
        {
            stopped_because = format!("{k} episodes");
            stop.store(true, Ordering::Relaxed);
        }
        // Minutes of the whole run, like episodes: a resumed run counts its earlier sessions
        // (up to its last recorded episode).
        if let Some(m) = cfg.stop.minutes
            && !stop.load(Ordering::Relaxed)
            && offset_s + started.elapsed().as_secs_f64() >= m * 60.0
        {
            stopped_because = format!("{m} minutes");
            stop.store(true, Ordering::Relaxed);
        }
        if stop.load(Ordering::Relaxed) {
            break;
        }
        // Supervision.
        let mut restarted = false;
        for (i, a) in actors.iter_mut().enumerate() {
            if a.not_before.is_some() {
                restarted |= a.restart_when_due(Some(line_tx.clone()))?;
            } else if let Some(st) = a.exited() {
                a.restarts += 1;
                if tty {
                    eprintln!();
                }
                tracing::warn!(actor = i, status = %st, "actor exited; restarting it");
                restarted |= a.restart_when_due(Some(line_tx.clone()))?;
            }
        }
        if restarted {
            write_pids(&run, &replay, &learner, &actors)?;
        }
        if let Some(st) = learner.exited() {
            restart_service(&mut learner, st, "from its newest checkpoint", line_tx.clone())?;
            write_pids(&run, &replay, &learner, &actors)?;
        }
        if let Some(st) = replay.exited() {
            restart_service(&mut replay, st, "(it restores from its log)", line_tx.clone())?;
            write_pids(&run, &replay, &learner, &actors)?;
        }
        std::thread::sleep(Duration::from_millis(100));
    }
    if tty {
        eprintln!();
    }
    let stop_point = (Instant::now(), inserts_total, learner_status.lock().unwrap_or_else(|e| e.into_inner()).updates);
    eprintln!("stopping: {stopped_because}");

    // Orderly shutdown: actors (flush their batches), the learner (final checkpoint), the replay.
    for a in &mut actors {
        if let Some(c) = a.child.as_ref() {
            crate::signals::terminate(c.id());
        }
    }
    for a in &mut actors {
        // An actor sends its last batch and waits up to 10 s for the acknowledgements.
        a.stop(Duration::from_secs(30));
    }
    learner.stop(Duration::from_secs(60));
    // Episodes that arrived while the actors stopped.
    while let Ok(e) = ep_rx.try_recv() {
        record_episode(e, offset_s + started.elapsed().as_secs_f64(), &mut rows, &mut csv)?;
    }
    replay.stop(Duration::from_secs(60));
    let _ = collector_stop_tx.send(true);
    rt.shutdown_timeout(Duration::from_secs(2));
    drop(line_tx);
    let final_updates = {
        let mut u = learner_status.lock().unwrap_or_else(|e| e.into_inner()).updates;
        while let Ok((role, line)) = line_rx.try_recv() {
            if role == "learner"
                && let Ok(event) = serde_json::from_str::<LearnerEvent>(&line)
            {
                u = event.updates();
            }
        }
        u
    };
    draw_curves(&run, &cfg, &rows);
    // An evaluation still running writes into eval/ too: it ends first (a few episodes).
    if let Some(p) = progress_eval.take() {
        p.finish(&run)?;
    }

    // An evaluation of the stop criterion still running when a cap or Ctrl-C stopped the run
    // ends first; if it met the goal, the run met its criteria after all.
    if let Some((at, h)) = gate_eval.take()
        && let Some((at, why, s)) = judge(at, h.join(), offset_s + started.elapsed().as_secs_f64())?
        && milestone.is_none()
    {
        milestone = Some(at);
        stopped_because = format!("{stopped_because}; meanwhile {why}");
        criteria_evaluation = Some(s);
    }
    // A run stopped by its criteria keeps the policy that met them as its policy; the learner's
    // last one (a few seconds of training later) stays beside it.
    if criteria_evaluation.is_some() {
        let (policy, last) = (run.join("policy.safetensors"), run.join("policy-last.safetensors"));
        if policy.exists() {
            fs::rename(&policy, &last).with_context(|| format!("renaming {}", policy.display()))?;
        }
        fs::copy(&gate_policy, &policy).with_context(|| format!("copying {} to {}", gate_policy.display(), policy.display()))?;
    }

    // Evaluation of the final policy.
    let evaluation = if cfg.eval.episodes > 0 && run.join("policy.safetensors").exists() {
        // Only this evaluation's pictures remain.
        if let Ok(dir) = fs::read_dir(run.join("eval")) {
            for f in dir.flatten() {
                if f.file_name().to_string_lossy().starts_with("episode-") {
                    let _ = fs::remove_file(f.path());
                }
            }
        }
        let map = eval_map;
        eprintln!("evaluating the final policy: {} episodes on {map} (deterministic) ...", cfg.eval.episodes);
        match eval::evaluate(&run.join("policy.safetensors"), &map, &cfg.env, cfg.eval.episodes, eval_seed, Some(&run.join("eval"))) {
            Ok(s) => {
                eprintln!("  {}", s.one_line());
                append_eval(&run, offset_s + started.elapsed().as_secs_f64(), "final", &s)?;
                Some(s)
            }
            Err(e) => {
                tracing::warn!(error = %format!("{e:#}"), "evaluation failed");
                None
            }
        }
    } else {
        None
    };

    let w = cfg.stop.window;
    let steady = steady_start.map(|(t, e, u)| {
        let secs = (stop_point.0 - t).as_secs_f64().max(1e-9);
        Rates { from_s: (t - started).as_secs_f64(), seconds: secs, env_steps_per_s: stop_point.1.saturating_sub(e) as f64 / secs, updates_per_s: stop_point.2.saturating_sub(u) as f64 / secs }
    });
    let summary = Summary {
        run: run.display().to_string(),
        preset: cfg.name.clone(),
        stopped_because,
        wall_s: offset_s + started.elapsed().as_secs_f64(),
        episodes: rows.len() as u64,
        env_steps: inserts_total,
        updates: final_updates,
        weights_version: learner_status.lock().unwrap_or_else(|e| e.into_inner()).weights_version,
        average_return: trailing_mean(rows.iter().map(|e| e.episode_return), w),
        average_steps: trailing_mean(rows.iter().map(|e| f64::from(e.steps)), w),
        window: w,
        criteria_met_at: milestone,
        criteria_evaluation,
        convergence_episode: protocol::convergence_episode(&rows, w, cfg.stop.convergence_tolerance),
        actor_restarts: actors.iter().map(|a| a.restarts).sum(),
        steady,
        evaluation,
    };
    write_atomic(&run.join("summary.json"), &serde_json::to_string_pretty(&summary)?)?;
    eprintln!(
        "done: {} episodes, {} env steps, {} updates in {:.0} s; avg{w} return {:.1}, steps {:.0}; convergence episode {}",
        summary.episodes,
        fmt_int(summary.env_steps),
        fmt_int(summary.updates),
        summary.wall_s,
        summary.average_return,
        summary.average_steps,
        summary.convergence_episode.map_or("-".to_owned(), |e| e.to_string())
    );
    eprintln!("  pictures: {}/curves.png, {}/eval/; summary: {}/summary.json", run.display(), run.display(), run.display());
    Ok(())
}

fn draw_curves(run: &Path, cfg: &TrainConfig, rows: &[EpisodeRow]) {
    let points: Vec<CurvePoint> = rows.iter().map(|r| CurvePoint { episode: r.episode, episode_return: r.episode_return, steps: r.steps }).collect();
    let style = CurveStyle {
        title: format!("{} - order-{} moving averages", cfg.name, cfg.stop.window),
        window: cfg.stop.window,
        return_goal: cfg.stop.average_return,
        steps_goal: cfg.stop.average_steps,
        footer: format!("{} episodes", rows.len()),
    };
    if let Err(e) = training_curves_png(&points, &style, &run.join("curves.png")) {
        tracing::warn!(error = %e, "cannot draw curves.png");
    }
}

/// `pids.json`: the processes of the run now (tests and operators use it).
fn write_pids(run: &Path, replay: &Proc, learner: &Proc, actors: &[Proc]) -> Result<()> {
    let v = serde_json::json!({
        "supervisor": std::process::id(), "replay": replay.pid(), "learner": learner.pid(),
        "actors": actors.iter().map(Proc::pid).collect::<Vec<_>>(),
        "restarts": total_restarts(replay, learner, actors),
    });
    write_atomic(&run.join("pids.json"), &serde_json::to_string(&v)?)
}

#[cfg(test)]
mod tests {
    use super::*;
    use mapless_actor::NoiseConfig;
    use mapless_learner_config::{AlgorithmKind, DriverConfig};
    use mapless_sim::RewardConfig;

    fn row(episode: u64, ret: f64, steps: u32) -> EpisodeRow {
        EpisodeRow {
            episode,
            wall_s: episode as f64,
            actor_id: "actor-0-1-2".into(),
            policy_version: 3,
            episode_return: ret,
            steps,
            terminal: steps < 1000,
            eqs: 12.0,
            ees: 1.5,
            distance_m: 40.0,
            shaded_time_s: 0.0,
        }
    }

    /// deploy/config/ (the compose cluster) is written by hand; it must keep parsing, pass each
    /// service's checks (TLS and token beyond loopback) and run the env1-sac preset's settings.
    #[test]
    fn the_compose_configs_parse_validate_and_match_the_env1_sac_preset() {
        let dir = Path::new(env!("CARGO_MANIFEST_DIR")).join("../deploy/config");
        let read = |f: &str| fs::read_to_string(dir.join(f)).unwrap_or_else(|e| panic!("{f}: {e}"));
        fn yaml<T: Serialize>(v: &T) -> serde_yaml::Value {
            serde_yaml::to_value(v).expect("serializes")
        }
        let preset = preset_config("env1-sac").unwrap();
        let preset = preset.resolve().unwrap();

        let replay = ServerConfig::from_yaml_file(&dir.join("replay.yaml")).unwrap();
        replay.validate().expect("replay.yaml passes the service's checks");
        assert!(!replay.listen.ip().is_loopback() && replay.tls.is_some() && replay.auth_token_file.is_some());
        assert_eq!(yaml(&replay.table), yaml(&preset.replay), "replay.yaml: the preset's table and rate limiter");

        let learner: LearnerServiceConfig = serde_yaml::from_str(&read("learner.yaml")).unwrap();
        assert_eq!(yaml(&learner.learner), yaml(&LearnerConfig { seed: preset.seed, ..preset.learner.clone() }), "learner.yaml: the preset's learner");
        assert_eq!(yaml(&learner.driver), yaml(&preset.driver));
        assert!(learner.replay.starts_with("https://") && learner.replay_security.tls_ca_file.is_some() && learner.replay_security.token_file.is_some());
        assert!(learner.tls.is_some() && learner.auth_token_file.is_some(), "weights beyond loopback need TLS and a token");

        let actor: ActorConfig = serde_yaml::from_str(&read("actor.yaml")).unwrap();
        actor.validate().expect("actor.yaml passes the actor's checks");
        assert_eq!(yaml(&actor.env), yaml(&preset.env), "actor.yaml: the preset's environment");
        assert_eq!(actor.map, preset.map);
        assert_eq!(yaml(&actor.exploration.noise), yaml(&preset.noise()));
        assert!(matches!(&actor.replay, ReplayTarget::Grpc { uri } if uri.starts_with("https://")));
        assert!(actor.weights.starts_with("https://") && actor.security.tls_ca_file.is_some() && actor.security.token_file.is_some());
    }

    #[test]
    fn every_preset_resolves_and_names_itself() {
        for (name, _) in PRESETS {
            let cfg = preset_config(name).unwrap_or_else(|e| panic!("{name}: {e}"));
            let cfg = cfg.resolve().unwrap_or_else(|e| panic!("{name}: {e:#}"));
            assert_eq!(&cfg.name, name);
            assert_eq!(cfg.replay.obs_dim, 17, "{name}: 7 beams → 17 observation values");
        }
        let sar = preset_config("outdoor20-sac").unwrap();
        assert_eq!(sar.resolve().unwrap().env.reward, RewardConfig::search_and_rescue());
        let env2 = preset_config("env2-td3").unwrap();
        let env2 = env2.resolve().unwrap();
        assert_eq!((env2.env.episode.max_steps, env2.learner.algorithm), (2000, AlgorithmKind::Td3));
        assert_eq!(env2.noise(), NoiseConfig::TD3_DEFAULT);
    }

    #[test]
    fn set_overrides_nested_fields_and_rejects_bad_paths() {
        let mut doc: serde_yaml::Value = serde_yaml::from_str(preset_text("env1-sac").unwrap().as_str()).unwrap();
        set_path(&mut doc, "learner.actor_lr", "1e-4").unwrap();
        set_path(&mut doc, "replay.rate_limiter.samples_per_insert", "8").unwrap();
        set_path(&mut doc, "stop.average_return", "null").unwrap();
        let cfg = parse_config(doc.clone()).unwrap();
        assert_eq!(cfg.learner.actor_lr, 1e-4);
        assert_eq!(cfg.replay.rate_limiter.samples_per_insert, Some(8.0));
        assert_eq!(cfg.stop.average_return, None);
        assert!(set_path(&mut doc, "map.inner", "1").is_err(), "map is a string, not a section");
        set_path(&mut doc, "learner.no_such_field", "1").unwrap();
        assert!(parse_config(doc).is_err(), "unknown fields are refused");
    }

    /// Every leaf of a resolved config as (dotted path, value).
    fn leaves(v: &serde_yaml::Value, path: &str, out: &mut Vec<(String, serde_yaml::Value)>) {
        match v {
            serde_yaml::Value::Mapping(m) => {
                for (k, v) in m {
                    let k = k.as_str().expect("string keys");
                    leaves(v, &if path.is_empty() { k.to_owned() } else { format!("{path}.{k}") }, out);
                }
            }
            _ => out.push((path.to_owned(), v.clone())),
        }
    }

    /// A different value of the same kind for `path`, if one can be written on a command line.
    fn another(path: &str, v: &serde_yaml::Value) -> Option<serde_yaml::Value> {
        use serde_yaml::Value as V;
        Some(match v {
            V::Bool(b) => V::Bool(!b),
            V::Number(n) if n.is_u64() || n.is_i64() => V::from(n.as_i64().unwrap_or(0) + 1),
            V::Number(n) => V::from(if n.as_f64()? == 0.0 { 0.5 } else { n.as_f64()? * 1.25 }),
            V::String(s) if path == "learner.algorithm" => V::from(if s == "td3" { "ddpg" } else { "td3" }),
            V::String(s) if path == "map" || path == "eval.map" => V::from(if s == "env2" { "env3" } else { "env2" }),
            V::String(s) => V::from(format!("{s}x")),
            V::Sequence(s) if !s.is_empty() => V::Sequence(Vec::new()),
            V::Null => V::from(3),
            _ => return None,
        })
    }

    fn lookup<'a>(v: &'a serde_yaml::Value, path: &str) -> Option<&'a serde_yaml::Value> {
        path.split('.').try_fold(v, |v, k| v.get(k))
    }

    #[test]
    fn every_set_path_reaches_the_resolved_config_or_is_refused_by_name() {
        for preset in ["env1-sac", "env2-ddpg", "outdoor20-sac"] {
            let (base, ..) = load_config(&train_args(preset, &[])).unwrap();
            let mut all = Vec::new();
            leaves(&serde_yaml::to_value(&base).unwrap(), "", &mut all);
            assert!(all.len() > 80, "{preset}: {} settable paths", all.len());
            let mut silent = Vec::new();
            for (path, value) in all {
                let Some(new) = another(&path, &value) else { continue };
                let set = format!("{path}={}", serde_yaml::to_string(&new).unwrap().trim());
                match load_config(&train_args(preset, &[&set])) {
                    Ok((cfg, ..)) => {
                        let resolved = serde_yaml::to_value(&cfg).unwrap();
                        let got = lookup(&resolved, &path);
                        // A number may come back as the other kind (3 → 3.0).
                        let same = got == Some(&new) || got.and_then(|g| g.as_f64()).zip(new.as_f64()).is_some_and(|(a, b)| a == b);
                        if !same {
                            silent.push(format!("--set {set} resolved to {got:?}"));
                        }
                    }
                    Err(e) => {
                        let (msg, leaf) = (format!("{e:#}"), path.rsplit('.').next().unwrap());
                        if !msg.contains(leaf) {
                            silent.push(format!("--set {set} refused without naming `{leaf}`: {msg}"));
                        }
                    }
                }
            }
            assert!(silent.is_empty(), "{preset}: --set paths that do not reach the config:\n{}", silent.join("\n"));
        }
        // The reward lives in env.reward: a preset's `reward:` is laid under --set, and a --set
        // of the shorthand replaces it (then later --set fields apply on top).
        let (c, ..) = load_config(&train_args("env1-sac", &["env.reward.speed_weight=2"])).unwrap();
        assert_eq!(c.env.reward, RewardConfig { speed_weight: 2.0, ..RewardConfig::exploration() });
        let (c, ..) = load_config(&train_args("env1-sac", &["env.reward.speed_weight=2", "reward=search_and_rescue", "env.reward.turn_penalty=1"])).unwrap();
        assert_eq!(c.env.reward, RewardConfig { turn_penalty: 1.0, ..RewardConfig::search_and_rescue() });
        let (c, ..) = load_config(&train_args("env2-sac", &["max_steps=3000"])).unwrap();
        assert_eq!(c.env.episode.max_steps, 3000);
        // Unknown keys are errors that name them.
        for (bad, named) in
            [("learner.no_such_knob=1", "no_such_knob"), ("no_such_section.x=1", "no_such_section"), ("env.reward.no_such_weight=1", "no_such_weight"), ("reward=no_such_reward", "no_such_reward")]
        {
            let e = format!("{:#}", load_config(&train_args("env1-sac", &[bad])).unwrap_err());
            assert!(e.contains(named), "--set {bad}: {e}");
        }
    }

    #[test]
    fn a_run_folder_written_by_an_older_version_still_reads_and_resumes() {
        // What config.yaml held before the knobs got one home: the shorthands beside env, the
        // learner's unread replay_capacity, an empty actors.noise, the derived seed and dims.
        let dir = tempfile::tempdir().unwrap();
        let (cfg, ..) = load_config(&train_args("env1-sac", &["seed=3"])).unwrap();
        let mut doc = serde_yaml::to_value(&cfg).unwrap();
        let m = doc.as_mapping_mut().unwrap();
        m.insert("reward".into(), "exploration".into());
        m.insert("max_steps".into(), 1000.into());
        set_path(&mut doc, "learner.replay_capacity", "1000000").unwrap();
        set_path(&mut doc, "actors.noise", "null").unwrap();
        std::fs::write(dir.path().join("config.yaml"), serde_yaml::to_string(&doc).unwrap()).unwrap();
        let back = read_run_config(dir.path()).unwrap().resolve().unwrap();
        assert_eq!(back, cfg, "read back as it was resolved");
        let mut args = train_args("env1-sac", &["seed=5", "env.sensor.beams=9"]);
        args.resume = Some(dir.path().to_owned());
        let (resumed, _, resuming) = load_config(&args).unwrap();
        assert!(resuming);
        assert_eq!((resumed.seed, resumed.learner.seed, resumed.replay.obs_dim), (5, 5, 21), "derived values follow what they derive from");
        // An actors.noise that said something is refused by name, with where it lives now.
        set_path(&mut doc, "actors.noise", "{kind: gaussian, sigma: 0.2}").unwrap();
        std::fs::write(dir.path().join("config.yaml"), serde_yaml::to_string(&doc).unwrap()).unwrap();
        let e = format!("{:#}", read_run_config(dir.path()).unwrap_err());
        assert!(e.contains("actors.noise") && e.contains("learner.td3.exploration"), "{e}");
    }

    #[test]
    fn evals_csv_gets_one_header_and_loses_only_a_torn_line() {
        let dir = tempfile::tempdir().unwrap();
        let s = eval::EvalSummary {
            map: "maps/a,b.yaml".into(),
            policy_version: 7,
            episodes: Vec::new(),
            mean_steps: 1000.0,
            mean_return: 400.0,
            mean_eqs: 120.0,
            mean_ees: 2.5,
            mean_distance_m: 49.0,
            mean_shaded_time_s: 0.0,
            collisions: 0,
        };
        append_eval(dir.path(), 10.0, "progress", &s).unwrap();
        let p = dir.path().join("evals.csv");
        let torn = format!("{}20.0,progr", std::fs::read_to_string(&p).unwrap());
        std::fs::write(&p, torn).unwrap();
        append_eval(dir.path(), 30.0, "final", &s).unwrap();
        let mut r = csv::Reader::from_path(&p).unwrap();
        assert_eq!(r.headers().unwrap().iter().next(), Some("wall_s"));
        let rows: Vec<csv::StringRecord> = r.records().map(|x| x.unwrap()).collect();
        let kinds: Vec<(&str, &str)> = rows.iter().map(|x| (&x[1], &x[3])).collect();
        assert_eq!(kinds, [("progress", "maps/a,b.yaml"), ("final", "maps/a,b.yaml")], "a map path with a comma stays one field");
    }

    fn train_args(preset: &str, set: &[&str]) -> TrainArgs {
        TrainArgs {
            preset: preset.into(),
            actors: None,
            vehicles: None,
            episodes: None,
            minutes: None,
            run: None,
            resume: None,
            set: set.iter().map(|s| (*s).to_owned()).collect(),
            force: false,
            print_config: false,
        }
    }

    #[test]
    fn a_presets_replay_section_is_laid_over_the_defaults_field_by_field() {
        // Every preset states its update-to-data ratio; the table's other fields stay this
        // command's defaults (they were replaced by TableConfig::default() when a preset named
        // `replay:`).
        for (name, _) in PRESETS {
            let (cfg, _, _) = load_config(&train_args(name, &[])).unwrap();
            let d = default_table();
            assert_eq!(cfg.replay.rate_limiter.samples_per_insert, Some(32.0), "{name}");
            assert_eq!((cfg.replay.rate_limiter.min_size_to_sample, cfg.replay.max_batch_rows), (d.rate_limiter.min_size_to_sample, d.max_batch_rows), "{name}");
            assert_eq!(cfg.driver, DriverConfig::default(), "{name}");
        }
        let (cfg, _, _) = load_config(&train_args("env1-sac", &["replay.rate_limiter.samples_per_insert=128", "driver.publish_every=10"])).unwrap();
        assert_eq!(cfg.replay.rate_limiter.samples_per_insert, Some(128.0));
        assert_eq!(cfg.replay.rate_limiter.error_buffer, default_table().rate_limiter.error_buffer);
        assert_eq!((cfg.driver.publish_every, cfg.driver.checkpoint_every), (10, DriverConfig::default().checkpoint_every));
        // Many vehicles per actor: the table takes their batches (batch_rows + vehicles rows).
        let (cfg, _, _) = load_config(&train_args("env1-sac", &["actors.vehicles=200"])).unwrap();
        assert_eq!(cfg.replay.max_batch_rows, 64 + 200);
        // ... and with the paper's ratio too, the limiter's slack must then grow: a clear error.
        let err = load_config(&train_args("env1-sac", &["actors.vehicles=200", "replay.rate_limiter.samples_per_insert=128"])).unwrap_err();
        assert!(format!("{err:#}").contains("error_buffer"), "{err:#}");
    }

    #[test]
    fn an_evaluation_goal_backs_the_averages_and_is_in_the_env1_presets() {
        let mut cfg = preset_config("env1-sac").unwrap();
        let goal = cfg.stop.eval_goal().expect("env1-sac stops on an evaluation too");
        assert_eq!((goal.eqs, goal.ees, goal.max_collisions), (Some(91.0), Some(2.63), 0), "Table III SAC");
        // Without averages to back, the goal does not stop a run (`averages_met` is false).
        cfg.stop.average_return = None;
        cfg.stop.average_steps = None;
        cfg.stop.window = 1;
        assert!(!averages_met(&[row(1, 500.0, 1000)], &cfg.stop));
        cfg.resolve().unwrap();
        for (p, eqs, ees) in [("env1-td3", 113.0, 2.40), ("env1-ddpg", 81.0, 1.82)] {
            let cfg = preset_config(p).unwrap();
            let g = cfg.stop.eval_goal().unwrap();
            assert_eq!((g.eqs, g.ees), (Some(eqs), Some(ees)), "{p}");
        }
    }

    #[test]
    fn stop_on_moving_averages_needs_a_full_window_and_both_goals() {
        let stop = StopCriteria { window: 3, average_return: Some(300.0), average_steps: Some(990.0), ..StopCriteria::default() };
        let mut rows = vec![row(1, 400.0, 1000), row(2, 400.0, 1000)];
        assert!(!averages_met(&rows, &stop), "fewer episodes than the window");
        rows.push(row(3, 400.0, 1000));
        assert!(averages_met(&rows, &stop));
        rows.push(row(4, 400.0, 900)); // steps average (1000+1000+900)/3 = 966.7 < 990
        assert!(!averages_met(&rows, &stop));
        let only_return = StopCriteria { average_steps: None, ..stop.clone() };
        assert!(averages_met(&rows, &only_return));
        let none = StopCriteria { average_return: None, average_steps: None, ..stop };
        assert!(!averages_met(&rows, &none), "no goals: never stops on averages");
    }

    #[test]
    fn episodes_csv_round_trips_and_skips_a_torn_line() {
        let dir = tempfile::tempdir().unwrap();
        let p = dir.path().join("episodes.csv");
        // An actor id is the peer's: a comma or a quote in it stays inside its field.
        let mut odd = row(2, 321.25, 1000);
        odd.actor_id = "actor,\"0\"".into();
        let rows = vec![row(1, -12.5, 37), odd];
        let mut w = episodes_writer(std::fs::File::create(&p).unwrap(), true);
        for r in &rows {
            w.serialize(r).unwrap();
        }
        drop(w);
        let text = std::fs::read_to_string(&p).unwrap();
        assert!(text.starts_with("episode,wall_s,actor_id,policy_version,return,steps,terminal,eqs,ees,distance_m,shaded_time_s\n1,1.0,actor-0-1-2,3,-12.5,37,1,"), "{text}");
        std::fs::write(&p, format!("{text}3,12.0,actor-0")).unwrap();
        let (back, bad) = read_episodes(&p);
        assert_eq!(bad, 1);
        assert_eq!(back, rows);
        // A file written before the csv crate (fixed decimals) reads back the same way.
        std::fs::write(&p, "episode,wall_s,actor_id,policy_version,return,steps,terminal,eqs,ees,distance_m,shaded_time_s\n7,12.345,actor-1-9-0,40,321.2500,1000,0,55,1.1300,49.000,0.00\n").unwrap();
        let (back, bad) = read_episodes(&p);
        assert_eq!((back.len(), bad, back[0].episode, back[0].terminal, back[0].episode_return), (1, 0, 7, false, 321.25));
    }
}
