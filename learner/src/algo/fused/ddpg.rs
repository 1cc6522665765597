//! DDPG's update ([`super::super::ddpg`], eqs. 1–5) through the hand-written passes: the same
//! steps in the same order, Adam and clipping; results equal up to float rounding. DDPG draws
//! no noise in an update.

use super::{Batch, critic_bodies, soft_update};
use crate::LearnerError;
use crate::algo::{Ddpg, UpdateStats, metric};
use crate::cpu::Body;

impl Ddpg {
    pub(in crate::algo) fn update_fused(&mut self, b: &Batch<'_>) -> Result<UpdateStats, LearnerError> {
        let (rows, o, na, h) = (b.rows, self.c.obs_dim, self.c.act_dim, self.c.hidden() as usize);
        let clip = self.c.cfg.grad_clip_norm;
        let actor_body = Body::single(o, h, na);
        let bodies = critic_bodies(1, o, na, h, self.c.cfg.critic_layer_norm);
        let w = &mut self.host;
        let _blas = w.begin();

        // Eq. 2: y = r + γ(1 − terminal) Q_t(s′, tanh π_t(s′)).
        w.tanh_action(&actor_body, self.target_actor.host().expect("host parameters"), b.next_obs, rows);
        w.critics_forward_at_action(&bodies, self.target_critic.host().expect("host parameters"), b.next_obs, na, rows);
        w.targets(b, self.c.cfg.bootstrap_discount(), self.c.cfg.td_target_max, |w, i| w.min_q(i));
        let critic = w.critic_step(&bodies, &mut self.critic, b, na, clip, self.c.updates)?;

        // Eqs. 3–5: descend −mean Q(s, tanh π(s)) in θ.
        let (actor_loss, actor_norm) = w.deterministic_actor_step(&actor_body, &bodies, &mut self.actor, &self.critic.net, b, o, na, clip, self.c.updates)?;

        let tau = self.c.cfg.tau;
        soft_update(&mut self.target_actor, &self.actor.net, tau, &w.lanes);
        soft_update(&mut self.target_critic, &self.critic.net, tau, &w.lanes);
        self.c.updates += 1;
        let mut scalars = vec![(metric::CRITIC_LOSS, critic.loss), (metric::ACTOR_LOSS, actor_loss), (metric::Q_MEAN, critic.q_mean), (metric::TARGET_MEAN, critic.target_mean)];
        scalars.extend(critic.grad_norm.map(|n| (metric::CRITIC_GRAD_NORM, n)));
        scalars.extend(actor_norm.map(|n| (metric::ACTOR_GRAD_NORM, n)));
        Ok(UpdateStats { scalars, td_errors: critic.td_errors })
    }
}
