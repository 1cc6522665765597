#!/usr/bin/env bash
# deploy/smoke.sh — end-to-end drill of the compose cluster (deploy/compose.yaml) on this
# machine's Docker: builds the images and secrets, starts replay + learner + $ACTORS actor
# replicas (`--scale actor=N`, default 4) on a private network (gRPC with TLS and role tokens between
# containers) and checks, printing each step and what it measured:
#
#   0. `up` starts the learner only once the replay is healthy and the actors once both are
#      (depends_on: service_healthy), every container's HEALTHCHECK reports healthy, and no
#      container's process runs as root;
#   1. the learner samples and updates, and publishes new weights versions;
#   2. N distinct actor ids, on slots 0..N-1, write rows into the replay (its /metrics), and
#      every replica acts with a published policy (version ≥ 2) with its batches acknowledged;
#      Prometheus (its port published on the host's loopback) scraped the replay, the learner
#      and every replica with the metrics token, a scrape without it or with a wrong one is
#      refused (401), and the mapless console renders; the replay's ServerInfo (`mapless-replay
#      info`) lists the actors for the learner's token and refuses a call without a token
#      (UNAUTHENTICATED) and with the actor's (PERMISSION_DENIED);
#   3. an actor process killed with SIGKILL is restarted by Docker, gets its slot back, and its
#      new incarnation (a new actor id on the same slot) writes;
#   4. `up -d --scale actor=N+2`: two new replicas register, take slots N and N+1, and write,
#      and Prometheus finds and scrapes them by itself;
#   5. `up -d --scale actor=2`: two replicas are left and keep writing;
#   5b. `--scale actor-shm=1`: a replica that mounts the replay's /dev/shm and iceoryx2 folder
#      writes over shared memory; killed with SIGKILL, it is restarted on its
#      slot, and the replay removes the dead writer's iceoryx2 resources;
#   6. `restart replay`: its rows come back from its volume and the actors (both transports)
#      write again;
#   7. one replica cut off the network for 15 s (`docker network disconnect`) writes again once
#      reconnected;
#   8. the three replicas (two over gRPC, one over shared memory), stopped, each report the
#      rows they sent, all acknowledged, and the replay holds exactly that many under each one's
#      id (nothing lost, nothing twice);
#   9. `docker-compose stop` ends the learner with a final checkpoint, and the monitor with
#      summary.json (a final evaluation of the learner's policy), curves.png, evals.csv and eval/
#      in its run folder, whose episodes.csv (checked at step 2) held every replica's episodes;
#  10. `down -v` leaves no container, network or volume of the project behind.
#
# Usage: deploy/smoke.sh   (SKIP_IMAGES=1 reuses built images; KEEP=1 leaves the cluster up;
#                           ACTORS=N replicas at first, default 4)
# Run it as root (or with sudo): step 3 kills the actor's process from the host, because
# `docker kill` counts as a deliberate stop and turns the restart policy off; and the replay's
# /metrics is read on its container's loopback (nsenter into its network namespace), since no
# port is published.
# The suite runs it (`tests/compose_drill.rs`, with MAPLESS_PROFILE=dev) wherever a Docker engine
# answers; it builds a multi-GB learner image (layers reused on a rerun).
set -euo pipefail
here="$(cd -- "$(dirname -- "${BASH_SOURCE[0]}")" && pwd -P)"
cd "$here"
export MAPLESS_TAG="${MAPLESS_TAG:-local}"
# Prometheus's host port: any free one (on the host's loopback), found with `docker-compose port`.
export MAPLESS_PROMETHEUS_PORT=0
actors="${ACTORS:-4}"
me=smoke project=mapless-smoke
# dc, leftovers, wait_for, die, learner_field, replay_metrics, prom, prom_up: deploy/lib.sh.
source ./lib.sh
[ "${SKIP_IMAGES:-}" = 1 ] || ./images.sh "$MAPLESS_TAG" || die "deploy/images.sh failed (its output is above)"
./certs.sh || die "deploy/certs.sh failed (its output is above)"
logs="$(mktemp -d)/compose.log"
finish() {
    local rc=$?
    dc logs --no-color > "$logs" 2>&1 || true
    if [ "${KEEP:-}" != 1 ]; then
        dc down -v >/dev/null 2>&1 || true
        if [ -n "$(leftovers)" ]; then echo "smoke: left behind after down -v:"; leftovers; rc=1; else echo "smoke: ok: down -v left no container, network or volume"; fi
    fi
    if [ $rc -eq 0 ]; then echo "smoke: PASS (logs: $logs)"; else echo "smoke: FAIL (logs: $logs)"; tail -40 "$logs"; print_failures; fi
    forget_failures
    exit $rc
}
trap finish EXIT
# Under `set -e` a failing command ends the drill without a word: name it.
trap 'failed "failed at line $LINENO: $BASH_COMMAND (exit $?)"' ERR
dc down -v >/dev/null 2>&1 || true
started=$SECONDS
dc up -d --scale actor="$actors"

