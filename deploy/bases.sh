#!/usr/bin/env bash
# deploy/bases.sh — makes, without a container registry, the two base images that
# deploy/Dockerfile starts from, under the names the Dockerfile uses:
#
#   debian:bookworm-slim        a minimal Debian 12 root, made by mmdebstrap from Debian's
#                               archive (the runtime stage of every mapless image)
#   rust:1.95-slim-bookworm     that root + gcc and libc6-dev (as the official image has them) +
#                               this machine's Rust 1.95 toolchain (cargo, rustc, rust-std)
#                               under /usr/local/cargo (the build stage)
#
# Where a registry is reachable you do not need this: `docker build` pulls the official images of
# those names. Here none is (deploy/README's "Images"), but Debian's archive and crates.io are, so
# the same Dockerfile builds from these. An existing image of either name is kept unless
# --force is given (then both are remade).
#
# Needs: docker, mmdebstrap (apt-get install mmdebstrap; it is installed here if missing and
# this runs as root), and a Rust 1.95 toolchain on the host (`rustc --print sysroot`).
#
# Usage: deploy/bases.sh [--force]
set -euo pipefail
umask 022
root="$(cd -- "$(dirname -- "${BASH_SOURCE[0]}")/.." && pwd -P)"
cd "$root"
readonly suite=bookworm rust_version=1.95
readonly debian_image="debian:$suite-slim" rust_image="rust:$rust_version-slim-$suite"
force=0
case "${1:-}" in
    --force) force=1 ;;
    "") ;;
    *) echo "usage: deploy/bases.sh [--force]" >&2; exit 2 ;;
esac
say() { printf 'bases.sh: %s\n' "$*" >&2; }
die() { printf 'bases.sh: error: %s\n' "$*" >&2; exit 1; }
have_image() { [ "$force" = 0 ] && docker image inspect "$1" >/dev/null 2>&1; }
command -v docker >/dev/null || die "docker not found"

# 1. debian:bookworm-slim. minbase is essential + apt; documentation, manuals and locales are
# left out as the official slim image leaves them out, and so are apt's lists (`apt-get update`
# first, as with the official image).
if have_image "$debian_image"; then
    say "$debian_image exists (--force remakes it)"
else
    if ! command -v mmdebstrap >/dev/null; then
        [ "$(id -u)" = 0 ] || die "mmdebstrap not found; apt-get install mmdebstrap"
        say "installing mmdebstrap (apt-get)"
        apt-get install -y mmdebstrap >/dev/null 2>&1 || { apt-get update >/dev/null && apt-get install -y mmdebstrap >/dev/null; } ||
            die "cannot install mmdebstrap"
    fi
    mirror="${MAPLESS_DEBIAN_MIRROR:-http://deb.debian.org}"
    say "$debian_image: mmdebstrap $suite from $mirror (about a minute)"
    mmdebstrap --quiet --variant=minbase --include=ca-certificates \
        --dpkgopt='path-exclude=/usr/share/doc/*' --dpkgopt='path-include=/usr/share/doc/*/copyright' \
        --dpkgopt='path-exclude=/usr/share/man/*' --dpkgopt='path-exclude=/usr/share/info/*' \
        --dpkgopt='path-exclude=/usr/share/locale/*' --dpkgopt='path-include=/usr/share/locale/locale.alias' \
        --aptopt='Acquire::Languages "none"' \
        --customize-hook='rm -rf "$1"/var/lib/apt/lists/* "$1"/var/cache/apt/*.bin "$1"/var/log/*.log' \
        "$suite" - \
        "deb $mirror/debian $suite main" "deb $mirror/debian $suite-updates main" "deb $mirror/debian-security $suite-security main" |
        docker import --change 'CMD ["bash"]' \
            --change "LABEL org.opencontainers.image.description=\"Debian $suite minbase, made by mapless deploy/bases.sh\"" \
            - "$debian_image" >/dev/null
fi

# 2. rust:1.95-slim-bookworm: the host's toolchain, copied (bin/cargo, bin/rustc, lib/ with
# rust-std for the host), where the official image puts it (CARGO_HOME=/usr/local/cargo, on PATH).
if have_image "$rust_image"; then
    say "$rust_image exists (--force remakes it)"
else
    command -v rustc >/dev/null || die "rustc not found: a Rust $rust_version toolchain is copied from the host"
    sysroot="$(rustc --print sysroot)"
    version="$("$sysroot/bin/rustc" --version | awk '{print $2}')"
    case "$version" in "$rust_version".*) ;; *) die "the host's rustc is $version, not $rust_version.x (set RUSTUP_TOOLCHAIN=$rust_version)" ;; esac
    ctx="target/images/rust-base"
    rm -rf "$ctx"
    mkdir -p "$ctx/cargo/bin"
    cp "$sysroot/bin/cargo" "$sysroot/bin/rustc" "$sysroot/bin/rustdoc" "$ctx/cargo/bin/"
    cp -a "$sysroot/lib" "$ctx/cargo/lib"
    rm -rf "$ctx/cargo/lib/rustlib/src" "$ctx/cargo/lib/rustlib/"manifest-* "$ctx/cargo/lib/rustlib/components"
    # The host's own certificate authorities (/usr/local/share/ca-certificates: e.g. the CA of an
    # egress proxy that re-signs TLS, as on the machines this project is built on) are trusted in
    # the build stage too, so cargo reaches crates.io and pip PyPI from inside `docker build`.
    mkdir -p "$ctx/ca"
    cp /usr/local/share/ca-certificates/*.crt "$ctx/ca/" 2>/dev/null || true
    [ -z "$(ls "$ctx/ca")" ] || say "$rust_image: trusting the host's extra CAs: $(cd "$ctx/ca" && echo *)"
    cat > "$ctx/Dockerfile" <<EOF
FROM $debian_image
RUN apt-get update && apt-get install -y --no-install-recommends ca-certificates gcc libc6-dev && rm -rf /var/lib/apt/lists/*
COPY ca/ /usr/local/share/ca-certificates/
RUN update-ca-certificates >/dev/null
ENV PIP_CERT=/etc/ssl/certs/ca-certificates.crt
ENV RUSTUP_HOME=/usr/local/rustup CARGO_HOME=/usr/local/cargo PATH=/usr/local/cargo/bin:/usr/local/sbin:/usr/local/bin:/usr/sbin:/usr/bin:/sbin:/bin RUST_VERSION=$version
COPY cargo/ /usr/local/cargo/
RUN cargo --version && rustc --version
EOF
    say "$rust_image: Rust $version from $sysroot ($(du -sh "$ctx/cargo" | cut -f1))"
    # The legacy builder: it needs no buildx plugin (Debian's docker.io has none), and this
    # Dockerfile is one stage.
    # (The legacy builder warns that it is deprecated; its log is shown only if it fails.)
    if ! DOCKER_BUILDKIT=0 docker build --quiet -t "$rust_image" "$ctx" >/dev/null 2>"$ctx.log"; then
        cat "$ctx.log" >&2
        die "docker build of $rust_image failed"
    fi
    rm -f "$ctx.log"
    rm -rf "$ctx"
fi
docker images --format '{{.Repository}}:{{.Tag}}  {{.Size}}' | grep -E "^($debian_image|$rust_image) " >&2
