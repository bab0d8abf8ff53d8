#!/usr/bin/env bash
# Build the Debian base image for deploy/Dockerfile without any image registry.
#
#   deploy/bootstrap-base.sh            # builds dcrad-base:bookworm unless it exists
#   deploy/bootstrap-base.sh --force    # rebuild it
#
# debootstrap installs a minimal Debian bookworm (variant minbase, plus Python 3.11
# and what the project's wheels need at run time) from the Debian mirror this machine
# already uses, and `docker import` turns the tree into an image. The root file system
# is also kept as a tarball in $DCRAD_CACHE_DIR (default ~/.cache/dcrad), so an image
# that was removed comes back in seconds without downloading again.
#
# Needs root (debootstrap chroots and creates device nodes), debootstrap and a running
# Docker Engine. Environment: DCRAD_BASE_IMAGE (default dcrad-base:bookworm),
# DCRAD_DEBIAN_MIRROR (default: the bookworm mirror from /etc/apt, else deb.debian.org),
# DCRAD_CACHE_DIR.
set -euo pipefail

IMAGE="${DCRAD_BASE_IMAGE:-dcrad-base:bookworm}"
SUITE=bookworm
CACHE_DIR="${DCRAD_CACHE_DIR:-${XDG_CACHE_HOME:-$HOME/.cache}/dcrad}"
# What the image gets on top of minbase:
#   python3, python3-venv   the interpreter (3.11, like the host that builds the wheels) and venv/ensurepip
#   libstdc++6, libgcc-s1   C++ runtime of the OpenImageIO, embreex and grpcio wheels (zlib1g, also
#                           needed by OpenImageIO, is in minbase); everything else the wheels need
#                           (TBB, Embree, OpenBLAS, gfortran) is vendored inside the wheels
INCLUDE="python3,python3-venv,libstdc++6,libgcc-s1"

force=0
case "${1:-}" in
    --force) force=1 ;;
    "") ;;
    *) echo "usage: $0 [--force]" >&2; exit 2 ;;
esac

log() { echo "bootstrap-base: $*" >&2; }

if ! docker info >/dev/null 2>&1; then
    log "error: cannot talk to the Docker Engine (is docker installed and the daemon running?)"
    exit 1
fi
if [ "$force" = 0 ] && docker image inspect "$IMAGE" >/dev/null 2>&1; then
    log "$IMAGE exists; nothing to do (--force rebuilds it)"
    exit 0
fi

tarball="$CACHE_DIR/$(echo "$IMAGE" | tr ':/' '--').tar.gz"
# image metadata that a registry image would carry
changes=(--change 'ENV PATH=/usr/local/sbin:/usr/local/bin:/usr/sbin:/usr/bin:/sbin:/bin'
         --change 'ENV LANG=C.UTF-8'
         --change 'CMD ["/bin/bash"]'
         --change "LABEL org.opencontainers.image.description=\"Debian $SUITE minbase with python3, by debootstrap\"")

if [ "$force" = 0 ] && [ -s "$tarball" ]; then
    log "importing the cached root file system $tarball"
    docker import "${changes[@]}" "$tarball" "$IMAGE" >/dev/null
    log "built $IMAGE"
    exit 0
fi

# The bookworm mirror this machine uses: a one-line "deb URL bookworm ..." entry in
# sources.list(.d/*.list), or a deb822 .sources stanza whose Suites list bookworm.
find_mirror() {
    local f
    for f in /etc/apt/sources.list /etc/apt/sources.list.d/*.list; do
        [ -r "$f" ] || continue
        # drop "[options]", keep "deb URL SUITE"
        sed -e 's/\[[^]]*\]//' "$f" | awk -v s="$SUITE" '$1 == "deb" && $3 == s { print $2; exit }'
    done
    for f in /etc/apt/sources.list.d/*.sources; do
        [ -r "$f" ] || continue
        # stanzas are separated by blank lines; print the first URI of one that has the suite
        awk -v s="$SUITE" '
            /^[[:space:]]*$/ { if (uri != "" && has) { print uri; exit } uri = ""; has = 0; next }
            tolower($1) == "uris:" { uri = $2 }
            tolower($1) == "suites:" { for (i = 2; i <= NF; i++) if ($i == s) has = 1 }
            END { if (uri != "" && has) print uri }' "$f"
    done
}
mirror="${DCRAD_DEBIAN_MIRROR:-$(find_mirror | head -n 1)}"
mirror="${mirror:-http://deb.debian.org/debian}"

if [ "$(id -u)" != 0 ]; then
    log "error: debootstrap needs root; run: sudo $0"
    exit 1
fi
if ! command -v debootstrap >/dev/null 2>&1; then
    log "error: debootstrap is missing; install it with: apt-get install debootstrap"
    exit 1
fi

work="$(mktemp -d /var/tmp/dcrad-rootfs.XXXXXX)"
trap 'rm -rf "$work"' EXIT
rootfs="$work/rootfs"
log "debootstrap $SUITE (minbase + $INCLUDE) from $mirror"
debootstrap --variant=minbase --include="$INCLUDE" "$SUITE" "$rootfs" "$mirror" >"$work/debootstrap.log" 2>&1 || {
    tail -n 30 "$work/debootstrap.log" >&2
    log "error: debootstrap failed (log above)"
    exit 1
}

# Slim the tree: package caches and lists, documentation (copyright files stay),
# man pages, translations; an image needs none of them, and apt still works after an
# `apt-get update` where a mirror is reachable. The standard library's compiled
# __pycache__ stays: the services run as a user who could not write it.
r="${rootfs:?}"   # never empty: the rm below must stay inside the tree
rm -rf "$r"/var/cache/apt/archives/*.deb "$r"/var/cache/apt/*.bin "$r"/var/lib/apt/lists/* \
       "$r"/var/log/* "$r"/usr/share/man/* "$r"/usr/share/info/* "$r"/usr/share/locale/* \
       "$r"/usr/share/lintian "$r"/tmp/* "$r"/var/tmp/*
find "$r/usr/share/doc" -mindepth 1 ! -name copyright ! -type d -delete
find "$r/usr/share/doc" -mindepth 1 -type d -empty -delete
# the engine provides /dev, /proc, /sys and these files in every container
rm -rf "${r:?}"/dev/* "${r:?}"/proc/* "${r:?}"/sys/*
: >"$r/etc/hostname"
: >"$r/etc/resolv.conf"

mkdir -p "$CACHE_DIR"
tar --numeric-owner -C "$rootfs" -czf "$tarball.tmp" .
mv "$tarball.tmp" "$tarball"
docker import "${changes[@]}" "$tarball" "$IMAGE" >/dev/null
log "built $IMAGE ($(du -h "$tarball" | cut -f1) compressed, cached in $tarball)"
