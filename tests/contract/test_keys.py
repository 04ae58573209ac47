"""Key space: builders, parser, selector chunks and user selectors (schemas.keys)."""

from __future__ import annotations

import fnmatch

import pytest
import zenoh
from hypothesis import given, settings
from hypothesis import strategies as st

from schemas import keys
from schemas.keys import InvalidKey, KeyKind, ParsedKey

NAME_CHARS = "abcXYZ019_.-"
names = st.text(alphabet="abcXYZ019_", min_size=1, max_size=1).flatmap(
    lambda first: st.text(alphabet=NAME_CHARS, max_size=20).map(lambda rest: first + rest)
)


def assert_zenoh_keyexpr(key: str) -> None:
    """zenoh accepts the key expression as written (canonical form, no autocanonize)."""
    assert str(zenoh.KeyExpr(key)) == key


# ---- names -------------------------------------------------------------------------------


@pytest.mark.parametrize("name", ["h1", "axis_0", "X", "a.b-c", "_x", "0", "a" * 64])
def test_legal_names(name):
    assert keys.validate_name(name) == name
    assert keys.is_name(name)


@pytest.mark.parametrize(
    "name",
    ["", "a/b", "*", "a*", "**", "@v1", "@x", "a$b", "a?", "a#", ".x", "-x", "a b", "a" * 65,
     "h1\n", "é", None, 3, b"h1"],
)
def test_illegal_names(name):
    with pytest.raises(InvalidKey, match="not a legal key chunk"):
        keys.validate_name(name, "host")
    assert not keys.is_name(name)


# ---- selector chunks ---------------------------------------------------------------------


@pytest.mark.parametrize(
    "chunk,zchunk",
    [("h1", "h1"), ("*", "*"), ("**", "**"), ("ax*", "ax$*"), ("h*", "h$*"), ("*x", "$*x"),
     ("a*b*c", "a$*b$*c"), ("ax$*", "ax$*"), ("$*", "*"), ("*.x", "$*.x"), ("a" * 64, "a" * 64)],
)
def test_selector_chunk_accepted_and_zenoh_spelling(chunk, zchunk):
    assert keys.validate_selector_chunk(chunk) == chunk
    assert keys.zenoh_chunk(chunk) == zchunk
    assert_zenoh_keyexpr(f"p/{zchunk}/q")


@pytest.mark.parametrize(
    "chunk,why",
    [("", "empty"), ("a/b", "'/'"), ("a?", "'?'"), ("?", "'?'"), ("a#", "'#'"), ("$", "'\\$'"),
     ("a$b", "'\\$'"), ("@v1", "verbatim"), ("@*", "verbatim"), ("a**", "'\\*\\*'"), ("**a", "'\\*\\*'"),
     ("a$**", "'\\*\\*'"), ("*$*", "adjacent"), (".x", "leading"), ("-x", "leading"), ("a b", "illegal"),
     ("a" * 65, "longer"), ("h1\n", "illegal"), (None, "string"), (1, "string")],
)
def test_selector_chunk_rejected(chunk, why):
    with pytest.raises(InvalidKey, match=why):
        keys.validate_selector_chunk(chunk, "host")
    with pytest.raises(InvalidKey):
        keys.zenoh_chunk(chunk)


# ---- builders ----------------------------------------------------------------------------


def test_builders_concrete():
    assert keys.agent_status("h1") == "drives/@v1/h1/agent"
    assert keys.agent_cmd("h1", "nmt") == "drives/@v1/h1/agent/cmd/nmt"
    assert keys.alive("h1") == "drives/@v1/h1/alive"
    assert keys.drive_status("h1", "x") == "drives/@v1/h1/drive/x/status"
    assert keys.drive_event("h1", "x") == "drives/@v1/h1/drive/x/event"
    assert keys.drive_cmd("h1", "x", "enable") == "drives/@v1/h1/drive/x/cmd/enable"
    assert keys.supervisor_alive("ops") == "drives/@v1/@sup/ops"
    assert keys.sim_control("seg0", 3, "fault") == "drives/@sim/seg0/3/fault"
    assert keys.sim_control("seg0", "*", "unplug") == "drives/@sim/seg0/*/unplug"


def test_builders_with_wildcards_are_valid_zenoh_keyexprs():
    built = [
        keys.agent_status("*"), keys.agent_cmd("h*", "nmt"), keys.alive("**"),
        keys.drive_status("h*", "ax*"), keys.drive_event("*", "*"), keys.drive_cmd("**", "x*1", "enable"),
        keys.drive_cmd("h1", "*", "*"), keys.supervisor_alive("*"), keys.sim_control("*", "*", "fault"),
        keys.ALL_DRIVE_STATUS, keys.ALL_DRIVE_EVENTS, keys.ALL_AGENT_STATUS, keys.ALL_ALIVE, keys.ALL_SUPERVISORS,
    ]
    for key in built:
        assert_zenoh_keyexpr(key)
    assert keys.drive_status("h*", "ax*") == "drives/@v1/h$*/drive/ax$*/status"


