//! Bringing the workspace's binaries up to date from inside a test that runs them as processes
//! (the cluster, the actor against a real replay, the shared-memory examples, the learner
//! benchmark). Included by path (`#[path = "../../tests/common/workspace_build.rs"]`).
//!
//! It builds with the same target selection as `cargo test --workspace --all-targets`
//! (./test.sh), so features resolve identically, and without the variables cargo sets for the
//! test process ([`per_crate_variable`]), so that it does nothing when the suite's build is
//! current. Either difference reruns ring's build script, and then every crate and test above
//! it is recompiled: minutes for each test binary that builds (it once filled CI's disk).
//! Checking only that a binary exists would run a stale one left by an older checkout.

use std::path::Path;
use std::process::Command;
use std::sync::OnceLock;

/// Builds the workspace once per test binary, in the profile whose output directory is
/// `profile_dir` (`target/debug` or `target/release`); panics, saying why, if the build fails.
pub fn build_workspace_once(profile_dir: &Path) {
    static BUILT: OnceLock<Result<(), String>> = OnceLock::new();
    let built = BUILT.get_or_init(|| {
        let mut cmd = Command::new(env!("CARGO"));
        cmd.current_dir(env!("CARGO_MANIFEST_DIR")).args(["build", "--quiet", "--workspace", "--all-targets"]);
        for (name, _) in std::env::vars_os() {
            if name.to_str().is_some_and(per_crate_variable) {
                cmd.env_remove(name);
            }
        }
        if profile_dir.file_name().is_some_and(|n| n == "release") {
            cmd.arg("--release");
        }
        match cmd.status() {
            Ok(s) if s.success() => Ok(()),
            Ok(s) => Err(format!("`cargo build --workspace --all-targets` failed: {s}")),
            Err(e) => Err(format!("cannot run cargo: {e}")),
        }
    });
    if let Err(e) = built {
        panic!("{e}");
    }
}

/// A variable cargo sets for one crate's build script, compiler or test process
/// (`CARGO_MANIFEST_DIR`, `CARGO_PKG_NAME`, `OUT_DIR`, …). A build script that declares
/// `rerun-if-env-changed` on one (ring's does, on eleven) is compared with the value in cargo's
/// own environment: inherited from a test, it differs from the suite's build, which had none,
/// and the build script reruns. `deploy/images.sh` drops the same names.
pub fn per_crate_variable(name: &str) -> bool {
    const PREFIXES: [&str; 5] = ["CARGO_PKG_", "CARGO_MANIFEST_", "CARGO_CRATE_", "CARGO_BIN_EXE_", "CARGO_CFG_"];
    const NAMES: [&str; 6] = ["OUT_DIR", "CARGO_TARGET_TMPDIR", "CARGO_PRIMARY_PACKAGE", "CARGO_BIN_NAME", "CARGO_RUSTC_CURRENT_DIR", "CARGO_MAKEFLAGS"];
    PREFIXES.iter().any(|p| name.starts_with(p)) || NAMES.contains(&name)
}
