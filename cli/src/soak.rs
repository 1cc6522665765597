//! `mapless bench soak`: the replay and the learner under many streams for a long time, with
//! their resources watched (issue 19 §2).
//!
//! ```text
//!  this process                                   children (the real binaries)
//!  ─────────────                                  ────────────────────────────
//!  S insert streams (one actor id each, paced) ──► mapless-replay  (persistence on, prioritised)
//!  K Sample streams + UpdatePriorities         ──►      ▲ Sample + priorities (batch 128)
//!  W weights subscribers                       ◄── mapless-learner (the learner-sized sampler,
//!  every `interval`: /proc of both children,          publishing its weights every 50 updates)
//!  the persistence folder, the learner's /metrics
//! ```
//!
//! Every `interval` it prints one line (and, with `--out`, appends a CSV row): rows/s acked,
//! insert and sample latency p50/p99 in that window, the learner's updates/s, and each
//! child's resident memory, threads and open files, and the bytes of the replay's folder.
//!
//! It fails (exit status 1) when
//! - a stream stalls: an insert stream with no acknowledgement, a sampler with no minibatch,
//!   or the learner with no update for `--stall-s`; a weights subscriber that has not received
//!   for `--stall-s` while another holds a newer version;
//! - a resource keeps growing: after the warm-up (the table full and a fifth of the run gone),
//!   its least-squares trend over the rest of the run adds up to more than a margin (memory:
//!   5 % of its mean + 16 MiB; threads: 2; open files: 8; the replay's folder: 25 % + 64 MiB,
//!   since snapshots and log segments come and go);
//! - any request fails or a child exits.

use std::fs;
use std::net::SocketAddr;
use std::path::{Path, PathBuf};
use std::sync::atomic::{AtomicBool, AtomicU64, Ordering};
use std::sync::{Arc, Mutex, mpsc as std_mpsc};
use std::time::{Duration, Instant};

use anyhow::{Context, Result, bail};
use mapless_learner_config::LearnerServiceConfig;
use mapless_net::GrpcEndpoint;
use mapless_net::metrics::bench_report;
use mapless_proto::MAX_MESSAGE_BYTES;
use mapless_proto::v1::replay_service_client::ReplayServiceClient;
use mapless_proto::v1::{PriorityUpdate, ProtocolVersion, SampleRequest, TransitionBatch};
use mapless_replay::server::ServerConfig;
use mapless_replay::{RateLimiterConfig, SamplerConfig};
use rand::{Rng, SeedableRng};
use tokio::sync::mpsc;
use tokio_stream::wrappers::ReceiverStream;

use crate::train::{preset_config, sibling, start_service};

/// What `mapless bench soak` was asked for.
#[derive(clap::Args, Debug, Clone)]
pub struct SoakArgs {
    /// Insert streams, one actor id each (one gRPC connection each, as actor processes have).
    #[arg(long, default_value_t = 64)]
    pub streams: usize,
    /// Length of the run in minutes (0.5 for 30 s).
    #[arg(long, default_value_t = 10.0)]
    pub minutes: f64,
    /// Rows per second offered by all insert streams together; 0 = each as fast as acknowledged.
    /// [ours: 25,600 — 16× what `mapless train --preset env1-sac` inserts on 2 cores.]
    #[arg(long, default_value_t = 25_600.0)]
    pub rows_per_s: f64,
    /// Rows per insert batch.
    #[arg(long, default_value_t = 64)]
    pub batch_rows: usize,
    /// Sample streams besides the learner's, each sending priority updates for every minibatch.
    #[arg(long, default_value_t = 4)]
    pub samplers: usize,
    /// Minibatches per second each of those streams asks for; 0 = as fast as served.
    #[arg(long, default_value_t = 50.0)]
    pub sample_rate: f64,
    /// Weights subscribers following the learner (0 = one per insert stream, as actors do).
    #[arg(long, default_value_t = 0)]
    pub subscribers: usize,
    /// Rows the replay keeps [the paper's capacity, Table I: 1,000,000].
    #[arg(long, default_value_t = 1_000_000)]
    pub capacity: usize,
    /// Seconds between the replay's snapshots [default: the replay's 30 s, or a tenth of a
    /// shorter run, so that the log is cut several times whatever the run's length].
    #[arg(long)]
    pub snapshot_interval_s: Option<f64>,
    /// Seconds between samples of the figures.
    #[arg(long, default_value_t = 5.0)]
    pub interval_s: f64,
    /// A stream without progress for this long has stalled.
    #[arg(long, default_value_t = 20.0)]
    pub stall_s: f64,
    /// Folder for the replay's persistence, the learner's files and the logs (kept); a
    /// temporary one, removed at the end, by default.
    #[arg(long)]
    pub dir: Option<PathBuf>,
    /// Also write every sample of the figures to DIR/soak.csv, and DIR/soak.png: rows/s,
    /// latency p99 and each process's memory, threads and open files over the run.
    #[arg(long, value_name = "DIR")]
    pub out: Option<PathBuf>,
    /// One JSON object per line: {"bench", "config", "value", "unit"}.
    #[arg(long)]
    pub json: bool,
}

