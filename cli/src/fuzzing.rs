//! Harness of the `config_sources` coverage-guided fuzz target (`fuzz/` at the repository
//! root, run with `cargo +nightly fuzz run config_sources`; docs/reliability.md, "Fuzzing"). It
//! takes arbitrary bytes as a preset document and `--set` overrides, resolves them exactly as
//! `mapless train` does, and panics only when an invariant breaks, never on the input's account.
//! `cli/tests/fuzz_corpora.rs` replays the committed corpus and regression inputs through the
//! same function on stable.
//!
//! ```text
//!   config_sources   document (YAML) | 0x00 | KEY=VALUE \n KEY=VALUE \n …
//!                    (no 0x00: the whole input is the document, no --set)
//! ```
//!
//! A configuration that resolves must survive the trip a run makes through its folder: written
//! as `config.yaml`, read back as `--resume` reads it and resolved again, it is the same
//! configuration; and resolving a resolved configuration changes nothing. A `map` that names a
//! file is not resolved (that reads the file system; the `map_files` target covers map files).

use crate::train::config::{apply_sets, expand_shorthands, parse_config, run_document};

/// One input: see the module's documentation.
pub fn config_sources(data: &[u8]) {
    let (doc, sets) = match data.iter().position(|&b| b == 0) {
        Some(i) => (&data[..i], &data[i + 1..]),
        None => (data, &[][..]),
    };
    let (Ok(doc), Ok(sets)) = (std::str::from_utf8(doc), std::str::from_utf8(sets)) else { return };
    let sets: Vec<String> = sets.lines().filter(|l| !l.is_empty()).map(str::to_owned).collect();
    let Ok(mut doc) = serde_yaml::from_str::<serde_yaml::Value>(doc) else { return };
    if expand_shorthands(&mut doc, false).is_err() || apply_sets(&mut doc, &sets).is_err() {
        return;
    }
    let Ok(parsed) = parse_config(doc) else { return };
    if names_a_file(&parsed.map) {
        return;
    }
    let Ok(cfg) = parsed.resolve() else { return };
    check(&cfg);
}

/// The invariants of a configuration that resolved.
pub fn check(cfg: &crate::train::config::TrainConfig) {
    let again = cfg.clone().resolve().unwrap_or_else(|e| panic!("a resolved configuration no longer resolves: {e:#}"));
    assert_eq!(&again, cfg, "resolving a resolved configuration changed it");
    let text = serde_yaml::to_string(cfg).unwrap_or_else(|e| panic!("a resolved configuration does not serialise: {e}"));
    let back = run_document(&text).and_then(parse_config).and_then(|c| c.resolve()).unwrap_or_else(|e| panic!("config.yaml as written does not load back: {e:#}\n{text}"));
    assert_eq!(&back, cfg, "config.yaml does not load back to the same configuration:\n{text}");
}

/// A map spec that reads a file (a path), rather than a built-in map or a generated world.
fn names_a_file(map: &str) -> bool {
    map.split('+').any(|item| item.contains(['/', '\\', '.']))
}
