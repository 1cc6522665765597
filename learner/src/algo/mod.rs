//! The paper's three off-policy actor–critic algorithms behind one [`Agent`] enum.
//!
//! | file | algorithm | paper |
//! |---|---|---|
//! | [`ddpg`] | DDPG: one critic, deterministic tanh actor | §II-A, eqs. 1–5 |
//! | [`td3`] | TD3: twin critics, smoothed target, delayed actor | §II-B, eqs. 6–8 |
//! | [`sac`] | SAC: twin critics, tanh-Gaussian actor, learned α | §II-C, eqs. 6, 9–11 |
//!
//! One [`Agent::update`] is one gradient step on one [`Minibatch`] (TD3's delay schedule is
//! internal). Everything an agent learns or draws lives inside it — networks, targets, Adam
//! moments, α, counters, and the PCG64 streams that generate all of its noise — so a
//! checkpoint ([`crate::checkpoint`]) of the agent is an exact resume point. No algorithm
//! draws from libtorch's global RNG.
//!
//! # Actions
//!
//! Actions live in the normalised box [−1, 1]^act_dim; scaling to physical units (the car's
//! speed and yaw rate, Pendulum's torque) is the environment's job.
//!
//! # The published policy: names, shapes and inference
//!
//! [`Agent::policy_tensors`] returns the actor alone, as CPU f32 tensors in PyTorch layout
//! (weights `[out, in]`), under these names — the layout `mapless-actor` re-implements in
//! pure Rust, so any change here is a wire-format change:
//!
//! ```text
//!   actor.l0.weight  [H, obs]    actor.l0.bias  [H]
//!   actor.l1.weight  [H, H]      actor.l1.bias  [H]
//!   actor.out.weight [K, H]      actor.out.bias [K]
//!
//!   h₁ = relu(W₀·s + b₀);  h₂ = relu(W₁·h₁ + b₁);  y = W_out·h₂ + b_out
//!
//!   DDPG, TD3 (K = act_dim):    a = tanh(y)
//!   SAC       (K = 2·act_dim):  y = [ μ (first act_dim) | log σ (last act_dim) ]
//!                               log σ ← clamp(log σ, log_std_min, log_std_max)
//!                               explore:       a = tanh(μ + σ·ε),  ε ~ N(0, I)
//!                               deterministic: a = tanh(μ)
//! ```
//!
//! `log_std_min` / `log_std_max` are the config's `sac.log_std_min` / `sac.log_std_max`
//! (defaults −20 and 2) and are published in the policy's metadata under exactly those keys
//! ([`Agent::policy_metadata`]).
//!
//! # Metrics
//!
//! [`UpdateStats`] carries scalars under the fixed names of [`metric`] (CleanRL's
//! `losses/*`, `charts/*` namespaces) and the per-row |TD error| for prioritised replay.

pub mod ddpg;
mod fused;
pub mod sac;
pub mod td3;

use std::collections::{BTreeMap, HashMap};

use mapless_proto::v1::Algorithm;
use rand::SeedableRng;
use rand_distr::{Distribution, StandardNormal};
use rand_pcg::Pcg64;
use serde::{Deserialize, Serialize};
use tch::Tensor;

use crate::LearnerError;
use crate::batch::Minibatch;
use crate::config::{AlgorithmKind, ExplorationNoise, LearnerConfig};
use crate::nets::{ParamSet, mlp_forward, stacked_mlp_forward};
use crate::optim::{Adam, clip_grad_norm};

pub use ddpg::Ddpg;
pub use sac::Sac;
pub use td3::Td3;

