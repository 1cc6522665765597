//! SAC's update ([`super::super::sac`], eqs. 6, 9–11) through the hand-written passes: the
//! same steps 1–4 in the same order, Adam and clipping; results equal up to float rounding.
//! The standard normals ε (for s′, then for s) come from [`Sac::update_draws`], the one place
//! both paths draw them, so both see the same numbers.

use super::{Batch, critic_bodies, soft_update};
use crate::LearnerError;
use crate::algo::sac::{CRITICS, HALF_LN_2PI, SacStep};
use crate::algo::{Sac, Trained, UpdateStats, metric};
use crate::cpu::Body;
use crate::lanes::Lanes;

/// The tanh-Gaussian head on host memory: for actor outputs `[B, 2·act]` = [μ | raw log σ].
#[derive(Debug, Default)]
pub(in crate::algo) struct Head {
    /// u = μ + σε.
    u: Vec<f32>,
    /// a = tanh(u).
    a: Vec<f32>,
    /// Clamped log σ.
    log_std: Vec<f32>,
    /// Whether raw log σ was inside the clamp (its gradient passes).
    inside: Vec<bool>,
    /// ln π(a|s) `[B]`.
    log_prob: Vec<f32>,
}

impl Head {
    /// [`tanh_gaussian`](crate::algo::sac::tanh_gaussian) on host memory, the same operations in the same order.
    fn sample(&mut self, y: &[f32], eps: &[f32], rows: usize, act: usize, lo: f64, hi: f64) {
        let n = rows * act;
        for v in [&mut self.u, &mut self.a, &mut self.log_std] {
            v.resize(n, 0.0);
        }
        self.inside.resize(n, false);
        self.log_prob.resize(rows, 0.0);
        let (lo32, hi32) = (lo as f32, hi as f32);
        for r in 0..rows {
            let mut lp = 0.0f32;
            for j in 0..act {
                let (i, mean, raw) = (r * act + j, y[r * 2 * act + j], y[r * 2 * act + act + j]);
                let ls = raw.clamp(lo32, hi32);
                self.inside[i] = raw >= lo32 && raw <= hi32; // clamp's backward, bounds in f32
                let u = mean + ls.exp() * eps[i];
                self.u[i] = u;
                self.a[i] = u.tanh();
                self.log_std[i] = ls;
                let gaussian = eps[i] * eps[i] * -0.5 - ls - HALF_LN_2PI as f32;
                let log_det = (softplus(-u * 2.0) + u - std::f32::consts::LN_2) * 2.0;
                lp += gaussian + log_det;
            }
            self.log_prob[r] = lp;
        }
    }
}

/// libtorch's softplus (β 1, threshold 20).
fn softplus(x: f32) -> f32 {
    if x > 20.0 { x } else { x.exp().ln_1p() }
}

/// Its derivative as libtorch's backward computes it.
fn softplus_grad(x: f32) -> f32 {
    if x > 20.0 {
        1.0
    } else {
        let z = x.exp();
        z / (z + 1.0)
    }
}

