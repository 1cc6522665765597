//! `mapless-learner`: the learner process of a cluster — samples from the replay service over
//! gRPC, updates, publishes versioned weights on its own gRPC service, checkpoints, writes
//! TensorBoard scalars, and prints one JSON status line per second on stdout (what the
//! supervisor of `mapless train` reads).
//!
//! ```text
//!   replay ══Sample (prefetch)══► GrpcSource ─► Driver (update, publish every K, checkpoint every N)
//!                                                  └─► WeightsService (127.0.0.1 by default) ══► actors
//! ```
//! SIGINT/SIGTERM: stop after the current update, publish, checkpoint, exit 0.
//!
//! `mapless-learner --config learner.yaml [--run NAME]` runs it (`mapless train` starts it so);
//! `mapless-learner bench` measures updates per second (what `mapless bench learner` runs);
//! `mapless-learner health [ADDR] [--tls-ca-file F] [--token-file F]` asks a learner's gRPC
//! health service and exits 0 when it is SERVING (it has published weights), 1 otherwise — the
//! probe of a container's HEALTHCHECK.
//! The only executable that links libtorch.

use std::io::Write as _;
use std::path::{Path, PathBuf};
use std::process::ExitCode;
use std::sync::Arc;
use std::sync::atomic::{AtomicBool, AtomicU64, Ordering};
use std::time::{Duration, Instant};

use anyhow::{Context, Result, bail};
use clap::{Parser, Subcommand};
use mapless_learner::algo::{Agent, bench_updates};
use mapless_learner::config::{AlgorithmKind, LearnerConfig, LearnerEvent, LearnerServiceConfig};
use mapless_learner::driver::Driver;
use mapless_learner::source::{GrpcEndpoint, GrpcSource, SampleConfig};
use mapless_learner::weights::{DEFAULT_WEIGHTS_LISTEN, ServeOptions, WeightsPublisher, serve};
use mapless_learner::{Device, TorchThreads, checkpoint, device};
use mapless_net::health::{GrpcProbeArgs, Health, grpc_probe};
use mapless_net::metrics::{self, bench_report};
use mapless_net::serve::Security;
use mapless_proto::atomic_file::{Durability, write_file_atomically_with};
use mapless_proto::weights_file::write_safetensors_file;

#[derive(Parser)]
#[command(
    name = "mapless-learner",
    version,
    about = "The learner process of a mapless cluster (libtorch): samples from the replay, updates, publishes weights.",
    args_conflicts_with_subcommands = true
)]
struct Cli {
    /// Learner config (YAML; `mapless train` writes `run/learner.yaml`).
    #[arg(long)]
    config: Option<PathBuf>,
    /// Run name for the log lines.
    #[arg(long, default_value = "")]
    run: String,
    /// Log JSON lines instead of text.
    #[arg(long, global = true)]
    log_json: bool,
    #[command(subcommand)]
    cmd: Option<Cmd>,
}

#[derive(Subcommand)]
enum Cmd {
    /// Gradient updates per second for DDPG, TD3 and SAC at the paper's sizes (17-float
    /// observations, 2 actions, 2×256 hidden, minibatch 128), with 1 and 2 threads
    /// (`mapless bench learner` runs this).
    Bench(BenchArgs),
    /// Asks a learner whether it is SERVING (grpc.health.v1.Health/Check on its weights
    /// service): exit 0 if so, else 1 with the reason. For a container's HEALTHCHECK.
    Health(GrpcProbeArgs),
}

#[derive(clap::Args)]
struct BenchArgs {
    /// Seconds per configuration.
    #[arg(long, default_value_t = 5.0)]
    seconds: f64,
    /// `cpu`, `cuda` or `cuda:N`.
    #[arg(long, default_value = "cpu")]
    device: String,
    /// libtorch intra-op thread counts to measure.
    #[arg(long, value_delimiter = ',', default_value = "1,2")]
    threads: Vec<usize>,
    /// Algorithms to measure.
    #[arg(long, value_delimiter = ',', default_value = "ddpg,td3,sac")]
    algos: Vec<String>,
    /// Also measure with the twin critics evaluated one after the other (TD3, SAC; the
    /// autograd path).
    #[arg(long)]
    unfused: bool,
    /// Also measure the libtorch autograd path (`fused_update: false`), for comparison
    /// with the default fused CPU update.
    #[arg(long)]
    autograd: bool,
    /// Measure with layer-normalised critics (`critic_layer_norm`).
    #[arg(long)]
    critic_layer_norm: bool,
    /// One JSON object per line: {"bench", "config", "value", "unit"}.
    #[arg(long)]
    json: bool,
    /// Minibatch size (default: the learner config's default, 128).
    #[arg(long)]
    batch_size: Option<usize>,
    /// Hidden layer width (default: the learner config's default, 256).
    #[arg(long)]
    hidden_width: Option<i64>,
}