/// Fixed metric names of [`UpdateStats::scalars`].
pub mod metric {
    /// Σₖ Lₖ, the (importance-weighted) critic loss of eqs. 1 / 6, summed over critics.
    pub const CRITIC_LOSS: &str = "losses/critic";
    /// The actor's loss: −mean Q (DDPG, TD3), J_π of eq. 11 (SAC). Absent on TD3 steps
    /// that do not update the actor.
    pub const ACTOR_LOSS: &str = "losses/actor";
    /// L_α of eq. 10 (SAC with automatic α).
    pub const ALPHA_LOSS: &str = "losses/alpha";
    /// Mean of Q(s, a) over the batch and the critics, for the replayed actions.
    pub const Q_MEAN: &str = "charts/q_mean";
    /// Mean of the TD target y.
    pub const TARGET_MEAN: &str = "charts/target_mean";
    /// α used in this update (SAC).
    pub const ALPHA: &str = "charts/alpha";
    /// −mean ln π(a|s) of the actor's fresh actions (SAC).
    pub const ENTROPY: &str = "charts/entropy";
    /// Critic gradient L2 norm before clipping (only when clipping is on).
    pub const CRITIC_GRAD_NORM: &str = "charts/critic_grad_norm";
    /// Actor gradient L2 norm before clipping (only when clipping is on).
    pub const ACTOR_GRAD_NORM: &str = "charts/actor_grad_norm";
}

/// What one update reports.
#[derive(Debug, Clone, Default, PartialEq)]
pub struct UpdateStats {
    /// `(name, value)` under the names of [`metric`].
    pub scalars: Vec<(&'static str, f64)>,
    /// Per row of the minibatch, |y − Q(s, a)| (for twin critics the mean over the two):
    /// the new priorities for prioritised replay, in the batch's row (and key) order.
    pub td_errors: Vec<f32>,
}

impl UpdateStats {
    /// The scalar called `name`, if this update reported it.
    pub fn get(&self, name: &str) -> Option<f64> {
        self.scalars.iter().find(|(n, _)| *n == name).map(|(_, v)| *v)
    }
}

/// One of the three algorithms. Build it with [`Agent::new`]. (One per learner process: the
/// variants' sizes do not matter.)
#[derive(Debug)]
#[allow(clippy::large_enum_variant)]
pub enum Agent {
    /// [`Ddpg`].
    Ddpg(Ddpg),
    /// [`Td3`].
    Td3(Td3),
    /// [`Sac`].
    Sac(Sac),
}

macro_rules! each {
    ($self:expr, $a:ident => $body:expr) => {
        match $self {
            Agent::Ddpg($a) => $body,
            Agent::Td3($a) => $body,
            Agent::Sac($a) => $body,
        }
    };
}

impl Agent {
    /// A freshly initialised agent for `cfg.algorithm` on `cfg.device` (checked against what
    /// libtorch can see). Initial weights come from `cfg.seed` alone.
    pub fn new(cfg: &LearnerConfig, obs_dim: usize, act_dim: usize) -> Result<Self, LearnerError> {
        cfg.validate()?;
        if obs_dim == 0 || act_dim == 0 {
            return Err(LearnerError::InvalidConfig { field: "obs_dim/act_dim", reason: format!("are {obs_dim}/{act_dim}; both must be ≥ 1") });
        }
        crate::malloc::retain_freed_memory();
        let device = crate::device::ToTch::to_tch(crate::device::available(&cfg.device)?);
        let common = Common::new(cfg.clone(), obs_dim, act_dim, device);
        let mut agent = match cfg.algorithm {
            AlgorithmKind::Ddpg => Self::Ddpg(Ddpg::new(common)?),
            AlgorithmKind::Td3 => Self::Td3(Td3::new(common)?),
            AlgorithmKind::Sac => Self::Sac(Sac::new(common)?),
        };
        if cfg.policy_average.is_some() {
            each!(&mut agent, a => a.c.policy_average = Some(a.actor.net.duplicate_as(ACTOR, AVERAGE)));
        }
        Ok(agent)
    }

    /// One gradient step on `batch` (TD3: the actor and the targets only every
    /// `td3.policy_delay`-th step). The batch's dimensions must be the agent's. On error
    /// (bad dimensions, a non-finite loss) no parameter changed in the failing stage.
    pub fn update(&mut self, batch: &Minibatch) -> Result<UpdateStats, LearnerError> {
        let c = self.common();
        if batch.obs_dim() != c.obs_dim || batch.act_dim() != c.act_dim {
            return Err(LearnerError::InvalidBatch(format!("batch has obs_dim {} act_dim {}, this agent learns {}/{}", batch.obs_dim(), batch.act_dim(), c.obs_dim, c.act_dim)));
        }
        // The one place that chooses the path: the hand-written CPU passes when configured,
        // on the CPU, and the batch is plain host f32; libtorch's autograd otherwise. Both draw
        // their noise through the same per-algorithm function, so they agree draw for draw.
        let stats = if c.cfg.fused_update
            && c.device == tch::Device::Cpu
            && let Some(host) = batch.host()
        {
            each!(self, a => a.update_fused(&host))
        } else {
            each!(self, a => a.update(batch))
        }?;
        each!(self, a => a.c.average_policy(&a.actor.net));
        Ok(stats)
    }

