"""The dashboard's view and metrics (pure logic, no network): rows, changes since a version,
offline expected drives, and the Prometheus exposition parsed back with the client's parser."""

from __future__ import annotations

import pytest
from prometheus_client.parser import text_string_to_metric_families

from dashboard.app import cross_site_refusal, recording_json, state_runs
from dashboard.cli import main as cli_main
from dashboard.metrics import registry_for, render
from dashboard.view import DISPLAY_OF_STATE, DISPLAYS, FleetView, display_of
from schemas import messages as m


def status(axis: str, state: str = "switch_on_disabled", **kw) -> m.DriveStatus:
    base = dict(host="h1", axis=axis, seq=1, time_ns=10**18, cycle=5, state=state, statusword=0x0250,
                controlword=0, goal="disabled", halt=False, mode=8, mode_display=8, position=7, velocity=0,
                torque=0, error_code=0)
    base.update(kw)
    return m.DriveStatus(**base)


def agent(**kw) -> m.AgentStatus:
    base = dict(host="h1", seq=0, time_ns=0, state="running", backend="sim", cycle_us=1000, cycles=9000,
                period_p50_us=1000.0, period_p99_us=1100.0, period_max_us=2500.0, overruns=3, wkc_errors=1,
                expected_wkc=6, axes=["a", "b"], commands={"enable.done": 2, "enable.failed": 1})
    base.update(kw)
    return m.AgentStatus(**base)


def test_rows_changes_and_offline_expected_drives():
    v = FleetView({"h1": ["a", "b"], "h9": ["x"]})
    full = v.changes_since(0)
    assert {(d["host"], d["axis"], d["state"]) for d in full["drives"]} == {
        ("h1", "a", "offline"), ("h1", "b", "offline"), ("h9", "x", "offline")}
    v.on_alive("h1", True)
    v.on_agent(agent())
    v.on_status(status("a"))
    v.on_status(status("b"))
    mark = v.version
    v.on_status(status("b", "fault", error_code=0x2310, statusword=0x0218))
    ch = v.changes_since(mark)
    assert [(d["axis"], d["state"], d["alarm"]) for d in ch["drives"]] == [("b", "fault", True)]
    assert v.changes_since(v.version)["drives"] == []
    snap = v.snapshot()
    assert snap["summary"]["by_state"]["fault"] == 1 and snap["summary"]["by_state"]["offline"] == 1
    assert snap["summary"]["agents_up"] == 1 and snap["summary"]["agents_expected_offline"] == 1
    v.on_alive("h1", False)  # the agent went away: its drives stand out as not online
    rows = {d["axis"]: d for d in v.snapshot()["drives"] if d["host"] == "h1"}
    assert not rows["a"]["online"] and rows["a"]["alarm"]
    v.on_event(m.Event(host="h1", axis="b", seq=1, time_ns=1, cycle=2, kind="fault", error_code=0x2310))
    assert v.changes_since(mark)["events"][0]["alarm"] is True
    d = v.drive("h1", "a")
    assert d is not None and d["motion"]["position"] == [7]
    assert v.drive("h1", "nope") is None


def test_metrics_exposition_follows_the_conventions():
    v = FleetView({"h9": ["x"]})
    v.on_alive("h1", True)
    v.on_agent(agent())
    v.on_status(status("a", "operation_enabled"))
    v.on_status(status("b", "fault", error_code=0x7500, lost=True, al_state="safeop"))
    fams = {f.name: f for f in text_string_to_metric_families(render(registry_for(v)).decode())}
    cur = {(s.labels["axis"], s.labels["state"]) for s in fams["drives_drive_state"].samples if s.value == 1}
    assert cur == {("a", "operation_enabled"), ("b", "fault")}
    assert len(fams["drives_drive_state"].samples) == 2 * len(m.DRIVE_STATES)
    assert {s.labels["axis"]: s.value for s in fams["drives_drive_error_code"].samples} == {"a": 0, "b": 0x7500}
    assert {s.labels["axis"]: s.value for s in fams["drives_drive_lost"].samples} == {"a": 0, "b": 1}
    assert {(s.labels["axis"], s.labels["al_state"]) for s in fams["drives_drive_al_state"].samples
            if s.value == 1} == {("a", "op"), ("b", "safeop")}
    assert fams["drives_cycle_overruns"].type == "counter"
    assert [s.value for s in fams["drives_cycle_overruns"].samples if s.name.endswith("_total")] == [3]
    period = {s.labels["quantile"]: s.value for s in fams["drives_cycle_period_seconds"].samples}
    assert period == {"0.5": 0.001, "0.99": 0.0011, "1": 0.0025}
    cmds = {(s.labels["op"], s.labels["outcome"]): s.value for s in fams["drives_commands"].samples
            if s.name == "drives_commands_total"}
    assert cmds == {("enable", "done"): 2, ("enable", "failed"): 1}
    up = {s.labels["host"]: s.value for s in fams["drives_agent_up"].samples}
    assert up == {"h1": 1.0, "h9": 0.0}
    by_state = {s.labels["state"]: s.value for s in fams["drives_drives"].samples}
    assert by_state["fault"] == 1 and by_state["offline"] == 1 and by_state["operation_enabled"] == 1


