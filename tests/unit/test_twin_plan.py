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


# ---- device files: EDS hosts run canopen-sim and the agent's [can]; ESI hosts ecat-sim --esi ---------

EDS_DATA = __import__("pathlib").Path(__file__).resolve().parents[1] / "data" / "eds"


def test_device_files_per_axis_relative_to_the_fleet_file(tmp_path):
    from supervisor.fleetfile import FleetFileError, load

    (tmp_path / "fleet.toml").write_text('[hosts.c]\naxes = ["a", "b"]\ndevices = ["x.eds", "sub/y.EDS"]\n'
                                         '[hosts.e]\naxes = ["p", "q", "r"]\ndevice = "d.xml@0x1234:2"\n')
    f = load(tmp_path / "fleet.toml")
    assert f.hosts["c"].devices == (str(tmp_path / "x.eds"), str(tmp_path / "sub/y.EDS"))
    assert f.hosts["c"].device_kind == "eds" and f.hosts["e"].device_kind == "esi"
    assert f.hosts["e"].devices == (str(tmp_path / "d.xml@0x1234:2"),) * 3
    for spec, needle in (({"devices": ["a.eds"]}, r"one device file per axis \(2\)"),
                         ({"devices": ["a.eds", "b.xml"]}, "EDS and ESI files mixed"),
                         ({"device": "a.txt"}, r"'a.txt' is neither an EDS \(.eds\) nor an ESI \(.xml\)"),
                         ({"device": "a.eds", "devices": ["a.eds", "a.eds"]}, "not both"),
                         ({"device": "a.eds", "profile": "indy7"}, "no built-in profile")):
        with pytest.raises(FleetFileError, match=needle):
            parse({"hosts": {"h": {"axes": ["a", "b"], **spec}}})


def test_eds_host_gets_can_nodes_with_the_eds_policy_where_the_cycle_can_run_it():
    from twin.plan import can_channel, sim_device_args

    classic, interp = str(EDS_DATA / "classic.eds"), str(EDS_DATA / "interpolated.eds")
    f = parse({"hosts": {"c": {"axes": ["a", "b", "c"], "devices": [classic, classic, interp]}}})
    data = agent_toml(f, f.hosts["c"], "sim", "tcp/127.0.0.1:1", can=can_channel(4242, 0))
    cfg = config_from_dict(data)
    assert cfg.backend == "canopen" and cfg.can.channel == "ff11::7a64:1092:1" and cfg.sim_drives == 0
    assert [(n.node_id, n.eds, n.pdo) for n in cfg.can.nodes] == [
        (1, classic, "eds"), (2, classic, "eds"), (3, interp, "default")]   # interp: 0x6040 in two RPDOs
    assert [d.axis for d in cfg.drives] == ["a", "b", "c"]
    assert sim_device_args(f.hosts["c"]) == ["--eds", f"{classic}*2", "--eds", interp]
    with pytest.raises(PlanError, match=r"\['can'\] are set by the twin"):
        g = parse({"hosts": {"c": {"axes": ["a"], "device": classic, "agent": {"can": {}}}}})
        agent_toml(g, g.hosts["c"], "sim", "tcp/127.0.0.1:1", can="ff11::1")
    with pytest.raises(PlanError, match="a secure twin"):
        agent_toml(f, f.hosts["c"], "sim", "tcp/127.0.0.1:1", pki="/p", can="ff11::1")


def test_esi_host_needs_the_ecat_backend_and_passes_each_device_to_ecat_sim():
    from twin.plan import sim_device_args

    f = parse({"hosts": {"e": {"axes": ["p", "q", "r"], "devices": ["/d/a.xml", "/d/a.xml", "/d/b.xml@0x7:0x2"]}}})
    assert sim_device_args(f.hosts["e"]) == ["--esi", "/d/a.xml*2", "--esi", "/d/b.xml@0x7:0x2"]
    cfg = config_from_dict(agent_toml(f, f.hosts["e"], "ecat", "tcp/127.0.0.1:1", ifname="tw1m"))
    assert cfg.ifname == "tw1m" and cfg.backend == "pysoem"
    with pytest.raises(PlanError, match="ESI devices run on ecat-sim: use the ecat backend"):
        agent_toml(f, f.hosts["e"], "sim", "tcp/127.0.0.1:1")


def test_twin_builds_each_simulator_command_line_from_the_device_files():
    from twin.ecat import ecat_plan
    from twin.twin import Twin

    classic = str(EDS_DATA / "classic.eds")
    twin = Twin({"hosts": {"e": {"axes": ["p", "q"], "devices": ["/d/a.xml@0x7", "/d/b.xml"]},
                           "c": {"axes": ["a", "b"], "device": classic}}}, backend="ecat")
    twin.workdir = "/w"
    twin.ecat_hosts = {"e": ecat_plan(twin.prefix, 1)}                 # what start() makes (no namespace here)
    esi = twin.sim_argv("e")
    assert esi[:4] == ["ip", "netns", "exec", twin.ecat_hosts["e"].netns]
    assert esi[esi.index("--ifname") + 1] == twin.ecat_hosts["e"].sim and esi[esi.index("--drives") + 1] == "2"
    assert esi[-4:] == ["--esi", "/d/a.xml@0x7", "--esi", "/d/b.xml"]
    can = twin.sim_argv("c")
    assert can[1:3] == ["-m", "bus_agent.sim.canopen.cli"] and "--eds" in can and f"{classic}*2" in can
    assert can[can.index("--channel") + 1] == twin.can_hosts["c"].strip() and can[can.index("--name") + 1] == "c"