    /// Actions `[N, act_dim]` in [−1, 1] for observations `[N, obs_dim]` (moved to the
    /// agent's device), without gradient. `explore`: DDPG and TD3 add their configured noise
    /// (clamped back into [−1, 1]); SAC samples tanh(μ + σε). Otherwise the deterministic
    /// policy: tanh(y) or, for SAC, tanh(μ).
    pub fn act(&mut self, obs: &Tensor, explore: bool) -> Result<Tensor, LearnerError> {
        let d = self.common().obs_dim as i64;
        let size = obs.size();
        if size.len() != 2 || size[1] != d || size[0] < 1 {
            return Err(LearnerError::InvalidBatch(format!("observations of shape {size:?}, expected [N, {d}]")));
        }
        let obs = obs.to_kind(tch::Kind::Float).to_device(self.common().device);
        let _guard = tch::no_grad_guard();
        each!(self, a => a.act(&obs, explore))
    }

    /// [`Agent::act`] on row-major host slices: `obs` holds N whole observations; returns
    /// N × act_dim values. Non-finite observations are an error.
    pub fn act_slice(&mut self, obs: &[f32], explore: bool) -> Result<Vec<f32>, LearnerError> {
        let d = self.common().obs_dim;
        if obs.is_empty() || !obs.len().is_multiple_of(d) {
            return Err(LearnerError::InvalidBatch(format!("{} observation values are not whole rows of {d}", obs.len())));
        }
        if let Some(i) = obs.iter().position(|v| !v.is_finite()) {
            return Err(LearnerError::InvalidBatch(format!("observation value {i} is {}", obs[i])));
        }
        let t = Tensor::from_slice(obs).view([(obs.len() / d) as i64, d as i64]);
        let a = self.act(&t, explore)?.to(tch::Device::Cpu);
        Ok(Vec::<f32>::try_from(&a.reshape([-1]))?)
    }

    /// Resets exploration state (DDPG/TD3 Ornstein–Uhlenbeck noise) — call at episode start.
    pub fn reset_exploration(&mut self) {
        self.common_mut().explore.reset();
    }

    /// The policy network alone: `(name, CPU f32 tensor)` in the layout of the module docs:
    /// the running average of the actor's weights when `policy_average` is set (under the
    /// actor's names), the trained actor otherwise.
    pub fn policy_tensors(&self) -> Vec<(String, Tensor)> {
        each!(self, a => match &a.c.policy_average {
            Some(avg) => avg
                .named_cpu()
                .into_iter()
                .map(|(name, t)| (name.strip_prefix(AVERAGE).map_or(name.clone(), |rest| format!("{ACTOR}{rest}")), t))
                .collect(),
            None => a.actor_params().named_cpu(),
        })
    }

    /// Metadata to publish with [`Agent::policy_tensors`]: `algorithm` (`ddpg`/`td3`/`sac`),
    /// `obs_dim`, `act_dim`, `hidden_width`, `version` (the update counter), and for SAC
    /// `sac.log_std_min` / `sac.log_std_max`.
    pub fn policy_metadata(&self) -> BTreeMap<String, String> {
        let c = self.common();
        let mut m = BTreeMap::new();
        m.insert("algorithm".into(), c.cfg.algorithm.as_str().into());
        m.insert("obs_dim".into(), c.obs_dim.to_string());
        m.insert("act_dim".into(), c.act_dim.to_string());
        m.insert("hidden_width".into(), c.cfg.hidden_width.to_string());
        m.insert("version".into(), c.updates.to_string());
        if c.cfg.n_step > 1 {
            // The actors' rows must sum as many rewards, with the same γ, as the targets
            // bootstrap over.
            m.insert(mapless_proto::META_N_STEP.into(), c.cfg.n_step.to_string());
            m.insert(mapless_proto::META_GAMMA.into(), c.cfg.gamma.to_string());
        }
        if let Self::Sac(_) = self {
            m.insert("sac.log_std_min".into(), c.cfg.sac.log_std_min.to_string());
            m.insert("sac.log_std_max".into(), c.cfg.sac.log_std_max.to_string());
        }
        m
    }

