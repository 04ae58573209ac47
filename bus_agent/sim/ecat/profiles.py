"""Per-slave profiles of ``ecat-sim``: drives that map PDOs the way real ones do.

A profile is a drive model (:class:`bus_agent.sim.drive_model.DriveProfile`: identity, modes,
state machine quirks) plus a PDO catalogue: which PDOs the drive offers, which it assigns at
power-on, and what the master may change (ETG.1000.6 §5.6.7.4). One segment can mix them:
``ecat-sim --profile generic*2,omron1s*4,roassign``.

- ``generic`` / ``indy7``: flexible mapping (0x1600..0x1603 / 0x1A00..0x1A03 writable in PRE-OP).
- ``omron1s``: predefined PDOs only, selected through 0x1C12/0x1C13 (Omron 1S-like: RxPDO 0x1701 =
  6040, 607A, 60B8, 60FE:01; TxPDO 0x1B01 = 603F, 6041, 6064, 6077, 60F4, 60B9, 60BA, 60BC, 60FD);
  entries read-only (0x06010002), an assignment entry written while sub 0 != 0 is refused
  (0x06010003), a PDO it does not offer is out of range (0x06090030); 0x6060, 0x6061 and 0x606C
  are served by SDO only.
- ``roassign``: the generic drive with a read-only 0x1C12 and 0x1600 (writes: 0x06010002).

Modifiers: ``:dc`` makes a profile DC capable (0x0008 bit 2, system time, SYNC0); ``:dc-required``
also refuses OP in modes 8/9/10 without SYNC0 (AL 0x0030) and raises a sync error (0x001A) when
process data stops arriving in step with SYNC0. ``:no-mailbox``: a slave without a mailbox (SII
mailbox sizes 0, SM0/SM1 unused); ``:no-coe``: a mailbox without CoE (SII protocols: FoE only;
a CoE request is answered with the mailbox error "unsupported protocol").
"""

from __future__ import annotations

from dataclasses import dataclass, field, replace
from typing import Mapping, Sequence

from bus_agent.bus.pdo import RXPDO_DEFAULT, RXPDO_INDEX, TXPDO_DEFAULT, TXPDO_INDEX, mapping_entry
from bus_agent.sim.drive_model import PROFILES as DRIVE_PROFILES
from bus_agent.sim.drive_model import DriveProfile, ObjectEntry
from bus_agent.sim.ecat.sii import COE_DETAILS, MBX_PROTO_COE, SM_DEFAULTS, SmDefault

ABORT_READ_ONLY = 0x06010002
ABORT_SUB0_FIRST = 0x06010003
ABORT_WRONG_STATE = 0x08000022


def _entries(*objs: tuple[int, int, int]) -> tuple[int, ...]:
    return tuple(mapping_entry(i, s, b) for i, s, b in objs)


@dataclass(frozen=True)
class PdoCatalog:
    """The PDOs a simulated drive offers and what the master may change in PRE-OP."""

    maps: Mapping[int, tuple[int, ...]]          # PDO index -> power-on u32 entries
    assign: Mapping[int, tuple[int, ...]]        # 0x1C12/0x1C13 -> power-on PDO indices
    writable_maps: frozenset[int] = frozenset()  # PDOs whose entries the master may write
    writable_assign: frozenset[int] = frozenset({0x1C12, 0x1C13})
    sub0_first_abort: int = ABORT_WRONG_STATE    # an entry written while sub 0 != 0
    max_entries: int = 8
    max_pdos: int = 4
    #: PDO -> the PDOs it may not be assigned with (ESI <Exclude>): abort 0x06040043
    excludes: Mapping[int, frozenset[int]] = field(default_factory=dict)


def _flexible(ro_rx: bool = False) -> PdoCatalog:
    maps: dict[int, tuple[int, ...]] = {}
    for base, default in ((RXPDO_INDEX, RXPDO_DEFAULT), (TXPDO_INDEX, TXPDO_DEFAULT)):
        for k in range(4):
            maps[base + k] = _entries(*(e[:3] for e in default)) if k == 0 else ()
    writable = frozenset(p for p in maps if not (ro_rx and p == RXPDO_INDEX))
    return PdoCatalog(maps=maps, assign={0x1C12: (RXPDO_INDEX,), 0x1C13: (TXPDO_INDEX,)}, writable_maps=writable,
                      writable_assign=frozenset({0x1C13} if ro_rx else {0x1C12, 0x1C13}))


FLEXIBLE = _flexible()
READ_ONLY_RX = _flexible(ro_rx=True)
OMRON_LIKE = PdoCatalog(
    maps={
        0x1701: _entries((0x6040, 0, 16), (0x607A, 0, 32), (0x60B8, 0, 16), (0x60FE, 1, 32)),
        0x1702: _entries((0x6040, 0, 16), (0x607A, 0, 32), (0x60FF, 0, 32), (0x6071, 0, 16), (0x60B8, 0, 16)),
        0x1B01: _entries((0x603F, 0, 16), (0x6041, 0, 16), (0x6064, 0, 32), (0x6077, 0, 16), (0x60F4, 0, 32),
                         (0x60B9, 0, 16), (0x60BA, 0, 32), (0x60BC, 0, 32), (0x60FD, 0, 32)),
        0x1B02: _entries((0x603F, 0, 16), (0x6041, 0, 16), (0x6064, 0, 32), (0x6077, 0, 16), (0x60FD, 0, 32)),
    },
    assign={0x1C12: (0x1701,), 0x1C13: (0x1B01,)},
    sub0_first_abort=ABORT_SUB0_FIRST, max_pdos=3, max_entries=10)


