"""``canopen-sim``: CANopen CiA 402 drive nodes on a CAN bus.

    canopen-sim --channel CH [--interface udp_multicast|socketcan] --nodes N [--first-id 1]
                [--profile generic|indy7] [--name can0] [--zenoh-connect EP]... [--write-eds PATH]
    canopen-sim --channel CH --eds FILE[*COUNT] [--eds FILE[*COUNT]]... [--first-id 1] ...

With ``--eds`` (repeatable, in node order) each node's object dictionary is its EDS's (through
python-canopen's import): defaults, access, ``$NODEID`` expressions, the default PDO mappings,
the drive model on its CiA 402 objects; objects the EDS lacks abort 0x06020000. Nodes are
numbered from ``--first-id`` (1) in order. ``--write-eds PATH`` writes the built-in profile's EDS.

Each node answers SDO, NMT and SYNC, produces heartbeats, TPDOs and EMCY (docs/canopen.md).
With ``--zenoh-connect``/``--zenoh-listen`` it serves fault injection on
``drives/@sim/<name>/<node index>/<action>`` (fault, unplug, plug, status). Prints
``canopen-sim ready ...`` once the nodes have booted. With udp_multicast, the default channel
is an interface-local IPv6 group (ff11::): its frames never leave this machine.
"""

from __future__ import annotations

import argparse
import json
import os
import sys

from bus_agent.devices.eds import EdsError, load, parse_spec
from bus_agent.sim.canopen.dictionary import NodeDictionary, from_eds
from bus_agent.sim.drive_model import PROFILES
from bus_agent.sim.process import add_options, enter_rt, start_logging
from bus_agent.stop_signals import StopSignals

DEFAULT_CHANNEL = "ff11::7a64:1"  # IPv6 interface-local scope: loopback only (RFC 4291 §2.7)


def build_parser() -> argparse.ArgumentParser:
    p = argparse.ArgumentParser(prog="canopen-sim", description=__doc__.split("\n\n")[0])
    p.add_argument("--channel", default=DEFAULT_CHANNEL, help="CAN channel (udp_multicast: a multicast group)")
    p.add_argument("--interface", default="udp_multicast", choices=("udp_multicast", "socketcan"))
    p.add_argument("--nodes", type=int, default=None, help="number of nodes of --profile (1..127; default 1)")
    p.add_argument("--eds", action="append", default=[], metavar="FILE[*COUNT]",
                   help="COUNT nodes (default 1) whose object dictionary is FILE's (repeatable, in node order)")
    p.add_argument("--first-id", type=int, default=1, help="node id of the first node")
    p.add_argument("--profile", choices=sorted(PROFILES), default="generic")
    p.add_argument("--name", default="can0", help="segment name (the Zenoh control key chunk)")
    p.add_argument("--zenoh-connect", action="append", default=[], metavar="EP")
    p.add_argument("--zenoh-listen", action="append", default=[], metavar="EP")
    p.add_argument("--write-eds", metavar="PATH", help="write the simulated drive's EDS file and exit")
    add_options(p, "node loop")
    return p


def eds_dictionaries(specs: list[tuple[str, int]], ids: list[int]) -> list[NodeDictionary]:
    """One dictionary per node id, ``specs`` ((file, count), in order) read for each. Raises EdsError."""
    files = [path for path, n in specs for _ in range(n)]
    return [from_eds(load(path, nid)) for path, nid in zip(files, ids)]


def main(argv: list[str] | None = None) -> int:
    args = build_parser().parse_args(argv)
    start_logging(args)
    if args.write_eds:
        from bus_agent.sim.canopen.od import write_eds

        write_eds(args.write_eds, PROFILES[args.profile])
        print(f"canopen-sim: EDS written to {args.write_eds}")
        return 0
    if args.eds and args.nodes is not None:
        print("canopen-sim: --nodes and --eds exclude each other (--eds FILE*COUNT gives the count)", file=sys.stderr)
        return 2
    try:
        specs = [parse_spec(s) for s in args.eds]
    except EdsError as exc:
        print(f"canopen-sim: {exc}", file=sys.stderr)
        return 2
    count = sum(n for _p, n in specs) if specs else (1 if args.nodes is None else args.nodes)
    ids = list(range(args.first_id, args.first_id + count))
    if count < 1 or ids[0] < 1 or ids[-1] > 127:
        print(f"canopen-sim: node ids {args.first_id}..{args.first_id + count - 1} outside 1..127", file=sys.stderr)
        return 2
    dictionaries = None
    if specs:
        try:
            dictionaries = eds_dictionaries(specs, ids)
        except EdsError as exc:
            print(f"canopen-sim: {exc}", file=sys.stderr)
            return 2
    from bus_agent.bus.base import BusError
    from bus_agent.bus.canopen.bus import open_can
    from bus_agent.sim.canopen.segment import Segment

    try:
        bus = open_can(args.channel, args.interface)
    except BusError as exc:
        print(f"canopen-sim: {exc}", file=sys.stderr)
        return 2
    segment = Segment(bus, ids, args.profile, dictionaries=dictionaries)
    session = control = None
    if args.zenoh_connect or args.zenoh_listen:
        import zenoh

        from bus_agent.sim.control import SimControl

        conf = zenoh.Config()
        conf.insert_json5("scouting/multicast/enabled", "false")
        if args.zenoh_connect:
            conf.insert_json5("connect/endpoints", json.dumps(args.zenoh_connect))
        if args.zenoh_listen:
            conf.insert_json5("listen/endpoints", json.dumps(args.zenoh_listen))
        session = zenoh.open(conf)
        control = SimControl(session, args.name, segment.control_handlers(), len(ids))

    # the node loop looks at stop.stopped: the handler takes no lock (bus_agent.stop_signals)
    stop = StopSignals()
    segment.stop_signals = stop
    enter_rt(args, "canopen-sim node loop")
    segment.boot()
    what = (f"eds={','.join(f'{os.path.basename(p)}*{n}' for p, n in specs)}" if specs
            else f"profile={args.profile}")
    print(f"canopen-sim ready channel={args.channel} interface={args.interface} nodes={','.join(map(str, ids))} "
          f"{what} name={args.name}", flush=True)
    try:
        segment.run()
    finally:
        if control is not None:
            control.close()
        if session is not None:
            session.close()
        bus.shutdown()
        print(f"canopen-sim stopped frames_in={segment.frames_in} frames_out={segment.frames_out} "
              f"max_lag_ms={segment.max_lag_s * 1000:.1f}", flush=True)
    return 0


if __name__ == "__main__":
    sys.exit(main())
