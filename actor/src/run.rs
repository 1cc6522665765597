//! One actor process: many vehicles in one world, acting with the newest published policy,
//! streaming every transition to the replay and every finished episode to the stats collector.
//!
//! ```text
//!   weights stream ──follow──► newest snapshot ──(between steps)──► Policy (pure Rust)
//!   VecEnv obs ──► Policy / uniform warm-up ──► + exploration ──► VecEnv::step
//!        └─ rows (obs, action, reward, next_obs, terminal, truncated, policy version) ─► batch
//!   batch of `batch_rows` ──► Sink (iceoryx2 or gRPC; acked, resent, de-duplicated)
//!   finished episodes ──► StatsService.Report (best effort)
//! ```
//!
//! Exploration (issue 5): uniform random actions until the first weights arrive and for the
//! first `warmup_steps` vehicle-steps; then SAC samples from its own distribution, TD3 adds
//! Gaussian noise and DDPG Ornstein–Uhlenbeck noise (reset at each episode start).

use std::sync::Arc;
use std::sync::atomic::{AtomicBool, AtomicU64, Ordering};
use std::time::{Duration, Instant, SystemTime, UNIX_EPOCH};

use mapless_net::health::Health;
use mapless_net::shm::ShmConfig;
use mapless_net::{ClientSecurity, metrics};
use mapless_proto::v1::{EpisodeStats, ProtocolVersion, WeightsSnapshot};
use mapless_proto::{Transition, TransitionBatchBuilder};
use mapless_sim::worlds::{DEFAULT_WORLDS_PER_FAMILY, Split, WorldPool};
use mapless_sim::{EnvConfig, VecEnv, VecStep};
use rand::{Rng, SeedableRng};
use rand_pcg::Pcg64;
use serde::{Deserialize, Serialize};
use tokio::sync::{mpsc, watch};

use crate::nstep::{NStepAdder, NStepReturns};
use crate::sink::{InsertClient, InsertStats, ShmInsertClient, Sink};
use crate::{ActMode, ExplorationNoise, NoiseProcess, Policy};

/// How an actor reaches the replay.
#[derive(Clone, Debug, Serialize, Deserialize, PartialEq)]
#[serde(tag = "kind", rename_all = "snake_case", deny_unknown_fields)]
pub enum ReplayTarget {
    /// iceoryx2 shared memory (the replay runs on this host, or in a container whose /dev/shm
    /// and iceoryx2 folder this one mounts: deploy/compose.yaml's `actor-shm`).
    Shm {
        /// The ingest's service-name prefix and domain, as the replay service was given.
        prefix: String,
        #[serde(default)]
        domain: String,
        /// The same replay's gRPC address, for `--index auto` only: the slot comes from
        /// `RegisterActor` over gRPC (with `security`), the rows over shared memory. None: the
        /// index must be given (`--index N`), as `mapless train` gives it.
        #[serde(default, skip_serializing_if = "Option::is_none")]
        register: Option<String>,
    },
    /// gRPC `Insert`, e.g. `http://127.0.0.1:50051`.
    Grpc { uri: String },
}

/// Exploration while training.
#[derive(Clone, Debug, Serialize, Deserialize, PartialEq)]
#[serde(default, deny_unknown_fields)]
pub struct ExplorationSettings {
    /// Vehicle-steps of uniform random actions at the start of each actor process (the
    /// policy is used only after these and once weights have arrived).
    pub warmup_steps: u64,
    /// Noise added to deterministic policies (DDPG: OU, TD3: Gaussian), handed over from the
    /// algorithm's config (`learner.{ddpg,td3}.exploration`); absent for SAC and evaluation.
    pub noise: Option<ExplorationNoise>,
    /// Share of transitions stored as their mirror image (left ↔ right, `EnvConfig::mirror_obs`),
    /// each drawn on its own; 0: none, and no random number is spent on it. Handed over from
    /// `actors.mirror_share`.
    #[serde(default)]
    pub mirror_share: f64,
}

impl Default for ExplorationSettings {
    fn default() -> Self {
        ExplorationSettings { warmup_steps: 1_000, noise: None, mirror_share: 0.0 }
    }
}

