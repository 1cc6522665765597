//! The `checkpoint_files` fuzz target's committed inputs on stable: every file of
//! `fuzz/corpus/checkpoint_files/` and `fuzz/regressions/checkpoint_files/` goes through the
//! harness the fuzzer runs (`mapless_learner::fuzzing`). The seeds:
//! `MAPLESS_WRITE_FUZZ_SEEDS=1 cargo test -p mapless-learner --test fuzz_corpora -- --ignored`.

use mapless_learner::fuzzing::{FILES, checkpoint_files, input, op};

#[path = "../../tests/common/fuzz_corpus.rs"]
mod fuzz_corpus;

/// File indices of `FILES`.
const MANIFEST: u8 = 0;
const STATE: u8 = 1;
const TENSORS: u8 = 2;
const POLICY: u8 = 3;
const LATEST: u8 = 4;

fn seeds() -> Vec<(String, Vec<u8>)> {
    assert_eq!(FILES.len(), 5);
    let mut out = Vec::new();
    for (base, name) in [(0u8, "ddpg"), (1, "td3"), (2, "sac")] {
        out.push((format!("{name}-unedited"), input(base, &[])));
        out.push((format!("{name}-tensors-flipped"), input(base, &[&[op::FLIP, TENSORS, 200, 0, 0x10]])));
        out.push((format!("{name}-state-truncated"), input(base, &[&[op::TRUNCATE, STATE, 100, 0]])));
        out.push((format!("{name}-policy-deleted"), input(base, &[&[op::DELETE, POLICY]])));
    }
    // Forged: a state byte changed and the sums recomputed, so the change reaches the parser.
    out.push(("sac-state-forged".into(), input(2, &[&[op::FLIP, STATE, 40, 0, 0x01], &[op::FIX_SUMS]])));
    out.push(("ddpg-state-emptied-forged".into(), input(0, &[&[op::REPLACE, STATE, 2], b"{}", &[op::FIX_SUMS]])));
    out.push(("td3-manifest-dims-changed".into(), input(1, &[&[op::OVERWRITE, MANIFEST, 0, 0, 1, b' ']])));
    out.push(("ddpg-latest-escapes".into(), input(0, &[&[op::REPLACE, LATEST, 6], b"../etc"])));
    out.push(("sac-tensors-forged".into(), input(2, &[&[op::FLIP, TENSORS, 0, 2, 0x01], &[op::FIX_SUMS]])));
    out
}

#[test]
fn checkpoint_files_corpus_and_regressions() {
    assert!(fuzz_corpus::replay_inputs("checkpoint_files", checkpoint_files) > 0, "no committed inputs for checkpoint_files");
}

#[test]
fn the_seeds_pass_the_harness() {
    for (name, data) in seeds() {
        eprintln!("{name}");
        checkpoint_files(&data);
    }
}

/// Writes the seeds into `fuzz/corpus/checkpoint_files/seed-<name>` (run by hand).
#[test]
#[ignore]
fn write_seed_corpus() {
    fuzz_corpus::write_seeds("checkpoint_files", seeds());
}
