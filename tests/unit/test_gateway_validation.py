"""Command validation of the gateway (bus_agent.gateway.gateway.parse_command): pure, no session."""

from __future__ import annotations

import msgpack
import pytest

from bus_agent.gateway.gateway import RequestError, axes_in_key, parse_command
from schemas import keys
from schemas import messages as m

HOST = "h1"
AXES = ("x1", "x2", "y1")


def req(op="enable", **kw):
    body = {"v": m.SCHEMA_VERSION, "type": "command_request", "request_id": "r1", "op": op}
    body.update(kw)
    return msgpack.packb(body)


def key(axis="x1", op="enable"):
    return keys.drive_cmd(HOST, axis, op)


def test_valid_enable_addresses_one_axis():
    p = parse_command(req(), key(), HOST, AXES)
    assert p.axes == ("x1",)
    assert p.request.op == "enable" and p.args == {}


@pytest.mark.parametrize("query_key, expected", [
    (keys.drive_cmd(HOST, "*", "enable"), ("x1", "x2", "y1")),
    (keys.drive_cmd("*", "*", "enable"), ("x1", "x2", "y1")),
    (keys.drive_cmd(HOST, "x*", "enable"), ("x1", "x2")),
    (keys.drive_cmd(HOST, "x2", "*"), ("x2",)),
    ("drives/@v1/**", ("x1", "x2", "y1")),
])
def test_fan_out_selectors(query_key, expected):
    assert parse_command(req(), query_key, HOST, AXES).axes == expected


def test_selector_for_other_drives_addresses_none():
    assert axes_in_key(keys.drive_cmd(HOST, "z9", "enable"), HOST, AXES) == ()
    assert axes_in_key(keys.drive_cmd("h2", "*", "enable"), HOST, AXES) == ()


@pytest.mark.parametrize("payload, words", [
    (None, "no payload"),
    (b"\xc1\xff\x00garbage", "not valid msgpack"),
    (msgpack.packb([1, 2, 3]), "not a map"),
    (req(v=2), "schema version 2"),
    (msgpack.packb({"v": 1, "type": "command_request", "op": "enable"}), "request_id"),
    (msgpack.packb({"v": 1, "type": "command_request", "request_id": "r"}), "op"),
    (req(op="jump"), "'jump'"),
    (req(op="set_mode", args={"mode": 5}), "mode"),
    (req(op="set_mode", args={}), "mode"),
    (req(op="set_mode", args={"mode": True}), "mode"),
    (req(op="halt", args={}), "on"),
    (req(args={"force": True}), "force"),
    (req(timeout_s=-1.0), "timeout_s"),
    (req(request_id=""), "request_id"),
    (req(surprise=1), "surprise"),
    (msgpack.packb({"v": 1, "type": "drive_status"}), "expected command_request"),
])
def test_malformed_payloads_name_the_problem(payload, words):
    with pytest.raises(RequestError) as e:
        parse_command(payload, key(op="set_mode" if b"set_mode" in (payload or b"") else "enable"), HOST, AXES)
    assert words in str(e.value)


def test_op_must_match_the_key():
    with pytest.raises(RequestError, match="does not match the key"):
        parse_command(req(op="disable"), key(op="enable"), HOST, AXES)


def test_unknown_op_in_key_and_payload():
    with pytest.raises(RequestError, match="jump"):
        parse_command(req(op="jump"), key(op="jump"), HOST, AXES)


def test_agent_op_on_drive_key_and_drive_op_on_agent_key():
    with pytest.raises(RequestError, match="not a drive op"):
        parse_command(req(op="nmt", args={"command": "start"}), key(op="nmt"), HOST, AXES)
    with pytest.raises(RequestError, match="not an agent op"):
        parse_command(req(op="enable"), keys.agent_cmd(HOST, "enable"), HOST, AXES, agent=True)


def test_agent_nmt():
    p = parse_command(req(op="nmt", args={"command": "preop", "axis": "x2"}), keys.agent_cmd(HOST, "nmt"), HOST,
                      AXES, agent=True)
    assert p.axes == () and p.args == {"command": "preop", "axis": "x2"}
    with pytest.raises(RequestError, match="not an axis of h1"):
        parse_command(req(op="nmt", args={"command": "preop", "axis": "zz"}), keys.agent_cmd(HOST, "nmt"), HOST,
                      AXES, agent=True)
    with pytest.raises(RequestError, match="command"):
        parse_command(req(op="nmt", args={"command": "explode"}), keys.agent_cmd(HOST, "nmt"), HOST, AXES,
                      agent=True)


def test_lease_args_defaults_and_holder_identity():
    p = parse_command(req(op="lease", args={"holder": "supA"}, supervisor="supA"), key(op="lease"), HOST, AXES)
    assert p.args == {"holder": "supA", "ttl_s": m.LEASE_TTL_DEFAULT_S, "takeover": False}
    with pytest.raises(RequestError, match="differs from supervisor"):
        parse_command(req(op="lease", args={"holder": "supA"}, supervisor="supB"), key(op="lease"), HOST, AXES)
    with pytest.raises(RequestError, match="ttl_s"):
        parse_command(req(op="lease", args={"holder": "supA", "ttl_s": 0.0}), key(op="lease"), HOST, AXES)
    with pytest.raises(RequestError, match="holder"):
        parse_command(req(op="release", args={}), key(op="release"), HOST, AXES)


def test_group_move_names_its_axes_on_a_host_wide_key():
    """A synchronized move of part of a host's axes: one ``drive/*`` query, the args name the
    axes (``targets`` absolute per axis, or ``axes`` with to/by); the agent takes exactly those."""
    wide = key("*", "move")
    p = parse_command(req("move", args={"by": 5.0, "sync": True, "axes": ["x1", "y1"]}), wide, HOST, AXES)
    assert p.axes == ("x1", "y1")
    p = parse_command(req("move", args={"targets": {"x2": 1.0}, "sync": True}), wide, HOST, AXES)
    assert p.axes == ("x2",)
    for args, words in (({"by": 5.0, "axes": ["x1"]}, "needs sync true"),
                        ({"to": 1.0, "sync": True, "axes": []}, "empty"),
                        ({"to": 1.0, "sync": True, "axes": ["x1", "z9"]}, "z9 not addressed"),
                        ({"sync": True, "axes": ["x1"], "targets": {"x1": 1.0}}, "not both")):
        with pytest.raises(RequestError, match=words):
            parse_command(req("move", args=args), wide, HOST, AXES)
    with pytest.raises(RequestError, match="x2 not addressed"):
        parse_command(req("move", args={"by": 1.0, "sync": True, "axes": ["x1", "x2"]}), key("x1", "move"), HOST, AXES)