/// One sample of the figures, every `interval_s`.
#[derive(Debug, Clone, Copy, Default, serde::Serialize)]
struct Tick {
    t_s: f64,
    rows_per_s: f64,
    insert_p50_ms: f64,
    insert_p99_ms: f64,
    sample_p50_ms: f64,
    sample_p99_ms: f64,
    minibatches_per_s: f64,
    learner_updates_per_s: f64,
    weights_versions: u64,
    replay_rss_mib: f64,
    replay_threads: u64,
    replay_open_files: u64,
    replay_dir_mib: f64,
    learner_rss_mib: f64,
    learner_threads: u64,
    learner_open_files: u64,
    table_full: bool,
}

/// Progress shared by the client tasks: counters, this window's latencies, the time (ms since
/// the start) each stream last made progress.
struct Shared {
    start: Instant,
    stop: AtomicBool,
    acked_rows: AtomicU64,
    minibatches: AtomicU64,
    priority_updates: AtomicU64,
    insert_us: Mutex<Vec<u32>>,
    sample_us: Mutex<Vec<u32>>,
    all_insert_us: Mutex<Vec<u32>>,
    all_sample_us: Mutex<Vec<u32>>,
    insert_last_ms: Vec<AtomicU64>,
    sample_last_ms: Vec<AtomicU64>,
    sub_last_ms: Vec<AtomicU64>,
    sub_version: Vec<AtomicU64>,
    snapshots_received: AtomicU64,
    failures: AtomicU64,
    first_failures: Mutex<Vec<String>>,
}

impl Shared {
    fn now_ms(&self) -> u64 {
        self.start.elapsed().as_millis() as u64
    }

    fn failed(&self, what: String) {
        self.failures.fetch_add(1, Ordering::Relaxed);
        let mut f = self.first_failures.lock().expect("failures lock");
        if f.len() < 10 {
            f.push(what);
        }
    }

    fn stopping(&self) -> bool {
        self.stop.load(Ordering::Relaxed)
    }
}

fn record(window: &Mutex<Vec<u32>>, all: &Mutex<Vec<u32>>, d: Duration) {
    let us = d.as_micros().min(u32::MAX as u128) as u32;
    window.lock().expect("latency lock").push(us);
    all.lock().expect("latency lock").push(us);
}

/// p-quantile in ms of latencies in µs (sorts them); NaN for none.
fn quantile_ms(v: &mut [u32], p: f64) -> f64 {
    if v.is_empty() {
        return f64::NAN;
    }
    v.sort_unstable();
    v[((v.len() as f64 * p) as usize).min(v.len() - 1)] as f64 / 1000.0
}

async fn replay_client(addr: SocketAddr) -> Result<ReplayServiceClient<tonic::transport::Channel>> {
    let c = ReplayServiceClient::connect(format!("http://{addr}")).await.with_context(|| format!("connecting to the replay at {addr}"))?;
    Ok(c.max_decoding_message_size(MAX_MESSAGE_BYTES).max_encoding_message_size(MAX_MESSAGE_BYTES))
}

/// Sleeps until `next` unless stopping; returns false when stopping.
async fn pace(next: &mut Instant, period: Option<Duration>, s: &Shared) -> bool {
    if let Some(p) = period {
        let now = Instant::now();
        // Behind by more than a period: start afresh rather than burst to catch up.
        *next = if *next + p < now { now } else { *next + p };
        tokio::time::sleep_until((*next).into()).await;
    }
    !s.stopping()
}

/// One actor's insert stream: a paced batch, its acknowledgement, again. A failed stream is
/// counted and reopened after a second; sequence numbers go on, so nothing is inserted twice.
async fn insert_stream(i: usize, addr: SocketAddr, obs_dim: usize, a: Arc<SoakArgs>, s: Arc<Shared>) {
    let actor = format!("soak-{i:03}");
    let per_stream = a.rows_per_s / a.streams as f64;
    let period = (per_stream > 0.0).then(|| Duration::from_secs_f64(a.batch_rows as f64 / per_stream));
    let template = mapless_replay::bench::synthetic_batch(&actor, 1, a.batch_rows, obs_dim);
    // Spread the streams' phases over one period.
    let mut next = Instant::now() + period.map(|p| p.mul_f64(i as f64 / a.streams as f64)).unwrap_or_default();
    let mut seq = 0u64;
    'connect: while !s.stopping() {
        let opened: Result<_> = async {
            let mut c = replay_client(addr).await?;
            let (tx, rx) = mpsc::channel::<TransitionBatch>(1);
            let acks = c.insert(ReceiverStream::new(rx)).await.context("opening Insert")?.into_inner();
            Ok((tx, acks))
        }
        .await;
        let (tx, mut acks) = match opened {
            Ok(x) => x,
            Err(e) => {
                s.failed(format!("{actor}: {e:#}"));
                tokio::time::sleep(Duration::from_secs(1)).await;
                continue;
            }
        };
        while pace(&mut next, period, &s).await {
            seq += 1;
            let mut b = template.clone();
            b.sequence = seq;
            let t0 = Instant::now();
            if tx.send(b).await.is_err() {
                s.failed(format!("{actor}: the Insert stream closed"));
                tokio::time::sleep(Duration::from_secs(1)).await;
                continue 'connect;
            }
            match acks.message().await {
                Ok(Some(ack)) if ack.sequence == seq => {
                    record(&s.insert_us, &s.all_insert_us, t0.elapsed());
                    s.acked_rows.fetch_add(ack.accepted_rows as u64, Ordering::Relaxed);
                    s.insert_last_ms[i].store(s.now_ms(), Ordering::Relaxed);
                }
                Ok(Some(ack)) => {
                    s.failed(format!("{actor}: ack for sequence {} while {seq} was awaited", ack.sequence));
                }
                Ok(None) => {
                    s.failed(format!("{actor}: the replay ended the Insert stream"));
                    tokio::time::sleep(Duration::from_secs(1)).await;
                    continue 'connect;
                }
                Err(status) => {
                    s.failed(format!("{actor}: Insert: {:?}: {}", status.code(), status.message()));
                    tokio::time::sleep(Duration::from_secs(1)).await;
                    continue 'connect;
                }
            }
        }
        return;
    }
}

