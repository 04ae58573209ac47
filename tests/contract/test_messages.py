"""Messages and codec (schemas.messages): round trips, validation, and 'only SchemaError'."""

from __future__ import annotations

import dataclasses
import math
import re

import msgpack
import pytest
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

from schemas import messages as m
from schemas.messages import SchemaError

from .strategies import any_message, message, msgpack_values

PROPERTY = settings(max_examples=200, deadline=None, suppress_health_check=[HealthCheck.too_slow])


def drive_status(**kw):
    base = dict(host="h1", axis="x", seq=1, time_ns=2, cycle=3, state="fault", statusword=0x0218,
                controlword=0x0080, goal="disabled", halt=False, mode=8, mode_display=8, position=-5,
                velocity=0, torque=0, error_code=0x2310)
    base.update(kw)
    return m.DriveStatus(**base)


def agent_status(**kw):
    base = dict(host="h1", seq=0, time_ns=0, state="running", backend="sim", cycle_us=1000, cycles=9,
                period_p50_us=1000.0, period_p99_us=1010.5, period_max_us=1100.0, overruns=0,
                wkc_errors=0, expected_wkc=3, axes=["x", "y"], al_states={"x": "op", "y": "safeop"},
                leases={"x": "ops"}, groups={"g": ["h1/x", "h2/y"]})
    base.update(kw)
    return m.AgentStatus(**base)


EXAMPLES = [
    drive_status(),
    drive_status(error_text="Overcurrent", al_state="safeop", lost=True, lease_holder="ops", slave=3),
    agent_status(),
    agent_status(axes=[], al_states={}, leases={}, groups={}),
    m.Event(host="h1", axis="x", seq=4, time_ns=5, cycle=6, kind="transition",
            from_state="switched_on", to_state="operation_enabled", request_id="r1"),
    m.Event(host="h1", axis="x", seq=4, time_ns=5, cycle=6, kind="fault", error_code=0x7500, detail="ecat"),
    m.CommandRequest(request_id="r1", op="enable"),
    m.CommandRequest(request_id="r2", op="set_mode", args={"mode": 9}, timeout_s=2.5, supervisor="ops"),
    m.CommandRequest(request_id="r3", op="halt", args={"on": True}),
    m.CommandRequest(request_id="r4", op="lease", args={"holder": "ops", "ttl_s": 30.0, "takeover": True}),
    m.CommandRequest(request_id="r5", op="release", args={"holder": "ops"}),
    m.CommandRequest(request_id="r6", op="nmt", args={"command": "preop", "axis": "x"}),
    m.CommandReply(request_id="r1", host="h1", op="enable", outcome="done", axis="x",
                   state="operation_enabled", elapsed_s=0.012, cycles=12),
    m.CommandReply(request_id="r6", host="h1", op="nmt", outcome="busy", lease_holder="other"),
    m.RecordingRequest(),
    m.RecordingRequest(what="fault", last_s=2.5),
    m.Recording(host="h1", reason="fault", cycle_us=1000, first_cycle=7, n_cycles=2, time_origin_ns=5,
                axes=["x", "y"], channels={"cycle": [7, 8], "statusword": [0x0237, 0x0237, 0x0237, 0x0218]},
                axis="y", detail="error code 0x2310", trigger_cycle=8),
]


def test_recording_channels_hold_one_value_per_cycle_and_axis():
    with pytest.raises(SchemaError, match=r"recording.channels\['statusword'\]: 3 values, expected 4"):
        m.encode(m.Recording(host="h1", reason="last", cycle_us=1000, first_cycle=1, n_cycles=2, time_origin_ns=0,
                             axes=["x", "y"], channels={"statusword": [1, 2, 3]}))
    with pytest.raises(SchemaError, match=r"channels\['cycle'\]\[1\]: expected int"):
        m.encode(m.Recording(host="h1", reason="last", cycle_us=1000, first_cycle=1, n_cycles=2, time_origin_ns=0,
                             channels={"cycle": [1, "2"]}))
    with pytest.raises(SchemaError, match="unknown field"):
        m.decode(msgpack.packb({"v": 1, "type": "recording_request", "what": "last", "extra": 1}))


