#!/bin/sh
# Virtual EtherCAT testbed: veth pairs (optionally in namespaces) for ecat-sim. Idempotent.
#   deploy/testbed.sh up   [--prefix zd] [--count N] [--netns]
#   deploy/testbed.sh down [--prefix zd] [--count N] [--netns]
# Pair i: <prefix><i>m (pysoem / bus-agent side), <prefix><i>s (ecat-sim side), e.g.
#   ecat-sim --ifname zd0s --drives 16 &   bus-agent ... --ifname zd0m
set -eu
cd "$(dirname "$0")/.."
PY=${PYTHON:-.venv/bin/python}
[ -x "$PY" ] || PY=python3
if [ "$(id -u)" != 0 ]; then
    echo "testbed.sh: needs root (veth pairs, namespaces)" >&2
    exit 1
fi
case "${1:-}" in
    up|down) exec "$PY" -m bus_agent.sim.netns "$@" ;;
    *) echo "usage: $0 up|down [--prefix P] [--count N] [--netns]" >&2; exit 2 ;;
esac