@dataclass(frozen=True)
class EcatProfile:
    """One slave type of ``ecat-sim``: drive model plus PDO catalogue."""

    name: str
    description: str
    drive: DriveProfile
    pdos: PdoCatalog = field(default=FLEXIBLE)
    dc: bool = False           # DC capable (0x0008 bit 2; the registers SOEM uses; SYNC0)
    dc_required: bool = False  # refuses OP in modes 8/9/10 without SYNC0 (AL 0x0030); sync error 0x001A
    mailbox: str = "coe"       # MAILBOX_KINDS: "coe", "no-coe" (a mailbox without CoE), "none" (no mailbox)
    #: From an ESI (bus_agent.sim.ecat.esi_profile); the defaults are the built-in drives'.
    sync0_always: bool = False  # dc_required in every mode (an ESI offering only DC op modes)
    dictionary: Mapping[tuple[int, int], ObjectEntry] | None = None  # SDO-visible objects (None: built-in)
    hidden: Mapping[tuple[int, int], int] = field(default_factory=dict)  # mapped objects not in it
    sms: tuple[SmDefault, ...] = SM_DEFAULTS   # SM0..SM3: mailbox out/in, outputs, inputs
    coe_details: int = COE_DETAILS             # SII General byte 5 (SDO info 0x02, complete access 0x20)
    sii_order: str = ""                        # SII order string (the ESI <Type>)
    mailbox_protocols: int = MBX_PROTO_COE     # SII word 0x1C (CoE 0x04, FoE 0x08, ...): without CoE no SDO


_OMRON_DRIVE = DriveProfile(
    name="omron1s", vendor_id=0x00000ABC, product_code=0x00402101, revision=0x00010000,
    device_name="SimPredefined1S", supported_modes=DRIVE_PROFILES["generic"].supported_modes,
    statusword_extra=0x0200, not_ready_on_power_up=False, mode_echo_delay_steps=2, power_on_position=100_000,
    power_on_mode=8)
_RO_DRIVE = DriveProfile(
    name="roassign", vendor_id=0x00000ABC, product_code=0x00402102, revision=0x00010000,
    device_name="SimReadOnlyAssign", supported_modes=DRIVE_PROFILES["generic"].supported_modes,
    statusword_extra=0x0200, not_ready_on_power_up=False)

PROFILES: dict[str, EcatProfile] = {
    "generic": EcatProfile("generic", "flexible mapping, default 0x1600/0x1A00 (13/15 bytes)", DRIVE_PROFILES["generic"]),
    "indy7": EcatProfile("indy7", "generic mapping, Indy7-like power-up (0x0220, accepts Shutdown)",
                         DRIVE_PROFILES["indy7"]),
    "omron1s": EcatProfile("omron1s", "predefined PDOs only (0x1701/0x1B01 default, 0x1702/0x1B02), read-only "
                           "entries; 0x6060/0x6061/0x606C by SDO only", _OMRON_DRIVE, OMRON_LIKE),
    "roassign": EcatProfile("roassign", "flexible TxPDO, read-only 0x1C12 and 0x1600", _RO_DRIVE, READ_ONLY_RX),
}


#: What a slave's mailbox offers: CoE (a CiA 402 drive), a mailbox without CoE (its SII word
#: 0x1C names FoE only; a CoE request gets the mailbox error "unsupported protocol"), or none.
MAILBOX_KINDS = ("coe", "no-coe", "none")

#: Profile modifiers: ``omron1s:dc``, ``generic:dc-required``, ``generic:no-mailbox``.
MODIFIERS: dict[str, dict[str, object]] = {"dc": {"dc": True}, "dc-required": {"dc": True, "dc_required": True},
                                           "no-coe": {"mailbox": "no-coe"}, "no-mailbox": {"mailbox": "none"}}


def as_ecat(profile: "EcatProfile | DriveProfile | str") -> EcatProfile:
    """An EcatProfile from a profile, a drive model profile (flexible mapping) or a name."""
    if isinstance(profile, EcatProfile):
        return profile
    if isinstance(profile, DriveProfile):
        return PROFILES.get(profile.name) or EcatProfile(profile.name, profile.device_name, profile)
    name, _, mods = profile.partition(":")
    if name not in PROFILES:
        raise ValueError(f"unknown profile {name!r}; known: {', '.join(PROFILES)} "
                         f"(modifiers {', '.join(':' + m for m in MODIFIERS)})")
    base = PROFILES[name]
    if not mods:
        return base
    if mods not in MODIFIERS:
        raise ValueError(f"profile {profile!r}: unknown modifier {mods!r}; known: {', '.join(MODIFIERS)}")
    return replace(base, name=profile, **MODIFIERS[mods])  # type: ignore[arg-type]


def parse_profiles(spec: "str | EcatProfile | DriveProfile | Sequence[EcatProfile | DriveProfile | str]",
                   n: int) -> list[EcatProfile]:
    """One profile per slave from ``"generic*2,omron1s"`` (the last repeats to fill ``n``)."""
    items: list[EcatProfile] = []
    if isinstance(spec, str):
        for part in (p.strip() for p in spec.split(",")):
            name, _, count = part.partition("*")
            if count and (not count.isdigit() or int(count) < 1):
                raise ValueError(f"profile {part!r}: the count after '*' must be a positive integer")
            items.extend([as_ecat(name)] * (int(count) if count else 1))
    elif isinstance(spec, (EcatProfile, DriveProfile)):
        items = [as_ecat(spec)]
    else:
        items = [as_ecat(p) for p in spec]
    if not items:
        raise ValueError("no profile given")
    if len(items) > n:
        raise ValueError(f"{len(items)} profiles given for {n} slave(s)")
    return items + [items[-1]] * (n - len(items))
