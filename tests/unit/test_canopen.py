"""The CANopen backend's pure parts and the simulated node, without a bus: NMT table (seed 001),
heartbeat consumer, PDO mapping and frames on the shared codec, EMCY texts, the SYNC counter, PDO policies against a simulated node,
the node's NMT/SYNC/SDO behaviour, and the [can] configuration."""

from __future__ import annotations

import struct

import pytest
from canopen.sdo import SdoAbortedError

from bus_agent.bus.base import ALState
from bus_agent.bus.canopen import emcy, pdo
from bus_agent.bus.canopen.heartbeat import HeartbeatConsumer
from bus_agent.bus.canopen.nmt import (AL_OF_NMT, NMT_FOR_AL, NmtCommand, NmtState, after_command, decode_command,
                                       decode_heartbeat, nmt_frame)
from bus_agent.bus.mapping import MappingError, SlaveMapping, describe, pdo_spans
from bus_agent.bus.pdo import DriveInputs, DriveOutputs, mapping_entry
from bus_agent.cli import _parser, build_config
from bus_agent.config import ConfigError, config_from_dict
from bus_agent.sim.canopen.node import SimNode
from bus_agent.sim.drive_model import PROFILES
from schemas.error_codes import describe as describe_error

S, C = NmtState, NmtCommand


# ---- NMT (seed 001: states, commands, frame) ---------------------------------------------------

@pytest.mark.parametrize("state,command,after", [
    (S.PRE_OPERATIONAL, C.START, S.OPERATIONAL),
    (S.OPERATIONAL, C.STOP, S.STOPPED),
    (S.STOPPED, C.ENTER_PRE_OPERATIONAL, S.PRE_OPERATIONAL),
    (S.PRE_OPERATIONAL, C.STOP, S.STOPPED),
    (S.OPERATIONAL, C.ENTER_PRE_OPERATIONAL, S.PRE_OPERATIONAL),
    (S.STOPPED, C.START, S.OPERATIONAL),
    *((s, c, S.INITIALISING) for s in (S.PRE_OPERATIONAL, S.OPERATIONAL, S.STOPPED)
      for c in (C.RESET_NODE, C.RESET_COMMUNICATION)),
])
def test_nmt_transitions_of_the_seed(state: NmtState, command: NmtCommand, after: NmtState) -> None:
    assert after_command(state, command) is after


def test_nmt_frame_bytes_and_decoding() -> None:
    assert nmt_frame(C.START, 3) == b"\x01\x03"
    assert nmt_frame(C.STOP, 0) == b"\x02\x00"
    assert nmt_frame(C.ENTER_PRE_OPERATIONAL, 127) == b"\x80\x7f"
    assert nmt_frame(C.RESET_NODE, 1) == b"\x81\x01" and nmt_frame(C.RESET_COMMUNICATION, 1) == b"\x82\x01"
    with pytest.raises(ValueError):
        nmt_frame(C.START, 128)
    assert decode_command(b"\x01\x05") == (C.START, 5)
    assert decode_command(b"\x55\x05") == (None, 5)
    with pytest.raises(ValueError):
        decode_command(b"\x01")


def test_heartbeat_states_decode_with_toggle_bit_and_unknown() -> None:
    assert decode_heartbeat(b"\x85") is S.OPERATIONAL
    assert decode_heartbeat(b"\x7f") is S.PRE_OPERATIONAL
    assert decode_heartbeat(b"\x04") is S.STOPPED
    assert decode_heartbeat(b"\x33") is S.UNKNOWN and decode_heartbeat(b"") is S.UNKNOWN


def test_nmt_and_al_mappings_are_inverse_where_both_exist() -> None:
    for al, command in NMT_FOR_AL.items():
        if command is not C.RESET_COMMUNICATION:
            assert AL_OF_NMT[after_command(S.PRE_OPERATIONAL if al is not ALState.PREOP else S.OPERATIONAL,
                                           command)] is al
    assert AL_OF_NMT[S.UNKNOWN] is ALState.NONE


