"""The dashboard as an operator uses it, in a real headless Chromium against real agents.

A secured fleet (drives-pki: mutual TLS, the ACL): a router, two agents (h1, h2, two simulated
drives each) in one test-bed process, an expected host h9 that never comes, and
``drives-dashboard --commands`` under its own operator identity ``dash``. The browser's computed
styles tell a faulted, a lost and an enabled drive apart; drives sit in their host's section with
the agent's health; the attention banner names the fault, the lost drive and the offline host;
the drive page's plot places every status at the agent's time stamp; the flight-recording viewer
shows the fault's window; a command button sends nothing until its confirmation is accepted.
"""

from __future__ import annotations

import threading
import time
import urllib.error
import urllib.request
from typing import Any, Iterator

import pytest
import zenoh

from bus_agent.security import pki
from bus_agent.sim.child import wait_for
from bus_agent.sim.control import sim_inject
from schemas import keys
from schemas import messages as m
from supervisor.fleet import Fleet
from supervisor.session import zenoh_config
from supervisor.testbed import (Proc, start_agents, start_dashboard,
                               start_router)

pytestmark = pytest.mark.timeout(240)

PRINCIPALS = {"r1": ["router"], "h1": ["agent", "testbed"], "h2": ["agent", "testbed"],
              "dash": ["operator", "maintenance"], "tester": ["operator", "maintenance", "testbed"]}
OFFLINE = "h9"


@pytest.fixture(scope="module")
def bed(tmp_path_factory: pytest.TempPathFactory) -> Iterator[dict[str, Any]]:
    d = tmp_path_factory.mktemp("pki")
    pki.init(d)
    for name, roles in PRINCIPALS.items():
        pki.issue(d, name, roles)
    fleet_file = d / "fleet.toml"
    fleet_file.write_text('[hosts.h1]\naxes = ["axis0", "axis1"]\n[hosts.h2]\naxes = ["axis0", "axis1"]\n'
                          f'[hosts.{OFFLINE}]\naxes = ["x"]\n')
    router, ep = start_router(pki=str(d), identity="r1")
    agents: Proc | None = None
    dash: Proc | None = None
    fleet: Fleet | None = None
    try:
        # a 2 s SM watchdog: a host stall on a shared machine does not fault or drop the drives under test
        agents = start_agents(["h1", "h2"], 2, ep, pki=str(d), sm_watchdog_s=2.0)
        dash, url = start_dashboard(ep, "--fleet", str(fleet_file), "--pki", str(d), "--identity", "dash", "--commands")
        fleet = Fleet(connect=[ep], pki=d, identity="tester", connect_timeout_s=10.0).open()
        assert fleet.wait_for_agents(["h1", "h2"], 20)
        yield {"ep": ep, "url": url, "pki": d, "fleet": fleet, "dash": dash}
    finally:
        if fleet is not None:
            fleet.close()
        for p in (dash, agents, router):
            if p is not None:
                p.stop()



def js(driver: Any, script: str, *args: Any) -> Any:
    return driver.execute_script(script, *args)


def display(driver: Any, host: str, axis: str) -> str | None:
    return js(driver, "const r = document.getElementById(arguments[0]); return r && r.dataset.display;",
              f"drive-{host}-{axis}")


def state_colour(driver: Any, host: str, axis: str) -> str:
    """The background colour of the drive's state cell, as the browser computed it."""
    return js(driver, "return getComputedStyle(document.querySelector('#' + arguments[0] + ' td.state'))"
                      ".backgroundColor;", f"drive-{host}-{axis}")


def banner(driver: Any) -> list[tuple[str, str]]:
    return [tuple(item) for item in js(driver, "const b = document.getElementById('attention'); if (b.hidden) return [];"
                      "return Array.from(b.querySelectorAll('li')).map((li) => [li.dataset.kind, li.dataset.ref]);")]


def click(driver: Any, css: str) -> None:
    """A real click on the element; found again if the page rebuilt its row in between."""
    from selenium.common.exceptions import StaleElementReferenceException

    for _ in range(5):
        try:
            driver.find_element("css selector", css).click()
            return
        except StaleElementReferenceException:
            continue
    raise AssertionError(f"{css}: rebuilt under every click")


