"""``bus-agent scan``: read a segment without controlling it (never beyond PRE-OP, no Zenoh).

Per slave: position, name, identity (0x1018 by SDO, else the SII), DC capability (ESC 0x0008
bit 2), mailbox protocols (SII word 0x1C), supported drive modes (0x6502), the PDO assignment
and every mapped entry with its name, bit offset and size, and the SM2/SM3 lengths the mapping
needs. ``--toml`` prints ``[[drives]]`` blocks ready for the agent's configuration.

The report (:class:`SlaveScan`) and its three renderings are pure; :func:`scan_segment` is the
pysoem I/O (config_init only: the slaves end in PRE-OP, as config_init leaves them).
"""

from __future__ import annotations

import json
import struct
from dataclasses import dataclass, field
from typing import Any, Callable, Sequence

from bus_agent.bus.base import BusError
from bus_agent.bus.mapping import SlaveMapping, read_mapping
from bus_agent.bus.mailbox import mailbox_protocols, transfer_failure_text
from bus_agent.cia402.states import Mode


@dataclass(frozen=True)
class SlaveScan:
    """What ``scan`` learnt about one slave (``error``: what could not be read, and why)."""

    position: int
    name: str
    vendor_id: int
    product_code: int
    revision: int
    serial: int
    dc: bool
    mailbox: tuple[str, ...]
    modes: tuple[int, ...] | None       # from 0x6502; None when the drive has none
    mapping: SlaveMapping | None
    errors: tuple[str, ...] = field(default=())
    device: str | None = None                 # --esi: the matched ESI device's name
    differences: tuple[str, ...] | None = None  # --esi: where the mapping differs from its default
    names: tuple[tuple[tuple[int, int], str], ...] = ()  # --esi: vendor objects' names

    def to_dict(self) -> dict[str, Any]:
        m = self.mapping
        out: dict[str, Any] = {
            "position": self.position, "name": self.name, "vendor_id": self.vendor_id,
            "product_code": self.product_code, "revision": self.revision, "serial": self.serial, "dc": self.dc,
            "mailbox": list(self.mailbox), "modes": list(self.modes) if self.modes is not None else None,
            "errors": list(self.errors)}
        if self.device is not None or self.differences is not None:
            out.update(esi_device=self.device, esi_differences=list(self.differences or ()))
        if m is not None:
            names = dict(self.names)

            def entries(es):  # type: ignore[no-untyped-def]
                return [{"index": e.index, "subindex": e.subindex,
                         "name": "padding" if e.padding else names.get(e.key, e.name),
                         "bit_offset": e.bit_offset, "bits": e.bits, "pdo": e.pdo} for e in es]
            out.update(rx_pdos=list(m.rx_pdos), tx_pdos=list(m.tx_pdos), rx=entries(m.rx), tx=entries(m.tx),
                       sm2_bytes=m.out_bytes, sm3_bytes=m.in_bytes)
        return out


def decode_modes(bits: int) -> tuple[int, ...]:
    return tuple(int(m) for m in Mode if bits >> m.supported_bit & 1)


def render_json(scans: Sequence[SlaveScan]) -> str:
    return json.dumps({"slaves": [s.to_dict() for s in scans]}, indent=2)


