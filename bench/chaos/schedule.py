"""The soak's schedule, pure and seeded: the same seed and length give the same steps.

Two lanes run side by side. The **command lane** sends a command every 0.1-0.4 s (enable,
disable, quick stop, halt, fault reset, moves, jogs, stops, mode changes, and malformed ones) to
one drive or to every drive of a host; its steps are started on time, each in its own worker, so
commands overlap each other and the faults. The **injection lane** runs one episode at a time:
a drive fault, an unplug (plugged again after ``hold_s``), a WKC fault (off after ``hold_s``), a
cut link (restored after ``hold_s``), an agent killed with SIGKILL (restarted after ``hold_s``)
or the router killed (likewise); an episode starts at its time or when the one before it ended.
"""

from __future__ import annotations

import math
import random
from dataclasses import asdict, dataclass, field
from typing import Any

#: The soak's fleet: three hosts of two simulated drives, one cross-host group and one spanning a
#: host and a half, one drive in no group. Limits in counts (the default unit).
FLEET: dict[str, Any] = {
    "hosts": {h: {"axes": ["a", "b"]} for h in ("c1", "c2", "c3")},
    "groups": {"line": ["c1/a", "c2/a"], "cell": ["c2/b", "c3/a", "c3/b"]},
}
MAX_VELOCITY = 200_000.0        # counts/s: 200 counts per 1 ms cycle
MAX_ACCELERATION = 10_000_000.0  # counts/s^2: a step changes by at most 10 counts per cycle
MAX_JERK = 1_000_000_000.0
MOTION = {"max_velocity": MAX_VELOCITY, "max_acceleration": MAX_ACCELERATION, "max_jerk": MAX_JERK}

FAULT_CODES = (0x2310, 0x5530, 0x7121, 0x4210, 0x8611)
#: Command lane: op -> weight (``malformed``: a command built with one flaw of :data:`FLAWS`).
COMMAND_WEIGHTS = {"enable": 22, "fault_reset": 14, "move": 16, "jog": 8, "disable": 6, "quick_stop": 5, "halt": 5,
                   "stop": 5, "set_mode": 3, "malformed": 8}
#: Injection lane: kind -> (weight, hold seconds range).
INJECTION_WEIGHTS = {"fault": (30, (0.0, 0.0)), "unplug": (15, (0.3, 2.0)), "wkc_fault": (15, (0.2, 1.5)),
                     "cut": (10, (1.0, 5.0)), "agent_restart": (10, (0.3, 1.5)), "router_restart": (5, (0.3, 1.5))}
#: How a malformed command is broken; every one must be refused with nothing changed.
FLAWS = ("not_msgpack", "not_a_map", "missing_request_id", "empty_request_id", "op_mismatch", "unknown_argument",
         "mode_out_of_range", "wrong_version", "wrong_type", "move_to_and_by", "negative_velocity",
         "jog_without_velocity", "unknown_field", "wrong_message_type", "nan_timeout")


@dataclass(frozen=True)
class Step:
    """One step: at ``at_s`` from the start, in ``lane`` (``command`` or ``inject``), ``kind`` (an
    op, ``malformed``, or an injection kind) on ``target`` (``host/axis``, ``host/*``, ``host`` or
    '' for the router), with ``args``; ``timeout_s`` of a command, ``hold_s`` of an episode,
    ``flaw`` of a malformed command."""

    at_s: float
    lane: str
    kind: str
    target: str
    args: dict[str, Any] = field(default_factory=dict)
    timeout_s: float = 3.0
    hold_s: float = 0.0
    flaw: str = ""

    def to_json(self) -> dict[str, Any]:
        return {k: v for k, v in asdict(self).items() if v not in ("", {}, 0.0) or k in ("at_s", "lane", "kind")}


def refs(fleet: dict[str, Any]) -> list[str]:
    return [f"{h}/{a}" for h, spec in fleet["hosts"].items() for a in spec["axes"]]


