//! Soft Actor-Critic (Haarnoja et al. 2018, with automatic entropy tuning), as the paper
//! writes it (§II-C).
//!
//! Networks: a stochastic actor π(·|s; θ) whose output is [μ | log σ] (2·act_dim values,
//! log σ clamped to [`log_std_min`, `log_std_max`]); k = 2 critics Q_k(s, a|φ_k) with target
//! copies Q_tk(φ_tk) (no target actor); the entropy weight α = exp(log α).
//!
//! **The tanh-Gaussian policy.** An unbounded u = μ + σ·ε (ε ~ N(0, I), the
//! reparameterisation) is squashed, a = tanh(u). Its log-density, with the change-of-variables
//! correction for the tanh, summed over the action's components j:
//!
//! ```text
//!   ln π(a|s) = Σⱼ [ −½εⱼ² − ln σⱼ − ½ln 2π  −  ln(1 − tanh²(uⱼ)) ]
//!   ln(1 − tanh²(u)) = 2 (ln 2 − u − softplus(−2u))        (exact, and stable for large |u|)
//! ```
//!
//! Every [`Sac::update`], on a minibatch of M transitions, with α the value before the step:
//!
//! 1. **Critics**, eqs. 6 and 9: minimise Σ_k L_k, L_k = (1/M) Σᵢ wᵢ (yᵢ − Q_k(sᵢ, aᵢ))², with
//!    ```text
//!      yᵢ = Rᵢ + γ (1 − terminalᵢ) [ min_k Q_tk(sᵢ₊₁, ãᵢ₊₁) − α ln π(ãᵢ₊₁|sᵢ₊₁) ],
//!      ãᵢ₊₁ ~ π(·|sᵢ₊₁; θ)  (fresh sample)
//!    ```
//! 2. **Actor**, eq. 11: minimise J_π = (1/M) Σᵢ [ α ln π(ãᵢ|sᵢ) − min_k Q_k(sᵢ, ãᵢ) ] in θ,
//!    ãᵢ = tanh(μ + σεᵢ) reparameterised, using the critics just updated.
//! 3. **α**, eq. 10: minimise L_α = (1/M) Σᵢ (−α ln π(ãᵢ|sᵢ) − αH) over log α, with ln π from
//!    step 2 held fixed and H the target entropy (−act_dim by default). Its gradient in
//!    log α is ∂L_α/∂ln α = −α·(mean ln π + H): when the policy's entropy −mean ln π is below
//!    H, the gradient is negative and α grows.
//! 4. **Targets**: φ_tk ← (1−τ)φ_tk + τφ_k.
//!
//! Departures from the paper's text:
//! - eq. 9 as printed puts "−α ln π" outside the γ-discounted term; we use Haarnoja et al.'s
//!   (and MATLAB's) soft value, γ·(min Q_t − α ln π), and the terminal mask;
//! - eq. 11 as printed takes min over the *target* critics Q_tk; Haarnoja et al., MATLAB's
//!   documentation, CleanRL and SB3 all use the critics being trained, Q_k, which is what we
//!   do (with τ = 0.001 the targets would lag the actor by ~1000 updates);
//! - α is parameterised as exp(log α) so it stays positive (Haarnoja et al.'s code, CleanRL);
//! - importance weights on the critic loss, as in [`super::ddpg`].

use tch::Tensor;

use super::{Common, CriticStep, Trained, UpdateStats, cap_targets, critic_step, critics, finite, fused, metric};
use crate::LearnerError;
use crate::batch::Minibatch;
use crate::nets::{ParamSet, mlp_forward, mlp_specs, stacked_mlp_specs};
use crate::optim::Adam;

/// Number of critics (paper: k = 2, "similar to TD3").
pub const CRITICS: i64 = 2;

/// ½ ln 2π.
pub(super) const HALF_LN_2PI: f64 = 0.918_938_533_204_672_7;