def test_examples_cover_every_message_type():
    assert {type(e) for e in EXAMPLES} == set(m.MESSAGE_TYPES)


@pytest.mark.parametrize("msg", EXAMPLES, ids=lambda e: type(e).__name__)
def test_round_trip_examples(msg):
    data = m.encode(msg)
    assert m.decode(data) == msg
    assert m.decode(data, type(msg)) == msg
    body = msgpack.unpackb(data, raw=False)
    assert body["v"] == m.SCHEMA_VERSION and body["type"] == msg.TYPE
    sparse = {n for n in getattr(msg, "SPARSE", ()) if getattr(msg, n) == ""}
    assert set(body) == {"v", "type"} | {f.name for f in dataclasses.fields(msg)} - sparse


def test_sparse_request_fields_go_on_the_wire_only_when_set():
    """A command_request without ``on_behalf_of`` is byte for byte what agents that predate the
    field accept (they refuse unknown fields); with it, the field is carried and decoded."""
    plain = m.CommandRequest("r1", "enable", {}, 5.0, "sup")
    body = msgpack.unpackb(m.encode(plain), raw=False)
    assert "on_behalf_of" not in body
    assert m.encode_new(m.CommandRequest, {"request_id": "r1", "op": "enable", "supervisor": "sup"})[1] == m.encode(plain)
    acting = dataclasses.replace(plain, on_behalf_of="alice")
    data = m.encode(acting)
    assert msgpack.unpackb(data, raw=False)["on_behalf_of"] == "alice"
    assert m.decode(data) == acting
    with pytest.raises(SchemaError, match="on_behalf_of"):
        m.encode(dataclasses.replace(plain, on_behalf_of="not a name"))


@given(any_message)
@PROPERTY
def test_round_trip_every_message_type(msg):
    back = m.decode(m.encode(msg))
    assert back == msg
    assert m.encode(back) == m.encode(msg)  # re-encoding is stable


@pytest.mark.parametrize("cls", m.MESSAGE_TYPES, ids=lambda c: c.__name__)
def test_round_trip_per_type_with_defaults(cls):
    @given(message(cls))
    @settings(max_examples=50, deadline=None)
    def run(msg):
        assert m.decode(m.encode(msg), cls) == msg

    run()


def test_defaults_fill_missing_optional_fields():
    body = {"v": 1, "type": "command_request", "request_id": "r", "op": "enable"}
    req = m.from_dict(body)
    assert req == m.CommandRequest(request_id="r", op="enable", args={}, timeout_s=5.0, supervisor="")


def test_decode_accepts_zbytes_like_objects():
    class ZB:
        def __init__(self, b):
            self.b = b

        def to_bytes(self):
            return self.b

    msg = EXAMPLES[0]
    assert m.decode(ZB(m.encode(msg))) == msg


def test_floats_accept_ints_and_normalise():
    msg = agent_status(period_p50_us=1000)
    back = m.decode(m.encode(msg))
    assert isinstance(back.period_p50_us, float) and back.period_p50_us == 1000.0


# ---- rejections name the field ---------------------------------------------------------------


def _body(msg, **changes):
    body = m.to_dict(msg)
    for k, v in changes.items():
        if v is KeyError:
            del body[k]
        else:
            body[k] = v
    return body