/// Everything one actor process needs.
#[derive(Clone, Debug, Serialize, Deserialize, PartialEq)]
#[serde(deny_unknown_fields)]
pub struct ActorConfig {
    /// Built-in map name, path to a map YAML, `gen:FAMILY:SEED`, or several joined by `+`
    /// (`gen:FAMILY` alone: that family's training worlds).
    pub map: String,
    /// Training worlds per family named in `map` (seeds 0..N).
    #[serde(default = "default_worlds_per_family")]
    pub worlds_per_family: usize,
    /// Simulator settings (vehicle, sensor, reward, step limit, EQS grid).
    pub env: EnvConfig,
    /// Vehicles simulated by this process.
    pub vehicles: usize,
    /// Exploration.
    #[serde(default)]
    pub exploration: ExplorationSettings,
    /// Transitions per batch sent to the replay.
    pub batch_rows: usize,
    /// Batches unacknowledged at most.
    #[serde(default = "default_in_flight")]
    pub max_in_flight: usize,
    /// n-step rows (`crate::nstep`), handed over from `learner.n_step` and `learner.gamma`;
    /// none: one row per step, as the paper's one-step targets take. Published weights must
    /// say the same n and γ (snapshot metadata `n_step`, `gamma`), else they are refused.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub n_step: Option<NStepReturns>,
    /// The replay.
    pub replay: ReplayTarget,
    /// The learner's weights service, e.g. `http://127.0.0.1:50052`.
    pub weights: String,
    /// The run's stats collector; none: episodes are only logged.
    #[serde(default)]
    pub stats: Option<String>,
    /// TLS and token for the gRPC services.
    #[serde(default)]
    pub security: ClientSecurity,
    /// Base seed; process `index` uses its own streams derived from it.
    #[serde(default)]
    pub seed: u64,
    /// Prometheus `/metrics` address, with `/healthz` beside it (`mapless-actor health ADDR`
    /// asks it); loopback, or any address with `metrics_token_file`; port 0 picks one, logged at
    /// start; none: off.
    #[serde(default)]
    pub metrics_listen: Option<std::net::SocketAddr>,
    /// File holding the bearer token a scraper of `/metrics` must send; needed beyond loopback
    /// (plain HTTP: a private network, as compose's) [default: none, loopback only].
    #[serde(default)]
    pub metrics_token_file: Option<std::path::PathBuf>,
}

fn default_worlds_per_family() -> usize {
    DEFAULT_WORLDS_PER_FAMILY
}

fn default_in_flight() -> usize {
    8
}

impl ActorConfig {
    /// Checks what can be checked without connecting.
    pub fn validate(&self) -> Result<(), String> {
        self.env.validate().map_err(|e| e.to_string())?;
        if self.vehicles == 0 || self.vehicles > 4096 {
            return Err(format!("vehicles must be in 1..=4096, got {}", self.vehicles));
        }
        if self.batch_rows == 0 || self.batch_rows > 65_536 {
            return Err(format!("batch_rows must be in 1..=65536, got {}", self.batch_rows));
        }
        if self.max_in_flight == 0 {
            return Err("max_in_flight must be >= 1".into());
        }
        if !(0.0..=1.0).contains(&self.exploration.mirror_share) {
            return Err(format!("exploration.mirror_share must be a share in [0, 1], got {}", self.exploration.mirror_share));
        }
        if let Some(r) = &self.n_step {
            r.validate()?;
        }
        Ok(())
    }
}

/// Counters of a finished (or stopped) actor.
#[derive(Clone, Debug, Default, Serialize)]
pub struct ActorReport {
    pub actor_id: String,
    pub vehicle_steps: u64,
    pub episodes: u64,
    pub policy_version: u64,
    pub policies_loaded: u64,
    pub bad_snapshots: u64,
    /// Transitions stored as their mirror image (`exploration.mirror_share`).
    pub mirrored_rows: u64,
    /// Steps stored in no row: the last n − 1 of episodes that hit the step limit, with
    /// n-step rows (`n_step`).
    pub n_step_dropped: u64,
    pub unacked_at_exit: bool,
    pub sink: InsertStats,
}

/// What `/metrics` shows, updated every step.
#[derive(Default)]
struct Gauges {
    vehicle_steps: AtomicU64,
    episodes: AtomicU64,
    policy_version: AtomicU64,
    batches_acked: AtomicU64,
    reconnects: AtomicU64,
}

