"""The expected-fleet file (supervisor/fleetfile.py): pure parsing and its errors."""

import pytest

from supervisor.fleetfile import FleetFileError, load, parse


def test_hosts_axes_groups_from_toml(tmp_path):
    p = tmp_path / "fleet.toml"
    p.write_text('[hosts.h1]\naxes = ["axis0", "axis1"]\n[hosts.h2]\naxes = ["x"]\ncycle_us = 2000\n'
                 '[groups]\ngantry = ["h1/axis0", "h2/x"]\n')
    f = load(p)
    assert list(f.hosts) == ["h1", "h2"]
    assert f.refs() == [("h1", "axis0"), ("h1", "axis1"), ("h2", "x")]
    assert f.hosts["h2"].cycle_us == 2000
    assert f.groups == {"gantry": ("h1/axis0", "h2/x")}
    assert f.expects("h1", "axis1") and not f.expects("h1", "x") and not f.expects("h3")


def test_dict_form():
    assert parse({"hosts": {"c1": {"axes": ["a", "b"]}}}).refs() == [("c1", "a"), ("c1", "b")]


@pytest.mark.parametrize("data, needle", [
    ({}, "hosts"),
    ({"hosts": {"h1": {"axes": []}}}, "hosts.h1.axes"),
    ({"hosts": {"h1": {"axes": ["a"], "axis": 1}}}, "unknown key"),
    ({"hosts": {"h 1": {"axes": ["a"]}}}, "not a name"),
    ({"hosts": {"h1": {"axes": ["a", "a"]}}}, "repeat"),
    ({"hosts": {"h1": {"axes": ["a"]}}, "groups": {"g": ["h2/a"]}}, "not an expected drive"),
    ({"hosts": {"h1": {"axes": ["a"], "cycle_us": 5}}}, "cycle_us"),
    ({"hosts": {"h1": {"axes": ["a"]}}, "extra": 1}, "unknown key"),
])
def test_errors_name_the_key(data, needle):
    with pytest.raises(FleetFileError, match=needle):
        parse(data)


def test_unreadable_and_malformed_files(tmp_path):
    with pytest.raises(FleetFileError, match="cannot read"):
        load(tmp_path / "nope.toml")
    bad = tmp_path / "bad.toml"
    bad.write_text("[hosts.h1\n")
    with pytest.raises(FleetFileError, match="not valid TOML"):
        load(bad)