@pytest.mark.parametrize(
    "msg,changes,match",
    [
        (EXAMPLES[0], {"v": KeyError}, "v: missing"),
        (EXAMPLES[0], {"v": 2}, "v: schema version 2 is not supported"),
        (EXAMPLES[0], {"v": "1"}, "v: schema version must be an integer"),
        (EXAMPLES[0], {"v": True}, "v: schema version must be an integer"),
        (EXAMPLES[0], {"type": "nope"}, "type: 'nope' is not a message type"),
        (EXAMPLES[0], {"type": KeyError}, "type: None"),
        (EXAMPLES[6], {"extra": 1}, "unknown field"),
        (EXAMPLES[0], {"axis": KeyError}, "drive_status.axis: required field missing"),
        (EXAMPLES[0], {"statusword": 0x10000}, "drive_status.statusword: 65536 out of range"),
        (EXAMPLES[0], {"statusword": -1}, "drive_status.statusword"),
        (EXAMPLES[0], {"statusword": True}, "drive_status.statusword: expected int, got bool"),
        (EXAMPLES[0], {"statusword": 1.5}, "drive_status.statusword: expected int, got float"),
        (EXAMPLES[0], {"halt": 1}, "drive_status.halt: expected bool"),
        (EXAMPLES[0], {"state": "on"}, "drive_status.state: 'on' is not one of"),
        (EXAMPLES[0], {"host": "a/b"}, "drive_status.host: 'a/b' is not a legal name"),
        (EXAMPLES[0], {"host": ""}, "drive_status.host: '' is not a legal name"),
        (EXAMPLES[0], {"axis": "*"}, "drive_status.axis"),
        (EXAMPLES[0], {"lease_holder": "@sup"}, "drive_status.lease_holder"),
        (EXAMPLES[0], {"error_text": "x" * 201}, "drive_status.error_text: longer than 200"),
        (EXAMPLES[0], {"torque": 2**15}, "drive_status.torque"),
        (EXAMPLES[0], {"seq": 2**64}, "drive_status.seq"),
        (EXAMPLES[2], {"period_p50_us": float("nan")}, "agent_status.period_p50_us: must be a finite"),
        (EXAMPLES[2], {"period_p50_us": float("inf")}, "agent_status.period_p50_us: must be a finite"),
        (EXAMPLES[2], {"period_p50_us": 10**400}, "agent_status.period_p50_us: number too large"),
        (EXAMPLES[2], {"period_p50_us": "1"}, "agent_status.period_p50_us: expected number"),
        (EXAMPLES[2], {"axes": "x"}, "agent_status.axes: expected a list"),
        (EXAMPLES[2], {"axes": msgpack.ExtType(5, b"ab")}, "agent_status.axes: msgpack extension type 5"),
        (EXAMPLES[0], {"host": msgpack.Timestamp(1, 0)}, "drive_status.host: expected str, got Timestamp"),
        (EXAMPLES[2], {"axes": ["x", 3]}, r"agent_status.axes\[1\]: expected str"),
        (EXAMPLES[2], {"axes": ["x/y"]}, r"agent_status.axes\[0\]: 'x/y' is not a legal name"),
        (EXAMPLES[2], {"al_states": {"x": "running"}}, r"agent_status.al_states\['x'\]: 'running' is not one of"),
        (EXAMPLES[2], {"al_states": {"x*": "op"}}, "agent_status.al_states: key 'x\\*'"),
        (EXAMPLES[2], {"al_states": ["x"]}, "agent_status.al_states: expected a map"),
        (EXAMPLES[2], {"al_states": {1: "op"}}, "agent_status.al_states: expected a map with string keys"),
        (EXAMPLES[2], {"leases": {"x": ""}}, r"agent_status.leases\['x'\]"),
        (EXAMPLES[2], {"groups": {"g": "h1/x"}}, r"agent_status.groups\['g'\]: expected a list"),
        (EXAMPLES[2], {"groups": {"g": ["h1"]}}, r"agent_status.groups\['g'\]\[0\]: 'h1' is not 'host/axis'"),
        (EXAMPLES[2], {"groups": {"g": ["h1/x/y"]}}, r"agent_status.groups\['g'\]\[0\]"),
        (EXAMPLES[2], {"cycle_us": 0}, "agent_status.cycle_us: 0 out of range"),
        (EXAMPLES[4], {"kind": "Boom!"}, "event.kind"),
        (EXAMPLES[6], {"request_id": ""}, "command_request.request_id: shorter than 1"),
        (EXAMPLES[6], {"op": "setpoint"}, "command_request.op: 'setpoint' is not one of"),
        (EXAMPLES[6], {"timeout_s": -1.0}, "command_request.timeout_s"),
        (EXAMPLES[6], {"timeout_s": 3601}, "command_request.timeout_s"),
        (EXAMPLES[6], {"supervisor": "a b"}, "command_request.supervisor"),
        (EXAMPLES[6], {"args": [1]}, "command_request.args: expected a map"),
        (EXAMPLES[6], {"args": {"x": 1}}, "command_request.args: unknown argument.s. x for op enable .takes no arguments"),
        (EXAMPLES[6], {"args": {"x": b"\x00"}}, "command_request.args.x: bytes is not allowed"),
        (EXAMPLES[6], {"args": {"x": {"y": msgpack.ExtType(1, b"")}}}, "command_request.args.x.y: msgpack extension type 1"),
        (EXAMPLES[6], {"args": {"x": 2**64}}, "command_request.args.x: integer .* does not fit"),
        (EXAMPLES[6], {"args": {"x": [[[[[[[[[1]]]]]]]]]}}, "nested deeper"),
        (EXAMPLES[7], {"args": {}}, "command_request.args.mode: required for op set_mode"),
        (EXAMPLES[7], {"args": {"mode": 2}}, "command_request.args.mode: 2 is not one of"),
        (EXAMPLES[7], {"args": {"mode": "8"}}, "command_request.args.mode: expected int"),
        (EXAMPLES[8], {"args": {"on": 1}}, "command_request.args.on: expected bool"),
        (EXAMPLES[9], {"args": {"holder": "ops", "ttl_s": 0.05}}, "command_request.args.ttl_s: 0.05 out of range"),
        (EXAMPLES[9], {"args": {"holder": "ops", "ttl_s": 3601}}, "command_request.args.ttl_s"),
        (EXAMPLES[9], {"args": {"holder": "ops", "takeover": "yes"}}, "command_request.args.takeover: expected bool"),
        (EXAMPLES[9], {"args": {"ttl_s": 5}}, "command_request.args.holder: required"),
        (EXAMPLES[10], {"args": {"holder": ""}}, "command_request.args.holder: '' is not a legal name"),
        (EXAMPLES[11], {"args": {"command": "boot"}}, "command_request.args.command: 'boot' is not one of"),
        (EXAMPLES[11], {"args": {"command": "stop", "axis": "a/b"}}, "command_request.args.axis"),
        (EXAMPLES[11], {"args": {"command": "stop", "slave": 1}}, "unknown argument.s. slave for op nmt"),
        (EXAMPLES[12], {"outcome": "OK"}, "command_reply.outcome"),
        (EXAMPLES[12], {"error_code": 70000}, "command_reply.error_code"),
        (EXAMPLES[13], {"axis": "a b"}, "command_reply.axis"),
    ],
)
def test_from_dict_rejects_with_field_named(msg, changes, match):
    body = _body(msg, **changes)
    with pytest.raises(SchemaError, match=match):
        m.from_dict(body)
    try:
        data = msgpack.packb(body, use_bin_type=True)
    except (OverflowError, TypeError, ValueError):
        return  # not representable in msgpack: from_dict only
    with pytest.raises(SchemaError) as err:
        m.decode(data)
    # msgpack itself refuses non-string map keys (strict_map_key) before field validation.
    assert re.search(match, str(err.value)) or "int is not allowed for map key" in str(err.value)


