#!/usr/bin/env bash
# A Docker engine for the Compose test (tests/compose) on a Debian machine: installs what is missing and starts
# dockerd when it is not running. Idempotent; .ci/run calls it. Needs root (or sudo).
#
# posemetry's Dockerfile takes the model files as a named build context (`docker build --build-context models=DIR`),
# which needs BuildKit 0.10 or newer inside the engine (Docker 23+). Debian bookworm's docker.io is 20.10 and
# refuses it ("unsupported frontend capability moby.buildkit.frontend.contexts"), and bookworm has neither buildx
# nor Compose v2. So the engine, its CLI, buildx and Compose v2 are Debian trixie's packages (docker.io 26.1,
# docker-buildx 0.13, docker-compose 2.26): their .deb files are fetched with a private apt configuration (the
# machine's own sources stay as they are) and installed with their dependencies from the machine's own release
# (containerd, runc, tini, iptables). mmdebstrap builds the stand-in base images (tests/compose/standins).
#
# Environment: POSEMETRY_DEBIAN_MIRROR (default http://deb.debian.org/debian), POSEMETRY_DOCKERD_LOG (where a
# dockerd started here logs, default /tmp/posemetry-dockerd.log).
set -euo pipefail

sudo=""
[ "$(id -u)" -eq 0 ] || sudo="sudo"
mirror=${POSEMETRY_DEBIAN_MIRROR:-http://deb.debian.org/debian}
log=${POSEMETRY_DOCKERD_LOG:-/tmp/posemetry-dockerd.log}
say() { echo "setup-docker: $*" >&2; }

# An engine that builds the Dockerfile as documented, and the two plugins the test drives.
engine_ok() {
    command -v dockerd >/dev/null && command -v docker >/dev/null || return 1
    local major
    major=$(dockerd --version | sed -nE 's/^Docker version ([0-9]+).*/\1/p')
    [ -n "$major" ] && [ "$major" -ge 23 ] || return 1
    docker buildx version >/dev/null 2>&1 && docker compose version >/dev/null 2>&1
}

started=$SECONDS
if ! engine_ok || ! command -v mmdebstrap >/dev/null; then
    debs=()
    if ! engine_ok; then
        apt_dir=$(mktemp -d)
        trap 'rm -rf "$apt_dir"' EXIT
        mkdir -p "$apt_dir/lists/partial" "$apt_dir/archives/partial"
        echo "deb [signed-by=/usr/share/keyrings/debian-archive-keyring.gpg] $mirror trixie main" >"$apt_dir/sources.list"
        private=(
            -o "Dir::Etc::SourceList=$apt_dir/sources.list" -o "Dir::Etc::SourceParts=$apt_dir/none"
            -o "Dir::State::Lists=$apt_dir/lists" -o "Dir::Cache::Archives=$apt_dir/archives"
            -o "APT::Sandbox::User=root"
        )
        say "fetching docker.io, docker-cli, docker-buildx and docker-compose from Debian trixie"
        $sudo apt-get "${private[@]}" update -qq
        (cd "$apt_dir" && $sudo apt-get "${private[@]}" download -qq docker.io docker-cli docker-buildx docker-compose)
        debs=("$apt_dir"/*.deb)
    fi
    $sudo apt-get update -qq
    $sudo env DEBIAN_FRONTEND=noninteractive apt-get install -y -qq --no-install-recommends "${debs[@]}" mmdebstrap \
        >/dev/null
    engine_ok || {
        say "the installed engine still lacks BuildKit named contexts, buildx or Compose v2"
        exit 1
    }
    say "installed in $((SECONDS - started)) s: $(dockerd --version)"
fi

if ! docker info >/dev/null 2>&1; then
    if [ -d /run/systemd/system ]; then
        $sudo systemctl start docker
    else
        say "starting dockerd (log: $log)"
        $sudo sh -c "setsid dockerd >'$log' 2>&1 </dev/null &"
    fi
    for _ in $(seq 60); do
        docker info >/dev/null 2>&1 && break
        sleep 1
    done
    docker info >/dev/null 2>&1 || {
        say "dockerd did not start:"
        tail -n 30 "$log" >&2 || true
        exit 1
    }
fi
say "ready in $((SECONDS - started)) s: engine $(docker info --format '{{.ServerVersion}}'), $(docker compose version)"