def test_recording_json_splits_axes():
    rec = m.Recording(host="h1", reason="fault", cycle_us=1000, first_cycle=10, n_cycles=2, time_origin_ns=0,
                      axes=["a", "b"], channels={"time_ns": [0, 1_000_000], "statusword": [1, 2, 3, 4]},
                      trigger_cycle=11)
    j = recording_json(rec, "b")
    assert j["t"] == [0.0, 0.001] and j["drives"]["b"]["statusword"] == [2, 4] and list(j["drives"]) == ["b"]
    assert j["t0_ms"] == 0 and j["cycle_channels"] == {}


def test_recording_states_come_in_runs():
    # switch_on_disabled, operation_enabled twice, fault: three runs from their first cycles
    assert state_runs([0x0250, 0x0237, 0x0237, 0x0218]) == [[0, "switch_on_disabled", "disabled"],
                                                            [1, "operation_enabled", "enabled"], [3, "fault", "fault"]]
    assert state_runs([]) == []


def test_display_classes_cover_every_state_and_lost_drives():
    assert set(DISPLAY_OF_STATE) == set(m.DRIVE_STATES)  # every contract state has a colour
    assert set(DISPLAY_OF_STATE.values()) | {"offline"} == set(DISPLAYS)
    assert display_of("operation_enabled", False, True) == "enabled"
    assert display_of("quick_stop_active", False, True) == "quick_stop"
    assert display_of("fault_reaction_active", False, True) == "fault"
    assert display_of("operation_enabled", True, True) == "lost"   # the old contract: last state, lost
    assert display_of("unknown", False, True) == "lost"            # the new: state unknown
    assert display_of("fault", True, False) == "offline"           # no live agent: offline first


def test_lost_drive_row_keeps_its_last_known_state_and_conflicts_reach_the_host_row():
    v = FleetView()
    v.on_alive("h1", True)
    v.on_status(status("a", "operation_enabled"))
    v.on_status(status("a", "unknown", lost=True, seq=2))
    row = v.snapshot()["drives"][0]
    assert (row["display"], row["lost"], row["last_state"], row["alarm"]) == ("lost", True, "operation_enabled", True)
    v.on_status(status("a", "switch_on_disabled", seq=3))
    row = v.snapshot()["drives"][0]
    assert (row["display"], row["lost"], row["last_state"]) == ("disabled", False, "")
    mark = v.version
    v.on_conflicts({"h1": "host name h1 is used by 2 agents"})
    hosts = v.changes_since(mark)["hosts"]
    assert [(h["host"], h["conflict"]) for h in hosts] == [("h1", "host name h1 is used by 2 agents")]
    mark = v.version
    v.on_conflicts({"h1": "host name h1 is used by 2 agents"})
    assert v.changes_since(mark)["hosts"] == []   # unchanged: nothing sent
    v.on_conflicts({})
    assert v.snapshot()["hosts"][0]["conflict"] == ""


def test_grafana_dashboard_and_scrape_config_use_exposed_metrics():
    import json
    import re
    from pathlib import Path

    root = Path(__file__).resolve().parents[2]
    v = FleetView({"h9": ["x"]})
    v.on_alive("h1", True)
    v.on_agent(agent(dc={"a": "sync0"}, dc_offset_p50_us=500.0, dc_offset_p99_us=510.0))
    v.on_status(status("a", "operation_enabled"))
    exposed = {s.name for f in text_string_to_metric_families(render(registry_for(v)).decode()) for s in f.samples}
    dash = json.loads((root / "deploy" / "grafana-dashboard.json").read_text())
    used = {name for p in dash["panels"] for t in p["targets"] for name in re.findall(r"drives_[a-z_]+", t["expr"])}
    assert used and used <= exposed, used - exposed
    assert "/metrics" in (root / "deploy" / "prometheus.yml").read_text()