learner_updates() { local u; u=$(learner_field updates); [ "${u:-0}" -gt 100 ]; }
learner_versions() { local v; v=$(learner_field weights_version); [ "${v:-0}" -ge 3 ]; }

# Prometheus scraped the replay, the learner and N actor replicas, each up.
prom_scraped() { [ "$(prom_up | sort | uniq -c | awk '$3 == 1 {printf "%s=%s ", $2, $1}')" = "actor=$1 learner=1 replay=1 " ]; }
# Actor ids with rows in the replay, and their row counts: "actor-<slot>-<pid>-<ms> ROWS".
actor_rows() { replay_metrics | actor_rows_in | awk '$2 > 0'; }
# Their slots, space-separated and sorted: "0 1 2 3".
slots_writing() { actor_rows | cut -d- -f2 | sort -un | tr '\n' ' ' | sed 's/ $//'; }
want_slots() { [ "$(slots_writing)" = "$1" ]; }
# Names holding a slot (the exposition writes floats: "4.0").
registered() { replay_metrics | sed -n 's/^replay_actor_slots{.*} \([0-9.e+]*\)$/\1/p' | awk '{ printf "%d", $1 }'; }
# A replica's slot and its current actor id, from its own log.
slot_of() { docker logs "$1" 2>&1 | grep "registered with the replay" | grep -o ' slot=[0-9]*' | tail -1 | cut -d= -f2; }
id_of() { docker logs "$1" 2>&1 | grep -o 'actor_id=actor-[^ ]*' | tail -1 | cut -d= -f2; }
rows_of() { actor_rows | awk -v id="$1" '$1 == id {print $2}'; }
# An actor's "acting" lines (every 10 s): policy_version=V batches_acked=B actor_id=ID.
actor_ok() {
    docker logs "$1" 2>&1 | grep " acting " | awk '
        { v = 0; b = 0
          for (i = 1; i <= NF; i++) { split($i, kv, "="); if (kv[1] == "policy_version") v = kv[2]; if (kv[1] == "batches_acked") b = kv[2] } }
        v >= 2 && b > 0 { ok = 1 } END { exit !ok }'
}
seq_slots() { seq -s ' ' 0 $(( $1 - 1 )); }
show_actors() {
    echo "smoke: replay: $(registered) names hold slots; actor ids writing (id rows):"
    actor_rows | sed 's/^/smoke:   /'
}

# Every container of the project: its HEALTHCHECK's verdict (the image's `health` subcommand),
# or for Prometheus, which has none, that it runs (what it scraped is checked below).
all_healthy() {
    local c
    for c in $(dc ps -q); do
        case "$(docker inspect -f '{{if .State.Health}}{{.State.Health.Status}}{{else}}no-check {{.State.Status}}{{end}}' "$c")" in
            healthy|"no-check running") ;;
            *) return 1 ;;
        esac
    done
}
wait_for 120 "every container reports healthy" all_healthy
# No container runs its process as root: each runs as the images' user, 65532 (deploy/Dockerfile, deploy/images.sh).
for c in $(dc ps -q); do
    uid=$(ps -o uid= -p "$(docker inspect -f '{{.State.Pid}}' "$c")" | tr -d ' ')
    [ "$uid" = 65532 ] || die "container ${c:0:12} ($(docker inspect -f '{{.Name}}' "$c")) runs as uid $uid, not 65532"
done
echo "smoke: ok: every container's process runs as uid 65532, not root"
wait_for 300 "learner updates > 100" learner_updates
echo "smoke: $(( SECONDS - started ))s from up to > 100 learner updates"
wait_for 120 "learner published weights version ≥ 3" learner_versions
wait_for 120 "$actors distinct actor ids on slots $(seq_slots "$actors") write to the replay" want_slots "$(seq_slots "$actors")"
for cid in $(dc ps -q actor); do
    wait_for 120 "replica ${cid:0:12} (slot $(slot_of "$cid"), $(id_of "$cid")) acts with policy ≥ v2, batches acknowledged" actor_ok "$cid"
