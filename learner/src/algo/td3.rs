//! Twin-Delayed Deep Deterministic Policy Gradient (Fujimoto et al. 2018), as the paper writes
//! it (§II-B).
//!
//! Networks: actor π(s|θ) (a = tanh of its output), k = 2 critics Q_k(s, a|φ_k), and targets
//! π_t(θ_t), Q_tk(φ_tk). The two critics are evaluated as one stacked network
//! ([`crate::nets::stacked_mlp_forward`]); they share nothing but the input.
//!
//! Every [`Td3::update`], on a minibatch of M transitions:
//!
//! 1. **Critics**, eqs. 6–7, every update: minimise Σ_k L_k,
//!    ```text
//!      L_k = (1/M) Σᵢ wᵢ (yᵢ − Q_k(sᵢ, aᵢ|φ_k))²
//!      yᵢ  = Rᵢ + γ (1 − terminalᵢ) min_k Q_tk(sᵢ₊₁, clip(π_t(sᵢ₊₁|θ_t) + ε, −1, 1)|φ_tk)
//!      ε   = clip(N(0, σ²), −c, c)        (target-policy smoothing; σ = 0.45, c = 0.5)
//!    ```
//! 2. **Actor**, eqs. 3, 5, 8, only on every `policy_delay`-th update (2): descend
//!    −(1/M) Σᵢ min_k Q_k(sᵢ, π(sᵢ|θ)|φ_k) in θ only, i.e. G_aᵢ = ∇_a min_k Q_k (eq. 8).
//! 3. **Targets**, on the same delayed updates: θ_t ← (1−τ)θ_t + τθ, φ_tk ← (1−τ)φ_tk + τφ_k.
//!
//! With the update counter n counted from 1, the actor and targets move on n = 2, 4, 6, … .
//!
//! Departures, stated or differing:
//! - eq. 8 uses min_k Q_k for the actor's gradient, as the paper writes; Fujimoto et al.
//!   (and CleanRL, SB3) use Q₁ alone. We follow the paper.
//! - the terminal mask, importance weights and clip of the smoothed action to the action box
//!   as in [`super::ddpg`] (the paper's "clip" in eq. 7 bounds both the noise and the action).
//! - ε is drawn from the agent's own PCG64 stream, so it is reproducible and checkpointed.

use tch::Tensor;

use super::fused;
use super::{Common, CriticStep, Trained, UpdateStats, cap_targets, critic_step, critics, deterministic_act, finite, metric};
use crate::LearnerError;
use crate::batch::Minibatch;
use crate::nets::{ParamSet, mlp_forward, mlp_specs, stacked_mlp_specs};
use crate::optim::Adam;

/// Number of critics (paper: k = 2).
pub const CRITICS: i64 = 2;

/// A TD3 agent. See the module docs for the update.
#[derive(Debug)]
pub struct Td3 {
    pub(crate) c: Common,
    pub(super) actor: Trained,
    pub(super) critic: Trained,
    pub(super) target_actor: ParamSet,
    pub(super) target_critic: ParamSet,
    /// Buffers of the fused CPU update ([`LearnerConfig::fused_update`]).
    ///
    /// [`LearnerConfig::fused_update`]: crate::config::LearnerConfig::fused_update
    pub(super) host: fused::Work,
}

impl Td3 {
    pub(crate) fn new(mut c: Common) -> Result<Self, LearnerError> {
        let (o, a, h) = (c.obs_dim as i64, c.act_dim as i64, c.hidden());
        let actor = ParamSet::new(mlp_specs("actor", o, h, a, &mut c.init_rng), c.device)?;
        let critic = ParamSet::new(stacked_mlp_specs("critic", CRITICS, o + a, h, 1, &mut c.init_rng), c.device)?;
        let target_actor = actor.duplicate_as("actor", "target_actor");
        let target_critic = critic.duplicate_as("critic", "target_critic");
        Ok(Self { actor: Trained::new(actor, c.cfg.actor_lr, &c), critic: Trained::new(critic, c.cfg.critic_lr, &c), target_actor, target_critic, host: fused::Work::default(), c })
    }

    /// The standard normals behind ε of eq. 7 for `rows` transitions, `rows · act_dim` into
    /// `out`, from the agent's noise stream. Both paths of an update draw through here (the
    /// fused one in [`super::fused`]), so they see the same numbers.
    pub(crate) fn smoothing_draws(&mut self, rows: usize, out: &mut Vec<f32>) {
        self.c.noise.fill(out, rows * self.c.act_dim);
    }