def agent_count(fleet: Fleet, host: str, key: str) -> int:
    st = fleet.agents()[host].status
    return dict(st.commands).get(key, 0) if st is not None else 0


def test_colours_grouping_health_and_banner(bed: dict[str, Any], browser: Any) -> None:
    fleet: Fleet = bed["fleet"]
    browser.get(bed["url"] + "/")
    wait_for(lambda: all(display(browser, h, a) == "disabled" for h in ("h1", "h2") for a in ("axis0", "axis1")), 20,
             "every drive shown disabled")
    # grouped by host: each drive row sits in its host's section, sections in host order
    groups = js(browser, "return Array.from(document.querySelectorAll('#drives section.host')).map((s) => "
                         "[s.dataset.host, Array.from(s.querySelectorAll('table.drives tbody tr')).map((r) => r.id)]);")
    assert groups == [["h1", ["drive-h1-axis0", "drive-h1-axis1"]], ["h2", ["drive-h2-axis0", "drive-h2-axis1"]],
                      [OFFLINE, [f"drive-{OFFLINE}-x"]]], groups
    # the agent's health in its section: alive and running, cycles counted, overruns and WKC errors shown
    health = js(browser, "return Array.from(document.querySelectorAll('#host-h1 #agent-h1 td')).map((c) => c.textContent);")
    assert health[0] == "running" and int(health[2]) > 0 and health[5].isdigit() and health[6].isdigit(), health
    assert browser.find_element("id", f"agent-{OFFLINE}").get_attribute("data-state") == "offline"
    assert ("offline", OFFLINE) in banner(browser)
    assert "commands as dash" in browser.find_element("id", "mode").text

    assert fleet.command("enable", fleet.select("h1/axis0")).ok
    sim_inject(fleet.session, "h1", 1, "fault", error_code=0x2310)
    wait_for(lambda: display(browser, "h1", "axis0") == "enabled" and display(browser, "h1", "axis1") == "fault", 10,
             "the enable and the fault on the page")
    enabled, fault, disabled = (state_colour(browser, "h1", "axis0"), state_colour(browser, "h1", "axis1"),
                                state_colour(browser, "h2", "axis1"))
    assert len({enabled, fault, disabled}) == 3, (enabled, fault, disabled)
    assert fault == "rgb(198, 40, 40)", fault  # the fault red of style.css, computed by the browser
    wait_for(lambda: ("fault", "h1/axis1") in banner(browser), 5, "the fault in the banner")
    # read in one script: the page rebuilds rows and banner items on every change (no stale elements)
    assert "0x2310" in js(browser, "return document.querySelector(\"#attention li[data-ref='h1/axis1']\").textContent;")

    sim_inject(fleet.session, "h2", 0, "unplug")
    wait_for(lambda: display(browser, "h2", "axis0") == "lost", 10, "the lost drive on the page")
    lost = state_colour(browser, "h2", "axis0")
    assert lost not in (enabled, fault, disabled), lost
    wait_for(lambda: ("lost", "h2/axis0") in banner(browser), 5, "the lost drive in the banner")
    assert js(browser, "return document.querySelector('#drive-h2-axis0 td.state').textContent;").startswith("lost")
    errors = [e for e in browser.get_log("browser") if e["level"] == "SEVERE"]
    assert not errors, errors


