//! `mapless-replay`: the replay service process — one table, served over gRPC, with
//! Prometheus metrics, until SIGINT or SIGTERM.
//!
//! ```text
//!  config file ─┐
//!  flags ───────┴─► ServerConfig ─► DurableTable::open (restores --data-dir) ─► gRPC  (listen)
//!                                                                           └─► /metrics (metrics)
//!  SIGINT/SIGTERM ─► streams end UNAVAILABLE ─► servers stop ─► DurableTable::close (final snapshot)
//! ```
//!
//! Prints `listening on ADDR` (and `metrics on http://ADDR/metrics`) on stdout once bound, so a
//! caller that passed `--listen 127.0.0.1:0` can read the port.
//!
//! `mapless-replay health [ADDR] [--tls-ca-file F] [--token-file F]` is the probe of a
//! container's HEALTHCHECK: it asks the standard gRPC health service and exits 0 when the
//! replay is SERVING, 1 otherwise (its flags may come from `MAPLESS_HEALTH_*` variables).

use std::io::Write as _;
use std::net::SocketAddr;
use std::path::PathBuf;
use std::process::ExitCode;
use std::sync::Arc;

use anyhow::{Context, Result};
use clap::{Parser, Subcommand, ValueEnum};
use mapless_net::TlsFiles;
use mapless_net::health::{GrpcProbeArgs, InfoArgs, grpc_probe, replay_info};
use mapless_net::metrics::MetricsAccess;
use mapless_replay::server::{DEFAULT_LISTEN, ServerConfig, serve};
use mapless_replay::shm::ShmIngest;
use mapless_replay::{DurableTable, SamplerConfig, metrics};
use tokio::net::TcpListener;
use tokio::sync::watch;
use tracing::{Instrument, info, info_span, warn};

#[derive(Clone, Copy, Debug, ValueEnum)]
enum Sampler {
    Uniform,
    Prioritized,
}

/// The mapless experience replay service. Flags override the config file; the file's
/// missing keys take their defaults.
#[derive(Debug, Parser)]
#[command(name = "mapless-replay", version, args_conflicts_with_subcommands = true)]
struct Cli {
    #[command(subcommand)]
    cmd: Option<Cmd>,
    /// YAML config file (see replay/README.md).
    #[arg(long)]
    config: Option<PathBuf>,
    /// gRPC address [default: 127.0.0.1:50051]. Non-loopback addresses need --tls-cert,
    /// --tls-key and --auth-token-file.
    #[arg(long, value_name = "ADDR")]
    listen: Option<SocketAddr>,
    /// Prometheus /metrics address [default: 127.0.0.1:9464].
    #[arg(long, value_name = "ADDR", conflicts_with = "no_metrics")]
    metrics: Option<SocketAddr>,
    /// Do not serve /metrics.
    #[arg(long)]
    no_metrics: bool,
    /// Table name [default: transitions].
    #[arg(long)]
    table_name: Option<String>,
    /// Rows kept [default: 1000000, paper Table I].
    #[arg(long)]
    capacity: Option<usize>,
    /// Observation length [default: 17].
    #[arg(long)]
    obs_dim: Option<usize>,
    /// Action length [default: 2].
    #[arg(long)]
    act_dim: Option<usize>,
    /// Sampling strategy [default: uniform]; `prioritized` keeps the file's alpha/beta/epsilon
    /// when the file already chose it.
    #[arg(long, value_enum)]
    sampler: Option<Sampler>,
    /// Rows stored before the first sample [default: 1000].
    #[arg(long)]
    min_size_to_sample: Option<u64>,
    /// Sampled rows per inserted row (unset: no ratio).
    #[arg(long)]
    samples_per_insert: Option<f64>,
    /// Rate limiter slack in sampled rows [default: 100000].
    #[arg(long)]
    error_buffer: Option<f64>,
    /// Largest SampleRequest.prefetch honoured [default: 16].
    #[arg(long)]
    max_prefetch: Option<u32>,
    /// Most Sample streams open at once; more are refused with RESOURCE_EXHAUSTED [default: 256].
    #[arg(long)]
    max_sample_streams: Option<u32>,
    /// Seed of the sampler's random stream [default: 0].
    #[arg(long)]
    seed: Option<u64>,
    /// Persist the table here (write-ahead log + snapshots); restored on start.
    #[arg(long, value_name = "DIR")]
    data_dir: Option<PathBuf>,
    /// Do not ingest over iceoryx2 shared memory (gRPC only).
    #[arg(long)]
    no_shm: bool,
    /// TLS certificate chain (PEM).
    #[arg(long, requires = "tls_key")]
    tls_cert: Option<PathBuf>,
    /// TLS private key (PEM).
    #[arg(long, requires = "tls_cert")]
    tls_key: Option<PathBuf>,
    /// File holding a full-rights bearer token (every method; `auth_token_file`). Tokens per
    /// role (actor, learner) are set in the config file's `auth_token_files`.
    #[arg(long, value_name = "FILE")]
    auth_token_file: Option<PathBuf>,
    /// Log JSON objects instead of text.
    #[arg(long)]
    log_json: bool,
    /// Print the effective configuration as YAML and exit.
    #[arg(long)]
    print_config: bool,
}

