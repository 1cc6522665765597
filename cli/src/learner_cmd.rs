//! `mapless learner`: the learner process of a cluster — samples from the replay service over
//! gRPC, updates, publishes versioned weights on its own gRPC service, checkpoints, writes
//! TensorBoard scalars, and prints one JSON status line per second on stdout (what the
//! supervisor of `mapless train` reads).
//!
//! ```text
//!   replay ══Sample (prefetch)══► GrpcSource ─► Driver (update, publish every K, checkpoint every N)
//!                                                  └─► WeightsService (127.0.0.1 by default) ══► actors
//! ```
//! SIGINT/SIGTERM: stop after the current update, publish, checkpoint, exit 0.

use std::net::SocketAddr;
use std::path::{Path, PathBuf};
use std::sync::Arc;
use std::sync::atomic::{AtomicBool, AtomicU64, Ordering};
use std::time::{Duration, Instant};

use anyhow::{Context, Result};
use mapless_learner::algo::Agent;
use mapless_learner::config::LearnerConfig;
use mapless_learner::driver::{Driver, DriverConfig};
use mapless_learner::source::{GrpcEndpoint, GrpcSource, GrpcSourceConfig};
use mapless_learner::weights::{ServeOptions, WeightsPublisher, serve, write_safetensors_file};
use mapless_learner::{TorchThreads, checkpoint};
use mapless_replay::server::{ServerConfig, TlsFiles};
use serde::{Deserialize, Serialize};

/// Everything the learner process needs (`mapless train` writes it as `learner.yaml`).
#[derive(Clone, Debug, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct LearnerServiceConfig {
    /// Algorithm and hyperparameters.
    pub learner: LearnerConfig,
    /// Publishing, checkpoint and metrics cadence.
    #[serde(default)]
    pub driver: DriverConfig,
    /// Observation and action lengths (the replay table's).
    pub obs_dim: usize,
    pub act_dim: usize,
    /// The replay service, e.g. `http://127.0.0.1:50051`.
    pub replay: String,
    /// Where the weights service listens (`127.0.0.1:0`: any free port, printed on stdout).
    pub weights_listen: SocketAddr,
    /// Checkpoints go here; with `resume`, the newest one is loaded at start.
    pub checkpoint_dir: PathBuf,
    /// TensorBoard event files.
    pub tensorboard_dir: Option<PathBuf>,
    /// Newest published policy, for evaluation and deployment (`.safetensors`, written at
    /// start, every [`POLICY_FILE_EVERY`] while the weights version advances, and at exit).
    pub policy_file: Option<PathBuf>,
    /// Continue from the newest checkpoint in `checkpoint_dir` when there is one.
    #[serde(default)]
    pub resume: bool,
    /// libtorch threads (intra-op); inter-op is 1.
    #[serde(default = "one")]
    pub threads: usize,
    /// The weights service's TLS certificate and key (required, with `auth_token_file`, on a
    /// non-loopback `weights_listen`).
    #[serde(default)]
    pub tls: Option<TlsFiles>,
    /// File holding the bearer token subscribers must send.
    #[serde(default)]
    pub auth_token_file: Option<PathBuf>,
    /// CA and token for reaching a replay service on another host.
    #[serde(default)]
    pub replay_security: mapless_actor::run::Security,
    /// Prometheus `/metrics` address (loopback); none: off.
    #[serde(default)]
    pub metrics_listen: Option<SocketAddr>,
}

/// What `/metrics` shows.
#[derive(Default)]
struct Gauges {
    updates: AtomicU64,
    updates_per_s_milli: AtomicU64,
    weights_version: AtomicU64,
    batches: AtomicU64,
    reconnects: AtomicU64,
}

impl Gauges {
    fn render(&self) -> String {
        use mapless_actor::metrics::line;
        let g = |a: &AtomicU64| a.load(Ordering::Relaxed) as f64;
        let mut out = String::new();
        line(&mut out, "mapless_learner_updates_total", "counter", "Gradient updates done.", g(&self.updates));
        line(&mut out, "mapless_learner_updates_per_second", "gauge", "Updates per second over the last second.", g(&self.updates_per_s_milli) / 1000.0);
        line(&mut out, "mapless_learner_weights_version", "gauge", "Newest published weights version.", g(&self.weights_version));
        line(&mut out, "mapless_learner_minibatches_total", "counter", "Minibatches received from the replay.", g(&self.batches));
        line(&mut out, "mapless_learner_replay_reconnects_total", "counter", "Replay sample streams reopened.", g(&self.reconnects));
        out
    }
}

