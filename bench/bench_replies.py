"""CPU of the command reply path per command, for 16 and 64 drives, next to bare msgpack in the
same run (one process, no network, min of N so that a loaded machine does not decide):

- **gateway**: decode and validate the request (``parse_command``), then build and encode one
  ``CommandReply`` per addressed drive (what ``gw-command`` does per command besides zenoh);
- **collector**: decode and validate those replies (what a supervisor does with them);
- **publish pass**: build and encode one ``DriveStatus`` per drive from its fields (what
  ``gw-publish`` does in every cycle of an enable, competing with the replies for the GIL);
- **status decode**: decode and validate those statuses (what ``supervisor.Fleet`` and every
  watcher do with each one);
- **bare**: ``msgpack.packb``/``unpackb`` of the same maps (the floor of any encoding).

Each request has a new request id, so the per-field memory of accepted strings in
``schemas.messages`` helps only with what repeats in an agent (names, states, outcomes).

    python -m bench.bench_replies [--rounds N] [--out PATH]

Writes ``bench/results/bench_replies.json`` (microseconds per command, ratios to bare msgpack,
load average). No root.
"""

from __future__ import annotations

import itertools
import time
from typing import Any, Callable

import msgpack

from bench.common import bench_parser, loadavg, run_stamp, write_result
from bus_agent.gateway.requests import parse_command
from schemas import keys
from schemas import messages as m

SIZES = (16, 64)


def best_us(fn: Callable[[], Any], rounds: int, repeats: int = 7) -> float:
    """Minimum over ``repeats`` of the mean thread CPU time of one ``fn()``, in microseconds."""
    best = float("inf")
    for _ in range(repeats):
        t0 = time.thread_time()
        for _ in range(rounds):
            fn()
        best = min(best, (time.thread_time() - t0) / rounds * 1e6)
    return round(best, 2)


def _status(host: str, axis: str, seq: int) -> dict:
    return dict(host=host, axis=axis, seq=seq, time_ns=time.time_ns(), cycle=seq, state="operation_enabled",
                statusword=0x0237, controlword=0x000F, goal="enabled", halt=False, error_code=0, mode=8, mode_display=8,
                position=1000 + seq, velocity=3, torque=-2, al_state="op", slave=0, objects={"digital_inputs": 0})


def figures(drives: int, rounds: int) -> dict:
    host = "bench"
    axes = tuple(f"axis{i}" for i in range(drives))
    key = keys.drive_cmd(host, "*", "enable")
    ids = itertools.count()

    def gateway() -> None:
        rid = f"sup-{next(ids)}"
        payload = m.encode(m.CommandRequest(request_id=rid, op="enable", timeout_s=5.0, supervisor="sup"))
        parsed = parse_command(payload, key, host, axes)
        for a in parsed.axes:
            m.encode_new(m.CommandReply, dict(request_id=rid, host=host, op="enable", outcome="done", axis=a,
                                              state="operation_enabled", elapsed_s=0.0071, cycles=7))

    replies = [m.encode(m.CommandReply(request_id="sup-1", host=host, op="enable", outcome="done", axis=a,
                                       state="operation_enabled", elapsed_s=0.0071, cycles=7)) for a in axes]
    maps = [m.to_dict(m.decode(r)) for r in replies]
    statuses = [_status(host, a, 1) for a in axes]
    status_payloads = [m.encode_new(m.DriveStatus, s)[1] for s in statuses]
    status_maps = [msgpack.unpackb(s) for s in status_payloads]

    def collector() -> None:
        for r in replies:
            m.decode(r, m.CommandReply)

    def publish() -> None:
        for s in statuses:
            m.encode_new(m.DriveStatus, s)

    def status_decode() -> None:
        for s in status_payloads:
            m.decode(s, m.DriveStatus)

    def bare_status_decode() -> None:
        for s in status_payloads:
            msgpack.unpackb(s, raw=False)

    def bare_replies() -> None:
        for d in maps:
            msgpack.unpackb(msgpack.packb(d, use_bin_type=True), raw=False)

    def bare_status() -> None:
        for d in status_maps:
            msgpack.packb(d, use_bin_type=True)

    out = {"gateway_us": best_us(gateway, rounds), "collector_us": best_us(collector, rounds),
           "publish_pass_us": best_us(publish, rounds), "bare_msgpack_replies_us": best_us(bare_replies, rounds),
           "bare_msgpack_status_us": best_us(bare_status, rounds), "status_decode_us": best_us(status_decode, rounds),
           "bare_msgpack_status_decode_us": best_us(bare_status_decode, rounds)}
    out["gateway_over_bare"] = round(out["gateway_us"] / out["bare_msgpack_replies_us"], 2)
    out["collector_over_bare"] = round(out["collector_us"] / out["bare_msgpack_replies_us"], 2)
    out["publish_pass_over_bare"] = round(out["publish_pass_us"] / out["bare_msgpack_status_us"], 2)
    out["status_decode_over_bare"] = round(out["status_decode_us"] / out["bare_msgpack_status_decode_us"], 2)
    return out


def run(rounds: int) -> dict:
    start = loadavg()
    return {"rounds": rounds, "drives": {str(n): figures(n, max(1, rounds * 16 // n)) for n in SIZES},
            **run_stamp(start)}


def main(argv: list[str] | None = None) -> int:
    p = bench_parser("bench_replies", __doc__)
    p.add_argument("--rounds", type=int, default=200, help="commands per repeat for 16 drives (default 200)")
    args = p.parse_args(argv)
    write_result(run(args.rounds), args.out)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