def test_heartbeat_consumer_silence_and_boot_up() -> None:
    hb = HeartbeatConsumer((1, 2), timeout_s=0.3)
    assert hb.state(1, 0.0) is S.UNKNOWN
    hb.on_frame(1, b"\x05", 1.0)
    assert hb.state(1, 1.2) is S.OPERATIONAL and hb.state(1, 1.31) is S.UNKNOWN
    hb.on_frame(1, b"\x00", 2.0)            # boot-up: lost its communication parameters
    hb.on_frame(1, b"\x7f", 2.1)
    assert hb.state(1, 2.1) is S.INITIALISING and hb.booted(1) and hb.boots(1) == 1
    hb.configured(1)
    assert hb.state(1, 2.1) is S.PRE_OPERATIONAL
    hb.on_frame(9, b"\x05", 2.0)            # not ours: ignored
    assert hb.state(2, 2.0) is S.UNKNOWN


# ---- PDO mapping and frames (the shared SlaveMapping and DriveCodec) -----------------------------

def _map(rpdos, tpdos, node_id: int = 1) -> SlaveMapping:
    """A mapping of PDO 1..n from (index, subindex, bits) triples."""
    return pdo.pdos_mapping(node_id, [[mapping_entry(*e) for e in p] for p in rpdos],
                            [[mapping_entry(*e) for e in p] for p in tpdos])


def test_default_mapping_fits_frames_and_round_trips() -> None:
    mp = pdo.default_mapping(5)
    assert dict(mp.cob_ids) == {0x1600: 0x205, 0x1601: 0x305, 0x1A00: 0x185, 0x1A01: 0x285}
    assert pdo_spans(mp.rx) == ((0x1600, 0, 7), (0x1601, 7, 6)) and pdo_spans(mp.tx) == ((0x1A00, 0, 7), (0x1A01, 7, 8))
    frames = pdo.PdoFrames(mp)
    assert frames.tpdo_cob_ids == (0x185, 0x285) and frames.rpdo_cob_ids == (0x205, 0x305)
    out = DriveOutputs(controlword=0x000F, target_position=-123456, target_velocity=789, target_torque=-5,
                       modes_of_operation=8)
    sent = frames.rpdo_frames(out)
    assert sent == [(0x205, struct.pack("<Hib", 0x000F, -123456, 8)), (0x305, struct.pack("<ih", 789, -5))]
    node = _node(5)                                                  # the device side reads them back
    node.on_frame(0x000, nmt_frame(C.START, 5), 0.0)
    for cob, data in sent:
        node.on_frame(cob, data, 0.0)
    assert node._pending == {(0x6040, 0): 0x000F, (0x607A, 0): -123456, (0x6060, 0): 8, (0x60FF, 0): 789,
                             (0x6071, 0): -5}
    inputs = DriveInputs()
    assert frames.store_tpdo(0x185, struct.pack("<HiB", 0x1637, -42, 8))
    assert frames.store_tpdo(0x285, struct.pack("<ihH", 1000, -7, 0x8611))
    frames.decode_into(inputs)
    assert inputs == DriveInputs(0x1637, -42, 1000, -7, 8, 0x8611)
    assert not frames.store_tpdo(0x186, b"\0" * 8)                  # another node's
    assert not frames.store_tpdo(0x185, b"\0\0")                    # too short: nothing changes
    assert not frames.store_tpdo(0x185, struct.pack("<HiB", 0x1637, -42, 8))  # the same again: at rest
    assert frames.store_tpdo(0x185, struct.pack("<HiB", 0x1637, -41, 8))      # changed
    frames.decode_into(inputs)
    assert inputs.statusword == 0x1637 and inputs.position_actual == -41
    assert frames.codec.absent_inputs == () and frames.codec.extra_names == ()


