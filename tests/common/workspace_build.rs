//! Bringing the workspace's binaries up to date from inside a test that runs them as processes
//! (the cluster, the actor against a real replay, the shared-memory examples, the learner
//! benchmark). Included by path (`#[path = "../../tests/common/workspace_build.rs"]`).
//!
//! It builds with the same target selection as `cargo test --workspace --all-targets`
//! (./test.sh), so features resolve identically and this only relinks, or does nothing. A
//! narrower `-p <crate>` build resolves features differently and reruns ring's build script,
//! which then makes the next workspace build recompile and relink every crate and test above
//! it (minutes, and gigabytes of disk: it filled CI's). Checking only that a binary exists would
//! run a stale one left by an older checkout.

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
