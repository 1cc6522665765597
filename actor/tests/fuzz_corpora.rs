//! The `policy_safetensors` fuzz target's committed inputs on stable: every file of
//! `fuzz/corpus/policy_safetensors/` and `fuzz/regressions/policy_safetensors/` goes through
//! the harness the fuzzer runs (`mapless_actor::fuzzing`). The seeds are written by the
//! project's own encoder:
//! `MAPLESS_WRITE_FUZZ_SEEDS=1 cargo test -p mapless-actor --test fuzz_corpora -- --ignored`.

use mapless_actor::fuzzing::{policy_safetensors, seed_policy};
use mapless_proto::v1::Algorithm;

#[path = "../../tests/common/fuzz_corpus.rs"]
mod fuzz_corpus;

fn seeds() -> Vec<(String, Vec<u8>)> {
    let mut out = Vec::new();
    for (name, algorithm) in [("ddpg", Algorithm::Ddpg), ("td3", Algorithm::Td3), ("sac", Algorithm::Sac)] {
        out.push((name.to_string(), seed_policy(algorithm, 1.0)));
        out.push((format!("{name}-large-weights"), seed_policy(algorithm, 3e37)));
    }
    let mut truncated = seed_policy(Algorithm::Td3, 1.0);
    truncated.truncate(truncated.len() - 3);
    out.push(("td3-truncated".into(), truncated));
    out
}

#[test]
fn policy_safetensors_corpus_and_regressions() {
    assert!(fuzz_corpus::replay_inputs("policy_safetensors", policy_safetensors) > 0, "no committed inputs for policy_safetensors");
}

#[test]
fn the_seeds_pass_the_harness() {
    for (_, data) in seeds() {
        policy_safetensors(&data);
    }
}

/// Writes the seeds into `fuzz/corpus/policy_safetensors/seed-<name>` (run by hand).
#[test]
#[ignore]
fn write_seed_corpus() {
    fuzz_corpus::write_seeds("policy_safetensors", seeds());
}
