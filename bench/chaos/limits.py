"""The wire-limits monitor: every target in the flight recordings within the axis's limits.

A flight recording (``drives/@v1/<host>/agent/recording``) holds every cycle's statusword,
controlword and targets as written to the wire. A drive follows its targets while it is in
Operation enabled (statusword & 0x6F == 0x27) and the controlword says enable operation without
halt (controlword & 0x018F == 0x000F); only such cycles are judged. Per cycle of period T:

- cyclic synchronous position (0x6061 = 8): the position target's step |p[k] - p[k-1]| is at
  most max_velocity x T, and the change of step |s[k] - s[k-1]| at most max_acceleration x T^2;
- cyclic synchronous velocity (0x6061 = 9): |v[k]| is at most max_velocity and
  |v[k] - v[k-1]| at most max_acceleration x T.

Targets are whole counts, so each bound gets the rounding it allows (1 count on a step, 2 on a
change of step). Overlapping recordings are judged once per cycle (the cycle's monotonic start
time identifies it across fetches and agent restarts).
"""

from __future__ import annotations

from collections import defaultdict

from .trace import Result, Trace, Violation

CSP, CSV = 8, 9
#: Rounding allowance of whole-count targets: on a step, on a change of step.
STEP_SLACK, ACCEL_SLACK = 1.0, 2.0
EXAMPLES = 5


def follows(statusword: int, controlword: int) -> bool:
    """Whether a drive with these words follows its targets (operation enabled, enable operation, no halt)."""
    return statusword & 0x6F == 0x27 and controlword & 0x018F == 0x000F


def check_limits(trace: Trace) -> Result:
    r = Result("wire_limits")
    seen: set[tuple[str, str, int]] = set()
    over: dict[tuple[str, str], list[dict]] = defaultdict(list)
    for rec in trace.recordings:
        ch = rec.channels
        n, na = rec.n_cycles, len(rec.axes)
        t = rec.cycle_us * 1e-6
        times = ch.get("time_ns", [])
        if len(times) != n:
            continue
        for j, axis in enumerate(rec.axes):
            lim = trace.limits.get(f"{rec.host}/{axis}")
            if lim is None:
                continue
            sw, cw = ch["statusword"][j::na], ch["controlword"][j::na]
            mode, tp, tv = ch["mode_display"][j::na], ch["target_position"][j::na], ch["target_velocity"][j::na]
            vstep, astep = lim.max_velocity * t + STEP_SLACK, lim.max_acceleration * t * t + ACCEL_SLACK
            vmax, adv = lim.max_velocity + STEP_SLACK, lim.max_acceleration * t + STEP_SLACK
            run = 0  # consecutive following cycles up to k
            for k in range(n):
                run = run + 1 if follows(sw[k], cw[k]) else 0
                key = (rec.host, axis, times[k])
                if run < 2 or key in seen:
                    continue
                seen.add(key)
                m = mode[k]
                if m == CSP:
                    step = tp[k] - tp[k - 1]
                    r.checked += 1
                    if abs(step) > vstep:
                        over[(f"{rec.host}/{axis}", "position step above max_velocity x period")].append(
                            {"time_ns": times[k], "step": step, "limit": round(vstep - STEP_SLACK, 3)})
                    if run >= 3 and mode[k - 1] == CSP:
                        d = step - (tp[k - 1] - tp[k - 2])
                        r.checked += 1
                        if abs(d) > astep:
                            over[(f"{rec.host}/{axis}", "position step change above max_acceleration x period^2")].append(
                                {"time_ns": times[k], "step_change": d, "limit": round(astep - ACCEL_SLACK, 3)})
                elif m == CSV:
                    r.checked += 1
                    if abs(tv[k]) > vmax:
                        over[(f"{rec.host}/{axis}", "velocity target above max_velocity")].append(
                            {"time_ns": times[k], "target_velocity": tv[k], "limit": lim.max_velocity})
                    if mode[k - 1] != CSV:
                        continue  # the cycle before wrote another mode's targets: no change to judge
                    r.checked += 1
                    if abs(tv[k] - tv[k - 1]) > adv:
                        over[(f"{rec.host}/{axis}", "velocity target change above max_acceleration x period")].append(
                            {"time_ns": times[k], "change": tv[k] - tv[k - 1], "limit": round(adv - STEP_SLACK, 3)})
    for (ref, what), cases in sorted(over.items()):
        worst = max(cases, key=lambda c: abs(next(v for k, v in c.items() if k not in ("time_ns", "limit"))))
        r.violations.append(Violation(r.monitor, what, {"drive": ref, "count": len(cases), "worst": worst,
                                                        "examples": cases[:EXAMPLES]}))
    return r