/// A learner-like sampler: a Sample stream (minibatch 128, prefetch 2), and for every
/// minibatch a priority update of its keys. Latency: how long it waited for each minibatch.
async fn sample_stream(j: usize, addr: SocketAddr, table: String, a: Arc<SoakArgs>, s: Arc<Shared>) {
    let mut rng = rand_pcg::Pcg64::seed_from_u64(j as u64);
    let period = (a.sample_rate > 0.0).then(|| Duration::from_secs_f64(1.0 / a.sample_rate));
    let mut next = Instant::now();
    'connect: while !s.stopping() {
        let opened: Result<_> = async {
            let mut c = replay_client(addr).await?;
            let req = SampleRequest {
                protocol_version: ProtocolVersion::V1 as i32,
                table: table.clone(),
                batch_size: 128,
                prefetch: 2,
                timeout_ms: 0,
                max_batches: 0,
                importance_beta: Some(0.4),
                float_columns_as_bytes: true,
            };
            let stream = c.sample(req).await.context("opening Sample")?.into_inner();
            Ok((c, stream))
        }
        .await;
        let (mut c, mut stream) = match opened {
            Ok(x) => x,
            Err(e) => {
                s.failed(format!("sampler {j}: {e:#}"));
                tokio::time::sleep(Duration::from_secs(1)).await;
                continue;
            }
        };
        while pace(&mut next, period, &s).await {
            let t0 = Instant::now();
            let batch = match stream.message().await {
                Ok(Some(b)) => b,
                Ok(None) => {
                    s.failed(format!("sampler {j}: the replay ended the Sample stream"));
                    continue 'connect;
                }
                Err(status) => {
                    s.failed(format!("sampler {j}: Sample: {:?}: {}", status.code(), status.message()));
                    tokio::time::sleep(Duration::from_secs(1)).await;
                    continue 'connect;
                }
            };
            record(&s.sample_us, &s.all_sample_us, t0.elapsed());
            s.minibatches.fetch_add(1, Ordering::Relaxed);
            s.sample_last_ms[j].store(s.now_ms(), Ordering::Relaxed);
            let priorities = batch.keys.iter().map(|_| rng.random_range(0.01..2.0)).collect();
            let update = PriorityUpdate { protocol_version: ProtocolVersion::V1 as i32, table: table.clone(), keys: batch.keys, priorities };
            match c.update_priorities(update).await {
                Ok(_) => {
                    s.priority_updates.fetch_add(1, Ordering::Relaxed);
                }
                Err(status) => s.failed(format!("sampler {j}: UpdatePriorities: {:?}: {}", status.code(), status.message())),
            }
        }
        return;
    }
}

/// One actor's weights follower: every snapshot the learner publishes (newest wins).
async fn subscriber(k: usize, weights: SocketAddr, s: Arc<Shared>) {
    let endpoint = GrpcEndpoint::new(format!("http://{weights}"));
    let id = format!("soak-sub-{k:03}");
    while !s.stopping() {
        let next_version = s.sub_version[k].load(Ordering::Relaxed) + 1;
        let mut sub = match mapless_net::weights::subscribe(&endpoint, next_version, &id).await {
            Ok(sub) => sub,
            Err(e) => {
                s.failed(format!("{id}: {e}"));
                tokio::time::sleep(Duration::from_secs(1)).await;
                continue;
            }
        };
        while !s.stopping() {
            let got = tokio::select! {
                got = sub.next() => got,
                _ = tokio::time::sleep(Duration::from_millis(250)) => {
                    if s.stopping() { return; }
                    continue;
                }
            };
            match got {
                Ok(Some(snap)) => {
                    s.sub_version[k].store(snap.version, Ordering::Relaxed);
                    s.sub_last_ms[k].store(s.now_ms(), Ordering::Relaxed);
                    s.snapshots_received.fetch_add(1, Ordering::Relaxed);
                }
                Ok(None) => break,
                Err(e) => {
                    if !s.stopping() {
                        s.failed(format!("{id}: {e}"));
                    }
                    tokio::time::sleep(Duration::from_secs(1)).await;
                    break;
                }
            }
        }
    }
}

