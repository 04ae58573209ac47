"""canopen-sim running drives from EDS files, checked over real CAN frames between processes
(python-can udp_multicast in a namespace of their own: tests/system/canbed.py).

The files are the project's own: the EDS ``canopen-sim --write-eds`` writes and the hand-written
ones of tests/data/eds/ (each exercising quirks of vendors' files). A plain python-canopen probe
(its own ``RemoteNode`` per node, the object dictionary imported from the same file, nothing of
this project) reads every object the EDS lists and compares it with the EDS default, reads each
node's PDO configuration by SDO and compares it with the EDS default mapping, receives TPDOs on a
SYNC and decodes them with the EDS's mapping, sends an RPDO with a vendor object; ``bus-agent scan
--eds`` then names each node's EDS and the one PDO that no longer is its default. Then the agent:
``[[can.nodes]] eds`` with PDO policy ``eds`` and a vendor object named in ``objects``, and a
node whose identity is not its EDS's refused at start-up.
"""

from __future__ import annotations

import json
import sys
from pathlib import Path
from typing import Iterator

import pytest

from bus_agent.sim.child import free_port
from supervisor.fleet import Fleet
from tests.conftest import require_root
from tests.system.canbed import CHANNEL, CanBed

pytestmark = [pytest.mark.root]

DATA = Path(__file__).resolve().parents[1] / "data" / "eds"
CLASSIC, VENDOR = DATA / "classic.eds", DATA / "vendor.eds"

#: The plain python-canopen probe: argv = channel, then node:file pairs. Prints one JSON line.
PROBE = r"""
import json, sys, time
import canopen
from canopen.sdo import SdoAbortedError

# objects whose value the drive computes (the EDS default is its power-on value at best)
COMPUTED = {(0x1001, 0), (0x1018, 4), (0x603F, 0), (0x6041, 0), (0x6061, 0), (0x6064, 0), (0x606C, 0), (0x6077, 0),
            (0x60F4, 0), (0x60FD, 0), (0x60B9, 0), (0x60BA, 0), (0x60BC, 0), (0x6502, 0)}

def variables(od):
    for obj in od.values():
        if isinstance(obj, canopen.objectdictionary.ODVariable):
            yield obj
        else:
            yield from obj.subindices.values()

def pdos(maps):
    return {n: [m.cob_id, m.enabled, m.trans_type, [[v.index, v.subindex, v.length] for v in m]]
            for n, m in maps.items()}

net = canopen.Network()
net.connect(interface="udp_multicast", channel=sys.argv[1], fd=False)
report = {}
for spec in sys.argv[2:]:
    nid, path = spec.split(":", 1)
    nid = int(nid)
    with open(path, encoding="latin-1") as f:          # python-canopen opens with the locale's encoding
        node = canopen.RemoteNode(nid, canopen.import_od(f, nid))
    net.add_node(node)
    r = report[nid] = {"checked": 0, "differs": [], "absent": None}
    for var in variables(node.object_dictionary):
        if var.default is None or (var.index, var.subindex) in COMPUTED:
            continue
        raw = node.sdo.upload(var.index, var.subindex)
        value = var.decode_raw(raw)
        r["checked"] += 1
        if value != var.default:
            r["differs"].append([hex(var.index), var.subindex, repr(value), repr(var.default)])
    try:
        node.sdo.upload(0x2FFF, 0)                       # in no test EDS
    except SdoAbortedError as e:
        r["absent"] = e.code
    node.tpdo.read(from_od=True); node.rpdo.read(from_od=True)
    r["eds_pdos"] = [pdos(node.rpdo.map), pdos(node.tpdo.map)]
    node.tpdo.read(); node.rpdo.read()                  # by SDO: what the node has
    r["node_pdos"] = [pdos(node.rpdo.map), pdos(node.tpdo.map)]

for nid, node in net.nodes.items():
    node.nmt.state = "OPERATIONAL"
time.sleep(0.2)
for attempt in range(20):                              # TPDOs answer a SYNC
    net.sync.transmit()
    time.sleep(0.05)
    if all(node.tpdo[1].timestamp for node in net.nodes.values()):
        break
for nid, node in net.nodes.items():
    report[nid]["tpdo1"] = [[v.index, v.subindex, v.raw] for v in node.tpdo[1]] if node.tpdo[1].timestamp else None

# the vendor node: RPDO1 (6040 + a vendor object) is disabled by default; enable and use it
vendor = int(sys.argv[-1].split(":")[0])
node = net.nodes[vendor]
node.nmt.state = "PRE-OPERATIONAL"
time.sleep(0.1)
rpdo = node.rpdo[1]
rpdo.read()
rpdo.enabled = True
rpdo.save()
node.nmt.state = "OPERATIONAL"
time.sleep(0.1)
rpdo["Brake release delay"].raw = 700
rpdo["Controlword"].raw = 0x0006
rpdo.transmit()                                        # event-driven (255): applied on receipt
time.sleep(0.2)
net.sync.transmit()
time.sleep(0.2)
report["rpdo"] = {"delay": node.sdo.upload(0x2100, 0).hex(), "statusword": node.sdo.upload(0x6041, 0).hex()}
for node in net.nodes.values():
    node.nmt.state = "PRE-OPERATIONAL"
net.disconnect()
print(json.dumps(report), flush=True)
"""