    /// The wire enum of this agent's algorithm.
    pub fn algorithm(&self) -> Algorithm {
        self.common().cfg.algorithm.to_proto()
    }

    /// Gradient steps taken ([`Agent::update`] calls that succeeded).
    pub fn updates(&self) -> u64 {
        self.common().updates
    }

    /// The config the agent was built from.
    pub fn config(&self) -> &LearnerConfig {
        &self.common().cfg
    }

    /// Observation width.
    pub fn obs_dim(&self) -> usize {
        self.common().obs_dim
    }

    /// Action width.
    pub fn act_dim(&self) -> usize {
        self.common().act_dim
    }

    /// The device the agent's tensors live on.
    pub fn device(&self) -> tch::Device {
        self.common().device
    }

    /// SAC's current α (None for DDPG and TD3).
    pub fn alpha(&self) -> Option<f64> {
        match self {
            Self::Sac(s) => Some(s.alpha()),
            _ => None,
        }
    }

    /// Every trained or tracked tensor, CPU copies under stable names (networks, targets,
    /// optimiser moments as `optim.{net}.exp_avg` / `.exp_avg_sq`, SAC's `log_alpha`): what a
    /// checkpoint stores. Intended for checkpoints and for tests that compare runs.
    pub fn state_tensors(&self) -> Vec<(String, Tensor)> {
        let mut out = Vec::new();
        each!(self, a => {
            for set in a.nets() {
                out.extend(set.named_cpu());
            }
            for (name, opt) in a.opts() {
                let (m, v) = opt.moments();
                out.push((format!("optim.{name}.exp_avg"), m.to(tch::Device::Cpu).copy()));
                out.push((format!("optim.{name}.exp_avg_sq"), v.to(tch::Device::Cpu).copy()));
            }
        });
        out
    }

    /// Overwrites named tensors of [`Agent::state_tensors`]'s networks (`actor.l0.weight`,
    /// `target_critic.out.bias`, `log_alpha`, …) with the given values, e.g. to set known
    /// weights in a test or to warm-start a policy. Optimiser state is untouched. A name the
    /// agent does not have, or another shape, is an error (earlier names stay written).
    pub fn set_tensors(&mut self, named: &[(&str, Tensor)]) -> Result<(), LearnerError> {
        for (name, value) in named {
            let mut done = false;
            each!(self, a => {
                for set in a.nets_mut() {
                    let found = set.set(name, value).map_err(|reason| {
                        LearnerError::InvalidNetwork { name: (*name).to_string(), reason }
                    })?;
                    if found {
                        done = true;
                        break;
                    }
                }
            });
            if !done {
                return Err(LearnerError::InvalidNetwork { name: (*name).to_string(), reason: "no parameter of this agent has that name".into() });
            }
        }
        Ok(())
    }

    /// The non-tensor state a checkpoint stores (counters, random streams).
    pub(crate) fn state_meta(&self) -> AgentMeta {
        let c = self.common();
        let mut optim_steps = BTreeMap::new();
        each!(self, a => {
            for (name, opt) in a.opts() {
                optim_steps.insert(name.to_string(), opt.steps());
            }
        });
        AgentMeta { updates: c.updates, optim_steps, noise_rng: c.noise.rng.clone(), explore: c.explore.clone() }
    }

