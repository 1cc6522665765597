#!/usr/bin/env bash
# deploy/smoke.sh — end-to-end check of the compose cluster (deploy/compose.yaml) on this
# machine's Docker: builds the images and secrets, starts replay + learner + 2 actors on a
# private network (gRPC with TLS and a token between containers) and checks, printing each step:
#
#   1. the learner samples and updates, and publishes new weights versions;
#   2. every actor acts with a published policy (version ≥ 2) and the replay acknowledges its batches;
#   3. an actor process killed with SIGKILL is restarted by Docker and its new incarnation writes;
#   4. `docker-compose stop` ends the learner with a final checkpoint.
#
# Usage: deploy/smoke.sh   (SKIP_IMAGES=1 reuses built images; KEEP=1 leaves the cluster up)
# Run it as root (or with sudo): step 3 kills the actor's process from the host, because
# `docker kill` counts as a deliberate stop and turns the restart policy off.
# Not part of ./test.sh: it needs a Docker engine and builds a multi-GB learner image.
set -euo pipefail
here="$(cd -- "$(dirname -- "${BASH_SOURCE[0]}")" && pwd -P)"
cd "$here"
export MAPLESS_TAG="${MAPLESS_TAG:-local}"
[ "${SKIP_IMAGES:-}" = 1 ] || ./images.sh "$MAPLESS_TAG"
./certs.sh
project=mapless-smoke
if command -v docker-compose >/dev/null; then compose=(docker-compose); else compose=(docker compose); fi
dc() { "${compose[@]}" -p "$project" -f compose.yaml "$@"; }
logs="$(mktemp -d)/compose.log"
finish() {
    local rc=$?
    dc logs --no-color > "$logs" 2>&1 || true
    [ "${KEEP:-}" = 1 ] || dc down -v >/dev/null 2>&1 || true
    if [ $rc -eq 0 ]; then echo "smoke: PASS (logs: $logs)"; else echo "smoke: FAIL (logs: $logs)"; tail -40 "$logs"; fi
}
trap finish EXIT
dc down -v >/dev/null 2>&1 || true
dc up -d

# wait_for SECONDS WHAT COMMAND...: runs COMMAND every 2 s until it succeeds.
wait_for() {
    local limit=$1 what=$2; shift 2
    local start=$SECONDS
    until "$@"; do
        if (( SECONDS - start > limit )); then echo "smoke: timed out after ${limit}s waiting for: $what" >&2; return 1; fi
        sleep 2
    done
    echo "smoke: ok after $(( SECONDS - start ))s: $what"
}
# Newest learner status line: {"event":"status","updates":N,...,"weights_version":V}.
learner_field() { dc logs --no-color learner 2>/dev/null | grep -o "\"$1\":[0-9]*" | tail -1 | cut -d: -f2; }
learner_updates() { local u; u=$(learner_field updates); [ "${u:-0}" -gt 100 ]; }
learner_versions() { local v; v=$(learner_field weights_version); [ "${v:-0}" -ge 3 ]; }
# An actor's "acting" lines (every 10 s): policy_version=V batches_acked=B actor_id=ID.
actor_ok() {
    dc logs --no-color "$1" 2>/dev/null | grep " acting " | awk '
        { v = 0; b = 0
          for (i = 1; i <= NF; i++) { split($i, kv, "="); if (kv[1] == "policy_version") v = kv[2]; if (kv[1] == "batches_acked") b = kv[2] } }
        v >= 2 && b > 0 { ok = 1 } END { exit !ok }'
}
actor_incarnations() {
    local n
    n=$(dc logs --no-color "$1" 2>/dev/null | grep " acting " | grep -o 'batches_acked=[1-9][0-9]* .*actor_id=[^ ]*' | grep -o 'actor_id=[^ ]*' | sort -u | wc -l)
    [ "$n" -ge 2 ]
}

wait_for 300 "learner updates > 100" learner_updates
wait_for 120 "learner published weights version ≥ 3" learner_versions
wait_for 120 "actor-0 acts with policy ≥ v2, batches acknowledged" actor_ok actor-0
wait_for 120 "actor-1 acts with policy ≥ v2, batches acknowledged" actor_ok actor-1

cid=$(dc ps -q actor-0)
pid=$(docker inspect -f '{{.State.Pid}}' "$cid")
echo "smoke: kill -9 actor-0 (pid $pid on this host)"
kill -9 "$pid"
wait_for 60 "Docker restarted actor-0" bash -c "[ \"\$(docker inspect -f '{{.RestartCount}}' $cid)\" -ge 1 ]"
wait_for 120 "actor-0's new incarnation writes" actor_incarnations actor-0
echo "smoke: learner at $(learner_field updates) updates, weights v$(learner_field weights_version)"

dc stop -t 60 >/dev/null 2>&1
dc logs --no-color learner 2>/dev/null | grep -q '"event":"stopped"' || { echo "smoke: the learner did not report its final checkpoint" >&2; exit 1; }
echo "smoke: ok: the learner stopped with a final checkpoint"