@pytest.fixture(scope="module")
def sim_eds(tmp_path_factory: pytest.TempPathFactory) -> Path:
    from bus_agent.sim.canopen import cli

    path = tmp_path_factory.mktemp("eds") / "sim.eds"
    assert cli.main(["--write-eds", str(path)]) == 0
    return path


@pytest.fixture()
def bed() -> Iterator[CanBed]:
    require_root()
    b = CanBed("e")
    try:
        yield b
    finally:
        b.close()


def test_python_canopen_probe_sees_each_node_as_its_eds_says(bed: CanBed, sim_eds: Path) -> None:
    bed.module("canopen-sim", "bus_agent.sim.canopen.cli", "--channel", CHANNEL, "--interface", "udp_multicast",
               "--eds", f"{CLASSIC}*2", "--eds", str(sim_eds), "--eds", str(VENDOR), ready="canopen-sim ready")
    r = bed.run(sys.executable, "-c", PROBE, CHANNEL, f"1:{CLASSIC}", f"2:{CLASSIC}", f"3:{sim_eds}", f"4:{VENDOR}",
                timeout_s=120)
    assert r.returncode == 0, r.stderr[-3000:]
    report = json.loads(r.stdout.strip().splitlines()[-1])
    for nid in ("1", "2", "3", "4"):
        node = report[nid]
        assert node["differs"] == [], (nid, node["differs"])          # every default as the EDS says
        assert node["checked"] >= 20 and node["absent"] == 0x06020000, node
        assert node["node_pdos"] == node["eds_pdos"], nid             # the default mapping, read by SDO
    assert report["1"]["checked"] == report["2"]["checked"] and report["3"]["checked"] > 100
    assert report["2"]["node_pdos"][1]["1"][0] == 0x182                # $NODEID resolved per node
    assert report["2"]["node_pdos"][0]["2"][:2] == [0x302, False]      # "$NODEID + 0x80000300": disabled
    # TPDO1 as python-canopen decodes it with the EDS's mapping (statusword: switch on disabled)
    (sw1,), (sw4, temperature) = report["1"]["tpdo1"], report["4"]["tpdo1"]
    assert sw1[:2] == [0x6041, 0] and sw1[2] & 0x4F == 0x40
    sw, pos, mode = report["3"]["tpdo1"]
    assert (sw[:2], pos[:2], mode[:2]) == ([0x6041, 0], [0x6064, 0], [0x6061, 0]) and sw[2] & 0x4F == 0x40
    assert sw4[:2] == [0x6041, 0] and sw4[2] & 0x4F == 0x40 and temperature == [0x2101, 0, 25]  # vendor object
    # RPDO1 enabled by the probe: the vendor object stored, the controlword applied (ready to switch on)
    assert bytes.fromhex(report["rpdo"]["delay"]) == (700).to_bytes(2, "little")
    assert int.from_bytes(bytes.fromhex(report["rpdo"]["statusword"]), "little") & 0x6F == 0x21
    # bus-agent scan --eds DIR: each node's EDS by identity, node 4's RPDO1 (enabled above) not its default
    r = bed.run(sys.executable, "-m", "bus_agent.cli", "scan", "--can", CHANNEL, "--can-interface", "udp_multicast",
                "--eds", str(DATA), "--json", timeout_s=60)
    assert r.returncode == 0, r.stderr[-2000:]
    nodes = {n["node_id"]: n for n in json.loads(r.stdout)["nodes"]}
    assert [(nodes[i]["eds"], nodes[i]["device"]) for i in (1, 2, 3, 4)] == [
        (str(CLASSIC), "Classic402"), (str(CLASSIC), "Classic402"), ("", ""), (str(VENDOR), "Vendor402")]
    assert nodes[1]["differences"] == [] and nodes[4]["differences"] == ["RPDO1: node 0x204 [6040 2100], EDS not valid"]


