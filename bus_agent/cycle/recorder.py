"""The flight recorder: the last seconds of every cycle of every drive, in preallocated rings.

The cycle thread calls :meth:`Recorder.record` once per cycle (after the outputs are written):
it stores the cycle's values into ``array`` slots allocated at start-up (no allocation, no lock,
no I/O) and looks at the cycle's events for triggers. A ``fault``, ``reflex`` or ``lost`` event
(or :meth:`Recorder.request`, an explicit request) opens a window: ``pre_s`` before the trigger
and ``post_s`` after it. When the cycle has recorded the after part, it hands the window to the
``recorder`` thread, which copies it out of the ring (the ring keeps turning meanwhile; what was
overwritten during the copy is cut off) into one of the ``keep`` frozen recordings, kept until
replaced by newer ones. A trigger while a window is open belongs to that window.

:meth:`Recorder.fetch` (any thread but the cycle's) returns a :class:`RecordingData`: the last
seconds of the ring, or the latest window of a trigger kind (one still recording its after part
is waited for, bounded, so a fetch right after a fault gets that fault's window), or (``now``) a
window frozen on request, once it is complete. Channels and their meaning: ``schemas.messages.RECORDING_CHANNELS``.
"""

from __future__ import annotations

import collections
import logging
import threading
import time
from array import array
from dataclasses import dataclass, field
from typing import Any, Callable, Iterable, Protocol, Sequence

from bus_agent.runtime import CycleEvent

log = logging.getLogger(__name__)

#: Array type code of every channel (schemas.messages.RECORDING_CHANNELS names them): targets as
#: int64 (whatever a motion generator writes), process data as its PDO width.
CYCLE_CODES = {"cycle": "q", "time_ns": "q", "period_ns": "q", "wkc": "i"}
DRIVE_CODES = {"statusword": "H", "controlword": "H", "target_position": "q", "target_velocity": "q",
               "target_torque": "q", "position": "i", "velocity": "i", "torque": "h", "error_code": "H",
               "mode_display": "b"}
#: Event kinds that freeze a window (plus "request", from :meth:`Recorder.request`).
TRIGGER_KINDS = ("fault", "reflex", "lost")
#: Defaults: ring length, the part of a window before and after its trigger, frozen windows kept.
DEFAULT_SECONDS = 10.0
DEFAULT_PRE_S = 5.0
DEFAULT_POST_S = 1.0
DEFAULT_KEEP = 4


class RecordingUnavailable(LookupError):
    """No recording of the kind asked for (none frozen yet, recorder off, or failed)."""


class RecordedDrive(Protocol):
    """What the recorder reads of a drive (``bus_agent.cycle.drive.Drive``)."""

    inputs: Any           # DriveInputs: statusword, position_actual, velocity_actual, torque_actual, ...
    index: int            # position in the recorder's axes
    controlword: int
    out: Any              # DriveOutputs as written: target_position, target_velocity, target_torque


@dataclass(frozen=True)
class RecordingData:
    """Consecutive recorded cycles (``schemas.messages.Recording`` without the host)."""

    reason: str                 # "last" or the trigger kind
    cycle_us: int
    first_cycle: int
    n_cycles: int
    time_origin_ns: int         # wall clock at the first recorded cycle
    axes: tuple[str, ...]
    channels: dict[str, list[int]] = field(default_factory=dict)
    axis: str = ""
    detail: str = ""
    trigger_cycle: int = 0


@dataclass
class _Window:
    kind: str
    axis: str
    detail: str
    trigger_cycle: int
    start: int                  # first record index (the ring's running count) of the window
    end: int                    # one past the last record index
    asks: list["_Ask"] = field(default_factory=list)
    data: RecordingData | None = None
    #: Set once the recorder thread has copied the window out (or failed to): a fetch of its
    #: kind waits for it rather than answer with an older window or none.
    frozen: threading.Event = field(default_factory=threading.Event)


@dataclass
class _Ask:
    """An explicit request: answered by the window it opened or joined."""

    detail: str
    window: _Window | None = None
    done: threading.Event = field(default_factory=threading.Event)


