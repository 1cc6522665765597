//! `mapless monitor`: the run folder of a cluster that `mapless train` did not start — the
//! compose cluster (deploy/compose.yaml's `monitor` service), or services started by hand.
//!
//! ```text
//!   actors ──episodes (StatsService; TLS + actor token beyond loopback)──► monitor ─► RUN/episodes.csv, curves.png
//!   learner's policy_file (its volume, read-only) ──copied when it changes──► RUN/policy.safetensors ─► evaluations: evals.csv, eval/
//!   replay's and learner's /metrics (metrics token) ──every second──► env steps, replay size, updates, weights version
//!   SIGTERM ─► final curves, final evaluation, RUN/summary.json
//! ```
//!
//! It writes what `mapless train` writes, with the same code: `episodes.csv` and `curves.png`
//! as episodes come, an evaluation of the newest policy every `eval.every_minutes`, the preset's
//! stop criteria judged as `mapless train` judges them (moving averages backed by an evaluation
//! of the newest policy) — met, they are logged and kept in `summary.json`, but nothing is
//! stopped: the monitor does not own the cluster. On SIGTERM (`docker stop`) it draws the
//! curves, evaluates the newest policy (`eval.episodes`) and writes `summary.json`. A restarted
//! monitor continues the folder's `episodes.csv`, as `mapless train --resume` does.
//!
//! Its settings are one YAML file, [`MonitorConfig`] (deploy/config/monitor.yaml).

use std::fs;
use std::net::SocketAddr;
use std::path::{Path, PathBuf};
use std::process::ExitCode;
use std::time::{Duration, Instant, SystemTime};

use anyhow::{Context, Result};
use indicatif::ProgressBar;
use mapless_learner_config::LearnerEvent;
use mapless_net::health::{GrpcProbeArgs, grpc_probe};
use mapless_net::serve::{RoleTokenFiles, Security, TlsFiles};
use mapless_proto::v1::{EpisodeStats, ServerInfoResponse};
use serde::{Deserialize, Serialize};

use super::config::{TrainConfig, preset_with_sets};
use super::curves::{Curves, draw_curves};
use super::episodes::Episodes;
use super::evaluate::Evaluations;
use super::folder::RunFolder;
use super::status::{LearnerEnd, Status};
use super::stop::{INTERRUPTED, Interrupt, StopRules};
use super::summary::{End, Summary};
use crate::scrape;

/// `mapless monitor`'s settings (one YAML file; an unknown key is an error).
#[derive(Clone, Debug, Serialize, Deserialize, PartialEq)]
#[serde(deny_unknown_fields)]
pub struct MonitorConfig {
    /// The preset the cluster's services were written from (deploy/config's are env1-sac's):
    /// its map and environment for the evaluations, its `eval` settings, its `stop` criteria
    /// (window, goals) and its name in `summary.json`.
    pub preset: String,
    /// Overrides of the preset, as `mapless train --set KEY=VALUE` takes them.
    #[serde(default)]
    pub set: Vec<String>,
    /// The run folder: episodes.csv, curves.png, evals.csv, eval/, policy.safetensors (the
    /// learner's, copied), summary.json.
    pub run: PathBuf,
    /// Where the actors report their episodes (`stats:` in their config). Beyond loopback it
    /// needs `tls` and the actors' token (`auth_token_files.actor`), as every service does.
    pub stats_listen: SocketAddr,
    #[serde(default)]
    pub tls: Option<TlsFiles>,
    /// The tokens the stats service accepts; `Report` needs the actor role's.
    #[serde(default)]
    pub auth_token_files: RoleTokenFiles,
    /// The learner's published policy (its `policy_file`): copied into the run folder when it
    /// changes, and evaluated from there.
    pub policy_file: PathBuf,
    /// The replay's `/metrics` (`host:port`): env steps and replay size, read every second.
    #[serde(default)]
    pub replay_metrics: Option<String>,
    /// The learner's `/metrics` (`host:port`): updates and the weights version.
    #[serde(default)]
    pub learner_metrics: Option<String>,
    /// The token those `/metrics` ask for (`metrics_token_file` in their configs).
    #[serde(default)]
    pub metrics_token_file: Option<PathBuf>,
}

#[derive(clap::Args, Debug)]
#[command(args_conflicts_with_subcommands = true)]
pub struct MonitorArgs {
    /// The monitor's settings (YAML; deploy/config/monitor.yaml is the compose cluster's).
    #[arg(long)]
    pub config: Option<PathBuf>,
    #[command(subcommand)]
    pub probe: Option<MonitorProbe>,
}

