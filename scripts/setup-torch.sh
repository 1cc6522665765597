#!/usr/bin/env bash
# Install libtorch for the learner into <repo>/.torch (git-ignored), from PyPI.
#
#   .torch/
#     venv/                 python3 -m venv; `pip install torch==$TORCH_VERSION`
#     libtorch -> venv/lib/python3.X/site-packages/torch      (relative symlink)
#                  lib/libtorch_cpu.so, lib/libtorch.so, include/, ...
#
# Why PyPI: download.pytorch.org (where the standalone libtorch zips live) is not always
# reachable, PyPI is. The torch wheel ships the same shared libraries and headers as the
# libtorch zip, built with the C++11 ABI. On linux x86_64 the only torch 2.13.0 wheel on PyPI
# is the CUDA build, so pip also pulls the nvidia-* wheels (~4.7 GB installed). They are needed
# even on a CPU-only machine: libtorch.so links libtorch_cuda.so, and libtorch_cpu.so itself
# links libcudart/libcupti. torch's libraries find them through their own
# `$ORIGIN/../../nvidia/*/lib` RPATH, which is why we keep the site-packages layout intact
# and point at it with a symlink instead of copying `torch/` elsewhere.
#
# `.cargo/config.toml` sets LIBTORCH=.torch/libtorch (relative to the repo root), so after
# this script a plain `cargo build` / `cargo test` finds libtorch; the stable symlink means
# nothing in the build depends on the Python minor version.
#
# Idempotent: when the pinned version is already installed it only re-checks the symlink
# (about a second). Works from any working directory.
#
# Environment:
#   PYTHON   interpreter used to create the venv (default: python3)
set -euo pipefail

# tch 0.26 binds exactly this libtorch version; change both together.
readonly TORCH_VERSION="2.13.0"

say() { printf 'setup-torch: %s\n' "$*"; }
die() {
    printf 'setup-torch: error: %s\n' "$*" >&2
    exit 1
}

script_dir="$(cd -- "$(dirname -- "${BASH_SOURCE[0]}")" && pwd -P)"
repo_root="$(cd -- "$script_dir/.." && pwd -P)"
[[ -f "$repo_root/Cargo.toml" ]] || die "cannot find the repository root (no Cargo.toml in $repo_root)"

torch_root="$repo_root/.torch"
venv="$torch_root/venv"
venv_python="$venv/bin/python"
link="$torch_root/libtorch"
python="${PYTHON:-python3}"

# Prints the installed torch version, or nothing. Reads package metadata only: importing
# torch would load ~1 GB of shared libraries just to answer this.
installed_torch_version() {
    "$venv_python" - <<'EOF' 2>/dev/null || true
import importlib.metadata as m
try:
    print(m.version("torch"))
except m.PackageNotFoundError:
    pass
EOF
}

# Accept local version labels too (e.g. 2.13.0+cpu).
version_matches() { [[ "$1" == "$TORCH_VERSION" || "$1" == "$TORCH_VERSION+"* ]]; }

mkdir -p "$torch_root" || die "cannot create $torch_root"

# 1. The venv. A venv whose interpreter no longer runs (its base python was upgraded or
#    removed) is rebuilt from scratch.
if [[ -x "$venv_python" ]] && "$venv_python" -c 'pass' 2>/dev/null; then
    say "venv: $venv (exists)"
else
    if [[ -e "$venv" ]]; then
        say "venv: $venv is broken; recreating it"
        rm -rf -- "$venv"
    fi
    command -v "$python" >/dev/null 2>&1 ||
        die "'$python' not found; install python3 (with the venv module) or set PYTHON=/path/to/python3"
    say "venv: creating $venv with $("$python" --version 2>&1)"
    "$python" -m venv "$venv" ||
        die "'$python -m venv' failed (on Debian/Ubuntu: apt-get install python3-venv)"
fi

# 2. torch itself.
current="$(installed_torch_version)"
if [[ -n "$current" ]] && version_matches "$current"; then
    say "torch: $current already installed"
else
    if [[ -n "$current" ]]; then
        say "torch: found $current, want $TORCH_VERSION; reinstalling"
    fi
    say "torch: pip install torch==$TORCH_VERSION (CUDA wheel + nvidia-* deps, several GB; takes a few minutes)"
    "$venv_python" -m pip install --disable-pip-version-check --no-input --no-cache-dir "torch==$TORCH_VERSION" ||
        die "pip install torch==$TORCH_VERSION failed (is PyPI reachable? is there ~6 GB free under $torch_root?)"
    current="$(installed_torch_version)"
    version_matches "$current" || die "after pip install, torch reports version '${current:-none}', not $TORCH_VERSION"
fi

# 3. The stable symlink .torch/libtorch -> venv/lib/pythonX.Y/site-packages/torch. Relative,
#    so the checkout can move. torch is a compiled package, so it lives in platlib.
platlib="$("$venv_python" -c 'import sysconfig; print(sysconfig.get_paths()["platlib"])')" ||
    die "cannot ask the venv's python for its site-packages directory"
torch_pkg="$platlib/torch"
[[ -d "$torch_pkg" ]] || die "torch package directory not found at $torch_pkg"
target="${torch_pkg#"$torch_root"/}"
[[ "$target" != "$torch_pkg" ]] || die "site-packages ($platlib) is not under $torch_root"

if [[ -L "$link" && "$(readlink -- "$link")" == "$target" ]]; then
    say "link: $link -> $target (unchanged)"
else
    if [[ -e "$link" && ! -L "$link" ]]; then
        die "$link exists and is not a symlink; move it away and re-run"
    fi
    ln -sfn -- "$target" "$link" || die "cannot create symlink $link"
    say "link: $link -> $target"
fi

# 4. What torch-sys needs: headers and the shared libraries it links.
for f in lib/libtorch.so lib/libtorch_cpu.so lib/libc10.so include/torch/csrc/api/include/torch/torch.h; do
    [[ -e "$link/$f" ]] || die "expected $link/$f, it is missing; the torch install looks incomplete (rm -rf $venv and re-run)"
done

say "ok: LIBTORCH=$link (libtorch $TORCH_VERSION); .cargo/config.toml points cargo at it"