def test_a_pdo_ends_on_a_byte_and_objects_outside_the_cycle_are_carried_as_on_ethercat() -> None:
    # TPDO1: statusword + a 4-bit manufacturer object (padded to 3 bytes); TPDO2: position, digital inputs
    mp = _map([[(0x6040, 0, 16), (0x60B8, 0, 16)]], [[(0x6041, 0, 16), (0x2001, 0, 4)], [(0x6064, 0, 32), (0x60FD, 0, 32)]])
    assert pdo_spans(mp.tx) == ((0x1A00, 0, 3), (0x1A01, 3, 8))
    frames = pdo.PdoFrames(mp)
    frames.store_tpdo(0x181, b"\x37\x02\x0f")
    frames.store_tpdo(0x281, struct.pack("<iI", -5, 0x00010000))
    inputs = DriveInputs()
    frames.decode_into(inputs)
    assert (inputs.statusword, inputs.position_actual, inputs.extra) == (0x0237, -5, (0x00010000,))
    assert frames.codec.extra_names == ("digital_inputs",)           # decoded by name, as on EtherCAT
    assert set(frames.codec.absent_inputs) == {"velocity", "torque", "mode_display", "error_code"}
    assert frames.rpdo_frames(DriveOutputs(controlword=6)) == [(0x201, struct.pack("<HH", 6, 0))]  # 0x60B8: 0
    assert "TxPDO 0x1A00@0x181 [6041 2001] 0x1A01@0x281 [6064 60FD]" in describe(mp)


@pytest.mark.parametrize("rpdos,tpdos,why", [
    ([[(0x6040, 0, 16), (0x607A, 0, 32), (0x60FF, 0, 32)]], [[(0x6041, 0, 16)]], "maps 80 bits, a CAN frame carries 64"),
    ([[(0x607A, 0, 32)]], [[(0x6041, 0, 16)]], "0x6040 .controlword. is not in the outputs"),
    ([[(0x6040, 0, 16)]], [[(0x6064, 0, 32)]], "0x6041 .statusword. is not in the inputs"),
    ([[(0x6040, 0, 16)], [(0x6040, 0, 16)]], [[(0x6041, 0, 16)]], "0x6040:00 is mapped twice in the RPDOs"),
])
def test_mappings_the_cycle_cannot_use_are_refused_with_the_reason(rpdos, tpdos, why) -> None:
    with pytest.raises(MappingError, match=why):
        pdo.PdoFrames(_map(rpdos, tpdos))
    node = _node(1)
    read, write = _sdo(node)
    with pytest.raises(MappingError, match=f"node 1: PDO policy 'explicit': .*{why}"):
        pdo.mapping_for("explicit", 1, read, write, _map(rpdos, tpdos))
    assert pdo.read_mapping(read) == pdo.default_mapping(1)         # refused before anything was written
    with pytest.raises(MappingError, match="5 RPDOs, the pre-defined connection set has RPDO 1..4"):
        _map([[(0x6040, 0, 16)]] * 5, [[(0x6041, 0, 16)]])


def test_emcy_decoding_and_texts_from_the_one_table() -> None:
    e = emcy.decode(3, emcy.encode(0x8130, 0x11))
    assert (e.node_id, e.error_code, e.error_register, e.reset) == (3, 0x8130, 0x11, False)
    assert e.text == "life guard error or heartbeat error" == describe_error(0x8130)
    assert emcy.decode(3, b"\x00\x00\x00").reset and emcy.decode(3, b"").text == "error reset or no error"
    assert emcy.error_text(0x2310) == "continuous over-current" and emcy.error_text(0x8611) == "following error"
    assert emcy.error_text(0x8240) == "unexpected SYNC data length"
    assert emcy.error_text(0x2399) == "current, device output side (0x2399)"      # unknown: its sub-class
    assert emcy.error_text(0x6A12) == "device software (0x6A12)"                  # unknown: its class
    assert emcy.error_text(0xFF42) == "manufacturer-specific error (0xFF42)"


# ---- the simulated node, and the PDO policies against it ------------------------------------------

def _node(node_id: int = 1) -> SimNode:
    return SimNode(node_id, PROFILES["generic"], serial=node_id)


def _sdo(node: SimNode):
    return (lambda i, s: node.get_data(i, s)), (lambda i, s, d: node.set_data(i, s, d))


def test_policy_drive_reads_the_default_mapping_the_node_powers_up_with() -> None:
    node = _node(4)
    read, write = _sdo(node)
    assert pdo.mapping_for("drive", 4, read, write) == pdo.default_mapping(4)
    with pytest.raises(MappingError, match="'node' is not one of drive, default, explicit"):
        pdo.mapping_for("node", 4, read, write)                      # the old word: only in TOML, translated


