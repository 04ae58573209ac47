"""PDO mapping logic and the per-drive codec (pure): offsets, policies, write order, refusals."""

from __future__ import annotations

import struct

import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from bus_agent.bus.codec import DriveCodec
from bus_agent.bus.mapping import (DEFAULT_MAPPING, OBJECTS, MappingError, MappingPolicy, StartupSdo, check_mapping,
                                   mapping_of, plan_writes, read_mapping)
from bus_agent.bus.pdo import RX_STRUCT, TX_STRUCT, DriveInputs, DriveOutputs, mapping_entry
from bus_agent.config import ConfigError, config_from_dict

_FMT = {"u8": "<B", "i8": "<b", "u16": "<H", "i16": "<h", "u32": "<I", "i32": "<i", "u64": "<Q", "i64": "<q"}
TX_FIELD_OBJECTS = {(0x6064, 0): "position_actual", (0x606C, 0): "velocity_actual", (0x6077, 0): "torque_actual",
                    (0x6061, 0): "modes_of_operation_display", (0x603F, 0): "error_code"}
_VENDOR = [(0x2000 + k, 1, bits) for k, bits in enumerate((8, 16, 32, 64))]


def _objects(rx: bool):
    known = [(i, s) for (i, s) in OBJECTS if (i, s) not in ((0x6040, 0), (0x6041, 0))]
    return st.lists(st.one_of(
        st.sampled_from(known).map(lambda k: (k[0], k[1], int(OBJECTS[k].datatype[1:]))),
        st.sampled_from(_VENDOR),
        st.sampled_from([(0, 0, 8), (0, 0, 16), (0, 0, 1), (0, 0, 7)]),  # padding, also sub-byte
    ), max_size=12, unique_by=lambda e: (e[0], e[1]) if e[0] else object())


def _byte_aligned(entries):
    """A sub-byte padding entry is followed by the padding that completes its byte."""
    out = []
    for e in entries:
        out.append(e)
        if e[0] == 0 and e[2] % 8:
            out.append((0, 0, 8 - e[2] % 8))
    return out


