//! The `mapless` binary end to end: maps pictures, a rollout, the sim and learner benchmarks' JSON lines,
//! and clear errors for bad input.

#[path = "../../tests/common/workspace_build.rs"]
mod workspace_build;

use std::path::{Path, PathBuf};
use std::process::Command;

fn mapless(args: &[&str]) -> std::process::Output {
    Command::new(env!("CARGO_BIN_EXE_mapless")).args(args).env("RUST_LOG", "warn").output().expect("mapless runs")
}

fn tmp(name: &str) -> PathBuf {
    let d = Path::new(env!("CARGO_TARGET_TMPDIR")).join("cli").join(name);
    let _ = std::fs::remove_dir_all(&d);
    std::fs::create_dir_all(&d).unwrap();
    d
}

fn png_size(path: &Path) -> (u32, u32) {
    let bytes = std::fs::read(path).unwrap();
    assert_eq!(&bytes[..8], b"\x89PNG\r\n\x1a\n", "{} is a PNG", path.display());
    let w = u32::from_be_bytes(bytes[16..20].try_into().unwrap());
    let h = u32::from_be_bytes(bytes[20..24].try_into().unwrap());
    (w, h)
}

#[test]
fn maps_show_draws_every_builtin_map() {
    let d = tmp("maps");
    for m in ["env1", "env2", "env3", "outdoor20"] {
        let out = d.join(format!("{m}.png"));
        let o = mapless(&["maps", "show", m, "--out", out.to_str().unwrap()]);
        assert!(o.status.success(), "{m}: {}", String::from_utf8_lossy(&o.stderr));
        let (w, h) = png_size(&out);
        assert!(w > 800 && h > 800, "{m}: {w}x{h}");
    }
}

#[test]
fn rollout_writes_a_trajectory_picture_and_episode_json() {
    let d = tmp("rollout");
    let o = mapless(&["rollout", "--map", "env2", "--steps", "300", "--seed", "4", "--out", d.to_str().unwrap(), "--json"]);
    assert!(o.status.success(), "{}", String::from_utf8_lossy(&o.stderr));
    let v: serde_json::Value = serde_json::from_slice(&o.stdout).unwrap();
    let steps = v["steps"].as_u64().unwrap();
    assert!((1..=300).contains(&steps));
    assert!(v["terminal"].as_bool().unwrap() || v["truncated"].as_bool().unwrap());
    assert!(v["eqs"].as_u64().unwrap() >= 1);
    png_size(&d.join("trajectory.png"));
    let file: serde_json::Value = serde_json::from_str(&std::fs::read_to_string(d.join("episode.json")).unwrap()).unwrap();
    assert_eq!(file, v);
}

#[test]
fn bench_sim_json_prints_one_object_per_scan_preset() {
    let o = mapless(&["bench", "sim", "--json", "--seconds", "0.05", "--vehicles", "4"]);
    assert!(o.status.success(), "{}", String::from_utf8_lossy(&o.stderr));
    let lines: Vec<serde_json::Value> = String::from_utf8(o.stdout).unwrap().lines().map(|l| serde_json::from_str(l).unwrap()).collect();
    let beams: Vec<u64> = lines.iter().map(|l| l["config"]["beams"].as_u64().unwrap()).collect();
    assert_eq!(beams, [7, 100, 1080]);
    for l in &lines {
        assert_eq!(l["bench"], "sim.vehicle_steps_per_s");
        assert_eq!(l["unit"], "steps/s");
        assert_eq!(l["config"]["map"], "env2");
        assert!(l["value"].as_f64().unwrap() > 0.0);
    }
}

