//! Harness of the `policy_safetensors` fuzz target (`fuzz/` at the repository root, run with
//! `cargo +nightly fuzz run policy_safetensors`; docs/reliability.md, "Fuzzing"), kept here so
//! that `actor/tests/fuzz_corpora.rs` replays the committed inputs through the same code on
//! stable.
//!
//! ```text
//!   bytes ─► weights_file::snapshot_from_safetensors ─► Policy::from_snapshot ─► Policy::act
//! ```
//!
//! Arbitrary bytes must come out as an error, never a panic. What the loader accepts must
//! write back to a file that reads as the same snapshot, and a policy it builds must turn
//! finite observations into actions in [−1, 1], or say why it cannot.

use mapless_proto::v1::{Algorithm, NamedTensor, ProtocolVersion, WeightsSnapshot};
use mapless_proto::weights_file::{snapshot_from_safetensors, snapshot_to_safetensors};
use rand::SeedableRng;

use crate::policy::{ActMode, Policy};

/// Observations the policy is asked about: zeros, ones, and a spread of signs and magnitudes.
fn observations(obs_dim: usize, rows: usize) -> Vec<Vec<f32>> {
    let spread = (0..obs_dim * rows).map(|i| ((i % 7) as f32 - 3.0) * 10f32.powi((i % 5) as i32 - 2)).collect();
    vec![vec![0.0; obs_dim * rows], vec![1.0; obs_dim * rows], spread]
}

/// The `policy_safetensors` target: see the module doc.
pub fn policy_safetensors(data: &[u8]) {
    let Ok(snapshot) = snapshot_from_safetensors(data, "fuzz input") else { return };
    let bytes = snapshot_to_safetensors(&snapshot).unwrap_or_else(|e| panic!("an accepted snapshot does not write back: {e}"));
    let again = snapshot_from_safetensors(&bytes, "rewritten").unwrap_or_else(|e| panic!("a rewritten snapshot does not read back: {e}"));
    assert_eq!(again, snapshot, "the rewritten file reads as another snapshot");
    let Ok(mut policy) = Policy::from_snapshot(&snapshot) else { return };
    let (obs_dim, act_dim) = (policy.obs_dim(), policy.act_dim());
    let mut rng = rand_pcg::Pcg64Mcg::seed_from_u64(1);
    for rows in [1, 3] {
        for obs in observations(obs_dim, rows) {
            for mode in [ActMode::Deterministic, ActMode::Sample] {
                let mut actions = vec![0.0; rows * act_dim];
                match policy.act(&obs, mode, &mut rng, &mut actions) {
                    Ok(()) => assert!(actions.iter().all(|a| (-1.0..=1.0).contains(a)), "actions {actions:?} outside [-1, 1] (or NaN)"),
                    Err(crate::ActorError::BadWeights(_)) => {}
                    Err(e) => panic!("acting on finite observations failed: {e}"),
                }
            }
        }
    }
}

/// A small valid policy file (obs 3 → 4 → 4 → act 2) of `algorithm`, for seeds.
pub fn seed_policy(algorithm: Algorithm, scale: f32) -> Vec<u8> {
    let (obs, hidden, act) = (3u64, 4u64, 2u64);
    let out = if algorithm == Algorithm::Sac { 2 * act } else { act };
    let values = |n: u64, k: f32| (0..n).map(|i| scale * k * ((i % 5) as f32 - 2.0) / 4.0).collect::<Vec<f32>>();
    let tensor = |name: &str, shape: Vec<u64>, k: f32| {
        let n = shape.iter().product();
        NamedTensor::from_f32(name, shape, &values(n, k)).expect("seed tensor")
    };
    let mut metadata = std::collections::HashMap::new();
    if algorithm == Algorithm::Sac {
        metadata.insert(crate::policy::META_LOG_STD_MIN.to_string(), "-20".to_string());
        metadata.insert(crate::policy::META_LOG_STD_MAX.to_string(), "2".to_string());
    }
    let snapshot = WeightsSnapshot {
        protocol_version: ProtocolVersion::V1 as i32,
        version: 3,
        algorithm: algorithm as i32,
        created_unix_ms: 1,
        obs_dim: obs as u32,
        act_dim: act as u32,
        tensors: vec![
            tensor("actor.l0.weight", vec![hidden, obs], 1.0),
            tensor("actor.l0.bias", vec![hidden], 0.5),
            tensor("actor.l1.weight", vec![hidden, hidden], -1.0),
            tensor("actor.l1.bias", vec![hidden], 0.25),
            tensor("actor.out.weight", vec![out, hidden], 2.0),
            tensor("actor.out.bias", vec![out], 0.1),
        ],
        metadata,
    };
    snapshot_to_safetensors(&snapshot).expect("seed policy encodes")
}
