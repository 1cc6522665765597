//! The learner's configuration: which algorithm, its hyperparameters, and where it runs.
//!
//! Defaults reproduce the paper: the values of its Table I ("non-default hyperparameters")
//! are marked [paper Table I]; everything else the paper left at a MATLAB Reinforcement
//! Learning Toolbox default, which we could only infer, and is marked [inferred, …] with the
//! source (SPEC §2). Every field has a default, so a config file names only what it changes;
//! unknown fields are refused, so a typo is an error rather than a silent default.
//!
//! ```yaml
//! algorithm: sac
//! device: cuda
//! sac: { initial_alpha: 0.5 }
//! ```

use serde::{Deserialize, Serialize};

use crate::ConfigError;

/// Which of the paper's three algorithms (§II-A/B/C).
#[derive(Clone, Copy, Debug, Serialize, Deserialize, PartialEq, Eq, Hash)]
#[serde(rename_all = "snake_case")]
pub enum AlgorithmKind {
    /// Deep Deterministic Policy Gradient, paper eqs. 1–5.
    Ddpg,
    /// Twin-Delayed DDPG, paper eqs. 6–8.
    Td3,
    /// Soft Actor-Critic, paper eqs. 6, 9–11.
    Sac,
}

impl AlgorithmKind {
    /// `ddpg`, `td3` or `sac`, as in config files and checkpoint metadata.
    pub fn as_str(self) -> &'static str {
        match self {
            Self::Ddpg => "ddpg",
            Self::Td3 => "td3",
            Self::Sac => "sac",
        }
    }

    /// The wire enum.
    pub fn to_proto(self) -> mapless_proto::v1::Algorithm {
        use mapless_proto::v1::Algorithm;
        match self {
            Self::Ddpg => Algorithm::Ddpg,
            Self::Td3 => Algorithm::Td3,
            Self::Sac => Algorithm::Sac,
        }
    }
}

impl std::str::FromStr for AlgorithmKind {
    type Err = ConfigError;
    fn from_str(s: &str) -> Result<Self, ConfigError> {
        match s.trim().to_ascii_lowercase().as_str() {
            "ddpg" => Ok(Self::Ddpg),
            "td3" => Ok(Self::Td3),
            "sac" => Ok(Self::Sac),
            other => Err(ConfigError::InvalidConfig { field: "algorithm", reason: format!("is `{other}`; expected `ddpg`, `td3` or `sac`") }),
        }
    }
}

