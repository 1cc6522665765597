#!/usr/bin/env bash
# deploy/images.sh — builds the cluster's container images from this checkout's binaries (no
# compilation inside Docker; deploy/build.sh builds the same names from source, deploy/Dockerfile):
#
#   mapless-replay:TAG   the replay service       (mapless-replay; glibc only, ~10 MB)
#   mapless-actor:TAG    an actor process         (mapless-actor;  glibc only, ~10 MB)
#   mapless-monitor:TAG  the run folder           (mapless monitor; glibc only, ~10 MB)
#   mapless-learner:TAG  the learner              (mapless-learner; libtorch, several GB)
#   mapless-prometheus:TAG  Prometheus, from Debian's package (see stage_prometheus below)
#
# Each runs as the user `nonroot` (uid and gid 65532), never as root.
#
# Each image is one layer made by `docker import` (as `FROM scratch` + `COPY` would make it): the
# release binary plus exactly the shared libraries `ldd` finds for it (system ones at their paths,
# libtorch and its CUDA libraries in /opt/mapless/lib), so nothing is pulled from a registry and
# the actor and replay images carry no libtorch. The
# learner image runs on CPU: libraries that CUDA loads at run time (cuDNN's engines, NVRTC's
# builtins) are not in the ldd closure, so `device: cuda` needs an image built from a CUDA base.
#
# Each image has a HEALTHCHECK that runs its own binary's `health` subcommand (no shell, no curl:
# the images have neither): `mapless-replay health` and `mapless-learner health` ask the gRPC
# health service (grpc.health.v1.Health) on the default loopback port, `mapless-actor health` asks
# GET /healthz on the actor's metrics address. `MAPLESS_HEALTH_ADDR`, `MAPLESS_HEALTH_TLS_CA_FILE`
# and `MAPLESS_HEALTH_TOKEN_FILE` point the probe elsewhere (deploy/compose.yaml sets them).
#
# Usage: deploy/images.sh [TAG]   (default TAG: local; also $MAPLESS_PROFILE=release|dev, and
# $LIBTORCH to link a libtorch already installed instead of scripts/setup-torch.sh's)
set -euo pipefail
# The images' files keep the modes they are staged with, and their user is not root: whatever
# the caller's umask, staged files are world-readable (and executables world-executable).
umask 022
root="$(cd -- "$(dirname -- "${BASH_SOURCE[0]}")/.." && pwd -P)"
cd "$root"
tag="${1:-local}"
profile="${MAPLESS_PROFILE:-release}"
out_dir="target/$([ "$profile" = dev ] && echo debug || echo "$profile")"
command -v docker >/dev/null || { echo "images.sh: docker not found" >&2; exit 1; }
# A LIBTORCH already set in the environment wins, as in .cargo/config.toml (no install then).
if [ -z "${LIBTORCH:-}" ]; then bash scripts/setup-torch.sh; fi
echo "images.sh: building the binaries ($profile)" >&2
# Without the variables cargo sets for one crate (CARGO_MANIFEST_DIR, CARGO_PKG_*, OUT_DIR, …:
# present when a test runs this): ring's build script reruns when they differ from the last
# build's, and everything above it is recompiled (tests/common/workspace_build.rs).
unset_per_crate=()
while IFS='=' read -r name _; do
    case "$name" in
        CARGO_PKG_* | CARGO_MANIFEST_* | CARGO_CRATE_* | CARGO_BIN_EXE_* | CARGO_CFG_* | OUT_DIR | CARGO_TARGET_TMPDIR | CARGO_PRIMARY_PACKAGE | CARGO_BIN_NAME | CARGO_RUSTC_CURRENT_DIR | CARGO_MAKEFLAGS) unset_per_crate+=(-u "$name") ;;
    esac
done < <(env)
cargo() { env "${unset_per_crate[@]}" cargo "$@"; }
if [ "$profile" = dev ]; then
    # The test suite's own binaries (tests/compose_drill.rs): the suite's target selection, so
    # this finds them built. `-p …` would resolve features differently and rerun ring's build
    # script, making the next workspace build recompile everything (gigabytes of CI's disk).
    cargo build --locked --workspace --all-targets
else
    cargo build --locked --profile "$profile" -p mapless-learner -p mapless-actor -p mapless-replay -p mapless-cli --bins
fi