#[derive(Debug, Subcommand)]
enum Cmd {
    /// Asks a replay whether it is SERVING (grpc.health.v1.Health/Check): exit 0 if so, else 1
    /// with the reason. For a container's HEALTHCHECK.
    Health(GrpcProbeArgs),
    /// Asks a replay for its ServerInfo: the table's size and capacity, and the rows, batches
    /// and duplicates each actor id has stored. Needs the learner role's token (or the
    /// full-rights one) where the replay checks tokens.
    Info(InfoArgs),
}

impl Cli {
    fn config(&self) -> Result<ServerConfig> {
        let mut c = match &self.config {
            Some(path) => ServerConfig::from_yaml_file(path)?,
            None => ServerConfig::default(),
        };
        let t = &mut c.table;
        macro_rules! set {
            ($flag:expr => $field:expr) => {
                if let Some(v) = $flag.clone() {
                    $field = v;
                }
            };
        }
        set!(self.listen => c.listen);
        set!(self.table_name => t.name);
        set!(self.capacity => t.capacity);
        set!(self.obs_dim => t.obs_dim);
        set!(self.act_dim => t.act_dim);
        set!(self.min_size_to_sample => t.rate_limiter.min_size_to_sample);
        set!(self.error_buffer => t.rate_limiter.error_buffer);
        set!(self.max_prefetch => c.max_prefetch);
        set!(self.max_sample_streams => c.max_sample_streams);
        set!(self.seed => c.seed);
        if let Some(spi) = self.samples_per_insert {
            t.rate_limiter.samples_per_insert = Some(spi);
        }
        match self.sampler {
            Some(Sampler::Uniform) => t.sampler = SamplerConfig::Uniform,
            Some(Sampler::Prioritized) if !matches!(t.sampler, SamplerConfig::Prioritized { .. }) => {
                t.sampler = serde_yaml::from_str("kind: prioritized").context("default prioritized sampler")?;
            }
            _ => {}
        }
        if self.metrics.is_some() {
            c.metrics_listen = self.metrics;
        }
        if self.no_metrics {
            c.metrics_listen = None;
        }
        if let Some(dir) = &self.data_dir {
            c.persistence.dir = Some(dir.clone());
        }
        if self.no_shm {
            c.shm_enabled = false;
        }
        if let (Some(cert), Some(key)) = (&self.tls_cert, &self.tls_key) {
            c.tls = Some(TlsFiles { cert: cert.clone(), key: key.clone() });
        }
        if let Some(f) = &self.auth_token_file {
            c.auth_token_file = Some(f.clone());
        }
        c.log_json |= self.log_json;
        Ok(c)
    }
}

fn init_logging(json: bool) {
    mapless_net::logging::init(json, "info");
    mapless_net::logging::identify(&[("role", "replay")]);
}

fn main() -> ExitCode {
    let cli = Cli::parse();
    match &cli.cmd {
        Some(Cmd::Health(args)) => return grpc_probe("mapless-replay", args, DEFAULT_LISTEN),
        Some(Cmd::Info(args)) => return replay_info(args, DEFAULT_LISTEN),
        None => {}
    }
    let runtime = match tokio::runtime::Builder::new_multi_thread().enable_all().build() {
        Ok(r) => r,
        Err(e) => {
            eprintln!("mapless-replay: cannot start the async runtime: {e}");
            return ExitCode::FAILURE;
        }
    };
    match runtime.block_on(start(cli)) {
        Ok(()) => ExitCode::SUCCESS,
        Err(e) => {
            // `{:#}` prints the whole context chain on one line, without a backtrace.
            eprintln!("mapless-replay: {e:#}");
            ExitCode::FAILURE
        }
    }
}

async fn start(cli: Cli) -> Result<()> {
    let cfg = cli.config()?;
    if cli.print_config {
        print!("{}", serde_yaml::to_string(&cfg)?);
        return Ok(());
    }
    init_logging(cfg.log_json);
    // Refuse an insecure non-loopback address (and bad table settings) before touching disk.
    cfg.validate()?;
    let options = cfg.serve_options()?;
    let span = info_span!("replay", table = %cfg.table.name);
    run(cfg, options).instrument(span).await
}