def test_wildcard_builders_select_the_right_concrete_keys():
    sel = zenoh.KeyExpr(keys.drive_cmd("h*", "ax*", "enable"))
    assert sel.intersects(zenoh.KeyExpr(keys.drive_cmd("h1", "axis1", "enable")))
    assert not sel.intersects(zenoh.KeyExpr(keys.drive_cmd("g1", "axis1", "enable")))
    assert not sel.intersects(zenoh.KeyExpr(keys.drive_cmd("h1", "axis1", "disable")))
    # '*' never matches the verbatim supervisor chunk, so agent selectors never see supervisors.
    assert not zenoh.KeyExpr(keys.ALL_ALIVE).intersects(zenoh.KeyExpr(keys.supervisor_alive("ops")))
    assert not zenoh.KeyExpr(keys.agent_status("**")).intersects(zenoh.KeyExpr("drives/@v2/h1/agent"))


@pytest.mark.parametrize(
    "call",
    [lambda: keys.agent_status("a/b"), lambda: keys.agent_cmd("h1", "nm?"), lambda: keys.alive("@x"),
     lambda: keys.drive_status("h1", ""), lambda: keys.drive_event("h1", "x#"),
     lambda: keys.drive_cmd("h1", "x", "$op"), lambda: keys.supervisor_alive("a b"),
     lambda: keys.sim_control("s", -1, "fault"), lambda: keys.sim_control("s", 70000, "fault"),
     lambda: keys.sim_control("s", True, "fault"), lambda: keys.sim_control("s/x", 0, "fault")],
)
def test_builders_reject_illegal_names(call):
    with pytest.raises(InvalidKey):
        call()


# ---- parser ------------------------------------------------------------------------------


@given(host=names, axis=names, op=names, sup=names)
@settings(max_examples=200, deadline=None)
def test_build_parse_round_trip(host, axis, op, sup):
    assert keys.parse(keys.agent_status(host)) == ParsedKey(KeyKind.AGENT_STATUS, host=host)
    assert keys.parse(keys.agent_cmd(host, op)) == ParsedKey(KeyKind.AGENT_CMD, host=host, op=op)
    assert keys.parse(keys.alive(host)) == ParsedKey(KeyKind.ALIVE, host=host)
    assert keys.parse(keys.agent_recording(host)) == ParsedKey(KeyKind.AGENT_RECORDING, host=host)
    assert keys.parse(keys.drive_status(host, axis)) == ParsedKey(KeyKind.DRIVE_STATUS, host=host, axis=axis)
    assert keys.parse(keys.drive_event(host, axis)) == ParsedKey(KeyKind.DRIVE_EVENT, host=host, axis=axis)
    assert keys.parse(keys.drive_cmd(host, axis, op)) == ParsedKey(KeyKind.DRIVE_CMD, host=host, axis=axis, op=op)
    assert keys.parse(keys.supervisor_alive(sup)) == ParsedKey(KeyKind.SUPERVISOR, name=sup)
    assert keys.parse_sim_control(keys.sim_control(host, 7, op)) == (host, 7, op)
    assert_zenoh_keyexpr(keys.drive_cmd(host, axis, op))


def test_parse_accepts_zenoh_keyexpr_objects():
    assert keys.parse(zenoh.KeyExpr("drives/@v1/h1/drive/x/status")).axis == "x"


@pytest.mark.parametrize(
    "key",
    ["", "drives", "drives/@v1", "drives/@v2/h1/agent", "other/@v1/h1/agent", "drives/@v1/h1",
     "drives/@v1/h1/agent/cmd", "drives/@v1/h1/agent/cmd/nmt/x", "drives/@v1/h1/drive/x",
     "drives/@v1/h1/drive/x/statu", "drives/@v1/h1/drive/x/cmd", "drives/@v1/h1/drive/x/cmd/a/b",
     "drives/@v1/*/agent", "drives/@v1/h$*/agent", "drives/@v1/h1/drive/*/status",
     "drives/@v1/h1/drive/x/cmd/*", "drives/@v1/@sup", "drives/@v1/@sup/*", "drives/@v1/@sup/a/b",
     "drives/@v1/@other/agent", "drives/@v1//agent", "drives/@v1/h1/alive/"],
)
def test_parse_rejects(key):
    with pytest.raises(InvalidKey):
        keys.parse(key)


