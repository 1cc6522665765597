//! Exploration noise for deterministic policies (DDPG, TD3): what a learner's algorithm asks
//! to be added to its actions, and the one implementation of it.
//!
//! The learner's config names it (`learner.ddpg.exploration`, `learner.td3.exploration`, with
//! their sources), the actors apply it to every vehicle's action ([`NoiseProcess`]), and the
//! learner applies it when it acts itself (its in-process environments). Both sides run
//! [`ExplorationNoise::apply`], so they agree on the process and its discretisation. SAC
//! explores by sampling its own distribution and takes none.
//!
//! The noisy action is clipped to the action box [−1, 1] before it is applied and stored.

use rand::Rng;
use rand_distr::StandardNormal;
use serde::{Deserialize, Serialize};

/// Noise added to a deterministic policy's action when acting to explore.
#[derive(Clone, Copy, Debug, Serialize, Deserialize, PartialEq)]
#[serde(rename_all = "snake_case", tag = "kind", deny_unknown_fields)]
pub enum ExplorationNoise {
    /// a + σ·N(0, I), independent at every step (TD3).
    Gaussian {
        /// σ.
        sigma: f64,
    },
    /// Ornstein–Uhlenbeck (DDPG), MATLAB's discretisation: x ← x + θ(μ − x)·dt + σ·√dt·N(0, I);
    /// a + x. The state starts at μ and restarts there at each episode start.
    OrnsteinUhlenbeck {
        /// θ, mean attraction.
        theta: f64,
        /// σ.
        sigma: f64,
        /// μ, the mean the process reverts to.
        mean: f64,
        /// dt, the sample time in seconds.
        dt: f64,
    },
}

impl ExplorationNoise {
    /// TD3's default [inferred, MATLAB `rlTD3AgentOptions.ExplorationModel`: Gaussian σ ≈ 0.32
    /// (SPEC §2)].
    pub const TD3_DEFAULT: ExplorationNoise = ExplorationNoise::Gaussian { sigma: 0.32 };
    /// DDPG's default [inferred, MATLAB `rlDDPGAgentOptions.NoiseOptions`: θ = 0.15, σ = 0.3,
    /// μ = 0; dt = 0.1 s, the simulator's sample time (SPEC §2)].
    pub const DDPG_DEFAULT: ExplorationNoise = ExplorationNoise::OrnsteinUhlenbeck { theta: 0.15, sigma: 0.3, mean: 0.0, dt: 0.1 };

    /// `Err` (saying why) unless σ, θ are finite and ≥ 0, μ is finite and dt > 0.
    pub fn check(&self) -> Result<(), String> {
        let ok = match *self {
            Self::Gaussian { sigma } => sigma.is_finite() && sigma >= 0.0,
            Self::OrnsteinUhlenbeck { theta, sigma, mean, dt } => theta.is_finite() && theta >= 0.0 && sigma.is_finite() && sigma >= 0.0 && mean.is_finite() && dt.is_finite() && dt > 0.0,
        };
        if ok { Ok(()) } else { Err(format!("{self:?}: σ, θ must be finite and ≥ 0, μ finite, dt > 0")) }
    }

    /// Where an Ornstein–Uhlenbeck state starts and restarts (μ); 0 for Gaussian noise.
    pub fn start(&self) -> f32 {
        match *self {
            Self::OrnsteinUhlenbeck { mean, .. } => mean as f32,
            Self::Gaussian { .. } => 0.0,
        }
    }