fn main() -> ExitCode {
    let cli = Cli::parse();
    if let Some(Cmd::Health(args)) = &cli.cmd {
        return grpc_probe("mapless-learner", args, DEFAULT_WEIGHTS_LISTEN);
    }
    // Benchmarks would drown their figures in info lines.
    mapless_net::logging::init(cli.log_json, if cli.cmd.is_some() { "warn" } else { "info" });
    mapless_net::logging::identify(&[("run", &cli.run), ("role", "learner")]);
    let result = match (&cli.cmd, &cli.config) {
        (Some(Cmd::Bench(a)), _) => bench(a),
        (Some(Cmd::Health(_)), _) => unreachable!("answered above"),
        (None, Some(config)) => run(config),
        (None, None) => Err(anyhow::anyhow!("give --config FILE (the learner's YAML; `mapless train` writes run/learner.yaml), or a subcommand")),
    };
    match result {
        Ok(()) => ExitCode::SUCCESS,
        Err(e) => {
            eprintln!("error: {e:#}");
            ExitCode::FAILURE
        }
    }
}

/// What `/metrics` shows.
#[derive(Default)]
struct Gauges {
    updates: AtomicU64,
    updates_per_s_milli: AtomicU64,
    weights_version: AtomicU64,
    batches: AtomicU64,
    reconnects: AtomicU64,
    checkpoint_failures: AtomicU64,
}

impl Gauges {
    fn render(&self, refusals: &mapless_net::AuthRefusals) -> String {
        let g = |a: &AtomicU64| a.load(Ordering::Relaxed) as f64;
        let mut x = metrics::Exposition::new();
        x.counter("mapless_learner_updates", "Gradient updates done.", g(&self.updates))
            .gauge("mapless_learner_updates_per_second", "Updates per second over the last second.", g(&self.updates_per_s_milli) / 1000.0)
            .gauge("mapless_learner_weights_version", "Newest published weights version.", g(&self.weights_version))
            .counter("mapless_learner_minibatches", "Minibatches received from the replay.", g(&self.batches))
            .counter("mapless_learner_replay_reconnects", "Replay sample streams reopened.", g(&self.reconnects))
            .counter("mapless_learner_checkpoint_failures", "Periodic checkpoints that could not be written (a full disk, an I/O error); training went on.", g(&self.checkpoint_failures));
        refusals.write(&mut x, "mapless_learner_auth_refusals");
        x.text()
    }
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
    write_file_atomically_with(path, Durability::Unsynced, |f| f.write_all(format!("{version}\n").as_bytes()))?;
    Ok(())
}

fn has_checkpoint(dir: &Path) -> bool {
    checkpoint::resolve(dir).is_ok()
}