def test_policy_explicit_is_written_and_used_by_the_node() -> None:
    node = _node(2)
    read, write = _sdo(node)
    explicit = _map([[(0x6040, 0, 16), (0x6060, 0, 8)]], [[(0x6041, 0, 16), (0x603F, 0, 16), (0x6061, 0, 8)]], 2)
    assert pdo.mapping_for("explicit", 2, read, write, explicit) == explicit
    assert pdo.read_mapping(read) == explicit                      # read back from the node
    node.on_frame(0x000, nmt_frame(C.START, 2), 0.0)
    node.on_frame(0x202, struct.pack("<Hb", 0x0006, 8), 0.01)
    frames = node.on_frame(0x080, b"", 0.02)
    tpdos = [f for f in frames if 0x180 <= f[0] < 0x300]
    assert [cob for cob, _ in tpdos] == [0x182]                    # PDO 2 is invalid now
    sw, code, _mode = struct.unpack("<HHb", tpdos[0][1])            # 5 bytes, in the explicit order
    assert code == 0 and sw == node.model.statusword
    with pytest.raises(SdoAbortedError) as e:                      # operational: mapping locked
        pdo.mapping_for("default", 2, read, write)
    assert e.value.code == 0x08000022
    assert pdo.read_mapping(read) == explicit                      # nothing changed


def test_sync_counter_checked_by_the_node() -> None:
    node = _node(6)
    read, write = _sdo(node)
    for bad in (1, 241):
        with pytest.raises(SdoAbortedError) as e:
            write(0x1019, 0, bytes((bad,)))
        assert e.value.code == 0x06090030                          # reserved values
    write(0x1019, 0, b"\x03")
    node.on_frame(0x000, nmt_frame(C.START, 6), 0.0)
    t = 0.0
    for counter in (2, 3, 1, 2, 3, 1):                             # any start, then 1..3 in turn
        t += 0.01
        node.on_frame(0x080, bytes((counter,)), t)
    assert (node.counters["sync_counter_errors"], node.counters["sync_length_errors"]) == (0, 0)
    node.on_frame(0x080, b"\x03", t + 0.01)                         # 2 expected
    assert node.counters["sync_counter_errors"] == 1 and node.last_sync_counter == 3
    emcys = [f for k in range(3) for f in node.on_frame(0x080, b"", t + 0.02 + k / 100) if f[0] == 0x086]
    assert emcys == [(0x086, emcy.encode(0x8240, 0))]              # one EMCY for a run of wrong lengths
    assert node.counters["sync_length_errors"] == 3
    node.on_frame(0x000, nmt_frame(C.RESET_COMMUNICATION, 6), t + 0.1)
    assert read(0x1019, 0) == b"\x00"                              # reset: SYNC without data again
    node.on_frame(0x080, b"", t + 0.2)
    assert node.counters["sync_length_errors"] == 3


def test_pdo_configuration_is_refused_in_operational_and_needs_count_zero() -> None:
    node = _node(1)
    read, write = _sdo(node)
    with pytest.raises(SdoAbortedError) as e:
        write(0x1A00, 1, struct.pack("<I", mapping_entry(0x6041, 0, 16)))
    assert e.value.code == 0x06010000                              # sub 0 must be 0 first
    write(0x1A00, 0, b"\x00")
    with pytest.raises(SdoAbortedError) as e:
        write(0x1A00, 2, struct.pack("<I", mapping_entry(0x6065, 0, 32)))  # not PDO-mappable
    assert e.value.code == 0x06040041
    node.on_frame(0x000, nmt_frame(C.START, 1), 0.0)
    with pytest.raises(SdoAbortedError) as e:
        write(0x1A00, 0, b"\x01")
    assert e.value.code == 0x08000022


