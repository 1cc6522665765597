# deploy/lib.sh — what deploy/smoke.sh and deploy/scale.sh share: the compose command for the
# project $project, waiting with a limit, and reading the learner's status lines, the replay's
# /metrics (inside its network namespace: no port publishes it) and Prometheus's HTTP API.
# Sourced from deploy/ with $me (the prefix of messages) and $project set.
if command -v docker-compose >/dev/null; then compose=(docker-compose); else compose=(docker compose); fi
# More compose files after compose.yaml (overrides), if the caller sets any.
compose_overrides=()
dc() {
    local files=(-f compose.yaml) f
    for f in "${compose_overrides[@]}"; do files+=(-f "$f"); done
    "${compose[@]}" -p "$project" "${files[@]}" "$@"
}
# What is left of the project: containers, networks, volumes (one line each).
leftovers() {
    local f="label=com.docker.compose.project=$project"
    { docker ps -aq --filter "$f"; docker network ls -q --filter "$f"; docker volume ls -q --filter "$f"; } | sed '/^$/d'
}
# Why the drill failed, one "ME: …" line per failure, for the caller's finish to print last
# (after the services' log tails, where a CI excerpt of the output's end still shows it). The
# record is $MAPLESS_DRILL_FAILURE_FILE when that is set (tests/compose_drill.rs puts it in its
# panic), else a temporary file that finish removes (forget_failures).
failures="${MAPLESS_DRILL_FAILURE_FILE:-$(mktemp)}"
failed() {
    echo "$me: $*" >&2
    echo "$me: $*" >> "$failures"
}
# die MESSAGE: records MESSAGE and ends the drill.
die() { failed "$*"; exit 1; }
# The recorded failures, for finish: "ME: FAILED: …" lines.
print_failures() { sed "s/^\([^:]*\): /\1: FAILED: /" "$failures"; }
# Removes the record at the end, unless it is the caller's ($MAPLESS_DRILL_FAILURE_FILE).
forget_failures() { [ -n "${MAPLESS_DRILL_FAILURE_FILE:-}" ] || rm -f "$failures"; }
# wait_for SECONDS WHAT COMMAND...: runs COMMAND every 2 s until it succeeds.
wait_for() {
    local limit=$1 what=$2; shift 2
    local start=$SECONDS
    until "$@"; do
        if (( SECONDS - start > limit )); then failed "timed out after ${limit}s waiting for: $what"; return 1; fi
        sleep 2
    done
    echo "$me: ok after $(( SECONDS - start ))s: $what"
}
# Newest learner status line: {"event":"status","updates":N,...,"weights_version":V}.
learner_field() { dc logs --no-color learner 2>/dev/null | grep -o "\"$1\":[0-9]*" | tail -1 | cut -d: -f2; }
# The replay's /metrics, read inside its network namespace, with the metrics token (as the
# prometheus service reads it); `replay_metrics_status ARGS` prints the HTTP status instead.
replay_metrics() {
    local pid
    pid=$(docker inspect -f '{{.State.Pid}}' "$(dc ps -q replay)")
    nsenter -t "$pid" -n curl -sf --max-time 5 -H "Authorization: Bearer $(cat secrets/metrics-token)" http://127.0.0.1:9464/metrics
}
replay_metrics_status() {
    local pid
    pid=$(docker inspect -f '{{.State.Pid}}' "$(dc ps -q replay)")
    nsenter -t "$pid" -n curl -s -o /dev/null -w '%{http_code}' --max-time 5 "$@" http://127.0.0.1:9464/metrics
}
# "ID ROWS" per actor id, from /metrics text on stdin (replay_actor_rows_total).
actor_rows_in() { sed -n 's/^replay_actor_rows_total{.*actor="\(actor-[^"]*\)"} \([0-9.e+]*\)$/\1 \2/p'; }
# growing_ids CMD...: the actor ids whose row counts grow over 8 s (a rate-limited actor lands a
# batch every few seconds on a loaded machine), sorted, one per line; CMD
# prints the replay's /metrics (replay_metrics here, a Swarm task's in deploy/swarm.sh).
growing_ids() {
    local a b
    a=$("$@" | actor_rows_in)
    sleep 8
    b=$("$@" | actor_rows_in)
    join <(sort -k1,1 <<<"$a") <(sort -k1,1 <<<"$b") | awk '$3 > $2 { print $1 }' | sort
}
# Prometheus's HTTP API on the host port compose published (MAPLESS_PROMETHEUS_PORT=0 in the callers).
prom() { curl -sf --max-time 5 "http://$(dc port prometheus 9090)$1"; }
# "JOB UP" for every target of `up`, one per line.
prom_up() { prom "/api/v1/query?query=up" | python3 -c 'import json,sys; [print(r["metric"]["job"], r["value"][1]) for r in json.load(sys.stdin)["data"]["result"]]'; }
