"""Agent configuration: frozen dataclasses loaded from TOML, with errors that name the key.

One file configures one bus agent (one host, one EtherCAT segment). ``deploy/agent.example.toml``
documents every key. Loading is pure apart from reading the file; :meth:`AgentConfig.with_overrides`
applies CLI flags and re-validates. Bad input raises :class:`ConfigError` and builds nothing.
"""

from __future__ import annotations

import dataclasses
import logging
import tomllib
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, Mapping

from bus_agent.cia402.states import Mode
from bus_agent.bus.dc import DC_MODES, DcConfig
from bus_agent.bus.mapping import POLICIES, SDO_TYPES, MappingError, MappingPolicy, SlaveSetup, StartupSdo
from bus_agent.bus.pdo import RXPDO_INDEX, TXPDO_INDEX
from bus_agent.motion.config import HomingConfig, MotionConfig, MotionConfigError
from bus_agent.security.exposure import exposed_endpoints, refusal
from bus_agent.can_config import CanConfig, can_from_table, validate_can
from bus_agent.toml_table import ConfigError, Table
from schemas.keys import InvalidKey, validate_name

log = logging.getLogger(__name__)

ZENOH_MODES = ("peer", "client", "router")
#: What a drive does when its lease holder disappears (carried out by the gateway as a DriveCommand).
LEASE_REACTIONS = ("quick_stop_then_disable", "quick_stop", "disable")
#: What the other local members of a group do when one member faults or is lost.
REFLEXES = ("quick_stop", "disable")
SIM_PROFILES = ("generic", "indy7")
#: Where the Zenoh gateway runs: a child process (the cycle keeps its GIL) or threads of the agent.
GATEWAY_MODES = ("process", "thread")
@dataclass(frozen=True)
class ZenohConfig:
    mode: str = "peer"
    listen: tuple[str, ...] = ()
    connect: tuple[str, ...] = ()
    scouting: bool = False  # multicast scouting: off unless asked (tests and plants set endpoints)
    pki: str | None = None       # drives-pki directory: mTLS links, ACL, authenticated commands
    identity: str | None = None  # principal in it; an agent's is its host name (the default)
    insecure: bool = False       # allow a non-loopback listen without pki (explicit opt-out)


@dataclass(frozen=True)
class Identity:
    """Expected 0x1018 identity of a slave; a mismatch stops start-up. ``revision`` None = any."""

    vendor_id: int
    product_code: int
    revision: int | None = None

    def matches(self, vendor_id: int, product_code: int, revision: int) -> bool:
        return (vendor_id == self.vendor_id and product_code == self.product_code
                and (self.revision is None or revision == self.revision))

    def __str__(self) -> str:
        rev = "any" if self.revision is None else f"0x{self.revision:08X}"
        return f"vendor 0x{self.vendor_id:08X} product 0x{self.product_code:08X} revision {rev}"


@dataclass(frozen=True)
class PdoMapping:
    """PDO mapping override, written by SDO in PRE-OP (0x1C12/0x1C13 assignment, 0x16xx/0x1Axx).

    The mapped objects are always the project's default layout (``bus_agent.bus.pdo``: the records
    ``DriveOutputs``/``DriveInputs`` have a fixed layout); the override chooses which PDO objects
    carry it, for drives whose power-on mapping differs from it.
    """

    rx_pdo: int = RXPDO_INDEX
    tx_pdo: int = TXPDO_INDEX


@dataclass(frozen=True)
class AutoReset:
    """Bounded, backed-off automatic fault reset. Off by default: faults are reset on command."""

    enabled: bool = False
    max_attempts: int = 3          # per window; then it stops and reports
    backoff_s: float = 1.0         # wait in Fault before the first attempt; doubled per attempt
    backoff_max_s: float = 30.0
    window_s: float = 60.0         # attempts are forgotten after this long without a fault


@dataclass(frozen=True)
class DrivePolicy:
    transition_timeout_s: float = 5.0   # per goal (seed 000's 5 s)
    fault_reset_retries: int = 3        # bounded rising edges on controlword bit 7
    auto_reset: AutoReset = AutoReset()
    lease_reaction: str = "quick_stop_then_disable"
    lease_ttl_s: float = 2.0