def test_decode_rejects_wrong_expected_type():
    with pytest.raises(SchemaError, match="type: expected command_reply, got drive_status"):
        m.decode(m.encode(EXAMPLES[0]), m.CommandReply)


@pytest.mark.parametrize("data,match", [
    (b"", "not valid msgpack"), (b"\xc1", "not valid msgpack"), (msgpack.packb(1), "not a map"),
    (msgpack.packb([1]), "not a map"), (msgpack.packb({1: 2}, strict_types=False), "not valid msgpack"),
    (m.encode(EXAMPLES[0]) + b"\x00", "not valid msgpack"), (None, "not valid msgpack"), ("text", "not valid msgpack"),
])
def test_decode_rejects_garbage(data, match):
    with pytest.raises(SchemaError, match=match):
        m.decode(data)


def test_encode_validates_so_nothing_invalid_reaches_the_wire():
    with pytest.raises(SchemaError, match="drive_status.state"):
        m.encode(drive_status(state="enabled"))
    with pytest.raises(SchemaError, match="command_request.args.mode"):
        m.encode(m.CommandRequest(request_id="r", op="set_mode", args={"mode": 5}))
    with pytest.raises(SchemaError, match="not a message type"):
        m.encode(object())
    with pytest.raises(SchemaError, match="not a message type"):
        m.to_dict({"v": 1})


