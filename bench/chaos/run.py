"""The soak's shell: the twin's processes, the schedule's lanes, the final disable, the verdict.

A :class:`~twin.Twin` runs the fleet of :data:`bench.chaos.schedule.FLEET` (a router and one
agent per host in separate processes, each host behind a cuttable link; ``backend="ecat"``: each
agent's pysoem against ``ecat-sim`` in a network namespace of its own). The twin is used for
what only it can do (start, kill and restart processes, cut links); commands, simulator faults,
status, events and flight recordings go through the soak's own plain client
(:mod:`bench.chaos.wire`). Three lanes run at once: commands, injection episodes, and a fetch of
every agent's flight recording every :data:`RECORDING_EVERY_S`. After the schedule, everything is
put back (links, slaves), every drive is disabled, and each drive's status is taken.
"""

from __future__ import annotations

import logging
import threading
import time
from array import array
from concurrent.futures import ThreadPoolExecutor
from dataclasses import dataclass, field
from typing import Any, Sequence

from twin import Twin, TwinError

from .schedule import FLEET, MOTION, Step
from .trace import Command, Injection, Limits, Recording, Trace
from .wire import WireClient, drive_key, malformed, pack, request

log = logging.getLogger(__name__)

RECORDING_EVERY_S = 4.0
#: Channels the limits monitor reads (the rest of a recording is dropped at once: memory).
KEPT_CHANNELS = ("time_ns", "statusword", "controlword", "mode_display", "target_position", "target_velocity")
#: How long the end waits for every host to answer, and for every drive to be found again.
HEAL_TIMEOUT_S = 60.0
COMMAND_WORKERS = 16
#: How long an unplug or WKC fault is asked to be undone before the soak gives up (a harness error).
UNDO_TIMEOUT_S = 15.0
#: After the final disable, how long a drive reported lost may take to be found again.
FINAL_FOUND_S = 5.0


def soak_fleet(fleet: dict[str, Any] = FLEET) -> dict[str, Any]:
    """The twin's fleet: :data:`FLEET` with the soak's motion limits and a group reflex of quick stop."""
    return {"hosts": {h: {**spec, "agent": {"reflex": "quick_stop", "defaults": {"motion": dict(MOTION)}}}
                      for h, spec in fleet["hosts"].items()},
            "groups": fleet["groups"]}


@dataclass
class Counts:
    """What the soak did, for the result."""

    commands: dict[str, int] = field(default_factory=dict)
    injections: dict[str, int] = field(default_factory=dict)
    injections_refused: int = 0
    recordings: int = 0
    recordings_missed: int = 0
    harness_errors: list[str] = field(default_factory=list)