/// Runs the learner process until SIGINT/SIGTERM.
fn run(config_path: &Path) -> Result<()> {
    let text = std::fs::read_to_string(config_path).with_context(|| format!("reading {}", config_path.display()))?;
    let cfg: LearnerServiceConfig = serde_yaml::from_str(&text).with_context(|| format!("parsing {}", config_path.display()))?;
    cfg.learner.validate()?;
    TorchThreads { intra_op: cfg.threads.max(1), inter_op: 1 }.apply()?;

    let rt = tokio::runtime::Builder::new_multi_thread().worker_threads(1).thread_name("learner-io").enable_all().build()?;
    let stop = Arc::new(AtomicBool::new(false));
    let (stop_tx, stop_rx) = tokio::sync::watch::channel(false);
    // SERVING once the first weights are out, NOT_SERVING from the stop signal on (the last
    // update, publication and checkpoint are still to come then).
    let health = Health::new();
    {
        let (stop, health) = (Arc::clone(&stop), health.clone());
        rt.spawn(async move {
            mapless_net::signals::termination().await;
            tracing::info!("signal received; stopping after this update");
            health.drain();
            stop.store(true, Ordering::Relaxed);
        });
    }

    let endpoint: GrpcEndpoint = cfg.replay_security.endpoint(&cfg.replay)?;
    let mut source_cfg = SampleConfig::new(endpoint, cfg.learner.batch_size as u32);
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
    let security = Security::read(cfg.tls.as_ref(), cfg.auth_token_file.as_deref(), &cfg.auth_token_files)?;
    if !security.allows(&addr) {
        bail!("weights_listen {addr} is not loopback: set tls (cert, key) and a token (auth_token_files: {{actor: FILE}}, or auth_token_file), or listen on 127.0.0.1");
    }
    let refusals = security.refusals.clone();
    let options = ServeOptions { security, health: health.clone(), ..ServeOptions::default() };
    let server = rt.spawn(serve(listener, publisher, options, async move {
        let _ = shutdown.wait_for(|s| *s).await;
    }));
    let gauges = Arc::new(Gauges::default());
    if let Some(m) = cfg.metrics_listen {
        let g = Arc::clone(&gauges);
        let access = metrics::MetricsAccess::from_token_file(cfg.metrics_token_file.as_deref())?;
        let bound = metrics::spawn(&rt, m, Arc::new(move || g.render(&refusals)), health.clone(), access, stop_rx.clone()).with_context(|| format!("binding /metrics on {m}"))?;
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
    let mut published_file_ok = true;
    while !stop.load(Ordering::Relaxed) {
        driver.try_step(Duration::from_millis(200))?;
        if last.0.elapsed() >= Duration::from_secs(1) {
            let n = driver.agent().updates();
            let s = driver.source().stats();
            let updates_per_s = (n - last.1) as f64 / last.0.elapsed().as_secs_f64();
            let weights_version = driver.weights_version();
            println!("{}", serde_json::to_string(&LearnerEvent::Status { updates: n, updates_per_s, weights_version, batches: s.batches, reconnects: s.reconnects })?);
            if weights_version != last_recorded_version {
                // A hint for a resume, not state: on a full disk it waits for space (warned once).
                match std::fs::create_dir_all(&cfg.checkpoint_dir).map_err(anyhow::Error::from).and_then(|()| write_version_file(&published_file, weights_version)) {
                    Ok(()) => last_recorded_version = weights_version,
                    Err(e) if published_file_ok => {
                        tracing::warn!(error = %format!("{e:#}"), file = %published_file.display(), "cannot record the published version; trying again each second");
                        published_file_ok = false;
                    }
                    Err(_) => {}
                }
                published_file_ok |= last_recorded_version == weights_version;
            }
            gauges.updates.store(n, Ordering::Relaxed);
            gauges.updates_per_s_milli.store((updates_per_s * 1000.0) as u64, Ordering::Relaxed);
            gauges.weights_version.store(weights_version, Ordering::Relaxed);
            gauges.batches.store(s.batches, Ordering::Relaxed);
            gauges.reconnects.store(s.reconnects, Ordering::Relaxed);
            gauges.checkpoint_failures.store(driver.checkpoint_failures(), Ordering::Relaxed);
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
    let ck = driver.checkpoint().context("writing the final checkpoint (the newest one before it, named by LATEST, is still whole)")?;
    write_policy(&driver, &cfg.policy_file);
    tracing::info!(checkpoint = %ck.display(), updates = driver.agent().updates(), weights_version = driver.weights_version(), "final checkpoint written");
    println!("{}", serde_json::to_string(&LearnerEvent::Stopped { updates: driver.agent().updates(), weights_version: driver.weights_version(), checkpoint: ck })?);
    let _ = stop_tx.send(true);
    let _ = rt.block_on(server);
    rt.shutdown_timeout(Duration::from_secs(2));
    Ok(())
}

/// `mapless-learner bench`: updates per second, and the matrix-product ceiling they are held
/// against (`mapless_learner::ceiling`).
fn bench(a: &BenchArgs) -> Result<()> {
    let BenchArgs { seconds, ref device, ref threads, ref algos, unfused, autograd, critic_layer_norm, json, batch_size, hidden_width } = *a;
    let defaults = LearnerConfig::default();
    let (batch_size, hidden_width) = (batch_size.unwrap_or(defaults.batch_size), hidden_width.unwrap_or(defaults.hidden_width));
    if batch_size == 0 || hidden_width < 1 {
        bail!("--batch-size and --hidden-width must be ≥ 1");
    }
    if !(seconds > 0.0) || threads.is_empty() || threads.contains(&0) {
        bail!("--seconds must be > 0 and every --threads count ≥ 1");
    }
    // Fails here, with the reason, when the device is not usable on this machine.
    device::available(device)?;
    let (obs_dim, act_dim) = (17usize, 2usize);
    let kinds = algos
        .iter()
        .map(|a| match a.trim().to_ascii_lowercase().as_str() {
            "ddpg" => Ok(AlgorithmKind::Ddpg),
            "td3" => Ok(AlgorithmKind::Td3),
            "sac" => Ok(AlgorithmKind::Sac),
            other => bail!("unknown algorithm `{other}` (expected ddpg, td3 or sac)"),
        })
        .collect::<Result<Vec<_>>>()?;
    if !json {
        println!("learner updates per second on {device}: obs {obs_dim}, act {act_dim}, 2×{hidden_width} hidden, minibatch {batch_size}, {seconds} s each");
    }
    let dev = device::available(device)?;
    for &t in threads.iter() {
        TorchThreads { intra_op: t, inter_op: 1 }.apply()?;
        // The bound every algorithm is measured against: libtorch's product of the hidden
        // layer's shape, here, with these threads (mapless_learner::ceiling).
        let base = LearnerConfig { batch_size, hidden_width, ..LearnerConfig::default() };
        let shape = format!("{}x{}x{}", base.batch_size, base.hidden_width, base.hidden_width);
        let mut f32_gflops = 0.0;
        for (name, bf16) in [("f32", false), ("bf16", true)] {
            let g = mapless_learner::ceiling::matmul_gflops(base.batch_size as i64, base.hidden_width, bf16, dev, seconds.min(2.0))?;
            if name == "f32" {
                f32_gflops = g;
            }
            bench_report(json, "learner.matmul_gflops", serde_json::json!({"device": device, "threads": t, "dtype": name, "shape": shape}), g, "GFLOP/s");
        }
        for &kind in &kinds {
            // (fused_update, fused_critics): the default first, then what was asked for.
            let mut variants = vec![(true, true)];
            if autograd {
                variants.push((false, true));
            }
            if unfused && kind != AlgorithmKind::Ddpg {
                variants.push((false, false));
            }
            for (fused_update, fused) in variants {
                let cfg = LearnerConfig { algorithm: kind, device: device.to_owned(), fused_critics: fused, fused_update, critic_layer_norm, batch_size, hidden_width, ..LearnerConfig::default() };
                // libtorch fixes the inter-op pool once per process; only the intra-op count varies.
                let v = bench_updates(&cfg, obs_dim, act_dim, TorchThreads { intra_op: t, inter_op: 1 }, seconds)?;
                // The fused update runs on the CPU only; elsewhere the autograd path runs.
                let path = if fused_update && dev == Device::Cpu { "fused" } else { "autograd" };
                let config = serde_json::json!({"algo": kind.as_str(), "device": device, "threads": t, "obs_dim": obs_dim, "act_dim": act_dim, "hidden": cfg.hidden_width, "batch": cfg.batch_size, "update": path, "fused_critics": fused && kind != AlgorithmKind::Ddpg, "critic_layer_norm": critic_layer_norm});
                bench_report(json, "learner.updates_per_s", config, v, "updates/s");
                if fused_update {
                    // Matrix-product work per update, and the updates/s that f32 products alone
                    // would allow at the rate just measured: an estimate of the most f32 code can do.
                    let flops = mapless_learner::ceiling::update_flops(&cfg, obs_dim, act_dim);
                    let bound = f32_gflops * 1e9 / flops;
                    let config = serde_json::json!({"algo": kind.as_str(), "device": device, "threads": t, "flop_per_update": flops, "f32_matmul_gflops": (f32_gflops * 10.0).round() / 10.0});
                    bench_report(json, "learner.f32_ceiling_updates_per_s", config.clone(), bound, "updates/s");
                    bench_report(json, "learner.share_of_f32_ceiling", config, v / bound, "fraction");
                }
            }
        }
    }
    Ok(())
}