/// Everything the learner's agent (`mapless_learner::algo::Agent`) is built from. Stored in every checkpoint.
#[derive(Clone, Debug, Serialize, Deserialize, PartialEq)]
#[serde(default, deny_unknown_fields)]
pub struct LearnerConfig {
    /// Which algorithm [paper: all three are compared].
    pub algorithm: AlgorithmKind,
    /// `cpu`, `cuda` or `cuda:N` (see [`crate::Device`]; whether libtorch can use it is checked where the learner starts).
    pub device: String,
    /// Seed of the learner's random streams: initial weights, SAC's reparameterisation
    /// noise, TD3's target-smoothing noise, exploration noise.
    pub seed: u64,
    /// Width of both hidden layers of every network [inferred: 256; paper §II-B gives two
    /// ReLU hidden layers but not their width].
    pub hidden_width: i64,
    /// γ, discount factor [paper Table I: 0.995].
    pub gamma: f64,
    /// n of n-step TD targets: each replayed row carries the discounted sum of n rewards and
    /// the observation n steps later (the actors build such rows, `mapless_actor::nstep`), and
    /// eqs. 2, 7 and 9 bootstrap it with γⁿ instead of γ [paper: 1, one-step targets].
    /// Beyond the paper, 3 in `explore-sac`, 1 in the other presets. Its reason: a collision's price reaches the
    /// states n steps before it in one update instead of n (Sutton 1988; Hessel et al. 2018,
    /// "Rainbow"; Barth-Maron et al. 2018, D4PG); `explore-sac`'s cave misses are turns begun
    /// too late (docs/experiments.md). Off-policy, the sum follows the acting policy's own rewards,
    /// uncorrected, as those agents do. Measured at 3 on `explore-sac`, two seeds: no better
    /// than one-step targets alone (docs/experiments.md, "n-step targets"); adopted there with
    /// the start's offset, hard starts, the capped bonus, a price on coming close and the mean
    /// of a run's last 16 policies ("A price on coming close"), with which the gates' averages
    /// held early.
    pub n_step: usize,
    /// Actor (policy) learning rate [paper Table I: 5e-5].
    pub actor_lr: f64,
    /// Critic (Q-function) learning rate [paper Table I: 5e-4].
    pub critic_lr: f64,
    /// τ, target smoothing factor: θ_t ← (1−τ)θ_t + τθ after each target update
    /// [paper Table I: 0.001].
    pub tau: f64,
    /// M, minibatch size in eqs. 1, 3, 6, 10, 11 [paper Table I: 128].
    pub batch_size: usize,
    /// Largest global L2 norm of each network's gradient before the optimiser step; `null`
    /// disables clipping [inferred: 1.0, MATLAB `rlOptimizerOptions.GradientThreshold`; note
    /// MATLAB's default method clips each parameter tensor's norm, we clip the whole
    /// network's gradient as `torch.nn.utils.clip_grad_norm_` does].
    pub grad_clip_norm: Option<f64>,
    /// Adam's moment decay rates and ε for every optimiser.
    pub adam: AdamConfig,
    /// Evaluate twin critics as one batched network (`baddbmm` over stacked weights) rather
    /// than one after the other. Same parameters and results up to float rounding; purely a
    /// speed choice. Measured on the 2-core reference box, 1 thread, 17 obs / 2 actions,
    /// 2×256, batch 128 (`learner/examples/bench_updates.rs`), SAC: fused 126 vs 121 updates/s on
    /// 1 thread (97 vs 119 in a busier run), 180 vs 152 on 2 threads; a wash for DDPG (one
    /// critic) [inferred: true]. Applies to the autograd path (CUDA, `fused_update: false`);
    /// the fused CPU update runs each critic's layers as their own products.
    pub fused_critics: bool,
    /// On the CPU, run each update through hand-written forward and backward passes (one
    /// BLAS product per layer into reused buffers, fused elementwise loops, no autograd graph;
    /// `learner/src/cpu.rs`) instead of libtorch's autograd. The same equations, noise draws,
    /// Adam and clipping; results equal to the autograd path up to float rounding (tested).
    /// Purely a speed choice, for all three algorithms; see docs/learner.md for what it gave
    /// [inferred: true]. CUDA always uses autograd.
    pub fused_update: bool,
    /// Normalise each critic hidden layer's pre-activations per sample (layer normalisation
    /// without a learned gain or bias: zero mean, unit variance over the layer's units, ε
    /// 1e-5) before its ReLU. Beyond the paper, off in every paper preset [paper §II-B: plain
    /// ReLU layers]. Its reason: the critics' loss and Q grow through every `explore-sac` run
    /// and two runs with larger scans diverged (docs/experiments.md); normalised critic features
    /// are the standard cure for that growth (Ball et al. 2023, RLPD; Yue et al. 2023,
    /// "Understanding, predicting and better resolving Q-value divergence"). Without a gain or
    /// bias the parameters, checkpoints' layout and the published actor are unchanged; only
    /// the critics (all algorithms, both update paths) compute differently.
    pub critic_layer_norm: bool,
    /// Largest TD target: every algorithm's yᵢ (eqs. 2, 7, 9) is clipped to at most this
    /// before the critic step; `null` clips nothing. Beyond the paper, null in the paper's presets,
    /// 335 in `explore-sac` (300 plus room for its bonus on the EQS) [inferred: null]. Its reason: no return can exceed the reward's per-step supremum over
    /// 1 − γ, yet runs of `explore-sac` with five rays per beam drove their Q means past 2,000
    /// (docs/experiments.md). With eq. (1), the default 12 m sensor and 0.5 m/s the bound is
    /// (0.0075·12² + 1.5·0.5²)/(1 − 0.995) = 291 (`mapless maps stats` gives a world's own),
    /// plus, in expectation, α·ln 4/(1 − γ) for SAC's entropy bonus. A guard against the
    /// critics' runaway, not a cure for what starts it.
    pub td_target_max: Option<f64>,
    /// τ̄ of a running average of the actor's weights that is published in place of the
    /// actor (to the actors, to every evaluation, as the run's policy): after the n-th update
    /// θ̄ ← θ̄ + max(τ̄, 1/n)·(θ − θ̄), the plain mean of the first 1/τ̄ actors and an
    /// exponential average over about 1/τ̄ updates after that (Polyak & Juditsky 1992; Nikishin
    /// et al. 2018, "Improving stability in deep RL with weight averaging"). `null` publishes
    /// the trained actor itself. Beyond the paper, null in every preset [inferred: null]. Its
    /// reason: the policy one `explore-sac` run kept and one of its own earlier policies were
    /// collision-free in 10 and in 23 of the same 30 held-out cave episodes (docs/experiments.md); an average
    /// over the actor's recent weights is the usual guard against shipping a bad one. Training
    /// is unchanged: the actor loss, the critics and SAC's α all use the trained actor.
    pub policy_average: Option<f64>,
    /// DDPG's own settings.
    pub ddpg: DdpgConfig,
    /// TD3's own settings.
    pub td3: Td3Config,
    /// SAC's own settings.
    pub sac: SacConfig,
}

