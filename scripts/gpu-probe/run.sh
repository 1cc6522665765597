#!/usr/bin/env bash
# CUDA probe of the mapless learner, for a GPU machine without Rust: `bash gpu/run.sh` from the
# repository root. The binaries beside this script were built against PyTorch 2.11.0 (cu130)
# and load the machine's own torch 2.11 libraries (found through python3 below).
# Results: $OUT/log.txt (everything), $OUT/bench.jsonl (bench JSON lines), /tmp/mrun (train run).
# Env knobs: OUT, PYTHON, BENCH_SECONDS (default 2), TRAIN_MINUTES (whole minutes, default 2), TRAIN_ACTORS (default 8),
# LEARNER_DEVICE (train only, default cuda), SKIP_TRAIN=1.
set -uo pipefail
HERE="$(cd "$(dirname "${BASH_SOURCE[0]}")" && pwd)"
OUT="${OUT:-$PWD/gpu-out}"
mkdir -p "$OUT"
exec > >(tee -a "$OUT/log.txt") 2>&1
BENCH_SECONDS="${BENCH_SECONDS:-2}"
TRAIN_MINUTES="${TRAIN_MINUTES:-2}"
TRAIN_ACTORS="${TRAIN_ACTORS:-8}"
LEARNER_DEVICE="${LEARNER_DEVICE:-cuda}"
T0=$(date +%s)
RESULTS=()
note() { RESULTS+=("$*"); echo "### $*"; }
hdr() { echo; echo "=================== $* (t=$(( $(date +%s) - T0 )) s)"; }

hdr "machine"
nvidia-smi -L || echo "nvidia-smi -L failed"
nvidia-smi --query-gpu=name,driver_version,memory.total --format=csv,noheader || true
echo "cores: $(nproc)"

hdr "torch libraries"
PY=""
for c in "${PYTHON:-}" /opt/torch/.venv/bin/python3 python3; do
    [ -n "$c" ] || continue
    if "$c" -c 'import torch' >/dev/null 2>&1; then PY="$c"; break; fi
done
if [ -z "$PY" ]; then echo "no python3 that imports torch: set PYTHON=/path/to/python3"; exit 1; fi
TORCH_DIR="$("$PY" -c 'import torch,os;print(os.path.dirname(torch.__file__))' 2>/dev/null)"
SITE="$(dirname "$TORCH_DIR")"
NV_LIBS="$(ls -d "$SITE"/nvidia/*/lib 2>/dev/null | paste -sd: -)"
export LD_LIBRARY_PATH="$TORCH_DIR/lib${NV_LIBS:+:$NV_LIBS}${LD_LIBRARY_PATH:+:$LD_LIBRARY_PATH}"
echo "python: $PY"
echo "LD_LIBRARY_PATH=$LD_LIBRARY_PATH"
"$PY" -c 'import torch;print("python torch", torch.__version__, "cuda", torch.version.cuda, "available", torch.cuda.is_available(), torch.cuda.get_device_name(0) if torch.cuda.is_available() else "")' 2>&1 | grep -v UserWarning | grep -v '_conversion_method' || true
echo "binaries built against torch 2.11.0; this machine has $("$PY" -c 'import torch;print(torch.__version__)' 2>/dev/null)"

hdr "ldd gpu/mapless-learner"
MISSING="$(ldd "$HERE/mapless-learner" | grep -i 'not found')"
if [ -n "$MISSING" ]; then echo "$MISSING"; note "ldd: libraries not found (see above)"; else echo "no missing libraries"; fi
ldd "$HERE/mapless-learner" | grep -E 'libtorch|libc10|cudart|cublas\.|libcudnn\.' || true

hdr "cuda test (learner/tests/cuda.rs)"
timeout 180 "$HERE/cuda-test" --nocapture --test-threads=1 2>&1 | tee "$OUT/cuda-test.txt"
rc=${PIPESTATUS[0]}
if grep -q 'skipped' "$OUT/cuda-test.txt"; then
    note "CUDA TEST: SKIPPED -- libtorch saw no CUDA device (the probe FAILED), rc=$rc"
