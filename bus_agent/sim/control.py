"""Simulator control over Zenoh: fault injection on ``drives/@sim/<segment>/<slave>/<action>``.

A simulator (the in-process :class:`bus_agent.bus.sim_bus.SimBus` or ``ecat-sim``) serves one
queryable per segment on ``drives/@sim/<segment>/*/*`` (``schemas.keys.sim_control``). A query's
key names the slave (0-based position, or ``*`` for every slave) and the action; its payload is
a msgpack map of arguments. Each slave handled gets a reply on its concrete key with the msgpack
map ``{"ok": True, "detail": str}``; a refused request gets ``reply_err`` with the msgpack map
``{"ok": False, "error": str}`` naming the segment, slave, action and reason. Nothing is changed
by a refused request.

The ``@sim`` root is a verbatim chunk: production ACLs deny it whole, and no wildcard of the
production key space (``drives/@v1/...``) reaches it.

Handlers run on a worker thread of this module, never in the Zenoh callback.
"""

from __future__ import annotations

import logging
import threading
from typing import Any, Callable, Mapping

import msgpack
import zenoh

from schemas.keys import SIM_ROOT, InvalidKey, parse_sim_control, sim_control, validate_name

log = logging.getLogger(__name__)

Handler = Callable[[int, dict], str]

#: Queue depth of the queryable's channel (requests beyond it wait in Zenoh).
CHANNEL_CAPACITY = 64
DEFAULT_TIMEOUT_S = 2.0


class SimControlError(RuntimeError):
    """A simulator refused a control request, or none answered."""


def _encode(obj: Mapping[str, Any]) -> bytes:
    return msgpack.packb(obj, use_bin_type=True)


def parse_control_key(key: str, segment: str) -> tuple[str, str]:
    """Split ``drives/@sim/<segment>/<slave>/<action>`` into (slave chunk, action), the slave
    chunk being a position or ``*``; the segment may be ``*``. Raises ValueError otherwise.
    The concrete form is checked by :func:`schemas.keys.parse_sim_control`."""
    parts = str(key).split("/")
    if len(parts) == 5 and parts[2] in (segment, "*"):
        slave = parts[3]
        concrete = "/".join(parts[:2] + [segment, "0" if slave == "*" else slave, parts[4]])
        try:
            _seg, _pos, action = parse_sim_control(concrete)
        except InvalidKey as exc:
            raise ValueError(str(exc)) from None
        return slave, action
    raise ValueError(f"key {key!r} is not {SIM_ROOT}/{segment}/<slave>/<action>")