done
[ "$(registered)" = "$actors" ] || die "the replay holds $(registered) slots, expected $actors"
show_actors

# The run folder (the monitor): episodes from every replica arrive in episodes.csv.
run_file() { docker cp "$(dc ps -q monitor):/runs/compose/$1" - 2>/dev/null | tar -xO; }
episode_actors() { run_file episodes.csv | python3 -c 'import csv,sys; print(len({r["actor_id"] for r in csv.DictReader(sys.stdin)}))'; }
monitor_has_all() { [ "$(episode_actors)" -ge "$1" ]; }
wait_for 180 "the monitor's episodes.csv holds episodes of all $actors replicas" monitor_has_all "$actors"
echo "smoke: ok: the run folder (monitor) holds $(run_file episodes.csv | tail -n +2 | wc -l) episodes from $(episode_actors) actor ids"

# Observability from the host: Prometheus (the one published port) scraped every replica, found
# by DNS, with the metrics token; a scrape without it is refused; the mapless console renders.
wait_for 60 "Prometheus scraped the replay, the learner and all $actors actor replicas (up == 1)" prom_scraped "$actors"
status=$(replay_metrics_status) && [ "$status" = 401 ] || die "a scrape of the replay's /metrics without the token got HTTP $status, not 401"
status=$(replay_metrics_status -H "Authorization: Bearer wrong") && [ "$status" = 401 ] || die "a scrape with a wrong token got HTTP $status, not 401"
console=$(prom "/consoles/mapless.html") || die "the mapless console did not render"
grep -q "mapless cluster" <<<"$console" && ! grep -qi "error executing template" <<<"$console" || die "the mapless console: ${console:0:400}"
echo "smoke: ok: Prometheus on the host's $(dc port prometheus 9090) scraped every replica; no token or a wrong one: 401; the console renders"

# Tokens and roles: the replay's ServerInfo, asked inside its container over TLS, answers the
# learner's token with every actor id that wrote; no token is UNAUTHENTICATED and the actor's
# token PERMISSION_DENIED (a leaked actor token cannot read the replay).
replay_info() { docker exec "$(dc ps -q replay)" /usr/local/bin/mapless-replay info 127.0.0.1:50051 --tls-ca-file /secrets/ca.pem "$@" 2>&1; }
info=$(replay_info --token-file /secrets/learner-token) || die "server info with the learner's token failed: $info"
listed=$(grep -c '^actor actor-' <<<"$info" || true)
[ "$listed" -ge "$actors" ] || die "server info lists $listed actor ids, expected $actors: $info"
echo "smoke: ok: server info (learner's token) lists $listed actor ids: $(head -1 <<<"$info")"
if out=$(replay_info); then die "server info without a token was answered: $out"; fi
grep -qi "unauthenticated" <<<"$out" || die "server info without a token failed, but not as UNAUTHENTICATED: $out"
if out=$(replay_info --token-file /secrets/actor-token); then die "server info with the actor's token was answered: $out"; fi
grep -qi "permission" <<<"$out" || die "server info with the actor's token failed, but not as PERMISSION_DENIED: $out"
echo "smoke: ok: without a token and with the actor's token, server info is refused ($(tail -1 <<<"$out" | cut -c1-160))"

cid=$(dc ps -q actor | sed -n 1p)
slot=$(slot_of "$cid"); old_id=$(id_of "$cid")
pid=$(docker inspect -f '{{.State.Pid}}' "$cid")
echo "smoke: kill -9 replica ${cid:0:12} (slot $slot, $old_id; pid $pid on this host)"
kill -9 "$pid"
wait_for 60 "Docker restarted it" bash -c "[ \"\$(docker inspect -f '{{.RestartCount}}' $cid)\" -ge 1 ]"
new_incarnation_writes() { local id; id=$(id_of "$cid"); [ "$id" != "$old_id" ] && [ -n "$(rows_of "$id")" ]; }
wait_for 120 "its new incarnation writes" new_incarnation_writes
new_id=$(id_of "$cid")
[ "$(slot_of "$cid")" = "$slot" ] || die "the restarted replica got slot $(slot_of "$cid"), not its own $slot"
[ "$(registered)" = "$actors" ] || die "a restart took a new slot ($(registered) held)"
echo "smoke: ok: the restarted replica kept slot $slot under a new incarnation id $new_id"

