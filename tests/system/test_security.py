"""The secure fleet's negative matrix, with real processes on loopback: a ``drives-router`` with
``--pki`` (mutual TLS, ACL compiled from principals.toml, default deny) and a ``bus-agent --pki``
on simulated drives, each its own process; attackers and observers are zenoh sessions of this
process connected through the router with their own certificates.

Each check fails if access is granted, and most have a positive control beside them (the same
act by a principal allowed to do it succeeds), so a test cannot pass because nothing works.
The positive path across two namespaced hosts is tests/system/test_security_multihost.py.
"""

from __future__ import annotations

import datetime as dt
import shutil
import subprocess
import sys
import time
from pathlib import Path
from typing import Any, Iterator

import pytest
import zenoh

from bus_agent.gateway.zenoh_config import make_zenoh_config
from bus_agent.security import pki
from bus_agent.sim.child import ROOT, ChildProcess, free_port, wait_for
from bus_agent.sim.control import SimControlError, sim_inject
from schemas import keys
from schemas import messages as m
from supervisor.fleet import Fleet, NoAgentError
from supervisor.results import DENIED
from supervisor.selectors import DriveRef

pytestmark = pytest.mark.timeout(180)

PRINCIPALS = {"r1": ["router"], "r2": ["router"], "h1": ["agent", "testbed"], "h2": ["agent"], "h9": ["agent"],
              "alice": ["operator"], "bob": ["operator"], "mia": ["maintenance"], "vic": ["viewer"],
              "tb": ["testbed"], "olga": ["operator"]}
#: Operators limited to some hosts (``drives-pki issue --hosts``).
SCOPED = {"carl": ("h1",), "dora": ("h2", "h9")}
AX0, AX1 = DriveRef("h1", "axis0"), DriveRef("h1", "axis1")


class Bed:
    def __init__(self, pki_dir: Path, endpoint: str, router: ChildProcess, agent: ChildProcess) -> None:
        self.pki = pki_dir
        self.ep = endpoint
        self.router = router
        self.agent = agent
        self.sessions: list[zenoh.Session] = []

    def session(self, identity: str, *, mode: str = "client", endpoint: str = "") -> zenoh.Session:
        s = zenoh.open(make_zenoh_config(mode, [], [endpoint or self.ep], pki=self.pki, identity=identity))
        self.sessions.append(s)
        return s

    def fleet(self, identity: str) -> Fleet:
        return Fleet(connect=[self.ep], pki=self.pki, identity=identity, connect_timeout_s=10.0)

    def close(self) -> None:
        for s in self.sessions:
            s.close()
        self.sessions.clear()


@pytest.fixture(scope="module")
def bed(tmp_path_factory: pytest.TempPathFactory) -> Iterator[Bed]:
    d = tmp_path_factory.mktemp("pki")
    pki.init(d)
    for name, roles in PRINCIPALS.items():
        pki.issue(d, name, roles)
    for name, hosts in SCOPED.items():
        pki.issue(d, name, ["operator"], hosts=hosts)
    port = free_port()
    ep = f"tls/127.0.0.1:{port}"
    router = ChildProcess("drives-router", [sys.executable, "-m", "bus_agent.router", "--pki", str(d),
                                            "--identity", "r1", "--listen", ep], ready_marker="drives-router ready")
    agent = None
    try:
        router.expect_ready(30)
        cfg = d / "h1.toml"
        # The TOML keys, not flags; a group with a member on h9 (an agent that never runs).
        cfg.write_text(f'host = "h1"\nsim_drives = 2\n\n[zenoh]\npki = "{d}"\nconnect = ["{ep}"]\n\n'
                       '[groups]\nline = ["h1/axis0", "h9/axis0"]\n')
        agent = ChildProcess("bus-agent h1", [sys.executable, "-m", "bus_agent.cli", "--config", str(cfg),
                                              "--log-level", "INFO"], ready_marker="bus-agent ready")
        agent.expect_ready(60)
        assert "identity=h1 (tls)" in agent.output()
        b = Bed(d, ep, router, agent)
        yield b
        b.close()
    finally:
        if agent is not None:
            agent.stop()
        router.stop()