    /// Restores what [`Agent::state_tensors`] and [`Agent::state_meta`] produced. Every name
    /// must be present with this agent's shape and no other name may appear; the error says
    /// which. On error the agent may be partly overwritten: discard it.
    pub(crate) fn restore_state(&mut self, tensors: &HashMap<String, Tensor>, meta: AgentMeta) -> Result<(), String> {
        let device = self.device();
        let get = |name: &str| tensors.get(name).map(|t| t.to_device(device));
        let mut expected = 0usize;
        each!(self, a => {
            for set in a.nets_mut() {
                expected += set.names().len();
                set.load_named(&get)?;
            }
            for (name, opt) in a.opts_mut() {
                let steps = *meta
                    .optim_steps
                    .get(name)
                    .ok_or_else(|| format!("optimiser `{name}` has no step count"))?;
                let m = get(&format!("optim.{name}.exp_avg"))
                    .ok_or_else(|| format!("tensor `optim.{name}.exp_avg` is missing"))?;
                let v = get(&format!("optim.{name}.exp_avg_sq"))
                    .ok_or_else(|| format!("tensor `optim.{name}.exp_avg_sq` is missing"))?;
                let want = opt.moments().0.size();
                if m.size() != want || v.size() != want {
                    return Err(format!(
                        "optimiser `{name}` moments have shapes {:?}/{:?}, need {want:?}",
                        m.size(),
                        v.size()
                    ));
                }
                opt.restore(&m, &v, steps);
                expected += 2;
            }
        });
        if tensors.len() != expected {
            return Err(format!("{} tensors stored, this agent has {expected}", tensors.len()));
        }
        if meta.explore.cfg != self.common().explore.cfg {
            return Err("exploration noise settings differ from the stored ones".into());
        }
        let c = self.common_mut();
        c.updates = meta.updates;
        c.noise.rng = meta.noise_rng;
        c.explore = meta.explore;
        Ok(())
    }

    fn common(&self) -> &Common {
        each!(self, a => &a.c)
    }

    fn common_mut(&mut self) -> &mut Common {
        each!(self, a => &mut a.c)
    }
}

/// Non-tensor agent state in a checkpoint.
#[derive(Debug, Clone, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub(crate) struct AgentMeta {
    pub updates: u64,
    pub optim_steps: BTreeMap<String, u64>,
    pub noise_rng: Pcg64,
    pub explore: Explorer,
}

// ---------------------------------------------------------------------------------------------
// Plumbing shared by the three algorithms.
// ---------------------------------------------------------------------------------------------

/// What every algorithm carries besides its networks.
#[derive(Debug)]
pub(crate) struct Common {
    pub cfg: LearnerConfig,
    pub obs_dim: usize,
    pub act_dim: usize,
    pub device: tch::Device,
    /// Initialisation draws (only at construction).
    pub init_rng: Pcg64,
    /// Noise inside updates: TD3 target smoothing, SAC reparameterisation.
    pub noise: NoiseSource,
    /// Noise for exploring actions.
    pub explore: Explorer,
    /// Successful updates.
    pub updates: u64,
    /// The running average of the actor's weights (`LearnerConfig::policy_average`), named
    /// `actor_average.*`; what [`Agent::policy_tensors`] publishes when set.
    pub policy_average: Option<ParamSet>,
}

/// The leading name of the actor's parameters, and of their running average.
const ACTOR: &str = "actor";
const AVERAGE: &str = "actor_average";

/// Stream ids that split one seed into independent PCG64 streams.
const STREAM_INIT: u64 = 0x1a17;
const STREAM_NOISE: u64 = 0x2b28;
const STREAM_EXPLORE: u64 = 0x3c39;

fn stream(seed: u64, id: u64) -> Pcg64 {
    // Pcg64::new(state, stream) gives distinct sequences for distinct stream ids.
    Pcg64::new(u128::from(seed) << 64 | u128::from(id), u128::from(id) << 1 | 1)
}

impl Common {
    pub fn new(cfg: LearnerConfig, obs_dim: usize, act_dim: usize, device: tch::Device) -> Self {
        let exploration = match cfg.algorithm {
            AlgorithmKind::Ddpg => Some(cfg.ddpg.exploration),
            AlgorithmKind::Td3 => Some(cfg.td3.exploration),
            AlgorithmKind::Sac => None,
        };
        Self {
            init_rng: stream(cfg.seed, STREAM_INIT),
            noise: NoiseSource { rng: stream(cfg.seed, STREAM_NOISE) },
            explore: Explorer { cfg: exploration, rng: stream(cfg.seed, STREAM_EXPLORE), ou: Vec::new() },
            cfg,
            obs_dim,
            act_dim,
            device,
            updates: 0,
            policy_average: None,
        }
    }