def test_following_error_and_dc_offset_only_when_known():
    v = FleetView()
    v.on_alive("h1", True)
    v.on_agent(agent(axes=["a", "b", "c", "d"], dc={"a": "sync0", "b": "off"}, dc_offset_p50_us=480.5,
                     dc_offset_p99_us=512.0))
    v.on_agent(agent(host="h2", dc={"x": "off"}, dc_offset_p50_us=0.0, dc_offset_p99_us=0.0))
    v.on_alive("h2", True)
    # a: maps 0x60F4 (the drive's own, in any state); b: CSP in Operation enabled (the agent's);
    # c: CSP but disabled; d: enabled in CSV (the agent's figure means nothing there)
    v.on_status(status("a", objects={"following_error_actual_value": -12}, following_error=3))
    v.on_status(status("b", "operation_enabled", following_error=40))
    v.on_status(status("c", following_error=0))
    v.on_status(status("d", "operation_enabled", mode=9, mode_display=9, following_error=5))
    v.on_status(status("e", "operation_enabled", following_error=5, absent=["position"]))
    fams = {f.name: f for f in text_string_to_metric_families(render(registry_for(v)).decode())}
    fe = {(s.labels["axis"], s.labels["source"]): s.value
          for s in fams["drives_drive_following_error_increments"].samples}
    assert fe == {("a", "0x60F4"): -12.0, ("b", "agent"): 40.0}
    dc = {(s.labels["host"], s.labels["quantile"]): s.value for s in fams["drives_dc_offset_seconds"].samples}
    assert dc == {("h1", "0.5"): 0.0004805, ("h1", "0.99"): 0.000512}  # h2: DC capable, no SYNC0: no series
    rows = {d["axis"]: d["following_error"] for d in v.snapshot()["drives"]}
    assert rows == {"a": -12, "b": 40, "c": None, "d": None, "e": None}
    hosts = {h["host"]: (h["dc_offset_p50_us"], h["dc_offset_p99_us"]) for h in v.snapshot()["hosts"]}
    assert hosts == {"h1": (480.5, 512.0), "h2": (None, None)}


def test_target_clamps_counter_per_drive():
    """The output stage's clamps (drive status ``target_clamps``) as a counter per drive; a status
    from an older agent without the field reads 0."""
    v = FleetView()
    v.on_alive("h1", True)
    v.on_agent(agent())
    v.on_status(status("a", "operation_enabled", target_clamps=365))
    v.on_status(status("b"))
    fams = {f.name: f for f in text_string_to_metric_families(render(registry_for(v)).decode())}
    got = {s.labels["axis"]: s.value for s in fams["drives_drive_target_clamps"].samples
           if s.name == "drives_drive_target_clamps_total"}
    assert got == {"a": 365.0, "b": 0.0}


def test_commands_refused_from_other_sites_and_as_non_json():
    ok = {"content-type": "application/json", "host": "127.0.0.1:8402", "origin": "http://127.0.0.1:8402"}
    assert cross_site_refusal(ok) == ""
    assert cross_site_refusal({"content-type": "application/json; charset=utf-8", "host": "h:1"}) == ""
    assert "application/json" in cross_site_refusal({**ok, "content-type": "text/plain"})
    assert "origin" in cross_site_refusal({**ok, "origin": "https://evil.example"})


def test_commands_need_an_identity(capsys):
    with pytest.raises(SystemExit) as exc:
        cli_main(["--commands"])
    assert exc.value.code == 2 and "--commands needs an identity" in capsys.readouterr().err


def test_a_lost_drive_shows_the_last_known_state_of_its_status():
    """The agent's ``last_known_state`` (issue 23: a lost drive's state is unknown) wins over the
    state the view saw last; an older agent's status without it falls back to the view's own."""
    from dashboard.view import drive_row
    lost = status("a", "unknown", lost=True, last_known_state="operation_enabled")
    row = drive_row(lost, True, last_state="switch_on_disabled")
    assert row["display"] == "lost" and row["last_state"] == "operation_enabled"
    assert drive_row(status("a", "unknown", lost=True), True, "fault")["last_state"] == "fault"
    assert drive_row(status("a", "operation_enabled"), True, "fault")["last_state"] == ""
