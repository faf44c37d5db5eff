#!/usr/bin/env bash
# Build every image of the compose stack with podman on a machine that reaches Debian's and PyPI's package
# servers but no container registry (docs/deployment.md, "The podman path"):
#   1. a Debian bookworm root filesystem by debootstrap (minbase + python3, python3-venv, ca-certificates),
#      imported as localhost/thermofield-base:<recipe>; kept as a tarball in $THERMOFIELD_CACHE_DIR;
#   2. thermofield's three images FROM it (docker/Dockerfile, BASE build argument);
#   3. PostgreSQL, RabbitMQ and Mosquitto from Debian's packages (docker/local/*.Dockerfile).
# Everything is cached: the base image and every layer stay in podman's store, pip's downloads in a cache
# mount, so a rebuild with unchanged inputs takes seconds. pip trusts $PIP_CA_BUNDLE (default the host's CA
# bundle): TLS is intercepted on this machine, as behind a plant's inspecting proxy.
set -euo pipefail
cd "$(dirname "$0")/../.."
source docker/local/podman-env.sh

recipe="debootstrap --variant=minbase --include=python3,python3-venv,ca-certificates bookworm; updates, security; policy-rc.d"
recipe_id=$(printf '%s' "$recipe" | sha256sum | cut -c1-12)
base="localhost/thermofield-base:bookworm-$recipe_id"
cache_dir=${THERMOFIELD_CACHE_DIR:-/var/cache/thermofield}
ca_bundle=${PIP_CA_BUNDLE:-/etc/ssl/certs/ca-certificates.crt}
version=$(sed -n 's/^version = "\(.*\)"/\1/p' pyproject.toml)

step() { printf '%s build-images: %s\n' "$(date -u +%T)" "$*"; }

if ! podman image exists "$base"; then
    tarball="$cache_dir/bookworm-minbase-$recipe_id.tar"
    if [ ! -s "$tarball" ]; then
        step "debootstrap bookworm (about a minute)"
        rootfs=$(mktemp -d)
        trap 'rm -rf "$rootfs"' EXIT
        debootstrap --variant=minbase --include=python3,python3-venv,ca-certificates bookworm "$rootfs" \
            > "$rootfs.log" 2>&1 || { tail -20 "$rootfs.log"; exit 1; }
        cat > "$rootfs/etc/apt/sources.list" <<SOURCES
deb http://deb.debian.org/debian bookworm main
deb http://deb.debian.org/debian bookworm-updates main
deb http://deb.debian.org/debian-security bookworm-security main
SOURCES
        # No service starts while a package installs in an image build (as in Debian's official images).
        printf '#!/bin/sh\nexit 101\n' > "$rootfs/usr/sbin/policy-rc.d" && chmod +x "$rootfs/usr/sbin/policy-rc.d"
        rm -rf "$rootfs"/var/cache/apt/archives/*.deb "$rootfs"/var/lib/apt/lists/*
        mkdir -p "$cache_dir"
        tar --numeric-owner -C "$rootfs" -cf "$tarball.part" . && mv "$tarball.part" "$tarball"
        rm -rf "$rootfs" "$rootfs.log"
        trap - EXIT
    fi
    step "import $tarball as $base"
    podman import --quiet --change 'CMD ["/bin/bash"]' "$tarball" "$base" >/dev/null
fi

build() {  # build TAG [podman build arguments...]
    local tag=$1 started=$SECONDS
    shift
    podman build --quiet --network host --layers --ignorefile docker/Dockerfile.dockerignore \
        --build-arg "BASE=$base" --secret "id=pip_ca,src=$ca_bundle" -t "$tag" "$@" . >/dev/null
    step "$tag ($((SECONDS - started)) s)"
}

build localhost/thermofield-postgres:15 -f docker/local/postgres.Dockerfile
build localhost/thermofield-rabbitmq:3.10 -f docker/local/rabbitmq.Dockerfile
build localhost/thermofield-mosquitto:2 -f docker/local/mosquitto.Dockerfile
build "localhost/thermofield:$version" -f docker/Dockerfile --target service
build "localhost/thermofield-gateway:$version" -f docker/Dockerfile --target gateway
build "localhost/thermofield-rerun:$version" -f docker/Dockerfile --target rerun
podman images --filter reference='localhost/thermofield*' --format '{{.Repository}}:{{.Tag}} {{.Size}}'