#[derive(clap::Subcommand, Debug)]
pub enum MonitorProbe {
    /// Asks a monitor's stats service whether it is SERVING (grpc.health.v1.Health): exit 0 if
    /// so, else 1 (a container's HEALTHCHECK).
    Health(GrpcProbeArgs),
}

/// The stats service's default address in a probe.
const DEFAULT_ADDR: &str = "127.0.0.1:50053";

/// Runs `mapless monitor`.
pub fn monitor(args: &MonitorArgs) -> Result<ExitCode> {
    if let Some(MonitorProbe::Health(a)) = &args.probe {
        return Ok(grpc_probe("mapless monitor", a, DEFAULT_ADDR));
    }
    let path = args.config.as_deref().context("mapless monitor: --config FILE (or the `health` probe)")?;
    let cfg = read_config(path)?;
    let train = preset_with_sets(&cfg.preset, &cfg.set).with_context(|| format!("{}: preset {}", path.display(), cfg.preset))?;
    let security = Security::read(cfg.tls.as_ref(), None, &cfg.auth_token_files)?;
    let metrics_token = match &cfg.metrics_token_file {
        Some(f) => Some(fs::read_to_string(f).with_context(|| format!("reading {}", f.display()))?.trim().to_owned()),
        None => None,
    };
    // The folder continues (a restarted monitor keeps its episodes); config.yaml is the preset's.
    let run = RunFolder::prepare(&cfg.run, &train, true, false)?;
    mapless_net::logging::identify(&[("run", &run.name), ("role", "monitor")]);
    let rt = tokio::runtime::Builder::new_multi_thread().worker_threads(1).thread_name("monitor-io").enable_all().build()?;
    let interrupt = Interrupt::listen(&rt);
    let listener = rt.block_on(tokio::net::TcpListener::bind(cfg.stats_listen)).with_context(|| format!("binding the stats service to {}", cfg.stats_listen))?;
    let (ep_tx, mut ep_rx) = tokio::sync::mpsc::channel::<EpisodeStats>(8192);
    let (stop_tx, stop_rx) = tokio::sync::watch::channel(false);
    let collector = rt.spawn(async move { mapless_net::stats::serve_collector(listener, &security, ep_tx, stop_rx).await });
    tracing::info!(stats = %cfg.stats_listen, policy = %cfg.policy_file.display(), preset = %train.name, "monitoring into {}", run.dir.display());

    let mut episodes = Episodes::open(&run.dir)?;
    let mut status = Status::new(episodes.offset_s, None);
    let mut rules = StopRules::new(&train.stop, episodes.before, train.env.episode.max_steps);
    let mut evals = Evaluations::new(&train, &run.dir);
    let mut curves = Curves::new(&run.dir, episodes.rows.len());
    let mut policy = PolicyCopy::new(&cfg.policy_file, &run.dir.join("policy.safetensors"));
    let (mut replay_scrape, mut learner_scrape) = (Scrape::new(&cfg.replay_metrics), Scrape::new(&cfg.learner_metrics));
    let quiet = ProgressBar::hidden();
    let (mut polled, mut logged): (Option<Instant>, Instant) = (None, Instant::now());
    let mut announced = false;
    loop {
        if collector.is_finished() {
            let e = rt.block_on(collector).map_err(|e| anyhow::anyhow!("the stats service panicked: {e}"))?;
            anyhow::bail!("the stats service stopped: {}", e.err().map_or_else(|| "without an error".to_owned(), |e| e.to_string()));
        }
        while let Ok(e) = ep_rx.try_recv() {
            episodes.record(e, status.wall_s())?;
        }
        if polled.is_none_or(|t| t.elapsed() >= Duration::from_secs(1)) {
            policy.refresh();
            follow(&mut replay_scrape, &mut learner_scrape, metrics_token.as_deref(), &mut status);
            polled = Some(Instant::now());
        }
        if logged.elapsed() >= Duration::from_secs(10) {
            log_status(&train, &status, &episodes);
            logged = Instant::now();
        }
        evals.progress_tick(&status, &quiet)?;
        curves.tick(&train, &episodes.rows);
        if let Some((at, s)) = evals.gate_ended(&status, &quiet)? {
            rules.judge(at, s);
        }
        let at = || status.milestone(episodes.count());
        evals.start_due(rules.averages(&episodes.rows, at), at)?;
        // The criteria, once met, are told once; the cluster goes on (it is not the monitor's).
        if !announced && rules.met() {
            tracing::info!("criteria met: {} (the cluster goes on; the monitor keeps recording)", rules.stopped_because());
            announced = true;
        }
        if interrupt.came() {
            break;
        }
        std::thread::sleep(Duration::from_millis(100));
    }
    tracing::info!("stopping: final curves, evaluation and summary.json");
    let _ = stop_tx.send(true);
    let _ = rt.block_on(async { tokio::time::timeout(Duration::from_secs(6), collector).await });
    while let Ok(e) = ep_rx.try_recv() {
        episodes.record(e, status.wall_s())?;
    }
    policy.refresh();
    follow(&mut replay_scrape, &mut learner_scrape, metrics_token.as_deref(), &mut status);
    let stopped_at = status.counters();
    draw_curves(&run.dir, &train, &episodes.rows);
    evals.finish_progress()?;
    if let Some((at, s)) = evals.gate_after_stop(&status)? {
        rules.judge(at, s);
    }
    let evaluation = evals.final_evaluation(&status)?;
    let mut outcome = rules.outcome();
    outcome.stopped_because = match outcome.criteria_met_at {
        Some(_) => format!("{INTERRUPTED}: the monitor was stopped (the cluster is not its to stop); on the way, {}", outcome.stopped_because),
        None => format!("{INTERRUPTED}: the monitor was stopped (the cluster is not its to stop)"),
    };
    let learner = LearnerEnd { updates: status.learner.updates, weights_version: status.learner.weights_version };
    let end = End { wall_s: status.wall_s(), env_steps: status.env_steps, learner, actor_restarts: 0, steady: status.steady_rates(stopped_at), evaluation, kept_policy: None };
    let summary = Summary::new(&run.dir, &train, &episodes, outcome, end);
    summary.write(&run.dir)?;
    tracing::info!(episodes = summary.episodes, env_steps = summary.env_steps, updates = summary.updates, "wrote {}", run.dir.join("summary.json").display());
    Ok(ExitCode::SUCCESS)
}

