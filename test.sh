#!/usr/bin/env bash
# mapless — the whole test suite.
#
# Installs what the tests need (torch 2.13.0 from PyPI into the git-ignored .torch/, for the
# learner's tch 0.26; see scripts/setup-torch.sh), checks the formatting (rustfmt.toml) and the
# lints (clippy, warnings denied; [workspace.lints] in Cargo.toml), then runs every test of every crate: unit
# and integration tests, the CLI end to end, and the criterion benches once each in test mode
# (so they keep compiling and running), then doc tests.
#
# Works from any directory; idempotent. CI (`.ci/run`) runs exactly this.
set -euo pipefail
root="$(cd -- "$(dirname -- "${BASH_SOURCE[0]}")" && pwd -P)"
cd "$root"
command -v cargo >/dev/null || { echo "test.sh: cargo not found; install Rust from https://rustup.rs" >&2; exit 1; }
bash "$root/scripts/setup-torch.sh"
# CI builds once from scratch: incremental caches would only take disk (gigabytes).
if [ "${CI:-}" = true ]; then export CARGO_INCREMENTAL=0; fi
cargo fmt --all --check
cargo clippy --locked --workspace --all-targets -- -D warnings
cargo test --locked --workspace --all-targets
cargo test --locked --workspace --doc