def render_text(scans: Sequence[SlaveScan]) -> str:
    lines = []
    for s in scans:
        lines.append(f"slave {s.position} {s.name!r}: vendor 0x{s.vendor_id:08X} product 0x{s.product_code:08X} "
                     f"revision 0x{s.revision:08X} serial {s.serial}; DC {'yes' if s.dc else 'no'}; "
                     f"mailbox {','.join(s.mailbox) or 'none'}; modes "
                     + (",".join(str(m) for m in s.modes) if s.modes else
                        "none listed (0x6502 = 0)" if s.modes is not None else "unknown (no 0x6502)"))
        if s.device is not None:
            lines.append(f"  ESI device {s.device!r}: mapping "
                         + ("as its ESI default" if not s.differences else "differs from its ESI default:"))
            lines.extend(f"    - {d}" for d in s.differences or ())
        m = s.mapping
        names = dict(s.names)
        if m is not None:
            for side, pdos, es, sm, size in (("RxPDO", m.rx_pdos, m.rx, "SM2", m.out_bytes),
                                             ("TxPDO", m.tx_pdos, m.tx, "SM3", m.in_bytes)):
                lines.append(f"  {side} {', '.join(f'0x{p:04X}' for p in pdos) or 'none'} ({sm} {size} bytes)")
                for e in es:
                    what = "padding" if e.padding else f"0x{e.index:04X}:{e.subindex:02X} {names.get(e.key, e.name)}"
                    lines.append(f"    bit {e.bit_offset:4d} +{e.bits:<2d} {what}")
        for err in s.errors:
            lines.append(f"  ! {err}")
    return "\n".join(lines)


def render_toml(scans: Sequence[SlaveScan]) -> str:
    """``[[drives]]`` blocks: identity, a cyclic synchronous mode it supports, its own mapping."""
    out = []
    for s in scans:
        mode = next((m for m in (8, 9, 10) if s.modes is None or m in s.modes), None)
        out.append("[[drives]]")
        out.append(f"slave = {s.position}")
        out.append(f'axis = "axis{s.position}"                # {s.name}')
        if mode is not None:
            out.append(f"mode = {mode}")
        out.append("[drives.identity]")
        out.append(f"vendor_id = 0x{s.vendor_id:08X}")
        out.append(f"product_code = 0x{s.product_code:08X}")
        out.append(f"revision = 0x{s.revision:08X}")
        m = s.mapping
        if m is not None:
            out.append("[drives.mapping]")
            out.append('policy = "drive"                # what the drive holds now:')
            out.append(f"# rx = [{', '.join(f'0x{p:04X}' for p in m.rx_pdos)}]   "
                       f"tx = [{', '.join(f'0x{p:04X}' for p in m.tx_pdos)}]")
        out.append("")
    return "\n".join(out)


SdoRead = Callable[[int, int, int], bytes]


def scan_slave(position: int, name: str, sii: tuple[int, int, int], dc: bool, mailbox_word: int,
               sdo_read: SdoRead) -> SlaveScan:
    """One slave's report from its SII identity (vendor, product, revision), DC flag, mailbox
    word and an SDO reader; what cannot be read is listed in ``errors``."""
    errors = []
    vendor, product, revision = sii
    serial = 0
    protocols = mailbox_protocols(mailbox_word)
    modes = None
    mapping = None
    if "CoE" in protocols:
        try:
            vendor, product, revision, serial = (struct.unpack("<I", sdo_read(0x1018, k, 4)[:4])[0] for k in (1, 2, 3, 4))
        except Exception as e:
            errors.append(f"0x1018 identity: {e}")
        try:
            modes = decode_modes(struct.unpack("<I", sdo_read(0x6502, 0, 4)[:4])[0])
        except Exception as e:
            errors.append(f"0x6502 supported drive modes: {e}")
        try:
            mapping = read_mapping(sdo_read)
        except Exception as e:
            errors.append(f"PDO mapping (0x1C12/0x1C13): {e}")
    return SlaveScan(position, name, vendor, product, revision, serial, dc, protocols, modes, mapping, tuple(errors))


