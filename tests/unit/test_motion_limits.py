"""Software position limits written to the drive: 0x607D:1/2 from the axis's [motion] config at
start-up (the start-up SDO path), scaled to counts, clamped to i32, optional; the simulated drive
limits position targets to them; moves beyond them are refused by the agent."""

from __future__ import annotations

import dataclasses

import pytest

from bus_agent.bus.pdo import DriveOutputs
from bus_agent.config import ConfigError, DriveConfig, config_from_dict
from bus_agent.motion.config import MotionConfig
from bus_agent.sim.drive_model import DriveModel
from tests.unit.motion_rig import Rig

I32_MIN, I32_MAX = -2**31, 2**31 - 1


@pytest.mark.parametrize("cfg, sdos", [
    (MotionConfig(), ()),
    (MotionConfig(min_position=-1000, max_position=2000), ((0x607D, 1, -1000), (0x607D, 2, 2000))),
    (MotionConfig(max_position=5.5, counts_per_unit=1000), ((0x607D, 1, I32_MIN), (0x607D, 2, 5500))),
    (MotionConfig(min_position=-1, max_position=2, counts_per_unit=-100), ((0x607D, 1, -200), (0x607D, 2, 100))),
    (MotionConfig(min_position=-1e12, max_position=1e12), ((0x607D, 1, I32_MIN), (0x607D, 2, I32_MAX))),
    (MotionConfig(min_position=-1000, max_position=2000, write_limits=False), ()),
])
def test_limit_sdos_in_counts(cfg, sdos):
    assert cfg.limit_sdos() == sdos


def test_drive_setup_writes_the_limits_before_the_configured_sdos():
    d = DriveConfig(slave=0, motion=MotionConfig(min_position=-10, max_position=10))
    assert [(s.index, s.subindex, s.type, s.value) for s in d.setup.sdos] == [(0x607D, 1, "i32", -10),
                                                                              (0x607D, 2, "i32", 10)]
    assert d.needs_setup


def test_toml_write_limits_parsed_and_checked():
    base = {"host": "h1", "sim_drives": 1}
    cfg = config_from_dict({**base, "drives": [{"slave": 0, "motion": {"max_position": 100.0, "write_limits": False}}]})
    assert cfg.drives[0].motion.write_limits is False and cfg.drives[0].setup.sdos == ()
    with pytest.raises(ConfigError, match="write_limits"):
        config_from_dict({**base, "drives": [{"slave": 0, "motion": {"write_limits": "yes"}}]})


def test_limits_reach_the_drive_at_start_up_and_moves_beyond_are_refused():
    cfg = MotionConfig(min_position=-50_000, max_position=80_000)
    r = Rig(2, motion=cfg)
    assert (r.model(0).read(0x607D, 1), r.model(0).read(0x607D, 2)) == (-50_000, 80_000)
    assert (r.model(1).read(0x607D, 1), r.model(1).read(0x607D, 2)) == (-50_000, 80_000)
    r.tick(5)
    r.enable()
    got = r.do("move", "axis0", {"to": 90_000})
    assert got[0].outcome == "rejected" and "max_position 80000" in got[0].reason
    assert r.do("move", "axis0", {"to": 80_000})[0].outcome == "done"
    r2 = Rig(1, motion=dataclasses.replace(cfg, write_limits=False))
    assert r2.model(0).read(0x607D, 2) == I32_MAX


def test_simulated_drive_limits_position_targets_to_0x607d():
    m = DriveModel()
    m.write(0x607D, 2, 1_000)
    for cw, n in ((0x06, 5), (0x07, 2), (0x0F, 3)):
        for _ in range(n):
            m.apply_outputs(DriveOutputs(controlword=cw, modes_of_operation=1))
            m.step(0.001)
    for cw in (0x1F, 0x0F):  # PP set-point 5000: limited to 1000
        m.apply_outputs(DriveOutputs(controlword=cw, modes_of_operation=1, target_position=5_000))
        m.step(0.001)
    for _ in range(2000):
        m.apply_outputs(DriveOutputs(controlword=0x0F, modes_of_operation=1, target_position=5_000))
        m.step(0.001)
    assert m.position == 1_000
