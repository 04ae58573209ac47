"""The expected fleet: which hosts and axes should exist, and their groups (pure; no I/O but reading
the file).

One file describes a fleet for every tool that needs to know what *should* be there (``drivectl
--fleet``, ``Fleet(expected=...)``, the dashboard, the twin)::

    [hosts.h1]
    axes = ["axis0", "axis1"]
    # optional, used by tools that start agents (the twin); ignored by the others:
    # profile = "generic"      drive profile of a simulated host
    # cycle_us = 1000          cycle period
    # agent = { reflex = "disable" }   extra top-level keys of that host's agent TOML
    # device = "drive.eds"     every axis's device file: an EDS (CANopen) or ESI (EtherCAT,
    #                          "drive.xml[@PRODUCT[:REVISION]]"); relative to this file
    # devices = ["a.eds", "b.eds"]     or one per axis, in order (one kind per host)

    [hosts.h2]
    axes = ["x"]

    [groups]
    gantry = ["h1/axis0", "h2/x"]

The same content may be given as a dict (``{"hosts": {"c1": {"axes": ["a", "b"]}}}``). Unknown
keys are errors, so a typo never silently drops an expectation.
"""

from __future__ import annotations

import os
import re
import tomllib
from dataclasses import dataclass, field
from typing import Any, Mapping

#: Host and axis names, as the key space allows them (schemas/keys.py: one verbatim-free chunk).
_NAME = re.compile(r"^[A-Za-z0-9_.-]{1,64}$")
_HOST_KEYS = frozenset({"axes", "profile", "cycle_us", "agent", "device", "devices"})
#: Device-description files by suffix: EDS (CiA 306, CANopen) and ESI (ETG.2000, EtherCAT).
DEVICE_KINDS = {".eds": "eds", ".xml": "esi"}
_TOP_KEYS = frozenset({"hosts", "groups"})

#: Environment variable naming a fleet file for drivectl (the ``--fleet`` option wins).
FLEET_ENV = "DRIVES_FLEET"


class FleetFileError(ValueError):
    """The fleet description is malformed; the message names the file and the key."""


@dataclass(frozen=True)
class HostSpec:
    """One expected host: its axes in order, plus optional hints for tools that start agents."""

    name: str
    axes: tuple[str, ...]
    profile: str | None = None
    cycle_us: int | None = None
    agent: Mapping[str, Any] = field(default_factory=dict)
    #: One device file per axis (absolute paths; an ESI may carry "@PRODUCT[:REVISION]"), or none.
    devices: tuple[str, ...] = ()

    @property
    def device_kind(self) -> str | None:
        """``"eds"``, ``"esi"`` or None (the simulator's built-in drives)."""
        return device_kind(self.devices[0]) if self.devices else None


def device_kind(spec: str) -> str:
    """The kind of a device file (``FILE`` or ``FILE@PRODUCT[:REVISION]``) by its suffix; ValueError."""
    esi = spec.split("@", 1)[0]  # an ESI names its device after "@"
    kind = "esi" if esi.lower().endswith(".xml") else DEVICE_KINDS.get(os.path.splitext(spec)[1].lower())
    if kind is None:
        raise ValueError(f"{spec!r} is neither an EDS (.eds) nor an ESI (.xml)")
    return kind


@dataclass(frozen=True)
class ExpectedFleet:
    """Hosts and axes that should exist, and named groups of ``host/axis`` members."""

    hosts: Mapping[str, HostSpec]
    groups: Mapping[str, tuple[str, ...]] = field(default_factory=dict)
    source: str = "<dict>"

    def refs(self) -> list[tuple[str, str]]:
        """Every expected drive as ``(host, axis)``, hosts in file order."""
        return [(h.name, a) for h in self.hosts.values() for a in h.axes]

    def expects(self, host: str, axis: str | None = None) -> bool:
        """Whether ``host`` (and ``axis`` on it, when given) is expected."""
        spec = self.hosts.get(host)
        return spec is not None and (axis is None or axis in spec.axes)


def _err(source: str, where: str, what: str) -> FleetFileError:
    return FleetFileError(f"fleet {source}: {where}: {what}")


def _name(source: str, where: str, value: Any) -> str:
    if not isinstance(value, str) or not _NAME.match(value):
        raise _err(source, where, f"{value!r} is not a name (1-64 of [A-Za-z0-9_.-])")
    return value