# The user every image runs as (not root): the uid and gid distroless images call `nonroot`.
# It owns /data and /train (the replay's and the learner's volumes, which take their owner from
# the image when Docker creates them); deploy/certs.sh gives its gid read access to the secrets.
readonly run_uid=65532

# rootfs DIR FOLLOW OWNED...: DIR as one tar on stdout for `docker import`. FOLLOW=1 follows
# links (the libraries of a mapless image are links to their files here); 0 keeps them (a
# Debian package's links name paths inside the image). Everything is root's, but for the folders
# OWNED (relative to DIR), which are the user's.
rootfs() {
    python3 - "$run_uid" "$@" <<'PY'
import os, sys, tarfile
uid, root, follow, owned = int(sys.argv[1]), sys.argv[2], sys.argv[3] == "1", set(sys.argv[4:])
with tarfile.open(fileobj=sys.stdout.buffer, mode="w|", format=tarfile.PAX_FORMAT, dereference=follow, copybufsize=1 << 20) as tar:
    def fail(e):
        raise e
    for top, dirs, files in os.walk(root, followlinks=follow, onerror=fail):
        dirs.sort()
        for name in sorted(dirs) + sorted(files):
            path = os.path.join(top, name)
            arc = os.path.relpath(path, root)
            info = tar.gettarinfo(path, arcname=arc)
            mine = arc in owned
            info.uid = info.gid = uid if mine else 0
            info.uname = info.gname = "nonroot" if mine else "root"
            if info.isfile() and (follow or not os.path.islink(path)):
                with open(path, "rb") as f:
                    tar.addfile(info, f)
            else:
                tar.addfile(info)
PY
}

