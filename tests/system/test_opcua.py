"""drives-opcua against a real secure fleet, through an independent client (node-opcua).

One bed for the module (tests/system/opcuabed.py): router, agent h1 on 2 simulated drives,
drives-opcua, each its own process; every check is made by a node-opcua client process. Each
denial has its granted counterpart beside it, so a test cannot pass because nothing works.
"""

from __future__ import annotations

import shutil
from typing import Any, Iterator

import pytest

from bus_agent.sim.control import sim_inject
from bus_agent.gateway.zenoh_config import make_zenoh_config
from tests.conftest import require
from tests.system.opcuabed import OpcuaBed, client_modules, wait


pytestmark = [pytest.mark.timeout(240), pytest.mark.slow]


@pytest.fixture(scope="module")
def bed(tmp_path_factory: pytest.TempPathFactory) -> Iterator[OpcuaBed]:
    require(bool(shutil.which("node") and shutil.which("npm")), "node and npm (Node 20)",
            "apt-get install nodejs npm (deploy/apt-packages.txt)")
    require(client_modules() is not None, "node-opcua-client", "make venv (installs it into .venv/opcua-client)")
    b = OpcuaBed(tmp_path_factory.mktemp("opcua"))
    try:
        yield b
    finally:
        b.close()


def ns(answer: dict[str, Any]) -> int:
    return answer["namespaces"].index("urn:zenoh-drives")


def nid(idx: int, path: str) -> str:
    return f"ns={idx};s={path}"


def call(c, idx: int, drive: str, method: str, args: list[dict[str, Any]] | None = None) -> dict[str, Any]:
    return c.request("call", objectId=nid(idx, f"Drives/{drive}"), methodId=nid(idx, f"DriveType/{method}"),
                     args=args or [])


def _fault_free_disabled(bed: OpcuaBed) -> None:
    """h1's drives out of fault and disabled, by maintenance (mia) over OPC UA."""
    c, idx = bed.maintenance()
    for axis in ("axis0", "axis1"):
        if c.request("read", nodeId=nid(idx, f"Drives/h1/{axis}/State"))["value"] in ("fault", "fault_reaction_active"):
            assert call(c, idx, f"h1/{axis}", "FaultReset")["outputs"][0] == "done"
        assert call(c, idx, f"h1/{axis}", "Disable")["outputs"][0] == "done"


def test_anonymous_browses_reads_and_cannot_call(bed: OpcuaBed) -> None:
    c, a = bed.client()
    assert a["ok"], a
    idx = ns(a)
    hosts = {r["name"] for r in c.request("browse", nodeId=nid(idx, "Drives"))["refs"]}
    assert {"h1", "h9"} <= hosts  # h9: expected by --fleet, never seen
    drive = {r["name"] for r in c.request("browse", nodeId=nid(idx, "Drives/h1/axis0"))["refs"]}
    assert {"State", "Goal", "Statusword", "Position", "Velocity", "Torque", "ErrorCode", "ErrorText", "Lost",
            "AlState", "AxisState", "Homed", "LeaseHolder", "Enable", "Disable", "Shutdown", "QuickStop", "Halt",
            "FaultReset", "Stop", "MoveAbsolute"} <= drive
    state = c.request("read", nodeId=nid(idx, "Drives/h1/axis0/State"))
    assert state["status"] == "Good" and state["dataType"] == "String"
    assert state["value"] in ("switch_on_disabled", "operation_enabled", "ready_to_switch_on", "fault")
    code = c.request("read", nodeId=nid(idx, "Drives/h1/axis0/ErrorCode"))
    assert code["dataType"] == "UInt16"
    lost = c.request("read", nodeId=nid(idx, "Drives/h1/axis0/Lost"))
    assert (lost["dataType"], lost["value"]) == ("Boolean", False)
    assert c.request("read", nodeId=nid(idx, "Drives/h1/Alive"))["value"] is True
    assert c.request("read", nodeId=nid(idx, "Drives/h1/CycleP99us"))["value"] > 0
    offline = c.request("read", nodeId=nid(idx, "Drives/h9/AgentState"))
    assert offline["value"] == "offline"
    assert c.request("read", nodeId=nid(idx, "Drives/h9/axis0/State"))["status"] == "BadWaitingForInitialData"
    before = c.request("read", nodeId=nid(idx, "Drives/h1/axis0/Goal"))["value"]
    sent = bed.agent.output(5000).count("from opcua")
    denied = call(c, idx, "h1/axis0", "Enable")
    assert not denied["ok"] and "BadUserAccessDenied" in denied["error"], denied
    assert bed.agent.output(5000).count("from opcua") == sent  # nothing reached the agent
    assert c.request("read", nodeId=nid(idx, "Drives/h1/axis0/Goal"))["value"] == before
    c.request("close")


