//! Gymnasium's Pendulum-v1, for checking the learning algorithms on a task with known results
//! (SAC/TD3 reach a mean return of about −150 to −200 within ~20k steps).
//!
//! Dynamics as gymnasium/envs/classic_control/pendulum.py (g = 10):
//!
//! ```text
//!   θ̇' = clip(θ̇ + (3g/(2l) sin θ + 3/(m l²) u) dt, ±8)     θ' = θ + θ̇' dt     dt = 0.05
//!   reward = −(norm(θ)² + 0.1 θ̇² + 0.001 u²)                  u = clip(2a, ±2)
//!   obs = [cos θ, sin θ, θ̇]      reset: θ ~ U(−π, π), θ̇ ~ U(−1, 1)      truncated at 200 steps
//! ```
//!
//! The action is normalised like the vehicle's: a ∈ [−1, 1] maps to torque u = 2a.

use rand::{Rng, SeedableRng};
use rand_pcg::Pcg64Mcg;

use crate::env::StepOutcome;

pub const MAX_SPEED: f64 = 8.0;
pub const MAX_TORQUE: f64 = 2.0;
pub const DT: f64 = 0.05;
pub const G: f64 = 10.0;
pub const MASS: f64 = 1.0;
pub const LENGTH: f64 = 1.0;
pub const MAX_STEPS: u32 = 200;
pub const OBS_DIM: usize = 3;

#[derive(Clone, Debug)]
pub struct Pendulum {
    pub theta: f64,
    pub theta_dot: f64,
    steps: u32,
    rng: Pcg64Mcg,
}

impl Pendulum {
    pub fn new(seed: u64) -> Self {
        Pendulum { theta: 0.0, theta_dot: 0.0, steps: 0, rng: Pcg64Mcg::seed_from_u64(seed) }
    }

    pub fn reset(&mut self) -> [f32; 3] {
        self.theta = self.rng.random_range(-std::f64::consts::PI..std::f64::consts::PI);
        self.theta_dot = self.rng.random_range(-1.0..1.0);
        self.steps = 0;
        self.obs()
    }

    pub fn obs(&self) -> [f32; 3] {
        [self.theta.cos() as f32, self.theta.sin() as f32, self.theta_dot as f32]
    }

    /// One step with normalised action a (torque 2a). Never terminal; truncated at 200 steps.
    pub fn step(&mut self, a: f32) -> ([f32; 3], StepOutcome) {
        let u = (MAX_TORQUE * a as f64).clamp(-MAX_TORQUE, MAX_TORQUE);
        let th = self.theta;
        let cost = angle_normalize(th).powi(2) + 0.1 * self.theta_dot.powi(2) + 0.001 * u * u;
        let new_dot = (self.theta_dot + (3.0 * G / (2.0 * LENGTH) * th.sin() + 3.0 / (MASS * LENGTH * LENGTH) * u) * DT).clamp(-MAX_SPEED, MAX_SPEED);
        self.theta = th + new_dot * DT;
        self.theta_dot = new_dot;
        self.steps += 1;
        (self.obs(), StepOutcome { reward: -cost as f32, terminal: false, truncated: self.steps >= MAX_STEPS })
    }
}

/// Wraps to [−π, π).
fn angle_normalize(x: f64) -> f64 {
    (x + std::f64::consts::PI).rem_euclid(std::f64::consts::TAU) - std::f64::consts::PI
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn one_step_matches_gymnasium_by_hand() {
        // θ = π/2 (horizontal), θ̇ = 0, a = 0.5 → u = 1:
        // cost = (π/2)² = 2.4674011; θ̇' = (15·1 + 3·1)·0.05 = 0.9; θ' = π/2 + 0.045.
        let mut p = Pendulum::new(0);
        p.theta = std::f64::consts::FRAC_PI_2;
        p.theta_dot = 0.0;
        let (obs, o) = p.step(0.5);
        assert!((o.reward as f64 + std::f64::consts::FRAC_PI_2.powi(2) + 0.001).abs() < 1e-6);
        assert!((p.theta_dot - 0.9).abs() < 1e-12);
        assert!((p.theta - (std::f64::consts::FRAC_PI_2 + 0.045)).abs() < 1e-12);
        assert!((obs[0] as f64 - p.theta.cos()).abs() < 1e-6);
    }

    #[test]
    fn speed_is_clipped_and_episode_truncates_at_200() {
        let mut p = Pendulum::new(1);
        p.reset();
        let mut last = None;
        for _ in 0..200 {
            let (_, o) = p.step(1.0);
            assert!(p.theta_dot.abs() <= MAX_SPEED);
            assert!(!o.terminal);
            last = Some(o);
        }
        assert!(last.unwrap().truncated);
    }

    #[test]
    fn upright_and_still_costs_nothing() {
        let mut p = Pendulum::new(2);
        p.theta = 0.0;
        p.theta_dot = 0.0;
        let (_, o) = p.step(0.0);
        assert_eq!(o.reward, 0.0);
    }
}
