#!/usr/bin/env bash
# The image dcrad:latest, built offline: the wheels (deploy/build-wheels.sh), the compose build,
# then the dangling dcrad images that earlier builds left behind.  Every rebuild moves the tag
# dcrad:latest to a new image and leaves the old one as <none> (289 MB each); only images with
# dcrad's label (deploy/Dockerfile) are pruned, nothing else on the machine.
#
#   deploy/build-image.sh                    # with `docker compose`, else `docker-compose`
#   deploy/build-image.sh docker-compose     # with the given compose command
set -euo pipefail
root="$(cd "$(dirname "$0")/.." && pwd)"
cd "$root"
if [ "$#" -gt 0 ]; then
    compose=("$@")
elif docker compose version >/dev/null 2>&1; then
    compose=(docker compose)
else
    compose=(docker-compose)
fi
bash deploy/build-wheels.sh
"${compose[@]}" -f docker-compose.yml build
docker image prune --force --filter "label=org.opencontainers.image.title=dcrad" >/dev/null
