//! Pendulum-v1, exactly as gymnasium's `classic_control/pendulum.py` (with its `TimeLimit`
//! of 200 steps), seeded and serialisable.
//!
//! ```text
//!   state (θ, θ̇), θ = 0 upright;  u = clip(u, −2, 2)
//!   cost  = angle_normalize(θ)² + 0.1·θ̇² + 0.001·u²,   reward = −cost   (of the state *before*)
//!   θ̇′   = clip(θ̇ + (3g/(2l)·sin θ + 3/(m l²)·u)·dt, −8, 8)
//!   θ′    = θ + θ̇′·dt                      g = 10, m = 1, l = 1, dt = 0.05
//!   obs   = [cos θ, sin θ, θ̇] (f32);  reset: θ ~ U[−π, π], θ̇ ~ U[−1, 1]
//! ```
//!
//! The episode never terminates; after 200 steps it is *truncated* (the time limit), which
//! must not cut bootstrapping. Arithmetic is f64, as numpy's.

use rand::{Rng, SeedableRng};
use rand_pcg::Pcg64;
use serde::{Deserialize, Serialize};

/// Gravity, m/s².
pub const G: f64 = 10.0;
/// Mass, kg.
pub const M: f64 = 1.0;
/// Length, m.
pub const L: f64 = 1.0;
/// Step, s.
pub const DT: f64 = 0.05;
/// |θ̇| limit, rad/s.
pub const MAX_SPEED: f64 = 8.0;
/// |u| limit, N·m.
pub const MAX_TORQUE: f64 = 2.0;
/// Steps before truncation (gymnasium's registration of Pendulum-v1).
pub const MAX_EPISODE_STEPS: u32 = 200;
/// Observation width.
pub const OBS_DIM: usize = 3;
/// Action width.
pub const ACT_DIM: usize = 1;

/// What one step returns.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct PendulumStep {
    /// Observation after the step.
    pub obs: [f32; OBS_DIM],
    /// −cost.
    pub reward: f32,
    /// Always false: the pendulum never ends an episode by itself.
    pub terminal: bool,
    /// The 200-step time limit was reached.
    pub truncated: bool,
}

/// The environment; `Serialize` captures everything, RNG included, for exact resumes.
#[derive(Debug, Clone, Serialize, Deserialize, PartialEq)]
pub struct Pendulum {
    theta: f64,
    theta_dot: f64,
    steps: u32,
    rng: Pcg64,
}

/// θ wrapped into [−π, π), as Python's `((x + π) % (2π)) − π`.
pub fn angle_normalize(x: f64) -> f64 {
    use std::f64::consts::PI;
    (x + PI).rem_euclid(2.0 * PI) - PI
}

impl Pendulum {
    /// A pendulum whose resets draw from `seed`; call [`Pendulum::reset`] first.
    pub fn new(seed: u64) -> Self {
        Self { theta: 0.0, theta_dot: 0.0, steps: 0, rng: Pcg64::seed_from_u64(seed) }
    }

    /// Starts an episode: θ ~ U[−π, π), θ̇ ~ U[−1, 1) (numpy's half-open uniform).
    pub fn reset(&mut self) -> [f32; OBS_DIM] {
        use std::f64::consts::PI;
        self.theta = self.rng.random_range(-PI..PI);
        self.theta_dot = self.rng.random_range(-1.0..1.0);
        self.steps = 0;
        self.obs()
    }

    /// Sets the state directly (tests).
    pub fn set_state(&mut self, theta: f64, theta_dot: f64) {
        self.theta = theta;
        self.theta_dot = theta_dot;
    }

    /// (θ, θ̇).
    pub fn state(&self) -> (f64, f64) {
        (self.theta, self.theta_dot)
    }

    /// Steps taken in this episode.
    pub fn steps(&self) -> u32 {
        self.steps
    }

    /// [cos θ, sin θ, θ̇].
    pub fn obs(&self) -> [f32; OBS_DIM] {
        [self.theta.cos() as f32, self.theta.sin() as f32, self.theta_dot as f32]
    }

    /// One step with torque `u` in N·m (clipped to ±2). A non-finite torque counts as 0.
    pub fn step(&mut self, u: f64) -> PendulumStep {
        let u = if u.is_finite() { u.clamp(-MAX_TORQUE, MAX_TORQUE) } else { 0.0 };
        let (th, thdot) = (self.theta, self.theta_dot);
        let cost = angle_normalize(th).powi(2) + 0.1 * thdot * thdot + 0.001 * u * u;
        let new_thdot = (thdot + (3.0 * G / (2.0 * L) * th.sin() + 3.0 / (M * L * L) * u) * DT).clamp(-MAX_SPEED, MAX_SPEED);
        self.theta = th + new_thdot * DT;
        self.theta_dot = new_thdot;
        self.steps += 1;
        PendulumStep { obs: self.obs(), reward: -cost as f32, terminal: false, truncated: self.steps >= MAX_EPISODE_STEPS }
    }

    /// One step with a normalised action a ∈ [−1, 1] (torque = 2a), as the agents emit.
    pub fn step_normalized(&mut self, a: f32) -> PendulumStep {
        self.step(f64::from(a) * MAX_TORQUE)
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use std::f64::consts::PI;

    #[test]
    fn one_step_matches_gymnasium_by_hand() {
        let mut p = Pendulum::new(0);
        p.set_state(1.0, 0.5);
        let s = p.step(3.0); // clipped to 2
        let cost = 1.0 + 0.1 * 0.25 + 0.001 * 4.0;
        assert!((f64::from(s.reward) + cost).abs() < 1e-6);
        let thdot = 0.5 + (15.0 * 1.0f64.sin() + 3.0 * 2.0) * 0.05;
        let th = 1.0 + thdot * 0.05;
        let (t, td) = p.state();
        assert!((t - th).abs() < 1e-12 && (td - thdot).abs() < 1e-12);
        assert_eq!(s.obs, [th.cos() as f32, th.sin() as f32, thdot as f32]);
        assert!(!s.terminal && !s.truncated);
    }

    #[test]
    fn speed_is_clipped_and_angles_normalised_like_python() {
        let mut p = Pendulum::new(0);
        p.set_state(PI / 2.0, 7.9);
        p.step(2.0);
        assert_eq!(p.state().1, 8.0);
        assert!((angle_normalize(3.0 * PI / 2.0) + PI / 2.0).abs() < 1e-12);
        assert!((angle_normalize(-3.0 * PI / 2.0) - PI / 2.0).abs() < 1e-12);
        assert_eq!(angle_normalize(PI), -PI);
    }

    #[test]
    fn time_limit_truncates_at_200_and_resets_are_seeded_and_in_range() {
        let mut p = Pendulum::new(7);
        let o1 = p.reset();
        let (th, thd) = p.state();
        assert!((-PI..=PI).contains(&th) && (-1.0..=1.0).contains(&thd));
        for i in 1..=200 {
            let s = p.step_normalized(0.0);
            assert_eq!(s.truncated, i == 200);
            assert!(!s.terminal);
        }
        let mut q = Pendulum::new(7);
        assert_eq!(q.reset(), o1);
        let copy: Pendulum = serde_json::from_str(&serde_json::to_string(&p).unwrap()).unwrap();
        assert_eq!(copy, p);
    }
}