def _place(entries, values) -> bytes:
    """Reference encoder: every value at its bit offset (little-endian bit order)."""
    total = sum(e[2] for e in entries)
    acc, off = 0, 0
    for (index, sub, bits), v in zip(entries, values):
        acc |= (v & ((1 << bits) - 1)) << off
        off += bits
    return acc.to_bytes((total + 7) // 8, "little")


def _type(index, sub, bits):
    info = OBJECTS.get((index, sub))
    return info.datatype if info else f"u{bits}"


@settings(max_examples=150, deadline=None)
@given(rx=_objects(True), tx=_objects(False), data=st.data())
def test_codec_puts_every_value_at_its_offset(rx, tx, data):
    # the required objects somewhere in each side
    rx.insert(data.draw(st.integers(0, len(rx))), (0x6040, 0, 16))
    tx.insert(data.draw(st.integers(0, len(tx))), (0x6041, 0, 16))
    if any(e[:2] == (0x607A, 0) for e in rx) and not any(e[:2] == (0x6064, 0) for e in tx):
        tx.append((0x6064, 0, 32))
    rx = _byte_aligned(rx)
    tx = _byte_aligned(tx)
    rx_pdo = data.draw(st.sampled_from([0x1600, 0x1701]))
    m = mapping_of([(rx_pdo, [mapping_entry(*e) for e in rx])], [(0x1A00, [mapping_entry(*e) for e in tx])])
    assert check_mapping(m) == []
    codec = DriveCodec(m)
    assert codec.in_size == m.in_bytes and codec.out_size == m.out_bytes

    # inputs: random values placed by the reference encoder come out in the right fields
    values = []
    for index, sub, bits in tx:
        if index == 0:
            values.append(0)
            continue
        t = _type(index, sub, bits)
        lo, hi = (-(1 << (bits - 1)), (1 << (bits - 1)) - 1) if t.startswith("i") else (0, (1 << bits) - 1)
        values.append(data.draw(st.integers(lo, hi)))
    rec = DriveInputs()
    codec.decode_into(rec, _place(tx, values))
    by_key = {(i, s): v for (i, s, _b), v in zip(tx, values) if i}
    assert rec.statusword == by_key[(0x6041, 0)]
    for key, fld in TX_FIELD_OBJECTS.items():
        assert getattr(rec, fld) == by_key.get(key, 0)
    assert dict(zip(codec.extra_names, rec.extra)) == {
        OBJECTS[k].name if k in OBJECTS else f"0x{k[0]:04X}:{k[1]:02X}": v
        for k, v in by_key.items() if k not in TX_FIELD_OBJECTS and k != (0x6041, 0)}
    assert set(codec.absent_inputs) == {n for k, n in (((0x6064, 0), "position"), ((0x606C, 0), "velocity"),
                                                       ((0x6077, 0), "torque"), ((0x6061, 0), "mode_display"),
                                                       ((0x603F, 0), "error_code")) if k not in by_key}

    # outputs: the record's fields at their offsets, other objects and padding 0
    o = DriveOutputs(controlword=data.draw(st.integers(0, 0xFFFF)), target_position=data.draw(st.integers(-2**31, 2**31 - 1)),
                     target_velocity=data.draw(st.integers(-2**31, 2**31 - 1)), target_torque=data.draw(st.integers(-2**15, 2**15 - 1)),
                     modes_of_operation=data.draw(st.integers(-128, 127)))
    field_of = {(0x6040, 0): o.controlword, (0x607A, 0): o.target_position, (0x60FF, 0): o.target_velocity,
                (0x6071, 0): o.target_torque, (0x6060, 0): o.modes_of_operation}
    expected = _place(rx, [field_of.get((i, s), 0) for i, s, _b in rx])
    assert codec.encode(o) == expected


def test_default_mapping_codec_matches_the_fixed_structs():
    codec = DriveCodec(DEFAULT_MAPPING)
    o = DriveOutputs(0x000F, -123456, 789, -12, 8)
    assert codec.encode(o) == o.pack() and codec.out_size == RX_STRUCT.size
    i = DriveInputs(0x1237, 42, -7, 300, 8, 0x8611)
    rec = DriveInputs()
    codec.decode_into(rec, i.pack())
    assert rec == i and codec.in_size == TX_STRUCT.size and codec.absent_inputs == () and rec.extra == ()


def test_misaligned_required_object_is_refused():
    m = mapping_of([(0x1600, [mapping_entry(0, 0, 4), mapping_entry(0x6040, 0, 16), mapping_entry(0, 0, 4)])],
                   [(0x1A00, [mapping_entry(0x6041, 0, 16)])])
    with pytest.raises(MappingError, match="0x6040:00 is 16 bits at bit offset 4"):
        DriveCodec(m)


def test_check_mapping_names_what_is_missing():
    m = mapping_of([(0x1701, [mapping_entry(0x607A, 0, 32)])], [(0x1B01, [mapping_entry(0x603F, 0, 16)])])
    problems = check_mapping(m)
    assert any("0x6040" in p for p in problems) and any("0x6041" in p for p in problems)
    assert any("0x6064" in p for p in problems)


def _reader(table):
    return lambda index, sub, size: table[(index, sub)]


def test_read_mapping_walks_assignment_pdos_and_entries():
    t = {(0x1C12, 0): b"\x01", (0x1C12, 1): struct.pack("<H", 0x1701),
         (0x1701, 0): b"\x02", (0x1701, 1): struct.pack("<I", 0x60400010), (0x1701, 2): struct.pack("<I", 0x00000008),
         (0x1C13, 0): b"\x02", (0x1C13, 1): struct.pack("<H", 0x1B01), (0x1C13, 2): struct.pack("<H", 0x1B02),
         (0x1B01, 0): b"\x01", (0x1B01, 1): struct.pack("<I", 0x60410010),
         (0x1B02, 0): b"\x01", (0x1B02, 1): struct.pack("<I", 0x60FD0020)}
    m = read_mapping(_reader(t))
    assert m.rx_pdos == (0x1701,) and m.tx_pdos == (0x1B01, 0x1B02)
    assert [(e.index, e.bit_offset) for e in m.rx] == [(0x6040, 0), (0, 16)]
    assert [(e.index, e.bit_offset, e.pdo) for e in m.tx] == [(0x6041, 0, 0x1B01), (0x60FD, 16, 0x1B02)]
    assert m.out_bytes == 3 and m.in_bytes == 6


def test_plan_writes_order_and_sizes():
    steps = plan_writes(MappingPolicy("explicit", rx_entries=((0x6040, 0, 16),), tx_entries=((0x6041, 0, 16),),
                                      rx_pdo=0x1601), DEFAULT_MAPPING)
    seq = [(s.index, s.subindex, s.fmt) for s in steps]
    assert seq[:2] == [(0x1C12, 0, "<B"), (0x1C13, 0, "<B")]
    assert seq[2:5] == [(0x1601, 0, "<B"), (0x1601, 1, "<I"), (0x1601, 0, "<B")]
    assert steps[4].value == 1
    assert seq[-4:] == [(0x1C12, 1, "<H"), (0x1C12, 0, "<B"), (0x1C13, 1, "<H"), (0x1C13, 0, "<B")]
    # what the drive already holds is not written
    assert plan_writes(MappingPolicy("default"), DEFAULT_MAPPING) == []
    assert plan_writes(MappingPolicy(), DEFAULT_MAPPING) == []
    pre = plan_writes(MappingPolicy("predefined", rx=(0x1702,), tx=(0x1B01,)), DEFAULT_MAPPING)
    assert [(s.index, s.subindex, s.value) for s in pre] == [
        (0x1C12, 0, 0), (0x1C13, 0, 0), (0x1C12, 1, 0x1702), (0x1C12, 0, 1), (0x1C13, 1, 0x1B01), (0x1C13, 0, 1)]


@pytest.mark.parametrize("kwargs, match", [
    ({"policy": "fixed"}, "not one of drive, default, predefined, explicit"),
    ({"policy": "predefined", "rx": (0x1A00,), "tx": (0x1B01,)}, "rx: 6656 is not a RxPDO"),
    ({"policy": "predefined", "tx": (0x1B01,)}, "needs at least one PDO index"),
    ({"policy": "drive", "rx": (0x1701,)}, "belong to policy 'predefined'"),
    ({"policy": "explicit", "rx_entries": ((0x6040, 0, 16),), "tx_entries": ((0x6041, 0, 99),)}, r"tx_entries\[0\]"),
])
def test_policy_validation(kwargs, match):
    with pytest.raises(MappingError, match=match):
        MappingPolicy(**kwargs)


def test_startup_sdo_validation():
    assert StartupSdo(0x6060, 0, "i8", 8).data == b"\x08"
    with pytest.raises(MappingError, match="does not fit i8"):
        StartupSdo(0x6060, 0, "i8", 200)
    with pytest.raises(MappingError, match="type 'f32'"):
        StartupSdo(0x6060, 0, "f32", 1)


def test_config_mapping_and_sdos_from_toml_dict():
    c = config_from_dict({"host": "h1", "ifname": "eth1", "drives": [
        {"slave": 0, "mapping": {"policy": "predefined", "rx": [0x1701], "tx": [0x1B01]},
         "sdo": [{"index": 0x6065, "subindex": 0, "type": "u32", "value": 5000}]},
        {"slave": 1, "pdo": {"rx_pdo": 0x1601}}]})
    d0, d1 = c.drives
    assert d0.setup.policy == MappingPolicy("predefined", rx=(0x1701,), tx=(0x1B01,))
    assert d0.setup.sdos == (StartupSdo(0x6065, 0, "u32", 5000),)
    assert d1.setup.policy == MappingPolicy("default", rx_pdo=0x1601) and d1.needs_setup
    assert not config_from_dict({"host": "h1", "ifname": "e", "drives": [{"slave": 0}]}).drives[0].needs_setup
    for bad, match in (({"mapping": {"policy": "explicit", "rx_entries": [[0x6040, 0]]}}, r"rx_entries\[0\]"),
                       ({"mapping": {"policy": "drive", "colour": 1}}, "mapping.colour: unknown key"),
                       ({"sdo": [{"index": 0x6065, "type": "u32", "value": -1}]}, r"sdo\[0\].*does not fit u32")):
        with pytest.raises(ConfigError, match=match):
            config_from_dict({"host": "h1", "ifname": "e", "drives": [{"slave": 0, **bad}]})


def test_objects_decode_with_their_cia402_type_and_unknown_ones_unsigned_by_index():
    """INTEGER objects of the table (0x60F4, 0x6077, 0x60BA, 0x60FC) decode signed; UNSIGNED
    ones (0x60B9, 0x60FD) and a vendor object not in the table (0x2205:01) unsigned, named by index."""
    tx = [(0x6041, 0, 16), (0x60F4, 0, 32), (0x6077, 0, 16), (0x60BA, 0, 32), (0x60FC, 0, 32), (0x60B9, 0, 16),
          (0x60FD, 0, 32), (0x2205, 1, 16)]
    m = mapping_of([(0x1600, [mapping_entry(0x6040, 0, 16)])], [(0x1A00, [mapping_entry(*e) for e in tx])])
    codec = DriveCodec(m)
    assert codec.extra_names == ("following_error_actual_value", "touch_probe_1_positive_edge",  # 0x6077: torque
                                 "position_demand_internal_value", "touch_probe_status", "digital_inputs", "0x2205:01")
    raw = struct.pack("<HihiiHIH", 0x0237, -1234, -5, -70000, -3, 0xFFFF, 0xFFFFFFFF, 0xFFFE)
    rec = DriveInputs()
    codec.decode_into(rec, raw)
    objs = dict(zip(codec.extra_names, rec.extra))
    assert objs["following_error_actual_value"] == -1234 and objs["touch_probe_1_positive_edge"] == -70000
    assert objs["position_demand_internal_value"] == -3 and rec.torque_actual == -5
    assert objs["touch_probe_status"] == 0xFFFF and objs["digital_inputs"] == 0xFFFFFFFF and objs["0x2205:01"] == 0xFFFE
    assert OBJECTS[(0x60FC, 0)].datatype == "i32" and OBJECTS[(0x60B9, 0)].datatype == "u16"