/// Resident memory (bytes), threads and open files of a process, from /proc.
fn proc_figures(pid: u32) -> Option<(u64, u64, u64)> {
    let status = fs::read_to_string(format!("/proc/{pid}/status")).ok()?;
    let field = |name: &str| status.lines().find_map(|l| l.strip_prefix(name)).and_then(|v| v.split_whitespace().next()?.parse::<u64>().ok());
    let rss = field("VmRSS:")? * 1024;
    let threads = field("Threads:")?;
    let fds = fs::read_dir(format!("/proc/{pid}/fd")).ok()?.count() as u64;
    Some((rss, threads, fds))
}

/// Bytes of the files under `dir` (0 if it is gone).
fn dir_bytes(dir: &Path) -> u64 {
    let Ok(entries) = fs::read_dir(dir) else { return 0 };
    entries
        .flatten()
        .map(|e| match e.metadata() {
            Ok(m) if m.is_dir() => dir_bytes(&e.path()),
            Ok(m) => m.len(),
            Err(_) => 0,
        })
        .sum()
}

/// A counter's value from the exposition at `http://addr/metrics`.
fn scrape_counter(addr: SocketAddr, name: &str) -> Option<f64> {
    crate::scrape::value(&crate::scrape::metrics(&addr.to_string(), None).ok()?, name)
}

/// Growth checks over the samples; the reasons it fails, if any. After the warm-up (the table
/// full and a fifth of the run gone) each resource's least-squares trend over the remaining
/// samples, times their span, is how much it grew in a sustained way; oscillation (snapshots
/// written and removed, allocator pools) averages out.
fn verdict(ticks: &[Tick], a: &SoakArgs) -> Vec<String> {
    let warm_s = a.minutes * 60.0 / 5.0;
    let after: Vec<&Tick> = ticks.iter().filter(|t| t.table_full && t.t_s >= warm_s).collect();
    if after.len() < 5 {
        return vec![format!("only {} samples after the warm-up (table full and {warm_s:.0} s gone): run longer, lower --capacity or --interval-s", after.len())];
    }
    let span = after[after.len() - 1].t_s - after[0].t_s;
    // (what, value, relative and absolute margin over the span). Threads get a tenth of their
    // mean besides 2: tokio's blocking pool starts threads for bursts of file work and retires
    // them after 10 s idle, so a 30-second soak can read that churn as a trend of a few threads
    // (2.2 of a mean 20.5 on a 2-vCPU EPYC, 2026-12-06); a leak per request or per snapshot
    // grows by tens.
    type Check<'a> = (&'a str, &'a dyn Fn(&Tick) -> f64, f64, f64);
    let checks: [Check; 7] = [
        ("replay resident memory (MiB)", &|t| t.replay_rss_mib, 0.05, 16.0),
        ("replay threads", &|t| t.replay_threads as f64, 0.1, 2.0),
        ("replay open files", &|t| t.replay_open_files as f64, 0.0, 8.0),
        ("replay folder (MiB)", &|t| t.replay_dir_mib, 0.25, 64.0),
        ("learner resident memory (MiB)", &|t| t.learner_rss_mib, 0.05, 16.0),
        ("learner threads", &|t| t.learner_threads as f64, 0.1, 2.0),
        ("learner open files", &|t| t.learner_open_files as f64, 0.0, 8.0),
    ];
    let mut problems = Vec::new();
    for (name, f, rel, abs) in checks {
        let n = after.len() as f64;
        let (mx, my) = (after.iter().map(|t| t.t_s).sum::<f64>() / n, after.iter().map(|t| f(t)).sum::<f64>() / n);
        let sxx: f64 = after.iter().map(|t| (t.t_s - mx).powi(2)).sum();
        let sxy: f64 = after.iter().map(|t| (t.t_s - mx) * (f(t) - my)).sum();
        let growth = sxy / sxx * span;
        let allowed = rel * my + abs;
        if growth > allowed {
            problems.push(format!("{name} kept growing after the warm-up: {growth:.1} over {span:.0} s by its trend (mean {my:.1}; allowed {allowed:.1})"));
        }
    }
    problems
}

/// The picture's panels: throughput, latency p99, memory, threads and open files.
fn picture_panels(ticks: &[Tick]) -> Vec<mapless_plots::SeriesPanel> {
    use mapless_plots::{Series, SeriesPanel};
    const BLUE: [u8; 3] = [10, 50, 150];
    const RED: [u8; 3] = [200, 40, 40];
    const GREEN: [u8; 3] = [30, 130, 60];
    let line = |label: &str, rgb, f: &dyn Fn(&Tick) -> f64| Series { label: label.into(), rgb, points: ticks.iter().map(|t| (t.t_s, f(t))).collect() };
    vec![
        SeriesPanel {
            caption: "Throughput (per interval)".into(),
            y_title: "per second".into(),
            lines: vec![line("rows acknowledged", BLUE, &|t| t.rows_per_s), line("learner updates × 100", RED, &|t| t.learner_updates_per_s * 100.0)],
        },
        SeriesPanel {
            caption: "Latency p99 (per interval)".into(),
            y_title: "ms".into(),
            lines: vec![line("insert acknowledgement", BLUE, &|t| t.insert_p99_ms), line("wait for a minibatch", RED, &|t| t.sample_p99_ms)],
        },
        SeriesPanel {
            caption: "Memory and disk".into(),
            y_title: "MiB".into(),
            lines: vec![line("replay resident", BLUE, &|t| t.replay_rss_mib), line("learner resident", RED, &|t| t.learner_rss_mib), line("replay folder", GREEN, &|t| t.replay_dir_mib)],
        },
        SeriesPanel {
            caption: "Threads and open files".into(),
            y_title: "count".into(),
            lines: vec![
                line("replay threads", BLUE, &|t| t.replay_threads as f64),
                line("replay open files", GREEN, &|t| t.replay_open_files as f64),
                line("learner threads", RED, &|t| t.learner_threads as f64),
                line("learner open files", [150, 100, 20], &|t| t.learner_open_files as f64),
            ],
        },
    ]
}

