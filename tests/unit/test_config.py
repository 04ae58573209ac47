"""Agent configuration: TOML loading, defaults, errors naming the key, overrides."""

from __future__ import annotations

from pathlib import Path

import pytest

from bus_agent.config import AgentConfig, ConfigError, config_from_dict, load_config

ROOT = Path(__file__).resolve().parents[2]


def test_example_file_loads_with_every_key():
    cfg = load_config(ROOT / "deploy" / "agent.example.toml")
    assert cfg.host == "h1" and cfg.ifname == "eth1" and cfg.backend == "pysoem"
    assert cfg.cycle_us == 1000 and cfg.reflex == "quick_stop" and cfg.heartbeat_s == 1.0
    assert cfg.zenoh.mode == "peer" and cfg.zenoh.scouting is False
    x, y = cfg.drives
    assert (x.slave, x.axis, x.mode) == (0, "x", 8)
    assert x.identity.vendor_id == 0xABC and x.identity.revision is None
    assert x.pdo is None and x.mapping is not None and x.mapping.policy == "drive"
    assert [(s.index, s.type, s.value) for s in x.sdos] == [(0x6065, "u32", 10000)]
    assert x.policy.auto_reset.enabled and x.policy.auto_reset.max_attempts == 2
    assert x.policy.auto_reset.backoff_s == 1.0  # inherited from [defaults.auto_reset]
    assert (y.axis, y.identity, y.pdo) == ("y", None, None)
    assert not y.policy.auto_reset.enabled
    assert y.policy.lease_reaction == "quick_stop_then_disable"
    assert cfg.groups == {"gantry": ("h1/x", "h1/y", "h2/z")}


def test_defaults_and_default_drives():
    cfg = config_from_dict({"host": "h1", "sim_drives": 3})
    assert cfg.backend == "sim" and cfg.cycle_us == 1000 and cfg.reflex == "quick_stop"
    drives = cfg.drive_configs(3)
    assert [d.axis for d in drives] == ["axis0", "axis1", "axis2"]
    assert all(d.mode == 8 and not d.policy.auto_reset.enabled and d.policy.transition_timeout_s == 5.0
               for d in drives)


@pytest.mark.parametrize("data,key", [
    ({"sim_drives": 1}, "host"),
    ({"host": "h/1", "sim_drives": 1}, "host"),
    ({"host": "h1"}, "ifname or sim_drives"),
    ({"host": "h1", "ifname": "e", "sim_drives": 2}, "ifname and sim_drives"),
    ({"host": "h1", "sim_drives": 1, "cycle_us": "1000"}, "cycle_us"),
    ({"host": "h1", "sim_drives": 1, "cycle_us": 10}, "cycle_us"),
    ({"host": "h1", "sim_drives": 1, "reflex": "panic"}, "reflex"),
    ({"host": "h1", "sim_drives": 1, "zenoh": {"mode": "mesh"}}, "zenoh.mode"),
    ({"host": "h1", "sim_drives": 1, "zenoh": {"listen": [7447]}}, "zenoh.listen[0]"),
    ({"host": "h1", "sim_drives": 1, "colour": "red"}, "colour: unknown key"),
    ({"host": "h1", "sim_drives": 1, "drives": [{"axis": "x"}]}, "drives[0].slave"),
    ({"host": "h1", "sim_drives": 1, "drives": [{"slave": 0, "axis": "a*"}]}, "drives[0].axis"),
    ({"host": "h1", "sim_drives": 1, "drives": [{"slave": 0}, {"slave": 0}]}, "drives[1].slave"),
    ({"host": "h1", "sim_drives": 1, "drives": [{"slave": 0, "axis": "a"}, {"slave": 1, "axis": "a"}]},
     "drives[1].axis"),
    ({"host": "h1", "sim_drives": 1, "drives": [{"slave": 0, "mode": 2}]}, "drives[0].mode"),
    ({"host": "h1", "sim_drives": 1, "drives": [{"slave": 0, "identity": {"vendor_id": 1}}]},
     "drives[0].identity.product_code"),
    ({"host": "h1", "sim_drives": 1, "drives": [{"slave": 0, "pdo": {"rx_pdo": 0x1A00}}]}, "drives[0].pdo.rx_pdo"),
    ({"host": "h1", "sim_drives": 1, "drives": [{"slave": 0, "lease_reaction": "run"}]},
     "drives[0].lease_reaction"),
    ({"host": "h1", "sim_drives": 1, "drives": [{"slave": 0, "auto_reset": {"max_attempts": 0}}]},
     "drives[0].auto_reset.max_attempts"),
    ({"host": "h1", "sim_drives": 1, "drives": [{"slave": 0, "auto_reset": {"enable": True}}]},
     "drives[0].auto_reset.enable: unknown key"),
    ({"host": "h1", "sim_drives": 1, "defaults": {"transition_timeout_s": 0}}, "defaults.transition_timeout_s"),
    ({"host": "h1", "sim_drives": 1, "groups": {"g": ["axis0"]}}, "groups.g"),
    ({"host": "h1", "sim_drives": 1, "drives": [{"slave": 0}], "groups": {"g": ["h1/nope"]}}, "groups.g"),
    ({"host": "h1", "sim_drives": 1, "status": {"heartbeat_s": -1}}, "heartbeat_s"),
])
def test_errors_name_the_key(data, key):
    with pytest.raises(ConfigError) as e:
        config_from_dict(data)
    assert key in str(e.value)


