"""``ecat-sim``: a virtual EtherCAT segment of CiA 402 drives on one end of a veth pair.

    ecat-sim --ifname vethX --drives 16 [--profile generic*2,omron1s,roassign] [--name seg0]
             [--control /run/seg0.sock | --control 5555] [--zenoh-connect tcp/127.0.0.1:7447]...
    ecat-sim --ifname vethX --esi FILE[@PRODUCT[:REVISION]][*COUNT] [--esi ...]...
    ecat-sim --write-esi PATH

Unmodified SOEM/pysoem on the other end of the veth pair finds, configures and runs the
drives. Prints one readiness line on stdout (``ecat-sim ready ...``) once frames are served.
See docs/virtual-ethercat.md.
"""

from __future__ import annotations

import argparse
import json
import logging
import queue
import signal
import sys
import threading

from bus_agent.security.exposure import exposed_endpoints, refusal
from bus_agent.sim.ecat.profiles import PROFILES
from bus_agent.sim.ecat.control import ACTIONS, TcpControl, UnixControl, apply_action
from bus_agent.sim.ecat.frameloop import FrameLoop
from bus_agent.sim.ecat.segment import Segment
from bus_agent.sim.process import add_options, enter_rt, start_logging

log = logging.getLogger("bus_agent.sim.cli")


class QueuedControl:
    """Requests from other threads (the Zenoh worker), executed by the frame loop's poll."""

    def __init__(self) -> None:
        self._q: queue.Queue[tuple[dict, threading.Event, list]] = queue.Queue()

    def submit(self, req: dict, timeout: float = 2.0) -> dict:
        done, out = threading.Event(), list[dict]()
        self._q.put((req, done, out))
        if not done.wait(timeout):
            return {"ok": False, "error": "simulator busy: request not handled in time"}
        return out[0]

    def poll(self, handle) -> None:
        while True:
            try:
                req, done, out = self._q.get_nowait()
            except queue.Empty:
                return
            out.append(handle(req))
            done.set()

    def close(self) -> None:
        pass


def _zenoh_control(args, name: str, n: int, channel: QueuedControl):
    import zenoh

    from bus_agent.sim.control import SimControl

    from bus_agent.gateway.zenoh_config import make_zenoh_config

    conf = make_zenoh_config("peer", args.zenoh_listen, args.zenoh_connect, pki=args.pki, identity=args.identity)
    session = zenoh.open(conf)

    def make(action: str):
        def handler(position: int, payload: dict) -> str:
            reply = channel.submit({"action": action, "slave": position, **payload})
            if not reply.get("ok"):
                raise ValueError(reply.get("error", "refused"))
            return json.dumps({k: v for k, v in reply.items() if k != "ok"}) or "done"
        return handler

    handlers = {a: make(a) for a in ACTIONS}
    return session, SimControl(session, name, handlers, n)


def build_parser() -> argparse.ArgumentParser:
    profiles = "\n".join(f"  {name:10} {prof.description}" for name, prof in PROFILES.items())
    p = argparse.ArgumentParser(prog="ecat-sim", description=__doc__.split("\n\n")[0],
                                formatter_class=argparse.RawDescriptionHelpFormatter,
                                epilog=f"slave profiles (--profile):\n{profiles}\n\n"
                                       "modifiers (profile:modifier, e.g. omron1s:dc-required*16):\n"
                                       "  dc           DC capable: ESC 0x0008 bit 2, system time 0x0910, SYNC0\n"
                                       "  dc-required  also refuses OP in modes 8/9/10 without SYNC0 (AL 0x0030) and\n"
                                       "               raises a sync error (AL 0x001A) when process data stops\n"
                                       "               arriving in step with SYNC0\n"
                                       "  no-mailbox   no mailbox (SII mailbox sizes 0): no CoE, no SDO\n"
                                       "  no-coe       a mailbox without CoE: CoE requests get the mailbox error\n"
                                       "               'unsupported protocol'")
    p.add_argument("--ifname", help="network interface to serve (one end of a veth pair)")
    p.add_argument("--drives", type=int, help="number of slaves on the segment (1..1000; default 1, or the --esi count)")
    p.add_argument("--esi", action="append", default=[], metavar="FILE[@PRODUCT[:REVISION]][*COUNT]",
                   help="slaves from a vendor's ESI file, repeatable, in segment order: the device with this "
                        "product code (and revision), by default the first with CiA 402 objects (docs/simulator.md)")
    p.add_argument("--write-esi", metavar="PATH",
                   help="write an ESI file describing every built-in profile to PATH and exit")
    p.add_argument("--profile",
                   help="slave profile (default generic), or one per slave: 'generic*2,omron1s' (the last repeats); see below")
    p.add_argument("--name", default="seg0", help="segment name (the Zenoh control key chunk)")
    p.add_argument("--control", help="local JSON control socket: a UNIX datagram path or a TCP loopback port; "
                   f"actions: {', '.join(ACTIONS)} (docs/virtual-ethercat.md)")
    p.add_argument("--zenoh-connect", action="append", default=[], metavar="EP")
    p.add_argument("--zenoh-listen", action="append", default=[], metavar="EP")
    p.add_argument("--pki", metavar="DIR", help="drives-pki directory: the Zenoh control over mutual TLS")
    p.add_argument("--identity", metavar="NAME", help="principal in --pki (role testbed)")
    p.add_argument("--insecure", action="store_true", help="allow a non-loopback --zenoh-listen without --pki")
    p.add_argument("--step-us", type=int, default=1000, help="drive model step period while in SAFE-OP/OP")
    p.add_argument("--stale-us", type=int, default=1800,
                   help="frames older than this are dropped, never answered late (0: answer all)")
    add_options(p, "frame loop")
    return p


