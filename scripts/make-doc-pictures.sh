#!/usr/bin/env bash
# Regenerates the pictures in docs/img/ with the `mapless` command: every built-in map and two
# rollouts of the built-in reactive driver (env1 with the exploration reward, outdoor20 with the
# search-and-rescue reward). Works from any directory.
set -euo pipefail
root="$(cd -- "$(dirname -- "${BASH_SOURCE[0]}")/.." && pwd -P)"
cd "$root"
cargo build --release --locked -p mapless-cli
bin="$root/target/release/mapless"
img="$root/docs/img"
mkdir -p "$img"
for m in env1 env2 env3 outdoor20; do
    "$bin" maps show "$m" --out "$img/$m.png"
done
tmp="$(mktemp -d)"
trap 'rm -rf "$tmp"' EXIT
"$bin" rollout --map env1 --seed 0 --out "$tmp/env1"
cp "$tmp/env1/trajectory.png" "$img/rollout-env1-wander.png"
"$bin" rollout --map outdoor20 --reward search_and_rescue --seed 3 --out "$tmp/outdoor20"
cp "$tmp/outdoor20/trajectory.png" "$img/rollout-outdoor20-wander.png"
