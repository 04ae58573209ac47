"""What a twin killed with SIGKILL leaves behind, found and removed by the next start or ``--cleanup``.

A twin's children die with it (``bus_agent.sim.child``: ``PR_SET_PDEATHSIG``), and its link
relays are threads of its own process. What a SIGKILLed twin cannot remove is on disk and in the
kernel: its work directory (UNIX sockets, agent TOMLs, certificates) and, with the ecat backend,
its network namespaces (each holding its host's veth pair, deleted with it). So before it creates
anything a twin writes ``owner.json`` into its work directory: its pid, that pid's start time
(``/proc/<pid>/stat`` field 22, so a reused pid is not taken for the owner) and its namespaces.

:func:`clean_stale` (called by every :meth:`twin.Twin.start`, and by ``drives-twin --cleanup``)
removes the work directories under the temporary directory (``TMPDIR``) whose owner is gone,
with their namespaces and veth pairs. A twin that is still running is never touched; a directory
without ``owner.json`` (a twin between creating it and writing it) neither. Namespaces need root:
without it they are reported, not removed.
"""

from __future__ import annotations

import json
import logging
import os
import shutil
import tempfile
from pathlib import Path
from typing import Any, Mapping

from bus_agent.sim.netns import NetnsError

from .ecat import EcatHost, ecat_down

log = logging.getLogger(__name__)

WORKDIR_PREFIX = "drives-twin-"
OWNER_FILE = "owner.json"


def start_ticks(pid: int) -> int | None:
    """When process ``pid`` started (clock ticks since boot), or None if there is no such process."""
    try:
        stat = Path(f"/proc/{pid}/stat").read_text()
    except OSError:
        return None
    return int(stat.rsplit(")", 1)[1].split()[19])  # field 22; fields 1-2 end at the ")"


def write_owner(workdir: str, ecat_hosts: Mapping[str, EcatHost]) -> None:
    """Record this process as the owner of ``workdir`` and of the namespaces of ``ecat_hosts``."""
    pid = os.getpid()
    record = {"pid": pid, "start_ticks": start_ticks(pid),
              "ecat": [{"netns": e.netns, "master": e.master, "sim": e.sim} for e in ecat_hosts.values()]}
    tmp = Path(workdir, OWNER_FILE + ".tmp")
    tmp.write_text(json.dumps(record))
    tmp.replace(Path(workdir, OWNER_FILE))  # whole or absent: a half-written record is never read


def owner_gone(record: Mapping[str, Any]) -> bool:
    """Whether the process that wrote ``record`` no longer runs (its pid is free or reused)."""
    ticks = start_ticks(int(record["pid"]))
    return ticks is None or ticks != record.get("start_ticks")


def stale_workdirs(tmpdir: str | None = None) -> list[tuple[Path, dict[str, Any]]]:
    """Work directories (with their owner record) of twins whose process is gone."""
    out = []
    for d in sorted(Path(tmpdir or tempfile.gettempdir()).glob(WORKDIR_PREFIX + "*")):
        try:
            if d.stat().st_uid != os.geteuid():
                continue
            record = json.loads((d / OWNER_FILE).read_text())
        except (OSError, ValueError):
            continue  # not ours, being created, or not a twin's
        if isinstance(record, dict) and "pid" in record and owner_gone(record):
            out.append((d, record))
    return out


def clean_stale(tmpdir: str | None = None) -> list[str]:
    """Remove what dead twins left (see the module docstring); one line per thing removed or kept."""
    done = []
    for d, record in stale_workdirs(tmpdir):
        kept = False
        for e in record.get("ecat", []):
            host = EcatHost(netns=e["netns"], master=e["master"], sim=e["sim"])
            if os.geteuid() != 0:
                done.append(f"kept namespace {host.netns} of dead twin {record['pid']}: removing it needs root")
                kept = True
                continue
            try:
                ecat_down(host)
                done.append(f"removed namespace {host.netns} of dead twin {record['pid']}")
            except NetnsError as exc:
                done.append(f"could not remove namespace {host.netns}: {exc}")
                kept = True
        if not kept:  # keep the record while a namespace is left, so a later run still finds it
            shutil.rmtree(d, ignore_errors=True)
            done.append(f"removed work directory {d} of dead twin {record['pid']}")
    for line in done:
        log.warning("twin cleanup: %s", line)
    return done