/// Runs the soak; an error when it fails.
pub fn soak(a: SoakArgs) -> Result<()> {
    if a.streams == 0 || a.batch_rows == 0 || !(a.minutes > 0.0) || !(a.interval_s > 0.0) || !(a.stall_s > 0.0) || !(a.rows_per_s >= 0.0) || !(a.sample_rate >= 0.0) {
        bail!("--streams and --batch-rows must be ≥ 1; --minutes, --interval-s and --stall-s > 0; --rows-per-s and --sample-rate ≥ 0");
    }
    let subscribers = if a.subscribers == 0 { a.streams } else { a.subscribers };
    let temp = match &a.dir {
        Some(_) => None,
        None => Some(tempfile::Builder::new().prefix("mapless-soak-").tempdir()?),
    };
    let dir = a.dir.clone().unwrap_or_else(|| temp.as_ref().expect("temp dir").path().to_path_buf());
    fs::create_dir_all(dir.join("logs"))?;
    let dir = dir.canonicalize()?;
    let p = |x: &Path| x.to_string_lossy().into_owned();

    // The replay: the env1-sac table, prioritised (so priority updates do work), no ratio
    // limit (the insert streams are paced, the learner samples as fast as it updates),
    // persistence on with the default fsync policy.
    let preset = preset_config("env1-sac")?.resolve()?;
    let any_port = SocketAddr::from(([127, 0, 0, 1], 0));
    let mut table = preset.replay.clone();
    table.capacity = a.capacity;
    table.sampler = SamplerConfig::prioritized();
    table.rate_limiter = RateLimiterConfig { min_size_to_sample: 1_000, samples_per_insert: None, ..RateLimiterConfig::default() };
    let mut server = ServerConfig { listen: any_port, metrics_listen: Some(any_port), table, shm_enabled: false, ..ServerConfig::default() };
    server.persistence.dir = Some(dir.join("replay"));
    server.persistence.snapshot_interval_s = a.snapshot_interval_s.unwrap_or_else(|| (a.minutes * 6.0).min(mapless_replay::PersistenceConfig::default().snapshot_interval_s));
    server.validate().map_err(|e| anyhow::anyhow!("{e}"))?;
    fs::write(dir.join("replay.yaml"), serde_yaml::to_string(&server)?)?;
    let (line_tx, line_rx) = std_mpsc::channel::<(String, String)>();
    let replay_cmd = vec![p(&sibling("mapless-replay")?), "--config".into(), p(&dir.join("replay.yaml"))];
    let (mut replay, replay_addr, _) = start_service("replay", replay_cmd, dir.join("logs/replay.log"), "listening on ", &line_rx, &line_tx)?;

    let learner_cfg = LearnerServiceConfig::loopback(
        preset.learner.clone(),
        mapless_learner_config::DriverConfig { send_priorities: true, ..preset.driver.clone() },
        server.table.obs_dim,
        server.table.act_dim,
        format!("http://{replay_addr}"),
        dir.join("checkpoints"),
    );
    fs::write(dir.join("learner.yaml"), serde_yaml::to_string(&learner_cfg)?)?;
    let learner_cmd = vec![p(&sibling("mapless-learner")?), "--config".into(), p(&dir.join("learner.yaml")), "--run".into(), "soak".into()];
    let (mut learner, weights_addr, learner_metrics) = start_service("learner", learner_cmd, dir.join("logs/learner.log"), "weights on ", &line_rx, &line_tx)?;
    // Keep draining the children's stdout lines.
    std::thread::spawn(move || while line_rx.recv().is_ok() {});

    let a = Arc::new(a);
    let slots = |n: usize| (0..n).map(|_| AtomicU64::new(0)).collect::<Vec<_>>();
    let s = Arc::new(Shared {
        start: Instant::now(),
        stop: AtomicBool::new(false),
        acked_rows: AtomicU64::new(0),
        minibatches: AtomicU64::new(0),
        priority_updates: AtomicU64::new(0),
        insert_us: Mutex::default(),
        sample_us: Mutex::default(),
        all_insert_us: Mutex::default(),
        all_sample_us: Mutex::default(),
        insert_last_ms: slots(a.streams),
        sample_last_ms: slots(a.samplers),
        sub_last_ms: slots(subscribers),
        sub_version: slots(subscribers),
        snapshots_received: AtomicU64::new(0),
        failures: AtomicU64::new(0),
        first_failures: Mutex::default(),
    });
    let rt = tokio::runtime::Builder::new_multi_thread().worker_threads(2).thread_name("soak").enable_all().build()?;
    // Ctrl-C or SIGTERM ends the soak early, as a failure ("interrupted"), children stopped.
    {
        let s = Arc::clone(&s);
        rt.spawn(async move {
            crate::signals::termination().await;
            s.stop.store(true, Ordering::Relaxed);
        });
    }
    let mut tasks = Vec::new();
    for i in 0..a.streams {
        tasks.push((format!("insert stream {i}"), rt.spawn(insert_stream(i, replay_addr, server.table.obs_dim, Arc::clone(&a), Arc::clone(&s)))));
    }
    for j in 0..a.samplers {
        tasks.push((format!("sampler {j}"), rt.spawn(sample_stream(j, replay_addr, server.table.name.clone(), Arc::clone(&a), Arc::clone(&s)))));
    }
    for k in 0..subscribers {
        tasks.push((format!("weights subscriber {k}"), rt.spawn(subscriber(k, weights_addr, Arc::clone(&s)))));
    }

    let total = Duration::from_secs_f64(a.minutes * 60.0);
    let interval = Duration::from_secs_f64(a.interval_s);
    if !a.json {
        println!(
            "soak: {} insert streams offering {} rows/s in batches of {}, {} samplers at {} minibatches/s with priority updates, the learner (env1-sac, priorities on), {subscribers} weights subscribers; {} min; replay folder {}",
            a.streams,
            if a.rows_per_s > 0.0 { format!("{:.0}", a.rows_per_s) } else { "unlimited".into() },
            a.batch_rows,
            a.samplers,
            a.sample_rate,
            a.minutes,
            dir.join("replay").display()
        );
        println!(
            "{:>6} {:>9} {:>17} {:>17} {:>8} {:>8} {:>18} {:>18} {:>9}",
            "t s", "rows/s", "insert p50/p99 ms", "sample p50/p99 ms", "upd/s", "weights", "replay MiB/thr/fd", "learner MiB/thr/fd", "disk MiB"
        );
    }
    if let Some(out) = &a.out {
        fs::create_dir_all(out).with_context(|| format!("creating {}", out.display()))?;
    }
    let mut csv = a.out.as_ref().map(|out| out.join("soak.csv")).map(|path| csv::Writer::from_path(&path).with_context(|| format!("creating {}", path.display()))).transpose()?;
    let mut ticks: Vec<Tick> = Vec::new();
    let mut problems: Vec<String> = Vec::new();
    let (mut last_rows, mut last_batches, mut last_updates, mut last_t) = (0u64, 0u64, scrape_counter(learner_metrics, "mapless_learner_updates").unwrap_or(0.0), 0.0);
    let mut learner_last_progress_s = 0.0;
    let stall_ms = (a.stall_s * 1000.0) as u64;
    let mut next = Instant::now() + interval;
    while s.start.elapsed() < total {
        while Instant::now() < next && !s.stopping() {
            std::thread::sleep(next.saturating_duration_since(Instant::now()).min(Duration::from_millis(100)));
        }
        if s.stopping() {
            problems.push("interrupted".into());
            break;
        }
        next += interval;
        let t = s.start.elapsed().as_secs_f64();
        for (role, child) in [("replay", &mut replay), ("learner", &mut learner)] {
            if let Some(st) = child.exited() {
                problems.push(format!("{role} exited ({st}) at {t:.0} s; see {}", child.log.display()));
            }
        }
        if !problems.is_empty() {
            break;
        }
        let rows = s.acked_rows.load(Ordering::Relaxed);
        let batches = s.minibatches.load(Ordering::Relaxed);
        let updates = scrape_counter(learner_metrics, "mapless_learner_updates").unwrap_or(last_updates);
        let dt = t - last_t;
        let mut ins = std::mem::take(&mut *s.insert_us.lock().expect("latency lock"));
        let mut smp = std::mem::take(&mut *s.sample_us.lock().expect("latency lock"));
        let (rss_r, thr_r, fd_r) = replay.pid().and_then(proc_figures).unwrap_or_default();
        let (rss_l, thr_l, fd_l) = learner.pid().and_then(proc_figures).unwrap_or_default();
        let versions: Vec<u64> = s.sub_version.iter().map(|v| v.load(Ordering::Relaxed)).collect();
        let tick = Tick {
            t_s: t,
            rows_per_s: (rows - last_rows) as f64 / dt,
            insert_p50_ms: quantile_ms(&mut ins, 0.50),
            insert_p99_ms: quantile_ms(&mut ins, 0.99),
            sample_p50_ms: quantile_ms(&mut smp, 0.50),
            sample_p99_ms: quantile_ms(&mut smp, 0.99),
            minibatches_per_s: (batches - last_batches) as f64 / dt,
            learner_updates_per_s: (updates - last_updates) / dt,
            weights_versions: versions.iter().copied().max().unwrap_or(0),
            replay_rss_mib: rss_r as f64 / 1048576.0,
            replay_threads: thr_r,
            replay_open_files: fd_r,
            replay_dir_mib: dir_bytes(&dir.join("replay")) as f64 / 1048576.0,
            learner_rss_mib: rss_l as f64 / 1048576.0,
            learner_threads: thr_l,
            learner_open_files: fd_l,
            table_full: rows >= a.capacity as u64,
        };
        if updates > last_updates {
            learner_last_progress_s = t;
        }
        (last_rows, last_batches, last_updates, last_t) = (rows, batches, updates, t);
        if !a.json {
            println!(
                "{:>6.0} {:>9.0} {:>8.2} /{:>7.2} {:>8.2} /{:>7.2} {:>8.0} {:>8} {:>7.0} /{:>4} /{:>4} {:>7.0} /{:>4} /{:>4} {:>9.0}",
                tick.t_s,
                tick.rows_per_s,
                tick.insert_p50_ms,
                tick.insert_p99_ms,
                tick.sample_p50_ms,
                tick.sample_p99_ms,
                tick.learner_updates_per_s,
                tick.weights_versions,
                tick.replay_rss_mib,
                tick.replay_threads,
                tick.replay_open_files,
                tick.learner_rss_mib,
                tick.learner_threads,
                tick.learner_open_files,
                tick.replay_dir_mib
            );
        }
        if let Some(w) = csv.as_mut() {
            w.serialize(tick)?;
            w.flush()?;
        }
        ticks.push(tick);
        // Stalls.
        let now_ms = s.now_ms();
        if now_ms > stall_ms {
            let stalled = |last: &[AtomicU64]| last.iter().enumerate().filter(|(_, l)| now_ms - l.load(Ordering::Relaxed).min(now_ms) > stall_ms).map(|(i, _)| i).collect::<Vec<_>>();
            let newest = versions.iter().copied().max().unwrap_or(0);
            let subs: Vec<usize> = stalled(&s.sub_last_ms).into_iter().filter(|&k| versions[k] < newest).collect();
            for (what, idle) in [("insert streams", stalled(&s.insert_last_ms)), ("samplers", stalled(&s.sample_last_ms)), ("weights subscribers behind the newest version", subs)] {
                if !idle.is_empty() {
                    problems.push(format!("{} {what} made no progress for {} s at {t:.0} s (first: {:?})", idle.len(), a.stall_s, &idle[..idle.len().min(5)]));
                }
            }
            if t - learner_last_progress_s > a.stall_s {
                problems.push(format!("the learner made no update for {} s at {t:.0} s", a.stall_s));
            }
            if !problems.is_empty() {
                break;
            }
        }
    }

    // Stop: clients first (their streams end), then the learner, then the replay, gracefully.
    s.stop.store(true, Ordering::Relaxed);
    rt.block_on(async {
        for (name, t) in tasks {
            if tokio::time::timeout(Duration::from_secs(10), t).await.is_err() {
                tracing::warn!("{name} did not stop within 10 s");
            }
        }
    });
    drop(rt);
    learner.stop(Duration::from_secs(30));
    replay.stop(Duration::from_secs(30));

    problems.extend(verdict(&ticks, &a));
    let failures = s.failures.load(Ordering::Relaxed);
    if failures > 0 {
        problems.push(format!("{failures} requests failed; the first: {:?}", s.first_failures.lock().expect("failures lock")));
    }

    let elapsed = ticks.last().map_or(0.0, |t| t.t_s);
    let mut ins = std::mem::take(&mut *s.all_insert_us.lock().expect("latency lock"));
    let mut smp = std::mem::take(&mut *s.all_sample_us.lock().expect("latency lock"));
    let cfg = serde_json::json!({"streams": a.streams, "offered_rows_per_s": a.rows_per_s, "batch_rows": a.batch_rows, "samplers": a.samplers, "sample_rate": a.sample_rate, "subscribers": subscribers, "capacity": a.capacity, "minutes": a.minutes});
    if !a.json {
        println!("soak summary over {elapsed:.0} s:");
    }
    let first = ticks.first().copied().unwrap_or_default();
    let last = ticks.last().copied().unwrap_or_default();
    bench_report(a.json, "soak.rows_per_s", cfg.clone(), s.acked_rows.load(Ordering::Relaxed) as f64 / elapsed.max(1e-9), "rows/s");
    bench_report(a.json, "soak.insert_latency_p50_ms", cfg.clone(), quantile_ms(&mut ins, 0.50), "ms");
    bench_report(a.json, "soak.insert_latency_p99_ms", cfg.clone(), quantile_ms(&mut ins, 0.99), "ms");
    bench_report(a.json, "soak.sample_latency_p50_ms", cfg.clone(), quantile_ms(&mut smp, 0.50), "ms");
    bench_report(a.json, "soak.sample_latency_p99_ms", cfg.clone(), quantile_ms(&mut smp, 0.99), "ms");
    bench_report(a.json, "soak.priority_updates", cfg.clone(), s.priority_updates.load(Ordering::Relaxed) as f64, "updates");
    bench_report(a.json, "soak.learner_updates_per_s", cfg.clone(), ticks.iter().map(|t| t.learner_updates_per_s).sum::<f64>() / ticks.len().max(1) as f64, "updates/s");
    bench_report(a.json, "soak.weights_snapshots_received", cfg.clone(), s.snapshots_received.load(Ordering::Relaxed) as f64, "snapshots");
    bench_report(a.json, "soak.replay_rss_first_mib", cfg.clone(), first.replay_rss_mib, "MiB");
    bench_report(a.json, "soak.replay_rss_last_mib", cfg.clone(), last.replay_rss_mib, "MiB");
    bench_report(a.json, "soak.replay_rss_max_mib", cfg.clone(), ticks.iter().map(|t| t.replay_rss_mib).fold(0.0, f64::max), "MiB");
    bench_report(a.json, "soak.learner_rss_first_mib", cfg.clone(), first.learner_rss_mib, "MiB");
    bench_report(a.json, "soak.learner_rss_last_mib", cfg.clone(), last.learner_rss_mib, "MiB");
    bench_report(a.json, "soak.replay_threads_max", cfg.clone(), ticks.iter().map(|t| t.replay_threads).max().unwrap_or(0) as f64, "threads");
    bench_report(a.json, "soak.replay_open_files_max", cfg.clone(), ticks.iter().map(|t| t.replay_open_files).max().unwrap_or(0) as f64, "files");
    bench_report(a.json, "soak.replay_dir_max_mib", cfg.clone(), ticks.iter().map(|t| t.replay_dir_mib).fold(0.0, f64::max), "MiB");
    bench_report(a.json, "soak.failures", cfg, failures as f64, "requests");
    if let Some(out) = &a.out {
        let path = out.join("soak.png");
        let verdict = if problems.is_empty() { "passed".to_owned() } else { format!("FAILED: {}", problems[0]) };
        let footer = format!(
            "mapless bench soak --streams {} --minutes {} --rows-per-s {} --samplers {} --subscribers {subscribers} --capacity {} · {verdict}",
            a.streams, a.minutes, a.rows_per_s, a.samplers, a.capacity
        );
        mapless_plots::time_series_png(&picture_panels(&ticks), "mapless bench soak: the replay and the learner under load", "seconds since the start", &footer, &path)
            .with_context(|| format!("drawing {}", path.display()))?;
        if !a.json {
            println!("figures: {} and {}", out.join("soak.csv").display(), path.display());
        }
    }
    if !problems.is_empty() {
        bail!("soak failed:\n  {}\n(logs: {})", problems.join("\n  "), dir.join("logs").display());
    }
    if !a.json {
        println!("soak passed: no stream stalled, no request failed, nothing grew after the warm-up");
    }
    Ok(())
}