#[test]
fn bench_learner_json_prints_rates_the_f32_ceiling_and_both_update_paths() {
    // `bench learner` runs the `mapless-learner` beside `mapless`.
    let dir = std::path::Path::new(env!("CARGO_BIN_EXE_mapless")).parent().unwrap().to_path_buf();
    workspace_build::build_workspace_once(&dir);
    let o = mapless(&["bench", "learner", "--json", "--seconds", "0.1", "--threads", "1", "--algos", "sac", "--autograd"]);
    assert!(o.status.success(), "{}", String::from_utf8_lossy(&o.stderr));
    let lines: Vec<serde_json::Value> = String::from_utf8(o.stdout).unwrap().lines().map(|l| serde_json::from_str(l).unwrap()).collect();
    let names: Vec<&str> = lines.iter().map(|l| l["bench"].as_str().unwrap()).collect();
    assert_eq!(names, ["learner.matmul_gflops", "learner.matmul_gflops", "learner.updates_per_s", "learner.f32_ceiling_updates_per_s", "learner.share_of_f32_ceiling", "learner.updates_per_s",]);
    assert_eq!(lines[0]["config"]["dtype"], "f32");
    assert_eq!(lines[1]["config"]["dtype"], "bf16");
    assert_eq!(lines[2]["config"]["update"], "fused");
    assert_eq!(lines[5]["config"]["update"], "autograd");
    // SAC at the paper's sizes: 266,862,592 FLOP of products per update (mapless_learner::ceiling).
    assert_eq!(lines[3]["config"]["flop_per_update"].as_f64(), Some(266_862_592.0));
    for l in &lines {
        assert!(l["value"].as_f64().unwrap() > 0.0, "{l}");
    }
}

#[test]
fn bad_map_input_is_a_clear_error_not_a_panic() {
    let d = tmp("bad");
    let bad = d.join("bad.yaml");
    std::fs::write(&bad, "format: mapless-vector-map/v1\nname: x\nbounds: {min: [0, 0], max: [1, 1]}\nobstacles:\n  - circle: {center: [0.5, 0.5], radius: 0}\n").unwrap();
    let o = mapless(&["maps", "show", bad.to_str().unwrap(), "--out", d.join("x.png").to_str().unwrap()]);
    assert_eq!(o.status.code(), Some(1));
    let err = String::from_utf8_lossy(&o.stderr);
    assert!(err.contains("bad.yaml") && err.contains("obstacle 0 (circle)"), "{err}");
    let o = mapless(&["rollout", "--map", "nowhere", "--out", d.to_str().unwrap()]);
    assert_eq!(o.status.code(), Some(1));
    assert!(String::from_utf8_lossy(&o.stderr).contains("unknown map `nowhere`"));
}

#[test]
fn rasterized_map_reloads_as_a_ros_map_with_the_same_obstacles() {
    let d = tmp("raster");
    let o = mapless(&["maps", "rasterize", "env2", "--resolution", "0.1", "--out", d.to_str().unwrap()]);
    assert!(o.status.success(), "{}", String::from_utf8_lossy(&o.stderr));
    let ros = mapless_sim::Map::load(&d.join("env2.yaml")).unwrap();
    let vec = mapless_sim::Map::builtin("env2").unwrap();
    assert_eq!(ros.bounds, vec.bounds);
    // A round median end (r = 1.2 at (15.4, 15)) is blocked, open floor is free in both.
    assert!(!ros.is_free(15.4, 15.0) && !vec.is_free(15.4, 15.0));
    assert!(ros.is_free(-18.0, 18.0) && vec.is_free(-18.0, 18.0));
    // A ray from (−18, −5) east meets the round end of lane 2's median at x = −16.6 in both (to
    // within a pixel).
    let (a, b) = (ros.scene(0.0, 2.0).cast_ray(-18.0, -5.0, 1.0, 0.0, 12.0), vec.scene(0.0, 2.0).cast_ray(-18.0, -5.0, 1.0, 0.0, 12.0));
    assert!((b - 1.4).abs() < 1e-3, "{b}");
    assert!((a - b).abs() <= 0.11, "{a} vs {b}");
}

