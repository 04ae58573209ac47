"""What issue 9's additions cost on the agent's command and status paths, next to the work those
paths already do, in the same run (CPU time of one process, no network):

- **audit trail** per command addressed to 16 drives: one INFO log record (to a file, as an agent
  logs to stderr) plus 16 ``command`` events built and published (msgpack + a zenoh put on a
  real session), next to the gateway's existing per-command work: decode and validate the
  request, encode 16 replies and publish 16 ``outcome`` events;
- **error texts** per published status: ``schemas.error_codes.describe`` next to encoding the
  ``DriveStatus`` it goes into.

    python -m bench.bench_trust [--rounds N] [--out PATH]

Writes ``bench/results/bench_trust.json`` (ratios, microseconds per operation, load average).
Needs no root: the zenoh session is a peer with no links, so puts cost what they cost locally.
"""

from __future__ import annotations

import logging
import os
import statistics
import tempfile
import time
from typing import Any, Callable

import zenoh

from bench.common import bench_parser, loadavg, run_stamp, write_result
from bus_agent import runtime as rt
from bus_agent.gateway import gateway as gwmod
from bus_agent.gateway.gateway import Gateway, GatewaySettings, parse_command
from bus_agent.gateway.zenoh_config import make_zenoh_config
from schemas import keys
from schemas import messages as m
from schemas.error_codes import describe

AXES = tuple(f"axis{i}" for i in range(16))


class _Cycle:
    """The least a Gateway needs of a cycle (nothing is submitted here)."""

    snapshot_sink: Any = None
    latest = None

    def submit(self, cmd: Any) -> bool:
        return True

    def trigger_group(self, group: str, reason: str) -> None:
        pass


def _per_op_us(fn: Callable[[], None], rounds: int, repeats: int = 5) -> float:
    """Median over ``repeats`` of the mean CPU time of one ``fn()`` call, in microseconds."""
    out = []
    for _ in range(repeats):
        t0 = time.process_time()
        for _ in range(rounds):
            fn()
        out.append((time.process_time() - t0) / rounds * 1e6)
    return statistics.median(out)


def run(rounds: int) -> dict[str, Any]:
    load_start = loadavg()
    session = zenoh.open(make_zenoh_config("peer", (), ()))
    log_file = tempfile.NamedTemporaryFile(prefix="bench_trust", suffix=".log", delete=False)
    handler = logging.FileHandler(log_file.name)
    handler.setFormatter(logging.Formatter("%(asctime)s %(levelname)s %(name)s: %(message)s"))
    gwlog = logging.getLogger(gwmod.__name__)
    gwlog.addHandler(handler)
    gwlog.setLevel(logging.INFO)
    gwlog.propagate = False
    gw = Gateway(session, _Cycle(), GatewaySettings(host="b1", axes=AXES))
    try:
        gw.start()
        key = keys.drive_cmd("b1", "*", "enable")
        req = m.CommandRequest("sup-1-enable-1", "enable", {}, 5.0, "alice")
        payload = m.encode(req)
        parsed = parse_command(payload, key, "b1", AXES)

        def existing() -> None:
            parse_command(payload, key, "b1", AXES)
            for a in AXES:
                reply = m.CommandReply(request_id=req.request_id, host="b1", op="enable", outcome="done", axis=a,
                                       state="operation_enabled", elapsed_s=0.01, cycles=9)
                m.encode(reply)
                gw.publisher.publish_event(rt.CycleEvent(a, "outcome", detail="enable done", to_state="operation_enabled",
                                                         request_id=req.request_id), 1, time.time_ns())

        def audit() -> None:
            gw.commands.audit(key, parsed.request, parsed.axes, "alice", "accepted")
            events = gw.feed.events
            while events:
                ev, cycle, t_ns = events.popleft()
                gw.publisher.publish_event(ev, cycle, t_ns)

        status = m.DriveStatus(host="b1", axis="axis0", seq=1, time_ns=time.time_ns(), cycle=1, state="fault",
                               statusword=0x0218, controlword=0, goal="disabled", halt=False, mode=8,
                               mode_display=8, position=0, velocity=0, torque=0, error_code=0x2310,
                               error_text="continuous over-current")
        gw.inbox.idle.set()
        base_us = _per_op_us(existing, rounds)
        audit_us = _per_op_us(audit, rounds)
        encode_us = _per_op_us(lambda: m.encode(status), rounds * 16)
        codes = [0x2310, 0x2399, 0x4999, 0xFF01]
        describe_us = _per_op_us(lambda: [describe(c) for c in codes], rounds * 4) / len(codes)
    finally:
        gw.close()
        session.close()
        gwlog.removeHandler(handler)
        handler.close()
        os.unlink(log_file.name)
    return {
        "benchmark": "bench_trust", "rounds": rounds, "axes_per_command": len(AXES),
        "command_existing_us": round(base_us, 1), "command_audit_us": round(audit_us, 1),
        "audit_ratio": round(audit_us / base_us, 3),
        "status_encode_us": round(encode_us, 2), "error_text_us": round(describe_us, 3),
        "error_text_ratio": round(describe_us / encode_us, 4),
        **run_stamp(load_start),
    }


def main(argv: list[str] | None = None) -> int:
    p = bench_parser("bench_trust", __doc__)
    p.add_argument("--rounds", type=int, default=2000, help="commands per measurement (5 measurements)")
    args = p.parse_args(argv)
    write_result(run(args.rounds), args.out)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
