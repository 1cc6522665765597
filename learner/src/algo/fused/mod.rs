//! The hand-written CPU updates ([`LearnerConfig::fused_update`]): the same steps as the
//! libtorch path of [`super::ddpg`], [`super::td3`] and [`super::sac`], with the backward
//! passes written out over [`crate::cpu`]'s kernels. Read the paper's equations in those files;
//! this module only makes them fast.
//!
//! | file | what |
//! |---|---|
//! | `mod.rs` (here) | the shared pieces: critic stacks on `[s | a]`, the critic step of eqs. 1 / 6, ∂(min_k Q_k)/∂a, the actor's backward pass and step |
//! | [`ddpg`], [`td3`], [`sac`] | each algorithm's update, step for step beside its libtorch path |
//!
//! [`super::Agent::update`] is the one place that chooses between the two paths. Host memory
//! is reached only through its owners' safe accessors ([`crate::nets::ParamSet::host`],
//! [`crate::nets::ParamSet::host_mut`], [`crate::batch::Minibatch::host`]), so the borrow
//! checker keeps each network's writes away from its live slices. `tests/algo_targets.rs`
//! holds each algorithm's fused update to its libtorch update.
//!
//! [`LearnerConfig::fused_update`]: crate::config::LearnerConfig::fused_update

mod ddpg;
mod sac;
mod td3;

pub(super) use sac::Head;

use super::{CriticStep, Trained, metric};
use crate::LearnerError;
use crate::batch::HostBatch as Batch;
use crate::cpu::{Acts, Body, Scratch, clip_grad_norm};
use crate::lanes::Lanes;
use crate::nets::ParamSet;

/// [`ParamSet::soft_update_from`] on the host buffers ([`crate::cpu::soft_update`]): one loop,
/// no libtorch call.
pub(super) fn soft_update(target: &mut ParamSet, source: &ParamSet, tau: f64, lanes: &Lanes) {
    let t = target.host_mut().expect("host parameters");
    let s = source.host().expect("host parameters");
    crate::cpu::soft_update(t, s, tau, lanes);
}

/// Reused buffers of a fused update.
#[derive(Debug, Default)]
pub(crate) struct Work {
    /// Critic input `[B, obs + act]` of the last [`Work::critics_forward`].
    pub x: Vec<f32>,
    pub actor: Acts,
    /// The actor's activations on s′ (SAC, computed beside those on s).
    pub actor_next: Acts,
    pub critics: Vec<Acts>,
    pub scratch: Scratch,
    /// Per critic, ∂L/∂Q `[B]`.
    pub dq: Vec<Vec<f32>>,
    /// ∂L/∂a summed over the critics `[B, act]`.
    pub da: Vec<f32>,
    /// ∂L/∂(actor output).
    pub dy: Vec<f32>,
    pub critic_grad: Vec<f32>,
    pub actor_grad: Vec<f32>,
    /// TD targets `[B]`.
    pub y: Vec<f32>,
    /// An action `[B, act]` (the deterministic actors' tanh output).
    pub a: Vec<f32>,
    /// Per critic, its backward pass through the rows where it is the minimum
    /// ([`Work::min_q_action_grad`]).
    min_rows: Vec<MinRows>,
    /// Standard-normal draws of this update.
    pub noise: Vec<f32>,
    /// One lane, or two when libtorch has ≥ 2 intra-op threads ([`Work::begin`]).
    pub lanes: Lanes,
}

/// One critic's share of ∂(min_k Q_k)/∂a: the rows where it is the minimum, their activations
/// and ∂L/∂Q, and ∂L/∂a of those rows (the action columns of ∂L/∂[s | a]).
#[derive(Debug, Default)]
struct MinRows {
    sel: Vec<usize>,
    sub: Acts,
    dq: Vec<f32>,
    dx: Vec<f32>,
    scratch: Scratch,
}

