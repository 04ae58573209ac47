"""The ESI parser and writer (bus_agent.devices), the agent's use of a device (bus/esi_setup) and
the simulator's bit image, on the project's own files (tests/esi, and what --write-esi writes)."""

from __future__ import annotations

from pathlib import Path

import pytest

from bus_agent.bus.esi_setup import init_sdos, mapping_differences, match_slaves, object_infos, EsiMatchError
from bus_agent.bus.mapping import StartupSdo, mapping_of
from bus_agent.devices.esi import (EsiError, load_esi, parse_default_data, parse_esi, parse_esi_spec, parse_number,
                                   select_device)
from bus_agent.devices.esi_write import write_esi
from bus_agent.sim.ecat.esi_profile import esi_from_profile, profile_from_esi
from bus_agent.sim.ecat.image import BitImage
from bus_agent.sim.ecat.profiles import PROFILES

ESI = Path(__file__).resolve().parents[1] / "esi"


@pytest.mark.parametrize("text,value", [("#x1A00", 0x1A00), ("#X1a00", 0x1A00), ("0xF3F", 0xF3F),
                                        ("#x0x6041", 0x6041), ("2748", 2748), (" -12 ", -12)])
def test_numbers_in_every_vendor_format(text, value):
    assert parse_number(text) == value


def test_default_data_hex_bytes_or_decimal():
    assert parse_default_data("2C01", 2) == b"\x2c\x01"
    assert parse_default_data("250", 2) == (250).to_bytes(2, "little")  # decimal: odd length
    assert parse_default_data("1000", 4) == (1000).to_bytes(4, "little")  # decimal: wrong length for hex
    with pytest.raises(EsiError, match="neither hex bytes nor a decimal"):
        parse_default_data("zz", 1)


def test_quirk_file():
    boot, servo = load_esi(ESI / "quirks.xml")  # Latin-1 with an umlaut, two devices
    assert boot.vendor_name == "Quirk Werke München" and boot.type_name == "QuirkBoot"  # trailing space gone
    assert not boot.cia402 and boot.mailbox_protocols == ("FoE",) and boot.coe is None
    assert select_device([boot, servo]) is servo  # default: the first with CiA 402 objects
    assert servo.identity == (0xABC, 0x00402201, 0x00020000) and servo.profile_no == 402  # in <ChannelInfo>
    assert servo.name == "Quirk servo (predefined)"  # LcId 1033 over 1031
    assert servo.default_assign(True) == (0x1701,) and servo.default_assign(False) == (0x1B01,)
    rx = servo.pdo(0x1701)
    assert rx.fixed and rx.mandatory and rx.excludes == (0x1702, 0x1600)
    assert [(e.index, e.bits, e.padding) for e in rx.entries] == [(0x607A, 32, False), (0x2003, 1, False),
                                                                   (0, 7, True), (0x6040, 16, False)]
    assert servo.pdo(0x1600).entries == () and not servo.pdo(0x1600).fixed
    o = servo.objects
    assert o[(0x1C12, 1)].value() == 0x1701  # DefaultData written byte-swapped
    assert o[(0x1C12, 1)].access == "rw" and o[(0x1C13, 1)].access == "ro"  # the subitems' access wins
    assert o[(0x2001, 0)].value() == 250 and o[(0x2002, 0)].kind == "bool" and o[(0x1008, 0)].value() == "QuirkServo"
    assert (0x603F, 0) not in o and (0x1C00, 0) not in o
    assert servo.dc_required and [c.index for c in servo.init_cmds] == [0x6060, 0x2001]
    assert servo.coe.pdo_assign and not servo.coe.pdo_config and not servo.coe.complete_access


def test_namespaced_file_with_decimal_identity():
    (dev,) = load_esi(ESI / "configurable.xml")
    assert dev.identity == (2748, 4203265, 3) and dev.coe.sdo_info and dev.coe.complete_access
    assert dev.dc_capable and not dev.dc_required and dev.eeprom[:4] == bytes.fromhex("0C0E00CC")
    assert dev.init_cmds[1].transitions == ("IP", "PS") and dev.init_cmds[1].data == b"\xb0\x04"
    assert select_device([dev], 4203265, 3) is dev
    with pytest.raises(EsiError, match=r"no device 0x00402301:0x00000004; the file has 0x00402301:0x00000003"):
        select_device([dev], 4203265, 4, "configurable.xml")