/// Reads a monitor's config: an unknown or misspelt key is an error naming it.
pub(crate) fn read_config(path: &Path) -> Result<MonitorConfig> {
    let text = fs::read_to_string(path).with_context(|| format!("reading {}", path.display()))?;
    serde_path_to_error::deserialize(serde_yaml::Deserializer::from_str(&text)).with_context(|| format!("{}: not a monitor config", path.display()))
}

/// One `/metrics` the monitor follows, and whether its scrapes fail now.
struct Scrape {
    addr: String,
    failing: bool,
}

impl Scrape {
    fn new(addr: &Option<String>) -> Option<Scrape> {
        addr.as_ref().map(|a| Scrape { addr: a.clone(), failing: false })
    }

    /// The exposition, or `None`; the first failure of a streak is a warning (a wrong token, a
    /// service that went away), the rest debug lines, and the first success after it an info line.
    fn read(&mut self, token: Option<&str>) -> Option<String> {
        match scrape::metrics(&self.addr, token) {
            Ok(text) => {
                if std::mem::take(&mut self.failing) {
                    tracing::info!(addr = %self.addr, "/metrics answers again");
                }
                Some(text)
            }
            Err(e) if !self.failing => {
                tracing::warn!(error = %e, "cannot read /metrics; its figures stay as they were until it answers");
                self.failing = true;
                None
            }
            Err(e) => {
                tracing::debug!(error = %e, "a /metrics scrape failed");
                None
            }
        }
    }
}

/// The replay's and the learner's counters, from their `/metrics` (one that does not answer
/// keeps its last figures).
fn follow(replay: &mut Option<Scrape>, learner: &mut Option<Scrape>, token: Option<&str>, status: &mut Status) {
    let replay = replay.as_mut().and_then(|s| s.read(token)).map(|text| ServerInfoResponse {
        size: scrape::value(&text, "replay_size").unwrap_or(0.0) as u64,
        inserts_total: scrape::value(&text, "replay_inserts_total").unwrap_or(0.0) as u64,
        ..Default::default()
    });
    if let Some(text) = learner.as_mut().and_then(|s| s.read(token)) {
        status.learner_said(&LearnerEvent::Status {
            updates: scrape::value(&text, "mapless_learner_updates").unwrap_or(0.0) as u64,
            updates_per_s: scrape::value(&text, "mapless_learner_updates_per_second").unwrap_or(0.0),
            weights_version: scrape::value(&text, "mapless_learner_weights_version").unwrap_or(0.0) as u64,
            batches: scrape::value(&text, "mapless_learner_minibatches").unwrap_or(0.0) as u64,
            reconnects: scrape::value(&text, "mapless_learner_replay_reconnects").unwrap_or(0.0) as u64,
        });
    }
    status.replay_said(replay.as_ref());
}

