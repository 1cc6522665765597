//! Quick timing loop for `Agent::update` (no assertions): updates/s per algorithm, critic
//! evaluation mode, thread count.
//!
//! `cargo run --release -p mapless-learner --example bench_updates -- [seconds] [threads] [width] [batch] [obs] [act]`

use mapless_learner::TorchThreads;
use mapless_learner::algo::bench_updates;
use mapless_learner::config::{AlgorithmKind, LearnerConfig};

fn main() {
    let args: Vec<String> = std::env::args().skip(1).collect();
    let arg = |i: usize, d: f64| args.get(i).and_then(|s| s.parse().ok()).unwrap_or(d);
    let (seconds, threads, width, batch) = (arg(0, 3.0), arg(1, 1.0) as usize, arg(2, 256.0) as i64, arg(3, 128.0) as usize);
    let (obs, act) = (arg(4, 17.0) as usize, arg(5, 2.0) as usize);
    let threads = TorchThreads { intra_op: threads, inter_op: 1 };
    for algorithm in [AlgorithmKind::Sac, AlgorithmKind::Td3, AlgorithmKind::Ddpg] {
        for fused in [true, false] {
            let cfg = LearnerConfig { algorithm, hidden_width: width, batch_size: batch, fused_critics: fused, ..LearnerConfig::default() };
            let ups = bench_updates(&cfg, obs, act, threads, seconds).expect("bench");
            println!(
                "{{\"algorithm\":\"{}\",\"fused_critics\":{fused},\"threads\":{},\"width\":{width},\"batch\":{batch},\"obs\":{obs},\"act\":{act},\"updates_per_s\":{ups:.1}}}",
                algorithm.as_str(),
                threads.intra_op
            );
        }
    }
}
