#!/usr/bin/env bash
# mapless — the main job, on an embedded default: train SAC on env1 with a local actor–learner
# cluster (replay service, learner, 2 actor processes, all on this machine, supervised), until
# the paper's SAC quality is reached — the order-50 moving averages of episode return and steps
# reach return ≥ 320 and steps ≥ 990 of 1000, and an evaluation of the newest policy reaches
# EQS 91 and EES 2.63 without a collision (Table III), judged from episode 1,000 on (about 7
# minutes on 2 cores) — or 30 minutes have passed. Then the
# final policy is evaluated on env1 and the pictures are in runs/env1-sac/ (curves.png,
# eval/episode-*.png).
#
# Works from any directory; idempotent (rebuilds only what changed; starts runs/env1-sac/ afresh).
# Extra arguments go to `mapless train`, e.g. `./run.sh --minutes 60 --actors 3`.
# Continue a run instead: `target/release/mapless train --resume runs/env1-sac`.
set -euo pipefail
root="$(cd -- "$(dirname -- "${BASH_SOURCE[0]}")" && pwd -P)"
cd "$root"
command -v cargo >/dev/null || { echo "run.sh: cargo not found; install Rust from https://rustup.rs" >&2; exit 1; }
# `mapless-learner` links libtorch: install torch 2.13.0 into .torch/ (once).
bash "$root/scripts/setup-torch.sh"
echo "run.sh: building mapless, mapless-learner, mapless-actor and mapless-replay (release)…"
cargo build --release --locked -p mapless-cli -p mapless-learner -p mapless-actor -p mapless-replay --bins
exec "$root/target/release/mapless" train --preset env1-sac --run "$root/runs/env1-sac" --force --minutes 30 "$@"