/// A SAC agent. See the module docs for the update.
#[derive(Debug)]
pub struct Sac {
    pub(crate) c: Common,
    pub(super) actor: Trained,
    pub(super) critic: Trained,
    pub(super) target_critic: ParamSet,
    /// One tensor, `log_alpha` `[1]`.
    pub(super) log_alpha: Trained,
    pub(super) target_entropy: f64,
    /// Buffers of the fused CPU update ([`LearnerConfig::fused_update`]), reused every step.
    ///
    /// [`LearnerConfig::fused_update`]: crate::config::LearnerConfig::fused_update
    pub(super) host: (fused::Work, fused::Head),
}

/// What one SAC update measured, on either path (autograd in [`Sac::update`], the fused CPU
/// update in [`super::fused`]); [`SacStep::into_stats`] holds the one list of SAC's scalars.
#[derive(Debug)]
pub(super) struct SacStep {
    /// Σₖ Lₖ (eq. 6).
    pub critic_loss: f64,
    /// J_π (eq. 11).
    pub actor_loss: f64,
    /// L_α (eq. 10).
    pub alpha_loss: f64,
    /// Mean Q(s, a) of the replayed actions.
    pub q_mean: f64,
    /// Mean TD target y (eq. 9).
    pub target_mean: f64,
    /// α used in the update (the value before its step).
    pub alpha: f64,
    /// Mean ln π(ã|s) of the actor's fresh actions (the entropy is its negative).
    pub mean_log_prob: f64,
    /// The critics' gradient norm before clipping (only when clipping is on).
    pub critic_grad_norm: Option<f64>,
    /// The actor's gradient norm before clipping (only when clipping is on).
    pub actor_grad_norm: Option<f64>,
    /// Per row, |y − Q(s, a)| (the new priorities).
    pub td_errors: Vec<f32>,
}

impl SacStep {
    /// The update's report under the names of [`metric`].
    pub(super) fn into_stats(self) -> UpdateStats {
        let mut scalars = vec![
            (metric::CRITIC_LOSS, self.critic_loss),
            (metric::ACTOR_LOSS, self.actor_loss),
            (metric::ALPHA_LOSS, self.alpha_loss),
            (metric::Q_MEAN, self.q_mean),
            (metric::TARGET_MEAN, self.target_mean),
            (metric::ALPHA, self.alpha),
            (metric::ENTROPY, -self.mean_log_prob),
        ];
        scalars.extend(self.critic_grad_norm.map(|n| (metric::CRITIC_GRAD_NORM, n)));
        scalars.extend(self.actor_grad_norm.map(|n| (metric::ACTOR_GRAD_NORM, n)));
        UpdateStats { scalars, td_errors: self.td_errors }
    }
}

/// A sampled tanh-Gaussian action and its log-density.
#[derive(Debug)]
pub struct Sample {
    /// a = tanh(μ + σε), `[B, act_dim]`.
    pub action: Tensor,
    /// ln π(a|s), `[B, 1]`, with the tanh correction.
    pub log_prob: Tensor,
}

impl Sac {
    pub(crate) fn new(mut c: Common) -> Result<Self, LearnerError> {
        let (o, a, h) = (c.obs_dim as i64, c.act_dim as i64, c.hidden());
        let actor = ParamSet::new(mlp_specs("actor", o, h, 2 * a, &mut c.init_rng), c.device)?;
        let critic = ParamSet::new(stacked_mlp_specs("critic", CRITICS, o + a, h, 1, &mut c.init_rng), c.device)?;
        let target_critic = critic.duplicate_as("critic", "target_critic");
        let log_alpha = ParamSet::new(vec![("log_alpha".into(), vec![1], vec![c.cfg.sac.initial_alpha.ln() as f32])], c.device)?;
        let target_entropy = c.cfg.sac.target_entropy.unwrap_or(-(c.act_dim as f64));
        Ok(Self {
            actor: Trained::new(actor, c.cfg.actor_lr, &c),
            critic: Trained::new(critic, c.cfg.critic_lr, &c),
            log_alpha: Trained::new(log_alpha, c.cfg.sac.alpha_lr, &c),
            target_critic,
            target_entropy,
            host: Default::default(),
            c,
        })
    }

