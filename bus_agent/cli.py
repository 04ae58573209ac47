"""``bus-agent``: run one bus agent.

    bus-agent --sim 4                          # 4 simulated drives, no root, no router;
                                               # listens on tcp/127.0.0.1:7447 (drivectl's default)
    bus-agent --config /etc/zenoh-drives/agent.toml
    bus-agent --ifname eth1 --host h1 --connect tcp/router:7447
    bus-agent --ifname eth1 --esi /etc/zenoh-drives/esi/   # slaves matched to their ESI devices
    bus-agent scan --ifname eth1 [--esi PATH] [--json | --toml]   # read the segment (PRE-OP), no Zenoh

Flags override the configuration file. Once everything is up it prints one line,
``bus-agent ready host=<host> drives=<a,b,..> backend=<sim|pysoem> listen=<eps> connect=<eps>``.
SIGINT/SIGTERM run the ordered shutdown of every drive, then AL INIT, and exit 0. During start-up
they end it within 2 s in any step (what was opened is closed; no drive is enabled before
start-up is over), and every blocking start-up step has a deadline (exit 3). A call into C that
cannot be interrupted (SOEM's config_map on a malformed SII) is ended by the start-up guard
process: it prints the step to stderr and kills the agent (SIGKILL).
The Zenoh gateway runs in a child process (``bus_agent.gateway.bridge``) unless ``--gateway-thread``
(or ``gateway = "thread"`` in the file); if that child dies, the agent runs the same ordered
shutdown and exits 1.

Exit codes: 0 stopped cleanly; 1 the cycle or the gateway process failed while running; 2 bad
command line or configuration; 3 start-up failed (bus, slave identity, AL state, zenoh session).
"""

from __future__ import annotations

import argparse
import logging
import socket
import sys
from typing import Sequence

from bus_agent.can_config import CAN_INTERFACES, CanConfig, can_config
from bus_agent.config import SIM_PROFILES, ZENOH_MODES, AgentConfig, ConfigError, ZenohConfig, load_config
from bus_agent.stop_signals import StopSignals
from schemas.keys import is_name

log = logging.getLogger("bus_agent.cli")

DEFAULT_LISTEN = "tcp/127.0.0.1:7447"
EXIT_OK, EXIT_FAILED, EXIT_USAGE, EXIT_STARTUP = 0, 1, 2, 3
EXIT_CODES_HELP = """exit codes:
  0  stopped cleanly (SIGINT/SIGTERM: ordered shutdown of every drive, then AL INIT;
     during start-up: start-up abandoned, what was opened closed)
  1  the cycle or the gateway process failed while running (same ordered shutdown)
  2  bad command line or configuration (nothing started)
  3  start-up failed: bus, slave identity, AL state, zenoh session, a start-up step past its
     deadline, or the host name is held by another running agent (one agent per host name)
  killed (SIGKILL) by the start-up guard: a start-up step that cannot be interrupted did not
     return by its deadline, or within 1 s of SIGINT/SIGTERM (the reason is on stderr)"""


