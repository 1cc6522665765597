#!/usr/bin/env bash
# deploy/swarm.sh — drills deploy/stack.yaml on what one machine allows, a single-node swarm:
#
#   1. `docker swarm init` (unless this engine is in a swarm already), the node labelled for the
#      replay and the learner, secrets from deploy/certs.sh, `docker stack deploy`;
#   2. every service's task runs and turns healthy (replay, learner, monitor, 2 actors,
#      Prometheus), none as root; the learner updates;
#   3. 2 actor replicas, registered as actor-1 and actor-2 (their task slots), write into the
#      replay (its /metrics, read inside its container's network namespace);
#   4. `docker service scale <stack>_actor=4`: 4 distinct actor ids write, and Prometheus (found
#      by DNS round robin, no edit) scraped all four;
#   5. an actor's process killed with SIGKILL: the swarm starts a new task on the same slot, with
#      the same host name, so it gets its replay slot back and writes under a new incarnation;
#   6. `docker stack rm`, its volumes removed, and the swarm left if this drill made it.
#
# Usage: deploy/swarm.sh   (SKIP_IMAGES=1 reuses built images, MAPLESS_TAG picks them; root)
set -euo pipefail
here="$(cd -- "$(dirname -- "${BASH_SOURCE[0]}")" && pwd -P)"
cd "$here"
export MAPLESS_TAG="${MAPLESS_TAG:-local}"
stack=mapless-swarm
# wait_for and die (deploy/lib.sh; its compose helpers go unused here).
me=swarm project=$stack
source ./lib.sh
[ "${SKIP_IMAGES:-}" = 1 ] || ./images.sh "$MAPLESS_TAG" || die "deploy/images.sh failed (its output is above)"
./certs.sh || die "deploy/certs.sh failed (its output is above)"
say() { echo "swarm: $*"; }
made_swarm=0
if [ "$(docker info --format '{{.Swarm.LocalNodeState}}')" != active ]; then
    docker swarm init --advertise-addr 127.0.0.1 >/dev/null
    made_swarm=1
    say "initialised a single-node swarm"
fi
node=$(docker info --format '{{.Swarm.NodeID}}')
finish() {
    local rc=$?
    docker stack rm "$stack" >/dev/null 2>&1 || true
    # Tasks, then the network and volumes, go after a few seconds.
    for _ in $(seq 60); do [ -z "$(docker ps -aq --filter "label=com.docker.stack.namespace=$stack")" ] && break; sleep 1; done
    for _ in $(seq 30); do docker volume rm $(docker volume ls -q --filter "label=com.docker.stack.namespace=$stack") >/dev/null 2>&1 || true
        [ -z "$(docker volume ls -q --filter "label=com.docker.stack.namespace=$stack")" ] && break; sleep 1; done
    docker node update --label-rm mapless.replay --label-rm mapless.learner "$node" >/dev/null 2>&1 || true
    if [ "$made_swarm" = 1 ]; then docker swarm leave --force >/dev/null 2>&1 || true; fi
    left="$(docker ps -aq --filter "label=com.docker.stack.namespace=$stack"; docker volume ls -q --filter "label=com.docker.stack.namespace=$stack"; docker network ls -q --filter "label=com.docker.stack.namespace=$stack")"
    if [ -n "$left" ]; then say "left behind: $left"; rc=1; fi
    if [ $rc -eq 0 ]; then say "PASS"; else say "FAIL"; for s in replay learner monitor actor; do docker service logs --tail 15 "${stack}_$s" 2>&1 | sed "s/^/  /"; done; print_failures; fi
    forget_failures
    exit $rc
}
trap finish EXIT
trap 'failed "failed at line $LINENO: $BASH_COMMAND (exit $?)"' ERR
docker node update --label-add mapless.replay=true --label-add mapless.learner=true "$node" >/dev/null
docker stack deploy --resolve-image never -c stack.yaml "$stack" >/dev/null
say "deployed $stack"