def _pick(rng: random.Random, weights: dict[str, Any]) -> str:
    names = list(weights)
    w = [v[0] if isinstance(v, tuple) else v for v in weights.values()]
    return rng.choices(names, w)[0]


def _command(rng: random.Random, at: float, fleet: dict[str, Any]) -> Step:
    op = _pick(rng, COMMAND_WEIGHTS)
    hosts = list(fleet["hosts"])
    target = rng.choice(refs(fleet)) if rng.random() < 0.65 else f"{rng.choice(hosts)}/*"
    if op == "malformed":
        return Step(round(at, 3), "command", op, target, flaw=rng.choice(FLAWS), timeout_s=2.0)
    args: dict[str, Any] = {}
    timeout = 3.0
    if op == "halt":
        args = {"on": rng.random() < 0.5}
    elif op == "move":
        vel = MAX_VELOCITY * rng.choice((0.3, 0.6, 0.95, 1.0, 1.2))
        args = {"to": float(rng.randrange(-300_000, 300_000, 1000)), "velocity": vel}
        if target.endswith("/*") and rng.random() < 0.5:
            args["sync"] = True
        # the longest move from anywhere in range, at the velocity asked, with its ramps
        timeout = round(600_000 / min(vel, MAX_VELOCITY) + 2 * MAX_VELOCITY / MAX_ACCELERATION + 3.0, 2)
    elif op == "jog":
        for_s = round(rng.uniform(0.2, 1.5), 2)
        args = {"velocity": math.copysign(MAX_VELOCITY * rng.uniform(0.2, 1.0), rng.random() - 0.5), "for_s": for_s}
        timeout = for_s + 3.0
    elif op == "stop":
        args = {"release": True} if rng.random() < 0.5 else {}
    elif op == "set_mode":
        args = {"mode": rng.choice((8, 8, 9))}
    return Step(round(at, 3), "command", op, target, args, timeout_s=timeout)


def _injection(rng: random.Random, at: float, fleet: dict[str, Any], kind: str) -> Step:
    lo, hi = INJECTION_WEIGHTS[kind][1]
    hold = round(rng.uniform(lo, hi), 2)
    if kind in ("fault", "unplug"):
        target = rng.choice(refs(fleet))
    elif kind == "wkc_fault":
        target = rng.choice(refs(fleet)) if rng.random() < 0.7 else rng.choice(list(fleet["hosts"]))
    elif kind in ("cut", "agent_restart"):
        target = rng.choice(list(fleet["hosts"]))
    else:
        target = ""
    args = {"error_code": rng.choice(FAULT_CODES)} if kind == "fault" else {}
    return Step(round(at, 3), "inject", kind, target, args, hold_s=hold)


def make_schedule(seed: int, seconds: float, fleet: dict[str, Any] = FLEET) -> list[Step]:
    """Every step of a soak of ``seconds`` with ``seed``, in time order (commands from 0.5 s,
    injections from 3 s; an injection episode's nominal end plus 0.5-2 s starts the next). The
    first injection episodes are every kind once, in a seeded order, so a short soak meets them all."""
    rng = random.Random(seed)
    steps: list[Step] = []
    t = 0.5
    while t < seconds:
        steps.append(_command(rng, t, fleet))
        t += rng.uniform(0.1, 0.4)
    t = 3.0  # the first enables have gone out
    first = rng.sample(list(INJECTION_WEIGHTS), len(INJECTION_WEIGHTS))  # every kind once, early
    while t < seconds:
        s = _injection(rng, t, fleet, first.pop(0) if first else _pick(rng, INJECTION_WEIGHTS))
        steps.append(s)
        t += s.hold_s + rng.uniform(0.5, 2.0)
    steps.sort(key=lambda s: (s.at_s, s.lane))
    return steps


def schedule_json(seed: int, seconds: float, steps: list[Step], fleet: dict[str, Any] = FLEET) -> dict[str, Any]:
    """The schedule as written next to the result: replaying ``seed`` and ``seconds`` gives it again."""
    return {"seed": seed, "seconds": seconds, "fleet": fleet, "motion": MOTION, "steps": [s.to_json() for s in steps]}