def test_validate_returns_the_message():
    assert m.validate(EXAMPLES[0]) is EXAMPLES[0]
    with pytest.raises(SchemaError):
        m.validate(drive_status(position=2**31))


# ---- validate_args ---------------------------------------------------------------------------


def test_validate_args_normalises_and_fills_defaults():
    assert m.validate_args("set_mode", {"mode": 8}) == {"mode": 8}
    assert m.validate_args("halt", {"on": False}) == {"on": False}
    assert m.validate_args("lease", {"holder": "ops"}) == {"holder": "ops", "ttl_s": m.LEASE_TTL_DEFAULT_S, "takeover": False}
    out = m.validate_args("lease", {"holder": "ops", "ttl_s": 2, "takeover": True})
    assert out == {"holder": "ops", "ttl_s": 2.0, "takeover": True} and isinstance(out["ttl_s"], float)
    assert m.validate_args("release", {"holder": "ops"}) == {"holder": "ops"}
    assert m.validate_args("nmt", {"command": "reset_node"}) == {"command": "reset_node"}
    assert m.validate_args("nmt", {"command": "start", "axis": "x"}) == {"command": "start", "axis": "x"}
    for op in ("enable", "switch_on", "shutdown", "disable", "quick_stop", "fault_reset"):
        assert m.validate_args(op, {}) == {}
        assert m.validate_args(op, None) == {}


@pytest.mark.parametrize("op,args,match", [
    ("bogus", {}, "op: 'bogus'"),
    ("enable", {"on": True}, "args: unknown argument.s. on for op enable"),
    ("set_mode", {}, "args.mode: required for op set_mode"),
    ("set_mode", {"mode": True}, "args.mode: expected int"),
    ("set_mode", {"mode": 0}, "args.mode: 0 is not one of"),
    ("halt", {"on": "true"}, "args.on: expected bool"),
    ("lease", {"holder": "o/p"}, "args.holder"),
    ("lease", {"holder": "ops", "ttl_s": 0}, "args.ttl_s: 0.0 out of range"),
    ("lease", {"holder": "ops", "ttl_s": float("nan")}, "args.ttl_s: must be a finite"),
    ("release", {}, "args.holder: required"),
    ("nmt", {"command": "START"}, "args.command"),
    ("nmt", {"axis": "x"}, "args.command: required"),
    ("set_mode", [("mode", 8)], "args: expected a map"),
    ("set_mode", {8: "mode"}, "args: expected a map"),
])
def test_validate_args_rejects_naming_the_field(op, args, match):
    with pytest.raises(SchemaError, match=match):
        m.validate_args(op, args)


def test_every_op_has_an_arg_rule_or_none_and_every_arg_is_documented():
    assert set(m.OP_ARGS) <= set(m.DRIVE_OPS + m.AGENT_OPS)
    for spec in m.OP_ARGS.values():
        for arg in spec.values():
            assert arg.meta.get("doc")


def test_every_field_is_documented():
    for cls in m.MESSAGE_TYPES:
        for f in dataclasses.fields(cls):
            assert f.metadata.get("doc"), f"{cls.__name__}.{f.name} has no doc"


# ---- decode of anything raises only SchemaError ------------------------------------------------