fn one() -> usize {
    1
}

/// Status line printed every second.
#[derive(Serialize)]
struct Status {
    event: &'static str,
    updates: u64,
    updates_per_s: f64,
    weights_version: u64,
    batches: u64,
    reconnects: u64,
}

/// How often the policy file follows the published weights (a progress evaluation reads it;
/// the actor's weights are a few hundred kB, written atomically).
const POLICY_FILE_EVERY: Duration = Duration::from_secs(5);

fn write_policy(driver: &Driver, path: &Option<PathBuf>) {
    if let Some(p) = path {
        match driver.snapshot() {
            Ok(mut s) => {
                // The file holds the newest *published* version.
                s.version = driver.weights_version().max(1);
                if let Err(e) = write_safetensors_file(p, &s) {
                    tracing::warn!(error = %e, "cannot write the policy file");
                }
            }
            Err(e) => tracing::warn!(error = %e, "cannot snapshot the policy"),
        }
    }
}

/// Writes `version` to `path` whole or not at all (a temporary file beside it, renamed over it).
/// Not fsynced: it changes about every second, on the update loop's thread, and is only a hint
/// for a resume (the checkpoint holds the version that counts).
fn write_version_file(path: &Path, version: u64) -> Result<()> {
    let dir = path.parent().filter(|d| !d.as_os_str().is_empty()).unwrap_or(Path::new("."));
    let mut tmp = tempfile::Builder::new().prefix(".").suffix(".tmp").permissions(std::os::unix::fs::PermissionsExt::from_mode(0o644)).tempfile_in(dir)?;
    std::io::Write::write_all(&mut tmp, format!("{version}\n").as_bytes())?;
    tmp.persist(path)?;
    Ok(())
}

fn has_checkpoint(dir: &Path) -> bool {
    checkpoint::resolve(dir).is_ok()
}

