"""The soak's command client: a plain zenoh-python session speaking the README's wire contract.

Nothing of the project's supervisor is used here (no ``Fleet``, no key builders): the keys are
written as the README's "Key space and messages" section documents them and the payloads are
msgpack maps with ``v``, ``type`` and the documented fields, so the soak checks the contract from
outside, as a third-party client would meet it. The session is a Zenoh client of the twin's
router, with multicast scouting off and the README's 3 s link lease.

Everything seen is appended to a :class:`~bench.chaos.trace.Trace` (statuses, events and agent
statuses from subscriptions; replies of the commands sent here; flight recordings).
"""

from __future__ import annotations

import json
import threading
import time
from typing import Any

import msgpack
import zenoh

from .trace import AgentInfo, Command, ErrReply, Event, Recording, Reply, Status, Trace

V = 1
ROOT = "drives/@v1"
#: Extra time a query waits beyond the command's own timeout (the agent's grace, then ours).
QUERY_GRACE_S = 4.0


def drive_key(host: str, axis: str, what: str) -> str:
    """``drives/@v1/<host>/drive/<axis>/<what>`` (``status``, ``event``, ``cmd/<op>``)."""
    return f"{ROOT}/{host}/drive/{axis}/{what}"


def request(request_id: str, op: str, args: dict | None = None, timeout_s: float = 5.0) -> dict[str, Any]:
    """A ``command_request`` map."""
    return {"v": V, "type": "command_request", "request_id": request_id, "op": op, "args": args or {},
            "timeout_s": timeout_s, "supervisor": ""}


def pack(obj: Any) -> bytes:
    return msgpack.packb(obj, use_bin_type=True)


def unpack(raw: bytes) -> dict[str, Any] | None:
    try:
        obj = msgpack.unpackb(raw, raw=False)
    except Exception:
        return None
    return obj if isinstance(obj, dict) else None


def client_config(endpoint: str) -> zenoh.Config:
    """A client session's configuration: the router at ``endpoint``, no scouting, 3 s link lease."""
    conf = zenoh.Config()
    for key, value in {"mode": "client", "connect/endpoints": [endpoint], "connect/timeout_ms": 10000,
                       "scouting/multicast/enabled": False, "transport/link/tx/lease": 3000,
                       "transport/link/tx/keep_alive": 4}.items():
        conf.insert_json5(key, json.dumps(value))
    return conf


def _status(t: int, d: dict) -> Status:
    return Status(t, d["host"], d["axis"], d["seq"], d["time_ns"], d["cycle"], d["state"], bool(d.get("lost", False)),
                  d.get("goal", ""), d.get("mode", 0), bool(d.get("halt", False)), d.get("lease_holder", ""),
                  d.get("error_code", 0))


