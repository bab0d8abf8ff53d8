#!/usr/bin/env bash
# What tests/test_compose.py needs on a Debian 12 (bookworm) machine, installed only when
# missing, so running it again changes nothing:
#
#   debootstrap          deploy/bootstrap-base.sh builds the base image with it (no registry)
#   docker.io            Docker Engine and client (the daemon itself must be running)
#   docker-compose       the compose tool of our machines (1.29, Debian's package)
#   `docker compose`     the v2 plugin, so CI checks the compose file with both tools
#
# The v2 plugin is not in bookworm. Debian 13 (trixie) ships it in its docker-compose
# package, which would replace bookworm's docker-compose 1.29 (same package name), so only
# the plugin binary is taken out of that package: apt downloads it with a private source
# list and state (the machine's own apt configuration is untouched) and the binary goes to
# /usr/local/lib/docker/cli-plugins/. DCRAD_NO_COMPOSE_PLUGIN=1 skips that part.
#
# Needs root (apt-get) and Debian's package mirror; DCRAD_DEBIAN_MIRROR overrides
# http://deb.debian.org/debian for the plugin download.
set -euo pipefail

log() { echo "install-docker-prereqs: $*" >&2; }

if [ "$(id -u)" != 0 ]; then
    log "error: run as root (apt-get)"
    exit 1
fi

# -- Debian packages ------------------------------------------------------------------------
missing=()
command -v debootstrap >/dev/null 2>&1 || missing+=(debootstrap)
command -v docker >/dev/null 2>&1 || missing+=(docker.io)
command -v docker-compose >/dev/null 2>&1 || missing+=(docker-compose)
[ -r /usr/share/keyrings/debian-archive-keyring.gpg ] || missing+=(debian-archive-keyring)
if [ "${#missing[@]}" -gt 0 ]; then
    log "installing ${missing[*]}"
    apt-get update -qq
    DEBIAN_FRONTEND=noninteractive apt-get install -y -qq --no-install-recommends "${missing[@]}" >/dev/null
else
    log "debootstrap, docker and docker-compose are installed"
fi

# -- the docker compose v2 plugin ------------------------------------------------------------
plugin_dir=/usr/local/lib/docker/cli-plugins
if [ "${DCRAD_NO_COMPOSE_PLUGIN:-0}" = 1 ]; then
    log "DCRAD_NO_COMPOSE_PLUGIN=1: not installing the docker compose plugin"
elif docker compose version >/dev/null 2>&1; then
    log "the docker compose plugin is installed ($(docker compose version --short 2>/dev/null || true))"
else
    mirror="${DCRAD_DEBIAN_MIRROR:-http://deb.debian.org/debian}"
    tmp="$(mktemp -d)"
    trap 'rm -rf "$tmp"' EXIT
    mkdir -p "$tmp/lists/partial" "$tmp/cache/archives/partial"
    echo "deb [signed-by=/usr/share/keyrings/debian-archive-keyring.gpg] $mirror trixie main" >"$tmp/sources.list"
    apt_opts=(-o "Dir::Etc::SourceList=$tmp/sources.list" -o Dir::Etc::SourceParts=/dev/null
              -o "Dir::State::Lists=$tmp/lists" -o "Dir::Cache=$tmp/cache" -o APT::Sandbox::User=root)
    log "downloading Debian trixie's docker-compose package for its v2 plugin"
    apt-get "${apt_opts[@]}" update -qq
    (cd "$tmp" && apt-get "${apt_opts[@]}" download -qq docker-compose/trixie)
    dpkg-deb -x "$tmp"/docker-compose_*.deb "$tmp/root"
    install -D -m 0755 "$tmp/root/usr/libexec/docker/cli-plugins/docker-compose" "$plugin_dir/docker-compose"
    log "installed $(docker compose version) in $plugin_dir"
fi

# -- the daemon --------------------------------------------------------------------------------
if ! docker info >/dev/null 2>&1; then
    log "warning: the Docker daemon does not answer; tests/test_compose.py will fail until it runs"
fi
