"""Tests of the example cell against a twin of its fleet file, with the package's pytest plugin
(the ``drives_twin`` fixture comes from the installed entry point; nothing to import)."""

from __future__ import annotations

from pathlib import Path

import pytest

from cell import Cell

FLEET = Path(__file__).with_name("fleet.toml")

pytestmark = [pytest.mark.timeout(180)]


def test_sequence_runs_and_ends_disabled(drives_twin):
    twin = drives_twin(FLEET)
    enabled_after_feed = []

    def between(step: str) -> None:
        if step == "feed":
            enabled_after_feed.extend(twin.wait_state(r, "operation_enabled", 10).axis
                                      for r in ("press/clamp", "press/ram", "conv/belt"))

    result = Cell(twin.fleet, between_steps=between).run()
    assert result.state == "done", result
    assert result.steps_done == ["clamp", "press", "feed", "pause-feed", "resume-feed"]
    assert enabled_after_feed == ["clamp", "ram", "belt"]
    off = ("ready_to_switch_on", "switch_on_disabled")  # after the ordered shutdown: no drive enabled
    assert twin.fleet.wait_until(lambda f: all(f.status(r).state in off
                                               for r in ("press/clamp", "press/ram", "conv/belt")), 10)


def test_fault_stops_the_line_and_is_not_reset_blindly(drives_twin):
    twin = drives_twin(FLEET)

    def between(step: str) -> None:
        if step == "feed":  # everything enabled: the ram faults
            twin.fault("press/ram", 0x2310)
            twin.wait_state("press/ram", "fault", 10)

    result = Cell(twin.fleet, between_steps=between).run()
    assert result.state == "faulted", result
    assert result.fault == "press/ram 0x2310"
    assert "pause-feed" not in result.steps_done
    assert result.detail == "waiting for an operator"
    twin.wait_state("press/clamp", "switch_on_disabled", 10)
    twin.wait_state("conv/belt", "switch_on_disabled", 10)  # on the other host: reflex, then the cell
    assert twin.wait_state("press/ram", "fault", 2).error_code == 0x2310  # still faulted: nobody reset it


def test_a_lost_conveyor_host_stops_the_press(drives_twin):
    twin = drives_twin(FLEET)

    def between(step: str) -> None:
        if step == "feed":
            twin.cut("conv")  # the conveyor's cable: seen when the link lease runs out
            twin.fleet.wait_until(lambda f: "conv" not in f.hosts(), 15)

    result = Cell(twin.fleet, between_steps=between).run()
    assert result.state == "faulted" and result.fault in ("conv lost", "conv/belt lost"), result
    twin.wait_state("press/clamp", "switch_on_disabled", 10)
    twin.wait_state("press/ram", "switch_on_disabled", 10)