def scan_segment(ifname: str) -> list[SlaveScan]:
    """Open ``ifname``, config_init (slaves to PRE-OP, not beyond), read every slave, close.
    Raises BusError when the segment cannot be read."""
    import pysoem

    m = pysoem.Master()
    try:
        m.open(ifname)
    except Exception as e:
        raise BusError(f"{ifname}: cannot open the interface: {e}") from None
    try:
        n = m.config_init(release_gil=True)
        if n <= 0:
            raise BusError(f"{ifname}: no slave answered (is the segment connected and powered?)")
        out = []
        for pos, s in enumerate(m.slaves):
            try:
                features = struct.unpack("<H", bytes(s._fprd(0x0008, 2, 2000))[:2])[0]
                word = struct.unpack("<H", bytes(s.eeprom_read(0x1C, 2000))[:2])[0]
            except Exception as e:
                raise BusError(f"slave {pos} ({s.name!r}): registers not readable: {e}") from None

            def read(index: int, sub: int, size: int, s: Any = s) -> bytes:
                try:
                    return bytes(s.sdo_read(index, sub, size, release_gil=True))
                except pysoem.SdoError:
                    raise
                except Exception as e:
                    raise BusError(f"SDO upload 0x{index:04X}:{sub:02X}: {transfer_failure_text(e)}") from None

            out.append(scan_slave(pos, s.name, (s.man, s.id, s.rev), bool(features & 0x0004), word, read))
        return out
    finally:
        m.close()


def with_esi(scans: Sequence[SlaveScan], devices: Sequence[Any], source: str) -> tuple[list[SlaveScan], list[str]]:
    """Each scan with its ESI device's name and the differences of its mapping from the ESI
    default; and a line per slave whose identity matches no device."""
    from dataclasses import replace

    from bus_agent.bus.esi_setup import mapping_differences, object_infos
    from bus_agent.devices.esi import match_identity

    out, unmatched = [], []
    for s in scans:
        dev = match_identity(devices, s.vendor_id, s.product_code, s.revision)
        if dev is None:
            unmatched.append(f"slave {s.position} ({s.name!r}): identity vendor 0x{s.vendor_id:08X} product "
                             f"0x{s.product_code:08X} revision 0x{s.revision:08X} matches no device in the ESI {source}")
            out.append(s)
            continue
        diffs = tuple(mapping_differences(dev, s.mapping)) if s.mapping is not None else ()
        out.append(replace(s, device=dev.name, differences=diffs,
                           names=tuple((key, info.name) for key, info in object_infos(dev))))
    return out, unmatched


def main(argv: Sequence[str]) -> int:
    """``bus-agent scan --ifname IF [--esi PATH] [--json] [--toml]``: exit 0, 3 when the segment
    cannot be read, 4 when a slave matches no device of the ESI (the report is printed)."""
    import argparse
    import sys

    p = argparse.ArgumentParser(prog="bus-agent scan", description="Read an EtherCAT segment without controlling "
                                "it: identities, DC, mailbox, modes, PDO mapping (never beyond PRE-OP, no Zenoh).")
    p.add_argument("--ifname", required=True, help="NIC (or veth end) of the segment; needs root")
    p.add_argument("--esi", metavar="PATH", help="ESI file or directory: name each slave's device (by identity) and "
                   "list where its mapping differs from the ESI default")
    fmt = p.add_mutually_exclusive_group()
    fmt.add_argument("--json", action="store_true", help="one JSON document")
    fmt.add_argument("--toml", action="store_true", help="[[drives]] blocks for the agent's configuration")
    args = p.parse_args(list(argv))
    devices = None
    if args.esi:
        from bus_agent.devices.esi import EsiError, load_esi

        try:
            devices = load_esi(args.esi)
        except EsiError as e:
            print(f"bus-agent scan: --esi: {e}", file=sys.stderr)
            return 2
    try:
        scans = scan_segment(args.ifname)
    except BusError as e:
        print(f"bus-agent scan: {e}", file=sys.stderr)
        return 3
    unmatched: list[str] = []
    if devices is not None:
        scans, unmatched = with_esi(scans, devices, args.esi)
    print(render_json(scans) if args.json else render_toml(scans) if args.toml else render_text(scans))
    for line in unmatched:
        print(f"bus-agent scan: {line}", file=sys.stderr)
    return 4 if unmatched else 0