@pytest.fixture()
def alice(bed: Bed) -> Iterator[Fleet]:
    """The operator; every test starts with h1's drives fault-free and disabled."""
    with bed.fleet("alice") as f:
        assert f.wait_for_agents(["h1"], timeout_s=10, drives=2), f.hosts()
        if any(st.state in ("fault", "fault_reaction_active") for st in f.fetch_status("h1/*").values()):
            with bed.fleet("mia") as mia:
                assert mia.fault_reset("h1/*").ok
        assert f.disable("h1/*").ok
        yield f


def _states(f: Fleet) -> dict[DriveRef, str]:
    return {r: st.state for r, st in f.fetch_status("h1/*").items()}


def _query(s: zenoh.Session, key: str, payload: bytes | None = None, timeout_s: float = 3.0) -> tuple[list, list, float]:
    """(ok replies as (key, bytes), error texts, seconds until the query ended)."""
    t0 = time.monotonic()
    ok, err = [], []
    for r in s.get(key, payload=payload, timeout=timeout_s, consolidation=zenoh.ConsolidationMode.NONE):
        if r.ok is not None:
            ok.append((str(r.ok.key_expr), r.ok.payload.to_bytes()))
        elif r.err is not None:
            err.append(r.err.payload.to_string())
    return ok, err, time.monotonic() - t0


def _request(op: str, supervisor: str = "", **args: Any) -> bytes:
    return m.encode(m.CommandRequest(f"t-{op}-{time.monotonic_ns()}", op, args, 2.0, supervisor))


def _status(host: str, axis: str, state: str, error_code: int = 0) -> bytes:
    return m.encode(m.DriveStatus(host=host, axis=axis, seq=1, time_ns=time.time_ns(), cycle=1, state=state,
                                  statusword=0x0008 if state == "fault" else 0x0237, controlword=0, goal="enabled",
                                  halt=False, mode=8, mode_display=8, position=0, velocity=0, torque=0,
                                  error_code=error_code))


# ---- links: no certificate, another CA, an expired certificate -----------------------------------


def _tls(ca: Path, cert: Path | None, key: Path | None) -> dict[str, Any]:
    tls: dict[str, Any] = {"root_ca_certificate": str(ca), "verify_name_on_connect": True}
    if cert is not None and key is not None:
        tls.update(connect_certificate=str(cert), connect_private_key=str(key), enable_mtls=True)
    return {"transport/link/tls": tls}


def _cannot_open(ep: str, extra: dict[str, Any] | None = None) -> str:
    try:
        s = zenoh.open(make_zenoh_config("client", [], [ep], connect_timeout_ms=1500, extra=extra))
    except zenoh.ZError as exc:
        return str(exc)
    s.close()
    raise AssertionError(f"a session opened to {ep} with {extra}")


def test_no_certificate_gets_no_link(bed: Bed) -> None:
    port = bed.ep.rsplit(":", 1)[1]
    _cannot_open(f"tcp/127.0.0.1:{port}")                                        # plain TCP to a TLS port
    _cannot_open(bed.ep, _tls(bed.pki / "ca.pem", None, None))                  # TLS, but no client certificate
    with pytest.raises(NoAgentError):
        Fleet(connect=[f"tcp/127.0.0.1:{port}"], connect_timeout_s=1.5).open()
    # Positive control: the same dial with alice's certificate works.
    f = pki.paths(bed.pki, "alice")
    s = zenoh.open(make_zenoh_config("client", [], [bed.ep], extra=_tls(f.ca, f.cert, f.key)))
    s.close()


def test_certificate_from_another_ca_gets_no_link(bed: Bed, tmp_path: Path) -> None:
    other = tmp_path / "other"
    pki.init(other)
    pki.issue(other, "alice", ["operator"])   # same name, other CA
    f = pki.paths(other, "alice")
    # Trusting our CA to check the router, presenting the other CA's alice:
    _cannot_open(bed.ep, _tls(bed.pki / "ca.pem", f.cert, f.key))


def test_expired_certificate_gets_no_link(bed: Bed, tmp_path: Path) -> None:
    d = tmp_path / "pki"
    shutil.copytree(bed.pki, d)
    pki.issue(d, "old", ["operator"], days=1, valid_from=dt.datetime.now(dt.timezone.utc) - dt.timedelta(days=30))
    f = pki.paths(d, "old")
    _cannot_open(bed.ep, _tls(f.ca, f.cert, f.key))
    with pytest.raises(ValueError, match="expired"):   # and our own tools refuse to use it
        make_zenoh_config("client", [], [bed.ep], pki=d, identity="old")


