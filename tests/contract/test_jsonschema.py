"""JSON Schema export (schemas.jsonschema): the real validator accepts exactly what the codec accepts.

The validator is the ``jsonschema`` package (a pinned test dependency), draft 2020-12, as a
dashboard in another language would apply the exported files. The schemas describe the JSON form
of a message; a map with no JSON form (NaN, infinities, bytes) is the codec's alone to reject.
"""

from __future__ import annotations

import json
import math

import jsonschema
import msgpack
import pytest
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

from schemas import jsonschema as js
from schemas import messages as m
from schemas.messages import SchemaError

from .strategies import any_message, msgpack_values
from .test_messages import EXAMPLES

SCHEMAS = js.all_schemas()
VALIDATORS = {name: jsonschema.Draft202012Validator(s) for name, s in SCHEMAS.items()}


def json_form(body):
    """``body`` as a JSON document would carry it, or None if it has no JSON form."""
    try:
        return json.loads(json.dumps(body, allow_nan=False))
    except (TypeError, ValueError):
        return None


def is_valid(type_name: str, body) -> bool:
    """The real validator's verdict on the JSON form of ``body`` (which must have one)."""
    doc = json_form(body)
    assert doc is not None, f"{body!r} has no JSON form"
    return VALIDATORS[type_name].is_valid(doc)


def test_schemas_are_valid_draft_2020_12():
    for schema in SCHEMAS.values():
        jsonschema.Draft202012Validator.check_schema(schema)


def test_one_schema_per_message_with_header():
    assert set(SCHEMAS) == {c.TYPE for c in m.MESSAGE_TYPES}
    for cls in m.MESSAGE_TYPES:
        s = SCHEMAS[cls.TYPE]
        assert s["$schema"] == "https://json-schema.org/draft/2020-12/schema"
        assert s["properties"]["v"] == {"description": "schema version", "type": "integer", "const": m.SCHEMA_VERSION}
        assert s["properties"]["type"]["const"] == cls.TYPE
        assert s["additionalProperties"] is (not cls.STRICT)
        assert s["required"][:2] == ["v", "type"]
        json.dumps(s)  # JSON-serialisable


def test_field_metadata_maps_to_keywords():
    ds = SCHEMAS["drive_status"]["properties"]
    assert ds["statusword"] == {"description": "0x6041", "type": "integer", "minimum": 0, "maximum": 0xFFFF}
    assert ds["state"]["enum"] == list(m.DRIVE_STATES)
    assert ds["error_text"]["maxLength"] == 200 and ds["error_text"]["default"] == ""
    assert ds["host"]["pattern"] == js.NAME_PATTERN
    assert ds["lease_holder"]["pattern"] == js.NAME_OR_EMPTY_PATTERN
    assert "host" in SCHEMAS["drive_status"]["required"] and "lost" not in SCHEMAS["drive_status"]["required"]
    ag = SCHEMAS["agent_status"]["properties"]
    assert ag["axes"]["items"]["pattern"] == js.NAME_PATTERN
    assert ag["al_states"]["additionalProperties"]["enum"] == list(m.AL_STATES)
    assert ag["groups"]["additionalProperties"]["items"]["pattern"] == js.MEMBER_PATTERN
    req = SCHEMAS["command_request"]
    assert req["properties"]["timeout_s"]["maximum"] == 3600.0
    rule = next(r for r in req["allOf"] if r["if"]["properties"]["op"]["const"] == "set_mode")
    assert rule["then"]["properties"]["args"]["properties"]["mode"]["enum"] == list(m.MODES)
    assert rule["then"]["required"] == ["args"]


@pytest.mark.parametrize("msg", EXAMPLES, ids=lambda e: type(e).__name__)
def test_schema_validates_encoded_examples(msg):
    body = msgpack.unpackb(m.encode(msg), raw=False)
    assert is_valid(msg.TYPE, body)


@given(any_message)
@settings(max_examples=200, deadline=None)
def test_schema_validates_every_encoded_message(msg):
    assert is_valid(msg.TYPE, msgpack.unpackb(m.encode(msg), raw=False))


REQ = {"v": 1, "type": "command_request", "request_id": "r"}


def _example(i: int, **changes) -> dict:
    return dict(msgpack.unpackb(m.encode(EXAMPLES[i])), **changes)