def _decode_only_schema_error(data) -> None:
    try:
        m.decode(data)
    except SchemaError as exc:
        assert "internal error" not in str(exc), str(exc)  # the safety net must never be needed


@given(st.binary(max_size=300))
@PROPERTY
def test_decode_random_bytes(data):
    _decode_only_schema_error(data)


@given(msgpack_values)
@PROPERTY
def test_decode_random_msgpack_structures(value):
    _decode_only_schema_error(msgpack.packb(value, use_bin_type=True))


FIELD_NAMES = sorted({f.name for c in m.MESSAGE_TYPES for f in dataclasses.fields(c)})


@given(st.sampled_from([c.TYPE for c in m.MESSAGE_TYPES]),
       st.dictionaries(st.sampled_from(FIELD_NAMES) | st.text(max_size=12), msgpack_values, max_size=12))
@PROPERTY
def test_decode_random_maps_with_valid_header(tname, body):
    body.update({"v": 1, "type": tname})
    _decode_only_schema_error(msgpack.packb(body, use_bin_type=True))


mutations = st.sampled_from(["drop", "set", "add", "flip_byte", "truncate", "insert_byte"])


@given(any_message, mutations, st.data())
@PROPERTY
def test_decode_mutated_valid_messages(msg, mutation, data):
    body = m.to_dict(msg)
    names = sorted(body)
    if mutation == "drop":
        del body[data.draw(st.sampled_from(names))]
        raw = msgpack.packb(body, use_bin_type=True)
    elif mutation == "set":
        body[data.draw(st.sampled_from(names))] = data.draw(msgpack_values)
        raw = msgpack.packb(body, use_bin_type=True)
    elif mutation == "add":
        body[data.draw(st.text(max_size=8))] = data.draw(msgpack_values)
        raw = msgpack.packb(body, use_bin_type=True)
    else:
        raw = bytearray(m.encode(msg))
        i = data.draw(st.integers(0, len(raw) - 1))
        if mutation == "flip_byte":
            raw[i] ^= data.draw(st.integers(1, 255))
        elif mutation == "truncate":
            raw = raw[:i]
        else:
            raw.insert(i, data.draw(st.integers(0, 255)))
        raw = bytes(raw)
    try:
        back = m.decode(raw)
    except SchemaError as exc:
        assert "internal error" not in str(exc), str(exc)
        return
    # Whatever decodes is a valid message that encodes again.
    assert type(back) in m.MESSAGE_TYPES
    assert m.decode(m.encode(back)) == back
    for f in dataclasses.fields(back):
        v = getattr(back, f.name)
        assert not (isinstance(v, float) and not math.isfinite(v))


def test_published_messages_ignore_unknown_fields_and_words():
    """The evolution rule (docs/contract.md): an older reader ignores a newer writer's optional
    fields and open-vocabulary words in published messages; commands stay strict."""
    body = m.to_dict(EXAMPLES[0]) | {"future_field": 12, "vendor_block": {"0x2205": 3}}
    assert m.from_dict(body) == EXAMPLES[0]
    ev = m.from_dict(m.to_dict(EXAMPLES[4]) | {"kind": "audit", "requester": "alice"})
    assert ev.kind == "audit"
    reply = m.from_dict(m.to_dict(EXAMPLES[12]) | {"outcome": "aborted"})
    assert reply.outcome == "aborted"
    with pytest.raises(SchemaError, match="unknown field"):
        m.from_dict(m.to_dict(EXAMPLES[6]) | {"principal": "bob"})


def test_drive_status_target_clamps_is_optional_both_ways():
    """``target_clamps`` (issue 23) evolves the contract as it allows: a status of an older agent
    (without it) decodes with 0, and a reader that does not know it ignores it (not strict)."""
    full = m.encode(drive_status(target_clamps=12))
    body = msgpack.unpackb(full, raw=False)
    assert m.decode(full).target_clamps == 12
    del body["target_clamps"]
    assert m.decode(msgpack.packb(body)).target_clamps == 0
    assert not m.DriveStatus.STRICT
