"""What a twin runs for an expected fleet (pure: no I/O, no processes).

For each host of the fleet file (``supervisor.fleetfile``) the twin starts one bus agent whose
configuration names exactly the fleet's axes: ``[[drives]] slave = i, axis = <i-th axis>``, the
groups that have a member on that host, the host's optional ``profile`` and ``cycle_us``, and
its ``agent = {...}`` overrides merged on top. Keys the twin owns (the host name, the backend,
the drives and the Zenoh endpoints) cannot be overridden: an override of them is an error that
names the host and the key, raised before anything starts.

A host whose fleet entry names device files runs those drives: EDS files make it a CANopen
host (``canopen-sim --eds`` per axis and the agent's ``[can]`` with each node's ``eds``, on an
interface-local IPv6 multicast group of its own: :func:`can_channel`), ESI files an EtherCAT host
of the ``ecat`` backend (``ecat-sim --esi`` per axis: :func:`sim_device_args`).

Every agent configuration built here is validated by ``bus_agent.config.config_from_dict``, so a
bad override fails with the agent's own message (``hosts.h1.agent: reflex: 'x' is not one of ...``).
"""

from __future__ import annotations

import copy
import itertools
from dataclasses import dataclass
from typing import Any, Mapping

from bus_agent.bus.canopen.pdo import check_frames, eds_mapping
from bus_agent.config import AgentConfig, ConfigError, config_from_dict
from bus_agent.devices.eds import EdsError, load as load_eds
from supervisor.fleetfile import ExpectedFleet, HostSpec

BACKENDS = ("sim", "ecat")
#: Top-level agent TOML keys the twin sets itself; a fleet file's ``agent`` table may not touch them.
TWIN_OWNED_KEYS = frozenset({"host", "ifname", "sim_drives", "drives", "zenoh", "gateway", "can"})


class PlanError(ValueError):
    """The fleet cannot be run as a twin (a forbidden or invalid agent override); names host and key."""


@dataclass(frozen=True)
class HostPlan:
    """One host of the twin: its name, axes in slave order and its agent's TOML content."""

    name: str
    axes: tuple[str, ...]
    agent_toml: Mapping[str, Any]

    def slave_of(self, axis: str) -> int:
        """The slave position the twin gave ``axis`` (its index in the fleet file)."""
        return self.axes.index(axis)


def _merge(base: dict[str, Any], over: Mapping[str, Any]) -> dict[str, Any]:
    """``over`` on top of ``base``, tables merged key by key (a deep copy; inputs untouched)."""
    out = copy.deepcopy(base)
    for k, v in over.items():
        if isinstance(v, Mapping) and isinstance(out.get(k), dict):
            out[k] = _merge(out[k], v)
        else:
            out[k] = copy.deepcopy(v)
    return out


def can_channel(twin_id: int, host_index: int) -> str:
    """A CAN host's udp_multicast group: IPv6 interface-local scope (ff11::, RFC 4291 §2.7), which
    the kernel delivers through loopback only, distinct per twin and host."""
    return f"ff11::7a64:{twin_id & 0xFFFF:x}:{host_index + 1:x}"


def can_pdo_policy(path: str, node_id: int) -> str:
    """``eds`` (the node's own default mapping) when the cycle can run it, else ``default`` (the
    project's layout, written by SDO). PlanError when the EDS cannot be read."""
    try:
        return "default" if check_frames(eds_mapping(load_eds(path, node_id))) else "eds"
    except EdsError as e:
        raise PlanError(str(e)) from None


def sim_device_args(spec: HostSpec) -> list[str]:
    """The simulator arguments that make ``spec``'s drives: ``--esi``/``--eds FILE[*COUNT]`` for
    each run of equal device files, in axis order; nothing for the built-in drives."""
    if not spec.devices:
        return []
    flag = f"--{spec.device_kind}"
    args: list[str] = []
    for device, run in itertools.groupby(spec.devices):
        n = len(list(run))
        args += [flag, device if n == 1 else f"{device}*{n}"]
    return args