@pytest.mark.parametrize("type_name,body", [
    ("drive_status", {"v": 1, "type": "drive_status"}),
    ("command_request", dict(REQ, op="set_mode")),
    ("command_request", dict(REQ, op="enable", args={"a": 1})),
    ("command_request", dict(REQ, request_id="", op="enable")),
    ("command_request", dict(REQ, op="enable", extra=1)),
    ("agent_status", _example(2, axes=["a\n"])),
    ("agent_status", _example(2, groups={"g": ["h1/x\n"]})),
    ("drive_status", _example(0, lease_holder="ops\n")),
    ("event", _example(4, kind="fault\n")),
    ("event", _example(4, kind="Fault")),
    ("agent_status", _example(2, v=2)),
    ("agent_status", _example(2, v=1.5)),
    ("drive_status", _example(0, mode=8.5)),
    ("drive_status", _example(0, statusword=True)),
    ("command_request", dict(REQ, op="set_mode", args={"mode": 8.5})),
    ("command_request", dict(REQ, op="set_mode", args={"mode": 2.0})),
    ("command_request", dict(REQ, op="halt", args={"on": 1})),
    ("command_request", dict(REQ, op="nmt", args={"command": "stop", "axis": ""})),
])
def test_schema_rejects_what_the_codec_rejects(type_name, body):
    with pytest.raises(SchemaError):
        m.from_dict(body)
    assert not is_valid(type_name, body)


@pytest.mark.parametrize("type_name,body,field,value", [
    # JSON has one number type: 8.0 is the integer 8 to a validator and to the codec alike
    ("agent_status", _example(2, v=1.0), "cycle_us", 1000),
    ("drive_status", _example(0, mode=8.0), "mode", 8),
    ("drive_status", _example(0, seq=2.0**63), "seq", 2**63),
    ("command_request", dict(REQ, op="set_mode", args={"mode": 8.0}), "args", {"mode": 8.0}),
    # readers of published messages ignore unknown fields and take new words in open vocabularies
    ("drive_status", _example(0, torque_limit=5), "torque", EXAMPLES[0].torque),
    ("event", _example(4, kind="homing_done"), "kind", "homing_done"),
    ("command_reply", _example(12, outcome="aborted"), "outcome", "aborted"),
])
def test_schema_accepts_what_the_codec_accepts(type_name, body, field, value):
    msg = m.from_dict(body)
    assert getattr(msg, field) == value and type(getattr(msg, field)) is type(value)
    assert is_valid(type_name, body)


def test_codec_normalises_integral_floats_to_int():
    assert m.validate_args("set_mode", {"mode": 8.0}) == {"mode": 8}
    assert type(m.validate_args("set_mode", {"mode": 8.0})["mode"]) is int
    msg = m.from_dict(_example(0, statusword=0x237 * 1.0))
    assert msg.statusword == 0x237 and type(msg.statusword) is int
    assert m.decode(m.encode(msg)) == msg


mutated_field = st.one_of(msgpack_values, st.sampled_from(
    ["", "x", "a/b", "h1/x", "op", "fault", "x\n", "new_word", -1, 2**16, 0.5, 8.0, 1.0, 1.5, math.inf]))


@given(any_message, st.data())
@settings(max_examples=200, deadline=None, suppress_health_check=[HealthCheck.too_slow])
def test_schema_and_codec_agree_on_mutated_messages(msg, data):
    """For any one-field mutation with a JSON form, the codec accepts the map exactly when the
    real validator does; without a JSON form the codec rejects it unless the value sits in a
    field a reader ignores."""
    body = msgpack.unpackb(m.encode(msg), raw=False)
    action = data.draw(st.sampled_from(["set", "drop", "add", "args"]))
    if action == "set":
        body[data.draw(st.sampled_from(sorted(body)))] = data.draw(mutated_field)
    elif action == "drop":
        del body[data.draw(st.sampled_from(sorted(body)))]
    elif action == "add":
        body[data.draw(st.text(max_size=6))] = data.draw(mutated_field)
    elif "args" in body:
        body["args"] = data.draw(st.dictionaries(
            st.sampled_from(["mode", "on", "holder", "ttl_s", "takeover", "command", "axis", "x"]),
            mutated_field | st.sampled_from([8, 9, True, False, "ops", 10.0, 0.01, "start", "bad"]), max_size=3))
    # only what msgpack can carry: round-trip the mutated map through the wire
    try:
        body = msgpack.unpackb(msgpack.packb(body, use_bin_type=True), raw=False)
    except Exception:
        return
    try:
        m.from_dict(body)
        codec_ok = True
    except SchemaError:
        codec_ok = False
    tname = body.get("type") if isinstance(body.get("type"), str) else None
    doc = json_form(body)
    if doc is None:
        cls = m._BY_TYPE.get(tname) if tname else None
        ignored = cls is not None and not cls.STRICT and any(
            json_form(v) is None for k, v in body.items() if k not in m._plan(cls)[0])
        assert not codec_ok or ignored, f"codec accepted {body!r}, which has no JSON form"
        return
    schema_ok = tname in VALIDATORS and VALIDATORS[tname].is_valid(doc)
    if codec_ok != schema_ok:
        raise AssertionError(f"codec={codec_ok} schema={schema_ok} for {body!r}")


def test_write_schemas(tmp_path):
    paths = js.write_schemas(tmp_path / "out")
    assert sorted(p.name for p in paths) == sorted(f"{c.TYPE}.schema.json" for c in m.MESSAGE_TYPES)
    for p in paths:
        assert json.loads(p.read_text()) == SCHEMAS[p.name.removesuffix(".schema.json")]