def test_a_file_whose_bytes_are_not_its_declared_encoding_is_read_as_latin_1():
    text = (ESI / "configurable.xml").read_text().replace("Config Drives Ltd", "Config Antriebe M\u00fcnchen")
    (dev,) = parse_esi(text.encode("latin-1"), "mislabelled.xml")  # declared UTF-8, written Latin-1
    assert dev.vendor_name == "Config Antriebe München"
    (dev,) = parse_esi(b"\xef\xbb\xbf" + text.encode("utf-8"), "bom.xml")  # UTF-8 with a byte order mark
    assert dev.vendor_name == "Config Antriebe München"


@pytest.mark.parametrize("data,match", [
    (b"<EtherCATInfo><Vendor>", "not well-formed"),
    (b"<Other/>", "root element is <Other>"),
    (b"<EtherCATInfo><Vendor><Id>#xZZ</Id></Vendor></EtherCATInfo>", "Vendor Id: '#xZZ' is not a number"),
    (b'<!DOCTYPE x [<!ENTITY a "aaaa"><!ENTITY b "&a;&a;">]><EtherCATInfo>&b;</EtherCATInfo>', "refused"),
])
def test_bad_files_are_clear_errors(data, match):
    with pytest.raises(EsiError, match=match):
        parse_esi(data, "bad.xml")


def test_esi_spec():
    assert parse_esi_spec("a/b.xml@#x402201:2*3") == ("a/b.xml", 0x402201, 2, 3)
    assert parse_esi_spec("b.xml") == ("b.xml", None, None, 1)
    with pytest.raises(EsiError, match="positive integer"):
        parse_esi_spec("b.xml*0")


def test_written_esi_reads_back_as_the_built_in_profiles():
    devices = [esi_from_profile(p) for p in PROFILES.values()]
    assert parse_esi(write_esi(devices)) == devices
    omron = profile_from_esi(devices[2])
    assert omron.pdos.maps == dict(PROFILES["omron1s"].pdos.maps)
    assert omron.pdos.assign == dict(PROFILES["omron1s"].pdos.assign) and not omron.pdos.writable_maps


def test_init_cmds_object_names_and_mapping_differences():
    servo = load_esi(ESI / "quirks.xml")[1]
    assert init_sdos(servo, ("PS",)) == (StartupSdo(0x6060, 0, "u8", 8), StartupSdo(0x2001, 0, "u16", 300))
    assert init_sdos(servo, ("PS",), overridden=[(0x2001, 0)]) == (StartupSdo(0x6060, 0, "u8", 8),)
    assert init_sdos(servo, ("SO",)) == ()
    names = dict(object_infos(servo))
    assert names[(0x2001, 0)].name == "Brake delay" and (0x6040, 0) not in names  # the CiA 402 table's own
    default = mapping_of([(0x1701, [e.mapping for e in servo.pdo(0x1701).entries])],
                         [(0x1B01, [e.mapping for e in servo.pdo(0x1B01).entries])])
    assert mapping_differences(servo, default) == []
    other = mapping_of([(0x1702, [e.mapping for e in servo.pdo(0x1702).entries])], [(0x1B01, [0x60410010])])
    assert mapping_differences(servo, other) == [
        "RxPDO (0x1C12) assigns 0x1702; the ESI default is 0x1701",
        "TxPDO (0x1C13) 0x1B01 maps [6041:00/16]; the ESI default is [6041:00/16 6064:00/32 2002:00/1 0000:00/7 "
        "6061:00/8 606C:00/32 6077:00/16]"]
    assert match_slaves([servo], [(0, "x", 0xABC, 0x00402201, 0x00030000)], "f")[0] is servo  # newer revision
    with pytest.raises(EsiMatchError, match="slave 1 \\('y'\\): identity vendor 0x00000ABC product 0x00402299"):
        match_slaves([servo], [(1, "y", 0xABC, 0x00402299, 1)], "f")


