//! A single-process training loop on Pendulum-v1 with the real replay table: the harness
//! the learning and resume tests share; and [`in_process::InProcess`], a replay source on a
//! table in this process.
//!
//! ```text
//!   Pendulum ──transition──► TransitionBatchBuilder ──insert──► mapless_replay::Table
//!      ▲                                                            │ sample (uniform)
//!      └──── agent.act(explore) ◄──── Agent::update ◄── Minibatch ◄─┘
//! ```

#![allow(dead_code)]

pub mod in_process;
pub mod tmpfs;

use std::time::Instant;

use mapless_learner::algo::Agent;
use mapless_learner::batch::Minibatch;
use mapless_learner::config::{AlgorithmKind, ExplorationNoise, LearnerConfig};
use mapless_learner::envs::pendulum::{ACT_DIM, OBS_DIM, Pendulum};
use mapless_proto::{Transition, TransitionBatchBuilder};
use mapless_replay::{DurableTable, PersistenceConfig, RateLimiterConfig, SamplerConfig, TableConfig};
use rand::{Rng, SeedableRng};
use rand_pcg::Pcg64;
use serde::{Deserialize, Serialize};

/// Pendulum's usual hyperparameters (rl-baselines3-zoo / CleanRL), not the paper's.
pub fn pendulum_config(algorithm: AlgorithmKind, seed: u64) -> LearnerConfig {
    let mut c = LearnerConfig { algorithm, seed, hidden_width: 64, gamma: 0.98, actor_lr: 1e-3, critic_lr: 1e-3, tau: 0.005, batch_size: 128, grad_clip_norm: None, ..LearnerConfig::default() };
    c.sac.alpha_lr = 1e-3;
    c.td3.exploration = ExplorationNoise::Gaussian { sigma: 0.1 };
    c.ddpg.exploration = ExplorationNoise::Gaussian { sigma: 0.1 };
    // CleanRL's TD3 smoothing (σ 0.2, clip 0.5).
    c.td3.target_noise_std = 0.2;
    c
}

pub fn table_config(capacity: usize, batch: usize) -> TableConfig {
    TableConfig {
        name: "pendulum".into(),
        capacity,
        obs_dim: OBS_DIM,
        act_dim: ACT_DIM,
        sampler: SamplerConfig::Uniform,
        rate_limiter: RateLimiterConfig { min_size_to_sample: batch as u64, samples_per_insert: None, ..RateLimiterConfig::default() },
        ..TableConfig::default()
    }
}

/// Everything of the loop besides the agent and the table, for exact resumes.
#[derive(Debug, Clone, Serialize, Deserialize, PartialEq)]
pub struct LoopState {
    pub env: Pendulum,
    /// Warm-up actions.
    pub rng: Pcg64,
    pub obs: [f32; OBS_DIM],
    pub steps: u64,
    pub episode: u64,
    pub episode_return: f64,
    pub returns: Vec<f64>,
}

pub struct Harness {
    pub agent: Agent,
    /// Memory only or persistent; the harness uses it as the `Table` it derefs to.
    pub table: DurableTable,
    pub s: LoopState,
    pub learning_starts: u64,
    pub batch: usize,
}

impl Harness {
    pub fn new(cfg: &LearnerConfig, table: DurableTable, seed: u64, learning_starts: u64) -> Self {
        let agent = Agent::new(cfg, OBS_DIM, ACT_DIM).expect("agent");
        let mut env = Pendulum::new(seed);
        let obs = env.reset();
        Self {
            agent,
            table,
            s: LoopState { env, rng: Pcg64::seed_from_u64(seed ^ 0x5eed), obs, steps: 0, episode: 0, episode_return: 0.0, returns: Vec::new() },
            learning_starts,
            batch: cfg.batch_size,
        }
    }

    pub fn memory_table(cfg: &LearnerConfig, seed: u64) -> DurableTable {
        DurableTable::open(table_config(50_000, cfg.batch_size), PersistenceConfig::default(), seed).expect("table").0
    }