def _agent_toml(listen: str, nodes: str) -> str:
    return f"""
host = "ce"
cycle_us = 10000
[zenoh]
listen = ["{listen}"]
[can]
channel = "{CHANNEL}"
interface = "udp_multicast"
nodes = [{nodes}]
"""


def test_agent_runs_nodes_by_their_eds_and_refuses_a_wrong_identity(bed: CanBed, tmp_path: Path) -> None:
    bed.module("canopen-sim", "bus_agent.sim.canopen.cli", "--channel", CHANNEL, "--interface", "udp_multicast",
               "--eds", str(CLASSIC), "--eds", str(VENDOR), ready="canopen-sim ready")
    wrong = tmp_path / "wrong.toml"
    wrong.write_text(_agent_toml(f"tcp/127.0.0.1:{free_port()}", f'{{ id = 1, eds = "{VENDOR}", pdo = "eds" }}'))
    r = bed.run(sys.executable, "-m", "bus_agent.cli", "--config", str(wrong), timeout_s=60)
    assert r.returncode != 0
    assert (f"node 1 (position 0, 'Classic402') is not the device of its EDS {VENDOR} (Vendor402): vendor id "
            "0x00001234, the EDS says 0x12345678; product code 0x00000402, the EDS says 0x00000007") in r.stderr, \
        r.stderr[-2000:]
    tcp, unix = f"tcp/127.0.0.1:{free_port()}", bed.unix_endpoint("agent")
    cfg = tmp_path / "agent.toml"
    cfg.write_text(_agent_toml(tcp, f'{{ id = 1, eds = "{CLASSIC}", pdo = "eds" }}, '
                               f'{{ id = 2, eds = "{VENDOR}", pdo = "explicit", rpdo = [[0x60400010]], '
                               f'tpdo = [[0x60410010, 0x21010010]] }}').replace("listen = [", f'listen = ["{unix}", '))
    agent = bed.module("agent ce", "bus_agent.cli", "--config", str(cfg), ready="bus-agent ready", timeout_s=60)
    assert "node 1: configured, PDO policy eds: RxPDO 0x1600@0x201 [6040], TxPDO 0x1A00@0x181 [6041]" in agent.output(300)
    with Fleet(connect=[unix], name="edstest") as fleet:
        assert fleet.wait_for_agents(["ce"], 20, drives=2)
        rc, out = bed.drivectl(tcp, "enable", "ce/*")
        assert rc == 0, out
        rows = bed.states(tcp)
        assert [rows[a]["state"] for a in ("ce/axis0", "ce/axis1")] == ["operation_enabled"] * 2, rows
        st = next(iter(fleet.fetch_status("ce/axis1").values()))
        assert st.objects == {"Temperature (°C)": 25}                # named and typed by the EDS
        rc, out = bed.drivectl(tcp, "disable", "ce/*")
        assert rc == 0, out
