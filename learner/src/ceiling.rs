//! How fast an update *could* be on this machine: the matrix-product work of one update, and
//! the rate at which libtorch multiplies matrices of the networks' shape here.
//!
//! At the paper's sizes (2×256 hidden, minibatch 128) an update is almost entirely matrix
//! products, so `matmul GFLOP/s ÷ FLOP per update` estimates the most updates/s any f32
//! implementation can reach, whatever it does about dispatch, allocation or fusion (an
//! estimate: the rate is MKL's at the dominant `[128, 256] × [256, 256]` shape; smaller layers
//! run slower, and on this project's machine it is near one core's FMA peak). `mapless bench learner` prints
//! both, and the fraction of that bound each algorithm reaches.
//!
//! Multiply–accumulates (MACs) per row, for a body `in → H → H → out`:
//!
//! ```text
//!   forward                      F(in, out) = in·H + H·H + H·out
//!   weight gradients             F(in, out)           (every layer)
//!   input gradients, hidden      H·H + H·out          (stops below the first layer)
//!   input gradients, to actions  act·H + H·H + H·out  (∂Q/∂a through a critic; not ∂Q/∂s)
//! ```
//!
//! Per update, `k` critics (`obs+act → 1`), actor `obs → K` (K = 2·act for SAC, act otherwise):
//!
//! ```text
//!   target     actor forward on s′ (target actor for DDPG/TD3) + k target-critic forwards
//!   critics    k × (forward + weight gradients + hidden input gradients)
//!   actor      actor forward + k critic forwards + one critic's gradients to actions
//!              + actor weight gradients + actor hidden input gradients
//!              (∂ min_k Q_k/∂a flows, row by row, through the smallest critic alone)
//!              (TD3: on every `policy_delay`-th update only, so divided by the delay)
//! ```
//!
//! FLOP = 2 · MACs · minibatch rows. Elementwise work (ReLU, Adam, the soft update) is a few
//! hundred thousand FLOP and not counted.

use std::time::Instant;

use tch::{Kind, Tensor};

use crate::LearnerError;
use crate::config::{AlgorithmKind, LearnerConfig};
use crate::device::ToTch;

/// FLOP of matrix products in one update of `cfg`'s algorithm and sizes (module docs).
pub fn update_flops(cfg: &LearnerConfig, obs_dim: usize, act_dim: usize) -> f64 {
    let h = cfg.hidden_width as f64;
    let (o, a) = (obs_dim as f64, act_dim as f64);
    let forward = |input: f64, output: f64| input * h + h * h + h * output;
    let hidden_input_grads = |output: f64| h * h + h * output;
    let (k, actor_out, actor_share) = match cfg.algorithm {
        AlgorithmKind::Ddpg => (1.0, a, 1.0),
        AlgorithmKind::Td3 => (2.0, a, 1.0 / cfg.td3.policy_delay.max(1) as f64),
        AlgorithmKind::Sac => (2.0, 2.0 * a, 1.0),
    };
    let critic = forward(o + a, 1.0);
    let actor = forward(o, actor_out);
    let target = actor + k * critic;
    let critics = k * (critic + critic + hidden_input_grads(1.0));
    let to_actions = a * h + hidden_input_grads(1.0);
    let actor_step = actor + k * critic + to_actions + actor + hidden_input_grads(actor_out);
    2.0 * cfg.batch_size as f64 * (target + critics + actor_share * actor_step)
}

/// GFLOP/s of libtorch's `[rows, width] × [width, width]` product on `device` with the
/// current thread settings, in f32 or (`bf16`) bfloat16, timed over about `seconds`.
pub fn matmul_gflops(rows: i64, width: i64, bf16: bool, device: crate::Device, seconds: f64) -> Result<f64, LearnerError> {
    let kind = if bf16 { Kind::BFloat16 } else { Kind::Float };
    let device = device.to_tch();
    let _guard = tch::no_grad_guard();
    let a = Tensor::f_randn([rows, width], (Kind::Float, device))?.f_to_kind(kind)?;
    let b = Tensor::f_randn([width, width], (Kind::Float, device))?.f_to_kind(kind)?;
    let out = a.f_mm(&b)?;
    for _ in 0..20 {
        let _ = a.f_mm_out(&out, &b)?;
    }
    let sync = || {
        if let tch::Device::Cuda(i) = device {
            tch::Cuda::synchronize(i as i64);
        }
    };
    sync();
    let start = Instant::now();
    let mut n = 0u64;
    loop {
        for _ in 0..50 {
            let _ = a.f_mm_out(&out, &b)?;
        }
        n += 50;
        sync();
        if start.elapsed().as_secs_f64() >= seconds {
            break;
        }
    }
    let flops = 2.0 * (rows * width * width) as f64 * n as f64;
    Ok(flops / start.elapsed().as_secs_f64() / 1e9)
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn sac_update_flops_at_the_papers_sizes_match_the_hand_count() {
        // H = 256, critic 19 → 1, actor 17 → 4, two critics, minibatch 128.
        let critic = 19 * 256 + 256 * 256 + 256; // 70,656
        let actor = 17 * 256 + 256 * 256 + 256 * 4; // 70,912
        let target = actor + 2 * critic; // 212,224
        let critics = 2 * (2 * critic + 256 * 256 + 256); // 414,208
        let to_actions = 2 * 256 + 256 * 256 + 256; // 66,304
        let actor_step = actor + 2 * critic + to_actions + actor + 256 * 256 + 256 * 4; // 416,000
        let macs: i64 = target + critics + actor_step; // 1,042,432 per row
        assert_eq!(macs, 1_042_432);
        let cfg = LearnerConfig::default();
        assert_eq!(cfg.algorithm, AlgorithmKind::Sac);
        let flops = update_flops(&cfg, 17, 2);
        assert_eq!(flops, 2.0 * 128.0 * macs as f64); // 266,862,592
    }

    #[test]
    fn td3_counts_the_actor_step_once_per_policy_delay_and_ddpg_one_critic() {
        let base = LearnerConfig::default();
        let td3 = |delay| {
            let mut cfg = LearnerConfig { algorithm: AlgorithmKind::Td3, ..base.clone() };
            cfg.td3.policy_delay = delay;
            update_flops(&cfg, 17, 2)
        };
        // The actor step of TD3 (actor 17 → 2): the difference between delay 1 and delay 2 is
        // half of it.
        let actor = (17 * 256 + 256 * 256 + 256 * 2) as f64;
        let critic = (19 * 256 + 256 * 256 + 256) as f64;
        let to_actions = (2 * 256 + 256 * 256 + 256) as f64;
        let actor_step = 2.0 * actor + 2.0 * critic + to_actions + (256 * 256 + 256 * 2) as f64;
        let diff = td3(1) - td3(2);
        assert!((diff - 2.0 * 128.0 * actor_step / 2.0).abs() < 1e-3, "{diff}");
        let ddpg = LearnerConfig { algorithm: AlgorithmKind::Ddpg, ..base };
        let one_critic = actor + critic + 2.0 * critic + (256 * 256 + 256) as f64 + 2.0 * actor + critic + to_actions + (256 * 256 + 256 * 2) as f64;
        assert_eq!(update_flops(&ddpg, 17, 2), 2.0 * 128.0 * one_critic);
    }

    #[test]
    fn matmul_rate_is_positive_and_finite() {
        let g = matmul_gflops(8, 16, false, crate::Device::Cpu, 0.01).unwrap();
        assert!(g.is_finite() && g > 0.0, "{g}");
    }
}
