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

// ---------------------------------------------------------------------------------------------
// episode_stats: the collector's records, episodes.csv, and a resume after a torn write
// ---------------------------------------------------------------------------------------------

/// Harness of the `episode_stats` target: the bytes an actor sends to a run's statistics
/// collector (`StatsService.Report`, served by `mapless train` and by `mapless monitor` beside a
/// compose cluster), recorded into a run's `episodes.csv`, which a crash may tear and a
/// `--resume` reads back.
///
/// ```text
///   episode_stats   cut u16 (LE) | frame* ;  frame = len u16 (LE) | len bytes (a protobuf EpisodeStats)
/// ```
///
/// Each frame is decoded and validated as the collector does ([`mapless_net::stats::validate`]):
/// the first frame that does not decode or breaks the contract ends the stream, and the records
/// before it stay recorded. Valid training records become rows of `episodes.csv`, numbered
/// after the last; evaluation records do not. Then a crash cuts the file to `cut` bytes (0xFFFF:
/// no crash), and the run resumes (`Episodes::open`, as `mapless train --resume`). Checked:
/// - the rows read back are exactly the rows whose line the cut left whole, field for field
///   (an actor id is the peer's: quotes, commas and odd characters stay in their field), and
///   no line is skipped as unreadable;
/// - the order-W moving averages after the resume are those of the rows kept;
/// - a record appended after the resume is numbered after the last row kept, and the file
///   then reads back as the kept rows plus that one, with nothing skipped.
pub fn episode_stats(data: &[u8]) {
    use crate::train::episodes::{EpisodeRow, Episodes, averages, read_episodes};
    use mapless_proto::v1::EpisodeStats;
    use prost::Message;

    let Some((cut, data)) = data.split_first_chunk::<2>() else { return };
    let cut = u16::from_le_bytes(*cut);
    // In memory where it can be (a disk-backed temp dir makes each input's files slow).
    let shm = std::path::Path::new("/dev/shm");
    let dir = if shm.is_dir() { tempfile::tempdir_in(shm) } else { tempfile::tempdir() }.expect("scratch directory");
    let path = dir.path().join("episodes.csv");
    let mut episodes = Episodes::open(dir.path()).expect("a fresh run's episodes");
    // Each recorded row with the file's length once its line was written.
    let mut written: Vec<(EpisodeRow, u64)> = Vec::new();
    for (i, frame) in frames(data).enumerate() {
        let Ok(e) = EpisodeStats::decode(frame) else { break };
        if mapless_net::stats::validate(&e).is_err() {
            break;
        }
        let evaluation = e.evaluation;
        episodes.record(e, i as f64 * 0.25).expect("a record written to episodes.csv");
        if !evaluation {
            let row = episodes.rows.last().expect("the row just recorded").clone();
            written.push((row, std::fs::metadata(&path).expect("episodes.csv").len()));
        }
    }
    assert_eq!(episodes.rows, written.iter().map(|(r, _)| r.clone()).collect::<Vec<_>>(), "rows in memory differ from the training records");
    drop(episodes);

    // A crash tears the file at `cut` bytes.
    let len = std::fs::metadata(&path).expect("episodes.csv").len();
    let kept_len = if cut == u16::MAX { len } else { u64::from(cut) % (len + 1) };
    std::fs::OpenOptions::new().write(true).open(&path).and_then(|f| f.set_len(kept_len)).expect("cut episodes.csv");
    let kept: Vec<EpisodeRow> = written.iter().filter(|(_, end)| *end <= kept_len).map(|(r, _)| r.clone()).collect();

    let mut resumed = Episodes::open(dir.path()).expect("a torn episodes.csv opens");
    assert_eq!(resumed.rows, kept, "a resume read back other rows than those whose line was whole");
    for w in [1, 3, 50] {
        let (a, b) = (resumed.averages(w), averages(&kept, w));
        assert!(same(a.0, b.0) && same(a.1, b.1), "order-{w} averages after the resume: {a:?}, of the rows kept: {b:?}");
    }
    let next =
        EpisodeStats { protocol_version: mapless_proto::v1::ProtocolVersion::V1 as i32, actor_id: "actor-after-resume".into(), episode_id: 1, terminal: true, steps: 7, ..EpisodeStats::default() };
    resumed.record(next, 1.0).expect("append after the resume");
    let expected_episode = kept.last().map_or(1, |r| r.episode + 1);
    assert_eq!(resumed.rows.last().map(|r| r.episode), Some(expected_episode), "the appended row's number");
    let after = resumed.rows.clone();
    drop(resumed);
    let (back, bad) = read_episodes(&path);
    assert_eq!(bad, 0, "episodes.csv after a resume and an append has unreadable lines");
    assert_eq!(back, after, "episodes.csv after a resume and an append reads back other rows");
}

/// Equal, or both NaN.
fn same(a: f64, b: f64) -> bool {
    a == b || (a.is_nan() && b.is_nan())
}

/// Splits `data` into frames of `len u16 (LE) | len bytes` (the last one cut short if the data
/// ends early).
fn frames(mut data: &[u8]) -> impl Iterator<Item = &[u8]> {
    std::iter::from_fn(move || {
        let (len, rest) = data.split_first_chunk::<2>()?;
        let (frame, rest) = rest.split_at(usize::from(u16::from_le_bytes(*len)).min(rest.len()));
        data = rest;
        Some(frame)
    })
}

/// `cut` and `frames` as [`episode_stats`] reads them (for writing seeds).
pub fn episode_stats_input(cut: u16, frames: &[Vec<u8>]) -> Vec<u8> {
    let mut out = cut.to_le_bytes().to_vec();
    for f in frames {
        let f = &f[..f.len().min(usize::from(u16::MAX))];
        out.extend_from_slice(&u16::try_from(f.len()).expect("clamped").to_le_bytes());
        out.extend_from_slice(f);
    }
    out
}