elif [ "$rc" -eq 0 ] && grep -q 'test result: ok. 1 passed' "$OUT/cuda-test.txt"; then
    note "CUDA TEST: PASSED on the GPU (DDPG, TD3, SAC: 10 updates each on cuda:0)"
else
    note "CUDA TEST: FAILED rc=$rc"
fi

hdr "learner bench -> $OUT/bench.jsonl"
: > "$OUT/bench.jsonl"
bench() { # device threads batch hidden
    echo "--- bench device=$1 threads=$2 batch=$3 hidden=$4"
    timeout 120 "$HERE/mapless-learner" bench --json --device "$1" --threads "$2" --batch-size "$3" --hidden-width "$4" \
        --algos ddpg,td3,sac --seconds "$BENCH_SECONDS" | tee -a "$OUT/bench.jsonl"
    local r=${PIPESTATUS[0]}
    [ "$r" -eq 0 ] || note "bench device=$1 batch=$3 hidden=$4 FAILED rc=$r"
}
bench cpu 1,8 128 256
bench cpu 8 1024 256
bench cuda 1 128 256
bench cuda 1 1024 256
bench cuda 1 4096 256
bench cuda 1 1024 1024
echo "--- updates/s (algo device threads batch hidden: value)"
"$PY" - "$OUT/bench.jsonl" <<'EOF' || true
import json, sys
for line in open(sys.argv[1]):
    try: r = json.loads(line)
    except Exception: continue
    if r.get("bench") == "learner.updates_per_s":
        c = r["config"]
        print(f'{c["algo"]:5s} {c["device"]:5s} t={c["threads"]:<2} batch={c["batch"]:<5} hidden={c["hidden"]:<5} {r["value"]:10.1f} updates/s  ({c["update"]})')
EOF

if [ "${SKIP_TRAIN:-0}" != 1 ] && [ -x "$HERE/mapless" ] && [ -x "$HERE/mapless-actor" ] && [ -x "$HERE/mapless-replay" ]; then
    hdr "mapless train --preset env1-sac --minutes $TRAIN_MINUTES --actors $TRAIN_ACTORS (x4 vehicles), learner on $LEARNER_DEVICE -> /tmp/mrun"
    # halfway through: which processes hold GPU memory (the learner should)
    ( sleep $(( TRAIN_MINUTES * 30 )); echo "--- nvidia-smi compute apps (mid-run):"; \
      nvidia-smi --query-compute-apps=pid,process_name,used_memory --format=csv 2>&1 ) &
    SMI_PID=$!
    timeout $(( TRAIN_MINUTES * 60 + 150 )) "$HERE/mapless" train --preset env1-sac --force --minutes "$TRAIN_MINUTES" --run "/tmp/mrun" \
        --actors "$TRAIN_ACTORS" --set learner.device="$LEARNER_DEVICE" --set eval.episodes=0 --set replay_persistence=false </dev/null 2>&1
    rc=${PIPESTATUS[0]}
    if [ "$rc" -eq 0 ]; then wait "$SMI_PID" 2>/dev/null; note "train: exit 0 (learner on $LEARNER_DEVICE)"; else
        kill "$SMI_PID" 2>/dev/null; note "train: FAILED rc=$rc"; echo "--- tail of /tmp/mrun/logs/learner.log:"; tail -n 30 "/tmp/mrun/logs/learner.log" 2>/dev/null || true
    fi
    echo "--- /tmp/mrun/summary.json"
    cat "/tmp/mrun/summary.json" 2>/dev/null && echo || echo "(no summary.json)"
    echo "--- learner device in the run's config:"
    grep -rn 'device' "/tmp/mrun/learner.yaml" 2>/dev/null || true
fi

hdr "done"
for r in "${RESULTS[@]}"; do echo "  $r"; done
echo "total $(( $(date +%s) - T0 )) s; results in $OUT"