def _parser() -> argparse.ArgumentParser:
    p = argparse.ArgumentParser(prog="bus-agent", description="Run a bus agent: an EtherCAT segment of CiA 402 "
                                "drives (or simulated drives) served over Zenoh. Flags override the --config "
                                "file; defaults are those of deploy/agent.example.toml.",
                                epilog=EXIT_CODES_HELP, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--config", metavar="TOML", help="agent configuration file (see deploy/agent.example.toml)")
    p.add_argument("--host", help="host name in the key space (default: from the config, else this machine's name)")
    backend = p.add_mutually_exclusive_group()
    backend.add_argument("--ifname", help="NIC (or veth end) of the EtherCAT segment: pysoem backend, needs root")
    backend.add_argument("--sim", type=int, metavar="N", help="simulate N drives in-process (no root)")
    backend.add_argument("--can", metavar="CHANNEL", help="CAN bus of CANopen drives: canopen backend "
                         "(SocketCAN interface, or a udp_multicast group; docs/canopen.md)")
    p.add_argument("--can-interface", choices=CAN_INTERFACES, help="python-can interface of --can (default socketcan)")
    p.add_argument("--nodes", metavar="IDS", help="CANopen node ids of --can, e.g. 1,2,3 (slave positions in that order)")
    p.add_argument("--sync-counter", type=int, metavar="N",
                   help="--can: SYNC carries a counter 1..N (2..240, written to every node's 0x1019; default: none)")
    p.add_argument("--esi", metavar="PATH", help="ESI file or directory of the slaves' devices: each slave matched "
                   "by identity (none matching stops start-up), InitCmds made, vendor objects named ([esi] in the "
                   "config; docs/device-files.md)")
    p.add_argument("--profile", choices=SIM_PROFILES, help="simulated drive profile (default generic)")
    p.add_argument("--cycle-us", type=int, metavar="US", help="cycle period in microseconds (default 1000)")
    p.add_argument("--heartbeat-s", type=float, metavar="S", help="status heartbeat period (default 1.0 s)")
    p.add_argument("--listen", action="append", metavar="EP", help="zenoh listen endpoint (repeatable; default "
                   f"{DEFAULT_LISTEN} when neither --config nor --connect is given, else none)")
    p.add_argument("--connect", action="append", metavar="EP", help="zenoh connect endpoint, e.g. a router (repeatable)")
    p.add_argument("--mode", choices=ZENOH_MODES, help="zenoh session mode (default peer)")
    p.add_argument("--pki", metavar="DIR", help="drives-pki directory: mutual TLS on every link, ACL on what it "
                   "listens on, commands only from authenticated principals (see docs/security.md)")
    p.add_argument("--identity", metavar="NAME", help="principal in --pki (default and only choice: the host name)")
    p.add_argument("--insecure", action="store_true", default=None,
                   help="allow listening on a non-loopback address without --pki")
    p.add_argument("--rt-priority", type=int, metavar="N",
                   help="SCHED_FIFO priority 1..99 of the cycle thread (needs root/CAP_SYS_NICE; default 0 = off)")
    p.add_argument("--record-s", type=float, metavar="S",
                   help="flight recorder ring length in seconds (default 10, 0 = off; [recorder] in the config)")
    p.add_argument("--gateway-thread", action="store_true",
                   help="run the Zenoh gateway as threads of this process (debugging) instead of a child process")
    p.add_argument("--log-level", default="INFO", choices=("DEBUG", "INFO", "WARNING", "ERROR"),
                   help="default INFO (the audit trail of commands is logged at INFO)")
    return p


def _default_host() -> str:
    name = socket.gethostname().split(".")[0]
    return name if is_name(name) else "h1"


def build_config(args: argparse.Namespace) -> AgentConfig:
    """The configuration from the file (if any) with the flags applied. Raises ConfigError."""
    if args.sim is not None and args.sim < 1:
        raise ConfigError(f"--sim: {args.sim} must be a number of drives >= 1")
    can = _can_flags(args)
    overrides = dict(host=args.host, ifname=args.ifname, sim_drives=args.sim, sim_profile=args.profile, can=can,
                     cycle_us=args.cycle_us, heartbeat_s=args.heartbeat_s, zenoh_mode=args.mode,
                     listen=args.listen, connect=args.connect, rt_priority=args.rt_priority,
                     record_s=args.record_s, esi=args.esi,
                     pki=args.pki, identity=args.identity, insecure=args.insecure,
                     gateway="thread" if args.gateway_thread else None)
    if args.config:
        return load_config(args.config).with_overrides(**overrides)
    if args.ifname is None and args.sim is None and can is None:
        raise ConfigError("give --config, --ifname NIC, --can CHANNEL --nodes IDS or --sim N (e.g. `bus-agent --sim 4`)")
    # Embedded default: a peer that drivectl reaches on loopback without any router.
    listen = tuple(args.listen or (() if args.connect else (DEFAULT_LISTEN,)))
    base = AgentConfig(host=args.host or _default_host(), sim_drives=args.sim or 0, ifname=args.ifname, can=can,
                       zenoh=ZenohConfig(listen=listen, pki=args.pki, identity=args.identity,
                                         insecure=bool(args.insecure)))
    overrides["listen"] = None
    return base.with_overrides(**overrides)


def _can_flags(args: argparse.Namespace) -> CanConfig | None:
    """--can/--can-interface/--nodes/--sync-counter as a CanConfig (None without --can). Raises ConfigError."""
    if args.can is None:
        if args.nodes is not None or args.can_interface is not None or args.sync_counter is not None:
            raise ConfigError("--nodes, --can-interface and --sync-counter go with --can CHANNEL")
        return None
    if not args.nodes:
        raise ConfigError("--can needs --nodes, e.g. --nodes 1,2,3")
    try:
        ids = tuple(int(x, 0) for x in args.nodes.split(","))
    except ValueError:
        raise ConfigError(f"--nodes: {args.nodes!r} is not a comma-separated list of node ids") from None
    return can_config(args.can, args.can_interface, ids, args.sync_counter or 0)


def main(argv: Sequence[str] | None = None) -> int:
    argv = list(sys.argv[1:] if argv is None else argv)
    if argv[:1] == ["scan"] and "--can" in argv:  # CANopen nodes (bus_agent/scan.py)
        from bus_agent.scan import main as can_scan_main

        return can_scan_main(argv[1:])
    if argv[:1] == ["scan"]:
        from bus_agent.bus.scan import main as scan_main  # reads a segment, controls nothing

        return scan_main(argv[1:])
    args = _parser().parse_args(argv)
    logging.basicConfig(level=args.log_level, stream=sys.stderr,
                        format="%(asctime)s %(levelname)s %(name)s: %(message)s")
    try:
        config = build_config(args)
    except ConfigError as exc:
        print(f"bus-agent: configuration error: {exc}", file=sys.stderr)
        return EXIT_USAGE
    if config.esi is not None:  # an unreadable ESI is a configuration error: found before the bus opens
        from bus_agent.devices.esi import EsiError, load_esi

        try:
            load_esi(config.esi.path)
        except EsiError as exc:
            print(f"bus-agent: configuration error: esi.path: {exc}", file=sys.stderr)
            return EXIT_USAGE

    stop = StopSignals()  # SIGTERM/SIGINT; the handler takes no lock (a burst of signals must not hang)

    from bus_agent.agent import Agent, AgentError  # after arg parsing: `--help` stays fast
    from bus_agent.startup_guard import StartupAbandoned, StartupSteps, start_guard

    agent = Agent(config, on_failure=lambda _reason: stop.request())
    # Every blocking start-up step has a deadline; a stop signal ends start-up in any step: in
    # order where Python runs, else by the guard process (bus_agent/startup_guard.py).
    guard = start_guard()
    try:
        agent.start(StartupSteps(stopped=lambda: stop.stopped, report=guard.report))
    except StartupAbandoned as exc:
        print(f"bus-agent: agent {config.host}: {exc}", file=sys.stderr)
        return EXIT_OK if exc.signalled else EXIT_STARTUP
    except AgentError as exc:
        print(f"bus-agent: {exc}", file=sys.stderr)
        return EXIT_STARTUP
    finally:
        guard.close()
    z = config.zenoh
    assert agent.bus is not None  # started
    print(f"bus-agent ready host={config.host} drives={','.join(agent.axes)} backend={agent.bus.backend} "
          f"listen={','.join(z.listen) or '-'} connect={','.join(z.connect) or '-'} "
          f"identity={f'{z.identity} (tls)' if z.pki else '- (insecure)'}", flush=True)
    code = EXIT_OK
    while not stop.wait(0.2):
        if agent.failed:
            break
    if agent.failed:
        log.error("agent %s: %s; shutting down", config.host, agent.failure)
        code = EXIT_FAILED
    if stop.signal_name:
        log.info("agent %s: signal %s: shutting down", config.host, stop.signal_name)
    agent.stop(ordered=True)
    print(f"bus-agent stopped host={config.host}", flush=True)
    return code


if __name__ == "__main__":
    sys.exit(main())
