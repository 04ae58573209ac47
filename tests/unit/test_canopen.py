"""The CANopen backend's pure parts and the simulated node, without a bus: NMT table (seed 001),
heartbeat consumer, PDO layout and codec, EMCY decoding, PDO policies against a simulated node,
the node's NMT/SYNC/SDO behaviour, and the [can] configuration."""

from __future__ import annotations

import struct

import pytest
from canopen.sdo import SdoAbortedError

from bus_agent.bus.base import ALState
from bus_agent.bus.canopen import emcy, mapping as m, pdo
from bus_agent.bus.canopen.heartbeat import HeartbeatConsumer
from bus_agent.bus.canopen.nmt import (AL_OF_NMT, NMT_FOR_AL, NmtCommand, NmtState, after_command, decode_command,
                                       decode_heartbeat, nmt_frame)
from bus_agent.bus.pdo import DriveInputs, DriveOutputs
from bus_agent.cli import _parser, build_config
from bus_agent.config import ConfigError, config_from_dict
from bus_agent.sim.canopen.node import SimNode
from bus_agent.sim.drive_model import PROFILES

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


# ---- PDO layout and codec -------------------------------------------------------------------------

def test_default_layout_fits_frames_and_round_trips() -> None:
    layout = m.default_layout(5)
    assert [p.cob_id for p in layout.rpdos] == [0x205, 0x305] and [p.cob_id for p in layout.tpdos] == [0x185, 0x285]
    assert all(p.bits <= 64 for p in layout.rpdos + layout.tpdos)
    codec = m.Codec(layout, 5)
    out = DriveOutputs(controlword=0x000F, target_position=-123456, target_velocity=789, target_torque=-5,
                       modes_of_operation=8)
    frames = codec.rpdo_frames(out)
    values: dict = {}
    for (cob, data), p in zip(frames, layout.rpdos):
        assert cob == p.cob_id and len(data) * 8 == p.bits
        values.update(m.decode_pdo(p.entries, data, m.RX_OBJECTS))
    assert m.Codec.outputs_from(values) == out
    inputs = DriveInputs()
    assert codec.apply_tpdo(0x185, struct.pack("<HiB", 0x1637, -42, 8), inputs)
    assert codec.apply_tpdo(0x285, struct.pack("<ihH", 1000, -7, 0x8611), inputs)
    assert inputs == DriveInputs(0x1637, -42, 1000, -7, 8, 0x8611)
    assert not codec.apply_tpdo(0x186, b"\0" * 8, inputs)      # another node's
    assert not codec.apply_tpdo(0x185, b"\0\0", inputs)        # too short: nothing changes
    assert inputs.statusword == 0x1637


@pytest.mark.parametrize("rpdos,tpdos,why", [
    ((((0x6040, 0, 16), (0x607A, 0, 32), (0x60FF, 0, 32)),), (((0x6041, 0, 16),),), "carries 64"),
    ((((0x6040, 0, 16), (0x6041, 0, 16)),), (((0x6041, 0, 16),),), "does not exchange"),
    ((((0x6040, 0, 32),),), (((0x6041, 0, 16),),), "the object has 16"),
    ((((0x607A, 0, 32),),), (((0x6041, 0, 16),),), "controlword"),
    ((((0x6040, 0, 16),),), (((0x6064, 0, 32),),), "statusword"),
    ((((0x6040, 0, 16),), ((0x6040, 0, 16),)), (((0x6041, 0, 16),),), "mapped twice"),
])
def test_layouts_the_cycle_cannot_use_are_refused_with_the_reason(rpdos, tpdos, why) -> None:
    layout = m.Layout(tuple(m.PdoMap(0x201 + 0x100 * i, e) for i, e in enumerate(rpdos)),
                      tuple(m.PdoMap(0x181 + 0x100 * i, e) for i, e in enumerate(tpdos)))
    with pytest.raises(m.LayoutError, match=why):
        m.Codec(layout, 1)


def test_emcy_decoding_and_texts() -> None:
    e = emcy.decode(3, emcy.encode(0x8130, 0x11))
    assert (e.node_id, e.error_code, e.error_register, e.reset) == (3, 0x8130, 0x11, False)
    assert e.text == "life guard error or heartbeat error"
    assert emcy.decode(3, b"\x00\x00\x00").reset
    assert emcy.error_text(0x2311) == "current" and emcy.error_text(0x8611) == "following error"
    assert emcy.error_text(0xAB00).startswith("unknown error code")


# ---- the simulated node, and the PDO policies against it ------------------------------------------

def _node(node_id: int = 1) -> SimNode:
    return SimNode(node_id, PROFILES["generic"], serial=node_id)


def _sdo(node: SimNode):
    return (lambda i, s: node.get_data(i, s)), (lambda i, s, d: node.set_data(i, s, d))


