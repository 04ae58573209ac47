"""What the agent takes from the slaves' ESI files (``bus-agent --esi PATH``). Pure.

- :func:`match_slaves`: each slave's ESI device by its identity (vendor id, product code,
  revision; an older revision of the same product when the exact one is not described), or a
  :class:`EsiMatchError` naming the slave and the identity that matches no device;
- :func:`init_sdos`: the device's CoE ``<InitCmds>`` for the transitions the agent makes, as
  start-up SDOs (TwinCAT and IgH make them too), less those the TOML's ``[[drives.sdo]]`` sets;
- :func:`object_infos`: names and types of the device's vendor objects, for ``objects``;
- :func:`mapping_differences`: where a slave's mapping differs from the ESI default
  (``bus-agent scan --esi``).
"""

from __future__ import annotations

import logging
from dataclasses import replace
from typing import Iterable, Sequence

from bus_agent.bus.base import BusError
from bus_agent.bus.mapping import OBJECTS, ObjectInfo, SlaveMapping, SlaveSetup, StartupSdo
from bus_agent.devices.esi import INT_TYPES, EsiDevice, InitCmd, match_identity

log = logging.getLogger(__name__)

#: InitCmd transitions made while the agent's slave is in PRE-OP on its way to SAFE-OP (INIT ->
#: PRE-OP, then PRE-OP -> SAFE-OP), and those made in SAFE-OP before OP.
PREOP_TRANSITIONS = ("IP", "PS")
SAFEOP_TRANSITIONS = ("SO",)
_SDO_TYPE_OF_SIZE = {1: "u8", 2: "u16", 4: "u32", 8: "u64"}
NAME_MAX = 64  # status `objects` keys (schemas/messages.py)


class EsiMatchError(BusError):
    """A slave whose identity matches no device of the ESI files: start-up stops."""


def match_slaves(devices: Sequence[EsiDevice], identities: Iterable[tuple[int, str, int, int, int]],
                 source: str) -> dict[int, EsiDevice]:
    """``{position: device}`` for ``(position, name, vendor, product, revision)``. Raises
    :class:`EsiMatchError` for the first slave without a device."""
    out = {}
    for pos, name, vendor, product, revision in identities:
        dev = match_identity(devices, vendor, product, revision)
        if dev is None:
            known = ", ".join(sorted({f"0x{d.vendor_id:08X}/0x{d.product_code:08X}/0x{d.revision:08X}"
                                      for d in devices})) or "none"
            raise EsiMatchError(
                f"slave {pos} ({name!r}): identity vendor 0x{vendor:08X} product 0x{product:08X} revision "
                f"0x{revision:08X} matches no device in the ESI {source} (vendor/product/revision there: {known})")
        if dev.revision != revision:
            log.info("slave %d (%r): revision 0x%08X not described, using %s", pos, name, revision, dev.label())
        out[pos] = dev
    return out


def _sdo_of(cmd: InitCmd) -> StartupSdo | None:
    typ = _SDO_TYPE_OF_SIZE.get(len(cmd.data))
    if typ is None or cmd.complete_access:
        return None
    return StartupSdo(cmd.index, cmd.subindex, typ, int.from_bytes(cmd.data, "little"))


def init_sdos(dev: EsiDevice, transitions: Sequence[str], overridden: Iterable[tuple[int, int]] = ()
              ) -> tuple[StartupSdo, ...]:
    """The device's InitCmds for ``transitions``, in file order, as start-up SDOs; those whose
    object the configuration writes itself (``overridden``) are left out: the TOML wins. A
    command of 1, 2, 4 or 8 bytes is taken; others (strings, complete access) are logged and
    left out."""
    skip = set(overridden)
    out = []
    for cmd in dev.init_cmds:
        if not set(cmd.transitions) & set(transitions) or (cmd.index, cmd.subindex) in skip:
            continue
        sdo = _sdo_of(cmd)
        if sdo is None:
            log.warning("%s: InitCmd 0x%04X:%02X (%d bytes%s) not applied: only 1/2/4/8-byte downloads are",
                        dev.name, cmd.index, cmd.subindex, len(cmd.data), ", complete access" * cmd.complete_access)
            continue
        out.append(sdo)
    return tuple(out)


def object_infos(dev: EsiDevice) -> tuple[tuple[tuple[int, int], ObjectInfo], ...]:
    """Name and type of each integer object of the device that the agent's table lacks (its
    vendor objects): for ``objects`` in the drive's status."""
    out = []
    for key, o in sorted(dev.objects.items()):
        if key in OBJECTS:
            continue
        dtype = INT_TYPES.get((o.kind, o.bits))
        if dtype is None and o.kind in ("bool", "uint") and o.bits < 8:
            dtype = "u8"
        if dtype is None:
            continue
        name = o.name if o.subindex == 0 or not o.object_name else f"{o.object_name}: {o.name}"
        out.append((key, ObjectInfo(name[:NAME_MAX], dtype)))
    return tuple(out)


def _entries_text(entries: Sequence[int]) -> str:
    return " ".join(f"{e >> 16:04X}:{(e >> 8) & 0xFF:02X}/{e & 0xFF}" for e in entries) or "empty"


def mapping_differences(dev: EsiDevice, m: SlaveMapping) -> list[str]:
    """Where the slave's mapping differs from the ESI default (the ``Sm`` assignment and those
    PDOs' entries); empty when it is the default."""
    out = []
    for rx, assigned, entries in ((True, m.rx_pdos, m.rx), (False, m.tx_pdos, m.tx)):
        side = "RxPDO (0x1C12)" if rx else "TxPDO (0x1C13)"
        default = dev.default_assign(rx)
        if tuple(assigned) != default:
            out.append(f"{side} assigns {', '.join(f'0x{p:04X}' for p in assigned) or 'none'}; the ESI default is "
                       f"{', '.join(f'0x{p:04X}' for p in default) or 'none'}")
        for pdo in assigned:
            esi = dev.pdo(pdo)
            have = [(e.index << 16) | (e.subindex << 8) | e.bits for e in entries if e.pdo == pdo]
            if esi is None:
                out.append(f"{side} 0x{pdo:04X} is not in the ESI")
            elif have != [e.mapping for e in esi.entries]:
                out.append(f"{side} 0x{pdo:04X} maps [{_entries_text(have)}]; the ESI default is "
                           f"[{_entries_text([e.mapping for e in esi.entries])}]")
    return out


def esi_setup(setup: SlaveSetup, dev: EsiDevice, init_cmds: bool = True) -> SlaveSetup:
    """``setup`` with the device's InitCmds (PRE-OP ones before the configured start-up SDOs,
    which they never repeat: the TOML wins) and its vendor objects' names and types."""
    own = {(sdo.index, sdo.subindex) for sdo in setup.sdos}
    pre = init_sdos(dev, PREOP_TRANSITIONS, own) if init_cmds else ()
    post = init_sdos(dev, SAFEOP_TRANSITIONS, own) if init_cmds else ()
    return replace(setup, sdos=pre + setup.sdos, safeop_sdos=post + setup.safeop_sdos, objects=object_infos(dev))