#[cfg(test)]
mod tests {
    use super::*;
    use clap::Parser as _;

    #[derive(clap::Parser)]
    struct Wrap {
        #[command(flatten)]
        a: SoakArgs,
    }

    fn ticks(n: usize, rss: impl Fn(usize) -> f64) -> Vec<Tick> {
        (0..n).map(|i| Tick { t_s: i as f64 * 5.0, table_full: i >= 2, replay_rss_mib: rss(i), replay_threads: 26, replay_open_files: 86, learner_rss_mib: 417.0, ..Tick::default() }).collect()
    }

    #[test]
    fn growth_after_the_warm_up_fails_and_a_plateau_passes() {
        let a = Wrap::parse_from(["soak", "--minutes", "10"]).a;
        // 120 samples over 10 min; the warm-up is the first 2 min (a fifth).
        let filling = ticks(120, |i| 40.0 + 200.0 * (i.min(24) as f64 / 24.0));
        assert_eq!(verdict(&filling, &a), Vec::<String>::new());
        let leaking = ticks(120, |i| 240.0 + i as f64);
        let problems = verdict(&leaking, &a);
        assert_eq!(problems.len(), 1, "{problems:?}");
        assert!(problems[0].starts_with("replay resident memory"), "{problems:?}");
        // A slow drift inside the margin (5 % of the mean + 16 MiB over the span) passes, and
        // so does a sawtooth (snapshots written and removed).
        assert!(verdict(&ticks(120, |i| 240.0 + i as f64 * 0.2), &a).is_empty());
        assert!(verdict(&ticks(120, |i| 240.0 + (i % 6) as f64 * 30.0), &a).is_empty());
        // Too short a run says so instead of passing.
        assert!(verdict(&ticks(10, |_| 40.0), &a)[0].starts_with("only"));
    }