    /// After the `updates`-th update: θ̄ ← θ̄ + max(τ̄, 1/updates)·(θ − θ̄) when the average
    /// is kept (`LearnerConfig::policy_average`).
    pub fn average_policy(&mut self, actor: &ParamSet) {
        if let (Some(avg), Some(tau)) = (self.policy_average.as_mut(), self.cfg.policy_average) {
            avg.soft_update_from(actor, tau.max(1.0 / self.updates.max(1) as f64));
        }
    }

    pub fn hidden(&self) -> i64 {
        self.cfg.hidden_width
    }
}

/// Standard-normal noise drawn from a PCG64 stream on the host (bit-reproducible across
/// devices and thread counts, and checkpointable, unlike libtorch's generator). Each algorithm
/// draws an update's noise through one function of its own (`Td3::smoothing_draws`,
/// `Sac::update_draws`) that both update paths call.
#[derive(Debug)]
pub(crate) struct NoiseSource {
    pub rng: Pcg64,
}

impl NoiseSource {
    /// `n` draws of N(0, 1) into `out` (cleared first).
    pub fn fill(&mut self, out: &mut Vec<f32>, n: usize) {
        out.clear();
        let rng = &mut self.rng;
        out.extend((0..n).map(|_| -> f32 { StandardNormal.sample(rng) }));
    }
}

/// Exploration noise for deterministic actors (DDPG, TD3), applied on the host.
#[derive(Debug, Clone, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub(crate) struct Explorer {
    pub cfg: Option<ExplorationNoise>,
    pub rng: Pcg64,
    /// Ornstein–Uhlenbeck state, one value per action component of the last call's batch.
    pub ou: Vec<f32>,
}

impl Explorer {
    fn reset(&mut self) {
        self.ou.clear();
    }

    /// Adds the configured noise to `actions` (row-major) and clamps into [−1, 1]: the
    /// actors' implementation ([`ExplorationNoise::apply`]), on this agent's stream.
    pub fn perturb(&mut self, actions: &mut [f32]) {
        if let Some(noise) = self.cfg {
            noise.apply(&mut self.ou, &mut self.rng, actions);
        }
    }
}

/// A network with its optimiser.
#[derive(Debug)]
pub(crate) struct Trained {
    pub net: ParamSet,
    pub opt: Adam,
    /// The flat gradient of the last step (reused buffer, [`ParamSet::flat_grad_into`]).
    grad: Tensor,
}

impl Trained {
    pub fn new(net: ParamSet, lr: f64, c: &Common) -> Self {
        let opt = Adam::new(net.numel(), c.device, lr, c.cfg.adam);
        let grad = net.flat().zeros_like();
        Self { net, opt, grad }
    }

    /// ∇ of `loss` with respect to this network's parameters only (other networks in the
    /// graph get no gradient and are not touched), clipped to the config's global norm, then
    /// one Adam step. Returns the norm before clipping when clipping is on.
    pub fn step(&mut self, loss: &Tensor, clip: Option<f64>) -> Result<Option<f64>, LearnerError> {
        let grads = Tensor::f_run_backward(&[loss], self.net.params(), false, false)?;
        ParamSet::flat_grad_into(&grads, &self.grad);
        let norm = clip.map(|c| clip_grad_norm(&mut self.grad, c));
        self.opt.step(self.net.flat(), &self.grad);
        Ok(norm)
    }
}

/// Acting with a deterministic tanh actor (DDPG, TD3): a = tanh(π(s)), plus the
/// exploration noise when exploring. Call under `no_grad`.
pub(crate) fn deterministic_act(actor: &ParamSet, obs: &Tensor, explore: bool, c: &mut Common) -> Result<Tensor, LearnerError> {
    let a = mlp_forward(actor.params(), obs).tanh();
    if !explore {
        return Ok(a);
    }
    let shape = a.size();
    let mut host = Vec::<f32>::try_from(&a.to(tch::Device::Cpu).reshape([-1]))?;
    c.explore.perturb(&mut host);
    Ok(Tensor::from_slice(&host).view(shape.as_slice()).to_device(c.device))
}

