"""The leases a Fleet holds: taking, giving back, and renewing them in the background.

Leases are renewed every ttl/3 by this part's thread while the Fleet is open; a drive whose
renewal answers ``busy`` (or ``rejected``) was taken over and is reported as ``lease_lost``.
When the process dies, its liveliness token vanishes and the agents run the lease reaction.
"""

from __future__ import annotations

import logging
import threading
from typing import Any, Callable, Iterable, Mapping

from .results import CommandResult
from .selectors import DriveRef, Selection

log = logging.getLogger("supervisor.fleet")

#: ``command(op, selection, args, timeout_s)``: the Fleet's command path.
Command = Callable[[str, Selection, Mapping[str, Any], float], CommandResult]


class FleetLeases:
    """The leases held by supervisor ``name``: given the Fleet's command path, ``selection_of``
    (a selection of exactly some drives) and ``emit`` (its events); owns the lease table and the
    renewal thread."""

    def __init__(self, name: str, default_ttl_s: float, command: Command,
                 selection_of: Callable[[Iterable[DriveRef]], Selection], emit: Callable[..., None]) -> None:
        self._name = name
        self._command = command
        self._selection_of = selection_of
        self._emit = emit
        self._lock = threading.Lock()
        self._held: dict[DriveRef, float] = {}  # drive -> ttl_s
        self._renewer: threading.Thread | None = None
        self._stop = threading.Event()
        self._default_ttl_s = default_ttl_s

    def lease(self, sel: Selection, ttl_s: float, takeover: bool, timeout_s: float) -> CommandResult:
        """Take (or with ``takeover`` seize) the selected drives' leases for ``ttl_s``; start the
        renewal when the first is held."""
        res = self._command("lease", sel, {"holder": self._name, "ttl_s": ttl_s, "takeover": bool(takeover)},
                            timeout_s)
        with self._lock:
            for r in res.results:
                if r.ok:
                    self._held[DriveRef(r.host, r.axis)] = ttl_s
            start = bool(self._held) and self._renewer is None
            if start:
                self._renewer = threading.Thread(target=self._renew_loop, name=f"fleet-{self._name}-lease",
                                                 daemon=True)
        if start:
            self._renewer.start()  # type: ignore[union-attr]
        return res

    def held(self) -> list[DriveRef]:
        """Drives whose lease this supervisor holds (as far as it knows)."""
        with self._lock:
            return sorted(self._held)

    def release(self, sel: Selection, timeout_s: float) -> CommandResult:
        """Give the selected drives' leases back (no reaction runs)."""
        res = self._command("release", sel, {"holder": self._name}, timeout_s)
        with self._lock:
            for ref in sel.drives:
                self._held.pop(ref, None)
        return res

    def stop(self) -> None:
        """End the renewal (the leases held lapse, or are released before)."""
        self._stop.set()
        if self._renewer is not None:
            self._renewer.join(timeout=5)

    def _renew_loop(self) -> None:
        while not self._stop.is_set():
            with self._lock:
                held = sorted(self._held)
                ttl = min(self._held.values(), default=self._default_ttl_s)
            if self._stop.wait(ttl / 3.0):
                return
            if not held:
                continue
            try:
                res = self._command("lease", self._selection_of(held),
                                    {"holder": self._name, "ttl_s": ttl, "takeover": False}, min(1.0, ttl / 3.0))
            except Exception:
                if self._stop.is_set():
                    return
                log.exception("supervisor %s: lease renewal failed", self._name)
                continue
            lost = [r for r in res.results if r.outcome in ("busy", "rejected")]
            with self._lock:
                for r in lost:
                    self._held.pop(DriveRef(r.host, r.axis), None)
            for r in lost:  # listeners see the held leases already without every lost drive
                log.warning("supervisor %s: lease on %s lost (%s, holder %r)", self._name, r.name,
                            r.outcome, r.lease_holder)
                self._emit("lease_lost", r)
            for r in res.results:
                if not r.ok and r not in lost:
                    log.warning("supervisor %s: lease renewal on %s: %s %s", self._name, r.name, r.outcome, r.error)


__all__ = ["FleetLeases"]