impl MinRows {
    /// Backs critic `body` (parameters `p`, activations `full`, ∂L/∂Q `dq` over all rows) up
    /// through the rows with a non-zero ∂L/∂Q only: the same sum, since every other row
    /// carries zero gradient, for about half the rows with two critics. Only the action
    /// columns (from `obs`) are formed; no weight gradient, so no input rows are needed.
    fn backward(&mut self, body: &Body, p: &[f32], full: &Acts, dq: &[f32], obs: usize, act: usize) {
        let rows = full.rows;
        let hidden = body.hidden();
        self.sel.clear();
        self.sel.extend((0..rows).filter(|&i| dq[i] != 0.0));
        let n = self.sel.len();
        self.dx.resize(n * act, 0.0);
        if n == rows {
            body.backward(p, &[], full, dq, None, Some((&mut self.dx, obs)), &mut self.scratch, &Lanes::ONE);
        } else {
            self.sub.rows = n;
            for (buf, src) in [(&mut self.sub.h1, &full.h1), (&mut self.sub.h2, &full.h2), (&mut self.sub.n1, &full.n1), (&mut self.sub.n2, &full.n2)] {
                buf.clear();
                if !src.is_empty() {
                    for &i in &self.sel {
                        buf.extend_from_slice(&src[i * hidden..(i + 1) * hidden]);
                    }
                }
            }
            for (buf, src) in [(&mut self.sub.r1, &full.r1), (&mut self.sub.r2, &full.r2)] {
                buf.clear();
                if !src.is_empty() {
                    buf.extend(self.sel.iter().map(|&i| src[i]));
                }
            }
            self.dq.clear();
            self.dq.extend(self.sel.iter().map(|&i| dq[i]));
            body.backward(p, &[], &self.sub, &self.dq, None, Some((&mut self.dx, obs)), &mut self.scratch, &Lanes::ONE);
        }
    }
}

/// The `k` critics of a [`crate::nets::stacked_mlp_specs`] stack on `obs + act` inputs,
/// layer-normalised when `norm` (`LearnerConfig::critic_layer_norm`).
fn critic_bodies(k: usize, obs: usize, act: usize, hidden: usize, norm: bool) -> Vec<Body> {
    (0..k).map(|j| Body::stacked(j, k, obs + act, hidden, 1).normed(norm)).collect()
}

impl Work {
    /// Call at the start of every fused update: sets the lanes up the first time and, with
    /// two, makes this thread's BLAS single-threaded until the guard drops (each lane is one
    /// thread; the products of one update are too small to split well).
    pub fn begin(&mut self) -> crate::lanes::BlasGuard {
        self.lanes.configure();
        self.lanes.single_threaded_blas()
    }

    /// Every critic of `bodies` (parameters `p`) on `x = [s | a]`; outputs in
    /// `self.critics[j].y`.
    pub fn critics_forward(&mut self, bodies: &[Body], p: &[f32], s: &[f32], a: &[f32], act: usize, rows: usize) {
        let obs = s.len() / rows.max(1);
        let width = obs + act;
        self.x.resize(rows * width, 0.0);
        for (r, out) in self.x.chunks_exact_mut(width).enumerate() {
            out[..obs].copy_from_slice(&s[r * obs..(r + 1) * obs]);
            out[obs..].copy_from_slice(&a[r * act..(r + 1) * act]);
        }
        self.critics.resize_with(bodies.len(), Acts::default);
        let x = &self.x;
        match (bodies, &mut self.critics[..]) {
            ([b0, b1], [c0, c1]) => {
                self.lanes.join(|| b0.forward(p, x, rows, c0), || b1.forward(p, x, rows, c1));
            }
            _ => {
                for (body, acts) in bodies.iter().zip(self.critics.iter_mut()) {
                    body.forward(p, x, rows, acts);
                }
            }
        }
    }

    /// min_k Q_k for row `i` of the last [`Work::critics_forward`]; NaN if any is NaN, as
    /// libtorch's `amin` (so a diverged critic fails the finite-loss check at once).
    pub fn min_q(&self, i: usize) -> f32 {
        self.critics.iter().map(|c| c.y[i]).fold(f32::INFINITY, |m, v| if m.is_nan() || v.is_nan() { f32::NAN } else { m.min(v) })
    }