def main(argv: list[str] | None = None) -> int:
    parser = build_parser()
    args = parser.parse_args(argv)
    if args.write_esi:
        return _write_esi(args.write_esi)
    if not args.ifname:
        parser.error("--ifname is required")
    start_logging(args)
    try:
        if args.esi and args.profile:
            raise ValueError("--profile and --esi: give the slaves one way (an --esi per file, in segment order)")
        profiles = args.profile = args.profile or "generic"
        if args.esi:
            from bus_agent.sim.ecat.esi_profile import profiles_from_specs

            profiles = profiles_from_specs(args.esi)
            if args.drives is not None and args.drives != len(profiles):
                raise ValueError(f"--drives {args.drives} but the --esi arguments give {len(profiles)} slave(s)")
            args.drives = len(profiles)
            args.profile = ",".join(p.name for p in profiles)
        elif args.drives is None:
            args.drives = 1
        segment = Segment(args.drives, profiles)
        loop = FrameLoop(segment, args.ifname, step_s=args.step_us / 1e6, stale_s=args.stale_us / 1e6)
    except (ValueError, OSError) as exc:
        print(f"ecat-sim: {exc}", file=sys.stderr)
        return 2
    loop.handle_control = lambda req: apply_action(loop, args.name, req)
    control_desc = "none"
    if args.control:
        try:
            if args.control.isdigit():
                tcp = TcpControl(int(args.control))
                loop.controls.append(tcp)
                control_desc = f"tcp:{tcp.port}"
            else:
                loop.controls.append(UnixControl(args.control))
                control_desc = f"unix:{args.control}"
        except OSError as exc:
            print(f"ecat-sim: control socket {args.control}: {exc}", file=sys.stderr)
            return 2
    zenoh_parts = None
    if args.zenoh_connect or args.zenoh_listen:
        exposed = exposed_endpoints(args.zenoh_listen)
        if exposed and not args.pki and not args.insecure:
            print(refusal("ecat-sim", exposed, "drives-pki issue DIR NAME --role testbed"), file=sys.stderr)
            return 2
        channel = QueuedControl()
        loop.controls.append(channel)
        try:
            zenoh_parts = _zenoh_control(args, args.name, args.drives, channel)
        except ValueError as exc:  # ZenohConfigError: a bad --pki/--identity
            print(f"ecat-sim: {exc}", file=sys.stderr)
            loop.close()
            return 2

    def on_signal(signum, frame):
        loop.stop()

    signal.signal(signal.SIGTERM, on_signal)
    signal.signal(signal.SIGINT, on_signal)

    def ready() -> None:
        print(f"ecat-sim ready ifname={args.ifname} drives={args.drives} profile={args.profile} "
              f"name={args.name} control={control_desc}", flush=True)

    enter_rt(args, "ecat-sim frame loop")
    try:
        loop.run(on_ready=ready)
    finally:
        if zenoh_parts:
            session, control = zenoh_parts
            control.close()
            session.close()
        loop.close()
        log.info("counters: %s", loop.counters)
    return 0


def _write_esi(path: str) -> int:
    """``--write-esi``: one ESI file with a device per built-in profile."""
    from bus_agent.devices.esi_write import write_esi
    from bus_agent.sim.ecat.esi_profile import esi_from_profile

    try:
        with open(path, "wb") as f:
            f.write(write_esi([esi_from_profile(p) for p in PROFILES.values()]))
    except OSError as exc:
        print(f"ecat-sim: --write-esi {path}: {exc}", file=sys.stderr)
        return 2
    print(f"ecat-sim: wrote {path} ({', '.join(PROFILES)})")
    return 0


if __name__ == "__main__":
    sys.exit(main())