def test_command_button_sends_only_after_confirmation(bed: dict[str, Any], browser: Any) -> None:
    fleet: Fleet = bed["fleet"]
    if display(browser, "h1", "axis1") != "fault":
        browser.get(bed["url"] + "/")
        sim_inject(fleet.session, "h1", 1, "fault", error_code=0x2310)
        wait_for(lambda: display(browser, "h1", "axis1") == "fault", 10, "the fault on the page")
    before = agent_count(fleet, "h1", "fault_reset.done")
    # another site's page cannot send one through the operator's browser: not JSON, or not our origin
    body = b'{"selector": "h1/axis1"}'
    for headers, code in (({"Content-Type": "text/plain"}, 415),
                          ({"Content-Type": "application/json", "Origin": "https://elsewhere.example"}, 403)):
        req = urllib.request.Request(bed["url"] + "/api/command/fault_reset", data=body, method="POST", headers=headers)
        with pytest.raises(urllib.error.HTTPError) as err:
            urllib.request.urlopen(req, timeout=10)
        assert err.value.code == code
    click(browser, "#drive-h1-axis1 button[data-op='fault_reset']")
    assert js(browser, "return document.getElementById('confirm').open;")
    assert "h1/axis1" in browser.find_element("id", "confirm-text").text
    assert "0x2310" in browser.find_element("id", "confirm-text").text  # the fault it would reset is named
    browser.find_element("id", "confirm-no").click()
    assert not js(browser, "return document.getElementById('confirm').open;")
    time.sleep(1.5)  # longer than the agent's status period: a command sent would be counted by now
    assert agent_count(fleet, "h1", "fault_reset.done") == before
    assert display(browser, "h1", "axis1") == "fault"

    click(browser, "#drive-h1-axis1 button[data-op='fault_reset']")
    browser.find_element("id", "confirm-yes").click()
    wait_for(lambda: browser.find_element("id", "cmd-result").get_attribute("data-outcome") in ("ok", "failed", "error"),
             15, "the command's answer on the page")
    assert browser.find_element("id", "cmd-result").get_attribute("data-outcome") == "ok", \
        browser.find_element("id", "cmd-result").text
    wait_for(lambda: display(browser, "h1", "axis1") == "disabled", 10, "the reset drive on the page")
    # a host's buttons address all its drives, asked about the same way
    click(browser, "#host-h2 .host-commands button[data-op='quick_stop']")
    assert "h2/*" in browser.find_element("id", "confirm-text").text
    browser.find_element("id", "confirm-no").click()
    wait_for(lambda: agent_count(fleet, "h1", "fault_reset.done") == before + 1, 5, "the agent's count of resets")