class SimControl:
    """Serve fault-injection requests for one simulated segment.

    ``handlers`` maps an action name (a legal key chunk) to ``handler(position, args) -> detail``;
    a handler raises ValueError/TypeError/KeyError (or any exception) to refuse. ``n_slaves``
    bounds the positions accepted. Call :meth:`close` to undeclare (idempotent).
    """

    def __init__(self, session: zenoh.Session, segment: str, handlers: Mapping[str, Handler], n_slaves: int) -> None:
        self.segment = validate_name(segment, "segment")
        for action in handlers:
            validate_name(action, "action")
        if n_slaves < 1:
            raise ValueError(f"n_slaves must be >= 1, got {n_slaves}")
        self._handlers = dict(handlers)
        self._n_slaves = n_slaves
        self.key = sim_control(segment, "*", "*")
        self._queryable = session.declare_queryable(self.key, handler=zenoh.handlers.FifoChannel(CHANNEL_CAPACITY))
        self._closed = False
        self._thread = threading.Thread(target=self._serve, name=f"sim-control-{segment}", daemon=True)
        self._thread.start()
        log.info("sim control for segment %s on %s (actions: %s)", segment, self.key, ", ".join(sorted(handlers)))

    def close(self) -> None:
        if self._closed:
            return
        self._closed = True
        try:
            self._queryable.undeclare()
        except Exception:  # session already closed: the channel ends anyway
            log.debug("sim control %s: undeclare failed", self.segment, exc_info=True)
        self._thread.join(timeout=5.0)

    def __enter__(self) -> "SimControl":
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()

    # ------------------------------------------------------------------ worker

    def _serve(self) -> None:
        try:
            for query in self._queryable:
                try:
                    self._handle(query)
                except Exception:
                    log.exception("sim control %s: failed to answer %s", self.segment, query.key_expr)
                finally:
                    query.drop()
        except Exception:
            log.debug("sim control %s: channel closed", self.segment, exc_info=True)

    def _refuse(self, query: zenoh.Query, message: str) -> None:
        log.warning("sim control %s: %s", self.segment, message)
        query.reply_err(_encode({"ok": False, "error": message}))

    def _handle(self, query: zenoh.Query) -> None:
        key = str(query.key_expr)
        try:
            slave, action = parse_control_key(key, self.segment)
        except ValueError as exc:
            self._refuse(query, str(exc))
            return
        where = f"segment {self.segment} slave {slave} action {action!r}"
        handler = self._handlers.get(action)
        if handler is None:
            self._refuse(query, f"{where}: unknown action (known: {', '.join(sorted(self._handlers))})")
            return
        if slave == "*":
            positions = list(range(self._n_slaves))
        elif int(slave) < self._n_slaves:
            positions = [int(slave)]
        else:
            self._refuse(query, f"{where}: no such slave (0..{self._n_slaves - 1} or '*')")
            return
        try:
            raw = query.payload.to_bytes() if query.payload is not None else b""
            args = msgpack.unpackb(raw, raw=False) if raw else {}
        except Exception as exc:
            self._refuse(query, f"{where}: payload is not msgpack: {exc}")
            return
        if not isinstance(args, dict) or not all(isinstance(k, str) for k in args):
            self._refuse(query, f"{where}: arguments must be a msgpack map with string keys, got {args!r}")
            return
        replies: list[tuple[int, str]] = []
        for pos in positions:
            try:
                detail = handler(pos, dict(args))
            except Exception as exc:
                # positions already handled keep their effect; say so
                done = f" (done before: {', '.join(str(p) for p, _ in replies)})" if replies else ""
                self._refuse(query, f"segment {self.segment} slave {pos} action {action!r}: {exc}{done}")
                return
            replies.append((pos, detail))
        for pos, detail in replies:
            log.info("sim control %s: slave %d %s %r: %s", self.segment, pos, action, args, detail)
            query.reply(sim_control(self.segment, pos, action), _encode({"ok": True, "detail": str(detail)}))


def sim_inject(session: zenoh.Session, segment: str, slave: int | str, action: str, *,
               timeout_s: float = DEFAULT_TIMEOUT_S, **args: Any) -> list[str]:
    """Ask the simulator of ``segment`` to perform ``action`` on ``slave`` (position or ``'*'``).

    Returns the ``detail`` of each reply (one per slave handled). Raises SimControlError when a
    simulator refuses, or when none answers within ``timeout_s``.
    """
    key = sim_control(segment, slave, action)
    details: list[str] = []
    errors: list[str] = []
    for reply in session.get(key, payload=_encode(args), timeout=timeout_s):
        if reply.ok is not None:
            body = _decode(reply.ok.payload.to_bytes())
            details.append(str(body.get("detail", "")) if isinstance(body, dict) else str(body))
        elif reply.err is not None:
            body = _decode(reply.err.payload.to_bytes())
            errors.append(str(body.get("error", body)) if isinstance(body, dict) else str(body))
    if errors:
        raise SimControlError("; ".join(errors))
    if not details:
        raise SimControlError(f"no simulator answered on {key} within {timeout_s} s")
    return details


def _decode(raw: bytes) -> Any:
    try:
        return msgpack.unpackb(raw, raw=False)
    except Exception:
        return raw.decode("utf-8", "replace")
