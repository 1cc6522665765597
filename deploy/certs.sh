#!/usr/bin/env bash
# deploy/certs.sh — a private CA, one server certificate for the services' host names, and a
# bearer token per role (actor-token, learner-token), and the token Prometheus sends to every
# /metrics (metrics-token), in deploy/secrets/ (git-ignored). Services
# that listen beyond loopback refuse to start without TLS and a token; this makes both for a
# compose or multi-host cluster.
#
# Usage: deploy/certs.sh [NAME...]   (default names: replay learner monitor localhost)
# Existing files are kept (delete deploy/secrets/ to start over), but for a server certificate
# that lacks one of the names, which is issued again. deploy/compose.yaml mounts
# single files: actors get ca.pem and actor-token (insert, register, subscribe: it cannot read
# the replay), the replay and the learner also learner-token, server.pem and server.key (each
# service checks both tokens); the CA's key (ca.key) never leaves the host. A `token` left by
# an older certs.sh is no longer used. The containers run as uid/gid 65532, so the files they
# mount belong to group 65532 (mode 640); changing a file's group needs root.
set -euo pipefail
umask 077
dir="$(cd -- "$(dirname -- "${BASH_SOURCE[0]}")" && pwd -P)/secrets"
mkdir -p "$dir"
cd "$dir"
if [ $# -gt 0 ]; then names=("$@"); else names=(replay learner monitor localhost); fi
if [ ! -s ca.pem ]; then
    openssl req -x509 -newkey ec -pkeyopt ec_paramgen_curve:P-256 -nodes -days 825 \
        -subj "/CN=mapless cluster CA" -keyout ca.key -out ca.pem 2>/dev/null
fi
# A new CA needs a new server certificate, and so does a name the certificate lacks (an older
# certs.sh made it without `monitor`).
covers_names() {
    local have n
    have=$(openssl x509 -in server.pem -noout -ext subjectAltName 2>/dev/null | tail -1 | tr -d ' ')
    for n in "${names[@]}"; do
        case ",$have," in *",DNS:$n,"*) ;; *) return 1 ;; esac
    done
}
if [ ! -s server.pem ] || [ ca.pem -nt server.pem ] || ! covers_names; then
    san=$(printf 'DNS:%s,' "${names[@]}"); san="${san%,},IP:127.0.0.1"
    openssl req -newkey ec -pkeyopt ec_paramgen_curve:P-256 -nodes -subj "/CN=${names[0]}" \
        -keyout server.key -out server.csr 2>/dev/null
    printf 'subjectAltName=%s\nbasicConstraints=CA:FALSE\nkeyUsage=digitalSignature\nextendedKeyUsage=serverAuth\n' "$san" > server.ext
    openssl x509 -req -in server.csr -CA ca.pem -CAkey ca.key -CAcreateserial -days 825 \
        -extfile server.ext -out server.pem 2>/dev/null
    rm -f server.csr server.ext
fi
for t in actor-token learner-token metrics-token; do
    [ -s "$t" ] || { openssl rand -hex 32 | tr -d '\n' > "$t"; }
done
chmod 600 ca.key
chmod 644 ca.pem server.pem
# The containers run as uid/gid 65532 (deploy/images.sh), not root: the files they mount are
# readable by that group and by nobody else; ca.key stays the host owner's alone.
readonly run_gid=65532
if ! chgrp "$run_gid" server.key actor-token learner-token metrics-token 2>/dev/null; then
    echo "certs.sh: cannot give group $run_gid (the containers' user) server.key and the tokens: run as root, or 'sudo chgrp $run_gid $dir/{server.key,actor-token,learner-token,metrics-token}'" >&2
    exit 1
fi
chmod 640 server.key actor-token learner-token metrics-token
echo "certs.sh: $dir: ca.pem, server.pem/server.key ($(openssl x509 -in server.pem -noout -ext subjectAltName | tail -1 | tr -d ' ')), actor-token, learner-token, metrics-token" >&2
