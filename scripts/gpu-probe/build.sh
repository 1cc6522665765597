#!/usr/bin/env bash
# Builds gpu/ (git-ignored): the mapless binaries linked against PyTorch 2.11.0 (cu130), plus
# run.sh, for a GPU machine that has that torch but no Rust toolchain and no network (the
# GPU machines lent to this project's sessions: see docs/learner.md, "CUDA"). There:
#
#     bash gpu/run.sh          # CUDA test, learner bench on CPU and CUDA, 2 min of training
#
# Why not the usual build: tch 0.26 binds libtorch 2.13.0, whose libraries (~4.7 GB with
# NVIDIA's) cannot travel to that machine; its own torch is 2.11.0. torch-sys 0.26's generated
# C++ wrapper calls 15 ATen functions that 2.11 lacks or declares differently (`_philox_*`,
# `_upsample_lanczos2d_aa*`, `_flash_attention_forward_no_dropout_inplace`,
# `_scaled_dot_product_attention_math_for_mps`); torch-2.11.patch makes them throw instead.
# mapless calls none of them. Nothing in the workspace changes: the build runs on a copy of
# the tracked files, with the patched torch-sys through `--config patch.crates-io...`.
#
# Environment: TORCH211_VENV (default .torch211/venv, git-ignored, ~4.6 GB), CARGO_TARGET_DIR
# (default target/gpu-probe). Idempotent; a second run rebuilds only what changed.
set -euo pipefail
root="$(cd -- "$(dirname -- "${BASH_SOURCE[0]}")/../.." && pwd -P)"
here="$root/scripts/gpu-probe"
venv="${TORCH211_VENV:-$root/.torch211/venv}"
work="$root/target/gpu-probe-src"
export CARGO_TARGET_DIR="${CARGO_TARGET_DIR:-$root/target/gpu-probe}"
say() { printf 'gpu-probe: %s\n' "$*"; }

if ! "$venv/bin/python" -c 'import importlib.metadata as m; assert m.version("torch").startswith("2.11.0")' 2>/dev/null; then
    say "installing torch 2.11.0 into $venv (PyPI; pulls NVIDIA's CUDA 13 wheels)"
    python3 -m venv "$venv"
    "$venv/bin/pip" install -q torch==2.11.0
fi
torch_dir="$(echo "$venv"/lib/python3.*/site-packages/torch)"
[[ -f "$torch_dir/lib/libtorch_cuda.so" ]] || { say "no libtorch_cuda.so under $torch_dir"; exit 1; }

say "copying the tracked files to $work"
rm -rf "$work/src" && mkdir -p "$work/src"
(cd "$root" && git ls-files -z | xargs -0 cp --parents -t "$work/src")
registry_src="$(ls -d "${CARGO_HOME:-$HOME/.cargo}"/registry/src/*/torch-sys-0.26.0 2>/dev/null | head -n1)"
if [[ -z "$registry_src" ]]; then
    (cd "$work/src" && cargo fetch --locked)
    registry_src="$(ls -d "${CARGO_HOME:-$HOME/.cargo}"/registry/src/*/torch-sys-0.26.0 | head -n1)"
fi
rm -rf "$work/torch-sys" && cp -r "$registry_src" "$work/torch-sys"
patch -s -p1 -d "$work/torch-sys" < "$here/torch-2.11.patch"

cd "$work/src"
export LIBTORCH="$torch_dir" LIBTORCH_CXX11_ABI=1 LIBTORCH_BYPASS_VERSION_CHECK=1
patch_cfg="patch.crates-io.torch-sys.path=\"$work/torch-sys\""
say "building against $torch_dir (release; $CARGO_TARGET_DIR)"
cargo build --release --config "$patch_cfg" -p mapless-cli -p mapless-learner -p mapless-actor -p mapless-replay --bins
cuda_test="$(cargo test --release --config "$patch_cfg" -p mapless-learner --test cuda --no-run --message-format=json 2>/dev/null |
    python3 -c 'import json,sys
for l in sys.stdin:
    m = json.loads(l)
    if m.get("reason") == "compiler-artifact" and m.get("executable") and m["target"]["name"] == "cuda": print(m["executable"])')"
[[ -x "$cuda_test" ]] || { say "the learner's cuda test did not build"; exit 1; }

mkdir -p "$root/gpu"
for b in mapless mapless-learner mapless-actor mapless-replay; do
    cp "$CARGO_TARGET_DIR/release/$b" "$root/gpu/$b"
done
cp "$cuda_test" "$root/gpu/cuda-test"
cp "$here/run.sh" "$root/gpu/run.sh"
strip "$root"/gpu/mapless* "$root/gpu/cuda-test"
say "gpu/ is ready ($(du -sh "$root/gpu" | cut -f1)): on the GPU machine, \`bash gpu/run.sh\`"