/// A status line every 10 s (the container's log is where a person reads it).
fn log_status(train: &TrainConfig, status: &Status, episodes: &Episodes) {
    let w = train.stop.window;
    let (r, s) = episodes.averages(w);
    tracing::info!(
        episodes = episodes.count(),
        env_steps = status.env_steps,
        env_steps_per_s = status.env_rate.per_s.round(),
        updates = status.learner.updates,
        weights_version = status.learner.weights_version,
        replay_size = status.replay_size,
        "avg{w} return {r:.1} steps {s:.0}"
    );
}

/// The learner's policy file, copied into the run folder whenever it changes (whole: a
/// temporary file, then a rename), so the evaluations read the newest one and never a torn one.
struct PolicyCopy {
    from: PathBuf,
    to: PathBuf,
    seen: Option<(SystemTime, u64)>,
    warned: bool,
}

impl PolicyCopy {
    fn new(from: &Path, to: &Path) -> PolicyCopy {
        PolicyCopy { from: from.to_owned(), to: to.to_owned(), seen: None, warned: false }
    }

    /// Copies the policy if it changed since the last copy; `true` when it did.
    fn refresh(&mut self) -> bool {
        let Ok(meta) = fs::metadata(&self.from) else { return false };
        let stamp = (meta.modified().unwrap_or(SystemTime::UNIX_EPOCH), meta.len());
        if self.seen == Some(stamp) {
            return false;
        }
        let copied = fs::read(&self.from)
            .map_err(anyhow::Error::from)
            .and_then(|bytes| mapless_proto::atomic_file::write_file_atomically(&self.to, &bytes).with_context(|| format!("writing {}", self.to.display())));
        match copied {
            Ok(()) => {
                self.seen = Some(stamp);
                self.warned = false;
                true
            }
            Err(e) => {
                if !self.warned {
                    tracing::warn!(error = %format!("{e:#}"), "cannot copy the learner's policy {}", self.from.display());
                    self.warned = true;
                }
                false
            }
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn the_compose_clusters_monitor_config_reads_and_names_an_unknown_key() {
        let deploy = Path::new(env!("CARGO_MANIFEST_DIR")).join("../deploy/config/monitor.yaml");
        let cfg = read_config(&deploy).unwrap();
        assert_eq!((cfg.preset.as_str(), cfg.stats_listen.port()), ("env1-sac", 50053));
        assert!(cfg.tls.is_some() && cfg.auth_token_files.actor.is_some() && cfg.auth_token_files.learner.is_none(), "TLS and the actors' token only");
        preset_with_sets(&cfg.preset, &cfg.set).unwrap();
        let dir = tempfile::tempdir().unwrap();
        let bad = dir.path().join("m.yaml");
        fs::write(&bad, fs::read_to_string(&deploy).unwrap() + "stats_lisen: 1\n").unwrap();
        let e = format!("{:#}", read_config(&bad).unwrap_err());
        assert!(e.contains("stats_lisen"), "{e}");
    }

    #[test]
    fn the_policy_is_copied_whole_and_only_when_it_changed() {
        let dir = tempfile::tempdir().unwrap();
        let (from, to) = (dir.path().join("learner.safetensors"), dir.path().join("run/policy.safetensors"));
        fs::create_dir_all(dir.path().join("run")).unwrap();
        let mut p = PolicyCopy::new(&from, &to);
        assert!(!p.refresh() && !to.exists(), "nothing published yet");
        fs::write(&from, b"v1").unwrap();
        assert!(p.refresh());
        assert!(!p.refresh(), "unchanged");
        assert_eq!(fs::read(&to).unwrap(), b"v1");
        fs::write(&from, b"v2 longer").unwrap();
        assert!(p.refresh());
        assert_eq!(fs::read(&to).unwrap(), b"v2 longer");
    }
}
