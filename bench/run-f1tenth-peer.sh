#!/usr/bin/env bash
# Side-by-side: `mapless bench sim` vs an F1TENTH-gym-style LiDAR (bench/f1tenth_peer.py), both on
# one core, map env2, 7/100/1080 beams. Idempotent; run from anywhere. See bench/README.md.
#   SECONDS_PER_CONFIG=3 (timed seconds per preset, both sides)   PYTHON=python3 (for the venv)
set -euo pipefail

BENCH_DIR="$(cd "$(dirname "${BASH_SOURCE[0]}")" && pwd)"
ROOT="$(dirname "$BENCH_DIR")"
VENV="$BENCH_DIR/.venv"
OUT="$BENCH_DIR/out"
SECS="${SECONDS_PER_CONFIG:-3}"
PYTHON="${PYTHON:-python3}"
# Pinned set that installs as wheels on CPython 3.11 (numba 0.61.2 supports numpy < 2.3).
PINS=(numpy==2.2.6 scipy==1.15.3 llvmlite==0.44.0 numba==0.61.2)

# Single core on both sides (ours is single-threaded by construction).
export NUMBA_NUM_THREADS=1 OMP_NUM_THREADS=1 OPENBLAS_NUM_THREADS=1 MKL_NUM_THREADS=1

# 1. Python environment, reinstalled only when the pins change.
if [[ ! -x "$VENV/bin/python" ]]; then
    "$PYTHON" -m venv "$VENV"
fi
if [[ "$(cat "$VENV/.pins" 2>/dev/null)" != "${PINS[*]}" ]]; then
    "$VENV/bin/python" -m pip install --quiet --disable-pip-version-check "${PINS[@]}"
    echo "${PINS[*]}" > "$VENV/.pins"
fi

# 2. Our CLI, and env2 as a ROS map_server map for the peer.
# `mapless` (maps, bench sim) needs no libtorch.
(cd "$ROOT" && cargo build --release --locked --quiet -p mapless-cli)
MAPLESS="$ROOT/target/release/mapless"
mkdir -p "$OUT"
"$MAPLESS" maps rasterize env2 --resolution 0.05 --out "$OUT" >&2

# 3. Both measurements, one after the other so they never share the cores.
echo "== peer: $VENV/bin/python $BENCH_DIR/f1tenth_peer.py --map-yaml $OUT/env2.yaml --seconds $SECS"
"$VENV/bin/python" "$BENCH_DIR/f1tenth_peer.py" --map-yaml "$OUT/env2.yaml" --seconds "$SECS" | tee "$OUT/peer.jsonl"
echo "== ours: $MAPLESS bench sim --json --map env2 --seconds $SECS"
"$MAPLESS" bench sim --json --map env2 --seconds "$SECS" | tee "$OUT/ours.jsonl"

# 4. The comparison, matched by beam count.
"$VENV/bin/python" - "$OUT/ours.jsonl" "$OUT/peer.jsonl" <<'EOF'
import json, sys
def load(path):
    rows = [json.loads(line) for line in open(path) if line.startswith("{")]
    return {r["config"]["beams"]: r for r in rows}
ours, peer = load(sys.argv[1]), load(sys.argv[2])
print()
print(f"{'beams':>5} {'fov':>5} {'ours steps/s':>14} {'peer scans/s':>14} {'ours/peer':>10}")
for beams in sorted(ours.keys() & peer.keys()):
    o, p = ours[beams]["value"], peer[beams]["value"]
    print(f"{beams:>5} {peer[beams]['config']['fov_deg']:>4}° {o:>14,.0f} {p:>14,.0f} {o / p:>9.1f}x")
print("(peer = scan + noise + iTTC only; ours = full vehicle-step: dynamics, collision, reward, EQS)")
EOF
