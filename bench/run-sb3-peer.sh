#!/usr/bin/env bash
# Side-by-side: `mapless bench learner` vs Stable-Baselines3 (and a CleanRL-style copy) SAC/TD3/DDPG
# gradient updates per second on CPU with 1 and 2 threads, the paper's sizes (obs 17, act 2,
# 2x256 hidden, batch 128). Idempotent; run from anywhere. See bench/sb3_peer.py for what is timed.
#   SECONDS_PER_CONFIG=5 (timed seconds per algorithm and thread count, both sides)
#   ROUNDS=3 (peer, then ours, this many times in turn; the table gives each side's median and
#     range, so a slow minute on a shared machine moves one sample, not the ratio)
#   THREADS="1 2" (peer thread counts)   PEER_ONLY=1 (skip building/running ours)
#   RUN_PREFIX="chrt -f 10" (prefix for both measured commands; on a shared machine, as root,
#     real-time priority gives both sides near-exclusive cores; nice does not help across cgroups)
#   PEER_FTZ=1 (the peer runs with torch.set_flush_denormal(True); see sb3_peer.py; the table
#     names its columns sb3+ftz, cleanrl+ftz)
#   Extra arguments go to sb3_peer.py (e.g. --impls sb3 --algos sac).
set -euo pipefail

BENCH_DIR="$(cd "$(dirname "${BASH_SOURCE[0]}")" && pwd)"
ROOT="$(dirname "$BENCH_DIR")"
SB3_DIR="$BENCH_DIR/.sb3"   # git-ignored (bench/.gitignore)
OUT="$BENCH_DIR/out"
SECS="${SECONDS_PER_CONFIG:-5}"
ROUNDS="${ROUNDS:-3}"
THREADS="${THREADS:-1 2}"
read -r -a THREAD_LIST <<< "$THREADS"
read -r -a PREFIX <<< "${RUN_PREFIX:-}"
PEER_ARGS=()
[[ "${PEER_FTZ:-0}" == 1 ]] && PEER_ARGS+=(--flush-denormal)
# Pure-Python wheels plus numpy, installed with --no-deps next to the repository's torch 2.13.0
# (.torch/venv, from scripts/setup-torch.sh), so torch is never downloaded twice. This is the
# complete runtime set for SB3's SAC/TD3/DDPG (typing_extensions comes with torch).
PINS=(stable-baselines3==2.9.2 gymnasium==1.4.0 cloudpickle==3.1.2 farama-notifications==0.0.6 numpy==2.2.6)

# 1. torch (shared with the learner's build), then the peer's packages in bench/.sb3.
PY="$ROOT/.torch/venv/bin/python"
if [[ ! -x "$PY" ]]; then
    "$ROOT/scripts/setup-torch.sh"
fi
if [[ "$(cat "$SB3_DIR/.pins" 2>/dev/null)" != "${PINS[*]}" ]]; then
    rm -rf "$SB3_DIR"
    "$PY" -m pip install --quiet --disable-pip-version-check --no-deps --target "$SB3_DIR" "${PINS[@]}"
    echo "${PINS[*]}" > "$SB3_DIR/.pins"
fi
export PYTHONPATH="$SB3_DIR${PYTHONPATH:+:$PYTHONPATH}"
mkdir -p "$OUT"

# 2. Our CLI, if it has `bench learner` (guarded: the learner bench may not exist yet).
MAPLESS="$ROOT/target/release/mapless"
HAVE_OURS=0
if [[ "${PEER_ONLY:-0}" != 1 ]]; then
    # From the repository root, so cargo reads .cargo/config.toml (where libtorch is).
    (cd "$ROOT" && cargo build --release --locked --quiet -p mapless-cli -p mapless-learner) \
        || { echo "run-sb3-peer.sh: building mapless failed" >&2; exit 1; }
    if [[ -x "$ROOT/target/release/mapless-learner" ]] && "$MAPLESS" bench learner --help > /dev/null 2>&1; then
        HAVE_OURS=1
    else
        echo "== ours: skipped (no \`mapless bench learner\` subcommand in this build)" >&2
    fi
fi

# 3. Both measurements, one after the other so they never share the cores, ROUNDS times in turn.
OURS_ARGS=(--json)
if [[ "$HAVE_OURS" == 1 ]] && "$MAPLESS" bench learner --help 2>&1 | grep -q -- '--seconds'; then
    OURS_ARGS+=(--seconds "$SECS")
