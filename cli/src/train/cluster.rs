//! The run's children together: the replay, the learner and the actors started in order (each
//! one's config written into the run folder, a service's rewritten with the ports it got, so
//! that a restarted one comes back on the same addresses), the stats collector that takes the
//! actors' episodes, `endpoints.json` and `pids.json`, supervision by the restart policies,
//! and the orderly stop.

use std::fs;
use std::net::SocketAddr;
use std::path::{Path, PathBuf};
use std::sync::mpsc as std_mpsc;
use std::time::Duration;

use anyhow::{Context, Result};
use indicatif::ProgressBar;
use mapless_actor::run::{ActorConfig, ExplorationSettings, ReplayTarget};
use mapless_learner_config::{LearnerConfig, LearnerEvent, LearnerServiceConfig};
use mapless_net::shm::ShmConfig;
use mapless_proto::v1::replay_service_client::ReplayServiceClient;
use mapless_proto::v1::{EpisodeStats, ProtocolVersion, ServerInfoRequest, ServerInfoResponse};
use mapless_replay::server::ServerConfig;

use super::children::{Proc, sibling, start_service};
use super::config::TrainConfig;
use super::folder::{RunFolder, write_atomic};
use super::restart;

/// The children's executables, beside this one.
pub(crate) struct Binaries {
    learner: String,
    replay: String,
    actor: String,
}

impl Binaries {
    pub(crate) fn find() -> Result<Binaries> {
        let path = |name: &str| sibling(name).map(|p| p.to_string_lossy().into_owned());
        Ok(Binaries { learner: path("mapless-learner")?, replay: path("mapless-replay")?, actor: path("mapless-actor")? })
    }
}

/// A line a child printed on stdout: its role and the line.
type Line = (String, String);

/// The run's children, the stats collector, and the runtime their I/O runs on.
pub(crate) struct Cluster {
    run: PathBuf,
    replay: Proc,
    learner: Proc,
    actors: Vec<Proc>,
    /// The children's stdout lines (each restart is handed the sender).
    line_tx: std_mpsc::Sender<Line>,
    line_rx: std_mpsc::Receiver<Line>,
    /// Episodes the actors report to the stats collector.
    episodes: tokio::sync::mpsc::Receiver<EpisodeStats>,
    collector_stop: tokio::sync::watch::Sender<bool>,
    replay_addr: SocketAddr,
    replay_client: Option<ReplayServiceClient<tonic::transport::Channel>>,
    rt: tokio::runtime::Runtime,
}