def test_drive_plot_places_statuses_at_the_agents_time_stamps(bed: dict[str, Any], browser: Any) -> None:
    fleet: Fleet = bed["fleet"]
    stamps: set[float] = set()
    fleet.on("status", lambda st: stamps.add(st.time_ns / 1e6) if (st.host, st.axis) == ("h1", "axis0") else None)
    st = fleet.status("h1/axis0")
    if st is not None and st.state == "fault":  # a host stall on this shared machine can trip the sim's heartbeat
        assert fleet.command("fault_reset", fleet.select("h1/axis0")).ok
    if st is None or st.state != "operation_enabled":
        res = fleet.command("enable", fleet.select("h1/axis0"))
        assert res.ok, res.to_dict()
    browser.get(bed["url"] + "/drive/h1/axis0")
    wait_for(lambda: js(browser, "return document.querySelectorAll('#commands button.cmd').length;") == 4, 10,
             "the drive's command buttons")
    time.sleep(1.2)  # a heartbeat at rest, then a move: publications close together, then far apart
    res = fleet.command("move", fleet.select("h1/axis0"), {"by": 20000.0, "velocity": 40000.0})
    assert res.ok, res.to_dict()
    time.sleep(1.5)

    def plotted() -> dict | None:
        p = js(browser, "const s = document.getElementById('live'); return s.plotted || null;")
        return p if p and len(p["ts"]) >= 8 else None

    try:
        p = wait_for(plotted, 20, "the live plot")
    except AssertionError:
        raise AssertionError((browser.get_log("browser"), js(browser, "const s = document.getElementById('live'); "
                              "return [s.dataset.samples, s.plotted && s.plotted.ts.length];")))
    ts, xs = p["ts"], p["xs"]
    # every sample drawn at its agent time stamp, on a linear time axis
    known = sorted(stamps)
    off = [t for t in ts if t >= known[0] and min(abs(t - k) for k in known) > 0.01]  # 10 us: float rounding
    assert not off, off[:5]
    for t, x in zip(ts, xs):
        assert abs(x - (p["left"] + (t - p["t0"]) / (p["t1"] - p["t0"]) * p["width"])) < 1e-6
    gaps = [b - a for a, b in zip(ts, ts[1:]) if b > a]
    assert max(gaps) > 3 * min(gaps), gaps  # uneven publications: an index axis would space them evenly
    ticks = js(browser, "return Array.from(document.querySelectorAll('#live text.tick')).map((e) => "
                        "[+e.dataset.ms, e.textContent]);")
    assert ticks and all(p["t0"] <= ms <= p["t1"] for ms, _ in ticks), ticks
    # labelled with the agent's clock (UTC)
    assert all(label.startswith(time.strftime("%H:%M:%S", time.gmtime(ms // 1000))) for ms, label in ticks), ticks


def test_recording_viewer_shows_the_fault_window(bed: dict[str, Any], browser: Any) -> None:
    fleet: Fleet = bed["fleet"]
    sim_inject(fleet.session, "h1", 1, "fault", error_code=0x2310)

    def fault_window() -> bool:
        browser.get(bed["url"] + "/recording/h1?what=fault&axis=axis1")
        wait_for(lambda: browser.find_element("id", "rec-info").get_attribute("data-state") in ("shown", "error"), 30,
                 "the recording's answer")
        return browser.find_element("id", "rec-info").get_attribute("data-state") == "shown"

    wait_for(fault_window, 20, "a frozen fault window", poll_s=1.0)
    info = browser.find_element("id", "rec-info")
    # the latest fault window (axis1's, or a later one: axis1 stays in fault, so it shows in either)
    assert info.get_attribute("data-reason") == "fault" and "cycles of 1000 us" in info.text, info.text
    svg = browser.find_element("id", "recording")
    assert int(svg.get_attribute("data-samples")) >= 1000  # cycles, not status publications
    labels = js(browser, "return Array.from(document.querySelectorAll('#recording rect.run')).map((r) => r.dataset.label);")
    assert "fault" in labels, labels
    assert js(browser, "return getComputedStyle(document.querySelector(\"#recording rect.run[data-label='fault']\"))"
                       ".fill;") == "rgb(198, 40, 40)"  # the fault colour of the fleet page
    assert js(browser, "return document.querySelectorAll('#recording line.marker').length;") == 1
    assert js(browser, "return Array.from(document.getElementById('axis').options).map((o) => o.value);") == \
        ["axis0", "axis1"]
    assert browser.find_element("id", "axis").get_attribute("value") == "axis1"


def test_banner_names_a_host_name_conflict(bed: dict[str, Any], browser: Any) -> None:
    browser.get(bed["url"] + "/")
    wait_for(lambda: display(browser, "h1", "axis0") is not None, 20, "the fleet page")
    assert not any(kind == "conflict" for kind, _ in banner(browser))
    # A second agent instance calling itself h2, as the wire shows one: its agent status under
    # h2's own certificate with another instance id (a real second agent is refused at start-up
    # since the host-name check works in every session mode: tests/system/test_host_claim.py).
    stop = threading.Event()

    def second_instance() -> None:
        conf = zenoh_config("client", [bed["ep"]], pki=str(bed["pki"]), identity="h2")
        with zenoh.open(conf) as s:
            seq = 0
            while not stop.is_set():
                seq += 1
                s.put(keys.agent_status("h2"), m.encode(m.AgentStatus(
                    host="h2", seq=seq, time_ns=time.time_ns(), state="running", backend="sim", cycle_us=1000,
                    cycles=seq, period_p50_us=1000.0, period_p99_us=1000.0, period_max_us=1000.0, overruns=0,
                    wkc_errors=0, expected_wkc=3, instance="second-h2")))
                stop.wait(0.3)
    t = threading.Thread(target=second_instance, daemon=True)
    t.start()
    try:
        wait_for(lambda: ("conflict", "h2") in banner(browser), 15, "the conflict in the banner")
        sec = browser.find_element("id", "host-h2")
        assert "conflict" in sec.get_attribute("class")
        assert "host-name conflict" in sec.find_element("css selector", ".conflict").text
    finally:
        stop.set()
        t.join(10)
    wait_for(lambda: ("conflict", "h2") not in banner(browser), 15, "the conflict gone from the banner")
