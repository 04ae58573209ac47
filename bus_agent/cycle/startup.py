"""Start-up of the segment: identities (0x1018), PDO mapping and start-up SDOs, SYNC0, supported modes.

Called by ``Cycle.open`` before the loop (blocking, seconds), never in a cycle:
:func:`open_segment` brings the segment to OP and returns its slaves and configured drives;
:func:`start_dc` sets up the DC steering once the slaves run.
"""

from __future__ import annotations

import dataclasses
import logging
from typing import Sequence

from bus_agent.bus.base import Bus, BusError, SlaveInfo
from bus_agent.bus.dc import DcSync
from bus_agent.bus.esi_setup import esi_setup, match_slaves
from bus_agent.devices.esi import EsiDevice, EsiError, load_esi
from bus_agent.bus.mapping import SlaveSetup
from bus_agent.cia402.controller import ControllerConfig, DriveController
from bus_agent.cia402.states import Mode
from bus_agent.config import AgentConfig, ConfigError, DriveConfig
from bus_agent.cycle.drive import CSX_MODES, MODE_UNWRITTEN, Drive
from bus_agent.cycle.timing import DcSteering
from bus_agent.motion.axis import AxisMotion

log = logging.getLogger("bus_agent.cycle.cycle")

SUPPORTED_DRIVE_MODES = 0x6502


def decode_supported_modes(bits: int) -> frozenset[int]:
    """The modes of operation set in a 0x6502 (supported drive modes) value."""
    return frozenset(int(m) for m in Mode if bits >> m.supported_bit & 1)


class IdentityMismatch(BusError):
    """A slave's 0x1018 identity is not the configured one; start-up stops."""


def open_segment(bus: Bus, config: AgentConfig, period_ns: int) -> tuple[list[SlaveInfo], list[Drive]]:
    """Open the bus, check every configured identity (0x1018), map PDOs and reach OP; the slaves
    and the configured drives (``Drive.index`` in configuration order). Raises IdentityMismatch /
    BusError / ConfigError (the caller closes the bus)."""
    slaves = list(bus.open())
    configs = config.drive_configs(len(slaves))
    for dc in configs:
        info = slaves[dc.slave]
        ident = info.identity
        if dc.identity is not None and not dc.identity.matches(ident.vendor_id, ident.product_code,
                                                             ident.revision):
            raise IdentityMismatch(
                f"slave {dc.slave} ({info.name!r}, axis {dc.axis!r}): identity vendor 0x{ident.vendor_id:08X} "
                f"product 0x{ident.product_code:08X} revision 0x{ident.revision:08X} does not match the "
                f"configured {dc.identity}")
        if dc.identity is None:
            log.info("slave %d (%s) axis %s: identity not configured, accepting vendor 0x%08X product 0x%08X",
                     dc.slave, info.name, dc.axis, ident.vendor_id, ident.product_code)
    devices = _esi_devices(config, slaves)
    setups = _slave_setups(bus, config, period_ns, configs)
    for pos, dev in devices.items():
        if pos in setups:
            setups[pos] = esi_setup(setups[pos], dev, config.esi.init_cmds)  # type: ignore[union-attr]
    overrides = {k: v for k, v in setups.items() if v != SlaveSetup()}
    bus.start(overrides or None)
    supported = {dc.slave: _read_supported_modes(bus, dc) for dc in configs}
    drives: list[Drive] = []
    for dc in configs:
        pol = dc.policy
        cc = ControllerConfig(transition_timeout_s=pol.transition_timeout_s,
                              fault_reset_retries=pol.fault_reset_retries, mode_timeout_s=pol.transition_timeout_s)
        d = Drive(cfg=dc, axis=dc.axis, slave=dc.slave,
                  ctrl=DriveController(cc, mode=dc.mode, supported_modes=supported[dc.slave]),
                  motion=AxisMotion(dc.motion, period_ns / 1e9), index=len(drives))
        _unmapped_objects(bus, d)
        drives.append(d)
    return slaves, drives


def _esi_devices(config: AgentConfig, slaves: Sequence[SlaveInfo]) -> dict[int, EsiDevice]:
    """``[esi]``/``--esi``: each slave's ESI device by identity (EsiMatchError when one has
    none; ConfigError for an unreadable file)."""
    esi = config.esi
    if esi is None:
        return {}
    try:
        devices = load_esi(esi.path)
    except EsiError as e:
        raise ConfigError(f"esi.path: {e}") from None
    found = match_slaves(devices, ((s.position, s.name, s.identity.vendor_id, s.identity.product_code,
                                    s.identity.revision) for s in slaves), esi.path)
    for pos, dev in found.items():
        log.info("slave %d: ESI device %s (%s)", pos, dev.label(), dev.source)
    return found