    /// ε of eq. 7 for `rows` transitions: N(0, σ²) clipped to ±c, `[rows, act_dim]`
    /// ([`Td3::smoothing_draws`] scaled and clipped).
    pub fn smoothing_noise(&mut self, rows: usize) -> Tensor {
        let mut z = Vec::new();
        self.smoothing_draws(rows, &mut z);
        let z = Tensor::from_slice(&z).view([rows as i64, self.c.act_dim as i64]).to_device(self.c.device);
        let t = &self.c.cfg.td3;
        (z * t.target_noise_std).clamp(-t.target_noise_clip, t.target_noise_clip)
    }

    /// yᵢ of eq. 7 for given, already clipped smoothing noise `eps` `[B, act_dim]`:
    /// Rᵢ + γ(1 − terminalᵢ) min_k Q_tk(sᵢ₊₁, clip(tanh π_t(sᵢ₊₁) + εᵢ, −1, 1)). `[B, 1]`.
    pub fn td_target(&self, b: &Minibatch, eps: &Tensor) -> Tensor {
        let _guard = tch::no_grad_guard();
        let next_action = (mlp_forward(self.target_actor.params(), &b.next_obs).tanh() + eps).clamp(-1.0, 1.0);
        let q_next = critics(self.target_critic.params(), &b.next_obs, &next_action, &self.c.cfg).amin(0, false);
        let not_done = b.terminal.ones_like() - &b.terminal;
        cap_targets(&b.reward + not_done * q_next * self.c.cfg.bootstrap_discount(), self.c.cfg.td_target_max)
    }

    /// One update along the paper's equations with libtorch's autograd (module docs). The
    /// fused CPU path ([`super::fused`]) takes the same steps.
    pub(crate) fn update(&mut self, b: &Minibatch) -> Result<UpdateStats, LearnerError> {
        let eps = self.smoothing_noise(b.rows());
        let y = self.td_target(b, &eps);
        let CriticStep { loss, q_mean, target_mean, grad_norm, td_errors } = critic_step(&mut self.critic, b, &y, &self.c)?;
        self.c.updates += 1;
        let mut scalars = vec![(metric::CRITIC_LOSS, loss), (metric::Q_MEAN, q_mean), (metric::TARGET_MEAN, target_mean)];
        scalars.extend(grad_norm.map(|n| (metric::CRITIC_GRAD_NORM, n)));

        if self.c.updates.is_multiple_of(self.c.cfg.td3.policy_delay) {
            // Eqs. 3, 5, 8: descend −mean min_k Q_k(s, π(s)) in θ only (critics through their
            // frozen views: ∂Q/∂a flows, no critic weight gradient is computed).
            let action = mlp_forward(self.actor.net.params(), &b.obs).tanh();
            let q = critics(self.critic.net.frozen(), &b.obs, &action, &self.c.cfg).amin(0, false);
            let actor_loss = -q.mean(None);
            let value = finite(&actor_loss, metric::ACTOR_LOSS, &self.c)?;
            let norm = self.actor.step(&actor_loss, self.c.cfg.grad_clip_norm)?;
            let tau = self.c.cfg.tau;
            self.target_actor.soft_update_from(&self.actor.net, tau);
            self.target_critic.soft_update_from(&self.critic.net, tau);
            scalars.push((metric::ACTOR_LOSS, value));
            scalars.extend(norm.map(|n| (metric::ACTOR_GRAD_NORM, n)));
        }
        Ok(UpdateStats { scalars, td_errors })
    }

    pub(crate) fn act(&mut self, obs: &Tensor, explore: bool) -> Result<Tensor, LearnerError> {
        deterministic_act(&self.actor.net, obs, explore, &mut self.c)
    }

    pub(crate) fn actor_params(&self) -> &ParamSet {
        &self.actor.net
    }

    pub(crate) fn nets(&self) -> Vec<&ParamSet> {
        let mut nets = vec![&self.actor.net, &self.critic.net, &self.target_actor, &self.target_critic];
        nets.extend(self.c.policy_average.as_ref());
        nets
    }

    pub(crate) fn nets_mut(&mut self) -> Vec<&mut ParamSet> {
        let mut nets = vec![&mut self.actor.net, &mut self.critic.net, &mut self.target_actor, &mut self.target_critic];
        nets.extend(self.c.policy_average.as_mut());
        nets
    }

    pub(crate) fn opts(&self) -> Vec<(&'static str, &Adam)> {
        vec![("actor", &self.actor.opt), ("critic", &self.critic.opt)]
    }

    pub(crate) fn opts_mut(&mut self) -> Vec<(&'static str, &mut Adam)> {
        vec![("actor", &mut self.actor.opt), ("critic", &mut self.critic.opt)]
    }
}