def test_node_nmt_reset_boots_with_defaults_and_leaving_operational_faults_an_enabled_drive() -> None:
    node = _node(7)
    read, write = _sdo(node)
    write(0x1017, 0, struct.pack("<H", 50))
    assert node.on_frame(0x000, nmt_frame(C.START, 7), 0.0)[-1] == (0x707, b"\x05")
    t = 0.0
    for cw in (0x06, 0x06, 0x06, 0x07, 0x07, 0x0F, 0x0F, 0x0F):
        t += 0.01
        node.on_frame(0x207, struct.pack("<HiB", cw, 0, 8), t)
        frames = node.on_frame(0x080, b"", t)
    sw = struct.unpack_from("<H", dict(frames)[0x187])[0]
    assert sw & 0x006F == 0x0027                                    # operation enabled
    frames = node.on_frame(0x000, nmt_frame(C.STOP, 0), t)          # broadcast stop
    assert node.state is S.STOPPED and (0x707, b"\x04") in frames
    frames = node.tick(t + 0.01)
    assert any(cob == 0x087 and struct.unpack_from("<H", d)[0] == 0x8130 for cob, d in frames) is False  # stopped: no EMCY
    assert node.model.error_code == 0x8130
    frames = node.on_frame(0x000, nmt_frame(C.RESET_COMMUNICATION, 7), t + 0.02)
    assert frames == [(0x707, b"\x00")] and node.state is S.PRE_OPERATIONAL
    assert struct.unpack("<H", read(0x1017, 0))[0] == 100          # communication objects back to defaults
    assert node.model.error_code == 0x8130                         # reset communication keeps the drive
    node.on_frame(0x000, nmt_frame(C.RESET_NODE, 7), t + 0.03)
    assert node.model.error_code == 0                              # reset node power-cycles it
    assert node.on_frame(0x000, nmt_frame(C.START, 8), t) == []     # another node's command


def test_node_sdo_identity_and_refusals() -> None:
    node = _node(3)
    read, write = _sdo(node)
    assert struct.unpack("<I", read(0x1018, 4))[0] == 3
    assert read(0x1008, 0) == b"SimDrive402"
    for index, sub, code in ((0x2000, 0, 0x06020000), (0x1018, 9, 0x06090011), (0x1C12, 0, 0x06020000)):
        with pytest.raises(SdoAbortedError) as e:
            read(index, sub)
        assert e.value.code == code
    with pytest.raises(SdoAbortedError) as e:
        write(0x6041, 0, b"\0\0")
    assert e.value.code == 0x06010002


# ---- configuration --------------------------------------------------------------------------------

def test_can_table_and_flags(caplog: pytest.LogCaptureFixture) -> None:
    cfg = config_from_dict({"host": "c1", "can": {"channel": "can0", "interface": "socketcan", "heartbeat_ms": 50,
                                                  "sync_counter": 240,
                                                  "nodes": [1, {"id": 2, "pdo": "node", "eds": "d.eds"},
                                                            {"id": 3, "pdo": "explicit",
                                                             "rpdo": [[0x60400010]], "tpdo": [[0x60410010]],
                                                             "sdo": [{"index": 0x605A, "value": 5, "size": 2}]}]}})
    assert cfg.backend == "canopen" and cfg.can is not None
    assert [n.node_id for n in cfg.can.nodes] == [1, 2, 3] and cfg.can.nodes[1].eds == "d.eds"
    assert cfg.can.nodes[2].startup_sdos == ((0x605A, 0, 5, 2),)
    assert [n.pdo for n in cfg.can.nodes] == ["default", "drive", "explicit"] and cfg.can.sync_counter == 240
    assert "can.nodes[1].pdo: 'node' is deprecated, say 'drive'" in caplog.text   # the old word, translated
    args = _parser().parse_args(["--can", "239.1.1.1", "--can-interface", "udp_multicast", "--nodes", "1,2,0x7f",
                                 "--host", "c2", "--sync-counter", "16"])
    flags = build_config(args)
    assert flags.can is not None and [n.node_id for n in flags.can.nodes] == [1, 2, 127]
    assert flags.can.sync_counter == 16
    assert flags.can.interface == "udp_multicast" and flags.backend == "canopen"