def agent_toml(fleet: ExpectedFleet, spec: HostSpec, backend: str, connect: str, ifname: str = "",
               pki: str = "", can: str = "") -> dict[str, Any]:
    """The agent TOML content (as a dict) for ``spec``: ``connect`` is its one Zenoh endpoint (the
    host's link to the router); ``ifname`` the EtherCAT master end for the ``ecat`` backend;
    ``pki`` a drives-pki directory holding the host's certificate (its identity is its name);
    ``can`` the udp_multicast group of a host with EDS devices."""
    if backend not in BACKENDS:
        raise PlanError(f"backend {backend!r} is not one of {', '.join(BACKENDS)}")
    where = f"fleet {fleet.source}: hosts.{spec.name}"
    if spec.device_kind == "esi" and backend != "ecat":
        raise PlanError(f"{where}: ESI devices run on ecat-sim: use the ecat backend (root)")
    if spec.devices and pki:
        raise PlanError(f"{where}: a secure twin (--pki) runs built-in drives only (device files: no TLS for the "
                        "simulator's fault injection)")
    forbidden = sorted(set(spec.agent) & TWIN_OWNED_KEYS)
    if forbidden:
        raise PlanError(f"fleet {fleet.source}: hosts.{spec.name}.agent: key(s) {forbidden} are set by the twin "
                        f"(host name, backend, drives from axes, zenoh endpoints); remove them")
    data: dict[str, Any] = {
        "host": spec.name,
        "zenoh": {"mode": "client", "connect": [connect], **({"pki": pki} if pki else {})},
        "drives": [{"slave": i, "axis": a} for i, a in enumerate(spec.axes)],
    }
    if spec.device_kind == "eds":
        data["can"] = {"channel": can, "interface": "udp_multicast",
                       "nodes": [{"id": i + 1, "eds": path, "pdo": can_pdo_policy(path, i + 1)}
                                 for i, path in enumerate(spec.devices)]}
    elif backend == "sim":
        data["sim_drives"] = len(spec.axes)
        if spec.profile is not None:
            data["sim_profile"] = spec.profile
    else:
        data["ifname"] = ifname
    if spec.cycle_us is not None:
        data["cycle_us"] = spec.cycle_us
    groups = {g: list(ms) for g, ms in fleet.groups.items() if any(m.split("/")[0] == spec.name for m in ms)}
    if groups:
        data["groups"] = groups
    data = _merge(data, spec.agent)
    check_agent_toml(data, f"fleet {fleet.source}: hosts.{spec.name}.agent")
    return data


def check_agent_toml(data: Mapping[str, Any], where: str) -> AgentConfig:
    """Validate agent TOML content as ``bus-agent --config`` would; PlanError naming ``where``."""
    try:
        return config_from_dict(data)
    except ConfigError as exc:
        raise PlanError(f"{where}: {exc}") from None


def plan(fleet: ExpectedFleet, backend: str, connect_of: Mapping[str, str],
         ifname_of: Mapping[str, str] | None = None, pki: str = "",
         can_of: Mapping[str, str] | None = None) -> list[HostPlan]:
    """One :class:`HostPlan` per host, in file order. ``connect_of[host]``: that host's Zenoh
    endpoint (its relay); ``ifname_of[host]``: its EtherCAT master end (``ecat`` backend);
    ``pki``: the directory with every host's certificate (a secure twin); ``can_of[host]``: the
    CAN group of a host with EDS devices."""
    return [HostPlan(spec.name, spec.axes,
                     agent_toml(fleet, spec, backend, connect_of[spec.name], (ifname_of or {}).get(spec.name, ""),
                                pki, (can_of or {}).get(spec.name, "")))
            for spec in fleet.hosts.values()]


def parse_ref(fleet: ExpectedFleet, ref: str) -> tuple[str, str]:
    """``"host/axis"`` of an expected drive -> ``(host, axis)``; PlanError naming what is wrong."""
    host, sep, axis = ref.partition("/") if isinstance(ref, str) else ("", "", "")
    if not sep or "/" in axis:
        raise PlanError(f"drive {ref!r} is not of the form 'host/axis'")
    if host not in fleet.hosts:
        raise PlanError(f"drive {ref!r}: no host {host!r} in the twin (hosts: {', '.join(fleet.hosts)})")
    if axis not in fleet.hosts[host].axes:
        raise PlanError(f"drive {ref!r}: host {host} has no axis {axis!r} (axes: {', '.join(fleet.hosts[host].axes)})")
    return host, axis


def check_host(fleet: ExpectedFleet, host: str) -> str:
    """``host`` if the twin runs it; PlanError otherwise."""
    if host not in fleet.hosts:
        raise PlanError(f"no host {host!r} in the twin (hosts: {', '.join(fleet.hosts)})")
    return host