impl Default for LearnerConfig {
    fn default() -> Self {
        Self {
            algorithm: AlgorithmKind::Sac,
            device: "cpu".into(),
            seed: 0,
            hidden_width: crate::DEFAULT_HIDDEN_WIDTH,
            gamma: 0.995,
            n_step: 1,
            actor_lr: 5e-5,
            critic_lr: 5e-4,
            tau: 0.001,
            batch_size: 128,
            grad_clip_norm: Some(1.0),
            adam: AdamConfig::default(),
            fused_critics: true,
            fused_update: true,
            critic_layer_norm: false,
            td_target_max: None,
            policy_average: None,
            ddpg: DdpgConfig::default(),
            td3: Td3Config::default(),
            sac: SacConfig::default(),
        }
    }
}

/// Adam (Kingma & Ba 2015) settings shared by every optimiser.
#[derive(Clone, Copy, Debug, Serialize, Deserialize, PartialEq)]
#[serde(default, deny_unknown_fields)]
pub struct AdamConfig {
    /// β₁, first-moment decay [inferred: 0.9, MATLAB `GradientDecayFactor`].
    pub beta1: f64,
    /// β₂, second-moment decay [inferred: 0.999, MATLAB `SquaredGradientDecayFactor`].
    pub beta2: f64,
    /// ε added to the denominator [inferred: 1e-8, MATLAB `Epsilon`].
    pub eps: f64,
}

impl Default for AdamConfig {
    fn default() -> Self {
        Self { beta1: 0.9, beta2: 0.999, eps: 1e-8 }
    }
}

/// Exploration noise of DDPG and TD3: one type and one implementation, shared with the actors
/// (`mapless_proto::exploration`).
pub use mapless_proto::exploration::ExplorationNoise;

fn check_noise(noise: &ExplorationNoise, field: &'static str) -> Result<(), ConfigError> {
    noise.check().map_err(|reason| ConfigError::InvalidConfig { field, reason })
}

/// DDPG (paper §II-A).
#[derive(Clone, Copy, Debug, Serialize, Deserialize, PartialEq)]
#[serde(default, deny_unknown_fields)]
pub struct DdpgConfig {
    /// Exploration [inferred, MATLAB `rlDDPGAgentOptions.NoiseOptions`: Ornstein–Uhlenbeck
    /// θ = 0.15, σ = 0.3, μ = 0; dt = 0.1 s, the simulator's sample time (SPEC §2)].
    pub exploration: ExplorationNoise,
}

impl Default for DdpgConfig {
    fn default() -> Self {
        Self { exploration: ExplorationNoise::DDPG_DEFAULT }
    }
}

/// TD3 (paper §II-B).
#[derive(Clone, Copy, Debug, Serialize, Deserialize, PartialEq)]
#[serde(default, deny_unknown_fields)]
pub struct Td3Config {
    /// Exploration [inferred, MATLAB `rlTD3AgentOptions.ExplorationModel`: Gaussian,
    /// σ ≈ 0.32 on the normalised action (SPEC §2)].
    pub exploration: ExplorationNoise,
    /// σ of ε in eq. 7, target-policy smoothing [inferred, MATLAB
    /// `TargetPolicySmoothModel`: 0.45 on the normalised action (SPEC §2)].
    pub target_noise_std: f64,
    /// ε in eq. 7 is clipped to ±this [inferred, MATLAB: 0.5 (SPEC §2)].
    pub target_noise_clip: f64,
    /// The actor and the targets are updated once every this many critic updates
    /// [inferred, MATLAB `PolicyUpdateFrequency` / Fujimoto et al.: 2].
    pub policy_delay: u64,
}