#[test]
fn worlds_generate_writes_a_ros_map_a_picture_and_the_vector_form_and_show_draws_a_sheet() {
    let d = tmp("worlds");
    let o = mapless(&["worlds", "generate", "--family", "field", "--seed", "7", "--out", d.to_str().unwrap(), "--resolution", "0.1"]);
    assert!(o.status.success(), "{}", String::from_utf8_lossy(&o.stderr));
    for f in ["field-7.yaml", "field-7.pgm", "field-7.png", "field-7.vector.yaml"] {
        assert!(d.join(f).is_file(), "{f} missing");
    }
    // The ROS map and the vector form load; the vector form is the world `gen:field:7` names.
    let ros = mapless_sim::Map::load(&d.join("field-7.yaml")).unwrap();
    let vector = mapless_sim::Map::load(&d.join("field-7.vector.yaml")).unwrap();
    let named = mapless_sim::worlds::resolve("gen:field:7").unwrap();
    assert_eq!(ros.bounds, named.bounds);
    assert_eq!(vector.rasterize(0.1).unwrap(), named.rasterize(0.1).unwrap());
    assert!(!vector.shaded.is_empty(), "a field's canopies are in its vector form");
    // A contact sheet of three caves; an unknown family is an error naming the families.
    let sheet = d.join("caves.png");
    let o = mapless(&["worlds", "show", "--family", "cave", "--seeds", "0..3", "--out", sheet.to_str().unwrap()]);
    assert!(o.status.success(), "{}", String::from_utf8_lossy(&o.stderr));
    assert!(std::fs::metadata(&sheet).unwrap().len() > 10_000);
    let o = mapless(&["worlds", "show", "--family", "lava", "--out", sheet.to_str().unwrap()]);
    assert!(!o.status.success() && String::from_utf8_lossy(&o.stderr).contains("rooms, cave, hall, forest, field"));
}

#[test]
fn maps_stats_and_analyze_eqs_print_json() {
    // env1's largest minimum range keeps a parked car below the paper's 0.32 per step.
    let o = mapless(&["maps", "stats", "env1", "--grid", "0.5", "--headings", "12", "--json"]);
    assert!(o.status.success(), "{}", String::from_utf8_lossy(&o.stderr));
    let v: serde_json::Value = serde_json::from_slice(&o.stdout).unwrap();
    let b = &v["bounds"];
    assert!(b["standing_still_per_step"].as_f64().unwrap() < 0.32, "{v}");
    assert!(b["per_step"].as_f64().unwrap() > b["standing_still_per_step"].as_f64().unwrap());
    // The EQS analysis: every candidate reading against the paper's 12 rows, best first.
    let o = mapless(&["analyze", "eqs", "--trajectories", "40", "--json"]);
    assert!(o.status.success(), "{}", String::from_utf8_lossy(&o.stderr));
    let v: serde_json::Value = serde_json::from_slice(&o.stdout).unwrap();
    assert_eq!(v["rows"].as_array().unwrap().len(), 12);
    let readings = v["readings"].as_array().unwrap();
    assert_eq!(readings.len(), 28);
    assert!(readings.windows(2).all(|w| w[0]["rows_fitting"].as_u64() >= w[1]["rows_fitting"].as_u64()));
    assert!(mapless(&["analyze", "eqs", "--trajectories", "0"]).status.code() != Some(0));
}

/// The policies shipped in the repository's `policies/` (each a folder with its card).
fn shipped_policies() -> Vec<String> {
    let dir = Path::new(env!("CARGO_MANIFEST_DIR")).join("../policies");
    let mut names: Vec<String> =
        std::fs::read_dir(&dir).map(|r| r.filter_map(Result::ok).filter(|e| e.path().join("card.json").is_file()).map(|e| e.file_name().to_string_lossy().into_owned()).collect()).unwrap_or_default();
    names.sort();
    names
}

#[test]
fn every_shipped_policy_still_scores_what_its_card_records() {
    // The paper's SAC on env1 and the explore policy at least; `mapless policies check` reruns
    // each card's short deterministic evaluations and fails on any difference.
    let names = shipped_policies();
    assert!(names.iter().any(|n| n == "env1-sac"), "policies/ ships env1-sac (found {names:?})");
    let o = mapless(&["policies", "check"]);
    let out = String::from_utf8_lossy(&o.stdout);
    assert!(o.status.success(), "{out}\n{}", String::from_utf8_lossy(&o.stderr));
    for n in &names {
        assert!(out.contains(&format!("{n}: holds")), "{n} not checked: {out}");
    }
}