impl Sac {
    pub(in crate::algo) fn update_fused(&mut self, b: &Batch<'_>) -> Result<UpdateStats, LearnerError> {
        let (rows, o, na, h) = (b.rows, self.c.obs_dim, self.c.act_dim, self.c.hidden() as usize);
        let mut eps = std::mem::take(&mut self.host.0.noise);
        self.update_draws(rows, &mut eps);
        let (eps_next, eps_now) = eps.split_at(rows * na);
        let alpha = self.alpha();
        let alpha32 = alpha as f32;
        let (lo, hi) = (self.c.cfg.sac.log_std_min, self.c.cfg.sac.log_std_max);
        let clip = self.c.cfg.grad_clip_norm;
        let actor_body = Body::single(o, h, 2 * na);
        let bodies = critic_bodies(CRITICS as usize, o, na, h, self.c.cfg.critic_layer_norm);
        let (w, head) = (&mut self.host.0, &mut self.host.1);
        let _blas = w.begin();

        // The actor on s′ (for the targets) beside the actor on s (for eq. 11; the critic step
        // in between leaves the actor as it is).
        let ap = self.actor.net.host().expect("host parameters");
        let (on_next, on_now) = (&mut w.actor_next, &mut w.actor);
        w.lanes.join(|| actor_body.forward(ap, b.next_obs, rows, on_next), || actor_body.forward(ap, b.obs, rows, on_now));

        // 1. Targets, eq. 9: y = r + γ(1 − terminal)(min_k Q_tk(s′, ã′) − α ln π(ã′|s′)).
        head.sample(&w.actor_next.y, eps_next, rows, na, lo, hi);
        let tp = self.target_critic.host().expect("host parameters");
        w.critics_forward(&bodies, tp, b.next_obs, &head.a, na, rows);
        w.targets(b, self.c.cfg.bootstrap_discount(), self.c.cfg.td_target_max, |w, i| w.min_q(i) - head.log_prob[i] * alpha32);

        // 2. Critics, eq. 6.
        let critic = w.critic_step(&bodies, &mut self.critic, b, na, clip, self.c.updates)?;

        // 3. Actor, eq. 11, against the critics just updated: J = mean(α ln π − min_k Q_k).
        head.sample(&w.actor.y, eps_now, rows, na, lo, hi);
        let cp = self.critic.net.host().expect("host parameters");
        w.critics_forward(&bodies, cp, b.obs, &head.a, na, rows);
        let mut actor_loss = 0.0f64;
        for i in 0..rows {
            actor_loss += f64::from(head.log_prob[i] * alpha32 - w.min_q(i));
        }
        let actor_loss = actor_loss / rows as f64;
        if !actor_loss.is_finite() {
            return Err(LearnerError::NonFiniteLoss { what: metric::ACTOR_LOSS, value: actor_loss, update: self.c.updates });
        }
        w.min_q_action_grad(&bodies, cp, o, na, rows);
        // Through the head: a = tanh(u), u = μ + σε,
        // ln π = Σ −½ε² − ln σ − ½ln 2π + 2(softplus(−2u) + u − ln 2).
        let dlogp = alpha32 / rows as f32;
        w.dy.resize(rows * 2 * na, 0.0);
        for i in 0..rows {
            for c in 0..na {
                let n = i * na + c;
                let (u, a) = (head.u[n], head.a[n]);
                let dlogdet_du = 2.0 * (1.0 - 2.0 * softplus_grad(-u * 2.0));
                let du = w.da[n] * (1.0 - a * a) + dlogp * dlogdet_du;
                let dls = du * eps_now[n] * head.log_std[n].exp() - dlogp;
                w.dy[i * 2 * na + c] = du;
                w.dy[i * 2 * na + na + c] = if head.inside[n] { dls } else { 0.0 };
            }
        }
        let actor_norm = w.actor_step(&actor_body, &mut self.actor, b.obs, clip);

        // 4. α, eq. 10, and the targets: as the libtorch path.
        let mean_log_prob = head.log_prob.iter().map(|&v| f64::from(v)).sum::<f64>() / rows as f64;
        let alpha_loss = -alpha * (mean_log_prob + self.target_entropy);
        if self.c.cfg.sac.autotune_alpha {
            let Trained { net, opt, .. } = &mut self.log_alpha;
            opt.step_host(net.host_mut().expect("host parameters"), &[alpha_loss as f32], &Lanes::ONE);
        }
        soft_update(&mut self.target_critic, &self.critic.net, self.c.cfg.tau, &w.lanes);
        self.c.updates += 1;

        self.host.0.noise = eps;
        Ok(SacStep {
            critic_loss: critic.loss,
            actor_loss,
            alpha_loss,
            q_mean: critic.q_mean,
            target_mean: critic.target_mean,
            alpha,
            mean_log_prob,
            critic_grad_norm: critic.grad_norm,
            actor_grad_norm: actor_norm,
            td_errors: critic.td_errors,
        }
        .into_stats())
    }
}