impl Default for Td3Config {
    fn default() -> Self {
        Self { exploration: ExplorationNoise::TD3_DEFAULT, target_noise_std: 0.45, target_noise_clip: 0.5, policy_delay: 2 }
    }
}

/// SAC (paper §II-C).
#[derive(Clone, Copy, Debug, Serialize, Deserialize, PartialEq)]
#[serde(default, deny_unknown_fields)]
pub struct SacConfig {
    /// α at the start, the entropy weight of eqs. 9 and 11 [inferred, MATLAB
    /// `EntropyWeightOptions.EntropyWeight`: 1].
    pub initial_alpha: f64,
    /// Learning rate of log α in eq. 10 [inferred, MATLAB `EntropyWeightOptions.LearnRate`:
    /// 3e-4].
    pub alpha_lr: f64,
    /// Tune α by eq. 10; `false` keeps `initial_alpha` fixed [inferred: true].
    pub autotune_alpha: bool,
    /// H, target entropy of eq. 10; `null` means −act_dim [inferred, MATLAB
    /// `EntropyWeightOptions.TargetEntropy`: −(number of actions) = −2 for the car].
    pub target_entropy: Option<f64>,
    /// Lower clamp of the actor's log σ output [inferred: −20, Haarnoja et al.'s code and
    /// Stable-Baselines3]. Published with the policy (`sac.log_std_min`).
    pub log_std_min: f64,
    /// Upper clamp of the actor's log σ output [inferred: 2, as above]
    /// (`sac.log_std_max`).
    pub log_std_max: f64,
}

impl Default for SacConfig {
    fn default() -> Self {
        Self { initial_alpha: 1.0, alpha_lr: 3e-4, autotune_alpha: true, target_entropy: None, log_std_min: -20.0, log_std_max: 2.0 }
    }
}

/// Widest hidden layer accepted: 64 times the paper's 256 (Table I). A layer of this width
/// is 2^28 parameters (1 GiB of f32) before Adam's two moments; wider ones would be refused
/// by libtorch as an allocation, which is not a clear error.
pub const MAX_HIDDEN_WIDTH: i64 = 16_384;

impl LearnerConfig {
    /// γⁿ, the discount of the bootstrapped value in every TD target (`n_step`).
    pub fn bootstrap_discount(&self) -> f64 {
        self.gamma.powi(self.n_step as i32)
    }