def test_operator_enables_subscriber_sees_it_and_audit_names_the_user(bed: OpcuaBed) -> None:
    _fault_free_disabled(bed)
    watcher, a = bed.client()
    idx = ns(a)
    state_id = nid(idx, "Drives/h1/axis0/State")
    watcher.request("subscribe", nodeIds=[state_id])
    watcher.wait_note(lambda n: n["nodeId"] == state_id and n["value"] == "switch_on_disabled")
    viewer, _ = bed.client(user=bed.password("vic"))
    refused = call(viewer, idx, "h1/axis0", "Enable")
    assert refused["status"] == "BadUserAccessDenied" and refused["outputs"][0] == "denied", refused
    assert "vic (viewer) may not enable" in refused["outputs"][1]
    op, _ = bed.client(user=bed.password("olga"))
    res = call(op, idx, "h1/axis0", "Enable")
    assert res["status"] == "Good" and res["outputs"] == ["done", ""], res
    note = watcher.wait_note(lambda n: n["nodeId"] == state_id and n["value"] == "operation_enabled")
    assert note["status"] == "Good"
    assert wait(lambda: "opcua for olga" in bed.agent.output(400)), bed.agent.output(40)
    assert "for vic" not in bed.agent.output(400)  # the viewer's call never left the server
    assert call(op, idx, "h1/axis0", "Disable")["outputs"][0] == "done"
    for c in (watcher, viewer, op):
        c.request("close")


def test_fault_raises_an_event_and_maintenance_resets_it(bed: OpcuaBed) -> None:
    _fault_free_disabled(bed)
    c, a = bed.client(user=bed.password("olga"))
    idx = ns(a)
    c.request("events")
    import zenoh

    with zenoh.open(make_zenoh_config("client", [], [bed.zenoh_ep], pki=bed.pki, identity="tb")) as s:
        sim_inject(s, "h1", 1, "fault", error_code=0x7500)
    ev = c.wait_note(lambda n: n.get("kind") == "event" and n.get("SourceName") == "h1/axis1"
                     and "fault" in (n.get("Message") or ""))
    assert ev["Severity"] == 800 and "0x7500" in ev["Message"], ev
    assert c.request("read", nodeId=nid(idx, "Drives/h1/axis1/ErrorCode"))["value"] == 0x7500
    # An operator may not reset faults; maintenance may.
    refused = call(c, idx, "h1/axis1", "FaultReset")
    assert refused["status"] == "BadUserAccessDenied", refused
    m, _ = bed.maintenance()
    assert call(m, idx, "h1/axis1", "FaultReset")["outputs"][0] == "done"
    c.wait_note(lambda n: n.get("kind") == "event" and n.get("SourceName") == "h1/axis1"
                and "left fault" in (n.get("Message") or ""))
    c.request("close")


def test_lost_drive_raises_an_event_and_its_return_another(bed: OpcuaBed) -> None:
    c, a = bed.client()
    idx = ns(a)
    c.request("events")
    import zenoh

    with zenoh.open(make_zenoh_config("client", [], [bed.zenoh_ep], pki=bed.pki, identity="tb")) as s:
        sim_inject(s, "h1", 0, "unplug")
        try:
            ev = c.wait_note(lambda n: n.get("kind") == "event" and n.get("SourceName") == "h1/axis0"
                             and " lost" in (n.get("Message") or ""), 15)
            assert ev["Severity"] == 900, ev
            assert c.request("read", nodeId=nid(idx, "Drives/h1/axis0/Lost"))["value"] is True
        finally:
            sim_inject(s, "h1", 0, "plug")
    back = c.wait_note(lambda n: n.get("kind") == "event" and n.get("SourceName") == "h1/axis0"
                       and "answers again" in (n.get("Message") or ""), 30)
    assert back["Severity"] == 400
    c.request("close")


