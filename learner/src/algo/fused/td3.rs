//! TD3's update ([`super::super::td3`], eqs. 6–8) through the hand-written passes: the same
//! steps, delay schedule, Adam and clipping; results equal up to float rounding. The smoothing
//! noise ε of eq. 7 comes from [`Td3::smoothing_draws`], the one place both paths draw it.

use super::{Batch, critic_bodies, soft_update};
use crate::LearnerError;
use crate::algo::td3::CRITICS;
use crate::algo::{Td3, UpdateStats, metric};
use crate::cpu::Body;

impl Td3 {
    pub(in crate::algo) fn update_fused(&mut self, b: &Batch<'_>) -> Result<UpdateStats, LearnerError> {
        let (rows, o, na, h) = (b.rows, self.c.obs_dim, self.c.act_dim, self.c.hidden() as usize);
        let (std, limit) = (self.c.cfg.td3.target_noise_std as f32, self.c.cfg.td3.target_noise_clip as f32);
        let clip = self.c.cfg.grad_clip_norm;
        let actor_body = Body::single(o, h, na);
        let bodies = critic_bodies(CRITICS as usize, o, na, h, self.c.cfg.critic_layer_norm);
        let mut z = std::mem::take(&mut self.host.noise);
        self.smoothing_draws(rows, &mut z);
        let w = &mut self.host;
        let _blas = w.begin();

        // Eq. 7: y = r + γ(1 − terminal) min_k Q_tk(s′, clip(tanh π_t(s′) + clip(ε), −1, 1)).
        actor_body.forward(self.target_actor.host().expect("host parameters"), b.next_obs, rows, &mut w.actor);
        let next: Vec<f32> = w.actor.y.iter().zip(&z).map(|(y, z)| (y.tanh() + (z * std).clamp(-limit, limit)).clamp(-1.0, 1.0)).collect();
        w.noise = z;
        w.critics_forward(&bodies, self.target_critic.host().expect("host parameters"), b.next_obs, &next, na, rows);
        w.targets(b, self.c.cfg.bootstrap_discount(), self.c.cfg.td_target_max, |w, i| w.min_q(i));
        let critic = w.critic_step(&bodies, &mut self.critic, b, na, clip, self.c.updates)?;
        self.c.updates += 1;
        let mut scalars = vec![(metric::CRITIC_LOSS, critic.loss), (metric::Q_MEAN, critic.q_mean), (metric::TARGET_MEAN, critic.target_mean)];
        scalars.extend(critic.grad_norm.map(|n| (metric::CRITIC_GRAD_NORM, n)));

        if self.c.updates.is_multiple_of(self.c.cfg.td3.policy_delay) {
            // Eqs. 3, 5, 8: descend −mean min_k Q_k(s, tanh π(s)) in θ.
            let (actor_loss, norm) = w.deterministic_actor_step(&actor_body, &bodies, &mut self.actor, &self.critic.net, b, o, na, clip, self.c.updates)?;
            let tau = self.c.cfg.tau;
            soft_update(&mut self.target_actor, &self.actor.net, tau, &w.lanes);
            soft_update(&mut self.target_critic, &self.critic.net, tau, &w.lanes);
            scalars.push((metric::ACTOR_LOSS, actor_loss));
            scalars.extend(norm.map(|n| (metric::ACTOR_GRAD_NORM, n)));
        }
        Ok(UpdateStats { scalars, td_errors: critic.td_errors })
    }
}