    pub fn persistent_table(cfg: &LearnerConfig, dir: &std::path::Path, seed: u64) -> DurableTable {
        let persistence = PersistenceConfig { dir: Some(dir.to_path_buf()), snapshot_interval_s: 0.0, ..PersistenceConfig::default() };
        DurableTable::open(table_config(50_000, cfg.batch_size), persistence, seed).expect("table").0
    }

    /// One environment step, its insert, and (after warm-up) one update.
    pub fn step(&mut self) {
        let s = &mut self.s;
        let action = if s.steps < self.learning_starts { s.rng.random_range(-1.0f32..1.0) } else { self.agent.act_slice(&s.obs, true).expect("act")[0] };
        let step_in_episode = s.env.steps();
        let out = s.env.step_normalized(action);
        let mut b = TransitionBatchBuilder::new(OBS_DIM, ACT_DIM);
        b.push(Transition {
            obs: &s.obs,
            action: &[action],
            reward: out.reward,
            next_obs: &out.obs,
            terminal: out.terminal,
            truncated: out.truncated,
            episode_id: s.episode,
            step: step_in_episode,
            policy_version: self.agent.updates(),
        })
        .expect("transition");
        self.table.insert(&b.finish("pendulum", s.steps + 1), None).expect("insert");
        s.steps += 1;
        s.episode_return += f64::from(out.reward);
        if out.terminal || out.truncated {
            s.returns.push(s.episode_return);
            s.episode_return = 0.0;
            s.episode += 1;
            s.obs = s.env.reset();
            self.agent.reset_exploration();
        } else {
            s.obs = out.obs;
        }
        if s.steps >= self.learning_starts {
            let sampled = self.table.sample(self.batch, None, None).expect("sample");
            let mb = Minibatch::from_sampled(&sampled, self.agent.device()).expect("minibatch");
            self.agent.update(&mb).expect("update");
        }
    }

    /// Mean return of `episodes` deterministic episodes on fixed evaluation seeds, run in
    /// lockstep (all Pendulum episodes last 200 steps).
    pub fn evaluate(&mut self, episodes: usize) -> f64 {
        let mut envs: Vec<Pendulum> = (0..episodes).map(|i| Pendulum::new(1_000_000 + i as u64)).collect();
        let mut obs: Vec<f32> = envs.iter_mut().flat_map(|e| e.reset()).collect();
        let mut total = 0.0;
        for _ in 0..mapless_learner::envs::pendulum::MAX_EPISODE_STEPS {
            let actions = self.agent.act_slice(&obs, false).expect("act");
            obs.clear();
            for (env, a) in envs.iter_mut().zip(&actions) {
                let out = env.step_normalized(*a);
                total += f64::from(out.reward);
                obs.extend_from_slice(&out.obs);
            }
        }
        total / episodes as f64
    }
}

/// Trains until the deterministic evaluation reaches `threshold` or `max_steps` pass;
/// evaluates every `every` steps after warm-up. Returns (steps, best score, seconds, scores).
pub fn train_until(algorithm: AlgorithmKind, seed: u64, threshold: f64, max_steps: u64, every: u64) -> (u64, f64, f64, Vec<(u64, f64)>) {
    mapless_learner::TorchThreads::default().apply().expect("threads");
    let cfg = pendulum_config(algorithm, seed);
    let table = Harness::memory_table(&cfg, seed);
    let mut h = Harness::new(&cfg, table, seed, 1_000);
    let start = Instant::now();
    let mut scores = Vec::new();
    let mut best = f64::NEG_INFINITY;
    while h.s.steps < max_steps {
        h.step();
        if h.s.steps > h.learning_starts && h.s.steps.is_multiple_of(every) {
            let score = h.evaluate(10);
            scores.push((h.s.steps, score));
            best = best.max(score);
            if score >= threshold {
                break;
            }
        }
    }
    (h.s.steps, best, start.elapsed().as_secs_f64(), scores)
}