def test_bad_arguments_get_a_bad_status_and_nothing_is_sent(bed: OpcuaBed) -> None:
    c, a = bed.client(user=bed.password("olga"))
    idx = ns(a)
    sent = bed.agent.output(1000).count("move")
    wrong_type = call(c, idx, "h1/axis0", "MoveAbsolute", [{"dataType": "String", "value": "far"},
                                                           {"dataType": "Double", "value": 10.0}])
    assert wrong_type["status"] == "BadTypeMismatch", wrong_type
    assert wrong_type["outputs"][0] == "rejected" and "Position" in wrong_type["outputs"][1]
    assert wrong_type["inputResults"][0] == "BadTypeMismatch"
    out_of_range = call(c, idx, "h1/axis0", "MoveAbsolute", [{"dataType": "Double", "value": 1.0},
                                                             {"dataType": "Double", "value": -5.0}])
    assert out_of_range["status"] == "BadOutOfRange" and "Velocity" in out_of_range["outputs"][1], out_of_range
    missing = call(c, idx, "h1/axis0", "MoveAbsolute", [{"dataType": "Double", "value": 1.0}])
    assert missing["status"] == "BadArgumentsMissing", missing
    assert bed.agent.output(1000).count("move") == sent  # nothing reached the agent
    # The same method with good arguments moves the drive (the positive control).
    _fault_free_disabled(bed)
    assert call(c, idx, "h1/axis0", "Enable")["outputs"][0] == "done"
    start = c.request("read", nodeId=nid(idx, "Drives/h1/axis0/Position"))["value"]
    moved = call(c, idx, "h1/axis0", "MoveAbsolute", [{"dataType": "Double", "value": 2.0},
                                                      {"dataType": "Double", "value": 5.0}])
    assert moved["status"] == "Good" and moved["outputs"] == ["done", ""], moved
    assert wait(lambda: c.request("read", nodeId=nid(idx, "Drives/h1/axis0/Position"))["value"] != start)
    assert "op move from opcua for olga" in bed.agent.output(1000)
    assert call(c, idx, "h1/axis0", "Disable")["outputs"][0] == "done"
    c.request("close")


def test_certificate_user_on_the_secure_endpoint_and_unknown_clients_refused(bed: OpcuaBed) -> None:
    _fault_free_disabled(bed)
    c, a = bed.client(user=bed.certificate("carl"), secure=True)
    assert a["ok"], a
    idx = ns(a)
    res = call(c, idx, "h1/axis1", "Enable")
    assert res["outputs"] == ["done", ""], res
    assert wait(lambda: "opcua for carl" in bed.agent.output(400))
    assert call(c, idx, "h1/axis1", "Disable")["outputs"][0] == "done"
    c.request("close")
    # A password user on the secure endpoint too.
    olga, a = bed.client(user=bed.password("olga"), secure=True)
    assert a["ok"], a
    assert call(olga, idx, "h1/axis1", "QuickStop")["status"] == "Good"
    assert call(olga, idx, "h1/axis1", "Disable")["outputs"][0] == "done"
    olga.request("close")
    # A user certificate over SecurityPolicy None (the token signed for Basic256Sha256), of an
    # operator whose principal is scoped to h9: h1's drives are not hers.
    dora, a = bed.client(user=bed.certificate("dora"))
    assert a["ok"], a
    scoped = call(dora, idx, "h1/axis1", "Enable")
    assert scoped["status"] == "BadUserAccessDenied" and "commands only h9" in scoped["outputs"][1], scoped
    dora.request("close")
    # The same application name, but a certificate of another CA: refused at session creation.
    # asyncua drops the refused channel's request unanswered: the client ends at its own timeout.
    stranger, refused = bed.client(secure=True, ca=bed.other, transactionTimeout=4000)
    assert not refused["ok"], refused
    assert wait(lambda: "secure channel refused" in bed.server.output(400)), bed.server.output(20)
    assert "not issued by" in bed.server.output(400)