@dataclass(frozen=True)
class DriveConfig:
    slave: int                          # 0-based position on the segment
    axis: str = ""                      # default f"axis{slave}"
    identity: Identity | None = None    # None: any identity accepted (logged)
    mode: int = int(Mode.CYCLIC_SYNC_POSITION)
    pdo: PdoMapping | None = None       # kept: the same as mapping policy "default" into these PDOs
    policy: DrivePolicy = DrivePolicy()
    mapping: MappingPolicy | None = None  # [drives.mapping]; None: "drive" (or "default" with pdo)
    sdos: tuple[StartupSdo, ...] = ()   # [[drives.sdo]]: applied in PRE-OP, again after a power cycle
    motion: MotionConfig = MotionConfig()

    def __post_init__(self) -> None:
        if not self.axis:
            object.__setattr__(self, "axis", f"axis{self.slave}")

    @property
    def setup(self) -> SlaveSetup:
        """Mapping policy and start-up SDOs of this drive's slave: the software position limits
        of ``[drives.motion]`` (0x607D:1/2) first, then ``[[drives.sdo]]`` (which may override them)."""
        policy = self.mapping
        if policy is None:
            policy = (MappingPolicy("default", rx_pdo=self.pdo.rx_pdo, tx_pdo=self.pdo.tx_pdo) if self.pdo
                      else MappingPolicy())
        limits = tuple(StartupSdo(index, sub, "i32", value) for index, sub, value in self.motion.limit_sdos())
        return SlaveSetup(policy, limits + self.sdos)

    @property
    def needs_setup(self) -> bool:
        """True when the slave needs more than its own mapping read (a policy writes, or SDOs)."""
        return self.setup != SlaveSetup()


@dataclass(frozen=True)
class RecorderConfig:
    """``[recorder]``: the flight recorder (bus_agent/cycle/recorder.py); ``seconds = 0`` turns it off."""

    seconds: float = 10.0               # ring length: the last seconds of every cycle
    pre_s: float = 5.0                  # a frozen window: before its trigger
    post_s: float = 1.0                 # ... and after it


@dataclass(frozen=True)
class EsiConfig:
    """``[esi]`` (or ``--esi PATH``): every slave is matched to a device of these ESI files by its
    identity (none matching stops start-up); its InitCmds are made (``init_cmds = false``: not;
    ``[[drives.sdo]]`` of the same object wins) and its vendor objects named in ``objects``."""

    path: str
    init_cmds: bool = True


