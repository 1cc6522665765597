//! The fused CPU update with two lanes (libtorch set to ≥ 2 intra-op threads: a helper thread
//! runs independent products beside the caller, each single-threaded) computes exactly what it
//! computes with one lane at one thread: every parameter, target, optimiser moment and statistic
//! bit for bit.
//!
//! Its own test binary, because it changes libtorch's process-wide intra-op thread count.

use mapless_learner::TorchThreads;
use mapless_learner::algo::Agent;
use mapless_learner::batch::Minibatch;
use mapless_learner::config::{AlgorithmKind, LearnerConfig};
use rand::SeedableRng;

fn threads(n: usize) {
    TorchThreads { intra_op: n, inter_op: 1 }.apply().expect("thread counts");
}

#[test]
fn two_lanes_update_bit_for_bit_as_one() {
    if !mapless_learner::lanes::available() {
        eprintln!("skipped: this libtorch's BLAS is not MKL, so a fused update has one lane only");
        return;
    }
    let (obs, act, rows) = (17usize, 2usize, 64usize);
    for kind in [AlgorithmKind::Sac, AlgorithmKind::Td3, AlgorithmKind::Ddpg] {
        let cfg = LearnerConfig { algorithm: kind, hidden_width: 96, seed: 5, grad_clip_norm: Some(0.5), ..LearnerConfig::default() };
        // Each agent picks its lanes at its first update, from the thread count then.
        threads(1);
        let mut one = Agent::new(&cfg, obs, act).unwrap();
        threads(2);
        let mut two = Agent::new(&cfg, obs, act).unwrap();
        let mut rng = rand_pcg::Pcg64::seed_from_u64(9);
        for step in 0..5 {
            let b = Minibatch::random(rows, obs, act, &mut rng, tch::Device::Cpu).expect("minibatch");
            threads(1);
            let s1 = one.update(&b).unwrap();
            threads(2);
            let s2 = two.update(&b).unwrap();
            assert_eq!(s1.scalars, s2.scalars, "{kind:?} step {step}: statistics");
            assert_eq!(s1.td_errors, s2.td_errors, "{kind:?} step {step}: TD errors");
        }
        threads(1);
        let (a, b) = (one.state_tensors(), two.state_tensors());
        assert_eq!(a.len(), b.len());
        for ((na, ta), (nb, tb)) in a.iter().zip(&b) {
            assert_eq!(na, nb);
            assert!(ta.equal(tb), "{kind:?} {na}: differs between one lane and two");
        }
    }
}
