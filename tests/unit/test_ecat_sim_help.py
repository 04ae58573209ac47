"""`ecat-sim --help` names every slave profile and modifier the issue and docs/virtual-ethercat.md use."""

from __future__ import annotations

import pytest

from bus_agent.sim.cli import build_parser
from bus_agent.sim.ecat.profiles import MODIFIERS, PROFILES, as_ecat


def test_help_lists_every_profile_and_modifier():
    text = build_parser().format_help()
    for name in (*PROFILES, *MODIFIERS):
        assert f"\n  {name} " in text, name
    assert as_ecat("omron1s:dc-required").dc_required and as_ecat("generic:dc").dc


def test_an_unknown_modifier_is_refused_by_name():
    with pytest.raises(ValueError, match="unknown modifier 'dc-maybe'"):
        as_ecat("omron1s:dc-maybe")


def test_help_names_every_control_action():
    from bus_agent.sim.ecat.control import ACTIONS

    text = " ".join(build_parser().format_help().split())
    for action in ACTIONS:
        assert action in text, action
    assert "mute_sdo" in ACTIONS