impl Cluster {
    /// Starts the replay, waits until it listens, starts the learner (which publishes its
    /// initial policy at once), the stats collector (on `rt`), then the actors.
    pub(crate) fn start(cfg: &TrainConfig, run: &RunFolder, resuming: bool, log_json: bool, bins: &Binaries, rt: tokio::runtime::Runtime) -> Result<Cluster> {
        // Ports: each service binds port 0 and says what it got (no bind-and-release race); the
        // configs are then rewritten with those ports so that a restarted child comes back on
        // the same addresses.
        let any_port = SocketAddr::from(([127, 0, 0, 1], 0));
        // One iceoryx2 domain per run folder: runs on one host stay apart, and a restarted
        // replay or actor cleans what a killed predecessor of *this* run left.
        let domain = format!("mpl{:08x}_", crc32fast::hash(run.abs.to_string_lossy().as_bytes()));
        let shm = ShmConfig { domain: domain.clone(), ..ShmConfig::for_table(&cfg.replay.name) };
        let p = |x: &Path| x.to_string_lossy().into_owned();
        let (line_tx, line_rx) = std_mpsc::channel::<Line>();
        // `mapless --log-json train` makes every process log JSON lines.
        let json_flag = |mut v: Vec<String>| {
            if log_json {
                v.push("--log-json".into());
            }
            v
        };

        let mut server = ServerConfig { listen: any_port, metrics_listen: Some(any_port), table: cfg.replay.clone(), shm: Some(shm.clone()), seed: cfg.seed, ..ServerConfig::default() };
        if cfg.replay_persistence {
            server.persistence.dir = Some(run.abs.join("replay"));
        }
        fs::write(run.join("replay.yaml"), serde_yaml::to_string(&server)?)?;
        let replay_cmd = json_flag(vec![bins.replay.clone(), "--config".into(), p(&run.abs.join("replay.yaml"))]);
        let (replay, replay_addr, replay_metrics) = start_service("replay", replay_cmd, run.logs.join("replay.log"), "listening on ", &line_rx, &line_tx)?;
        // A restarted replay comes back on the same ports.
        server.listen = replay_addr;
        server.metrics_listen = Some(replay_metrics);
        fs::write(run.join("replay.yaml"), serde_yaml::to_string(&server)?)?;

        let mut learner_cfg = LearnerServiceConfig {
            tensorboard_dir: Some(run.abs.join("tensorboard")),
            policy_file: Some(run.abs.join("policy.safetensors")),
            resume: true,
            threads: cfg.threads.learner,
            ..LearnerServiceConfig::loopback(
                LearnerConfig { seed: cfg.seed, ..cfg.learner.clone() },
                cfg.driver.clone(),
                cfg.env.obs_dim(),
                2,
                format!("http://{replay_addr}"),
                run.abs.join("checkpoints"),
            )
        };
        fs::write(run.join("learner.yaml"), serde_yaml::to_string(&learner_cfg)?)?;
        let learner_cmd = json_flag(vec![bins.learner.clone(), "--config".into(), p(&run.abs.join("learner.yaml")), "--run".into(), run.name.clone()]);
        let (learner, weights_addr, learner_metrics) = start_service("learner", learner_cmd, run.logs.join("learner.log"), "weights on ", &line_rx, &line_tx)?;
        // A restarted learner comes back on the same ports.
        learner_cfg.weights_listen = weights_addr;
        learner_cfg.metrics_listen = Some(learner_metrics);
        fs::write(run.join("learner.yaml"), serde_yaml::to_string(&learner_cfg)?)?;

        // Stats collector (in this process).
        let stats_listener = rt.block_on(tokio::net::TcpListener::bind("127.0.0.1:0"))?;
        let stats_addr = stats_listener.local_addr()?;
        let (ep_tx, episodes) = tokio::sync::mpsc::channel::<EpisodeStats>(8192);
        let (collector_stop, collector_stop_rx) = tokio::sync::watch::channel(false);
        rt.spawn(async move {
            if let Err(e) = mapless_net::stats::serve_collector(stats_listener, &Default::default(), ep_tx, collector_stop_rx).await {
                tracing::error!(error = %e, "stats collector stopped");
            }
        });

        let actor_cfg = ActorConfig {
            map: cfg.map.clone(),
            worlds_per_family: cfg.worlds_per_family,
            env: cfg.actor_env(),
            vehicles: cfg.actors.vehicles,
            exploration: ExplorationSettings { warmup_steps: if resuming { 0 } else { cfg.actors.warmup_steps }, noise: cfg.noise(), mirror_share: cfg.actors.mirror_share },
            batch_rows: cfg.actors.batch_rows,
            n_step: cfg.n_step_rows(),
            max_in_flight: 8,
            replay: ReplayTarget::Shm { prefix: shm.prefix.clone(), domain: shm.domain.clone(), register: None },
            weights: format!("http://{weights_addr}"),
            stats: Some(format!("http://{stats_addr}")),
            security: Default::default(),
            seed: cfg.seed,
            // Each actor process logs the port it got.
            metrics_listen: Some(SocketAddr::from(([127, 0, 0, 1], 0))),
            metrics_token_file: None,
        };
        fs::write(run.join("actor.yaml"), serde_yaml::to_string(&actor_cfg)?)?;

        let actor_cmd = |i: usize| json_flag(vec![bins.actor.clone(), "--config".into(), p(&run.abs.join("actor.yaml")), "--index".into(), i.to_string(), "--run".into(), run.name.clone()]);
        let mut actors: Vec<Proc> = Vec::new();
        for i in 0..cfg.actors.count {
            actors.push(Proc::spawn(&format!("actor-{i}"), actor_cmd(i), run.logs.join(format!("actor-{i}.log")), Some(line_tx.clone())).with_context(|| format!("actor {i}"))?);
        }
        fs::write(
            run.join("endpoints.json"),
            serde_json::to_string_pretty(&serde_json::json!({
                "replay": format!("http://{replay_addr}"), "replay_metrics": format!("http://{replay_metrics}/metrics"),
                "weights": format!("http://{weights_addr}"), "learner_metrics": format!("http://{learner_metrics}/metrics"), "stats": format!("http://{stats_addr}"),
                "shm_prefix": shm.prefix, "shm_domain": shm.domain,
            }))?,
        )?;
        let cluster = Cluster { run: run.dir.clone(), replay, learner, actors, line_tx, line_rx, episodes, collector_stop, replay_addr, replay_client: None, rt };
        cluster.write_pids()?;
        Ok(cluster)
    }