def test_a_link_ends_when_its_certificate_expires(bed: Bed, tmp_path: Path) -> None:
    """``close_link_on_expiration``: a certificate that expires while its link is up loses the
    link then (not at the next reconnection); a link with a valid certificate stays."""
    d = tmp_path / "pki"
    shutil.copytree(bed.pki, d)
    now = dt.datetime.now(dt.timezone.utc)
    pki.issue(d, "soon", ["viewer"], days=1, valid_from=now - dt.timedelta(days=1) + dt.timedelta(seconds=10))
    soon = zenoh.open(make_zenoh_config("client", [], [bed.ep], pki=d, identity="soon"))
    try:
        assert list(soon.info.routers_zid()), "linked while the certificate is valid"
        wait_for(lambda: not list(soon.info.routers_zid()), 30, "the link of the expired certificate closed")
        assert list(bed.session("vic").info.routers_zid())  # control: a valid certificate links
    finally:
        soon.close()


# ---- roles ----------------------------------------------------------------------------------------


def test_viewer_cannot_enable_reset_or_lease_but_watches(bed: Bed, alice: Fleet) -> None:
    with bed.fleet("vic") as vic:
        assert vic.wait_for_agents(["h1"], timeout_s=10, drives=2)     # reads status and agents
        report = vic.enable("h1/*", timeout_s=2.0)
        assert not report.ok
        assert {r.outcome for r in report.final} == {DENIED}, report.to_dict()
        assert all("'vic'" in r.error for r in report.final)
        for op in ("fault_reset", "lease", "quick_stop"):
            args = {"holder": "vic"} if op == "lease" else None
            res = vic.command(op, "h1/*", args, timeout_s=2.0)
            assert {r.outcome for r in res.results} == {DENIED}, (op, res.to_dict())
            assert res.elapsed_s < 1.0  # zero replies at once, not a timeout
        # Its own key under an operator's name: nothing reaches the agent.
        ok, err, _ = _query(bed.session("vic"), keys.drive_cmd("h1", "*", "enable", "alice"),
                            _request("enable", "alice"))
        assert ok == [] and err == []
    assert set(_states(alice).values()) == {"switch_on_disabled"}
    assert alice.status(AX0).lease_holder == ""


def test_maintenance_cannot_enable_but_resets_faults(bed: Bed, alice: Fleet) -> None:
    with bed.fleet("mia") as mia:
        res = mia.command("enable", "h1/*", timeout_s=2.0)
        assert {r.outcome for r in res.results} == {DENIED}, res.to_dict()
        assert set(_states(alice).values()) == {"switch_on_disabled"}
        # Positive: maintenance resets a fault (injected by the testbed principal).
        sim_inject(bed.session("tb"), "h1", 0, "fault", error_code=0x7500)
        assert wait_for(lambda: _states(alice).get(AX0) == "fault", 5, "h1/axis0 in fault")
        res = mia.fault_reset("h1/axis0")
        assert res.ok, res.to_dict()
        assert _states(alice)[AX0] == "switch_on_disabled"
    # And alice (operator) may enable.
    assert alice.enable("h1/*").ok


def test_operator_cannot_use_another_operators_lease_by_naming_them(bed: Bed, alice: Fleet) -> None:
    assert alice.lease("h1/axis0", ttl_s=30).ok
    try:
        assert alice.status(AX0) is not None
        assert wait_for(lambda: alice.fetch_status("h1/axis0")[AX0].lease_holder == "alice", 5, "lease published")
        bob_s = bed.session("bob")
        # 1. bob on his own key, claiming to be alice in the payload: refused, naming both.
        ok, err, _ = _query(bob_s, keys.drive_cmd("h1", "axis0", "enable", "bob"), _request("enable", "alice"))
        assert ok == [] and len(err) == 1 and "'alice'" in err[0] and "'bob'" in err[0], err
        # 2. bob releasing alice's lease (holder alice): refused the same way.
        ok, err, _ = _query(bob_s, keys.drive_cmd("h1", "axis0", "release", "bob"),
                            _request("release", "alice", holder="alice"))
        assert ok == [] and len(err) == 1, err
        # 3. bob on alice's key: the router never lets it through.
        ok, err, took = _query(bob_s, keys.drive_cmd("h1", "axis0", "enable", "alice"), _request("enable", "alice"))
        assert ok == [] and err == [] and took < 1.0
        # 4. as himself: busy, the lease names alice.
        with bed.fleet("bob") as bob:
            res = bob.command("enable", "h1/axis0", timeout_s=2.0)
            assert [r.outcome for r in res.results] == ["busy"], res.to_dict()
            assert res.results[0].lease_holder == "alice"
            res = bob.command("release", "h1/axis0", {"holder": "bob"}, timeout_s=2.0)
            assert res.results[0].outcome == "busy"
        st = alice.fetch_status("h1/axis0")[AX0]
        assert st.lease_holder == "alice" and st.state == "switch_on_disabled"
        # Positive control: alice uses her lease.
        assert alice.enable("h1/axis0").ok
    finally:
        alice.release()


