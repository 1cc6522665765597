#!/usr/bin/env bash
# mapless — the main job, on an embedded default.
#
# Today (issue 2): builds the `mapless` command and drives one simulated 1000-step episode in
# the paper's first environment (env1) with the built-in reactive driver, writing the
# trajectory picture (EQS cells, rings) and the episode's numbers to runs/demo/. Later issues
# turn this into local actor–learner training with SAC on env1.
#
# Works from any directory; idempotent (rebuilds only what changed, overwrites runs/demo/).
# Extra arguments go to `mapless rollout`, e.g. `./run.sh --map outdoor20 --reward sar`.
set -euo pipefail
root="$(cd -- "$(dirname -- "${BASH_SOURCE[0]}")" && pwd -P)"
cd "$root"
command -v cargo >/dev/null || { echo "run.sh: cargo not found; install Rust from https://rustup.rs" >&2; exit 1; }
# `mapless` links the learner, hence libtorch: install torch 2.13.0 into .torch/ (once).
bash "$root/scripts/setup-torch.sh"
echo "run.sh: building mapless (release)…"
cargo build --release --locked -p mapless-cli
exec "$root/target/release/mapless" rollout --map env1 --steps 1000 --seed 0 --out "$root/runs/demo" "$@"