    /// The events the learner has printed since the last call (its status every second).
    pub(crate) fn learner_said(&self) -> impl Iterator<Item = LearnerEvent> + '_ {
        learner_events(&self.line_rx)
    }

    /// The episodes the actors have reported since the last call.
    pub(crate) fn episodes(&mut self) -> impl Iterator<Item = EpisodeStats> + '_ {
        std::iter::from_fn(|| self.episodes.try_recv().ok())
    }

    /// What the replay says of itself (size, inserts), or `None` when it does not answer
    /// within a second: the supervisor's loop must never hang on the replay.
    pub(crate) fn replay_info(&mut self) -> Option<ServerInfoResponse> {
        let (client, addr) = (&mut self.replay_client, self.replay_addr);
        let info = self.rt.block_on(async {
            let fetch = async {
                if client.is_none() {
                    *client = ReplayServiceClient::connect(format!("http://{addr}")).await.ok();
                }
                let c = client.as_mut()?;
                c.server_info(ServerInfoRequest { protocol_version: ProtocolVersion::V1 as i32 }).await.ok().map(tonic::Response::into_inner)
            };
            tokio::time::timeout(Duration::from_secs(1), fetch).await.ok().flatten()
        });
        if info.is_none() {
            self.replay_client = None;
        }
        info
    }

    /// Actors running now, of all.
    pub(crate) fn actors_alive(&mut self) -> (usize, usize) {
        let n = self.actors.len();
        (self.actors.iter_mut().filter_map(|a| a.exited().is_none().then_some(())).count(), n)
    }

    /// Restarts of all children so far.
    pub(crate) fn restarts(&self) -> u32 {
        self.actor_restarts() + self.learner.restarts + self.replay.restarts
    }

    /// Restarts (exits) of the actors so far.
    pub(crate) fn actor_restarts(&self) -> u32 {
        self.actors.iter().map(|a| a.restarts).sum()
    }

    /// One turn of supervision: every child that exited is restarted by its policy (see
    /// `restart.rs`), and `pids.json` follows. What it logs goes `above` the progress line.
    pub(crate) fn supervise(&mut self, above: &ProgressBar) -> Result<()> {
        let mut restarted = false;
        for (i, a) in self.actors.iter_mut().enumerate() {
            restarted |= restart::actor(i, a, &self.line_tx, above)?;
        }
        if restarted {
            self.write_pids()?;
        }
        if let Some(st) = self.learner.exited() {
            restart::service(&mut self.learner, st, "from its newest checkpoint", &self.line_tx, above)?;
            self.write_pids()?;
        }
        if let Some(st) = self.replay.exited() {
            restart::service(&mut self.replay, st, "(it restores from its log)", &self.line_tx, above)?;
            self.write_pids()?;
        }
        Ok(())
    }

    /// `pids.json`: the processes of the run now (tests and operators use it).
    fn write_pids(&self) -> Result<()> {
        let v = serde_json::json!({
            "supervisor": std::process::id(), "replay": self.replay.pid(), "learner": self.learner.pid(),
            "actors": self.actors.iter().map(Proc::pid).collect::<Vec<_>>(),
            "restarts": self.restarts(),
        });
        write_atomic(&self.run.join("pids.json"), &serde_json::to_string(&v)?)
    }

    /// The orderly stop: the actors (they send what they hold and wait for the
    /// acknowledgements), the learner (final publication and checkpoint), then the replay
    /// (final snapshot). `late` takes the episodes that arrived while the actors stopped.
    /// Returns what the learner printed that was not read yet (its `stopped` event).
    pub(crate) fn stop(mut self, mut late: impl FnMut(EpisodeStats) -> Result<()>) -> Result<Vec<LearnerEvent>> {
        for a in &mut self.actors {
            if let Some(c) = a.child.as_ref() {
                crate::signals::terminate(c.id());
            }
        }
        for a in &mut self.actors {
            // An actor sends its last batch and waits up to 20 s for the acknowledgements.
            a.stop(Duration::from_secs(30));
        }
        self.learner.stop(Duration::from_secs(60));
        while let Ok(e) = self.episodes.try_recv() {
            late(e)?;
        }
        self.replay.stop(Duration::from_secs(60));
        let _ = self.collector_stop.send(true);
        let Cluster { rt, line_tx, line_rx, .. } = self;
        rt.shutdown_timeout(Duration::from_secs(2));
        drop(line_tx);
        Ok(learner_events(&line_rx).collect())
    }
}

/// The learner's events among the lines waiting in `rx` (the others are dropped).
fn learner_events(rx: &std_mpsc::Receiver<Line>) -> impl Iterator<Item = LearnerEvent> + '_ {
    rx.try_iter().filter(|(role, _)| role == "learner").filter_map(|(_, line)| serde_json::from_str(&line).ok())
}