def test_operator_scoped_to_other_hosts_is_denied_and_scoped_to_h1_granted(bed: Bed, alice: Fleet) -> None:
    with bed.fleet("dora") as dora:                       # operator of h2 and h9 only
        assert dora.wait_for_agents(["h1"], timeout_s=10, drives=2)  # reads every host
        report = dora.enable("h1/*", timeout_s=2.0)
        assert {r.outcome for r in report.final} == {DENIED}, report.to_dict()
        for op in ("disable", "quick_stop", "lease"):
            res = dora.command(op, "h1/*", {"holder": "dora"} if op == "lease" else None, timeout_s=2.0)
            assert {r.outcome for r in res.results} == {DENIED}, (op, res.to_dict())
            assert res.elapsed_s < 1.0  # zero replies at once, not a timeout
        ok, err, took = _query(bed.session("dora"), keys.drive_cmd("h1", "axis0", "enable", "dora"),
                               _request("enable", "dora"))
        assert ok == [] and err == [] and took < 1.0
    assert set(_states(alice).values()) == {"switch_on_disabled"}
    assert alice.status(AX0).lease_holder == ""
    with bed.fleet("carl") as carl:                       # operator of h1
        assert carl.wait_for_agents(["h1"], timeout_s=10, drives=2)
        report = carl.enable("h1/*")
        assert report.ok, report.to_dict()
        assert set(_states(alice).values()) == {"operation_enabled"}
        assert carl.disable("h1/*").ok
        # Still an operator only: no fault reset, on its own host either.
        res = carl.command("fault_reset", "h1/axis0", timeout_s=2.0)
        assert [r.outcome for r in res.results] == [DENIED], res.to_dict()


def test_revoked_operator_with_a_valid_certificate_is_denied_after_the_router_restarts(bed: Bed, alice: Fleet,
                                                                                     tmp_path: Path) -> None:
    """olga connects to a second router (r2, linked to r1 where agent h1 is): granted; her name
    is revoked in r2's copy of principals.toml and r2 restarts; her certificate, still valid by
    date and signed by the CA, opens a TLS link, and every command is denied."""
    d2 = tmp_path / "pki-r2"
    shutil.copytree(bed.pki, d2)
    ep2 = f"tls/127.0.0.1:{free_port()}"

    def router2() -> ChildProcess:
        r = ChildProcess("drives-router r2", [sys.executable, "-m", "bus_agent.router", "--pki", str(d2),
                                              "--identity", "r2", "--listen", ep2, "--connect", bed.ep],
                         ready_marker="drives-router ready")
        r.expect_ready(30)
        return r

    def olga() -> Fleet:  # her files from the original directory, where she is still a principal
        return Fleet(connect=[ep2], pki=bed.pki, identity="olga", connect_timeout_s=10.0)

    r2 = router2()
    try:
        with olga() as f:
            assert f.wait_for_agents(["h1"], timeout_s=20, drives=2), f.hosts()
            assert f.enable("h1/axis0").ok                     # positive control: granted before
            assert f.disable("h1/axis0").ok
    finally:
        r2.stop()
    assert pki.revoke(d2, "olga").name == "olga"
    assert not (d2 / "olga.pem").exists() and (bed.pki / "olga.pem").exists()
    r2 = router2()
    try:
        # Positive control through the restarted r2 first: alice reaches h1 (so routes are up).
        with Fleet(connect=[ep2], pki=bed.pki, identity="alice", connect_timeout_s=10.0) as a2:
            assert a2.wait_for_agents(["h1"], timeout_s=20, drives=2), a2.hosts()
        ok, err, _ = _query(bed.session("alice", endpoint=ep2), keys.drive_cmd("h1", "axis0", "disable", "alice"),
                            _request("disable", "alice"))
        assert len(ok) == 1 and err == [], (ok, err)
        # olga's certificate still opens a TLS link (a client session fails to open without one) ...
        s = bed.session("olga", endpoint=ep2)
        # ... and every command of hers ends at once without a reply.
        for op in ("enable", "disable"):
            ok, err, took = _query(s, keys.drive_cmd("h1", "axis0", op, "olga"), _request(op, "olga"))
            assert ok == [] and err == [] and took < 1.0, (op, ok, err)
    finally:
        r2.stop()
    assert set(_states(alice).values()) == {"switch_on_disabled"}