    /// One step of noise added to `actions` (row-major, any number of rows), then clipped to
    /// [−1, 1]. `state` holds the Ornstein–Uhlenbeck state, one value per action component;
    /// when its length is not the actions' it restarts at [`ExplorationNoise::start`]. One
    /// standard-normal draw from `rng` per component, in order.
    pub fn apply<R: Rng + ?Sized>(&self, state: &mut Vec<f32>, rng: &mut R, actions: &mut [f32]) {
        match *self {
            Self::Gaussian { sigma } => {
                let sigma = sigma as f32;
                for a in actions.iter_mut() {
                    let z: f32 = rng.sample(StandardNormal);
                    *a += sigma * z;
                }
            }
            Self::OrnsteinUhlenbeck { theta, sigma, mean, dt } => {
                if state.len() != actions.len() {
                    *state = vec![self.start(); actions.len()];
                }
                let (theta, mean, dt) = (theta as f32, mean as f32, dt as f32);
                let scale = sigma as f32 * dt.sqrt();
                for (a, x) in actions.iter_mut().zip(state.iter_mut()) {
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

/// Exploration noise for `vehicles` vehicles × `act_dim` components, each its own process.
/// `None` noise leaves actions as they are.
#[derive(Debug, Clone)]
pub struct NoiseProcess {
    noise: Option<ExplorationNoise>,
    act_dim: usize,
    state: Vec<f32>,
}

impl NoiseProcess {
    /// Every state at its start.
    pub fn new(noise: Option<ExplorationNoise>, vehicles: usize, act_dim: usize) -> Self {
        let start = noise.map_or(0.0, |n| n.start());
        NoiseProcess { noise, act_dim, state: vec![start; vehicles * act_dim] }
    }

    /// Restarts vehicle `i`'s process (call when its episode resets).
    pub fn reset(&mut self, i: usize) {
        if let Some(n) = self.noise {
            self.state[i * self.act_dim..(i + 1) * self.act_dim].fill(n.start());
        }
    }

    /// One step of noise added to `actions` (`[vehicles, act_dim]`), clipped to [−1, 1].
    pub fn apply<R: Rng + ?Sized>(&mut self, rng: &mut R, actions: &mut [f32]) {
        if let Some(n) = self.noise {
            n.apply(&mut self.state, rng, actions);
        }
    }

    /// The Ornstein–Uhlenbeck state, `[vehicles, act_dim]`.
    pub fn state(&self) -> &[f32] {
        &self.state
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use rand::SeedableRng;

    #[test]
    fn ou_noise_reaches_its_stationary_spread_and_is_autocorrelated() {
        // Stationary variance of the discretised process: σ²dt / (1 − (1 − θdt)²).
        let (theta, sigma, dt) = (0.15, 0.3, 0.1);
        let mut noise = NoiseProcess::new(Some(ExplorationNoise::OrnsteinUhlenbeck { theta, sigma, mean: 0.0, dt }), 1, 1);
        let mut rng = rand_pcg::Pcg64::seed_from_u64(3);
        let mut xs = Vec::new();
        for _ in 0..400_000 {
            let mut a = [0.0f32];
            noise.apply(&mut rng, &mut a);
            xs.push(f64::from(noise.state()[0]));
        }
        let xs = &xs[10_000..];
        let var = xs.iter().map(|x| x * x).sum::<f64>() / xs.len() as f64;
        let k = 1.0 - theta * dt;
        let want = sigma * sigma * dt / (1.0 - k * k);
        assert!((var / want - 1.0).abs() < 0.1, "variance {var}, expected {want}");
        let lag1 = xs.windows(2).map(|w| w[0] * w[1]).sum::<f64>() / (xs.len() - 1) as f64 / var;
        assert!((lag1 - k).abs() < 0.01, "lag-1 autocorrelation {lag1}, expected {k}");
    }

    #[test]
    fn noisy_actions_stay_in_the_action_box_and_reset_restarts_one_vehicle() {
        let mut noise = NoiseProcess::new(Some(ExplorationNoise::Gaussian { sigma: 5.0 }), 2, 2);
        let mut rng = rand_pcg::Pcg64::seed_from_u64(4);
        let mut a = [0.9f32, -0.9, 0.0, 0.0];
        noise.apply(&mut rng, &mut a);
        assert!(a.iter().all(|v| (-1.0..=1.0).contains(v)), "{a:?}");
        assert!(a.iter().any(|v| v.abs() == 1.0), "σ = 5 must push some action to the box's edge: {a:?}");

        let mut ou = NoiseProcess::new(Some(ExplorationNoise::DDPG_DEFAULT), 2, 2);
        for _ in 0..100 {
            ou.apply(&mut rng, &mut [0.0; 4]);
        }
        assert!(ou.state().iter().all(|x| *x != 0.0));
        ou.reset(1);
        assert!(ou.state()[..2].iter().all(|x| *x != 0.0));
        assert_eq!(&ou.state()[2..], &[0.0, 0.0]);
    }

    #[test]
    fn no_noise_leaves_actions_alone_and_a_state_of_another_length_restarts_at_the_mean() {
        let mut none = NoiseProcess::new(None, 1, 2);
        let mut a = [0.25f32, -0.5];
        none.apply(&mut rand_pcg::Pcg64::seed_from_u64(5), &mut a);
        assert_eq!(a, [0.25, -0.5]);

        let ou = ExplorationNoise::OrnsteinUhlenbeck { theta: 1.0, sigma: 0.0, mean: 0.5, dt: 0.1 };
        let mut state = vec![9.0; 3];
        let mut b = [0.0f32; 2];
        ou.apply(&mut state, &mut rand_pcg::Pcg64::seed_from_u64(6), &mut b);
        assert_eq!(state, vec![0.5, 0.5], "restarted at μ, and with σ = 0 and x = μ it stays there");
        assert_eq!(b, [0.5, 0.5]);
    }

    #[test]
    fn check_refuses_negative_or_non_finite_parameters() {
        assert!(ExplorationNoise::DDPG_DEFAULT.check().is_ok());
        assert!(ExplorationNoise::TD3_DEFAULT.check().is_ok());
        assert!(ExplorationNoise::Gaussian { sigma: -1.0 }.check().is_err());
        assert!(ExplorationNoise::OrnsteinUhlenbeck { theta: 0.15, sigma: 0.3, mean: 0.0, dt: 0.0 }.check().is_err());
        assert!(ExplorationNoise::OrnsteinUhlenbeck { theta: f64::NAN, sigma: 0.3, mean: 0.0, dt: 0.1 }.check().is_err());
    }
}