@pytest.mark.parametrize("key", ["drives/@sim/s/x/fault", "drives/@sim/s/-1/fault", "drives/@sim/s/1",
                                 "drives/@sim/*/1/fault", "drives/@v1/s/1/fault", "drives/@sim/s/99999/fault"])
def test_parse_sim_control_rejects(key):
    with pytest.raises(InvalidKey):
        keys.parse_sim_control(key)


def test_key_table_covers_every_kind():
    kinds = {k.kind for k in keys.KEY_TABLE}
    assert {k.value for k in KeyKind} <= kinds


# ---- user selectors ------------------------------------------------------------------------


@pytest.mark.parametrize(
    "selector,expected",
    [("h1/x", ("h1", "x")), ("h1/*", ("h1", "*")), ("*/x", ("*", "x")), ("*/*", ("*", "*")),
     ("**/x", ("*", "x")), ("h*/axis?", ("h$*", "axis$*")), ("h?/?", ("h$*", "*")),
     ("h[12]/ax[!0]", ("h$*", "ax$*")), ("h*?/a", ("h$*", "a")), ("h$*/a", ("h$*", "a")),
     ("h1/a*b?c", ("h1", "a$*b$*c")), ("[ab]*/x", ("*", "x")), ("h1", ("h1", "*")), ("**", ("*", "*")),
     ("h?", ("h$*", "*"))],
)
def test_selector_to_keyexpr(selector, expected):
    h, a = keys.selector_to_keyexpr(selector)
    assert (h, a) == expected
    for op in ("enable", "*"):
        key = keys.drive_cmd(h, a, op)  # the chunks are accepted by every builder, unchanged
        assert key == f"drives/@v1/{h}/drive/{a}/cmd/{op}"
        assert_zenoh_keyexpr(key)


@pytest.mark.parametrize(
    "selector,why",
    [("h1/x/y", "at most one '/'"), ("", "at most one '/'"), ("@x", "verbatim"), ("/x", "host is empty"),
     ("h1/", "axis is empty"), ("@sup/x", "verbatim"), ("h1/@x", "verbatim"), ("h#/x", "illegal character"),
     ("h$/x", "illegal character"), ("h 1/x", "illegal character"), ("h[/x", "illegal character"),
     ("h[a/]x", "illegal character"), ("h[*]/x", "character class"), (".h/x", "starts with"),
     ("h/-x", "starts with"), (None, "string"), ("h/" + "a" * 65, "longer")],
)
def test_selector_rejected(selector, why):
    with pytest.raises(InvalidKey, match=why):
        keys.selector_to_keyexpr(selector)
    with pytest.raises(InvalidKey):
        keys.selector_matches(selector, "h1", "x")


@pytest.mark.parametrize(
    "selector,host,axis,hit",
    [("h1/x", "h1", "x", True), ("h1/x", "h1", "y", False), ("h1/*", "h1", "anything", True),
     ("*/x", "h9", "x", True), ("h*/axis?", "h2", "axis1", True), ("h*/axis?", "h2", "axis12", False),
     ("h*/axis?", "h2", "axis", False), ("h[12]/x", "h3", "x", False), ("h[!12]/x", "h3", "x", True),
     ("H1/x", "h1", "x", False), ("**/*", "h1", "x", True), ("h1/x", "h1", 5, False),
     ("h1", "h1", "x", True), ("h1", "h10", "x", False), ("**", "h7", "y", True)],
)
def test_selector_matches(selector, host, axis, hit):
    assert keys.selector_matches(selector, host, axis) is hit


sel_chunks = st.lists(st.sampled_from(["a", "b", "1", "_", ".", "*", "?", "[ab]", "[!a]"]), min_size=1, max_size=6)


@given(hparts=sel_chunks, aparts=sel_chunks, host=st.text("ab1_.", min_size=1, max_size=6),
       axis=st.text("ab1_.", min_size=1, max_size=6))
@settings(max_examples=300, deadline=None)
def test_zenoh_query_never_misses_a_selected_drive(hparts, aparts, host, axis):
    """The widened zenoh key expression includes every drive the fnmatch selector selects."""
    hsel, asel = "".join(hparts), "".join(aparts)
    selector = f"{hsel}/{asel}"
    try:
        h, a = keys.selector_to_keyexpr(selector)
    except InvalidKey:
        assert hsel[0] in ".-" or asel[0] in ".-"
        return
    if not (keys.is_name(host) and keys.is_name(axis)):
        return
    hit = keys.selector_matches(selector, host, axis)
    assert hit == (fnmatch.fnmatchcase(host, hsel) and fnmatch.fnmatchcase(axis, asel))
    if hit:
        assert zenoh.KeyExpr(keys.drive_status(h, a)).intersects(zenoh.KeyExpr(keys.drive_status(host, axis)))