# ---- fake status, fake queryables and tokens, other hosts' names ---------------------------------


def test_only_the_agent_publishes_its_status_and_no_fake_fault_fires_a_reflex(bed: Bed, alice: Fleet) -> None:
    """A fault status for h9/axis0 (member of h1's group ``line``) would make h1/axis0 react (a
    ``reflex`` event): published by anyone but agent h9 it reaches nobody. Then agent h9
    publishes it: the reflex fires. (Reflex events, not h1/axis0's state, are the evidence: a
    drive may leave Operation enabled for reasons of its own.)"""
    assert alice.enable("h1/axis0").ok
    seen: list[bytes] = []
    reflexes: list[str] = []
    watcher = bed.session("vic")
    sub = watcher.declare_subscriber(keys.drive_status("*", "*"), lambda s: seen.append(s.payload.to_bytes()))
    ev_sub = watcher.declare_subscriber(keys.drive_event("h1", "axis0"), lambda s: reflexes.extend(
        ev.detail for ev in [m.decode(s.payload.to_bytes(), m.Event)] if ev.kind == "reflex"))
    try:
        fakes = {name: bed.session(name) for name in ("alice", "vic", "mia", "h2", "tb")}
        time.sleep(0.3)  # let the router propagate every declaration before the puts
        for name, s in fakes.items():
            s.put(keys.drive_status("h9", "axis0"), _status("h9", "axis0", "fault", 0x7500))
            s.put(keys.drive_status("h1", "axis1"), _status("h1", "axis1", "fault", 0x7500))  # a real drive
        # The real agent's heartbeat arrives meanwhile (1 s): proof the subscriber works.
        wait_for(lambda: any(m.decode(b, m.DriveStatus).host == "h1" for b in seen), 5, "h1's own status")
        time.sleep(0.5)
        fake = [st for st in (m.decode(b, m.DriveStatus) for b in seen) if (st.seq, st.cycle) == (1, 1)]
        assert fake == [], fake
        assert reflexes == [], reflexes
        # Positive control: the agent of h9 itself publishes the fault -> the group reflex on h1/axis0.
        bed.session("h9").put(keys.drive_status("h9", "axis0"), _status("h9", "axis0", "fault", 0x7500))
        assert wait_for(lambda: any("h9/axis0" in r for r in reflexes), 5, "the group reflex on h1/axis0")
    finally:
        sub.undeclare()
        ev_sub.undeclare()


def test_non_agents_cannot_serve_or_hold_tokens_under_an_agents_host(bed: Bed) -> None:
    """Also the ACL's liveliness filtering (upstream issue #1562), tested rather than assumed."""
    decls = []
    for name in ("vic", "alice", "h2"):
        s = bed.session(name)
        decls.append(s.declare_queryable(keys.drive_status("h1", "*"), lambda q, n=name: q.reply(
            keys.drive_status("h1", f"fake-{n}"), _status("h1", f"fake-{n}", "fault"))))
        decls.append(s.declare_queryable(keys.drive_cmd("h1", "*", "*", "*"), lambda q: q.reply(
            keys.drive_cmd("h1", "axis0", "enable", "alice"), b"fake")))
        decls.append(s.liveliness().declare_token(keys.alive("h1")))
        decls.append(s.liveliness().declare_token(keys.alive(f"h7{name}")))
    h9 = bed.session("h9")
    decls.append(h9.liveliness().declare_token(keys.alive("h9")))   # positive control
    obs = bed.session("mia")
    wait_for(lambda: [r for r in obs.liveliness().get(keys.alive("h9"), timeout=2) if r.ok], 5, "h9's token")
    tokens = sorted(str(r.ok.key_expr) for r in obs.liveliness().get(keys.ALL_ALIVE, timeout=2) if r.ok)
    assert tokens == [keys.alive("h1"), keys.alive("h9")], tokens
    ok, err, _ = _query(obs, keys.drive_status("h1", "*"))
    assert sorted(k for k, _ in ok) == [keys.drive_status("h1", "axis0"), keys.drive_status("h1", "axis1")]
    # A token history subscriber sees the same (no fake arrivals, no fake departures later).
    events: list[str] = []
    sub = obs.liveliness().declare_subscriber(keys.ALL_ALIVE, lambda s: events.append(f"{s.kind} {s.key_expr}"),
                                              history=True)
    wait_for(lambda: len(events) >= 2, 5, "token history")
    for d in decls:
        d.undeclare()
    wait_for(lambda: any("DELETE" in e and "h9" in e for e in events), 5, "h9's token undeclared")
    sub.undeclare()
    assert not any("h7" in e for e in events) and sum("h1" in e for e in events) == 1, events