def _devices(source: str, where: str, spec: Mapping[str, Any], axes: int) -> tuple[str, ...]:
    """``device`` (every axis) or ``devices`` (one per axis) as absolute paths, one kind per host."""
    if "device" in spec and "devices" in spec:
        raise _err(source, where, "give device (every axis) or devices (one per axis), not both")
    if "device" in spec:
        raw, key = [spec["device"]] * axes, "device"
    else:
        raw, key = spec.get("devices", []), "devices"
        if not isinstance(raw, list) or (raw and len(raw) != axes):
            raise _err(source, f"{where}.devices", f"a list of one device file per axis ({axes})")
    base = os.path.dirname(os.path.abspath(source)) if source != "<dict>" else os.getcwd()
    out = []
    for d in raw:
        if not isinstance(d, str) or not d:
            raise _err(source, f"{where}.{key}", f"{d!r} is not a file name")
        try:
            device_kind(d)
        except ValueError as e:
            raise _err(source, f"{where}.{key}", str(e)) from None
        out.append(os.path.join(base, d))
    if len({device_kind(d) for d in out}) > 1:
        raise _err(source, f"{where}.{key}", "EDS and ESI files mixed: a host's drives are on one bus")
    return tuple(out)


def parse(data: Mapping[str, Any], source: str = "<dict>") -> ExpectedFleet:
    """Validate ``data`` (the TOML's content, or the same as a dict) into an :class:`ExpectedFleet`."""
    if not isinstance(data, Mapping):
        raise _err(source, "top level", "must be a table")
    unknown = set(data) - _TOP_KEYS
    if unknown:
        raise _err(source, "top level", f"unknown key(s) {sorted(unknown)}; allowed: hosts, groups")
    raw_hosts = data.get("hosts")
    if not isinstance(raw_hosts, Mapping) or not raw_hosts:
        raise _err(source, "hosts", "at least one [hosts.NAME] table with axes = [...] is required")
    hosts: dict[str, HostSpec] = {}
    for hname, spec in raw_hosts.items():
        _name(source, "hosts", hname)
        where = f"hosts.{hname}"
        if not isinstance(spec, Mapping):
            raise _err(source, where, "must be a table")
        bad = set(spec) - _HOST_KEYS
        if bad:
            raise _err(source, where, f"unknown key(s) {sorted(bad)}; allowed: {sorted(_HOST_KEYS)}")
        axes = spec.get("axes")
        if not isinstance(axes, list) or not axes:
            raise _err(source, f"{where}.axes", "a non-empty list of axis names is required")
        names = tuple(_name(source, f"{where}.axes", a) for a in axes)
        if len(set(names)) != len(names):
            raise _err(source, f"{where}.axes", "axis names repeat")
        profile = spec.get("profile")
        if profile is not None and not isinstance(profile, str):
            raise _err(source, f"{where}.profile", "must be a string")
        cycle_us = spec.get("cycle_us")
        if cycle_us is not None and (not isinstance(cycle_us, int) or isinstance(cycle_us, bool)
                                     or not 100 <= cycle_us <= 1_000_000):
            raise _err(source, f"{where}.cycle_us", "must be an integer 100..1000000")
        agent = spec.get("agent", {})
        if not isinstance(agent, Mapping):
            raise _err(source, f"{where}.agent", "must be a table of agent TOML keys")
        devices = _devices(source, where, spec, len(names))
        if devices and profile is not None:
            raise _err(source, f"{where}.profile", "a host with device files has no built-in profile")
        hosts[hname] = HostSpec(hname, names, profile, cycle_us, dict(agent), devices)
    groups: dict[str, tuple[str, ...]] = {}
    raw_groups = data.get("groups", {})
    if not isinstance(raw_groups, Mapping):
        raise _err(source, "groups", "must be a table of name = [\"host/axis\", ...]")
    for gname, members in raw_groups.items():
        _name(source, "groups", gname)
        if not isinstance(members, list) or not members:
            raise _err(source, f"groups.{gname}", "a non-empty list of \"host/axis\" members is required")
        for m in members:
            if not isinstance(m, str) or m.count("/") != 1:
                raise _err(source, f"groups.{gname}", f"member {m!r} must be 'host/axis'")
            h, a = m.split("/")
            if h not in hosts or a not in hosts[h].axes:
                raise _err(source, f"groups.{gname}", f"member {m!r} is not an expected drive")
        groups[gname] = tuple(members)
    return ExpectedFleet(hosts, groups, source)


def load(source: str | os.PathLike[str] | Mapping[str, Any]) -> ExpectedFleet:
    """Read a fleet file (TOML path) or take the same content as a dict."""
    if isinstance(source, Mapping):
        return parse(source)
    path = os.fspath(source)
    try:
        with open(path, "rb") as f:
            data = tomllib.load(f)
    except OSError as e:
        raise FleetFileError(f"fleet {path}: cannot read: {e.strerror or e}") from None
    except tomllib.TOMLDecodeError as e:
        raise FleetFileError(f"fleet {path}: not valid TOML: {e}") from None
    return parse(data, path)
