#!/usr/bin/env bash
# Local stand-ins for the public base images that posemetry's Dockerfile and docker-compose.yml name, for machines
# that cannot pull from a registry of images (Docker Hub): `python:3.11-slim` (the Dockerfile's base), `redis:7`
# and PostgreSQL, built from Debian bookworm's packages. The Dockerfile and the Compose file stay exactly what users
# run; this only puts images under the names they use into the local image store.
#
# An image that is already present locally, or can be pulled, is used as it is; only the others are built. Debian
# bookworm has no PostgreSQL 16, so where `postgres:16` is unavailable the stand-in is PostgreSQL 15, tagged
# `postgres:15`, and the script's one line on stdout says which PostgreSQL image to use:
#     POSEMETRY_POSTGRES_IMAGE=postgres:16   or   POSEMETRY_POSTGRES_IMAGE=postgres:15
# (docker-compose.yml reads that variable). Progress and timings go to stderr.
#
# How: mmdebstrap (or, slower, debootstrap) makes one minimal bookworm root, `docker import` turns it into the base
# image `posemetry-standin/debian:bookworm`, and the three Dockerfiles beside this script install python3,
# redis-server and postgresql-15 on it (in parallel). Each stand-in is labelled `org.posemetry.standin`
# (`docker image ls --filter label=org.posemetry.standin`).
#
# Usage: tests/compose/standins/build.sh [--rebuild]    (--rebuild: build the stand-ins again, e.g. after editing
# their Dockerfiles; images that are not stand-ins are never replaced). Needs root for debootstrap/mmdebstrap.
# Environment: DOCKER (the client, default `docker`), POSEMETRY_STANDIN_MIRROR (Debian mirror, default
# http://deb.debian.org/debian) and POSEMETRY_STANDIN_SECURITY_MIRROR (default http://deb.debian.org/debian-security).
set -euo pipefail

here=$(cd "$(dirname "${BASH_SOURCE[0]}")" && pwd)
docker=${DOCKER:-docker}
mirror=${POSEMETRY_STANDIN_MIRROR:-http://deb.debian.org/debian}
security=${POSEMETRY_STANDIN_SECURITY_MIRROR:-http://deb.debian.org/debian-security}
base=posemetry-standin/debian:bookworm
rebuild=0
[ "${1:-}" = --rebuild ] && rebuild=1

say() { echo "standins: $*" >&2; }

# One run at a time on a machine: a second one waits here, then finds the images built.
exec 9>"${TMPDIR:-/tmp}/posemetry-standins.lock"
flock 9

is_standin() { [ -n "$($docker image inspect -f '{{index .Config.Labels "org.posemetry.standin"}}' "$1" 2>/dev/null)" ]; }
# Present and usable as it is (a stand-in counts unless --rebuild).
have() { $docker image inspect "$1" >/dev/null 2>&1 && { [ "$rebuild" = 0 ] || ! is_standin "$1"; }; }
available() {
    have "$1" && return 0
    is_standin "$1" && return 1 # --rebuild: do not replace a stand-in by pulling
    $docker pull -q "$1" >/dev/null 2>&1 && say "pulled $1"
}

need=() # image=Dockerfile
available python:3.11-slim || need+=("python:3.11-slim=python.Dockerfile")
available redis:7 || need+=("redis:7=redis.Dockerfile")
postgres=postgres:16
if ! available postgres:16; then
    postgres=postgres:15
    available postgres:15 || need+=("postgres:15=postgres.Dockerfile")
fi

if [ ${#need[@]} -eq 0 ]; then
    say "python:3.11-slim, redis:7 and $postgres are present"
    echo "POSEMETRY_POSTGRES_IMAGE=$postgres"
    exit 0
fi

started=$SECONDS
if ! have "$base"; then
    sources=("deb $mirror bookworm main" "deb $mirror bookworm-updates main" "deb $security bookworm-security main")
    change=(-c 'CMD ["bash"]' -c "LABEL org.posemetry.standin=\"Debian bookworm minbase\"")
    if command -v mmdebstrap >/dev/null; then
        say "mmdebstrap bookworm -> $base"
        mmdebstrap --quiet --variant=minbase bookworm - "${sources[@]}" | $docker import "${change[@]}" - "$base" >/dev/null
    elif command -v debootstrap >/dev/null; then
        say "debootstrap bookworm -> $base"
        root=$(mktemp -d)
        debootstrap --variant=minbase bookworm "$root" "$mirror" >&2
        printf '%s\n' "${sources[@]}" >"$root/etc/apt/sources.list"
        rm -rf "$root"/var/cache/apt/archives/*.deb "$root"/var/lib/apt/lists/*
        tar -C "$root" -c . | $docker import "${change[@]}" - "$base" >/dev/null
        rm -rf "$root"
    else
        say "needs mmdebstrap or debootstrap (apt-get install mmdebstrap)"
        exit 1
    fi
    say "base image in $((SECONDS - started)) s"
fi

logs=$(mktemp -d)
# The certificate authorities this machine trusts beyond Debian's go into the Python stand-in (see its Dockerfile).
host_ca=$(mktemp -d)
trap 'rm -rf "$logs" "$host_ca"' EXIT
find /usr/local/share/ca-certificates -name '*.crt' -exec cp {} "$host_ca/" \; 2>/dev/null || true
pids=()
for entry in "${need[@]}"; do
    image=${entry%%=*} dockerfile=${entry#*=}
    say "building $image ($dockerfile)"
    $docker build --progress=plain --build-arg BASE="$base" --build-context host-ca="$host_ca" \
        -f "$here/$dockerfile" -t "$image" "$here" \
        >"$logs/$dockerfile.log" 2>&1 &
    pids+=($!)
done
failed=0
for i in "${!need[@]}"; do
    entry=${need[$i]}
    if wait "${pids[$i]}"; then
        say "built ${entry%%=*} ($((SECONDS - started)) s since start)"
    else
        failed=1
        say "building ${entry%%=*} failed:"
        tail -n 40 "$logs/${entry#*=}.log" >&2
    fi
done
[ "$failed" = 0 ] || exit 1
say "done in $((SECONDS - started)) s"
echo "POSEMETRY_POSTGRES_IMAGE=$postgres"