def test_an_agent_cannot_publish_or_serve_under_another_hosts_name(bed: Bed, alice: Fleet) -> None:
    h2 = bed.session("h2")
    cmd_q = h2.declare_queryable(keys.drive_cmd("h1", "*", "*", "*"), lambda q: q.reply(
        keys.drive_cmd("h1", "axis0", "enable", "alice"), b"fake"))
    own = h2.declare_publisher(keys.drive_status("h2", "axis0"))
    seen: list[str] = []
    sub = bed.session("vic").declare_subscriber(keys.drive_status("*", "*"), lambda s: seen.append(str(s.key_expr)))
    try:
        time.sleep(0.3)
        h2.put(keys.drive_status("h1", "axis0"), _status("h1", "axis0", "fault"))
        h2.put(keys.drive_event("h1", "axis0"), b"fake event")
        own.put(_status("h2", "axis0", "switch_on_disabled"))  # positive control: its own host
        wait_for(lambda: keys.drive_status("h2", "axis0") in seen, 5, "h2's own status")
        res = alice.command("enable", "h1/*", timeout_s=3.0)
        assert res.ok and {r.host for r in res.results} == {"h1"} and not res.errors, res.to_dict()
        assert all((st.seq, st.cycle) != (1, 1) for st in alice.fetch_status("h1/*").values())  # not the fake
    finally:
        for d in (cmd_q, own, sub):
            d.undeclare()


def test_nobody_outside_testbed_reaches_sim_control(bed: Bed, alice: Fleet) -> None:
    for name in ("alice", "mia", "vic", "h2"):
        with pytest.raises(SimControlError, match="no simulator answered"):
            sim_inject(bed.session(name), "h1", 0, "fault", timeout_s=1.0, error_code=0x7500)
    s = bed.session("alice")
    ok, err, took = _query(s, keys.ALL_SIM)
    assert ok == [] and err == [] and took < 1.0
    assert set(_states(alice).values()) == {"switch_on_disabled"}
    # Positive control: the testbed principal reaches it (and is refused on bad input).
    with pytest.raises(SimControlError, match="error code must be"):
        sim_inject(bed.session("tb"), "h1", 0, "fault", error_code=-1)


# ---- secure by default ----------------------------------------------------------------------------


@pytest.mark.parametrize("argv, code, text", [
    (["-m", "bus_agent.cli", "--sim", "1", "--host", "hx", "--listen", "tcp/0.0.0.0:{port}"], 2, "--insecure"),
    (["-m", "bus_agent.router", "--listen", "tcp/0.0.0.0:{port}"], 2, "--insecure"),
    (["-m", "bus_agent.router", "--config", str(ROOT / "deploy" / "router.json5")], 2, "--insecure"),
    # --insecure passes the check: the TEST-NET address then fails to open (exit 3), proving it got that far.
    (["-m", "bus_agent.router", "--insecure", "--listen", "tcp/192.0.2.254:{port}"], 3, "cannot open"),
])
def test_non_loopback_listen_without_pki_is_refused(argv: list[str], code: int, text: str) -> None:
    argv = [a.replace("{port}", str(free_port())) for a in argv]
    proc = subprocess.run([sys.executable, *argv], capture_output=True, text=True, timeout=60, cwd=ROOT)
    assert proc.returncode == code, proc.stdout + proc.stderr
    assert text in proc.stderr, proc.stderr
    if code == 2:
        assert "--pki" in proc.stderr and "ready" not in proc.stdout