    /// Checks every field's domain; the error names the field.
    pub fn validate(&self) -> Result<(), ConfigError> {
        let bad = |field: &'static str, reason: String| Err(ConfigError::InvalidConfig { field, reason });
        let unit = |x: f64| x.is_finite() && (0.0..=1.0).contains(&x);
        let positive = |x: f64| x.is_finite() && x > 0.0;
        self.device.parse::<crate::Device>()?;
        if !(1..=MAX_HIDDEN_WIDTH).contains(&self.hidden_width) {
            return bad("hidden_width", format!("is {}; must be in 1..={MAX_HIDDEN_WIDTH}", self.hidden_width));
        }
        if !unit(self.gamma) {
            return bad("gamma", format!("is {}; must be in [0, 1]", self.gamma));
        }
        if !(1..=mapless_proto::MAX_N_STEP).contains(&self.n_step) {
            return bad("n_step", format!("is {}; must be in 1..={}", self.n_step, mapless_proto::MAX_N_STEP));
        }
        if !unit(self.tau) {
            return bad("tau", format!("is {}; must be in [0, 1]", self.tau));
        }
        for (field, lr) in [("actor_lr", self.actor_lr), ("critic_lr", self.critic_lr), ("sac.alpha_lr", self.sac.alpha_lr)] {
            if !positive(lr) {
                return bad(field, format!("is {lr}; must be finite and > 0"));
            }
        }
        if self.batch_size == 0 {
            return bad("batch_size", "is 0; must be ≥ 1".into());
        }
        if let Some(c) = self.grad_clip_norm
            && !positive(c)
        {
            return bad("grad_clip_norm", format!("is {c}; must be finite and > 0, or null"));
        }
        if let Some(m) = self.td_target_max
            && !m.is_finite()
        {
            return bad("td_target_max", format!("is {m}; must be finite, or null"));
        }
        if let Some(t) = self.policy_average
            && !(t.is_finite() && t > 0.0 && t <= 1.0)
        {
            return bad("policy_average", format!("is {t}; must be in (0, 1], or null"));
        }
        let a = &self.adam;
        if !(a.beta1.is_finite() && (0.0..1.0).contains(&a.beta1)) {
            return bad("adam.beta1", format!("is {}; must be in [0, 1)", a.beta1));
        }
        if !(a.beta2.is_finite() && (0.0..1.0).contains(&a.beta2)) {
            return bad("adam.beta2", format!("is {}; must be in [0, 1)", a.beta2));
        }
        if !positive(a.eps) {
            return bad("adam.eps", format!("is {}; must be finite and > 0", a.eps));
        }
        check_noise(&self.ddpg.exploration, "ddpg.exploration")?;
        check_noise(&self.td3.exploration, "td3.exploration")?;
        let t = &self.td3;
        if !(t.target_noise_std.is_finite() && t.target_noise_std >= 0.0) {
            return bad("td3.target_noise_std", format!("is {}; must be finite and ≥ 0", t.target_noise_std));
        }
        if !(t.target_noise_clip.is_finite() && t.target_noise_clip >= 0.0) {
            return bad("td3.target_noise_clip", format!("is {}; must be finite and ≥ 0", t.target_noise_clip));
        }
        if t.policy_delay == 0 {
            return bad("td3.policy_delay", "is 0; must be ≥ 1".into());
        }
        let s = &self.sac;
        if !positive(s.initial_alpha) {
            return bad("sac.initial_alpha", format!("is {}; must be finite and > 0", s.initial_alpha));
        }
        if let Some(h) = s.target_entropy
            && !h.is_finite()
        {
            return bad("sac.target_entropy", format!("is {h}; must be finite or null"));
        }
        if !(s.log_std_min.is_finite() && s.log_std_max.is_finite() && s.log_std_min < s.log_std_max) {
            return bad("sac.log_std_min", format!("and log_std_max are {} and {}; need finite min < max", s.log_std_min, s.log_std_max));
        }
        Ok(())
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn defaults_are_the_papers_table_one() {
        let c = LearnerConfig::default();
        assert_eq!((c.gamma, c.actor_lr, c.critic_lr, c.tau, c.batch_size), (0.995, 5e-5, 5e-4, 0.001, 128));
        assert_eq!((c.hidden_width, c.grad_clip_norm), (256, Some(1.0)));
        assert_eq!((c.sac.initial_alpha, c.sac.alpha_lr, c.sac.target_entropy), (1.0, 3e-4, None));
        assert_eq!((c.td3.target_noise_std, c.td3.target_noise_clip, c.td3.policy_delay), (0.45, 0.5, 2));
        assert!(matches!(c.ddpg.exploration, ExplorationNoise::OrnsteinUhlenbeck { theta: 0.15, sigma: 0.3, .. }));
        c.validate().unwrap();
    }

    #[test]
    fn a_partial_json_config_keeps_the_other_defaults_and_typos_are_refused() {
        let c: LearnerConfig = serde_json::from_str(r#"{"algorithm":"td3","td3":{"policy_delay":3}}"#).unwrap();
        assert_eq!(c.algorithm, AlgorithmKind::Td3);
        assert_eq!(c.td3.policy_delay, 3);
        assert_eq!(c.td3.target_noise_std, 0.45);
        assert_eq!(c.gamma, 0.995);
        assert!(serde_json::from_str::<LearnerConfig>(r#"{"gama":0.9}"#).is_err());
    }

    #[test]
    fn validation_names_the_offending_field() {
        let mut c = LearnerConfig::default();
        c.gamma = 1.5;
        assert!(c.validate().unwrap_err().to_string().contains("`gamma`"));
        let mut c = LearnerConfig::default();
        c.td3.policy_delay = 0;
        assert!(c.validate().unwrap_err().to_string().contains("`td3.policy_delay`"));
        let mut c = LearnerConfig::default();
        c.device = "tpu".into();
        assert!(matches!(c.validate().unwrap_err(), ConfigError::InvalidDevice { .. }));
        for (width, ok) in [(0, false), (1, true), (MAX_HIDDEN_WIDTH, true), (MAX_HIDDEN_WIDTH + 1, false), (i64::MAX, false)] {
            let c = LearnerConfig { hidden_width: width, ..LearnerConfig::default() };
            assert_eq!(c.validate().is_ok(), ok, "hidden_width {width}");
        }
    }
}