def test_bit_image_packs_bits_padding_and_signed_values():
    img = BitImage([(0x607A, 0, 32, True), (0x2003, 0, 1, False), (0, 0, 7, False), (0x6040, 0, 16, False)])
    buf = bytearray(img.size)
    img.pack_into(buf, 0, -2, 1, 0x000F)
    assert img.size == 7 and bytes(buf) == b"\xfe\xff\xff\xff\x01\x0f\x00"
    assert img.unpack_from(buf) == (-2, 1, 0x000F) and img.keys == [(0x607A, 0), (0x2003, 0), (0x6040, 0)]


def test_esi_configuration(tmp_path):
    from bus_agent.cli import _parser, build_config
    from bus_agent.config import ConfigError, EsiConfig, load_config

    cfg = build_config(_parser().parse_args(["--ifname", "veth0", "--esi", str(ESI)]))
    assert cfg.esi == EsiConfig(str(ESI), init_cmds=True)
    toml = tmp_path / "a.toml"
    toml.write_text(f'host = "h1"\nifname = "veth0"\n[esi]\npath = "{ESI}"\ninit_cmds = false\n')
    assert load_config(toml).esi == EsiConfig(str(ESI), init_cmds=False)
    assert load_config(toml).with_overrides(esi="/other").esi == EsiConfig("/other", init_cmds=False)
    with pytest.raises(ConfigError, match="ESI files describe EtherCAT slaves"):
        build_config(_parser().parse_args(["--sim", "2", "--esi", str(ESI)]))


def test_sdo_information_fragments_and_descriptions():
    import struct

    from bus_agent.sim.ecat import sdo_info

    prof = profile_from_esi(load_esi(ESI / "configurable.xml")[0])
    objects = prof.dictionary
    values = lambda i, s: objects[(i, s)].default  # noqa: E731
    replies = sdo_info.handle(struct.pack("<BBHH", 1, 0, 0, 1), objects, values, room=10)
    indexes = sorted({i for i, _s in objects})
    assert len(replies) == (2 + 2 * len(indexes) + 9) // 10  # 10-byte pieces (list type first)
    assert [struct.unpack_from("<BBH", r)[2] for r in replies] == list(range(len(replies) - 1, -1, -1))
    assert all(r[0] == 0x82 for r in replies[:-1]) and replies[-1][0] == 0x02  # bit 7: more follow
    body = b"".join(r[4:] for r in replies)
    assert struct.unpack(f"<H{len(indexes)}H", body) == (1, *indexes)
    (desc,) = sdo_info.handle(struct.pack("<BBHH", 3, 0, 0, 0x1A00), objects, values, room=100)
    assert struct.unpack_from("<HHBB", desc, 4) == (0x1A00, 0x0007, 5, 8) and desc[10:] == b"TxPDO 1 mapping"
    (entry,) = sdo_info.handle(struct.pack("<BBHHBB", 5, 0, 0, 0x2101, 0, 0), objects, values, room=100)
    assert struct.unpack_from("<HBBHHH", entry, 4) == (0x2101, 0, 0, 0x0003, 16, 0x07 | 0x80)
    assert entry[14:] == b"Motor temperature"
    (err,) = sdo_info.handle(struct.pack("<BBHH", 3, 0, 0, 0x5000), objects, values, room=100)
    assert struct.unpack("<BBHI", err) == (7, 0, 0, 0x06020000)


def test_an_unreadable_esi_is_a_configuration_error_before_the_bus_opens(tmp_path, capsys):
    from bus_agent.cli import main

    bad = tmp_path / "bad.xml"
    bad.write_text("<EtherCATInfo><Vendor>")
    assert main(["--ifname", "zdnosuchif0", "--esi", str(bad)]) == 2
    assert "configuration error: esi.path: " in capsys.readouterr().err
    assert main(["--ifname", "zdnosuchif0", "--esi", str(tmp_path / "none")]) == 2
    assert "no such file or directory" in capsys.readouterr().err
