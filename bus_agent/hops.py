"""Time stamps of a command's hops across processes, for the benchmarks' breakdown (off by default).

With ``ZENOH_DRIVES_HOPS=<directory>`` in the environment, :func:`stamp` records
``(hop, time.monotonic_ns())`` in memory, and each process writes its stamps to
``<directory>/hops-<pid>.txt`` (one ``hop ns`` line each) when it exits. CLOCK_MONOTONIC is one
clock for every process of the machine, so the client's, the gateway's and the cycle's stamps
line up. ``bench.bench_agent --hops`` uses it to say where an enable's time goes.

Off, a stamp costs one global test. On, it is a deque append: cycle-safe (no I/O, no lock).
"""

from __future__ import annotations

import atexit
import collections
import os
import time

#: Names a directory: stamps are recorded and written there at exit.
ENV = "ZENOH_DRIVES_HOPS"
#: At most this many stamps are kept per process (the oldest go).
MAX_STAMPS = 1_000_000

_dir = os.environ.get(ENV, "")
ENABLED = bool(_dir)
_stamps: collections.deque[tuple[str, int]] = collections.deque(maxlen=MAX_STAMPS)


def stamp(hop: str) -> None:
    """Record that ``hop`` happened now (a no-op unless :data:`ENV` is set)."""
    if ENABLED:
        _stamps.append((hop, time.monotonic_ns()))


def write() -> None:
    """Write this process's stamps to ``<dir>/hops-<pid>.txt`` (also called at exit)."""
    if not ENABLED or not _stamps:
        return
    path = os.path.join(_dir, f"hops-{os.getpid()}.txt")
    with open(path, "a") as f:
        f.writelines(f"{hop} {ns}\n" for hop, ns in list(_stamps))
    _stamps.clear()


def read(directory: str) -> list[tuple[int, str]]:
    """Every stamp written under ``directory``, as ``(ns, hop)`` in time order."""
    out: list[tuple[int, str]] = []
    for name in os.listdir(directory):
        if name.startswith("hops-") and name.endswith(".txt"):
            with open(os.path.join(directory, name)) as f:
                for line in f:
                    hop, _, ns = line.strip().rpartition(" ")
                    if hop:
                        out.append((int(ns), hop))
    out.sort()
    return out


def rounds(stamps: list[tuple[int, str]], start: str, end: str) -> list[dict[str, list[float]]]:
    """The rounds in ``stamps`` (``(ns, hop)`` in time order): each from a ``start`` stamp to the
    first ``end`` stamp after it (a round without one is dropped); per round, every hop stamped
    in between with its times in ms after the round's start. Pure."""
    out: list[dict[str, list[float]]] = []
    current: dict[str, list[float]] | None = None
    t0 = 0
    for ns, hop in stamps:
        if hop == start:
            current, t0 = {}, ns
        elif current is not None:
            current.setdefault(hop, []).append((ns - t0) / 1e6)
            if hop == end:
                out.append(current)
                current = None
    return out


def breakdown(rounds_: list[dict[str, list[float]]]) -> dict[str, dict[str, float]]:
    """Where the time of the rounds (:func:`rounds`) goes: per hop, the p50 over the rounds of
    its first and of its last stamp (ms after the round's start) and its stamps per round; hops
    in the order of their p50 first stamp. Pure."""
    def p50(xs: list[float]) -> float:
        xs = sorted(xs)
        return round(xs[len(xs) // 2], 3)

    table = {h: {"first_ms": p50([r[h][0] for r in rounds_ if h in r]),
                 "last_ms": p50([r[h][-1] for r in rounds_ if h in r]),
                 "per_round": round(sum(len(r.get(h, ())) for r in rounds_) / len(rounds_), 1)}
             for h in {h for r in rounds_ for h in r}}
    return dict(sorted(table.items(), key=lambda kv: kv[1]["first_ms"]))


if ENABLED:
    atexit.register(write)