async fn run(cfg: ServerConfig, mut options: mapless_replay::server::ServeOptions) -> Result<()> {
    // ── Table construction: the one place the table is built. ───────────────────────────
    // DurableTable::open restores what `persistence.dir` (--data-dir) holds; with no dir the
    // table lives in memory only. Opening replays the log, so it runs off the async runtime.
    let (table_cfg, persistence, seed) = (cfg.table.clone(), cfg.persistence.clone(), cfg.seed);
    let (durable, report) = tokio::task::spawn_blocking(move || DurableTable::open(table_cfg, persistence, seed)).await.context("table open task")?.context("opening the replay table")?;
    if cfg.persistence.dir.is_some() {
        info!(rows = report.rows, records = report.records_replayed, snapshot = ?report.snapshot, fault = ?report.fault, elapsed = ?report.elapsed, "table restored");
        for w in &report.warnings {
            warn!("{w}");
        }
    }
    let table = Arc::clone(durable.table());
    // Actor slots (`RegisterActor`) live beside the table's files, under the table's lock.
    let registry = Arc::new(cfg.open_registry().context("loading the actor slots")?);
    if let Some(path) = registry.path() {
        info!(path = %path.display(), registered = registry.counts().registered, max = registry.max_slots(), "actor slots loaded");
    }
    options.registry = Arc::clone(&registry);
    // ─────────────────────────────────────────────────────────────────────────────────────

    // Same-host actors write over shared memory into the same table (cleans stale iceoryx2
    // resources left by killed processes before it opens its service).
    let shm = if cfg.shm_enabled {
        let (t, shm_cfg) = (Arc::clone(&table), cfg.shm_config());
        let ingest = tokio::task::spawn_blocking(move || ShmIngest::spawn(t, shm_cfg)).await.context("shm ingest task")?.context("starting the shared-memory ingest")?;
        println!("shm ingest on {}", ingest.service_name());
        Some(ingest)
    } else {
        None
    };

    let listener = TcpListener::bind(cfg.listen).await.with_context(|| format!("binding gRPC address {}", cfg.listen))?;
    let addr = listener.local_addr()?;
    // The token is read only when /metrics is on (`--no-metrics` needs no file).
    let metrics_access = if cfg.metrics_listen.is_some() { MetricsAccess::from_token_file(cfg.metrics_token_file.as_deref())? } else { MetricsAccess::open() };
    let metrics_listener = match cfg.metrics_listen {
        Some(m) => Some(TcpListener::bind(m).await.with_context(|| format!("binding metrics address {m}"))?),
        None => None,
    };
    let (stop_tx, stop_rx) = watch::channel(false);
    let stopped = |mut rx: watch::Receiver<bool>| async move {
        let _ = rx.wait_for(|s| *s).await;
    };
    let metrics_task = match metrics_listener {
        Some(l) => {
            let maddr = l.local_addr()?;
            info!(addr = %maddr, "metrics serving");
            println!("metrics on http://{maddr}/metrics");
            let (table, registry, refusals, health) = (Arc::clone(&table), Arc::clone(&registry), options.security.refusals.clone(), options.health.clone());
            let rx = stop_rx.clone();
            Some(tokio::spawn(async move { metrics::serve(l, table, registry, refusals, health, metrics_access, stopped(rx)).await }.in_current_span()))
        }
        None => None,
    };
    info!(%addr, capacity = cfg.table.capacity, obs_dim = cfg.table.obs_dim, act_dim = cfg.table.act_dim, "listening");
    println!("listening on {addr}");
    std::io::stdout().flush()?;

    let stop_tx = Arc::new(stop_tx);
    let on_signal = Arc::clone(&stop_tx);
    tokio::spawn(
        async move {
            mapless_net::signals::termination().await;
            on_signal.send_replace(true);
        }
        .in_current_span(),
    );
    let served = serve(listener, Arc::clone(&table), options, stopped(stop_rx)).await;
    // Also stops /metrics when gRPC serving failed rather than being signalled.
    stop_tx.send_replace(true);
    if let Some(task) = metrics_task {
        match task.await {
            Ok(Ok(())) => {}
            Ok(Err(e)) => warn!(error = %e, "metrics server failed"),
            Err(e) => warn!(error = %e, "metrics task failed"),
        }
    }
    // Stop shared-memory ingest, then the final snapshot and log sync for a persistent table;
    // close wakes anything still blocked.
    tokio::task::spawn_blocking(move || {
        if let Some(ingest) = shm {
            ingest.stop();
        }
        durable.close()
    })
    .await
    .context("table close task")?;
    served?;
    info!(size = table.size(), "stopped");
    Ok(())
}
