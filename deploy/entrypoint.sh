#!/bin/bash
# Entrypoint of the dcrad image: runs `dcrad "$@"` (so the command picks the service:
# `coordinator ...` or `worker ...`, or any other dcrad command).
#
# A worker must tell the coordinator an address where the coordinator can reach it. In a
# container that is the container's own IP address, which differs for every replica of a
# scaled service, so it cannot be written in the compose file: when DCRAD_ADVERTISE is not
# set, it becomes "<first address of this container's hostname>:<worker port>", the port
# being the --port argument, else DCRAD_WORKER_PORT. An explicit DCRAD_ADVERTISE or
# --advertise (e.g. from the Kubernetes downward API) wins.
set -euo pipefail

# the dcrad subcommand: the first argument that is not an option (`dcrad -v worker ...`)
cmd=""
for arg in "$@"; do
    case "$arg" in
        -*) ;;
        *) cmd="$arg"; break ;;
    esac
done

if [ "$cmd" = worker ] && [ -z "${DCRAD_ADVERTISE:-}" ]; then
    port="${DCRAD_WORKER_PORT:-50052}"
    advertise_given=0
    prev=""
    for arg in "$@"; do
        case "$prev" in --port) port="$arg" ;; --advertise) advertise_given=1 ;; esac
        case "$arg" in --port=*) port="${arg#--port=}" ;; --advertise=*) advertise_given=1 ;; esac
        prev="$arg"
    done
    if [ "$advertise_given" = 0 ]; then
        if [ "$port" = 0 ]; then
            echo "dcrad-entrypoint: a worker on --port 0 cannot advertise its port; set --port or DCRAD_ADVERTISE" >&2
            exit 2
        fi
        # `hostname -i` resolves the container's hostname through /etc/hosts, which the engine
        # (or the kubelet) writes with the container's address; prefer an IPv4 address
        addrs="$(hostname -i 2>/dev/null || true)"
        addr=""
        for a in $addrs; do
            case "$a" in
                127.*|::1) ;;
                *:*) [ -n "$addr" ] || addr="[$a]" ;;
                *) addr="$a"; break ;;
            esac
        done
        # no address: the hostname, which the engine's DNS resolves on a user-defined network
        addr="${addr:-$(hostname)}"
        export DCRAD_ADVERTISE="$addr:$port"
        echo "dcrad-entrypoint: advertising this worker as $DCRAD_ADVERTISE" >&2
    fi
fi

# exec: dcrad becomes process 1 and gets the engine's SIGTERM (a clean shutdown)
exec /opt/dcrad/lib/bin/dcrad "$@"
