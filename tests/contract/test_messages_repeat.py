"""The codec's memory of accepted values (issue 13's fast path) changes cost, never answers.

``schemas.messages`` remembers, per message field, the strings its full check accepted and takes
values of exactly the field's scalar type inside its range and choices without the full check.
These tests warm that memory with valid values first and then check that every invalid value is
still refused with the same text as on a cold codec, and that nothing learnt for one field
passes for another.
"""

from __future__ import annotations

import math

import pytest

from schemas import compiled
from schemas import messages as m

VALID = dict(request_id="r-1", host="h1", op="enable", outcome="done", axis="x1", state="operation_enabled",
             error_code=0, elapsed_s=0.007, cycles=7)


def _warm() -> None:
    for _ in range(3):
        m.decode(m.encode(m.CommandReply(**VALID)), m.CommandReply)


def _error(body: dict) -> str:
    with pytest.raises(m.SchemaError) as exc:
        m.from_dict({"v": m.SCHEMA_VERSION, "type": "command_reply", **body}, m.CommandReply)
    return str(exc.value)


@pytest.mark.parametrize("field, bad", [
    ("op", "operation_enabled"),       # accepted as a state, not an op
    ("state", "enable"),               # accepted as an op, not a state
    ("host", "h1/x1"),                 # not a name
    ("axis", ""),                      # allowed empty only where the field says so: axis may be ''
    ("error_code", True),              # bool is not an int
    ("error_code", 0x10000),           # out of range
    ("error_code", -1),
    ("cycles", 7.5),                   # not integral
    ("elapsed_s", math.nan),
    ("elapsed_s", math.inf),
    ("elapsed_s", "0.1"),
    ("request_id", "x" * 129),         # too long
    ("state", 3),
])
def test_invalid_values_are_refused_the_same_after_valid_ones_were_learnt(field: str, bad: object) -> None:
    body = {**VALID, field: bad}
    if field == "axis":  # '' is legal for axis (agent commands): the memory must keep it legal
        _warm()
        assert m.from_dict({"v": m.SCHEMA_VERSION, "type": "command_reply", **body}, m.CommandReply).axis == ""
        return
    cold = _error(body)
    _warm()
    assert _error(body) == cold


def test_repeats_encode_to_the_same_bytes_and_normalise_the_same() -> None:
    first = m.encode(m.CommandReply(**VALID))
    assert all(m.encode(m.CommandReply(**VALID)) == first for _ in range(5))
    # an int for a float field is still normalised to float; 8.0 for an int field to int
    msg = m.from_dict({"v": m.SCHEMA_VERSION, "type": "command_reply", **VALID, "elapsed_s": 1, "cycles": 8.0})
    assert type(msg.elapsed_s) is float and msg.elapsed_s == 1.0
    assert type(msg.cycles) is int and msg.cycles == 8


def test_the_memory_is_bounded_and_stays_correct_when_it_overflows() -> None:
    n = m._SEEN_MAX * 2 + 3
    for i in range(n):
        assert m.decode(m.encode(m.CommandReply(**{**VALID, "host": f"h-{i}"})), m.CommandReply).host == f"h-{i}"
    m._plan(m.CommandReply)
    assert 0 < len(compiled.SEEN["command_reply"]["host"]) <= m._SEEN_MAX
    assert "not a legal name" in _error({**VALID, "host": "h/1"})
    assert "longer than 128" in _error({**VALID, "request_id": "y" * 129})


def test_strict_commands_still_refuse_unknown_fields_after_warm_up() -> None:
    req = m.CommandRequest(request_id="r", op="enable")
    for _ in range(3):
        m.decode(m.encode(req), m.CommandRequest)
    with pytest.raises(m.SchemaError, match="unknown field"):
        m.from_dict({**m.to_dict(req), "extra": 1}, m.CommandRequest)


def test_encode_new_gives_what_the_constructor_and_encode_give() -> None:
    from tests.contract.test_messages import EXAMPLES
    for msg in EXAMPLES:
        cls = type(msg)
        fields = {f: getattr(msg, f) for f in m._plan(cls)[0] - {"v", "type"}}
        built, payload = m.encode_new(cls, fields)
        assert built == msg and payload == m.encode(msg)
        assert m.decode(payload, cls) == msg and m.decode(payload, cls).__dict__ == msg.__dict__


def test_encode_new_refuses_by_name_and_builds_nothing() -> None:
    with pytest.raises(m.SchemaError, match=r"command_reply\.error_code: 65536 out of range"):
        m.encode_new(m.CommandReply, {**VALID, "error_code": 0x10000})
    with pytest.raises(m.SchemaError, match=r"command_reply\.host: required field missing"):
        m.encode_new(m.CommandReply, {k: v for k, v in VALID.items() if k != "host"})
    with pytest.raises(m.SchemaError, match="unknown field.*'colour'"):
        m.encode_new(m.CommandReply, {**VALID, "colour": "red"})
    with pytest.raises(m.SchemaError, match="not a message type"):
        m.encode_new(dict, {})
