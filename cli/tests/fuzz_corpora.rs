//! The `config_sources` fuzz target's committed inputs on stable: every file of
//! `fuzz/corpus/config_sources/` and `fuzz/regressions/config_sources/` goes through the
//! harness the fuzzer runs (`mapless_cli::fuzzing`). The seeds are the built-in presets, with and
//! without `--set` overrides, and a run's `config.yaml` as `mapless train` writes it:
//! `MAPLESS_WRITE_FUZZ_SEEDS=1 cargo test -p mapless-cli --test fuzz_corpora -- --ignored`.

use mapless_cli::fuzzing::{check, config_sources};
use mapless_cli::train::config::{PRESETS, preset_config};

#[path = "../../tests/common/fuzz_corpus.rs"]
mod fuzz_corpus;

/// An input of the harness: `document | 0x00 | one --set per line`.
fn input(doc: &str, sets: &[&str]) -> Vec<u8> {
    let mut out = doc.as_bytes().to_vec();
    if !sets.is_empty() {
        out.push(0);
        out.extend_from_slice(sets.join("\n").as_bytes());
    }
    out
}

fn seeds() -> Vec<(String, Vec<u8>)> {
    let mut out: Vec<(String, Vec<u8>)> = PRESETS.iter().map(|(name, text)| ((*name).to_owned(), input(text, &[]))).collect();
    let env1 = PRESETS.iter().find(|p| p.0 == "env1-sac").unwrap().1;
    for (name, sets) in [
        ("env1-sac-paper-ratio", &["replay.rate_limiter.samples_per_insert=128", "seed=7"][..]),
        ("env1-sac-td3-noise", &["learner.algorithm=td3", "learner.td3.exploration={kind: gaussian, sigma: 0.2}"][..]),
        ("env1-sac-sar-reward", &["reward=search_and_rescue", "max_steps=3000", "map=outdoor20"][..]),
        ("env1-sac-sensor", &["env.sensor.beams=25", "env.sensor.fov_rad=4.712389", "actors.vehicles=8"][..]),
        ("env1-sac-families", &["map=env1+gen:rooms+gen:cave:3", "worlds_per_family=4", "stop.minutes=1.5"][..]),
    ] {
        out.push((name.to_owned(), input(env1, sets)));
    }
    let written = serde_yaml::to_string(&preset_config("explore-sac").unwrap().resolve().unwrap()).unwrap();
    out.push(("explore-sac-config-yaml".into(), input(&written, &[])));
    out
}

#[test]
fn config_sources_corpus_and_regressions() {
    assert!(fuzz_corpus::replay_inputs("config_sources", config_sources) > 0, "no committed inputs for config_sources");
}

/// Every seed resolves (so the fuzzer starts from configurations that pass, not from errors)
/// and passes the invariants.
#[test]
fn the_seeds_resolve_and_pass_the_invariants() {
    for (name, data) in seeds() {
        let (doc, sets) = match data.iter().position(|&b| b == 0) {
            Some(i) => (&data[..i], std::str::from_utf8(&data[i + 1..]).unwrap().lines().map(str::to_owned).collect()),
            None => (&data[..], Vec::new()),
        };
        let mut doc: serde_yaml::Value = serde_yaml::from_str(std::str::from_utf8(doc).unwrap()).unwrap();
        mapless_cli::train::config::expand_shorthands(&mut doc, false).unwrap();
        mapless_cli::train::config::apply_sets(&mut doc, &sets).unwrap_or_else(|e| panic!("seed {name}: {e:#}"));
        let cfg = mapless_cli::train::config::parse_config(doc).and_then(|c| c.resolve()).unwrap_or_else(|e| panic!("seed {name}: {e:#}"));
        check(&cfg);
    }
}

/// The check refuses a configuration that `resolve` would not accept again (here: a NaN
/// learning rate put in after resolving), so a field that slips through is caught.
#[test]
#[should_panic(expected = "no longer resolves")]
fn a_configuration_that_no_longer_resolves_fails_the_check() {
    let mut cfg = preset_config("env1-sac").unwrap().resolve().unwrap();
    cfg.learner.actor_lr = f64::NAN;
    check(&cfg);
}

/// Writes the seeds into `fuzz/corpus/config_sources/seed-<name>` (run by hand).
#[test]
#[ignore]
fn write_seed_corpus() {
    fuzz_corpus::write_seeds("config_sources", seeds());
}