# The running containers of a service.
tasks() { docker ps -q --filter "label=com.docker.swarm.service.name=${stack}_$1" --filter status=running; }
healthy() {
    local s c n
    for s in replay learner monitor actor; do
        n=0
        for c in $(tasks "$s"); do
            [ "$(docker inspect -f '{{.State.Health.Status}}' "$c")" = healthy ] || return 1
            n=$((n + 1))
        done
        [ "$n" -ge 1 ] || return 1
    done
    [ -n "$(tasks prometheus)" ]
}
in_netns() { local c=$1; shift; nsenter -t "$(docker inspect -f '{{.State.Pid}}' "$c")" -n "$@"; }
replay_metrics() { in_netns "$(tasks replay | head -1)" curl -sf --max-time 5 -H "Authorization: Bearer $(cat secrets/metrics-token)" http://127.0.0.1:9464/metrics; }
# Actor ids whose row counts grow over 8 s: "actor-<slot>-…".
writing() { growing_ids replay_metrics; }
writers() { [ "$(writing | wc -l)" -ge "$1" ]; }
learner_updates() { docker service logs "${stack}_learner" 2>/dev/null | grep -o '"updates":[0-9]*' | tail -1 | cut -d: -f2; }
learner_learns() { [ "$(learner_updates)" -gt 100 ] 2>/dev/null; }
scraped_actors() {
    in_netns "$(tasks prometheus | head -1)" curl -sfG --max-time 5 --data-urlencode 'query=up{job="actor"} == 1' http://127.0.0.1:9090/api/v1/query |
        python3 -c 'import json,sys; print(len(json.load(sys.stdin)["data"]["result"]))' 2>/dev/null
}
prom_sees() { [ "$(scraped_actors)" = "$1" ]; }

wait_for 240 "every service's task runs and is healthy" healthy
for c in $(docker ps -q --filter "label=com.docker.stack.namespace=$stack"); do
    uid=$(ps -o uid= -p "$(docker inspect -f '{{.State.Pid}}' "$c")" | tr -d ' ')
    [ "$uid" = 65532 ] || die "$(docker inspect -f '{{.Name}}' "$c") runs as uid $uid"
done
say "ok: no task runs as root"
wait_for 300 "the learner updates (> 100)" learner_learns
wait_for 120 "2 actor replicas write" writers 2
hosts=$(for c in $(tasks actor); do docker inspect -f '{{.Config.Hostname}}' "$c"; done | sort | tr '\n' ' ')
[ "$hosts" = "actor-1 actor-2 " ] || die "actor host names '$hosts', expected actor-1 actor-2"
say "ok: replicas named by task slot: $hosts; writing: $(writing | tr '\n' ' ')"

docker service scale --detach "${stack}_actor=4" >/dev/null
wait_for 180 "scaled to 4: 4 actor ids write" writers 4
wait_for 60 "Prometheus scraped all 4 actor replicas (DNS round robin)" prom_sees 4
say "writing: $(writing | tr '\n' ' ')"

victim=$(for c in $(tasks actor); do echo "$(docker inspect -f '{{.Config.Hostname}}' "$c") $c"; done | sort | head -1)
name=${victim% *}; cid=${victim#* }
old_id=$(docker logs "$cid" 2>&1 | grep -o 'actor_id=actor-[^ ]*' | tail -1 | cut -d= -f2)
say "kill -9 $name's process (task container ${cid:0:12}, $old_id)"
kill -9 "$(docker inspect -f '{{.State.Pid}}' "$cid")"
replaced() {
    local c
    for c in $(tasks actor); do
        [ "$c" != "$cid" ] && [ "$(docker inspect -f '{{.Config.Hostname}}' "$c")" = "$name" ] && { echo "$c"; return 0; }
    done
    return 1
}
wait_for 120 "the swarm started a new task as $name" replaced >/dev/null
new=$(replaced)
new_id() { docker logs "$new" 2>&1 | grep -o 'actor_id=actor-[^ ]*' | tail -1 | cut -d= -f2; }
writes_again() { local id; id=$(new_id); [ -n "$id" ] && [ "$id" != "$old_id" ] && writing | grep -qx "$id"; }
wait_for 120 "its new incarnation writes" writes_again
old_slot=$(cut -d- -f2 <<<"$old_id"); new_slot=$(cut -d- -f2 <<<"$(new_id)")
[ "$old_slot" = "$new_slot" ] || die "$name came back on replay slot $new_slot, not $old_slot"
say "ok: $name came back on replay slot $new_slot as $(new_id)"