impl Gauges {
    fn render(&self) -> String {
        let g = |a: &AtomicU64| a.load(Ordering::Relaxed) as f64;
        let mut x = metrics::Exposition::new();
        x.counter("mapless_actor_vehicle_steps", "Vehicle-steps taken by this actor process.", g(&self.vehicle_steps))
            .counter("mapless_actor_episodes", "Training episodes finished.", g(&self.episodes))
            .gauge("mapless_actor_policy_version", "Weights version acting now (0: warm-up).", g(&self.policy_version))
            .counter("mapless_actor_batches_acked", "Transition batches acknowledged by the replay.", g(&self.batches_acked))
            .counter("mapless_actor_reconnects", "Replay connections reopened.", g(&self.reconnects));
        x.text()
    }
}

/// An actor id unique to this incarnation: `actor-<index>-<pid>-<unix ms>` (a restarted
/// actor must not reuse its predecessor's id, whose sequence numbers the replay remembers).
pub fn incarnation_id(index: usize) -> String {
    let ms = SystemTime::now().duration_since(UNIX_EPOCH).map(|d| d.as_millis()).unwrap_or(0);
    format!("actor-{index}-{}-{ms}", std::process::id())
}

fn unix_ms() -> u64 {
    SystemTime::now().duration_since(UNIX_EPOCH).map(|d| d.as_millis() as u64).unwrap_or(0)
}

