"""``bus-agent scan``: list the drives a bus has, without running an agent.

    bus-agent scan --can CHANNEL [--can-interface socketcan|udp_multicast] [--nodes 1,2,3] [--eds PATH] [--json]

CAN: every CANopen node that answers an SDO (or is heard), with its identity (0x1018), device
type, name, heartbeat time and PDO mappings (bus_agent.bus.canopen.scan); with ``--eds`` (an EDS
file or a directory of them) each node's EDS by identity and where its mapping differs from the
EDS default. Exit codes: 0 nodes
found, 1 none found, 2 bad arguments or the bus cannot be opened.
"""

from __future__ import annotations

import argparse
import json
import sys
from typing import Sequence

from bus_agent.can_config import CAN_INTERFACES


def main(argv: Sequence[str]) -> int:
    p = argparse.ArgumentParser(prog="bus-agent scan", description="List the drives on a bus.")
    p.add_argument("--can", metavar="CHANNEL", required=True, help="CAN channel (SocketCAN interface or udp_multicast group)")
    p.add_argument("--can-interface", choices=CAN_INTERFACES, default="socketcan")
    p.add_argument("--nodes", metavar="IDS", help="only these node ids, e.g. 1,2,3 (default 1..127)")
    p.add_argument("--eds", metavar="PATH", help="an EDS file or a directory of *.eds: each node's by identity, and "
                   "where its PDO mapping differs from that EDS's default")
    p.add_argument("--json", action="store_true", help="one JSON document instead of the table")
    args = p.parse_args(list(argv))
    try:
        ids = tuple(int(x, 0) for x in args.nodes.split(",")) if args.nodes else ()
    except ValueError:
        print(f"bus-agent scan: --nodes {args.nodes!r} is not a comma-separated list of node ids", file=sys.stderr)
        return 2
    if any(not 1 <= i <= 127 for i in ids):
        print(f"bus-agent scan: node ids {ids} outside 1..127", file=sys.stderr)
        return 2
    from bus_agent.bus.base import BusError
    from bus_agent.bus.canopen.scan import eds_files, format_table, scan
    from bus_agent.devices.eds import EdsError

    try:
        files = eds_files(args.eds) if args.eds else []
    except EdsError as e:
        print(f"bus-agent scan: {e}", file=sys.stderr)
        return 2
    try:
        reports = scan(args.can, args.can_interface, ids, eds=files)
    except BusError as e:
        print(f"bus-agent scan: {e}", file=sys.stderr)
        return 2
    if args.json:
        print(json.dumps({"channel": args.can, "nodes": [r.as_dict() for r in reports]}, indent=1))
    else:
        print(format_table(reports) if reports else f"no CANopen node answered on {args.can}")
    return 0 if reports else 1
