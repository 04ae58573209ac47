"""``drives-twin`` run as a user runs it: a separate process fed commands on standard input."""

from __future__ import annotations

import sys
from pathlib import Path

from bus_agent.sim.child import ChildProcess, cmdline, descendants, wait_for


class TwinCli(ChildProcess):
    """``python -m twin.cli --fleet FLEET [extra...]``, ready at its ready line."""

    def __init__(self, fleet: Path, *extra: str) -> None:
        super().__init__("drives-twin", [sys.executable, "-m", "twin.cli", "--fleet", str(fleet), *extra],
                         ready_marker="drives-twin ready", stdin=True)

    @property
    def endpoint(self) -> str:
        line = next(ln for ln in self.lines if ln.startswith("drives-twin ready"))
        return dict(w.split("=", 1) for w in line.split()[2:])["endpoint"]

    def command(self, line: str, timeout_s: float = 30.0) -> str:
        """Send one command line; its one answer line (``ok ...`` or ``error ...``)."""
        n = len(self.lines)
        assert self.popen.stdin is not None
        self.popen.stdin.write(line + "\n")
        self.popen.stdin.flush()
        return wait_for(lambda: next((ln for ln in self.lines[n:] if ln.startswith(("ok ", "error "))), None),
                        timeout_s, f"answer to {line!r}")

    def workdir(self) -> Path:
        """The twin's work directory (where its agents' TOMLs are)."""
        conf = next(c for p in descendants(self.pid) if "--config" in (c := cmdline(p)))
        return Path(conf.split("--config ", 1)[1].split()[0]).parent
