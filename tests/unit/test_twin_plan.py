"""The twin's plan (twin/plan.py): agent configurations from a fleet file, and drive refs. Pure."""

import pytest

from bus_agent.config import config_from_dict
from supervisor.fleetfile import parse
from twin.plan import PlanError, agent_toml, check_host, parse_ref, plan

FLEET = {
    "hosts": {
        "press": {"axes": ["ram", "feed"], "cycle_us": 2000, "agent": {"reflex": "disable"}},
        "robot": {"axes": ["j1", "j2", "j3"], "profile": "indy7"},
        "conv": {"axes": ["belt"]},
    },
    "groups": {"line": ["press/feed", "conv/belt"], "arm": ["robot/j1", "robot/j2", "robot/j3"]},
}


def test_every_host_gets_exactly_its_axes_groups_and_hints():
    f = parse(FLEET)
    plans = plan(f, "sim", {h: f"unixsock-stream/{h}.link" for h in f.hosts})
    assert [p.name for p in plans] == ["press", "robot", "conv"]
    cfgs = {p.name: config_from_dict(p.agent_toml) for p in plans}
    assert [d.axis for d in cfgs["robot"].drives] == ["j1", "j2", "j3"]
    assert [d.slave for d in cfgs["robot"].drives] == [0, 1, 2]
    assert cfgs["robot"].sim_drives == 3 and cfgs["robot"].sim_profile == "indy7"
    assert cfgs["press"].cycle_us == 2000 and cfgs["press"].reflex == "disable"
    assert cfgs["conv"].cycle_us == 1000 and cfgs["conv"].reflex == "quick_stop"
    # only groups with a member on the host; members on other hosts kept (cross-host reflexes)
    assert dict(cfgs["press"].groups) == {"line": ("press/feed", "conv/belt")}
    assert dict(cfgs["robot"].groups) == {"arm": ("robot/j1", "robot/j2", "robot/j3")}
    assert cfgs["conv"].zenoh.connect == ("unixsock-stream/conv.link",) and cfgs["conv"].zenoh.listen == ()
    assert plans[1].slave_of("j3") == 2


def test_ecat_backend_names_the_master_end_and_no_sim_drives():
    f = parse({"hosts": {"h": {"axes": ["a"], "profile": "indy7"}}})
    cfg = config_from_dict(agent_toml(f, f.hosts["h"], "ecat", "tcp/127.0.0.1:1", ifname="tw1m"))
    assert cfg.ifname == "tw1m" and cfg.sim_drives == 0 and cfg.backend == "pysoem"


def test_nested_overrides_merge_without_touching_the_fleet():
    f = parse({"hosts": {"h": {"axes": ["a"], "agent": {"defaults": {"transition_timeout_s": 2.0},
                                                         "status": {"heartbeat_s": 0.5}}}}})
    cfg = config_from_dict(agent_toml(f, f.hosts["h"], "sim", "tcp/127.0.0.1:1"))
    assert cfg.default_policy.transition_timeout_s == 2.0 and cfg.heartbeat_s == 0.5
    assert dict(f.hosts["h"].agent) == {"defaults": {"transition_timeout_s": 2.0}, "status": {"heartbeat_s": 0.5}}


@pytest.mark.parametrize("agent, needle", [
    ({"host": "other"}, r"hosts\.h\.agent: key\(s\) \['host'\] are set by the twin"),
    ({"zenoh": {"connect": ["tcp/1.2.3.4:7447"]}}, r"\['zenoh'\]"),
    ({"drives": []}, r"\['drives'\]"),
    ({"reflex": "explode"}, r"hosts\.h\.agent: reflex: 'explode' is not one of"),
    ({"no_such_key": 1}, r"hosts\.h\.agent: no_such_key: unknown key"),
])
def test_bad_overrides_are_refused_naming_host_and_key(agent, needle):
    f = parse({"hosts": {"h": {"axes": ["a"], "agent": agent}}})
    with pytest.raises(PlanError, match=needle):
        agent_toml(f, f.hosts["h"], "sim", "tcp/127.0.0.1:1")


def test_unknown_backend_profile_refused():
    f = parse({"hosts": {"h": {"axes": ["a"], "profile": "nope"}}})
    with pytest.raises(PlanError, match="sim_profile: 'nope'"):
        agent_toml(f, f.hosts["h"], "sim", "tcp/127.0.0.1:1")
    with pytest.raises(PlanError, match="backend 'can'"):
        agent_toml(f, f.hosts["h"], "can", "tcp/127.0.0.1:1")


@pytest.mark.parametrize("ref, needle", [
    ("press", "not of the form"), ("press/ram/x", "not of the form"),
    ("nope/ram", "no host 'nope'"), ("press/j1", "host press has no axis 'j1'"),
])
def test_refs_are_checked_against_the_fleet(ref, needle):
    with pytest.raises(PlanError, match=needle):
        parse_ref(parse(FLEET), ref)
    assert parse_ref(parse(FLEET), "robot/j2") == ("robot", "j2")
    assert check_host(parse(FLEET), "conv") == "conv"
    with pytest.raises(PlanError, match="no host 'x'"):
        check_host(parse(FLEET), "x")