/// Runs the learner process until SIGINT/SIGTERM.
pub fn run(config_path: &Path) -> Result<()> {
    let text = std::fs::read_to_string(config_path).with_context(|| format!("reading {}", config_path.display()))?;
    let cfg: LearnerServiceConfig = serde_yaml::from_str(&text).with_context(|| format!("parsing {}", config_path.display()))?;
    cfg.learner.validate()?;
    TorchThreads { intra_op: cfg.threads.max(1), inter_op: 1 }.apply()?;

    let rt = tokio::runtime::Builder::new_multi_thread().worker_threads(1).thread_name("learner-io").enable_all().build()?;
    let stop = Arc::new(AtomicBool::new(false));
    let (stop_tx, stop_rx) = tokio::sync::watch::channel(false);
    {
        let stop = Arc::clone(&stop);
        rt.spawn(async move {
            crate::signals::termination().await;
            tracing::info!("signal received; stopping after this update");
            stop.store(true, Ordering::Relaxed);
        });
    }

    let endpoint: GrpcEndpoint = cfg.replay_security.endpoint(&cfg.replay)?;
    let mut source_cfg = GrpcSourceConfig::new(endpoint, cfg.learner.batch_size as u32);
    source_cfg.expected_dims = Some((cfg.obs_dim, cfg.act_dim));
    let source = Box::new(GrpcSource::start(source_cfg)?);
    let publisher = WeightsPublisher::new();
    let mut driver = if cfg.resume && has_checkpoint(&cfg.checkpoint_dir) {
        let d = Driver::resume(&cfg.checkpoint_dir, Some(&cfg.learner.device), source, publisher.clone(), cfg.driver.clone())?;
        tracing::info!(updates = d.agent().updates(), weights_version = d.weights_version(), "resumed from checkpoint");
        d
    } else {
        if cfg.resume {
            tracing::info!(dir = %cfg.checkpoint_dir.display(), "no checkpoint yet; starting fresh");
        }
        let agent = Agent::new(&cfg.learner, cfg.obs_dim, cfg.act_dim)?;
        Driver::new(agent, source, publisher.clone(), cfg.driver.clone(), 0)?
    };
    // The newest version ever published (written every second below), which may be above the
    // checkpoint's after a crash.
    let published_file = cfg.checkpoint_dir.join("PUBLISHED");
    if let Some(v) = std::fs::read_to_string(&published_file).ok().and_then(|t| t.trim().parse::<u64>().ok()) {
        driver.continue_versions_from(v);
    }
    driver = driver.with_checkpoints(&cfg.checkpoint_dir);
    if let Some(tb) = &cfg.tensorboard_dir {
        driver = driver.with_tensorboard(tb)?;
    }

    // Weights service; its address goes to stdout for the supervisor.
    let listener = rt.block_on(tokio::net::TcpListener::bind(cfg.weights_listen)).with_context(|| format!("binding the weights service on {}", cfg.weights_listen))?;
    let addr = listener.local_addr()?;
    let mut shutdown = stop_rx.clone();
    let security = ServerConfig { tls: cfg.tls.clone(), auth_token_file: cfg.auth_token_file.clone(), ..ServerConfig::default() }.security()?;
    if !addr.ip().is_loopback() && (security.tls.is_none() || security.token.is_none()) {
        anyhow::bail!("weights_listen {addr} is not loopback: set tls (cert, key) and auth_token_file, or listen on 127.0.0.1");
    }
    let options = ServeOptions { security, ..ServeOptions::default() };
    let server = rt.spawn(serve(listener, publisher, options, async move {
        let _ = shutdown.wait_for(|s| *s).await;
    }));
    let gauges = Arc::new(Gauges::default());
    if let Some(m) = cfg.metrics_listen {
        let g = Arc::clone(&gauges);
        let bound = mapless_actor::metrics::spawn(&rt, m, Arc::new(move || g.render()), stop_rx.clone()).with_context(|| format!("binding /metrics on {m}"))?;
        println!("metrics on http://{bound}/metrics");
    }
    println!("weights on {addr}");
    // Publish now: actors act with the initial (or, resumed, the newest) policy while the
    // replay fills.
    driver.publish()?;
    write_policy(&driver, &cfg.policy_file);

    let mut last = (Instant::now(), driver.agent().updates());
    let mut last_policy_write = Instant::now();
    let mut last_policy_version = driver.weights_version();
    let mut last_recorded_version = 0;
    while !stop.load(Ordering::Relaxed) {
        driver.try_step(Duration::from_millis(200))?;
        if last.0.elapsed() >= Duration::from_secs(1) {
            let n = driver.agent().updates();
            let s = driver.source().stats();
            let status = Status {
                event: "status",
                updates: n,
                updates_per_s: (n - last.1) as f64 / last.0.elapsed().as_secs_f64(),
                weights_version: driver.weights_version(),
                batches: s.batches,
                reconnects: s.reconnects,
            };
            println!("{}", serde_json::to_string(&status)?);
            if status.weights_version != last_recorded_version {
                std::fs::create_dir_all(&cfg.checkpoint_dir)?;
                write_version_file(&published_file, status.weights_version)?;
                last_recorded_version = status.weights_version;
            }
            gauges.updates.store(status.updates, Ordering::Relaxed);
            gauges.updates_per_s_milli.store((status.updates_per_s * 1000.0) as u64, Ordering::Relaxed);
            gauges.weights_version.store(status.weights_version, Ordering::Relaxed);
            gauges.batches.store(status.batches, Ordering::Relaxed);
            gauges.reconnects.store(status.reconnects, Ordering::Relaxed);
            last = (Instant::now(), n);
        }
        if last_policy_write.elapsed() >= POLICY_FILE_EVERY && driver.weights_version() != last_policy_version {
            write_policy(&driver, &cfg.policy_file);
            last_policy_write = Instant::now();
            last_policy_version = driver.weights_version();
        }
    }
    // Final: publish, checkpoint, policy file.
    if driver.agent().updates() > 0 {
        driver.publish()?;
    }
    let ck = driver.checkpoint()?;
    write_policy(&driver, &cfg.policy_file);
    tracing::info!(checkpoint = %ck.display(), updates = driver.agent().updates(), weights_version = driver.weights_version(), "final checkpoint written");
    println!("{}", serde_json::json!({"event": "stopped", "updates": driver.agent().updates(), "weights_version": driver.weights_version(), "checkpoint": ck}));
    let _ = stop_tx.send(true);
    let _ = rt.block_on(server);
    rt.shutdown_timeout(Duration::from_secs(2));
    Ok(())
}