class Soak:
    """One run: ``Soak(steps, seed).run(backend)`` returns the filled :class:`Trace`."""

    def __init__(self, steps: list[Step], seed: int, fleet: dict[str, Any] = FLEET) -> None:
        self.steps = steps
        self.seed = seed
        self.fleet = fleet
        hosts = {h: tuple(spec["axes"]) for h, spec in fleet["hosts"].items()}
        lim = Limits(MOTION["max_velocity"], MOTION["max_acceleration"])
        self.trace = Trace(hosts=hosts, groups={g: tuple(m) for g, m in fleet["groups"].items()},
                           limits={f"{h}/{a}": lim for h, axes in hosts.items() for a in axes})
        self.counts = Counts()
        self.twin: Twin | None = None
        self.client: WireClient | None = None
        self._stop = threading.Event()
        self._busy_hosts: set[str] = set()   # hosts whose recorder cannot answer now (cut, restarting)
        self._rec_last: dict[str, int] = {}  # per host: time_ns of the last cycle kept
        self._t0 = 0.0

    # ---- the run --------------------------------------------------------------------------------

    def run(self, backend: str = "sim") -> Trace:
        self.trace.sim_in_agent = backend == "sim"
        twin = self.twin = Twin(soak_fleet(self.fleet), backend=backend, log_level="WARNING")
        twin.start()
        try:
            self.client = WireClient(twin.endpoint, self.trace)
            time.sleep(1.0)  # every drive's status seen once (heartbeat) before the first command
            self._t0 = time.monotonic()
            lanes = [threading.Thread(target=self._inject_lane, name="chaos-inject", daemon=True),
                     threading.Thread(target=self._recording_lane, name="chaos-record", daemon=True)]
            for t in lanes:
                t.start()
            self._command_lane()
            lanes[0].join()
            self._stop.set()
            lanes[1].join()
            self._finish()
        finally:
            self.trace.processes = len(twin.pids())
            if self.client is not None:
                self.client.close()
            twin.stop()  # its last look at the children comes before it stops them
            self.trace.unexpected_exits = list(twin.unexpected_exits)
        return self.trace

    def _wait_until(self, at_s: float) -> None:
        left = self._t0 + at_s - time.monotonic()
        if left > 0:
            time.sleep(left)

    # ---- command lane ---------------------------------------------------------------------------

    def _command_lane(self) -> None:
        with ThreadPoolExecutor(COMMAND_WORKERS, thread_name_prefix="chaos-cmd") as pool:
            for i, step in enumerate(self.steps):
                if step.lane != "command":
                    continue
                self._wait_until(step.at_s)
                pool.submit(self._send, f"chaos-{self.seed}-{i}", step)

    def _addressed(self, target: str) -> tuple[str, ...]:
        host, _, axis = target.partition("/")
        return tuple(f"{host}/{a}" for a in self.trace.hosts[host]) if axis == "*" else (target,)

    def _send(self, rid: str, step: Step) -> None:
        assert self.client is not None
        host, _, axis = step.target.partition("/")
        if step.kind == "malformed":
            op, payload = malformed(step.flaw, rid)
        else:
            op, payload = step.kind, pack(request(rid, step.kind, step.args, step.timeout_s))
        cmd = Command(rid, op, drive_key(host, axis, f"cmd/{op}"), self._addressed(step.target), 0,
                      args=dict(step.args), malformed=step.flaw)
        if cmd.malformed:
            cmd.before = {r: s for r in cmd.addressed if (s := self.client.status(r)) is not None}
        try:
            self.client.command(cmd, payload, step.timeout_s)
        finally:
            if cmd.malformed:
                cmd.after = {r: s for r in cmd.addressed if (s := self.client.status(r)) is not None}
            self.trace.commands.append(cmd)
            key = "malformed" if cmd.malformed else cmd.op
            self.counts.commands[key] = self.counts.commands.get(key, 0) + 1

    # ---- injection lane -------------------------------------------------------------------------

    def _inject_lane(self) -> None:
        for step in self.steps:
            if step.lane != "inject":
                continue
            self._wait_until(step.at_s)
            try:
                inj = self._episode(step)
            except TwinError as exc:
                self.counts.harness_errors.append(f"{step.kind} {step.target}: {exc}")
                log.error("chaos: %s %s failed: %s", step.kind, step.target, exc)
                return  # the twin could not bring a part back: the rest would judge nothing
            self.trace.injections.append(inj)
            self.counts.injections[step.kind] = self.counts.injections.get(step.kind, 0) + 1
            if not inj.ok:
                self.counts.injections_refused += 1

    def _sim(self, target: str, action: str, **args: Any) -> tuple[bool, str]:
        assert self.client is not None
        host, _, axis = target.partition("/")
        slave: int | str = self.trace.hosts[host].index(axis) if axis else "*"
        return self.client.sim(host, slave, action, **args)

    def _episode(self, step: Step) -> Injection:
        twin = self.twin
        assert twin is not None
        start = time.time_ns()
        kind, target, hold = step.kind, step.target, step.hold_s
        if kind == "fault":
            ok, detail = self._sim(target, "fault", **step.args)
            now = time.time_ns()
            return Injection(kind, target, start, now, now, ok, detail)
        if kind in ("unplug", "wkc_fault"):
            ok, detail = self._sim(target, "unplug") if kind == "unplug" else self._sim(target, "wkc_fault", on=True)
            applied = time.time_ns()
            time.sleep(hold)
            undo = time.monotonic() + UNDO_TIMEOUT_S
            while True:  # idempotent: asked again until the simulator says it is done
                ok2, detail2 = self._sim(target, "plug") if kind == "unplug" else \
                    self._sim(target, "wkc_fault", on=False)
                if ok2 or time.monotonic() > undo:
                    break
                time.sleep(0.2)
            if not ok2:
                self.counts.harness_errors.append(f"{kind} {target}: could not be undone: {detail2}")
            return Injection(kind, target, start, applied, time.time_ns(), ok, f"{detail}; {detail2}")
        hosts = [target] if target else list(self.trace.hosts)
        self._busy_hosts.update(hosts)
        try:
            if kind == "cut":
                twin.cut(target)
                time.sleep(hold)
                twin.restore(target)
                twin.wait_answering([target], HEAL_TIMEOUT_S)
            elif kind == "agent_restart":
                twin.kill_agent(target)
                time.sleep(hold)
                twin.restart_agent(target, HEAL_TIMEOUT_S)
            elif kind == "router_restart":
                twin.kill_router()
                time.sleep(hold)
                twin.restart_router(HEAL_TIMEOUT_S)
            else:
                raise ValueError(f"unknown injection {kind!r}")
        finally:
            self._busy_hosts.difference_update(hosts)
        return Injection(kind, target, start, start, time.time_ns(), True, "")

    # ---- flight recordings ----------------------------------------------------------------------

    def _recording_lane(self) -> None:
        while not self._stop.wait(RECORDING_EVERY_S):
            self._fetch_recordings(RECORDING_EVERY_S + 1.0)

    def _fetch_recordings(self, last_s: float) -> None:
        assert self.client is not None
        for host in self.trace.hosts:
            if host in self._busy_hosts:
                continue
            rec = self.client.recording(host, last_s)
            if rec is None:
                self.counts.recordings_missed += 1
                continue
            self.counts.recordings += 1
            self.trace.recordings.append(self._trimmed(rec))

    def _trimmed(self, rec: Recording) -> Recording:
        """Only the limits monitor's channels, as arrays, from two cycles before the first one not
        kept yet (it judges a cycle by the two before it)."""
        times = rec.channels.get("time_ns", [])
        last = self._rec_last.get(rec.host, -1)
        first = 0
        while first < len(times) and times[first] <= last:
            first += 1
        first = max(0, first - 2)
        na = len(rec.axes)
        if times:
            self._rec_last[rec.host] = times[-1]
        chans: dict[str, Sequence[int]] = {}
        for name in KEPT_CHANNELS:
            values = rec.channels.get(name, [])
            per = 1 if name == "time_ns" else na
            chans[name] = array("q", values[first * per:])
        return Recording(rec.t_ns, rec.host, rec.cycle_us, max(0, rec.n_cycles - first), rec.axes, chans)

    # ---- the end --------------------------------------------------------------------------------

    def _finish(self) -> None:
        """Every host answering, every drive found again, every drive disabled; their statuses."""
        assert self.client is not None and self.twin is not None
        hosts = list(self.trace.hosts)
        try:
            self.twin.wait_answering(hosts, HEAL_TIMEOUT_S)
        except TwinError as exc:
            self.counts.harness_errors.append(f"after the schedule: {exc}")
        deadline = time.monotonic() + HEAL_TIMEOUT_S
        while time.monotonic() < deadline:
            st = [self.client.status(r) for r in self.trace.refs()]
            if all(s is not None and not s.lost for s in st):
                break
            time.sleep(0.2)
        self._fetch_recordings(RECORDING_EVERY_S + 2.0)
        for h in hosts:
            cmd = Command(f"chaos-{self.seed}-final-{h}", "disable", drive_key(h, "*", "cmd/disable"),
                          self._addressed(f"{h}/*"), 0)
            self.client.command(cmd, pack(request(cmd.request_id, "disable", timeout_s=5.0)), 5.0)
            self.trace.commands.append(cmd)
            self.counts.commands["disable"] = self.counts.commands.get("disable", 0) + 1
        time.sleep(0.5)
        self.trace.final_ns = time.time_ns()
        final = self.trace.final
        deadline = time.monotonic() + FINAL_FOUND_S
        for r in self.trace.refs():
            # a slave lost by a host stall right now (its SM watchdog) is found again within moments
            while (s := self.client.status(r)) is not None and s.lost and time.monotonic() < deadline:
                time.sleep(0.1)
            final[r] = s
