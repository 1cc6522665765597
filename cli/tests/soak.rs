//! The 30-second soak (`mapless bench soak --minutes 0.5`, issue 19 §2): the real replay and
//! learner under 64 insert streams, 4 samplers with priority updates and 64 weights
//! subscribers. It must pass its own checks (no stall, no failed request, no growth after the
//! warm-up), and its figures must show that every part did work.

#[path = "../../tests/common/workspace_build.rs"]
mod workspace_build;

use std::collections::HashMap;
use std::path::PathBuf;
use std::process::Command;

fn mapless() -> PathBuf {
    let exe = PathBuf::from(env!("CARGO_BIN_EXE_mapless"));
    workspace_build::build_workspace_once(exe.parent().unwrap());
    exe
}

#[test]
fn a_thirty_second_soak_of_64_streams_passes_and_every_part_works() {
    let dir = tempfile::tempdir().unwrap();
    let out_dir = dir.path().join("out");
    // A lower offered rate and a small table than the 10-minute figures: a debug build on a
    // shared 2-core machine, and the table must fill well inside the 30 s.
    let out = Command::new(mapless())
        .args(["bench", "soak", "--streams", "64", "--minutes", "0.5", "--rows-per-s", "6400", "--capacity", "20000", "--interval-s", "2", "--json"])
        .arg("--dir")
        .arg(dir.path().join("soak"))
        .arg("--out")
        .arg(&out_dir)
        .output()
        .unwrap();
    let stdout = String::from_utf8_lossy(&out.stdout);
    let stderr = String::from_utf8_lossy(&out.stderr);
    assert!(out.status.success(), "soak failed ({}):\n{stdout}\n{stderr}", out.status);
    let figures: HashMap<String, f64> =
        stdout.lines().filter_map(|l| serde_json::from_str::<serde_json::Value>(l).ok()).map(|v| (v["bench"].as_str().unwrap().to_owned(), v["value"].as_f64().unwrap_or(f64::NAN))).collect();
    let f = |k: &str| *figures.get(k).unwrap_or_else(|| panic!("no {k} in\n{stdout}"));
    // Paced at 6,400 rows/s: half of it acknowledged at least (the first seconds are
    // connecting, and a stream behind by a period starts afresh rather than catch up).
    assert!(f("soak.rows_per_s") > 3_200.0, "{stdout}");
    assert!(f("soak.rows_per_s") < 7_000.0, "pacing ignored: {stdout}");
    assert_eq!(f("soak.failures"), 0.0);
    assert!(f("soak.priority_updates") > 100.0, "{stdout}");
    assert!(f("soak.learner_updates_per_s") > 0.0, "{stdout}");
    // Every subscriber received the initial policy at least, and the learner published more:
    // at least half of them received a newer one too (all of them, on an unloaded machine).
    assert!(f("soak.weights_snapshots_received") >= 96.0, "{stdout}");
    assert!(f("soak.insert_latency_p99_ms").is_finite() && f("soak.sample_latency_p99_ms").is_finite(), "{stdout}");
    assert!(f("soak.replay_rss_max_mib") > 0.0 && f("soak.replay_threads_max") > 1.0 && f("soak.replay_open_files_max") > 64.0, "64 connections are open files: {stdout}");
    assert!(f("soak.replay_dir_max_mib") > 0.0, "persistence was on: {stdout}");
    // The CSV holds one row per sample, every 2 s.
    let rows = csv::Reader::from_path(out_dir.join("soak.csv")).unwrap().records().count();
    assert!((12..=16).contains(&rows), "{rows} CSV rows");
    assert!(std::fs::metadata(out_dir.join("soak.png")).unwrap().len() > 10_000, "the picture");
    // The replay persisted: its folder holds a snapshot or a log.
    assert!(dir.path().join("soak/replay").read_dir().unwrap().count() > 0);
}