    /// y = r + γ(1 − terminal)·v, v per row from `value(row)` (eqs. 2, 7, 9), clipped to at
    /// most `max` (`LearnerConfig::td_target_max`) when set. A NaN stays NaN, as with
    /// libtorch's `clamp_max`, so a diverged critic still fails the finite-loss check.
    pub fn targets(&mut self, b: &Batch<'_>, gamma: f64, max: Option<f64>, value: impl Fn(&Self, usize) -> f32) {
        let gamma = gamma as f32;
        let max = max.map_or(f32::INFINITY, |m| m as f32);
        let mut y = std::mem::take(&mut self.y); // reused: `value` reads the rest of `self`
        y.clear();
        y.extend((0..b.rows).map(|i| {
            let t = b.reward[i] + (1.0 - b.terminal[i]) * value(self, i) * gamma;
            if t > max { max } else { t }
        }));
        self.y = y;
    }

    /// Eqs. 1 / 6 with importance weights: L = Σ_k (1/M) Σᵢ wᵢ (yᵢ − Q_k(sᵢ, aᵢ))², then one
    /// clipped Adam step of the critics. `self.y` holds the targets. Fails, before stepping,
    /// on a non-finite loss.
    pub fn critic_step(&mut self, bodies: &[Body], critic: &mut Trained, b: &Batch<'_>, act: usize, clip: Option<f64>, update: u64) -> Result<CriticStep, LearnerError> {
        let rows = b.rows;
        let k = bodies.len();
        let Trained { net, opt, .. } = critic;
        let p = net.host_mut().expect("host parameters");
        self.critics_forward(bodies, p, b.obs, b.action, act, rows);
        self.dq.resize_with(k, Vec::new);
        let (mut loss, mut q_sum) = (0.0f64, 0.0f64);
        let mut td_errors = vec![0.0f32; rows];
        let scale = 2.0 / rows as f32;
        for j in 0..k {
            self.dq[j].resize(rows, 0.0);
            for i in 0..rows {
                let q = self.critics[j].y[i];
                let td = q - self.y[i];
                loss += f64::from(td * td * b.weights[i]);
                q_sum += f64::from(q);
                self.dq[j][i] = scale * b.weights[i] * td;
                td_errors[i] += td.abs() / k as f32;
            }
        }
        let loss = loss / rows as f64;
        if !loss.is_finite() {
            return Err(LearnerError::NonFiniteLoss { what: metric::CRITIC_LOSS, value: loss, update });
        }
        self.critic_grad.clear();
        self.critic_grad.resize(p.len(), 0.0);
        for (j, body) in bodies.iter().enumerate() {
            body.backward(p, &self.x, &self.critics[j], &self.dq[j], Some(&mut self.critic_grad), None, &mut self.scratch, &self.lanes);
        }
        let grad_norm = clip.map(|c| clip_grad_norm(&mut self.critic_grad, c, &self.lanes));
        opt.step_host(p, &self.critic_grad, &self.lanes);
        Ok(CriticStep { loss, q_mean: q_sum / (k * rows) as f64, target_mean: self.y.iter().map(|&v| f64::from(v)).sum::<f64>() / rows as f64, grad_norm, td_errors })
    }

    /// For the critics' last forward on `[s | a]` (parameters `p`), ∂(−(1/M) Σᵢ min_k Q_k)/∂a
    /// into `self.da` — amin's backward: the whole gradient to the smaller critic, shared
    /// evenly on a tie. No critic weight gradient is computed. Returns (1/M) Σᵢ min_k Q_k.
    pub fn min_q_action_grad(&mut self, bodies: &[Body], p: &[f32], obs: usize, act: usize, rows: usize) -> f64 {
        let k = bodies.len();
        let g = -1.0 / rows as f32;
        self.dq.resize_with(k, Vec::new);
        let mut sum = 0.0f64;
        for i in 0..rows {
            let q = self.min_q(i);
            sum += f64::from(q);
            let ties = self.critics.iter().filter(|c| c.y[i] == q).count() as f32;
            for j in 0..k {
                self.dq[j].resize(rows, 0.0);
                self.dq[j][i] = if self.critics[j].y[i] == q { g / ties } else { 0.0 };
            }
        }
        self.da.clear();
        self.da.resize(rows * act, 0.0);
        self.min_rows.resize_with(k, MinRows::default);
        let (critics, dq) = (&self.critics, &self.dq);
        match (bodies, &mut self.min_rows[..]) {
            ([b0, b1], [m0, m1]) => {
                self.lanes.join(|| m0.backward(b0, p, &critics[0], &dq[0], obs, act), || m1.backward(b1, p, &critics[1], &dq[1], obs, act));
            }
            _ => {
                for (j, (body, m)) in bodies.iter().zip(self.min_rows.iter_mut()).enumerate() {
                    m.backward(body, p, &critics[j], &dq[j], obs, act);
                }
            }
        }
        // Summed in critic order, as one lane would.
        for m in &self.min_rows {
            for (r, &i) in m.sel.iter().enumerate() {
                for c in 0..act {
                    self.da[i * act + c] += m.dx[r * act + c];
                }
            }
        }
        sum / rows as f64
    }