/// Runs actor process `index` until `stop` turns true or `max_vehicle_steps` (if any) have been
/// taken; then sends what is left and waits (up to 20 s) for the acknowledgements.
pub fn run(cfg: &ActorConfig, index: usize, actor_id: &str, stop: Arc<AtomicBool>, max_vehicle_steps: Option<u64>) -> anyhow::Result<ActorReport> {
    cfg.validate().map_err(|e| anyhow::anyhow!("actor config: {e}"))?;
    // One map, or a list of maps and families: every episode draws its world from the pool
    // (the families' training worlds), built once here.
    let pool = WorldPool::build(&cfg.map, cfg.worlds_per_family, Split::Train, &cfg.env)?;
    if pool.len() > 1 {
        tracing::info!(worlds = pool.len(), map = %cfg.map, "training worlds built; each episode draws one");
    }
    let map_name = cfg.map.clone();
    let single_world = pool.len() == 1;
    let seed = cfg.seed.wrapping_add((index as u64).wrapping_mul(0x9E37_79B9_7F4A_7C15));
    let mut envs = VecEnv::with_worlds(pool.into_worlds(), cfg.vehicles, seed)?;
    let (n, d) = (envs.len(), envs.obs_dim());
    let mut rng = Pcg64::seed_from_u64(seed ^ 0xA5A5_5A5A);

    // One tokio worker for the weights follower, the stats reporter and the gRPC sink.
    let rt = tokio::runtime::Builder::new_multi_thread().worker_threads(1).thread_name("actor-io").enable_all().build()?;
    let (stop_tx, stop_rx) = watch::channel(false);
    let (weights_tx, mut weights_rx) = watch::channel::<Option<Arc<WeightsSnapshot>>>(None);
    let weights_endpoint = cfg.security.endpoint(&cfg.weights)?;
    rt.spawn(mapless_net::weights::follow(weights_endpoint, actor_id.to_owned(), weights_tx, stop_rx.clone()));
    let stats_tx = match &cfg.stats {
        Some(uri) => {
            let (tx, rx) = mpsc::channel::<EpisodeStats>(4096);
            rt.spawn(mapless_net::stats::report(cfg.security.endpoint(uri)?, rx));
            Some(tx)
        }
        None => None,
    };
    let mut sink = match &cfg.replay {
        ReplayTarget::Shm { prefix, domain, .. } => {
            let mut shm = ShmConfig { prefix: prefix.clone(), domain: domain.clone(), ..ShmConfig::default() };
            shm.max_in_flight = cfg.max_in_flight;
            // Short waits while the window is full, so a stop request is seen within 0.5 s
            // even while the replay's rate limiter holds inserts back.
            shm.send_timeout_ms = 500;
            match ShmInsertClient::connect(shm, actor_id, &stop) {
                Ok(s) => Sink::Shm(s),
                Err(_) => return Ok(ActorReport { actor_id: actor_id.to_owned(), ..ActorReport::default() }),
            }
        }
        ReplayTarget::Grpc { uri } => Sink::Grpc(InsertClient::new(rt.handle().clone(), cfg.security.endpoint(uri)?, cfg.max_in_flight)),
    };

    let mut report = ActorReport { actor_id: actor_id.to_owned(), ..ActorReport::default() };
    let gauges = Arc::new(Gauges::default());
    // `GET /healthz` beside /metrics (an actor serves no gRPC): SERVING while the loop below
    // acts with its sink connected, NOT_SERVING once it stops and drains.
    let health = Health::new();
    if let Some(addr) = cfg.metrics_listen {
        let g = Arc::clone(&gauges);
        let access = metrics::MetricsAccess::from_token_file(cfg.metrics_token_file.as_deref())?;
        metrics::spawn(&rt, addr, Arc::new(move || g.render()), health.clone(), access, stop_rx.clone())?;
    }
    health.serve();
    let mut policy: Option<Policy> = None;
    let mut noise = NoiseProcess::new(cfg.exploration.noise, n, 2);
    let mut obs = vec![0.0f32; n * d];
    let mut actions = vec![0.0f32; n * 2];
    // Mirror images (`exploration.mirror_share`), drawn from their own stream so that the
    // policy's samples stay those of the seed.
    let mirror_share = cfg.exploration.mirror_share;
    let mut mirror_rng = Pcg64::seed_from_u64(seed ^ 0x4D49_5252_4F52);
    let (mut m_obs, mut m_next) = (vec![0.0f32; d], vec![0.0f32; d]);
    let mut step_idx: Vec<u32> = vec![0; n];
    let mut episode_ids: Vec<u64> = vec![0; n];
    let mut out = VecStep::default();
    // A batch goes out at `batch_rows` or more: the step that fills it adds up to one row per
    // vehicle, or n with n-step rows (a collision stores the episode's last n); `mapless
    // train` sizes the replay's row limit (`max_batch_rows`) to match.
    let mut adder = NStepAdder::new(cfg.n_step, n, d, 2);
    let batch_capacity = cfg.batch_rows + n * adder.n();
    let mut builder = TransitionBatchBuilder::with_capacity(d, 2, batch_capacity);
    let mut sequence = 0u64;
    let mut last_log = Instant::now();
    let (mut ep_window, mut ret_window) = (0u64, 0.0f64);

    while !stop.load(Ordering::Relaxed) && max_vehicle_steps.is_none_or(|m| report.vehicle_steps < m) {
        // Swap policies between steps.
        if weights_rx.has_changed().unwrap_or(false) {
            let snap = weights_rx.borrow_and_update().clone();
            if let Some(s) = snap {
                // Weights whose targets bootstrap over other sums than these rows carry: refused.
                let checked = Policy::from_snapshot(&s).map(|p| (p, crate::nstep::check_snapshot(&s.metadata, cfg.n_step)));
                match checked {
                    Ok((_, Err(reason))) => {
                        report.bad_snapshots += 1;
                        tracing::error!(%reason, version = s.version, "published policy ignored; keeping the previous policy");
                    }
                    Ok((p, Ok(()))) if p.obs_dim() == d && p.act_dim() == 2 => {
                        if policy.is_none() {
                            tracing::info!(version = p.version(), "first policy weights arrived");
                        }
                        report.policy_version = p.version();
                        report.policies_loaded += 1;
                        policy = Some(p);
                    }
                    Ok((p, Ok(()))) => {
                        report.bad_snapshots += 1;
                        tracing::error!(obs_dim = p.obs_dim(), act_dim = p.act_dim(), expected_obs = d, "published policy has other dimensions than this map's observations; ignored");
                    }
                    Err(e) => {
                        report.bad_snapshots += 1;
                        tracing::error!(error = %e, version = s.version, "unusable policy weights; keeping the previous policy");
                    }
                }
            }
        }
        obs.copy_from_slice(envs.obs());
        let version = match policy.as_mut() {
            Some(p) if report.vehicle_steps >= cfg.exploration.warmup_steps => {
                p.act(&obs, ActMode::Sample, &mut rng, &mut actions)?;
                noise.apply(&mut rng, &mut actions);
                p.version()
            }
            _ => {
                for a in actions.iter_mut() {
                    *a = rng.random_range(-1.0f32..=1.0);
                }
                0
            }
        };
        for (i, e) in envs.envs().iter().enumerate() {
            // Read before stepping: a vehicle whose episode ends is reset by the step.
            (episode_ids[i], step_idx[i]) = (e.episode_id(), e.steps());
        }
        envs.step(&actions, &mut out)?;
        for i in 0..n {
            let step = Transition {
                obs: &obs[i * d..(i + 1) * d],
                action: &actions[2 * i..2 * i + 2],
                reward: out.reward[i],
                next_obs: &out.next_obs[i * d..(i + 1) * d],
                terminal: out.terminal[i],
                truncated: out.truncated[i],
                episode_id: ((i as u64) << 40) | episode_ids[i],
                step: step_idx[i],
                policy_version: version,
            };
            adder.step(i, step, |row| {
                if mirror_share > 0.0 && mirror_rng.random::<f64>() < mirror_share {
                    cfg.env.mirror_obs(row.obs, &mut m_obs);
                    cfg.env.mirror_obs(row.next_obs, &mut m_next);
                    report.mirrored_rows += 1;
                    let a = EnvConfig::mirror_action([row.action[0], row.action[1]]);
                    builder.push(Transition { obs: &m_obs, action: &a, next_obs: &m_next, ..row })
                } else {
                    builder.push(row)
                }
            })?;
        }
        report.vehicle_steps += n as u64;
        for (i, s) in out.finished.drain(..) {
            noise.reset(i);
            report.episodes += 1;
            ep_window += 1;
            ret_window += s.return_;
            let rec = EpisodeStats {
                protocol_version: ProtocolVersion::V1 as i32,
                actor_id: actor_id.to_owned(),
                episode_id: ((i as u64) << 40) | s.episode_id.max(1),
                policy_version: version,
                episode_return: s.return_,
                steps: s.steps,
                terminal: s.terminal,
                truncated: s.truncated && !s.terminal,
                eqs: s.eqs as f64,
                ees: s.ees,
                distance_m: s.distance_m,
                shaded_time_s: s.shaded_time_s,
                map: if single_world { map_name.clone() } else { s.map.clone() },
                evaluation: false,
                finished_unix_ms: unix_ms(),
            };
            if let Some(tx) = &stats_tx {
                // Best effort: a full queue drops the record rather than stall acting.
                let _ = tx.try_send(rec);
            }
        }
        if builder.len() >= cfg.batch_rows {
            sequence += 1;
            let full = std::mem::replace(&mut builder, TransitionBatchBuilder::with_capacity(d, 2, batch_capacity));
            if sink.send(full.finish(actor_id, sequence), &stop).is_err() {
                break;
            }
        }
        gauges.vehicle_steps.store(report.vehicle_steps, Ordering::Relaxed);
        gauges.episodes.store(report.episodes, Ordering::Relaxed);
        gauges.policy_version.store(report.policy_version, Ordering::Relaxed);
        gauges.batches_acked.store(sink.stats().acked, Ordering::Relaxed);
        gauges.reconnects.store(sink.stats().reconnects, Ordering::Relaxed);
        if last_log.elapsed() >= Duration::from_secs(10) {
            let s = sink.stats();
            tracing::info!(
                vehicle_steps = report.vehicle_steps,
                episodes = report.episodes,
                mean_return = if ep_window > 0 { ret_window / ep_window as f64 } else { f64::NAN },
                policy_version = report.policy_version,
                batches_acked = s.acked,
                reconnects = s.reconnects,
                "acting"
            );
            (ep_window, ret_window) = (0, 0.0);
            last_log = Instant::now();
        }
    }

    // Shutdown: what is built goes out, and we wait for its acknowledgement.
    health.drain();
    if !builder.is_empty() {
        sequence += 1;
        // `stop` is set: one attempt, then `flush` below keeps trying until its deadline.
        let _ = sink.send(builder.finish(actor_id, sequence), &stop);
    }
    // 20 s: a rate-limited replay acknowledges a held batch only as the learner samples, which
    // a loaded machine can take over 10 s to do for a few batches; inside the 30 s that the
    // local supervisor, compose and the stack give a stopping actor.
    report.unacked_at_exit = !sink.flush(Instant::now() + Duration::from_secs(20));
    report.sink = sink.stats().clone();
    report.n_step_dropped = adder.dropped();
    drop(stats_tx);
    let _ = stop_tx.send(true);
    // Give the stats reporter a moment to hand over the last records.
    rt.shutdown_timeout(Duration::from_secs(2));
    Ok(report)
}
