#!/usr/bin/env bash
# deploy/scale.sh — what the compose cluster (deploy/compose.yaml) does on this machine with 1,
# 2, 4 and 8 actor replicas: it starts replay + learner + 1 actor, times `up` to the learner's
# first update, then for each count scales the actors (`up -d --scale actor=N`), waits until N
# actor ids write and SETTLE seconds more, and over WINDOW seconds reads
#
#   env steps/s      rows the replay stored per second (replay_inserts_total; one row is one
#                    vehicle's env step)
#   updates/s        the learner's gradient updates per second (its status lines)
#   per replica      env steps/s divided by N
#
# and prints a table (and writes it as CSV to $OUT/scale.csv when OUT is set). Then `down -v`.
# The compose cluster's replay has the env1-sac rate limiter (32 samples per insert, so at most
# 4 env steps per update once it binds) and every container shares this machine's cores: the
# figures show where the cores, not the code, stop the scaling.
#
# SERVICE=actor-shm scales the same actor writing over shared memory instead (its replicas mount
# the replay's /dev/shm and iceoryx2 folder); LIMITER=off runs the replay without its rate limiter
# (an override of config/replay.yaml with an unbounded error buffer), so the figures are what
# the actors and the transport deliver rather than what the learner allows.
#
# Usage: deploy/scale.sh [COUNT...]   (default 1 2 4 8; WINDOW=60 SETTLE=20; SKIP_IMAGES=1 reuses
#                                      built images; MAPLESS_TAG picks them, default local)
# Root, as deploy/smoke.sh: the replay's /metrics is read inside its network namespace.
set -euo pipefail
here="$(cd -- "$(dirname -- "${BASH_SOURCE[0]}")" && pwd -P)"
cd "$here"
export MAPLESS_TAG="${MAPLESS_TAG:-local}" MAPLESS_PROMETHEUS_PORT=0
counts=("$@")
[ ${#counts[@]} -gt 0 ] || counts=(1 2 4 8)
window="${WINDOW:-60}" settle="${SETTLE:-20}"
[ "${SKIP_IMAGES:-}" = 1 ] || ./images.sh "$MAPLESS_TAG"
./certs.sh
me=scale project=mapless-scale
source ./lib.sh
service="${SERVICE:-actor}" other=actor
case "$service" in
    actor) other=actor-shm ;;
    actor-shm) ;;
    *) echo "scale: SERVICE is actor or actor-shm, not $service" >&2; exit 2 ;;
esac
tmp=$(mktemp -d)
if [ "${LIMITER:-on}" = off ]; then
    sed 's/^\(    error_buffer:\).*/\1 1.0e12/' config/replay.yaml > "$tmp/replay.yaml"
    grep -q "error_buffer: 1.0e12" "$tmp/replay.yaml" || die "config/replay.yaml has no rate_limiter.error_buffer to lift"
    printf 'services:\n  replay:\n    volumes:\n      - %s/replay.yaml:/config/replay.yaml:ro\n' "$tmp" > "$tmp/unlimited.yaml"
    compose_overrides=("$tmp/unlimited.yaml")
fi
trap 'rc=$?; dc down -v >/dev/null 2>&1 || true; rm -rf "$tmp"; forget_failures; exit $rc' EXIT
trap 'echo "scale: failed at line $LINENO: $BASH_COMMAND (exit $?)" >&2' ERR
dc down -v >/dev/null 2>&1 || true

counter() { replay_metrics | sed -n "s/^$1{.*} \([0-9.e+]*\)\$/\1/p" | awk '{ s += $1 } END { printf "%d", s }'; }
# The live replicas: actor ids whose row counts grow (a scaled-down or restarted one stops).
live_writers() { growing_ids replay_metrics | wc -l; }
enough_writers() { [ "$(live_writers)" -ge "$1" ]; }
first_update() { [ "$(learner_field updates)" -gt 0 ] 2>/dev/null; }

start=$SECONDS
dc up -d --scale "$service=${counts[0]}" --scale "$other=0" >/dev/null 2>&1
wait_for 300 "the learner's first update" first_update
to_update=$(( SECONDS - start ))
echo "scale: ${to_update} s from up (images built) to the learner's first update"

rows=()
for n in "${counts[@]}"; do
    dc up -d --scale "$service=$n" --scale "$other=0" >/dev/null 2>&1
    wait_for 180 "$n actor replicas write" enough_writers "$n"
    sleep "$settle"
    r0=$(counter replay_inserts_total); u0=$(learner_field updates); t0=$(date +%s.%N)
    sleep "$window"
    r1=$(counter replay_inserts_total); u1=$(learner_field updates); t1=$(date +%s.%N)
    line=$(awk -v n="$n" -v r0="$r0" -v r1="$r1" -v u0="$u0" -v u1="$u1" -v t0="$t0" -v t1="$t1" \
        'BEGIN { dt = t1 - t0; printf "%d,%.0f,%.0f,%.0f", n, (r1 - r0) / dt, (u1 - u0) / dt, (r1 - r0) / dt / n }')
    echo "scale: $n replicas: $(awk -F, '{ printf "%s env steps/s, %s updates/s, %s per replica", $2, $3, $4 }' <<<"$line")"
    rows+=("$line")
done

echo
echo "($service replicas, rate limiter ${LIMITER:-on})"
echo "| actor replicas | env steps/s | updates/s | env steps/s per replica |"
echo "|---:|---:|---:|---:|"
for l in "${rows[@]}"; do awk -F, '{ printf "| %s | %s | %s | %s |\n", $1, $2, $3, $4 }' <<<"$l"; done
echo "(time from up to the first update: ${to_update} s; window ${window} s after ${settle} s to settle; $(nproc) cores)"
if [ -n "${OUT:-}" ]; then
    mkdir -p "$OUT"
    { echo "replicas,env_steps_per_s,updates_per_s,env_steps_per_s_per_replica"; printf '%s\n' "${rows[@]}"; } > "$OUT/scale.csv"
    echo "scale: wrote $OUT/scale.csv"
fi