    #[test]
    fn a_blocking_pool_s_churn_passes_and_a_thread_per_snapshot_fails() {
        // The 30-second soak of the suite: 15 samples 2 s apart, the warm-up the first 6 s.
        let a = Wrap::parse_from(["soak", "--minutes", "0.5", "--interval-s", "2"]).a;
        let with_threads = |threads: &dyn Fn(usize) -> u64| {
            let mut t = ticks(15, |_| 240.0);
            for (i, tick) in t.iter_mut().enumerate() {
                tick.t_s = i as f64 * 2.0;
                tick.replay_threads = threads(i);
            }
            t
        };
        // Two file workers started late in the run and not yet retired (tokio keeps them 10 s):
        // the trend reads 2.4 threads over 22 s (more than the 2 once allowed), inside a tenth of the mean plus 2.
        let churn = with_threads(&|i| 20 + u64::from(i >= 9) + u64::from(i >= 12));
        assert_eq!(verdict(&churn, &a), Vec::<String>::new());
        // One thread kept every 4 s (fewer than one per snapshot, every 3 s here) is a leak.
        let leak = with_threads(&|i| 20 + i as u64 / 2);
        let problems = verdict(&leak, &a);
        assert!(problems.len() == 1 && problems[0].starts_with("replay threads kept growing"), "{problems:?}");
    }
}