def test_load_errors_name_the_file(tmp_path):
    p = tmp_path / "a.toml"
    p.write_text('host = "h1"\nsim_drives = 2\ncycle_us = "fast"\n')
    with pytest.raises(ConfigError, match=r"a\.toml: cycle_us"):
        load_config(p)
    p.write_text("host = \n")
    with pytest.raises(ConfigError, match="TOML syntax"):
        load_config(p)
    with pytest.raises(ConfigError, match="cannot read"):
        load_config(tmp_path / "missing.toml")


def test_missing_configured_slave_is_an_error():
    cfg = config_from_dict({"host": "h1", "sim_drives": 2, "drives": [{"slave": 3, "axis": "z"}]})
    with pytest.raises(ConfigError, match=r"drives\[0\]\.slave: position 3 .* 2 slave"):
        cfg.drive_configs(2)


def test_with_overrides():
    base = config_from_dict({"host": "h1", "sim_drives": 2})
    cfg = base.with_overrides(ifname="veth0", cycle_us=2000, listen=["tcp/127.0.0.1:7447"], host=None)
    assert cfg.ifname == "veth0" and cfg.sim_drives == 0 and cfg.backend == "pysoem"
    assert cfg.cycle_us == 2000 and cfg.zenoh.listen == ("tcp/127.0.0.1:7447",) and cfg.host == "h1"
    assert base.cycle_us == 1000  # frozen: the original is unchanged
    back = cfg.with_overrides(sim_drives=4)
    assert back.backend == "sim" and back.sim_drives == 4
    with pytest.raises(ConfigError, match="cycle_us"):
        base.with_overrides(cycle_us=5)
    with pytest.raises(ConfigError, match="unknown override"):
        base.with_overrides(speed=3)
    with pytest.raises(ConfigError, match="host"):
        AgentConfig(host="", sim_drives=1)


def test_startup_soem_call_deadline():
    base = {"host": "h1", "ifname": "eth1"}
    assert config_from_dict(base).soem_call_s == 30.0
    assert config_from_dict({**base, "startup": {"soem_call_s": 3}}).soem_call_s == 3.0
    for bad in (0.5, 601):
        with pytest.raises(ConfigError, match="startup.soem_call_s"):
            config_from_dict({**base, "startup": {"soem_call_s": bad}})
    with pytest.raises(ConfigError, match="startup"):
        config_from_dict({**base, "startup": {"deadline": 3}})
