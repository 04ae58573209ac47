"""Drive leases: exclusive control of drives by one supervisor (pure logic, no I/O, no clock).

A lease gives one supervisor (the *holder*, named like its liveliness token
``drives/@v1/@sup/<holder>``) exclusive command of a drive. While a drive is leased, commands
from anyone else get the outcome ``busy`` naming the holder. The holder renews by repeating
the ``lease`` op before ``ttl_s`` runs out, and ends it with ``release``. Another supervisor
takes it over only with ``takeover: true`` (an explicit, logged act). When the lease expires
or the holder's liveliness token disappears, the lease ends and the gateway runs the
configured loss reaction (default: quick stop, then disable) on the drives it covered.

The gateway owns one :class:`LeaseTable`, touched only from its command thread; every method
takes the current monotonic time, so tests drive the clock.
"""

from __future__ import annotations

from dataclasses import dataclass
from enum import Enum
from typing import Iterable

#: Bounds of a lease's time to live, seconds.
MIN_TTL_S = 0.1
MAX_TTL_S = 3600.0
DEFAULT_TTL_S = 10.0


class LeaseResult(str, Enum):
    """What a lease request or release did for one drive."""

    GRANTED = "granted"          # the drive was free
    RENEWED = "renewed"          # the holder repeated its lease
    TAKEN_OVER = "taken_over"    # another holder's lease was replaced (takeover: true)
    BUSY = "busy"                # leased by someone else; nothing changed
    RELEASED = "released"        # the holder gave it up
    NOT_LEASED = "not_leased"    # release of a free drive: nothing to do


class LeaseEnd(str, Enum):
    """Why a lease ended without a release: both run the loss reaction."""

    EXPIRED = "expired"
    HOLDER_LOST = "holder_lost"


@dataclass(frozen=True)
class Lease:
    axis: str
    holder: str
    ttl_s: float
    expires_s: float  # monotonic


@dataclass(frozen=True)
class LeaseDecision:
    """Per-drive answer. ``holder`` is the holder after the decision ('' if free);
    ``previous`` the holder before it (for takeover and busy)."""

    axis: str
    result: LeaseResult
    holder: str
    previous: str = ""

    @property
    def ok(self) -> bool:
        return self.result is not LeaseResult.BUSY


@dataclass(frozen=True)
class EndedLease:
    lease: Lease
    why: LeaseEnd


class LeaseTable:
    """Leases by axis. Not thread-safe: one owner thread."""

    def __init__(self) -> None:
        self._leases: dict[str, Lease] = {}

    def holder(self, axis: str) -> str:
        """Current holder of ``axis`` or ''."""
        lease = self._leases.get(axis)
        return lease.holder if lease else ""

    def holders(self) -> dict[str, str]:
        """axis -> holder for every leased axis (a copy)."""
        return {axis: lease.holder for axis, lease in self._leases.items()}

    def get(self, axis: str) -> Lease | None:
        return self._leases.get(axis)

    def check(self, axis: str, supervisor: str) -> str:
        """'' if ``supervisor`` may command ``axis``, else the holder that blocks it."""
        holder = self.holder(axis)
        return "" if not holder or holder == supervisor else holder

    def acquire(
        self, axes: Iterable[str], holder: str, ttl_s: float, takeover: bool, now_s: float
    ) -> list[LeaseDecision]:
        """Lease, renew or take over ``axes`` for ``holder``.

        All or nothing: if any axis is held by someone else and ``takeover`` is false, every
        axis answers BUSY (the busy ones naming their holder) and nothing changes, so a
        supervisor never ends up holding half of what it asked for.
        """
        if not holder:
            raise ValueError("a lease needs a holder name")
        if not MIN_TTL_S <= ttl_s <= MAX_TTL_S:
            raise ValueError(f"ttl_s {ttl_s!r} out of range [{MIN_TTL_S}, {MAX_TTL_S}]")
        axes = list(axes)
        blocked = {a: self.holder(a) for a in axes if self.holder(a) not in ("", holder)}
        if blocked and not takeover:
            first = next(iter(blocked.values()))
            # ``previous`` names who blocks: the axis' own holder, else the first blocker.
            return [LeaseDecision(a, LeaseResult.BUSY, self.holder(a), blocked.get(a, first)) for a in axes]
        out = []
        for axis in axes:
            previous = self.holder(axis)
            self._leases[axis] = Lease(axis, holder, float(ttl_s), now_s + ttl_s)
            if previous == holder:
                result = LeaseResult.RENEWED
            elif previous:
                result = LeaseResult.TAKEN_OVER
            else:
                result = LeaseResult.GRANTED
            out.append(LeaseDecision(axis, result, holder, previous))
        return out

    def release(self, axes: Iterable[str], holder: str) -> list[LeaseDecision]:
        """Release ``axes`` held by ``holder``; axes held by others answer BUSY and stay leased."""
        out = []
        for axis in axes:
            current = self.holder(axis)
            if not current:
                out.append(LeaseDecision(axis, LeaseResult.NOT_LEASED, ""))
            elif current != holder:
                out.append(LeaseDecision(axis, LeaseResult.BUSY, current, current))
            else:
                del self._leases[axis]
                out.append(LeaseDecision(axis, LeaseResult.RELEASED, "", current))
        return out

    def expire(self, now_s: float) -> list[EndedLease]:
        """Remove and return the leases whose time to live ran out at ``now_s``."""
        ended = [lease for lease in self._leases.values() if lease.expires_s <= now_s]
        for lease in ended:
            del self._leases[lease.axis]
        return [EndedLease(lease, LeaseEnd.EXPIRED) for lease in ended]

    def holder_lost(self, holder: str) -> list[EndedLease]:
        """Remove and return every lease of ``holder`` (its liveliness token disappeared)."""
        ended = [lease for lease in self._leases.values() if lease.holder == holder]
        for lease in ended:
            del self._leases[lease.axis]
        return [EndedLease(lease, LeaseEnd.HOLDER_LOST) for lease in ended]

    def next_expiry_s(self) -> float | None:
        """Earliest expiry time, to sleep until it; None without leases."""
        return min((lease.expires_s for lease in self._leases.values()), default=None)
