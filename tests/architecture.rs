//! The crates follow the data (docs/architecture.md): which workspace crate may depend on which,
//! read from `cargo metadata`, and libtorch reachable only from the learner.
//!
//! ```text
//!   proto ◄── net ◄── replay            sim ◄── actor ──► net
//!               ▲◄── learner-config ◄── learner (tch)     sim, proto ◄── plots
//!   cli (mapless): everything but the learner        tests: everything
//! ```

use std::collections::{BTreeMap, BTreeSet};
use std::process::Command;

use serde_json::Value;

/// The workspace crates each crate may depend on, in any section (normal, build, dev).
const ALLOWED: &[(&str, &[&str])] = &[
    ("mapless-proto", &[]),
    ("mapless-sim", &[]),
    // pictures of the simulator's maps and episodes, and training curves; proto only for the
    // workspace's one atomic file write (`mapless_proto::atomic_file`), no wire types
    ("mapless-plots", &["mapless-sim", "mapless-proto"]),
    ("mapless-net", &["mapless-proto"]),
    ("mapless-replay", &["mapless-proto", "mapless-net"]),
    ("mapless-actor", &["mapless-proto", "mapless-sim", "mapless-net"]),
    ("mapless-learner-config", &["mapless-proto", "mapless-net"]),
    ("mapless-learner", &["mapless-proto", "mapless-net", "mapless-learner-config"]),
    ("mapless-cli", &["mapless-proto", "mapless-sim", "mapless-plots", "mapless-net", "mapless-replay", "mapless-actor", "mapless-learner-config"]),
];

fn metadata(no_deps: bool) -> Value {
    let run = |offline: bool| {
        let cargo = std::env::var("CARGO").unwrap_or_else(|_| "cargo".into());
        let mut cmd = Command::new(cargo);
        cmd.args(["metadata", "--format-version", "1", "--locked"]).current_dir(env!("CARGO_MANIFEST_DIR"));
        if offline {
            cmd.arg("--offline");
        }
        if no_deps {
            cmd.arg("--no-deps");
        }
        cmd.output().expect("run cargo metadata")
    };
    // The whole resolve names crates of other platforms (anstyle-wincon, for Windows) that a
    // build here never downloads: offline first, then, on a fresh cargo home, from the registry.
    let mut out = run(true);
    if !out.status.success() {
        out = run(false);
    }
    assert!(out.status.success(), "cargo metadata failed: {}", String::from_utf8_lossy(&out.stderr));
    serde_json::from_slice(&out.stdout).expect("cargo metadata JSON")
}

#[test]
fn no_crate_depends_against_the_data_flow() {
    let meta = metadata(true);
    let packages = meta["packages"].as_array().expect("packages");
    let workspace: BTreeSet<String> = packages.iter().map(|p| p["name"].as_str().unwrap().to_owned()).collect();
    let allowed: BTreeMap<&str, &[&str]> = ALLOWED.iter().copied().collect();
    let mut wrong = Vec::new();
    for p in packages {
        let name = p["name"].as_str().unwrap();
        if name == "mapless-tests" {
            continue; // the integration crate may use every crate
        }
        let Some(ok) = allowed.get(name) else {
            wrong.push(format!("{name}: a crate the architecture test does not know; add it to ALLOWED and docs/architecture.md"));
            continue;
        };
        for d in p["dependencies"].as_array().unwrap() {
            let dep = d["name"].as_str().unwrap();
            if workspace.contains(dep) && !ok.contains(&dep) {
                wrong.push(format!("{name} → {dep} ({})", d["kind"].as_str().unwrap_or("normal")));
            }
        }
    }
    assert!(wrong.is_empty(), "edges against the data flow:\n  {}", wrong.join("\n  "));
}

#[test]
fn only_the_learner_reaches_libtorch() {
    let meta = metadata(false);
    let name_of: BTreeMap<&str, &str> = meta["packages"].as_array().unwrap().iter().map(|p| (p["id"].as_str().unwrap(), p["name"].as_str().unwrap())).collect();
    // Normal and build dependencies only: what ends up in the package's own library and binaries.
    let mut deps: BTreeMap<&str, Vec<&str>> = BTreeMap::new();
    for node in meta["resolve"]["nodes"].as_array().unwrap() {
        let id = node["id"].as_str().unwrap();
        let linked =
            node["deps"].as_array().unwrap().iter().filter(|d| d["dep_kinds"].as_array().unwrap().iter().any(|k| k["kind"].as_str() != Some("dev"))).map(|d| d["pkg"].as_str().unwrap()).collect();
        deps.insert(id, linked);
    }
    let reaches_torch = |root: &str| {
        let mut seen = BTreeSet::new();
        let mut todo = vec![root];
        while let Some(id) = todo.pop() {
            if !seen.insert(id) {
                continue;
            }
            if matches!(name_of[id], "torch-sys" | "tch") {
                return true;
            }
            todo.extend(deps.get(id).into_iter().flatten().copied());
        }
        false
    };
    for (id, name) in &name_of {
        let expect = matches!(*name, "mapless-learner" | "mapless-tests");
        if name.starts_with("mapless-") {
            assert_eq!(reaches_torch(id), expect, "{name} {} libtorch", if expect { "should reach" } else { "must not reach" });
        }
    }
}
