//! The algorithms learn Pendulum-v1 in process, with the real replay table, on CPU with one
//! libtorch thread: mean return ≥ −250 over 10 deterministic evaluation episodes within
//! 20,000 environment steps (SAC, TD3) or 30,000 (DDPG). Training stops at the first
//! evaluation (every 1,000 steps) that reaches the threshold.

mod common;

use mapless_learner::config::AlgorithmKind;

const THRESHOLD: f64 = -250.0;

fn learns(algorithm: AlgorithmKind, budget: u64) {
    let (steps, best, secs, scores) = common::train_until(algorithm, 1, THRESHOLD, budget, 1_000);
    eprintln!("{algorithm:?}: {steps} steps, best {best:.1}, {secs:.1} s, evaluations {scores:?}");
    assert!(best >= THRESHOLD, "{algorithm:?} reached only {best:.1} in {steps} steps (evaluations: {scores:?})");
}

#[test]
fn sac_learns_pendulum_within_20k_steps() {
    learns(AlgorithmKind::Sac, 20_000);
}

#[test]
fn td3_learns_pendulum_within_20k_steps() {
    learns(AlgorithmKind::Td3, 20_000);
}

#[test]
fn ddpg_learns_pendulum_within_30k_steps() {
    learns(AlgorithmKind::Ddpg, 30_000);
}