@dataclass(frozen=True)
class AgentConfig:
    host: str
    zenoh: ZenohConfig = ZenohConfig()
    ifname: str | None = None           # pysoem backend: NIC or veth end
    sim_drives: int = 0                 # sim backend: number of in-process drive models
    sim_profile: str = "generic"
    cycle_us: int = 1000
    drives: tuple[DriveConfig, ...] = ()  # empty: every slave found, with defaults
    groups: Mapping[str, tuple[str, ...]] = field(default_factory=dict)  # name -> "host/axis"
    reflex: str = "quick_stop"
    heartbeat_s: float = 1.0
    default_policy: DrivePolicy = DrivePolicy()
    default_motion: MotionConfig = MotionConfig()
    gateway: str = "process"            # GATEWAY_MODES
    rt_priority: int = 0                # [cycle] rt_priority: SCHED_FIFO of the cycle thread (0: off)
    express_reflex: bool = True         # [cycle] express_reflex: a remote trigger wakes the cycle (Cycle.express)
    spin_at_rest: bool = False          # [cycle] spin_at_rest: spin before deadlines with every drive off too
    dc: DcConfig = DcConfig()           # [dc]: distributed clocks (SYNC0, the cycle kept in step)
    recorder: RecorderConfig = RecorderConfig()
    can: CanConfig | None = None        # canopen backend: a CAN bus of CANopen nodes
    #: [startup] soem_call_s: deadline of each SOEM call start-up cannot interrupt (pysoem backend)
    soem_call_s: float = 30.0
    esi: EsiConfig | None = None        # [esi]: the slaves' ESI files (bus_agent.bus.esi_setup)

    def __post_init__(self) -> None:
        if self.zenoh.pki and not self.zenoh.identity:  # an agent's principal is its host name
            object.__setattr__(self, "zenoh", dataclasses.replace(self.zenoh, identity=self.host))
        _validate(self)

    @property
    def backend(self) -> str:
        return "canopen" if self.can else "pysoem" if self.ifname else "sim"

    def drive_configs(self, n_slaves: int) -> tuple[DriveConfig, ...]:
        """The drives to control on a segment of ``n_slaves``: the configured ones, or one per
        slave with defaults when none are configured. Raises ConfigError if a configured slave
        position is not on the segment."""
        if not self.drives:
            return tuple(DriveConfig(slave=i, policy=self.default_policy, motion=self.default_motion)
                         for i in range(n_slaves))
        for i, d in enumerate(self.drives):
            if d.slave >= n_slaves:
                raise ConfigError(f"drives[{i}].slave: position {d.slave} configured for axis {d.axis!r} "
                                  f"but the segment has {n_slaves} slave(s)")
        return self.drives

    def with_overrides(self, **overrides: Any) -> "AgentConfig":
        """A copy with CLI flags applied (``host``, ``ifname``, ``sim_drives``, ``sim_profile``,
        ``cycle_us``, ``reflex``, ``heartbeat_s``, ``zenoh_mode``, ``listen``, ``connect``,
        ``scouting``, ``pki``, ``identity``, ``insecure``, ``gateway``, ``rt_priority``, ``record_s``: the
        recorder's ring length, ``esi``: a path); None values are ignored. ``ifname`` clears ``sim_drives`` and vice versa."""
        o = {k: v for k, v in overrides.items() if v is not None}
        zkeys = {"zenoh_mode": "mode", "listen": "listen", "connect": "connect", "scouting": "scouting",
                 "pki": "pki", "identity": "identity", "insecure": "insecure"}
        top = {"host", "ifname", "sim_drives", "sim_profile", "cycle_us", "reflex", "heartbeat_s", "gateway",
               "rt_priority", "can", "esi"}
        if isinstance(o.get("esi"), str):  # --esi PATH: the file's [esi] options kept
            o["esi"] = dataclasses.replace(self.esi, path=o["esi"]) if self.esi else EsiConfig(o["esi"])
        record_s = o.pop("record_s", None)
        if record_s is not None:
            o["recorder"] = dataclasses.replace(self.recorder, seconds=record_s)
            top = top | {"recorder"}
        unknown = set(o) - top - set(zkeys)
        if unknown:
            raise ConfigError(f"unknown override(s): {', '.join(sorted(unknown))}")
        z = {zkeys[k]: (tuple(v) if k in ("listen", "connect") else v) for k, v in o.items() if k in zkeys}
        t = {k: v for k, v in o.items() if k in top}
        if t.get("ifname"):
            t.setdefault("sim_drives", 0)
            t.setdefault("can", None)
        elif t.get("sim_drives"):
            t.setdefault("ifname", None)
            t.setdefault("can", None)
        elif t.get("can"):
            t.setdefault("ifname", None)
            t.setdefault("sim_drives", 0)
        if "host" in t and "identity" not in z and self.zenoh.identity == self.host:
            z["identity"] = None  # derived from the old host name: derive it again
        zenoh: ZenohConfig = dataclasses.replace(self.zenoh, **z)  # type: ignore[arg-type]  # keys checked above
        return dataclasses.replace(self, zenoh=zenoh, **t)


# ---- validation -----------------------------------------------------------------------------


def _name(value: Any, key: str) -> str:
    try:
        return validate_name(value, key)
    except InvalidKey as e:
        raise ConfigError(str(e)) from None