    /// Backward through the actor's last forward on `obs` from `self.dy`, then one clipped
    /// Adam step. Returns the norm before clipping when clipping is on.
    pub fn actor_step(&mut self, body: &Body, actor: &mut Trained, obs: &[f32], clip: Option<f64>) -> Option<f64> {
        let Trained { net, opt, .. } = actor;
        let p = net.host_mut().expect("host parameters");
        self.actor_grad.clear();
        self.actor_grad.resize(p.len(), 0.0);
        body.backward(p, obs, &self.actor, &self.dy, Some(&mut self.actor_grad), None, &mut self.scratch, &self.lanes);
        let norm = clip.map(|c| clip_grad_norm(&mut self.actor_grad, c, &self.lanes));
        opt.step_host(p, &self.actor_grad, &self.lanes);
        norm
    }

    /// The deterministic actors' (DDPG, TD3) action a = tanh(π(s)) into `self.a`, actor
    /// parameters `actor_p`; the activations stay in `self.actor` for a backward pass.
    pub fn tanh_action(&mut self, body: &Body, actor_p: &[f32], s: &[f32], rows: usize) {
        body.forward(actor_p, s, rows, &mut self.actor);
        self.a.clear();
        self.a.extend(self.actor.y.iter().map(|v| v.tanh()));
    }

    /// [`Work::critics_forward`] at the action of the last [`Work::tanh_action`].
    pub fn critics_forward_at_action(&mut self, bodies: &[Body], p: &[f32], s: &[f32], act: usize, rows: usize) {
        let a = std::mem::take(&mut self.a);
        self.critics_forward(bodies, p, s, &a, act, rows);
        self.a = a;
    }

    /// The deterministic actors' step, eqs. 3–5 (DDPG) and 8 (TD3): descend
    /// J = −mean min_k Q_k(s, tanh π(s)) in θ against the critics `bodies` (parameters of
    /// `critic`), tanh's backward ·(1 − a²) between. Fails, before stepping, on a non-finite
    /// J. Returns (J, the gradient norm before clipping when clipping is on).
    #[allow(clippy::too_many_arguments)]
    pub fn deterministic_actor_step(
        &mut self,
        body: &Body,
        bodies: &[Body],
        actor: &mut Trained,
        critic: &ParamSet,
        b: &Batch<'_>,
        obs: usize,
        act: usize,
        clip: Option<f64>,
        update: u64,
    ) -> Result<(f64, Option<f64>), LearnerError> {
        let rows = b.rows;
        // The actor's and the critic's buffers are only read until `actor_step` writes the
        // actor's (the borrow checker ends these slices first).
        let actor_p = actor.net.host().expect("host parameters");
        self.tanh_action(body, actor_p, b.obs, rows);
        let cp = critic.host().expect("host parameters");
        self.critics_forward_at_action(bodies, cp, b.obs, act, rows);
        let loss = -self.min_q_action_grad(bodies, cp, obs, act, rows);
        if !loss.is_finite() {
            return Err(LearnerError::NonFiniteLoss { what: metric::ACTOR_LOSS, value: loss, update });
        }
        self.dy.clear();
        self.dy.extend(self.da.iter().zip(&self.a).map(|(d, a)| d * (1.0 - a * a)));
        let norm = self.actor_step(body, actor, b.obs, clip);
        Ok((loss, norm))
    }
}
