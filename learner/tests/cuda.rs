//! `--device cuda`: the same updates on an NVIDIA GPU. On a machine without one the test says
//! so and checks that asking for CUDA is a clear error rather than a crash.

use mapless_learner::LearnerError;
use mapless_learner::algo::{Agent, metric};
use mapless_learner::batch::Minibatch;
use mapless_learner::config::{AlgorithmKind, LearnerConfig};
use rand::SeedableRng;

#[test]
fn updates_run_on_cuda_or_the_test_skips_with_a_clear_message() {
    for algorithm in [AlgorithmKind::Ddpg, AlgorithmKind::Td3, AlgorithmKind::Sac] {
        let cfg = LearnerConfig { algorithm, device: "cuda".into(), hidden_width: 64, batch_size: 32, ..LearnerConfig::default() };
        match Agent::new(&cfg, 17, 2) {
            Err(err @ LearnerError::CudaUnavailable { .. }) => {
                let message = err.to_string();
                assert!(message.contains("no CUDA device") && message.contains("use `cpu`"), "{message}");
                eprintln!("skipped: {algorithm:?} on CUDA: {message}");
            }
            Err(other) => panic!("{algorithm:?}: unexpected error {other}"),
            Ok(mut agent) => {
                assert_eq!(agent.device(), tch::Device::Cuda(0));
                let mut rng = rand_pcg::Pcg64::seed_from_u64(1);
                let batch = Minibatch::random(32, 17, 2, &mut rng, agent.device()).unwrap();
                for _ in 0..10 {
                    let stats = agent.update(&batch).unwrap();
                    assert!(stats.get(metric::CRITIC_LOSS).is_some_and(f64::is_finite));
                }
                // Published weights come back to the host whatever the device.
                assert!(agent.policy_tensors().iter().all(|(_, t)| t.device() == tch::Device::Cpu));
                assert_eq!(agent.updates(), 10);
            }
        }
    }
}