/// Q-values of a stack of critics: `[K, B, 1]` for observations `[B, obs]` and actions
/// `[B, act]` (the critic's input is their concatenation, paper §II-B). `params` are a
/// critic [`ParamSet`]'s [`ParamSet::params`], or its [`ParamSet::frozen`] views where only
/// the action's gradient is wanted (the actor's loss). `cfg` gives the stack's evaluation
/// (`fused_critics`) and its layer normalisation (`critic_layer_norm`).
pub(crate) fn critics(params: &[Tensor], obs: &Tensor, action: &Tensor, cfg: &LearnerConfig) -> Tensor {
    let x = Tensor::cat(&[obs, action], 1);
    stacked_mlp_forward(params, &x, cfg.fused_critics, cfg.critic_layer_norm)
}

/// `y` clipped to at most `max` (`LearnerConfig::td_target_max`), or `y` itself.
pub(crate) fn cap_targets(y: Tensor, max: Option<f64>) -> Tensor {
    match max {
        Some(m) => y.clamp_max(m),
        None => y,
    }
}

/// What a critic step reports.
pub(crate) struct CriticStep {
    pub loss: f64,
    pub q_mean: f64,
    pub target_mean: f64,
    pub grad_norm: Option<f64>,
    pub td_errors: Vec<f32>,
}

/// One critic step for eqs. 1 / 6 with importance weights w (1 for uniform replay):
///
/// ```text
///   L = Σₖ Lₖ,   Lₖ = (1/M) Σᵢ wᵢ (yᵢ − Qₖ(sᵢ, aᵢ))²
/// ```
///
/// `y` is `[B, 1]` and carries no gradient. Checks the loss is finite before stepping.
pub(crate) fn critic_step(critic: &mut Trained, b: &Minibatch, y: &Tensor, c: &Common) -> Result<CriticStep, LearnerError> {
    let q = critics(critic.net.params(), &b.obs, &b.action, &c.cfg); // [K, B, 1]
    let td = &q - y; // broadcast over K
    let loss = (td.square() * &b.weights).sum(None) / b.rows() as f64;
    let loss_value = loss.double_value(&[]);
    if !loss_value.is_finite() {
        return Err(LearnerError::NonFiniteLoss { what: metric::CRITIC_LOSS, value: loss_value, update: c.updates });
    }
    let grad_norm = critic.step(&loss, c.cfg.grad_clip_norm)?;
    let _guard = tch::no_grad_guard();
    let td_rows = td.detach().abs().mean_dim(0, false, None).reshape([-1]);
    let mut td_errors = vec![0.0f32; b.rows()];
    td_rows.f_copy_data(&mut td_errors, b.rows())?;
    Ok(CriticStep { loss: loss_value, q_mean: q.detach().mean(None).double_value(&[]), target_mean: y.mean(None).double_value(&[]), grad_norm, td_errors })
}

/// Fails with [`LearnerError::NonFiniteLoss`] unless `loss` is finite; returns its value.
pub(crate) fn finite(loss: &Tensor, what: &'static str, c: &Common) -> Result<f64, LearnerError> {
    let v = loss.double_value(&[]);
    if v.is_finite() { Ok(v) } else { Err(LearnerError::NonFiniteLoss { what, value: v, update: c.updates }) }
}

/// Speed of [`Agent::update`]: how many it completes per second, on random minibatches of
/// `cfg.batch_size` rows, after a short warm-up, for about `seconds`. `threads` is applied
/// first (libtorch allows one inter-op setting per process). For `mapless bench learner`.
pub fn bench_updates(cfg: &LearnerConfig, obs_dim: usize, act_dim: usize, threads: crate::TorchThreads, seconds: f64) -> Result<f64, LearnerError> {
    threads.apply()?;
    let mut agent = Agent::new(cfg, obs_dim, act_dim)?;
    let mut rng = Pcg64::seed_from_u64(cfg.seed);
    let batches = (0..8).map(|_| Minibatch::random(cfg.batch_size, obs_dim, act_dim, &mut rng, agent.device())).collect::<Result<Vec<_>, _>>()?;
    for b in batches.iter().cycle().take(20) {
        agent.update(b)?;
    }
    let start = std::time::Instant::now();
    let mut n = 0u64;
    for b in batches.iter().cycle() {
        agent.update(b)?;
        n += 1;
        if n.is_multiple_of(8) && start.elapsed().as_secs_f64() >= seconds {
            break;
        }
    }
    Ok(n as f64 / start.elapsed().as_secs_f64())
}