def test_policy_node_reads_the_default_mapping_the_node_powers_up_with() -> None:
    node = _node(4)
    read, write = _sdo(node)
    assert pdo.layout_for("node", 4, read, write) == m.default_layout(4)


def test_policy_explicit_is_written_and_used_by_the_node() -> None:
    node = _node(2)
    read, write = _sdo(node)
    explicit = m.Layout(rpdos=(m.PdoMap(0x202, ((0x6040, 0, 16), (0x6060, 0, 8))),),
                        tpdos=(m.PdoMap(0x182, ((0x6041, 0, 16), (0x603F, 0, 16), (0x6061, 0, 8))),))
    assert pdo.layout_for("explicit", 2, read, write, explicit) == explicit
    assert pdo.read_layout(read) == explicit                       # read back from the node
    node.on_frame(0x000, nmt_frame(C.START, 2), 0.0)
    node.on_frame(0x202, struct.pack("<Hb", 0x0006, 8), 0.01)
    frames = node.on_frame(0x080, b"", 0.02)
    tpdos = [f for f in frames if 0x180 <= f[0] < 0x300]
    assert [cob for cob, _ in tpdos] == [0x182]                    # PDO 2 is invalid now
    sw, code, _mode = struct.unpack("<HHb", tpdos[0][1])            # 5 bytes, in the explicit order
    assert code == 0 and sw == node.model.statusword
    with pytest.raises(SdoAbortedError) as e:                      # operational: mapping locked
        pdo.layout_for("default", 2, read, write)
    assert e.value.code == 0x08000022
    assert pdo.read_layout(read) == explicit                       # nothing changed


def test_pdo_configuration_is_refused_in_operational_and_needs_count_zero() -> None:
    node = _node(1)
    read, write = _sdo(node)
    with pytest.raises(SdoAbortedError) as e:
        write(0x1A00, 1, struct.pack("<I", m.mapping_value((0x6041, 0, 16))))
    assert e.value.code == 0x06010000                              # sub 0 must be 0 first
    write(0x1A00, 0, b"\x00")
    with pytest.raises(SdoAbortedError) as e:
        write(0x1A00, 2, struct.pack("<I", m.mapping_value((0x6065, 0, 32))))  # not PDO-mappable
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

def test_can_table_and_flags() -> None:
    cfg = config_from_dict({"host": "c1", "can": {"channel": "can0", "interface": "socketcan", "heartbeat_ms": 50,
                                                  "nodes": [1, {"id": 2, "pdo": "node", "eds": "d.eds"},
                                                            {"id": 3, "pdo": "explicit",
                                                             "rpdo": [[0x60400010]], "tpdo": [[0x60410010]],
                                                             "sdo": [{"index": 0x605A, "value": 5, "size": 2}]}]}})
    assert cfg.backend == "canopen" and cfg.can is not None
    assert [n.node_id for n in cfg.can.nodes] == [1, 2, 3] and cfg.can.nodes[1].eds == "d.eds"
    assert cfg.can.nodes[2].startup_sdos == ((0x605A, 0, 5, 2),)
    args = _parser().parse_args(["--can", "239.1.1.1", "--can-interface", "udp_multicast", "--nodes", "1,2,0x7f",
                                 "--host", "c2"])
    flags = build_config(args)
    assert flags.can is not None and [n.node_id for n in flags.can.nodes] == [1, 2, 127]
    assert flags.can.interface == "udp_multicast" and flags.backend == "canopen"


@pytest.mark.parametrize("can,why", [
    ({"channel": "c", "nodes": []}, "at least one node"),
    ({"channel": "c", "nodes": [1, 1]}, "listed twice"),
    ({"channel": "c", "nodes": [128]}, "1..127"),
    ({"channel": "c", "nodes": [1], "interface": "vcan"}, "is not one of"),
    ({"channel": "c", "nodes": [{"id": 1, "pdo": "mine"}]}, "pdo"),
    ({"channel": "c", "nodes": [{"id": 1, "pdo": "explicit"}]}, "explicit"),
    ({"channel": "c", "nodes": [1], "speed": 5}, "can.speed: unknown key"),
])
def test_can_configuration_errors_name_the_key(can: dict, why: str) -> None:
    with pytest.raises(ConfigError, match=why):
        config_from_dict({"host": "c1", "can": can})
    with pytest.raises(ConfigError, match="choose one backend"):
        config_from_dict({"host": "c1", "ifname": "e", "can": {"channel": "c", "nodes": [1]}})


def test_can_flags_errors() -> None:
    for argv, why in ((["--can", "c"], "--nodes"), (["--nodes", "1"], "go with --can"),
                      (["--can", "c", "--nodes", "1,x"], "node ids")):
        with pytest.raises(ConfigError, match=why):
            build_config(_parser().parse_args(argv))
