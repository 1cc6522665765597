//! The `config_sources` fuzz target's committed inputs on stable: every file of
//! `fuzz/corpus/config_sources/` and `fuzz/regressions/config_sources/` goes through the
//! harness the fuzzer runs (`mapless_cli::fuzzing`). The seeds are the built-in presets, with and
//! without `--set` overrides, and a run's `config.yaml` as `mapless train` writes it:
//! `MAPLESS_WRITE_FUZZ_SEEDS=1 cargo test -p mapless-cli --test fuzz_corpora -- --ignored`.

use mapless_cli::fuzzing::{check, config_sources, episode_stats, episode_stats_input};
use mapless_cli::train::config::{PRESETS, preset_config};
use mapless_proto::v1::{EpisodeStats, ProtocolVersion};
use prost::Message;

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

/// Writes the seeds into `fuzz/corpus/config_sources/seed-<name>` and
/// `fuzz/corpus/episode_stats/seed-<name>` (run by hand).
#[test]
#[ignore]
fn write_seed_corpus() {
    fuzz_corpus::write_seeds("config_sources", seeds());
    fuzz_corpus::write_seeds("episode_stats", stats_seeds());
}

// ---------------------------------------------------------------------------------------------
// episode_stats
// ---------------------------------------------------------------------------------------------

/// A valid training record of `actor_id`, episode `id`.
fn record(actor_id: &str, id: u64, ret: f64, steps: u32) -> EpisodeStats {
    EpisodeStats {
        protocol_version: ProtocolVersion::V1 as i32,
        actor_id: actor_id.into(),
        episode_id: id,
        policy_version: id * 3,
        episode_return: ret,
        steps,
        terminal: steps < 1000,
        truncated: steps >= 1000,
        eqs: 12.0 + id as f64,
        ees: 1.25,
        distance_m: 0.05 * f64::from(steps),
        ..EpisodeStats::default()
    }
}

fn encoded(records: &[EpisodeStats]) -> Vec<Vec<u8>> {
    records.iter().map(Message::encode_to_vec).collect()
}

fn stats_seeds() -> Vec<(String, Vec<u8>)> {
    let three = encoded(&[record("actor-0-1-2", 1, 433.5, 1000), record("actor-1-1-2", 1, -12.25, 37), record("actor-0-1-2", 2, 301.0, 900)]);
    let odd =
        encoded(&[record("actor,\"0\"", 1, 1.0, 10), EpisodeStats { evaluation: true, ..record("eval", 2, 400.0, 1000) }, record("line\nbreak\rand é ☃", 3, 2.0, 20), record(" spaced ", 4, 3.0, 30)]);
    let extremes = encoded(&[EpisodeStats {
        policy_version: u64::MAX,
        episode_id: u64::MAX,
        episode_return: -f64::MAX,
        steps: u32::MAX,
        eqs: f64::MAX,
        ees: f64::MIN_POSITIVE / 4.0,
        distance_m: -0.0,
        shaded_time_s: 1e-300,
        ..record("x", 1, 0.0, 1)
    }]);
    let mut nan_then_more = encoded(&[record("a", 1, 1.0, 5), record("a", 2, 2.0, 6)]);
    nan_then_more.extend(encoded(&[EpisodeStats { episode_return: f64::NAN, ..record("a", 3, 0.0, 7) }, record("a", 4, 4.0, 8)]));
    let mut garbage = encoded(&[record("a", 1, 1.0, 5)]);
    garbage.push(vec![0xff, 0xff, 0xff, 0x0f]);
    garbage.extend(encoded(&[record("a", 2, 2.0, 6)]));
    let old_protocol = encoded(&[EpisodeStats { protocol_version: 0, ..record("a", 1, 1.0, 5) }]);
    let both_flags = encoded(&[EpisodeStats { terminal: true, truncated: true, ..record("a", 1, 1.0, 5) }]);
    vec![
        ("three-whole".into(), episode_stats_input(u16::MAX, &three)),
        ("three-torn-in-a-row".into(), episode_stats_input(200, &three)),
        ("three-torn-in-the-header".into(), episode_stats_input(10, &three)),
        ("odd-actor-ids-and-an-evaluation".into(), episode_stats_input(u16::MAX, &odd)),
        ("odd-actor-ids-torn".into(), episode_stats_input(170, &odd)),
        ("extremes".into(), episode_stats_input(u16::MAX, &extremes)),
        ("nan-return-ends-the-stream".into(), episode_stats_input(u16::MAX, &nan_then_more)),
        ("undecodable-frame-ends-the-stream".into(), episode_stats_input(u16::MAX, &garbage)),
        ("old-protocol".into(), episode_stats_input(u16::MAX, &old_protocol)),
        ("terminal-and-truncated".into(), episode_stats_input(0, &both_flags)),
        ("empty".into(), episode_stats_input(u16::MAX, &[])),
    ]
}

#[test]
fn episode_stats_corpus_and_regressions() {
    assert!(fuzz_corpus::replay_inputs("episode_stats", episode_stats) > 0, "no committed inputs for episode_stats");
}

#[test]
fn the_episode_stats_seeds_pass_the_harness() {
    for (name, data) in stats_seeds() {
        eprintln!("{name}");
        episode_stats(&data);
    }
}
