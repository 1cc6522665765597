//! Deep Deterministic Policy Gradient (Lillicrap et al. 2016), as the paper writes it
//! (§II-A).
//!
//! Networks: actor π(s|θ) (a = tanh of its output), critic Q(s, a|φ), and target copies
//! π_t(θ_t), Q_t(φ_t) with the same structure.
//!
//! Every [`Ddpg::update`], on a minibatch of M transitions:
//!
//! 1. **Critic**, eqs. 1–2: minimise
//!    ```text
//!      L = (1/M) Σᵢ wᵢ (yᵢ − Q(sᵢ, aᵢ|φ))²
//!      yᵢ = Rᵢ + γ (1 − terminalᵢ) Q_t(sᵢ₊₁, π_t(sᵢ₊₁|θ_t)|φ_t)
//!    ```
//! 2. **Actor**, eqs. 3–5: the deterministic policy gradient
//!    ∇_θJ ≈ (1/M) Σᵢ G_aᵢ G_πᵢ with G_aᵢ = ∇_a Q(sᵢ, π(sᵢ|θ)|φ) and G_πᵢ = ∇_θ π(sᵢ|θ),
//!    which is exactly the gradient autograd computes for the loss −(1/M) Σᵢ Q(sᵢ, π(sᵢ|θ)|φ)
//!    taken with respect to θ only (the critic is not changed by this step). The ascent on J is
//!    a descent on that loss.
//! 3. **Targets**: θ_t ← (1−τ)θ_t + τθ, φ_t ← (1−τ)φ_t + τφ.
//!
//! Exploration (acting, not learning): Ornstein–Uhlenbeck noise, θ = 0.15, σ = 0.3 by default
//! ([`crate::config::DdpgConfig`]).
//!
//! Departures from the paper, all stated by it only implicitly:
//! - the terminal mask (1 − terminal) in y: eq. 2 omits it, but a collision ends the episode
//!   and nothing follows it; a *truncated* step (the time limit) still bootstraps;
//! - the importance weights wᵢ (1 for uniform replay) for prioritised replay;
//! - the critic step comes first, and the actor step then uses the updated critic (as in
//!   Lillicrap et al.'s algorithm box).

use tch::Tensor;

use super::fused;
use super::{Common, CriticStep, Trained, UpdateStats, cap_targets, critic_step, critics, deterministic_act, finite, metric};
use crate::LearnerError;
use crate::batch::Minibatch;
use crate::nets::{ParamSet, mlp_forward, mlp_specs, stacked_mlp_specs};
use crate::optim::Adam;

/// A DDPG agent. See the module docs for the update.
#[derive(Debug)]
pub struct Ddpg {
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

impl Ddpg {
    pub(crate) fn new(mut c: Common) -> Result<Self, LearnerError> {
        let (o, a, h) = (c.obs_dim as i64, c.act_dim as i64, c.hidden());
        let actor = ParamSet::new(mlp_specs("actor", o, h, a, &mut c.init_rng), c.device)?;
        let critic = ParamSet::new(stacked_mlp_specs("critic", 1, o + a, h, 1, &mut c.init_rng), c.device)?;
        let target_actor = actor.duplicate_as("actor", "target_actor");
        let target_critic = critic.duplicate_as("critic", "target_critic");
        Ok(Self { actor: Trained::new(actor, c.cfg.actor_lr, &c), critic: Trained::new(critic, c.cfg.critic_lr, &c), target_actor, target_critic, host: fused::Work::default(), c })
    }

    /// yᵢ = Rᵢ + γ (1 − terminalᵢ) Q_t(sᵢ₊₁, tanh π_t(sᵢ₊₁)) — eq. 2 with the terminal mask.
    /// `[B, 1]`, no gradient.
    pub fn td_target(&self, b: &Minibatch) -> Tensor {
        let _guard = tch::no_grad_guard();
        let next_action = mlp_forward(self.target_actor.params(), &b.next_obs).tanh();
        let q_next = critics(self.target_critic.params(), &b.next_obs, &next_action, &self.c.cfg).get(0);
        let not_done = b.terminal.ones_like() - &b.terminal;
        cap_targets(&b.reward + not_done * q_next * self.c.cfg.bootstrap_discount(), self.c.cfg.td_target_max)
    }

    /// One update along the paper's equations with libtorch's autograd (module docs). The
    /// fused CPU path ([`super::fused`]) takes the same steps.
    pub(crate) fn update(&mut self, b: &Minibatch) -> Result<UpdateStats, LearnerError> {
        let y = self.td_target(b);
        let CriticStep { loss, q_mean, target_mean, grad_norm, td_errors } = critic_step(&mut self.critic, b, &y, &self.c)?;

        // Eqs. 3–5: descend −mean Q(s, π(s)) in θ only (the critic through its frozen views:
        // ∂Q/∂a flows, no critic weight gradient is computed).
        let action = mlp_forward(self.actor.net.params(), &b.obs).tanh();
        let q = critics(self.critic.net.frozen(), &b.obs, &action, &self.c.cfg);
        let actor_loss = -q.mean(None);
        let actor_loss_value = finite(&actor_loss, metric::ACTOR_LOSS, &self.c)?;
        let actor_norm = self.actor.step(&actor_loss, self.c.cfg.grad_clip_norm)?;

        let tau = self.c.cfg.tau;
        self.target_actor.soft_update_from(&self.actor.net, tau);
        self.target_critic.soft_update_from(&self.critic.net, tau);
        self.c.updates += 1;

        let mut scalars = vec![(metric::CRITIC_LOSS, loss), (metric::ACTOR_LOSS, actor_loss_value), (metric::Q_MEAN, q_mean), (metric::TARGET_MEAN, target_mean)];
        scalars.extend(grad_norm.map(|n| (metric::CRITIC_GRAD_NORM, n)));
        scalars.extend(actor_norm.map(|n| (metric::ACTOR_GRAD_NORM, n)));
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