def _validate(c: AgentConfig) -> None:
    _name(c.host, "host")
    if c.zenoh.mode not in ZENOH_MODES:
        raise ConfigError(f"zenoh.mode: {c.zenoh.mode!r} is not one of {', '.join(ZENOH_MODES)}")
    if c.zenoh.identity and c.zenoh.identity != c.host:
        raise ConfigError(f"zenoh.identity: {c.zenoh.identity!r} is not the host name {c.host!r} (an agent's "
                          "certificate is issued to its host name: drives-pki issue DIR HOST --role agent)")
    if c.zenoh.identity and not c.zenoh.pki:
        raise ConfigError("zenoh.identity needs zenoh.pki (the directory of drives-pki)")
    exposed = exposed_endpoints(c.zenoh.listen)
    if exposed and not c.zenoh.pki and not c.zenoh.insecure:
        raise ConfigError(refusal("zenoh.listen", exposed, "drives-pki init DIR; drives-pki issue DIR HOST "
                                  "--role agent; bus-agent --pki DIR"))
    if sum((bool(c.ifname), c.sim_drives > 0, c.can is not None)) > 1:
        raise ConfigError("ifname and sim_drives and can: choose one backend (a NIC, simulated drives or a CAN bus)")
    if not c.ifname and c.sim_drives <= 0 and c.can is None:
        raise ConfigError("ifname or sim_drives or can: one is required (a NIC name, a number of simulated drives > 0, "
                          "or a [can] table)")
    if c.can is not None:
        validate_can(c.can)
    if c.esi is not None and not c.ifname:
        raise ConfigError("esi: ESI files describe EtherCAT slaves: they go with ifname (the pysoem backend), "
                          "not with sim_drives or can")
    if c.sim_profile not in SIM_PROFILES:
        raise ConfigError(f"sim_profile: {c.sim_profile!r} is not one of {', '.join(SIM_PROFILES)}")
    if not 100 <= c.cycle_us <= 1_000_000:
        raise ConfigError(f"cycle_us: {c.cycle_us} is outside 100..1000000")
    if c.reflex not in REFLEXES:
        raise ConfigError(f"reflex: {c.reflex!r} is not one of {', '.join(REFLEXES)}")
    if not c.heartbeat_s > 0:
        raise ConfigError(f"status.heartbeat_s: {c.heartbeat_s} must be > 0")
    if c.gateway not in GATEWAY_MODES:
        raise ConfigError(f"gateway: {c.gateway!r} is not one of {', '.join(GATEWAY_MODES)}")
    if isinstance(c.rt_priority, bool) or not isinstance(c.rt_priority, int) or not 0 <= c.rt_priority <= 99:
        raise ConfigError(f"cycle.rt_priority: {c.rt_priority!r} must be 0 (off) or a SCHED_FIFO priority 1..99")
    if not 1.0 <= c.soem_call_s <= 600.0:
        raise ConfigError(f"startup.soem_call_s: {c.soem_call_s:g} must be 1..600 s")
    r = c.recorder
    if r.seconds and not (0 <= r.pre_s and 0 <= r.post_s and r.pre_s + r.post_s < r.seconds <= 600):
        raise ConfigError(f"recorder: need 0 <= pre_s + post_s < seconds <= 600 (got pre_s {r.pre_s:g}, "
                          f"post_s {r.post_s:g}, seconds {r.seconds:g}); seconds = 0 turns it off")
    _validate_policy(c.default_policy, "defaults")
    if c.dc.mode not in DC_MODES:
        raise ConfigError(f"dc.mode: {c.dc.mode!r} is not one of {', '.join(DC_MODES)}")
    if not 0 <= c.dc.sync0_cycle_ns <= 1_000_000_000:
        raise ConfigError(f"dc.sync0_cycle_ns: {c.dc.sync0_cycle_ns} outside 0 (the agent's cycle)..1000000000")
    if abs(c.dc.sync0_shift_ns) >= max(c.dc.sync0_cycle_ns, c.cycle_us * 1000):
        raise ConfigError(f"dc.sync0_shift_ns: {c.dc.sync0_shift_ns} must be smaller than the SYNC0 cycle")
    slaves: dict[int, int] = {}
    axes: dict[str, int] = {}
    for i, d in enumerate(c.drives):
        key = f"drives[{i}]"
        if not isinstance(d.slave, int) or d.slave < 0 or d.slave > 65535:
            raise ConfigError(f"{key}.slave: {d.slave!r} must be a position 0..65535")
        _name(d.axis, f"{key}.axis")
        if d.slave in slaves:
            raise ConfigError(f"{key}.slave: position {d.slave} already used by drives[{slaves[d.slave]}]")
        if d.axis in axes:
            raise ConfigError(f"{key}.axis: {d.axis!r} already used by drives[{axes[d.axis]}]")
        slaves[d.slave], axes[d.axis] = i, i
        if d.mode not in {int(m) for m in Mode}:
            raise ConfigError(f"{key}.mode: {d.mode!r} is not a CiA 402 mode (0x6060: 1,3,4,6,7,8,9,10)")
        _validate_policy(d.policy, key)
    for g, members in c.groups.items():
        _name(g, f"groups.{g}")
        if not members:
            raise ConfigError(f"groups.{g}: a group needs at least one member")
        for m in members:
            host, sep, axis = m.partition("/") if isinstance(m, str) else ("", "", "")
            if not sep:
                raise ConfigError(f"groups.{g}: member {m!r} must be 'host/axis'")
            _name(host, f"groups.{g} member host")
            _name(axis, f"groups.{g} member axis")
            if host == c.host and c.drives and axis not in axes:
                raise ConfigError(f"groups.{g}: member {m!r} is on this host but no drive has axis {axis!r}")


