#!/usr/bin/env bash
# deploy/build.sh — builds the mapless images from source with deploy/Dockerfile:
#
#   mapless-replay:TAG  mapless-actor:TAG  mapless-monitor:TAG  mapless-prometheus:TAG
#   mapless-learner:TAG (CPU)  [mapless-learner:TAG-cuda]
#
# under the names deploy/compose.yaml runs (MAPLESS_TAG, default `local`). The Dockerfile's base
# images (rust:1.95-slim-bookworm, debian:bookworm-slim) are used where this engine has them,
# pulled where a registry answers, and otherwise made locally by deploy/bases.sh.
#
# deploy/images.sh is the quick way to the same image names from binaries this checkout already
# built (the test suite's drill uses it: no compilation inside Docker); this is the conventional
# way, a from-source build a user with a registry (or none) runs as it is.
#
# Usage: deploy/build.sh [TAG] [--cuda]     (--cuda adds the CUDA learner, several GB)
set -euo pipefail
root="$(cd -- "$(dirname -- "${BASH_SOURCE[0]}")/.." && pwd -P)"
cd "$root"
tag=local cuda=0
for a in "$@"; do
    case "$a" in
        --cuda) cuda=1 ;;
        -*) echo "usage: deploy/build.sh [TAG] [--cuda]" >&2; exit 2 ;;
        *) tag="$a" ;;
    esac
done
say() { printf 'build.sh: %s\n' "$*" >&2; }
command -v docker >/dev/null || { say "docker not found"; exit 1; }

# BuildKit where the buildx plugin is installed (it builds only the stages a target needs); the
# legacy builder otherwise (Debian's docker.io 20.10 has no buildx).
if [ -z "${DOCKER_BUILDKIT:-}" ]; then
    if docker buildx version >/dev/null 2>&1; then export DOCKER_BUILDKIT=1; else export DOCKER_BUILDKIT=0; fi
fi

missing=0
for base in rust:1.95-slim-bookworm debian:bookworm-slim; do
    docker image inspect "$base" >/dev/null 2>&1 || docker pull --quiet "$base" >/dev/null 2>&1 || missing=1
done
if [ "$missing" = 1 ]; then
    say "a base image is neither here nor pullable: making them with deploy/bases.sh"
    bash deploy/bases.sh
fi

targets=(replay actor monitor prometheus learner)
[ "$cuda" = 1 ] && targets+=(learner-cuda)
for t in "${targets[@]}"; do
    case "$t" in learner-cuda) image="mapless-learner:$tag-cuda" ;; *) image="mapless-$t:$tag" ;; esac
    say "$image (docker build --target $t; BuildKit=$DOCKER_BUILDKIT)"
    start=$SECONDS
    docker build -f deploy/Dockerfile --target "$t" -t "$image" . 2>&1 | sed -u 's/^/    /' >&2
    say "$image built in $((SECONDS - start)) s"
done
docker images --format '{{.Repository}}:{{.Tag}}  {{.Size}}' | grep -E "^mapless-(replay|actor|monitor|prometheus|learner):$tag(-cuda)? " >&2