    /// α = exp(log α).
    pub fn alpha(&self) -> f64 {
        self.log_alpha.net.flat().double_value(&[0]).exp()
    }

    /// H, the target entropy of eq. 10.
    pub fn target_entropy(&self) -> f64 {
        self.target_entropy
    }

    /// μ and clamped log σ for observations `[B, obs_dim]`, each `[B, act_dim]`.
    pub fn mean_log_std(&self, obs: &Tensor) -> (Tensor, Tensor) {
        let out = mlp_forward(self.actor.net.params(), obs);
        let a = self.c.act_dim as i64;
        let s = &self.c.cfg.sac;
        (out.narrow(1, 0, a), out.narrow(1, a, a).clamp(s.log_std_min, s.log_std_max))
    }

    /// a = tanh(μ + σε) and ln π(a|s) (module docs) for given standard-normal `eps`
    /// `[B, act_dim]`. Differentiable in the actor's parameters.
    pub fn sample_with(&self, obs: &Tensor, eps: &Tensor) -> Sample {
        let (mean, log_std) = self.mean_log_std(obs);
        tanh_gaussian(&mean, &log_std, eps)
    }

    /// yᵢ of eq. 9 for given standard-normal `eps` `[B, act_dim]` used to sample ãᵢ₊₁:
    /// Rᵢ + γ(1 − terminalᵢ)(min_k Q_tk(sᵢ₊₁, ãᵢ₊₁) − α ln π(ãᵢ₊₁|sᵢ₊₁)). `[B, 1]`.
    pub fn td_target(&self, b: &Minibatch, eps: &Tensor) -> Tensor {
        self.td_target_with_alpha(b, eps, self.alpha())
    }

    /// [`Sac::td_target`] for a given α (the update reads α once).
    fn td_target_with_alpha(&self, b: &Minibatch, eps: &Tensor, alpha: f64) -> Tensor {
        let _guard = tch::no_grad_guard();
        let next = self.sample_with(&b.next_obs, eps);
        let q_next = critics(self.target_critic.params(), &b.next_obs, &next.action, &self.c.cfg).amin(0, false);
        let soft_value = q_next - next.log_prob * alpha;
        let not_done = b.terminal.ones_like() - &b.terminal;
        cap_targets(&b.reward + not_done * soft_value * self.c.cfg.bootstrap_discount(), self.c.cfg.td_target_max)
    }

    /// The standard normals of one update, `2 · rows · act_dim` into `out`: ε for s′ (the
    /// targets, eq. 9), then ε for s (the actor, eq. 11), from the agent's noise stream. Both
    /// paths of [`Sac::update`] draw through here, so the fused update sees the same numbers.
    pub(crate) fn update_draws(&mut self, rows: usize, out: &mut Vec<f32>) {
        self.c.noise.fill(out, 2 * rows * self.c.act_dim);
    }