def _validate_policy(p: DrivePolicy, key: str) -> None:
    if not p.transition_timeout_s > 0:
        raise ConfigError(f"{key}.transition_timeout_s: {p.transition_timeout_s} must be > 0")
    if not 1 <= p.fault_reset_retries <= 100:
        raise ConfigError(f"{key}.fault_reset_retries: {p.fault_reset_retries} must be 1..100")
    if p.lease_reaction not in LEASE_REACTIONS:
        raise ConfigError(f"{key}.lease_reaction: {p.lease_reaction!r} is not one of {', '.join(LEASE_REACTIONS)}")
    if not p.lease_ttl_s > 0:
        raise ConfigError(f"{key}.lease_ttl_s: {p.lease_ttl_s} must be > 0")
    a = p.auto_reset
    if not 1 <= a.max_attempts <= 100:
        raise ConfigError(f"{key}.auto_reset.max_attempts: {a.max_attempts} must be 1..100")
    if not 0 < a.backoff_s <= a.backoff_max_s:
        raise ConfigError(f"{key}.auto_reset.backoff_s: must be > 0 and <= backoff_max_s")
    if not a.window_s > 0:
        raise ConfigError(f"{key}.auto_reset.window_s: must be > 0")


# ---- TOML -----------------------------------------------------------------------------------


_NUM = (int, float)


def _policy(t: Table, base: DrivePolicy) -> DrivePolicy:
    a = t.table("auto_reset")
    b = base.auto_reset
    auto = AutoReset(
        enabled=a.get("enabled", bool, b.enabled),
        max_attempts=a.get("max_attempts", int, b.max_attempts),
        backoff_s=a.get("backoff_s", _NUM, b.backoff_s),
        backoff_max_s=a.get("backoff_max_s", _NUM, b.backoff_max_s),
        window_s=a.get("window_s", _NUM, b.window_s),
    )
    a.done()
    return DrivePolicy(
        transition_timeout_s=t.get("transition_timeout_s", _NUM, base.transition_timeout_s),
        fault_reset_retries=t.get("fault_reset_retries", int, base.fault_reset_retries),
        auto_reset=auto,
        lease_reaction=t.get("lease_reaction", str, base.lease_reaction),
        lease_ttl_s=t.get("lease_ttl_s", _NUM, base.lease_ttl_s),
    )


def _entries(t: Table, name: str) -> tuple[tuple[int, int, int], ...]:
    out = []
    for k, e in enumerate(t.get(name, list, [])):
        if not isinstance(e, list) or len(e) != 3 or not all(isinstance(x, int) and not isinstance(x, bool) for x in e):
            raise ConfigError(f"{t.key(name)}[{k}]: expected [index, subindex, bits], got {e!r}")
        out.append((e[0], e[1], e[2]))
    return tuple(out)


def _ints(t: Table, name: str) -> tuple[int, ...]:
    v = t.get(name, list, [])
    for k, x in enumerate(v):
        if not isinstance(x, int) or isinstance(x, bool):
            raise ConfigError(f"{t.key(name)}[{k}]: expected a PDO index (integer), got {x!r}")
    return tuple(v)


def _mapping(t: Table, key: str) -> MappingPolicy:
    """``[drives.mapping]``: policy = drive | default | predefined | explicit (bus_agent.bus.mapping)."""
    policy = t.get("policy", str, "drive")
    if policy not in POLICIES:
        raise ConfigError(f"{key}.policy: {policy!r} is not one of {', '.join(POLICIES)}")
    try:
        mp = MappingPolicy(policy=policy, rx=_ints(t, "rx"), tx=_ints(t, "tx"), rx_entries=_entries(t, "rx_entries"),
                           tx_entries=_entries(t, "tx_entries"), rx_pdo=t.get("rx_pdo", int, RXPDO_INDEX),
                           tx_pdo=t.get("tx_pdo", int, TXPDO_INDEX))
    except MappingError as e:
        raise ConfigError(f"{key}: {e}") from None
    t.done()
    return mp