def _slave_setups(bus: Bus, config: AgentConfig, period_ns: int,
                  configs: Sequence[DriveConfig]) -> dict[int, SlaveSetup]:
    """Mapping policy, start-up SDOs and SYNC0 per slave. ``[dc] mode = "auto"``: SYNC0 at the
    cycle time for DC-capable slaves whose mode is cyclic synchronous (8/9/10)."""
    dcc = config.dc
    capable = getattr(bus, "dc_capable", None)
    out = {}
    for dc in configs:
        s0 = None
        if dcc.mode == "auto" and capable is not None and dc.mode in CSX_MODES and capable(dc.slave):
            s0 = (dcc.sync0_cycle_ns or period_ns, dcc.sync0_shift_ns)
        out[dc.slave] = dataclasses.replace(dc.setup, sync0=s0, sync0_before_safeop=dcc.before_safeop and s0 is not None)
    return out


def start_dc(bus: Bus, config: AgentConfig, period_ns: int, drives: Sequence[Drive], steering: DcSteering) -> None:
    """After start(): the PI that keeps the cycle in step with SYNC0, per-slave DC states."""
    states = getattr(bus, "dc_states", None)
    if states is None:
        return
    st = states()
    steering.states = tuple(st)
    for d in drives:
        d.dc = st[d.slave]
    if getattr(bus, "dc_active", False):
        dcc = config.dc
        steering.sync = DcSync(dcc.sync0_cycle_ns or period_ns, dcc.sync0_shift_ns, dcc.target_fraction)
        steering.time_ns = bus.dc_time_ns  # type: ignore[attr-defined]
        # SOEM's reference clock: the first DC-capable slave; while its drive is lost the
        # time in the frames is not the slaves' (DcSync.step holds)
        ref = next((pos for pos, s in enumerate(st) if s != "none"), None)
        steering.ref = next((d for d in drives if d.slave == ref), None)


def _unmapped_objects(bus: Bus, d: Drive) -> None:
    """From the drive's codec: which objects are served by SDO and which are absent."""
    codec_of = getattr(bus, "codec", None)
    if codec_of is None:
        return  # a backend with the fixed default layout (sim)
    codec = codec_of(d.slave)
    d.absent = tuple(f for f in codec.absent_inputs if f in ("position", "velocity", "torque"))
    d.object_names = codec.extra_names
    d.sdo_mode = (0x6060, 0) not in codec.mapped_outputs
    d.sdo_mode_display = (0x6061, 0) not in codec.mapped_inputs
    d.sdo_error_code = (0x603F, 0) not in codec.mapped_inputs
    # No SDO here: the slaves are in OP and the loop does not run yet (SM watchdog). The
    # first cycle writes the configured mode (0x6060) by SDO and reads 0x6061 back.
    d.mode_written = MODE_UNWRITTEN
    served = [n for n, f in (("0x6060", d.sdo_mode), ("0x6061", d.sdo_mode_display), ("0x603F", d.sdo_error_code)) if f]
    if served or d.absent:
        log.info("axis %s (slave %d): not mapped, served by SDO: %s; absent: %s", d.axis, d.slave,
                 ", ".join(served) or "none", ", ".join(d.absent) or "none")

def _read_supported_modes(bus: Bus, d: DriveConfig) -> frozenset[int] | None:
    """0x6502 (supported drive modes) by SDO; None (any mode tried) when the drive has no
    0x6502 or the read fails. Raises ConfigError when the configured mode is not supported."""
    sdo_read = getattr(bus, "sdo_read", None)
    if sdo_read is None:
        return None
    # read in PRE-OP by a bus that can (no SDO between OP and the first cycle: SM watchdog)
    sdo_read = getattr(bus, "preop_sdo_read", sdo_read)
    try:
        raw = sdo_read(d.slave, SUPPORTED_DRIVE_MODES, 0, 4)
        if len(raw) < 1:
            raise BusError(f"slave {d.slave}: 0x6502 is empty")
        bits = int.from_bytes(bytes(raw)[:4], "little")
    except BusError as e:
        log.info("axis %s (slave %d): supported drive modes (0x6502) not available, any mode is tried: %s",
                 d.axis, d.slave, e)
        return None
    if bits == 0:  # some drives (and their ESI) give 0x6502 = 0: nothing said, any mode tried
        log.info("axis %s (slave %d): 0x6502 = 0 (no modes listed), any mode is tried", d.axis, d.slave)
        return None
    modes = decode_supported_modes(bits)
    log.info("axis %s (slave %d): 0x6502 = 0x%08X, modes %s", d.axis, d.slave, bits, sorted(modes))
    if d.mode not in modes:
        raise ConfigError(f"axis {d.axis!r} (slave {d.slave}): configured mode {d.mode} (0x6060) is not "
                          f"supported by the drive (0x6502 = 0x{bits:08X}: modes {sorted(modes)})")
    return modes
