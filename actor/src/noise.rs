//! Exploration noise for deterministic policies (DDPG, TD3), one independent process per
//! vehicle and action component. SAC explores by sampling its own distribution instead
//! ([`crate::policy::ActMode::Sample`]).
//!
//! Defaults are SPEC §2's [inferred, MATLAB RL Toolbox] values; the noisy action is clipped to
//! the action box [−1, 1] before it is applied and stored.

use rand::Rng;
use rand_distr::StandardNormal;
use serde::{Deserialize, Serialize};

/// Which noise to add to a deterministic policy's action.
#[derive(Debug, Clone, Copy, PartialEq, Serialize, Deserialize)]
#[serde(tag = "kind", rename_all = "snake_case", deny_unknown_fields)]
pub enum NoiseConfig {
    /// None (evaluation, or SAC).
    None,
    /// Independent Gaussian noise N(0, σ²) each step (TD3; SPEC §2: σ ≈ 0.32).
    Gaussian {
        /// Standard deviation.
        sigma: f32,
    },
    /// Ornstein–Uhlenbeck noise (DDPG; SPEC §2: θ = 0.15, σ = 0.3), MATLAB's discretisation
    /// `x ← x + θ(μ − x)·dt + σ·√dt·N(0, 1)` with `dt` the sample time; reset at each episode start.
    OrnsteinUhlenbeck {
        /// Mean attraction constant θ.
        theta: f32,
        /// Standard deviation σ.
        sigma: f32,
        /// Mean μ.
        mean: f32,
        /// Step length dt in seconds (the simulator's sample time, 0.1 s by default).
        dt: f32,
    },
}

impl NoiseConfig {
    /// TD3's default exploration noise.
    pub const TD3_DEFAULT: NoiseConfig = NoiseConfig::Gaussian { sigma: 0.32 };
    /// DDPG's default exploration noise.
    pub const DDPG_DEFAULT: NoiseConfig = NoiseConfig::OrnsteinUhlenbeck { theta: 0.15, sigma: 0.3, mean: 0.0, dt: 0.1 };
}

/// Noise state for `n` vehicles × `act_dim` components.
#[derive(Debug, Clone)]
pub struct Noise {
    config: NoiseConfig,
    act_dim: usize,
    state: Vec<f32>,
}

impl Noise {
    /// Noise for `vehicles` vehicles, OU state starting at its mean.
    pub fn new(config: NoiseConfig, vehicles: usize, act_dim: usize) -> Self {
        let start = match config {
            NoiseConfig::OrnsteinUhlenbeck { mean, .. } => mean,
            _ => 0.0,
        };
        Noise { config, act_dim, state: vec![start; vehicles * act_dim] }
    }

    /// Restarts vehicle `i`'s process (call when its episode resets).
    pub fn reset(&mut self, i: usize) {
        if let NoiseConfig::OrnsteinUhlenbeck { mean, .. } = self.config {
            self.state[i * self.act_dim..(i + 1) * self.act_dim].fill(mean);
        }
    }

    /// Adds one step of noise to `actions` (`[vehicles, act_dim]`) and clips to [−1, 1].
    pub fn apply<R: Rng + ?Sized>(&mut self, rng: &mut R, actions: &mut [f32]) {
        match self.config {
            NoiseConfig::None => {}
            NoiseConfig::Gaussian { sigma } => {
                for a in actions.iter_mut() {
                    let z: f32 = rng.sample(StandardNormal);
                    *a += sigma * z;
                }
            }
            NoiseConfig::OrnsteinUhlenbeck { theta, sigma, mean, dt } => {
                let scale = sigma * dt.sqrt();
                for (a, x) in actions.iter_mut().zip(self.state.iter_mut()) {
                    let z: f32 = rng.sample(StandardNormal);
                    *x += theta * (mean - *x) * dt + scale * z;
                    *a += *x;
                }
            }
        }
        for a in actions.iter_mut() {
            *a = a.clamp(-1.0, 1.0);
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use rand::SeedableRng;

    #[test]
    fn ou_noise_reaches_its_stationary_spread_and_is_autocorrelated() {
        // Stationary variance of the discretised process: σ²dt / (1 − (1 − θdt)²).
        let (theta, sigma, dt) = (0.15f32, 0.3f32, 0.1f32);
        let mut noise = Noise::new(NoiseConfig::OrnsteinUhlenbeck { theta, sigma, mean: 0.0, dt }, 1, 1);
        let mut rng = rand_pcg::Pcg64::seed_from_u64(3);
        let mut xs = Vec::new();
        for _ in 0..400_000 {
            let mut a = [0.0f32];
            noise.apply(&mut rng, &mut a);
            xs.push(f64::from(noise.state[0]));
        }
        let xs = &xs[10_000..];
        let var = xs.iter().map(|x| x * x).sum::<f64>() / xs.len() as f64;
        let k = 1.0 - f64::from(theta * dt);
        let want = f64::from(sigma * sigma * dt) / (1.0 - k * k);
        assert!((var / want - 1.0).abs() < 0.1, "variance {var}, expected {want}");
        let lag1 = xs.windows(2).map(|w| w[0] * w[1]).sum::<f64>() / (xs.len() - 1) as f64 / var;
        assert!((lag1 - k).abs() < 0.01, "lag-1 autocorrelation {lag1}, expected {k}");
    }

    #[test]
    fn noisy_actions_stay_in_the_action_box_and_reset_restarts_one_vehicle() {
        let mut noise = Noise::new(NoiseConfig::Gaussian { sigma: 5.0 }, 2, 2);
        let mut rng = rand_pcg::Pcg64::seed_from_u64(4);
        let mut a = [0.9f32, -0.9, 0.0, 0.0];
        noise.apply(&mut rng, &mut a);
        assert!(a.iter().all(|v| (-1.0..=1.0).contains(v)), "{a:?}");

        let mut ou = Noise::new(NoiseConfig::DDPG_DEFAULT, 2, 2);
        for _ in 0..100 {
            ou.apply(&mut rng, &mut [0.0; 4]);
        }
        assert!(ou.state.iter().all(|x| *x != 0.0));
        ou.reset(1);
        assert!(ou.state[..2].iter().all(|x| *x != 0.0));
        assert_eq!(&ou.state[2..], &[0.0, 0.0]);
    }
}