#[test]
fn a_shipped_policy_evaluates_and_drives_by_name_and_a_changed_card_fails_its_check() {
    let d = tmp("policies");
    let o = mapless(&["eval", "--policy", "env1-sac", "--map", "env3", "--episodes", "2", "--max-steps", "300", "--json", "--out", d.join("eval").to_str().unwrap()]);
    assert!(o.status.success(), "{}", String::from_utf8_lossy(&o.stderr));
    let v: serde_json::Value = serde_json::from_slice(&o.stdout).unwrap();
    assert_eq!(v["episodes"].as_array().unwrap().len(), 2);
    // Each episode says where it ended: the car there touches something exactly when the
    // episode ended in a collision (the simulator's own footprint test at that pose).
    let env3 = mapless_sim::World::new(mapless_sim::worlds::resolve("env3").unwrap(), mapless_sim::EnvConfig::default()).unwrap();
    for e in v["episodes"].as_array().unwrap() {
        let p: Vec<f64> = e["end_pose"].as_array().unwrap_or_else(|| panic!("no end pose: {e}")).iter().map(|x| x.as_f64().unwrap()).collect();
        assert_eq!(p.len(), 3, "{e}");
        assert_eq!(env3.collide.footprint_collides(p[0], p[1], p[2], &env3.footprint), e["collided"].as_bool().unwrap(), "{e}");
    }
    png_size(&d.join("eval/sheet.png"));
    let o = mapless(&["rollout", "--policy", "env1-sac", "--map", "env1", "--steps", "200", "--json", "--out", d.join("rollout").to_str().unwrap()]);
    assert!(o.status.success(), "{}", String::from_utf8_lossy(&o.stderr));
    let v: serde_json::Value = serde_json::from_slice(&o.stdout).unwrap();
    assert!(v["distance_m"].as_f64().unwrap() > 1.0, "the policy drives: {v}");
    // A card whose figures the policy no longer reaches fails `policies check`.
    let shelf = d.join("shelf/env1-sac");
    std::fs::create_dir_all(&shelf).unwrap();
    for f in ["config.yaml", "policy.safetensors", "card.json"] {
        std::fs::copy(Path::new(env!("CARGO_MANIFEST_DIR")).join("../policies/env1-sac").join(f), shelf.join(f)).unwrap();
    }
    let mut card: serde_json::Value = serde_json::from_str(&std::fs::read_to_string(shelf.join("card.json")).unwrap()).unwrap();
    // Keep only the short check rows (so that `--update` below stays quick).
    card["evaluations"].as_array_mut().unwrap().retain(|e| e["check"] == true);
    let check = card["evaluations"].as_array_mut().unwrap().iter_mut().find(|e| e["check"] == true).unwrap();
    check["mean_steps"] = serde_json::json!(check["mean_steps"].as_f64().unwrap() + 1.0);
    std::fs::write(shelf.join("card.json"), serde_json::to_string(&card).unwrap()).unwrap();
    let o = Command::new(env!("CARGO_BIN_EXE_mapless")).args(["policies", "check"]).env("MAPLESS_POLICIES", d.join("shelf")).env("RUST_LOG", "warn").output().unwrap();
    assert!(!o.status.success());
    let err = String::from_utf8_lossy(&o.stdout);
    assert!(err.contains("env1-sac on") && err.contains("mean steps"), "{err}");
    // `--update` reruns the card's evaluations, says what moved and writes it back: it holds again.
    let shelf_cmd = |args: &[&str]| Command::new(env!("CARGO_BIN_EXE_mapless")).args(args).env("MAPLESS_POLICIES", d.join("shelf")).env("RUST_LOG", "warn").output().unwrap();
    let o = shelf_cmd(&["policies", "check", "--update", "env1-sac"]);
    assert!(o.status.success(), "{}", String::from_utf8_lossy(&o.stderr));
    let out = String::from_utf8_lossy(&o.stdout);
    assert!(out.contains("env1-sac: updated") && out.contains("mean steps"), "{out}");
    assert!(shelf.join("card.md").exists() && d.join("shelf/README.md").exists());
    let o = shelf_cmd(&["policies", "check"]);
    assert!(o.status.success(), "{}{}", String::from_utf8_lossy(&o.stdout), String::from_utf8_lossy(&o.stderr));
    let o = mapless(&["eval", "--policy", "no-such-policy", "--map", "env3"]);
    assert!(!o.status.success());
    assert!(String::from_utf8_lossy(&o.stderr).contains("no shipped policy \"no-such-policy\""));
}