more=$(( actors + 2 ))
dc up -d --scale actor="$more" >/dev/null 2>&1
wait_for 120 "two new replicas: $more slots $(seq_slots "$more") write" want_slots "$(seq_slots "$more")"
[ "$(dc ps -q actor | wc -l)" = "$more" ] || die "$(dc ps -q actor | wc -l) actor containers, expected $more"
show_actors
wait_for 60 "Prometheus found the two new replicas by itself: $more actors scraped" prom_scraped "$more"

dc up -d --scale actor=2 >/dev/null 2>&1
[ "$(dc ps -q actor | wc -l)" = 2 ] || die "$(dc ps -q actor | wc -l) actor containers after scaling to 2"
declare -A before
for c in $(dc ps -q actor); do id=$(id_of "$c"); before[$id]=$(rows_of "$id"); done
both_grow() {
    local id
    for id in "${!before[@]}"; do
        [ "$(awk -v a="$(rows_of "$id")" -v b="${before[$id]:-0}" 'BEGIN { print (a > b) }')" = 1 ] || return 1
    done
}
wait_for 120 "scaled to 2: the two replicas left (${!before[*]}) keep writing" both_grow
echo "smoke: learner at $(learner_field updates) updates, weights v$(learner_field weights_version)"

# Shared memory between containers: an actor-shm replica (the replay's /dev/shm and iceoryx2
# folder, two volumes) registers over gRPC for the next slot and writes over shared memory (it
# has no gRPC sink); killed with SIGKILL, it is restarted, the replay finds its iceoryx2 node dead
# (a file lock the kernel released) and removes its resources, and the new incarnation writes.
dc up -d --scale actor=2 --scale actor-shm=1 >/dev/null 2>&1
shm_c=$(dc ps -q actor-shm)
shm_writes() { local id; id=$(id_of "$shm_c"); [ -n "$id" ] && [ -n "$(rows_of "$id")" ]; }
wait_for 120 "the actor-shm replica (slot $(slot_of "$shm_c")) writes over shared memory" shm_writes
shm_old=$(id_of "$shm_c")
kill -9 "$(docker inspect -f '{{.State.Pid}}' "$shm_c")"
shm_again() { local id; id=$(id_of "$shm_c"); [ "$id" != "$shm_old" ] && [ -n "$(rows_of "$id")" ]; }
wait_for 120 "killed with SIGKILL, the actor-shm replica is restarted and its new incarnation writes" shm_again
dead_cleaned() { dc logs --no-color replay 2>/dev/null | grep "resources of dead iceoryx2 nodes" >/dev/null; }
wait_for 60 "the replay removed the dead writer's iceoryx2 resources" dead_cleaned
[ "$(slot_of "$shm_c")" = "$(cut -d- -f2 <<<"$shm_old")" ] || die "the restarted actor-shm replica changed slot"
echo "smoke: ok: actor-shm $shm_old, killed, came back as $(id_of "$shm_c") on its slot, over shared memory"
before[$(id_of "$shm_c")]=$(rows_of "$(id_of "$shm_c")")

# Rows in the replay's table (the exposition writes floats).
table_size() { replay_metrics | sed -n 's/^replay_size{.*} \([0-9.e+]*\)$/\1/p' | awk '{ printf "%d", $1 }'; }
# Records every id in `before`'s rows now (both_grow then asks for more).
remember_rows() { local id; for id in "${!before[@]}"; do before[$id]=$(rows_of "$id"); done; }
replay_healthy() { [ "$(docker inspect -f '{{.State.Health.Status}}' "$(dc ps -q replay)")" = healthy ]; }

size_before=$(table_size); remember_rows
echo "smoke: restart the replay container (${size_before} rows stored)"
dc restart -t 60 replay >/dev/null 2>&1
wait_for 180 "the replay is healthy again" replay_healthy
size_after=$(table_size)
[ "${size_after:-0}" -ge "$size_before" ] || die "the replay came back with ${size_after:-no} rows, ${size_before} before"
for id in "${!before[@]}"; do
    awk -v a="$(rows_of "$id")" -v b="${before[$id]}" 'BEGIN { exit !(a >= b) }' || die "$id had ${before[$id]} rows before the restart, $(rows_of "$id") after"
done
echo "smoke: ok: the replay's contents came back from its volume (${size_before} rows before, ${size_after} after)"
wait_for 120 "the actors reconnected and write again" both_grow