def _sdo(t: Table) -> StartupSdo:
    """``[[drives.sdo]]``: index, subindex, type, value."""
    index, sub = t.get("index", int), t.get("subindex", int, 0)
    typ, value = t.get("type", str), t.get("value", int)
    if typ not in SDO_TYPES:
        raise ConfigError(f"{t.key('type')}: {typ!r} is not one of {', '.join(SDO_TYPES)}")
    try:
        sdo = StartupSdo(index, sub, typ, value)
    except MappingError as e:
        raise ConfigError(f"{t.path}: {e}") from None
    t.done()
    return sdo


def _motion(t: Table, base: MotionConfig) -> MotionConfig:
    """``[defaults.motion]`` / ``[drives.motion]`` (keys: bus_agent.motion.config.MotionConfig)."""
    m = t.table("motion")
    h = m.table("homing")
    b = base.homing
    opt = (int, float)
    try:
        homing = HomingConfig(
            method=h.get("method", int, b.method), switch_speed=h.get("switch_speed", _NUM, b.switch_speed),
            zero_speed=h.get("zero_speed", _NUM, b.zero_speed), acceleration=h.get("acceleration", _NUM, b.acceleration),
            offset=h.get("offset", _NUM, b.offset), timeout_s=h.get("timeout_s", _NUM, b.timeout_s))
        h.done()
        out = MotionConfig(
            max_velocity=m.get("max_velocity", _NUM, base.max_velocity),
            max_acceleration=m.get("max_acceleration", _NUM, base.max_acceleration),
            max_jerk=m.get("max_jerk", _NUM, base.max_jerk),
            min_position=m.get("min_position", opt, base.min_position),
            max_position=m.get("max_position", opt, base.max_position),
            position_window=m.get("position_window", _NUM, base.position_window),
            velocity_window=m.get("velocity_window", _NUM, base.velocity_window),
            settle_s=m.get("settle_s", _NUM, base.settle_s),
            limit_policy=m.get("limit_policy", str, base.limit_policy),
            require_homing=m.get("require_homing", bool, base.require_homing),
            write_limits=m.get("write_limits", bool, base.write_limits),
            counts_per_unit=m.get("counts_per_unit", _NUM, base.counts_per_unit),
            unit=m.get("unit", str, base.unit),
            homing=homing)
    except MotionConfigError as e:
        raise ConfigError(f"{t.key(str(e))}") from None
    m.done()
    return out


