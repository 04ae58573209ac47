#!/bin/sh
# Multi-host test bed: every host a network namespace on one virtual switch. Idempotent.
#   deploy/multihost.sh up   [--prefix mh] [--hosts 2] [--extra sup] [--subnet 10.213.7]
#   deploy/multihost.sh down [--prefix mh] [--hosts 2] [--extra sup]
#   deploy/multihost.sh cut|plug --host h2 [--prefix mh]     # pull / plug h2's cable at the switch
# Host i: namespace <prefix>h<i>, lan0 = <subnet>.<i>/24 on bridge br0 in namespace <prefix>sw,
# EtherCAT veth ecm0 (bus-agent --ifname) <-> ecs0 (ecat-sim --ifname) inside the namespace.
# Extra namespaces (--extra sup) get <subnet>.101, .102, ... and no EtherCAT pair.
# No namespace has a default route: the subnet exists only inside the bed. See deploy/README.md.
set -eu
cd "$(dirname "$0")/.."
PY=${PYTHON:-.venv/bin/python}
[ -x "$PY" ] || PY=python3
if [ "$(id -u)" != 0 ]; then
    echo "multihost.sh: needs root (namespaces, veth pairs, a bridge)" >&2
    exit 1
fi
case "${1:-}" in
    up|down|cut|plug) exec "$PY" -m bus_agent.sim.netns multihost "$@" ;;
    *) echo "usage: $0 up|down|cut|plug [--prefix P] [--hosts N] [--extra NAME]... [--subnet 10.X.Y] [--host H]" >&2
       exit 2 ;;
esac