cut=$(dc ps -q actor | sed -n 1p)
net=$(docker inspect -f '{{range $k, $v := .NetworkSettings.Networks}}{{$k}} {{end}}' "$cut" | awk '{ print $1 }')
remember_rows
echo "smoke: cut replica ${cut:0:12} ($(id_of "$cut")) off network $net for 15 s"
docker network disconnect "$net" "$cut"
sleep 15
docker network connect "$net" "$cut"
# Its connections either resume (TCP retransmits, backed off to several seconds by now) or are
# found dead by the HTTP/2 keepalive (a ping every 10 s, 20 s to answer) and reopened, the
# unacknowledged batches resent; give that its 30 s before judging.
sleep 30
remember_rows
wait_for 120 "the cut-off replica is back and writes again" both_grow

# Exactly-once: each actor, stopped, prints a report of the rows it handed to its sink and
# whether all were acknowledged; the replay must hold exactly that many rows under its id, after
# a replay restart and a network cut (resends are acknowledged as duplicates, not stored twice).
ids=$(dc ps -q actor actor-shm)
dc stop -t 60 actor actor-shm >/dev/null 2>&1
# Every replica is checked before the drill ends; a replica that fails shows its whole report
# (its sink's batches, acks, duplicates, rejections, reconnects and last error) and the replay's
# counters under its id, which tell a lost row from a doubled one.
failing=0
for c in $ids; do
    report=$(docker logs "$c" 2>/dev/null | grep '^{"actor_id"' | tail -1)
    id=$(grep -o '"actor_id":"[^"]*"' <<<"$report" | cut -d'"' -f4)
    sent=$(grep -o '"rows":[0-9]*' <<<"$report" | cut -d: -f2)
    if [ -z "$id" ] || [ -z "$sent" ]; then
        failed "replica ${c:0:12} printed no report at its stop; its last lines:"; docker logs --tail 5 "$c" 2>&1 | sed 's/^/smoke:   /'; failing=1; continue
    fi
    stored=$(rows_of "$id" | awk '{ printf "%d", $1 }')
    if ! grep -q '"unacked_at_exit":false' <<<"$report"; then
        failed "$id stopped with unacknowledged rows (sent $sent, the replay holds ${stored:-none})"
    elif [ "$stored" != "$sent" ]; then
        failed "$id sent $sent rows, the replay holds ${stored:-none} under its id"
    else
        echo "smoke: ok: $id sent $sent rows and the replay holds exactly $stored"; continue
    fi
    failing=1
    echo "smoke:   its report: $report"
    { replay_metrics | grep -F "\"$id\"" || true; } | sed 's/^/smoke:   replay: /'
    # The replay logs every jump in an actor's sequences (batches never stored), by range.
    { dc logs --no-color replay 2>/dev/null | grep "sequence gap" | grep -F "$id" || true; } | sed 's/^/smoke:   replay log: /'
done
[ $failing = 0 ] || die "exactly-once delivery failed (above)"

dc stop -t 60 >/dev/null 2>&1
# The monitor, stopped, drew the curves, evaluated the newest policy and wrote summary.json.
summary=$(run_file summary.json) || die "no summary.json in the monitor's run folder"
python3 - "$summary" <<'PY' || die "summary.json fails its check (its line above)"
import json, sys
s = json.loads(sys.argv[1])
ev = s.get("evaluation") or {}
ok = s["episodes"] > 0 and s["env_steps"] > 0 and s["updates"] > 0 and ev.get("policy_version", 0) >= 2 and len(ev.get("episodes", [])) > 0
print(f"smoke: {'ok' if ok else 'FAIL'}: summary.json: {s['episodes']} episodes, {s['env_steps']} env steps, {s['updates']} updates, "
      f"final evaluation of policy v{ev.get('policy_version')} on {ev.get('map')}: {len(ev.get('episodes', []))} episodes, mean steps {ev.get('mean_steps')}")
sys.exit(0 if ok else 1)
PY
for f in curves.png evals.csv policy.safetensors eval/episode-1.png; do
    [ -n "$(run_file "$f" | head -c 8)" ] || die "the run folder lacks $f"
done
echo "smoke: ok: the run folder also holds curves.png, evals.csv, policy.safetensors and eval/"
# Not `grep -q`: it would stop reading at the match, and under pipefail the SIGPIPE that `logs`
# then gets fails the pipeline.
dc logs --no-color learner 2>/dev/null | grep '"event":"stopped"' >/dev/null || die "the learner did not report its final checkpoint"
echo "smoke: ok: the learner stopped with a final checkpoint"