    /// One update along the paper's equations with libtorch's autograd (module docs). The
    /// fused CPU path ([`super::fused`]) takes the same steps.
    pub(crate) fn update(&mut self, b: &Minibatch) -> Result<UpdateStats, LearnerError> {
        let (rows, act, device) = (b.rows(), self.c.act_dim, self.c.device);
        let mut draws = Vec::new();
        self.update_draws(rows, &mut draws);
        let eps = |half: &[f32]| Tensor::from_slice(half).view([rows as i64, act as i64]).to_device(device);
        let (eps_next, eps_now) = (eps(&draws[..rows * act]), eps(&draws[rows * act..]));
        let alpha = self.alpha();

        let y = self.td_target_with_alpha(b, &eps_next, alpha);
        let CriticStep { loss, q_mean, target_mean, grad_norm, td_errors } = critic_step(&mut self.critic, b, &y, &self.c)?;

        // Eq. 11 with the updated critics, minimised in θ only: the critics run on their
        // frozen views, so the backward pass computes ∂Q/∂a but no critic weight gradient.
        let now = self.sample_with(&b.obs, &eps_now);
        let q = critics(self.critic.net.frozen(), &b.obs, &now.action, &self.c.cfg).amin(0, false);
        let actor_loss = (&now.log_prob * alpha - q).mean(None);
        let actor_loss_value = finite(&actor_loss, metric::ACTOR_LOSS, &self.c)?;
        let actor_norm = self.actor.step(&actor_loss, self.c.cfg.grad_clip_norm)?;

        // Eq. 10, gradient in log α written out (module docs), ln π held fixed.
        let mean_log_prob = now.log_prob.detach().mean(None).double_value(&[]);
        let alpha_loss = -alpha * (mean_log_prob + self.target_entropy);
        if self.c.cfg.sac.autotune_alpha {
            let grad = Tensor::from_slice(&[alpha_loss as f32]).to_device(device);
            self.log_alpha.opt.step(self.log_alpha.net.flat(), &grad);
        }

        self.target_critic.soft_update_from(&self.critic.net, self.c.cfg.tau);
        self.c.updates += 1;

        Ok(SacStep { critic_loss: loss, actor_loss: actor_loss_value, alpha_loss, q_mean, target_mean, alpha, mean_log_prob, critic_grad_norm: grad_norm, actor_grad_norm: actor_norm, td_errors }
            .into_stats())
    }

    pub(crate) fn act(&mut self, obs: &Tensor, explore: bool) -> Result<Tensor, LearnerError> {
        let (mean, log_std) = self.mean_log_std(obs);
        if !explore {
            return Ok(mean.tanh());
        }
        let eps = {
            let e = &mut self.c.explore.rng;
            let n = mean.numel();
            let v: Vec<f32> = (0..n).map(|_| rand_distr::Distribution::<f32>::sample(&rand_distr::StandardNormal, e)).collect();
            Tensor::from_slice(&v).view(mean.size().as_slice()).to_device(self.c.device)
        };
        Ok((mean + log_std.exp() * eps).tanh())
    }

    pub(crate) fn actor_params(&self) -> &ParamSet {
        &self.actor.net
    }

    pub(crate) fn nets(&self) -> Vec<&ParamSet> {
        let mut nets = vec![&self.actor.net, &self.critic.net, &self.target_critic, &self.log_alpha.net];
        nets.extend(self.c.policy_average.as_ref());
        nets
    }

    pub(crate) fn nets_mut(&mut self) -> Vec<&mut ParamSet> {
        let mut nets = vec![&mut self.actor.net, &mut self.critic.net, &mut self.target_critic, &mut self.log_alpha.net];
        nets.extend(self.c.policy_average.as_mut());
        nets
    }

    pub(crate) fn opts(&self) -> Vec<(&'static str, &Adam)> {
        vec![("actor", &self.actor.opt), ("critic", &self.critic.opt), ("alpha", &self.log_alpha.opt)]
    }

    pub(crate) fn opts_mut(&mut self) -> Vec<(&'static str, &mut Adam)> {
        vec![("actor", &mut self.actor.opt), ("critic", &mut self.critic.opt), ("alpha", &mut self.log_alpha.opt)]
    }
}

/// a = tanh(μ + σε) and ln π(a|s) with the tanh correction (module docs), for `mean`,
/// clamped `log_std` and `eps`, each `[B, act_dim]`. `log_prob` is `[B, 1]`.
pub fn tanh_gaussian(mean: &Tensor, log_std: &Tensor, eps: &Tensor) -> Sample {
    let u = mean + log_std.exp() * eps;
    let action = u.tanh();
    // Σⱼ −½εⱼ² − ln σⱼ − ½ln 2π − 2(ln 2 − uⱼ − softplus(−2uⱼ))
    let gaussian = eps.square() * -0.5 - log_std - HALF_LN_2PI;
    let log_det = ((-&u * 2.0).softplus() + &u - std::f64::consts::LN_2) * 2.0; // = −ln(1 − tanh²u)
    let log_prob = (gaussian + log_det).sum_dim_intlist(1, true, None);
    Sample { action, log_prob }
}
