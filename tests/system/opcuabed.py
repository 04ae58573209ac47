"""A secure fleet with drives-opcua in front, and an independent OPC UA client (node-opcua).

Processes (all real, loopback): a ``drives-router --pki``, a ``bus-agent --pki`` on simulated
drives (host h1), ``drives-opcua --pki`` (principal ``opcua``), and ``node`` running
tests/system/opcua/client.js, driven line by line (:class:`UaClient`).

node-opcua-client is installed once into ``.venv/opcua-client`` (``make venv`` does it; this
module does it too when it is missing), never into git.
"""

from __future__ import annotations

import json
import os
import shutil
import subprocess
import sys
import threading
import time
from pathlib import Path
from typing import Any, Callable

from bus_agent.sim.child import ROOT, ChildProcess, free_port

NODE_PACKAGE = "node-opcua-client@2.186.4"
CLIENT_DIR = ROOT / ".venv" / "opcua-client"
CLIENT_JS = Path(__file__).parent / "opcua" / "client.js"


def client_modules() -> Path | None:
    """``.venv/opcua-client/node_modules`` with node-opcua-client, installed if missing; None
    when node or npm is missing."""
    modules = CLIENT_DIR / "node_modules"
    if (modules / "node-opcua-client" / "package.json").is_file():
        return modules
    if not shutil.which("node") or not shutil.which("npm"):
        return None
    CLIENT_DIR.mkdir(parents=True, exist_ok=True)
    subprocess.run(["npm", "install", "--prefix", str(CLIENT_DIR), "--no-audit", "--no-fund", "--loglevel=error",
                    NODE_PACKAGE], check=True, timeout=600)
    return modules


class UaClient(ChildProcess):
    """node-opcua in its own process: :meth:`request` sends one command and returns its answer;
    data changes and events are collected in :attr:`notes`."""

    def __init__(self, name: str = "opcua-client") -> None:
        modules = client_modules()
        assert modules is not None
        self.answers: dict[int, dict[str, Any]] = {}
        self.notes: list[dict[str, Any]] = []
        self.cv = threading.Condition()
        self.next_id = 0
        old = os.environ.get("NODE_PATH")
        os.environ["NODE_PATH"] = str(modules)
        try:
            # Node 20 refuses RSA PKCS#1 v1.5 decryption, which OPC UA's password tokens use.
            super().__init__(name, ["node", "--security-revert=CVE-2023-46809", str(CLIENT_JS)], stdin=True)
        finally:
            if old is None:
                os.environ.pop("NODE_PATH")
            else:
                os.environ["NODE_PATH"] = old

    def on_line(self, line: str) -> None:
        try:
            msg = json.loads(line)
        except ValueError:
            return  # node-opcua's own warnings
        with self.cv:
            if "id" in msg:
                self.answers[msg["id"]] = msg
            else:
                self.notes.append(msg)
            self.cv.notify_all()

    def request(self, op: str, timeout_s: float = 30.0, **fields: Any) -> dict[str, Any]:
        with self.cv:
            self.next_id += 1
            rid = self.next_id
        assert self.popen.stdin is not None
        self.popen.stdin.write(json.dumps({"id": rid, "op": op, **fields}) + "\n")
        self.popen.stdin.flush()
        with self.cv:
            if not self.cv.wait_for(lambda: rid in self.answers or self.popen.poll() is not None, timeout_s):
                raise AssertionError(f"{op}: no answer in {timeout_s} s:\n{self.output()}")
            if rid not in self.answers:
                raise AssertionError(f"{op}: client exited:\n{self.output()}")
            return self.answers.pop(rid)

    def wait_note(self, pred: Callable[[dict[str, Any]], bool], timeout_s: float = 10.0) -> dict[str, Any]:
        """The first data change or event (from now on or already collected) for which ``pred`` holds."""
        with self.cv:
            found: list[dict[str, Any]] = []

            def check() -> bool:
                found[:] = [n for n in self.notes if pred(n)][:1]
                return bool(found)

            if not self.cv.wait_for(check, timeout_s):
                raise AssertionError(f"no matching notification in {timeout_s} s; got {self.notes[-10:]}")
            return found[0]