class Recorder:
    """Rings of ``seconds`` of cycles for ``axes``; see the module docstring. ``wall_ns`` and
    ``mono_ns`` turn recorded monotonic times into a wall-clock origin."""

    def __init__(self, axes: Sequence[str], cycle_us: int, seconds: float = DEFAULT_SECONDS,
                 pre_s: float = DEFAULT_PRE_S, post_s: float = DEFAULT_POST_S, keep: int = DEFAULT_KEEP, *,
                 wall_ns: Callable[[], int] = time.time_ns, mono_ns: Callable[[], int] = time.monotonic_ns) -> None:
        if seconds <= 0 or pre_s < 0 or post_s < 0 or pre_s + post_s >= seconds:
            raise ValueError(f"recorder: need 0 <= pre_s + post_s < seconds (got {pre_s:g} + {post_s:g}, {seconds:g})")
        self.axes = tuple(axes)
        self.cycle_us = cycle_us
        per_s = 1e6 / cycle_us
        self.size = max(2, int(seconds * per_s))
        self.pre = int(pre_s * per_s)
        self.post = max(1, int(post_s * per_s))
        n = len(self.axes)
        self._cyc = {k: array(c, bytes(array(c).itemsize * self.size)) for k, c in CYCLE_CODES.items()}
        self._drv = {k: array(c, bytes(array(c).itemsize * self.size * n)) for k, c in DRIVE_CODES.items()}
        #: The per-drive channels as memoryviews: a row is copied to the next without a new array.
        self._views = tuple(memoryview(a) for a in self._drv.values())
        self.written = 0            # records written so far; the next goes to slot written % size
        self.error = ""             # why recording stopped ('' while it runs)
        self._open: _Window | None = None
        self._latest: _Window | None = None   # the window opened last (cycle thread writes, fetchers read)
        self._requested: collections.deque[_Ask] = collections.deque()
        self._closed: collections.deque[_Window] = collections.deque()
        self._frozen: collections.deque[RecordingData] = collections.deque(maxlen=keep)
        self._lock = threading.Lock()      # fetchers and the freezer; never the cycle
        self._wake = threading.Event()
        self._stop = threading.Event()
        self._thread: threading.Thread | None = None
        self._wall_ns = wall_ns
        self._mono_ns = mono_ns

    @property
    def memory_bytes(self) -> int:
        """Bytes preallocated for the rings."""
        return sum(a.itemsize * len(a) for a in (*self._cyc.values(), *self._drv.values()))

    # ---- cycle thread ------------------------------------------------------------------------

    def record(self, cycle: int, now_ns: int, period_ns: int, wkc: int, drives: Sequence[RecordedDrive],
               events: Sequence[CycleEvent], changed: Sequence[RecordedDrive] | None = None) -> None:
        """Store one cycle. ``changed``: only these drives may differ from the last record (the
        others' values are copied from it, one block per channel), None: all. Cycle thread only;
        cycle-safe (array stores, no allocation beyond the block copies' views)."""
        if self.error:
            return
        i = self.written % self.size
        c = self._cyc
        try:
            c["cycle"][i] = cycle
            c["time_ns"][i] = now_ns
            c["period_ns"][i] = period_ns
            c["wkc"][i] = wkc
            d = self._drv
            sw, cw, tp, tv, tt = d["statusword"], d["controlword"], d["target_position"], d["target_velocity"], \
                d["target_torque"]
            pos, vel, tq, ec, md = d["position"], d["velocity"], d["torque"], d["error_code"], d["mode_display"]
            n = len(self.axes)
            row = i * n
            slots: Iterable[tuple[int, RecordedDrive]]
            if changed is not None and self.written:
                last = (i - 1) % self.size * n
                for ch in self._views:
                    ch[row:row + n] = ch[last:last + n]
                slots = ((row + drv.index, drv) for drv in changed)
            else:
                slots = enumerate(drives, row)
            for k, drv in slots:
                inp = drv.inputs
                sw[k] = inp.statusword
                cw[k] = drv.controlword
                out = drv.out  # the targets as written to the wire (after the output stage)
                tp[k] = out.target_position
                tv[k] = out.target_velocity
                tt[k] = out.target_torque
                pos[k] = inp.position_actual
                vel[k] = inp.velocity_actual
                tq[k] = inp.torque_actual
                ec[k] = inp.error_code
                md[k] = inp.modes_of_operation_display
        except (OverflowError, TypeError, IndexError) as exc:  # a value beyond its channel: stop recording, not the cycle
            self.error = f"recording stopped at cycle {cycle}: {exc}"
            return
        self.written += 1           # published after the values: a reader trusts records < written
        if events or self._requested:
            self._triggers(cycle, events)
        w = self._open
        if w is not None and self.written >= w.end:
            self._open = None
            self._closed.append(w)
            self._wake.set()

    def _triggers(self, cycle: int, events: Sequence[CycleEvent]) -> None:
        while self._requested:
            ask = self._requested.popleft()
            if self._open is None:
                self._open_window(_Window("request", "", ask.detail, 0, 0, 0), cycle)
            assert self._open is not None
            ask.window = self._open     # a request during an open window is answered by it
            self._open.asks.append(ask)
        if self._open is not None:
            return
        for ev in events:
            if ev.kind in TRIGGER_KINDS:
                self._open_window(_Window(ev.kind, ev.axis, ev.detail, 0, 0, 0), cycle)
                return

    def _open_window(self, w: _Window, cycle: int) -> None:
        w.trigger_cycle = cycle
        w.start = max(0, self.written - 1 - self.pre)
        w.end = self.written + self.post
        self._open = w
        self._latest = w

    # ---- other threads ---------------------------------------------------------------------------

    def request(self, detail: str = "explicit request") -> _Ask:
        """Freeze a window around the next cycle (kind ``request``, or the window open then);
        ``.done`` is set once it is frozen, ``.window.data`` holds it. Thread-safe."""
        ask = _Ask(detail)
        self._requested.append(ask)
        return ask

    def start(self) -> None:
        """Start the ``recorder`` thread that copies closed windows out of the ring."""
        if self._thread is None:
            self._thread = threading.Thread(target=self._run, name="recorder", daemon=True)
            self._thread.start()

    def stop(self) -> None:
        self._stop.set()
        self._wake.set()
        if self._thread is not None:
            self._thread.join(2.0)

    def _run(self) -> None:
        while not self._stop.is_set():
            self._wake.wait(0.25)
            self._wake.clear()
            self.freeze_closed()

    def freeze_closed(self) -> None:
        """Copy every closed window out of the ring (the recorder thread; tests call it directly)."""
        while self._closed:
            w = self._closed.popleft()
            try:
                w.data = self._copy(w.start, w.end, w.kind, w.axis, w.detail, w.trigger_cycle)
                with self._lock:
                    self._frozen.append(w.data)
            except Exception:  # never lose the thread; the log says what broke
                log.exception("recorder: freezing a %s window failed", w.kind)
            w.frozen.set()
            for ask in w.asks:
                ask.done.set()

    def fetch(self, what: str = "last", last_s: float = DEFAULT_SECONDS, timeout_s: float = 5.0) -> RecordingData:
        """A recording (see the module docstring); raises :class:`RecordingUnavailable`. Not from the cycle.

        A trigger kind whose latest window is still open (or not yet copied out) waits for it, at
        most ``timeout_s`` plus the window's after part; only then does an older window or none
        answer."""
        if what == "now":
            ask = self.request()
            if not ask.done.wait(timeout_s + self.post * self.cycle_us / 1e6) or ask.window is None \
                    or ask.window.data is None:
                raise RecordingUnavailable("the requested window was not frozen in time (is the cycle running?)")
            return ask.window.data
        if what == "last":
            if self.error:
                raise RecordingUnavailable(self.error)
            end = self.written
            n = min(end, self.size - 1, max(1, int(last_s * 1e6 / self.cycle_us)))
            if n <= 0:
                raise RecordingUnavailable("nothing recorded yet")
            return self._copy(end - n, end, "last", "", "", 0)
        pending = self._latest
        if pending is not None and not pending.frozen.is_set() and what in ("any", pending.kind):
            # A trigger of this kind opened a window whose after part is still being recorded:
            # the latest window is that one, answered once it is frozen (post_s after the trigger).
            wait_s = timeout_s + self.post * self.cycle_us / 1e6
            if not pending.frozen.wait(wait_s):
                raise RecordingUnavailable(
                    f"the {pending.kind} window (trigger at cycle {pending.trigger_cycle}) was not frozen within "
                    f"{wait_s:g} s (is the cycle running?)")
            if pending.data is None:
                raise RecordingUnavailable(f"the {pending.kind} window (trigger at cycle {pending.trigger_cycle}) "
                                           "could not be copied out of the ring" + (f" ({self.error})" if self.error else ""))
            return pending.data
        with self._lock:
            for data in reversed(self._frozen):
                if what == "any" or data.reason == what:
                    return data
        kinds = "any trigger" if what == "any" else f"a {what} trigger"
        raise RecordingUnavailable(f"no window frozen by {kinds} yet" + (f" ({self.error})" if self.error else ""))

    def _copy(self, start: int, end: int, reason: str, axis: str, detail: str, trigger_cycle: int) -> RecordingData:
        """Records [start, end) out of the ring; what the cycle overwrote meanwhile is cut off."""
        size, n = self.size, len(self.axes)
        start = max(start, end - size + 1)
        raw_c: dict[str, list[int]] = {}
        raw_d: dict[str, list[int]] = {}
        lo, hi = start % size, end % size
        for name, a in self._cyc.items():
            raw_c[name] = (a[lo:hi] if lo < hi else a[lo:] + a[:hi]).tolist() if end > start else []
        for name, a in self._drv.items():
            raw_d[name] = (a[lo * n:hi * n] if lo < hi else a[lo * n:] + a[:hi * n]).tolist() if end > start else []
        # Slot of record x is rewritten when record x + size is written: cut what may have changed.
        valid_from = self.written + 1 - size
        cut = max(0, valid_from - start)
        if cut:
            start += cut
            raw_c = {k: v[cut:] for k, v in raw_c.items()}
            raw_d = {k: v[cut * n:] for k, v in raw_d.items()}
        count = max(0, end - start)
        if count <= 0:
            raise RecordingUnavailable(f"the {reason} window was overwritten before it could be copied")
        times = raw_c["time_ns"]
        origin = self._wall_ns() - (self._mono_ns() - times[0])
        return RecordingData(reason=reason, cycle_us=self.cycle_us, first_cycle=raw_c["cycle"][0], n_cycles=count,
                             time_origin_ns=max(0, origin), axes=self.axes, channels={**raw_c, **raw_d},
                             axis=axis, detail=detail[:400], trigger_cycle=trigger_cycle)