class WireClient:
    """Subscriptions that fill ``trace``, and commands, status gets and recordings on demand."""

    def __init__(self, endpoint: str, trace: Trace) -> None:
        self.trace = trace
        self.session = zenoh.open(client_config(endpoint))
        self._lock = threading.Lock()
        self.undecodable = 0
        self._subs = [
            self.session.declare_subscriber(f"{ROOT}/*/drive/*/status", self._on_status),
            self.session.declare_subscriber(f"{ROOT}/*/drive/*/event", self._on_event),
            self.session.declare_subscriber(f"{ROOT}/*/agent", self._on_agent),
        ]

    def close(self) -> None:
        for s in self._subs:
            s.undeclare()
        self.session.close()

    def _decoded(self, sample: zenoh.Sample, type_: str) -> dict | None:
        d = unpack(sample.payload.to_bytes())
        if d is None or d.get("type") != type_:
            with self._lock:
                self.undecodable += 1
            return None
        return d

    def _on_status(self, sample: zenoh.Sample) -> None:
        if (d := self._decoded(sample, "drive_status")) is not None:
            self.trace.statuses.append(_status(time.time_ns(), d))

    def _on_event(self, sample: zenoh.Sample) -> None:
        if (d := self._decoded(sample, "event")) is not None:
            self.trace.events.append(Event(time.time_ns(), d["host"], d["axis"], d["seq"], d["time_ns"], d["cycle"],
                                           d["kind"], d.get("detail", ""), d.get("from_state", "unknown"),
                                           d.get("to_state", "unknown"), d.get("request_id", "")))

    def _on_agent(self, sample: zenoh.Sample) -> None:
        if (d := self._decoded(sample, "agent_status")) is not None:
            self.trace.agents.append(AgentInfo(time.time_ns(), d["host"], d["seq"], d.get("instance", ""),
                                               d.get("state", ""), float(d.get("period_max_us", 0.0))))

    # ---- queries ---------------------------------------------------------------------------------

    def command(self, cmd: Command, payload: bytes, timeout_s: float) -> Command:
        """Send ``payload`` as a query on ``cmd.key`` and gather every reply into ``cmd`` (no
        consolidation: a second reply for one drive must be seen)."""
        cmd.sent_ns = time.time_ns()
        try:
            replies = self.session.get(cmd.key, payload=payload, target=zenoh.QueryTarget.ALL,
                                       consolidation=zenoh.ConsolidationMode.NONE, timeout=timeout_s + QUERY_GRACE_S)
            for rep in replies:
                now = time.time_ns()
                if rep.ok is not None:
                    d = unpack(rep.ok.payload.to_bytes())
                    if d is None or d.get("type") != "command_reply":
                        cmd.errors.append(ErrReply(now, "", f"undecodable reply on {rep.ok.key_expr}"))
                        continue
                    cmd.replies.append(Reply(now, d["host"], d.get("axis", ""), d["request_id"], d["op"], d["outcome"],
                                             d.get("state", "unknown"), d.get("reason", "")))
                elif rep.err is not None:
                    text = rep.err.payload.to_bytes().decode("utf-8", "replace")
                    host = text.split(":", 1)[0] if ":" in text else ""
                    if host.startswith("agent "):  # "agent h1 is shutting down: ..."
                        host = host.split()[1]
                    cmd.errors.append(ErrReply(now, host if host in self.trace.hosts else "", text))
        except zenoh.ZError as exc:
            cmd.errors.append(ErrReply(time.time_ns(), "", f"query failed: {exc}"))
        cmd.done_ns = time.time_ns()
        return cmd

    def status(self, ref: str, timeout_s: float = 2.0) -> Status | None:
        """Drive ``host/axis``'s current status (a get on its status key), None without an answer."""
        host, _, axis = ref.partition("/")
        try:
            for rep in self.session.get(drive_key(host, axis, "status"), timeout=timeout_s):
                if rep.ok is not None and (d := unpack(rep.ok.payload.to_bytes())) is not None \
                        and d.get("type") == "drive_status":
                    return _status(time.time_ns(), d)
        except zenoh.ZError:
            pass
        return None

    def recording(self, host: str, last_s: float, timeout_s: float = 10.0) -> Recording | None:
        """The last ``last_s`` seconds of ``host``'s flight recorder, None when it did not answer."""
        payload = pack({"v": V, "type": "recording_request", "what": "last", "last_s": last_s})
        try:
            for rep in self.session.get(f"{ROOT}/{host}/agent/recording", payload=payload, timeout=timeout_s):
                if rep.ok is not None and (d := unpack(rep.ok.payload.to_bytes())) is not None \
                        and d.get("type") == "recording":
                    return Recording(time.time_ns(), d["host"], d["cycle_us"], d["n_cycles"], tuple(d.get("axes", ())),
                                     d.get("channels", {}))
        except zenoh.ZError:
            pass
        return None

    def sim(self, host: str, slave: int | str, action: str, timeout_s: float = 3.0, **args: Any) -> tuple[bool, str]:
        """A fault injection on ``drives/@sim/<host>/<slave>/<action>`` (the simulator segment is
        named after its host): (every reply ok, their texts)."""
        ok, texts = True, []
        try:
            for rep in self.session.get(f"drives/@sim/{host}/{slave}/{action}", payload=pack(args), timeout=timeout_s):
                if rep.ok is not None:
                    d = unpack(rep.ok.payload.to_bytes()) or {}
                    texts.append(str(d.get("detail", "")))
                elif rep.err is not None:
                    ok = False
                    d = unpack(rep.err.payload.to_bytes()) or {}
                    texts.append(str(d.get("error", "refused")))
        except zenoh.ZError as exc:
            return False, str(exc)
        return ok and bool(texts), "; ".join(texts) or "no simulator answered"


def malformed(flaw: str, request_id: str) -> tuple[str, bytes]:
    """A command broken by ``flaw`` (:data:`bench.chaos.schedule.FLAWS`): (the op of its key, its
    payload). Each is refused by the contract's codec (docs/contract.md)."""
    ok = request(request_id, "enable", timeout_s=2.0)
    if flaw == "not_msgpack":
        return "enable", b"\xc1\xc1 this is not msgpack"
    if flaw == "not_a_map":
        return "enable", pack([V, "command_request", request_id])
    if flaw == "missing_request_id":
        return "enable", pack({k: v for k, v in ok.items() if k != "request_id"})
    if flaw == "empty_request_id":
        return "enable", pack({**ok, "request_id": ""})
    if flaw == "op_mismatch":
        return "enable", pack({**ok, "op": "disable"})
    if flaw == "unknown_argument":
        return "enable", pack({**ok, "args": {"force": True}})
    if flaw == "mode_out_of_range":
        return "set_mode", pack(request(request_id, "set_mode", {"mode": 99}, 2.0))
    if flaw == "wrong_version":
        return "enable", pack({**ok, "v": V + 1})
    if flaw == "wrong_type":
        return "enable", pack({**ok, "timeout_s": "soon"})
    if flaw == "move_to_and_by":
        return "move", pack(request(request_id, "move", {"to": 1000.0, "by": 1000.0}, 2.0))
    if flaw == "negative_velocity":
        return "move", pack(request(request_id, "move", {"to": 1000.0, "velocity": -5.0}, 2.0))
    if flaw == "jog_without_velocity":
        return "jog", pack(request(request_id, "jog", {"for_s": 0.5}, 2.0))
    if flaw == "unknown_field":
        return "enable", pack({**ok, "priority": "high"})
    if flaw == "wrong_message_type":
        return "enable", pack({**ok, "type": "command_reply"})
    if flaw == "nan_timeout":
        return "enable", pack({**ok, "timeout_s": float("nan")})
    raise ValueError(f"unknown flaw {flaw!r}")