# stage NAME BINARY [SUBCOMMAND]: a root file system with BINARY (a stripped copy) and symbolic links to its
# libraries, streamed as one dereferenced tar into `docker import`. Neither a copy of libtorch nor
# a build context is written: the learner's 2.7 GB land on disk once, as the image's one layer
# (a build context cost three times that, and a CI machine once ran out of disk on it).
stage() {
    local name="$1" bin="$2" sub="${3:+\"$3\", }" dir="target/images/$1" lib dest
    rm -rf "$dir"
    mkdir -p "$dir/root/usr/local/bin" "$dir/root/opt/mapless/lib" "$dir/root/etc" "$dir/root/tmp" "$dir/root/data" "$dir/root/train" "$dir/root/runs" "$dir/root/tmp/iceoryx2"
    chmod 1777 "$dir/root/tmp"
    chmod 0750 "$dir/root/data" "$dir/root/train" "$dir/root/runs" "$dir/root/tmp/iceoryx2"
    printf 'root:x:0:0:root:/root:/sbin/nologin\nnonroot:x:%s:%s:nonroot:/data:/sbin/nologin\n' "$run_uid" "$run_uid" > "$dir/root/etc/passwd"
    printf 'root:x:0:\nnonroot:x:%s:\n' "$run_uid" > "$dir/root/etc/group"
    cp "$out_dir/$bin" "$dir/root/usr/local/bin/"
    # Symbols stay (panics still name their functions); the debug sections (line tables in
    # release, full DWARF in dev) do not: 50 MB of a 64 MB actor image.
    objcopy --strip-debug "$dir/root/usr/local/bin/$bin"
    # `ldd` lines: "libx.so => /path/libx.so (0x…)" and "/lib64/ld-linux-x86-64.so.2 (0x…)".
    ldd "$out_dir/$bin" | awk '$2 == "=>" && $3 ~ /^\// {print $3} $1 ~ /^\// {print $1}' | while read -r lib; do
        case "$lib" in
            /lib/*|/lib64/*|/usr/lib/*) dest="$dir/root$(dirname "$lib")" ;;
            *) dest="$dir/root/opt/mapless/lib" ;;
        esac
        mkdir -p "$dest"
        ln -sfn "$(readlink -f "$lib")" "$dest/$(basename "$lib")"
    done
    if ldd "$out_dir/$bin" | grep -q "not found"; then
        echo "images.sh: $bin has unresolved libraries:" >&2
        ldd "$out_dir/$bin" | grep "not found" >&2
        exit 1
    fi
    echo "images.sh: mapless-$name:$tag ($(du -shL "$dir/root" | cut -f1))" >&2
    rootfs "$dir/root" 1 data train runs tmp/iceoryx2 |
        docker import \
            --change 'ENV LD_LIBRARY_PATH=/opt/mapless/lib' \
            --change "USER $run_uid:$run_uid" \
            --change "LABEL org.opencontainers.image.title=\"mapless-$name\" org.opencontainers.image.source=\"mapless\"" \
            --change "HEALTHCHECK --interval=10s --timeout=5s --start-period=60s --retries=3 CMD [\"/usr/local/bin/$bin\", $sub\"health\"]" \
            --change "ENTRYPOINT [\"/usr/local/bin/$bin\"${3:+, \"$3\"}]" \
            - "mapless-$name:$tag" >/dev/null
}

# mapless-prometheus:TAG — Prometheus from the host's Debian (or Ubuntu) package archive (a Go
# binary, glibc only; 2.42 on Debian 12) with the JavaScript its web UI and consoles load, the
# example console libraries, and nothing else; deploy/compose.yaml mounts its configuration and
# the mapless console. The packages are fetched once into target/images/debs with `apt-get
# download` (Debian's archive is reachable where no registry is), so this needs apt-get and
# dpkg-deb; no HEALTHCHECK (the image has no client to ask /-/healthy).
stage_prometheus() {
    local dir=target/images/prometheus debs=target/images/debs lib
    local pkgs=(prometheus libjs-bootstrap4 libjs-popper.js libjs-d3 libjs-rickshaw libjs-eonasdan-bootstrap-datetimepicker libjs-jquery
        libjs-jquery-hotkeys libjs-moment libjs-moment-timezone libjs-mustache fonts-glyphicons-halflings)
    mkdir -p "$debs"
    if [ "$(ls "$debs"/*.deb 2>/dev/null | wc -l)" -lt "${#pkgs[@]}" ]; then
        ( cd "$debs" && { apt-get download "${pkgs[@]}" >/dev/null 2>&1 || { apt-get update >/dev/null && apt-get download "${pkgs[@]}" >/dev/null; }; } ) ||
            { echo "images.sh: cannot fetch Debian's prometheus package (apt-get download ${pkgs[*]})" >&2; exit 1; }
    fi
    rm -rf "$dir"
    mkdir -p "$dir/root/etc/prometheus" "$dir/root/prometheus" "$dir/root/tmp"
    chmod 1777 "$dir/root/tmp"
    for deb in "$debs"/*.deb; do dpkg-deb -x "$deb" "$dir/root"; done
    rm -rf "$dir/root/etc/init.d" "$dir/root/etc/default" "$dir/root/etc/logrotate.d" "$dir/root/lib/systemd" "$dir/root/usr/share/man" "$dir/root/usr/share/doc/"lib* \
        "$dir/root/usr/bin/promtool"
    cp -r "$dir/root/usr/share/doc/prometheus/examples/console_libraries" "$dir/root/etc/prometheus/"
    printf 'root:x:0:0:root:/root:/sbin/nologin\nnonroot:x:%s:%s:nonroot:/prometheus:/sbin/nologin\n' "$run_uid" "$run_uid" > "$dir/root/etc/passwd"
    printf 'root:x:0:\nnonroot:x:%s:\n' "$run_uid" > "$dir/root/etc/group"
    # (A statically linked build has no libraries: ldd fails, and nothing is copied.)
    { ldd "$dir/root/usr/bin/prometheus" || true; } | awk '$2 == "=>" && $3 ~ /^\// {print $3} $1 ~ /^\// {print $1}' | while read -r lib; do
        mkdir -p "$dir/root$(dirname "$lib")"
        cp -L "$lib" "$dir/root$lib"
    done
    echo "images.sh: mapless-prometheus:$tag ($(du -sh "$dir/root" | cut -f1); $(dpkg-deb -f "$debs"/prometheus_*.deb Version))" >&2
    rootfs "$dir/root" 0 prometheus |
        docker import \
            --change "USER $run_uid:$run_uid" \
            --change 'LABEL org.opencontainers.image.title="mapless-prometheus" org.opencontainers.image.source="mapless"' \
            --change 'ENTRYPOINT ["/usr/bin/prometheus"]' \
            - "mapless-prometheus:$tag" >/dev/null
}

stage replay mapless-replay
stage actor mapless-actor
# The `mapless` command as `mapless monitor` (the compose cluster's run folder; no libtorch).
stage monitor mapless monitor
stage learner mapless-learner
stage_prometheus
docker images --format '{{.Repository}}:{{.Tag}}  {{.Size}}' | grep -E "^mapless-(replay|actor|monitor|learner|prometheus):$tag " >&2