fi
: > "$OUT/sb3-peer.jsonl"
: > "$OUT/learner-ours.jsonl"
for ((round = 1; round <= ROUNDS; round++)); do
    echo "== round $round of $ROUNDS; load: $(uptime)"
    echo "== peer: PYTHONPATH=$SB3_DIR ${PREFIX[*]} $PY $BENCH_DIR/sb3_peer.py --seconds $SECS --threads $THREADS ${PEER_ARGS[*]} $*"
    ${PREFIX[@]+"${PREFIX[@]}"} "$PY" "$BENCH_DIR/sb3_peer.py" --seconds "$SECS" --threads "${THREAD_LIST[@]}" ${PEER_ARGS[@]+"${PEER_ARGS[@]}"} "$@" | tee -a "$OUT/sb3-peer.jsonl"
    if [[ "$HAVE_OURS" == 1 ]]; then
        # The subcommand itself covers 1 and 2 threads (issue 4).
        echo "== ours: ${PREFIX[*]} $MAPLESS bench learner ${OURS_ARGS[*]}"
        ${PREFIX[@]+"${PREFIX[@]}"} "$MAPLESS" bench learner "${OURS_ARGS[@]}" | tee -a "$OUT/learner-ours.jsonl"
    fi
done
echo "== load: $(uptime)"

# 4. The comparison, matched by (algorithm, threads). Accepts flat lines or the CLI's
#    {"bench", "config": {...}, "value", "unit"} shape.
[[ "$HAVE_OURS" == 1 ]] || exit 0
"$PY" - "$OUT/learner-ours.jsonl" "$OUT/sb3-peer.jsonl" <<'EOF'
import json, sys
def rows(path, bench="learner.updates_per_s"):
    for line in open(path):
        if line.startswith("{"):
            r = json.loads(line)
            if r.get("bench", "learner") not in (bench, "learner"):
                continue  # ours also prints the matmul rate and the f32 ceiling
            r.update(r.get("config") or {})
            algo = str(r.get("algo") or r.get("bench", "").rsplit(".", 1)[-1]).lower()
            value = r.get("updates_per_s", r.get("value"))
            if algo and value is not None and "threads" in r:
                impl = r.get("impl", "mapless") + ("+ftz" if r.get("flush_denormal") else "")
                yield impl, algo, int(r["threads"]), float(value)
from statistics import median
ours, ceiling, peer = {}, {}, {}
for _, a, t, v in rows(sys.argv[1]):
    ours.setdefault((a, t), []).append(v)  # one line per (algo, threads) and round
for _, a, t, v in rows(sys.argv[1], "learner.f32_ceiling_updates_per_s"):
    ceiling.setdefault((a, t), []).append(v)
for impl, a, t, v in rows(sys.argv[2]):
    peer.setdefault(impl, {}).setdefault((a, t), []).append(v)
def cell(vs):  # median, and the range when there is more than one round
    m = median(vs)
    return f"{m:,.1f}" + (f" ({min(vs):,.0f}-{max(vs):,.0f})" if len(vs) > 1 else "")
print()
impls = sorted(peer)
print(f"{'algo':>5} {'threads':>7} {'ours upd/s':>19} {'f32 ceiling':>11} " + " ".join(f"{i + ' upd/s':>19} {'ours/' + i:>10} {'ceiling/' + i:>13}" for i in impls))
for key in sorted(ours, key=lambda k: (["sac", "td3", "ddpg"].index(k[0]) if k[0] in ("sac", "td3", "ddpg") else 9, k[1])):
    o = median(ours[key])
    c = median(ceiling[key]) if key in ceiling else None
    cells = []
    for i in impls:
        ps = peer[i].get(key)
        if ps:
            p = median(ps)
            cells.append(f"{cell(ps):>19} {o / p:>9.2f}x {(f'{c / p:.2f}x' if c else '-'):>13}")
        else:
            cells.append(f"{'-':>19} {'-':>10} {'-':>13}")
    print(f"{key[0]:>5} {key[1]:>7} {cell(ours[key]):>19} {(f'{c:,.1f}' if c else '-'):>11} " + " ".join(cells))
print(f"(medians over {max(len(v) for v in ours.values())} rounds, range in brackets; ratios are of the medians)")
print("(target of issue 4: ours/sb3 >= 3x for SAC; 'f32 ceiling' is the updates/s that this machine's")
print(" f32 matrix products alone allow (mapless_learner::ceiling), an estimate of the most any f32 code can do)")
EOF