class OpcuaBed:
    """PKI, router, agent h1 (2 simulated drives), drives-opcua; :meth:`client` starts clients."""

    USERS = {"olga": ("operator", "olga-secret-1"), "vic": ("viewer", "vic-secret-1"),
             "mia": ("maintenance", "mia-secret-1")}

    def __init__(self, tmp: Path) -> None:
        from bus_agent.security import pki, users

        self.tmp = tmp
        self.pki = tmp / "pki"
        pki.init(self.pki)
        for name, roles, opcua in (("r1", ["router"], False), ("h1", ["agent", "testbed"], False),
                                   ("tb", ["testbed"], False), ("opcua", ["operator", "maintenance"], True),
                                   ("scada", ["viewer"], True), ("carl", ["operator"], True)):
            pki.issue(self.pki, name, roles, opcua=opcua)
        pki.issue(self.pki, "dora", ["operator"], hosts=["h9"], opcua=True)  # commands to h9 only
        for name, (role, password) in self.USERS.items():
            users.set_user(self.pki, name, [role], password)
        # A client certificate of another CA (an unknown client).
        self.other = tmp / "other-ca"
        pki.init(self.other)
        pki.issue(self.other, "scada", ["viewer"], opcua=True)
        (tmp / "fleet.toml").write_text('[hosts.h1]\naxes = ["axis0", "axis1"]\n\n[hosts.h9]\naxes = ["axis0"]\n')
        self.zenoh_ep = f"tls/127.0.0.1:{free_port()}"
        self.endpoint = f"opc.tcp://127.0.0.1:{free_port()}"
        self.procs: list[ChildProcess] = []
        self.router = self._start("drives-router", [sys.executable, "-m", "bus_agent.router", "--pki", str(self.pki),
                                                    "--identity", "r1", "--listen", self.zenoh_ep],
                                  "drives-router ready")
        cfg = tmp / "h1.toml"
        cfg.write_text(f'host = "h1"\nsim_drives = 2\n\n[zenoh]\npki = "{self.pki}"\nconnect = ["{self.zenoh_ep}"]\n')
        self.agent = self._start("bus-agent h1", [sys.executable, "-m", "bus_agent.cli", "--config", str(cfg),
                                                  "--log-level", "INFO"], "bus-agent ready", 60)
        self.server = self._start("drives-opcua", [sys.executable, "-m", "drives_opcua.cli", "--connect", self.zenoh_ep,
                                                   "--endpoint", self.endpoint, "--fleet", str(tmp / "fleet.toml"),
                                                   "--pki", str(self.pki), "--identity", "opcua",
                                                   "--log-level", "INFO"], "drives-opcua ready", 60)
        self.clients: list[UaClient] = []
        self._maintenance: tuple[UaClient, int] | None = None

    def _start(self, name: str, argv: list[str], marker: str, timeout_s: float = 30.0) -> ChildProcess:
        p = ChildProcess(name, argv, ready_marker=marker)
        self.procs.append(p)
        p.expect_ready(timeout_s)
        return p

    def client(self, *, user: dict[str, Any] | None = None, secure: bool = False, ca: Path | None = None,
               app: str = "scada", **extra: Any) -> tuple[UaClient, dict[str, Any]]:
        """A connected client and the connect answer (``ok`` false when refused). ``secure``:
        Basic256Sha256 SignAndEncrypt with application certificate ``app`` of ``ca``."""
        c = UaClient()
        self.clients.append(c)
        # Every client has an application certificate (of the CA, or of ``ca``): node-opcua would
        # otherwise make a self-signed one, seconds of RSA work per client.
        d = ca or self.pki
        fields: dict[str, Any] = {"endpoint": self.endpoint, "pkiFolder": str(self.tmp / f"client-pki-{d.name}"),
                                  "securityMode": "SignAndEncrypt" if secure else "None", "user": user,
                                  "clientCert": str(d / f"{app}.pem"), "clientKey": str(d / f"{app}.key"),
                                  "caCert": str(self.pki / "ca.pem"), "applicationUri": f"urn:zenoh-drives:{app}"}
        return c, c.request("connect", **fields, **extra)

    def maintenance(self) -> tuple[UaClient, int]:
        """One logged-in maintenance client (mia) kept for the module, and the namespace index."""
        if self._maintenance is None:
            c, a = self.client(user=self.password("mia"))
            assert a["ok"], a
            self._maintenance = (c, a["namespaces"].index("urn:zenoh-drives"))
        return self._maintenance

    def password(self, name: str) -> dict[str, Any]:
        return {"type": "password", "name": name, "password": self.USERS[name][1]}

    def certificate(self, name: str) -> dict[str, Any]:
        return {"type": "certificate", "cert": str(self.pki / f"{name}.pem"), "key": str(self.pki / f"{name}.key")}

    def close(self) -> None:
        for c in self.clients:
            c.stop(5)
        for p in reversed(self.procs):
            p.stop()


def wait(pred: Callable[[], bool], timeout_s: float = 10.0) -> bool:
    deadline = time.monotonic() + timeout_s
    while time.monotonic() < deadline:
        if pred():
            return True
        time.sleep(0.05)
    return pred()


if __name__ == "__main__":  # `make opcua-client`
    found = client_modules()
    if found is None:
        # Outside CI the OPC UA tests then skip saying so (tests/conftest.py require); in CI they fail.
        print("opcua-client: node and npm are needed for tests/system/test_opcua.py (deploy/apt-packages.txt: "
              "nodejs)", file=sys.stderr)
        sys.exit(1 if os.environ.get("CI", "").lower() in ("1", "true", "yes") else 0)
    print(f"node-opcua-client ready in {found}")
