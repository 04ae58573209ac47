"""JSON Schema export (schemas.jsonschema): the schemas accept what the codec accepts."""

from __future__ import annotations

import json

import msgpack
import pytest
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

from schemas import jsonschema as js
from schemas import messages as m
from schemas.messages import SchemaError

from . import mini_jsonschema
from .strategies import any_message, msgpack_values
from .test_messages import EXAMPLES

try:  # the real validator when it happens to be installed; never a dependency
    import jsonschema as _jsonschema_pkg
except ImportError:  # pragma: no cover - depends on the environment
    _jsonschema_pkg = None

SCHEMAS = js.all_schemas()


def is_valid(schema: dict, value) -> bool:
    ok = mini_jsonschema.is_valid(schema, value)
    if _jsonschema_pkg is not None and all(
        not (isinstance(x, float) and x != x) for x in _walk(value)
    ):
        real = _jsonschema_pkg.Draft202012Validator(schema).is_valid(value)
        assert real == ok, f"mini checker ({ok}) disagrees with jsonschema ({real}) on {value!r}"
    return ok


def _walk(v):
    yield v
    if isinstance(v, dict):
        for x in v.values():
            yield from _walk(x)
    elif isinstance(v, list):
        for x in v:
            yield from _walk(x)


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
    assert is_valid(SCHEMAS[msg.TYPE], body)


@given(any_message)
@settings(max_examples=200, deadline=None)
def test_schema_validates_every_encoded_message(msg):
    assert is_valid(SCHEMAS[msg.TYPE], msgpack.unpackb(m.encode(msg), raw=False))


@pytest.mark.parametrize("type_name,body", [
    ("drive_status", {"v": 1, "type": "drive_status"}),
    ("command_request", {"v": 1, "type": "command_request", "request_id": "r", "op": "set_mode"}),
    ("command_request", {"v": 1, "type": "command_request", "request_id": "r", "op": "enable", "args": {"a": 1}}),
    ("command_request", {"v": 1, "type": "command_request", "request_id": "", "op": "enable"}),
    ("agent_status", dict(msgpack.unpackb(m.encode(EXAMPLES[2])), axes=["a\n"])),
    ("agent_status", dict(msgpack.unpackb(m.encode(EXAMPLES[2])), v=2)),
    ("agent_status", dict(msgpack.unpackb(m.encode(EXAMPLES[2])), v=1.0)),
    ("drive_status", dict(msgpack.unpackb(m.encode(EXAMPLES[0])), mode=8.0)),
    ("command_request", {"v": 1, "type": "command_request", "request_id": "r", "op": "set_mode", "args": {"mode": 8.0}}),
    ("command_request", {"v": 1, "type": "command_request", "request_id": "r", "op": "halt", "args": {"on": 1}}),
    ("command_request", {"v": 1, "type": "command_request", "request_id": "r", "op": "nmt", "args": {"command": "stop", "axis": ""}}),
])
def test_schema_rejects_what_the_codec_rejects(type_name, body):
    with pytest.raises(SchemaError):
        m.from_dict(body)
    assert not is_valid(SCHEMAS[type_name], body)


mutated_field = st.one_of(msgpack_values, st.sampled_from(["", "x", "a/b", "h1/x", "op", "fault", -1, 2**16, 0.5]))


@given(any_message, st.data())
@settings(max_examples=200, deadline=None, suppress_health_check=[HealthCheck.too_slow])
def test_schema_and_codec_agree_on_mutated_messages(msg, data):
    """For any one-field mutation, the codec accepts the map exactly when the schema does."""
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
    schema = SCHEMAS.get(tname) if tname else None
    schema_ok = schema is not None and is_valid(schema, body)
    # bytes have no JSON form: the schema cannot reject them by type, the codec does
    if codec_ok != schema_ok:
        raise AssertionError(f"codec={codec_ok} schema={schema_ok} for {body!r}")


def test_write_schemas(tmp_path):
    paths = js.write_schemas(tmp_path / "out")
    assert sorted(p.name for p in paths) == sorted(f"{c.TYPE}.schema.json" for c in m.MESSAGE_TYPES)
    for p in paths:
        assert json.loads(p.read_text()) == SCHEMAS[p.name.removesuffix(".schema.json")]