@pytest.mark.parametrize("can,why", [
    ({"channel": "c", "nodes": []}, "at least one node"),
    ({"channel": "c", "nodes": [1, 1]}, "listed twice"),
    ({"channel": "c", "nodes": [128]}, "1..127"),
    ({"channel": "c", "nodes": [1], "interface": "vcan"}, "is not one of"),
    ({"channel": "c", "nodes": [{"id": 1, "pdo": "mine"}]}, "pdo"),
    ({"channel": "c", "nodes": [{"id": 1, "pdo": "explicit"}]}, "explicit"),
    ({"channel": "c", "nodes": [{"id": 1, "pdo": "eds"}]}, "'eds' uses the default mapping of the node's EDS: give eds"),
    ({"channel": "c", "nodes": [{"id": 1, "pdo": "predefined"}]}, "a CANopen node has no PDO assignment; use 'drive'"),
    ({"channel": "c", "nodes": [1], "sync_counter": 1}, "can.sync_counter: 1 must be 0 .* or 2..240"),
    ({"channel": "c", "nodes": [1], "sync_counter": 241}, "can.sync_counter: 241"),
    ({"channel": "c", "nodes": [1], "speed": 5}, "can.speed: unknown key"),
])
def test_can_configuration_errors_name_the_key(can: dict, why: str) -> None:
    with pytest.raises(ConfigError, match=why):
        config_from_dict({"host": "c1", "can": can})
    with pytest.raises(ConfigError, match="choose one backend"):
        config_from_dict({"host": "c1", "ifname": "e", "can": {"channel": "c", "nodes": [1]}})


def test_can_flags_errors() -> None:
    for argv, why in ((["--can", "c"], "--nodes"), (["--nodes", "1"], "go with --can"),
                      (["--sync-counter", "4"], "go with --can"), (["--can", "c", "--nodes", "1,x"], "node ids"),
                      (["--can", "c", "--nodes", "1", "--sync-counter", "241"], "can.sync_counter: 241")):
        with pytest.raises(ConfigError, match=why):
            build_config(_parser().parse_args(argv))


def test_the_can_example_configuration_loads() -> None:
    from pathlib import Path

    from bus_agent.config import load_config

    cfg = load_config(Path(__file__).resolve().parents[2] / "deploy" / "agent.can.example.toml")
    assert cfg.can is not None and [n.pdo for n in cfg.can.nodes] == ["default", "eds", "explicit"]


def test_the_bus_reports_which_nodes_inputs_changed() -> None:
    """CanopenBus.inputs_changed (the cycle's fast path on CAN): a node whose TPDOs repeat the
    same data is not reported and its inputs are not decoded again; a changed TPDO is; a missing
    one changes nothing. The network is a stand-in that records the frames sent."""
    from bus_agent.bus.canopen.bus import CanopenBus

    class Net:
        def __init__(self) -> None:
            self.sent: list[tuple[int, bytes]] = []

        def send_message(self, cob: int, data: bytes) -> None:
            self.sent.append((cob, bytes(data)))

    bus = CanopenBus("test", [5, 6])
    bus._network = Net()
    for node, nid in zip(bus._nodes, (5, 6)):
        node.frames = pdo.PdoFrames(pdo.default_mapping(nid))

    def tpdos(k: int, sw: int, position: int) -> None:
        node = bus._nodes[k]
        base = 0x180 + node.cfg.node_id
        for cob, data in ((base, struct.pack("<HiB", sw, position, 8)), (base + 0x100, struct.pack("<ihH", 0, 0, 0))):
            node.tpdo_seq[cob] = node.tpdo_seq.get(cob, 0) + 1
            node.tpdo_data[cob] = data

    tpdos(0, 0x0237, 10)
    tpdos(1, 0x0237, 20)
    assert bus.exchange() == 2 and bus.inputs_changed() == [0, 1]   # first frames: both decoded
    tpdos(0, 0x0237, 10)
    tpdos(1, 0x0237, 21)
    assert bus.exchange() == 2 and bus.inputs_changed() == [1]      # node 5 at rest
    assert bus.inputs(1).position_actual == 21 and bus.inputs(0).position_actual == 10
    tpdos(0, 0x0233, 10)
    assert bus.exchange() == 1 and bus.inputs_changed() == [0]      # node 6 silent: nothing changes
    assert bus.inputs(0).statusword == 0x0233 and bus.inputs(1).position_actual == 21