def config_from_dict(data: Mapping[str, Any]) -> AgentConfig:
    """Build an AgentConfig from parsed TOML (or any mapping of the same shape)."""
    t = Table(data, "")
    z = t.table("zenoh")
    zenoh = ZenohConfig(mode=z.get("mode", str, "peer"), listen=z.strings("listen"),
                        connect=z.strings("connect"), scouting=z.get("scouting", bool, False),
                        pki=z.get("pki", str, None), identity=z.get("identity", str, None),
                        insecure=z.get("insecure", bool, False))
    z.done()
    s = t.table("status")
    heartbeat_s = s.get("heartbeat_s", _NUM, 1.0)
    s.done()
    cy = t.table("cycle")
    rt_priority = cy.get("rt_priority", int, 0)
    express_reflex = cy.get("express_reflex", bool, True)
    spin_at_rest = cy.get("spin_at_rest", bool, False)
    cy.done()
    dct = t.table("dc")
    dc = DcConfig(mode=dct.get("mode", str, "auto"), sync0_cycle_ns=dct.get("sync0_cycle_ns", int, 0),
                  sync0_shift_ns=dct.get("sync0_shift_ns", int, 0), before_safeop=dct.get("before_safeop", bool, False))
    dct.done()
    rc = t.table("recorder")
    recorder = RecorderConfig(seconds=rc.get("seconds", _NUM, 10.0), pre_s=rc.get("pre_s", _NUM, 5.0),
                              post_s=rc.get("post_s", _NUM, 1.0))
    rc.done()
    st = t.table("startup")
    soem_call_s = st.get("soem_call_s", _NUM, 30.0)
    st.done()
    defaults_t = t.table("defaults")
    defaults = _policy(defaults_t, DrivePolicy())
    default_motion = _motion(defaults_t, MotionConfig())
    defaults_t.done()
    drives = []
    for i, raw in enumerate(t.get("drives", list, [])):
        d = Table(raw, f"drives[{i}]")
        slave = d.get("slave", int)
        ident = None
        if "identity" in d.data:
            it = d.table("identity")
            ident = Identity(vendor_id=it.get("vendor_id", int), product_code=it.get("product_code", int),
                             revision=it.get("revision", int, None))
            it.done()
        pdo = None
        if "pdo" in d.data:
            pt = d.table("pdo")
            pdo = PdoMapping(rx_pdo=pt.get("rx_pdo", int, RXPDO_INDEX), tx_pdo=pt.get("tx_pdo", int, TXPDO_INDEX))
            pt.done()
            if not 0x1600 <= pdo.rx_pdo <= 0x17FF:
                raise ConfigError(f"drives[{i}].pdo.rx_pdo: 0x{pdo.rx_pdo:04X} is not an RxPDO mapping (0x1600..0x17FF)")
            if not 0x1A00 <= pdo.tx_pdo <= 0x1BFF:
                raise ConfigError(f"drives[{i}].pdo.tx_pdo: 0x{pdo.tx_pdo:04X} is not a TxPDO mapping (0x1A00..0x1BFF)")
        mapping = _mapping(d.table("mapping"), f"drives[{i}].mapping") if "mapping" in d.data else None
        if mapping is not None and pdo is not None:
            raise ConfigError(f"drives[{i}]: 'pdo' and 'mapping' both given: use mapping (policy = \"default\", "
                              "rx_pdo, tx_pdo)")
        sdos = tuple(_sdo(Table(raw_sdo, f"drives[{i}].sdo[{k}]")) for k, raw_sdo in enumerate(d.get("sdo", list, [])))
        drives.append(DriveConfig(slave=slave, axis=d.get("axis", str, ""), identity=ident,
                                  mode=d.get("mode", int, int(Mode.CYCLIC_SYNC_POSITION)), pdo=pdo,
                                  policy=_policy(d, defaults), mapping=mapping, sdos=sdos,
                                  motion=_motion(d, default_motion)))
        d.done()
    g = t.table("groups")
    groups = {name: g.strings(name) for name in list(g.data)}
    g.done()
    cfg = AgentConfig(
        host=t.get("host", str),
        zenoh=zenoh,
        ifname=t.get("ifname", str, None),
        sim_drives=t.get("sim_drives", int, 0),
        sim_profile=t.get("sim_profile", str, "generic"),
        cycle_us=t.get("cycle_us", int, 1000),
        drives=tuple(drives),
        groups=groups,
        reflex=t.get("reflex", str, "quick_stop"),
        heartbeat_s=heartbeat_s,
        default_policy=defaults,
        default_motion=default_motion,
        gateway=t.get("gateway", str, "process"),
        rt_priority=rt_priority,
        express_reflex=express_reflex,
        spin_at_rest=spin_at_rest,
        dc=dc,
        recorder=recorder,
        can=can_from_table(t.table("can")) if "can" in t.data else None,
        soem_call_s=float(soem_call_s),
        esi=_esi(t.table("esi")) if "esi" in t.data else None,
    )
    t.done()
    return cfg


def _esi(t: Table) -> EsiConfig:
    esi = EsiConfig(path=t.get("path", str), init_cmds=t.get("init_cmds", bool, True))
    t.done()
    return esi


def load_config(path: str | Path) -> AgentConfig:
    """Read and validate an agent TOML file. Raises ConfigError (file, syntax or key)."""
    p = Path(path)
    try:
        with p.open("rb") as f:
            data = tomllib.load(f)
    except OSError as e:
        raise ConfigError(f"{p}: cannot read: {e.strerror}") from None
    except tomllib.TOMLDecodeError as e:
        raise ConfigError(f"{p}: TOML syntax error: {e}") from None
    try:
        return config_from_dict(data)
    except ConfigError as e:
        raise ConfigError(f"{p}: {e}") from None
