"""Pure parts of the secure fleet: roles and the ACL they compile to, principals.toml, the CA's
files, which endpoints are exposed, authenticated command keys and who the gateway says asks.
(The ACL as zenoh enforces it: tests/system/test_security.py.)"""

from __future__ import annotations

import datetime as dt
import stat
from pathlib import Path

import pytest
import zenoh
from cryptography import x509

from bus_agent.gateway.gateway import RequestError, parse_command, requester
from bus_agent.gateway.zenoh_config import ZenohConfigError, make_zenoh_config
from bus_agent.security import pki, principals
from bus_agent.security.cli import main as pki_main
from bus_agent.security.exposure import exposed_endpoints, is_loopback
from bus_agent.security.roles import MOTION_OPS, ROLE_AGENT_OPS, ROLE_DRIVE_OPS, RoleError, check_roles, compile_acl
from schemas import keys
from schemas import messages as m
from supervisor.results import DENIED, MISSING, aggregate
from supervisor.selectors import DriveRef


def _includes(rule_kes: list[str], key: str) -> bool:
    return any(zenoh.KeyExpr(k).includes(zenoh.KeyExpr(key)) for k in rule_kes)


def _allowed(acl: dict, who: str, flow: str, message: str, key: str) -> bool:
    pol = next(p for p in acl["policies"] if p["subjects"] == [f"cn:{who}"])
    rules = [r for r in acl["rules"] if r["id"] in pol["rules"]]
    return any(flow in r["flows"] and message in r["messages"] and _includes(r["key_exprs"], key) for r in rules)


P = [principals.Principal("alice", ("operator",)), principals.Principal("mia", ("maintenance",)),
     principals.Principal("vic", ("viewer",)), principals.Principal("h1", ("agent",)),
     principals.Principal("r1", ("router",)), principals.Principal("tb", ("testbed",))]


def test_every_op_of_the_contract_has_a_role_and_no_role_has_an_unknown_op() -> None:
    granted = {op for ops in ROLE_DRIVE_OPS.values() for op in ops}
    assert set(m.DRIVE_OPS) <= granted, f"ops nobody may send: {set(m.DRIVE_OPS) - granted}"
    assert granted <= set(m.DRIVE_OPS) | set(MOTION_OPS)
    assert set(m.AGENT_OPS) <= {op for ops in ROLE_AGENT_OPS.values() for op in ops}
    for ops in ROLE_AGENT_OPS.values():
        assert set(ops) <= set(m.AGENT_OPS)
    assert "fault_reset" not in ROLE_DRIVE_OPS["operator"] and "enable" not in ROLE_DRIVE_OPS["maintenance"]
    assert "move" not in ROLE_DRIVE_OPS["maintenance"]


@pytest.mark.parametrize("roles, match", [((), "no role"), (("boss",), "unknown role"),
                                          (("viewer", "viewer"), "twice"), (("router", "agent"), "router")])
def test_bad_roles_are_refused(roles: tuple[str, ...], match: str) -> None:
    with pytest.raises(RoleError, match=match):
        check_roles(roles)


def test_acl_is_default_deny_and_each_role_gets_only_its_verbs() -> None:
    acl = compile_acl(P)
    assert acl["enabled"] is True and acl["default_permission"] == "deny"
    q = "query"
    for op in m.DRIVE_OPS:
        key = keys.drive_cmd("h1", "axis0", op, "alice")
        assert _allowed(acl, "alice", "ingress", q, key) == (op in ROLE_DRIVE_OPS["operator"]), op
        key = keys.drive_cmd("h1", "axis0", op, "mia")
        assert _allowed(acl, "mia", "ingress", q, key) == (op in ROLE_DRIVE_OPS["maintenance"]), op
        assert not _allowed(acl, "vic", "ingress", q, keys.drive_cmd("h1", "axis0", op, "vic"))
    assert _allowed(acl, "mia", "ingress", q, keys.agent_cmd("h1", "nmt", "mia"))
    assert not _allowed(acl, "alice", "ingress", q, keys.agent_cmd("h1", "nmt", "alice"))
    # Only under one's own name, never the unauthenticated keys, never a wildcard principal.
    assert not _allowed(acl, "alice", "ingress", q, keys.drive_cmd("h1", "axis0", "enable", "bob"))
    assert not _allowed(acl, "alice", "ingress", q, keys.drive_cmd("h1", "axis0", "enable"))
    assert not _allowed(acl, "alice", "ingress", q, keys.drive_cmd("*", "*", "enable", "*"))
    assert _allowed(acl, "alice", "ingress", q, keys.drive_cmd("*", "*", "enable", "alice"))
    # Reading: the viewer status only; nobody but the agent publishes under its host.
    assert _allowed(acl, "vic", "ingress", "declare_subscriber", keys.ALL_DRIVE_STATUS)
    assert _allowed(acl, "vic", "egress", "put", keys.drive_status("h1", "axis0"))
    assert not _allowed(acl, "vic", "ingress", "declare_liveliness_subscriber", keys.ALL_SUPERVISORS)
    assert _allowed(acl, "mia", "ingress", q, keys.agent_recording("h1"))       # flight recordings
    assert _allowed(acl, "h1", "ingress", "declare_queryable", keys.agent_recording("h1"))
    assert not _allowed(acl, "vic", "ingress", q, keys.agent_recording("h1"))
    for who in ("alice", "mia", "vic", "tb"):
        assert not _allowed(acl, who, "ingress", "put", keys.drive_status("h1", "axis0"))
        assert not _allowed(acl, who, "ingress", "declare_queryable", keys.drive_cmd("h1", "*", "*", "*"))
        assert not _allowed(acl, who, "ingress", "liveliness_token", keys.alive("h1"))
    assert _allowed(acl, "h1", "ingress", "put", keys.drive_status("h1", "axis0"))
    assert not _allowed(acl, "h1", "ingress", "put", keys.drive_status("h2", "axis0"))
    assert _allowed(acl, "h1", "ingress", "declare_queryable", keys.drive_cmd("h1", "*", "*", "*"))
    assert not _allowed(acl, "h1", "ingress", "declare_queryable", keys.drive_cmd("h2", "*", "*", "*"))
    assert _allowed(acl, "h1", "ingress", "liveliness_token", keys.alive("h1"))
    assert not _allowed(acl, "h1", "ingress", "liveliness_token", keys.alive("h2"))
    # Supervisor tokens (leases) only under one's own name.
    assert _allowed(acl, "alice", "ingress", "liveliness_token", keys.supervisor_alive("alice"))
    assert not _allowed(acl, "alice", "ingress", "liveliness_token", keys.supervisor_alive("bob"))
    # Simulator control: the testbed role only.
    sim = keys.sim_control("h1", 0, "fault")
    for who in ("alice", "mia", "vic", "h1"):
        assert not _allowed(acl, who, "ingress", q, sim)
    assert _allowed(acl, "tb", "ingress", q, sim)


def test_acl_opens_in_a_zenoh_session() -> None:
    conf = make_zenoh_config("peer", extra={"access_control": compile_acl(P)})
    with zenoh.open(conf):
        pass


def test_principals_file_round_trips_and_names_bad_entries(tmp_path: Path) -> None:
    principals.save(tmp_path, P)
    assert principals.load(tmp_path) == {p.name: p for p in P}
    for text, match in [('[principals.x]\nroles = "operator"\n', "list of role"),
                        ('[principals.x]\nroles = ["god"]\n', "unknown role"),
                        ('[principals."a/b"]\nroles = ["viewer"]\n', "principal"),
                        ('[principals.x]\nroles = ["viewer"]\ncolour = 1\n', "colour"),
                        ('other = 1\n', "unknown key"), ('[principals\n', "TOML")]:
        (tmp_path / principals.FILE_NAME).write_text(text)
        with pytest.raises(principals.PrincipalsError, match=match):
            principals.load(tmp_path)


def test_pki_init_issue_list_remove(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    d = tmp_path / "pki"
    assert pki_main(["init", str(d)]) == 0
    assert stat.S_IMODE((d / "ca.key").stat().st_mode) == 0o600
    assert pki_main(["init", str(d)]) == 2  # never overwrites a CA
    assert pki_main(["issue", str(d), "r1", "--role", "router", "--san", "10.0.0.1", "--san", "r1.plant"]) == 0
    assert pki_main(["issue", str(d), "h1", "--role", "agent", "--role", "testbed", "--days", "30"]) == 0
    assert pki_main(["issue", str(d), "h1", "--role", "agent"]) == 2          # exists
    assert pki_main(["issue", str(d), "x", "--role", "viewer", "--san", "not a name"]) == 2
    assert pki_main(["issue", str(d), "ca", "--role", "viewer"]) == 2         # would clash with ca.pem
    cert = x509.load_pem_x509_certificate((d / "r1.pem").read_bytes())
    san = cert.extensions.get_extension_for_class(x509.SubjectAlternativeName).value
    assert {str(v) for v in san.get_values_for_type(x509.IPAddress)} == {"127.0.0.1", "10.0.0.1"}
    assert set(san.get_values_for_type(x509.DNSName)) == {"localhost", "r1.plant"}
    assert cert.subject.rfc4514_string() == "CN=r1"
    assert stat.S_IMODE((d / "h1.key").stat().st_mode) == 0o600
    assert principals.load(d)["h1"].roles == ("agent", "testbed")
    capsys.readouterr()
    assert pki_main(["list", str(d)]) == 0
    out = capsys.readouterr().out
    assert "h1" in out and "agent,testbed" in out and "600" in out
    assert pki_main(["remove", str(d), "h1"]) == 0
    assert "h1" not in principals.load(d) and not (d / "h1.key").exists()
    assert pki_main(["remove", str(d), "h1"]) == 2


def test_identity_checks_before_zenoh(tmp_path: Path) -> None:
    pki.init(tmp_path)
    pki.issue(tmp_path, "alice", ["operator"])
    pki.issue(tmp_path, "old", ["operator"], days=1, valid_from=dt.datetime.now(dt.timezone.utc) - dt.timedelta(days=9))
    ep = "tcp/127.0.0.1:1"
    conf = make_zenoh_config("client", [], [ep], pki=tmp_path, identity="alice")
    assert conf.get_json("connect/endpoints") == '["tls/127.0.0.1:1"]'
    assert '"enable_mtls":true' in conf.get_json("transport/link/tls").replace(" ", "")
    assert conf.get_json("access_control/enabled") == "false"  # a client that does not listen
    router = make_zenoh_config("router", [ep], [], pki=tmp_path, identity="alice")
    assert router.get_json("access_control/default_permission") == '"deny"'
    for identity, match in [("bob", "missing"), ("old", "expired")]:
        with pytest.raises(ZenohConfigError, match=match):
            make_zenoh_config("client", [], [ep], pki=tmp_path, identity=identity)
    (tmp_path / "alice.key").chmod(0o644)
    with pytest.raises(ZenohConfigError, match="readable by others"):
        make_zenoh_config("client", [], [ep], pki=tmp_path, identity="alice")
    with pytest.raises(ZenohConfigError, match="go together"):
        make_zenoh_config("client", [], [ep], pki=tmp_path)
    with pytest.raises(ZenohConfigError, match="udp"):
        make_zenoh_config("client", [], ["udp/127.0.0.1:1"], pki=tmp_path, identity="alice")


@pytest.mark.parametrize("ep, loopback", [
    ("tcp/127.0.0.1:7447", True), ("tls/127.0.0.2:7447", True), ("tcp/[::1]:7447", True),
    ("tcp/localhost:7447", True), ("unixsock-stream//tmp/z.sock", True), ("tcp/0.0.0.0:7447", False),
    ("tcp/10.0.0.1:7447", False), ("tcp/[::]:7447", False), ("tcp/router.plant:7447", False),
])
def test_exposed_endpoints(ep: str, loopback: bool) -> None:
    assert is_loopback(ep) is loopback
    assert exposed_endpoints([ep]) == ([] if loopback else [ep])


def test_authenticated_command_keys() -> None:
    key = keys.drive_cmd("h1", "axis0", "enable", "alice")
    assert key == "drives/@v1/h1/drive/axis0/cmd/enable/@sup/alice"
    p = keys.parse(key)
    assert (p.kind, p.host, p.axis, p.op, p.principal) == (keys.KeyKind.DRIVE_CMD, "h1", "axis0", "enable", "alice")
    assert keys.parse(keys.agent_cmd("h1", "nmt", "mia")).principal == "mia"
    assert keys.parse(keys.drive_cmd("h1", "axis0", "enable")).principal is None
    assert keys.command_principal(keys.drive_cmd("*", "*", "enable", "bob")) == "bob"
    assert keys.command_principal(keys.drive_status("h1", "x")) is None
    with pytest.raises(keys.InvalidKey):
        keys.command_principal("drives/@v1/h1/drive/*/cmd/enable/@sup/*")
    with pytest.raises(keys.InvalidKey):
        keys.parse("drives/@v1/h1/drive/x/status/@sup/alice")


def test_requester_comes_from_the_key_never_the_payload() -> None:
    k = keys.drive_cmd("h1", "*", "enable", "alice")
    assert requester(k, "", secure=True) == "alice"
    assert requester(k, "alice", secure=True) == "alice"
    with pytest.raises(RequestError, match="'bob'.*'alice'"):
        requester(k, "bob", secure=False)
    with pytest.raises(RequestError, match="@sup"):
        requester(keys.drive_cmd("h1", "*", "enable"), "alice", secure=True)
    assert requester(keys.drive_cmd("h1", "*", "enable"), "anyone", secure=False) == "anyone"
    # Through parse_command: the supervisor becomes the principal; a lease for someone else is refused.
    req = m.encode(m.CommandRequest("r1", "lease", {"holder": "alice"}, 1.0, ""))
    parsed = parse_command(req, keys.drive_cmd("h1", "axis0", "lease", "alice"), "h1", ("axis0",), secure=True)
    assert parsed.request.supervisor == "alice" and parsed.principal == "alice" and parsed.axes == ("axis0",)
    with pytest.raises(RequestError, match="holder"):
        parse_command(req, keys.drive_cmd("h1", "axis0", "lease", "bob"), "h1", ("axis0",), secure=True)


def test_a_command_answered_by_no_one_at_once_is_denied_not_missing() -> None:
    refs = [DriveRef("h1", "a"), DriveRef("h2", "a")]
    res = aggregate("enable", "r", refs, {}, gone_hosts=["h2"], timeout_s=5.0, elapsed_s=0.01,
                    denied_reason="denied at once: identity 'vic' may not enable")
    assert [(r.outcome, "vic" in r.error) for r in res.results] == [(DENIED, True), (MISSING, False)]
    assert [r.outcome for r in aggregate("enable", "r", refs[:1], {}, timeout_s=5.0).results] == [MISSING]


def test_host_scope_limits_commands_to_those_hosts_and_reading_stays_fleet_wide() -> None:
    carl = principals.Principal("carl", ("operator",), hosts=("h1", "h3"))
    acl = compile_acl([*P, carl])
    for host in ("h1", "h3"):
        assert _allowed(acl, "carl", "ingress", "query", keys.drive_cmd(host, "axis0", "enable", "carl"))
    assert not _allowed(acl, "carl", "ingress", "query", keys.drive_cmd("h2", "axis0", "enable", "carl"))
    # A wildcard host is not included in a rule naming h1: fan-outs must address hosts one by one.
    assert not _allowed(acl, "carl", "ingress", "query", keys.drive_cmd("*", "*", "enable", "carl"))
    assert not _allowed(acl, "carl", "ingress", "query", keys.drive_cmd("h1", "axis0", "fault_reset", "carl"))
    assert _allowed(acl, "carl", "ingress", "declare_subscriber", keys.ALL_DRIVE_STATUS)
    assert _allowed(acl, "carl", "egress", "put", keys.drive_status("h2", "axis0"))
    # Unscoped principals are unchanged.
    assert _allowed(acl, "alice", "ingress", "query", keys.drive_cmd("h2", "axis0", "enable", "alice"))


@pytest.mark.parametrize("roles, hosts, match", [(("viewer",), ("h1",), "send none"),
                                                 (("agent",), ("h1",), "send none"),
                                                 (("operator",), ("h1", "h1"), "twice"),
                                                 (("operator",), ("a/b",), "host")])
def test_bad_host_scopes_are_refused(roles: tuple[str, ...], hosts: tuple[str, ...], match: str) -> None:
    with pytest.raises(principals.PrincipalsError, match=match):
        principals.Principal("x", roles, hosts=hosts)


def test_issue_with_hosts_and_revoke(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    d = tmp_path / "pki"
    assert pki_main(["init", str(d)]) == 0
    assert pki_main(["issue", str(d), "carl", "--role", "operator", "--hosts", "h1,h2"]) == 0
    assert pki_main(["issue", str(d), "vic", "--role", "viewer", "--hosts", "h1"]) == 2   # a viewer sends nothing
    with pytest.raises(SystemExit) as exc:
        pki_main(["issue", str(d), "x", "--role", "operator", "--hosts", "h1,,h2"])
    assert exc.value.code == 2
    assert principals.load(d)["carl"].hosts == ("h1", "h2")
    assert pki_main(["issue", str(d), "bob", "--role", "operator"]) == 0
    serial = principals.load(d)["bob"].serial
    capsys.readouterr()
    assert pki_main(["revoke", str(d), "bob"]) == 0
    known, revoked = principals.load_all(d)
    assert "bob" not in known and revoked["bob"].serial == serial and revoked["bob"].revoked_at
    assert not (d / "bob.key").exists() and not (d / "bob.pem").exists()
    assert pki_main(["revoke", str(d), "bob"]) == 2                                    # already revoked
    assert pki_main(["issue", str(d), "bob", "--role", "operator"]) == 2               # never issued again
    assert "cannot be issued again" in capsys.readouterr().err
    assert pki_main(["remove", str(d), "carl"]) == 0                                   # remove is revoke
    assert set(principals.load_all(d)[1]) == {"bob", "carl"}
    assert pki_main(["list", str(d)]) == 0
    assert "REVOKED" in capsys.readouterr().out
    # Routers compile an explicit deny of every revoked name.
    acl = compile_acl(principals.load(d).values(), principals.load_all(d)[1])
    deny = next(r for r in acl["rules"] if r["id"] == "revoked")
    assert deny["permission"] == "deny" and set(deny["flows"]) == {"ingress", "egress"}
    assert next(s for s in acl["subjects"] if s["id"] == "cn:revoked")["cert_common_names"] == ["bob", "carl"]
    with zenoh.open(make_zenoh_config("peer", extra={"access_control": acl})):
        pass  # zenoh accepts it


def test_principals_file_names_bad_revoked_entries(tmp_path: Path) -> None:
    for text, match in [('[revoked.x]\nwhen = 1\n', "when"),
                        ('[principals.x]\nroles = ["viewer"]\n[revoked.x]\nserial = "1"\n', "both"),
                        ('[principals.x]\nroles = ["operator"]\nhosts = "h1"\n', "hosts")]:
        (tmp_path / principals.FILE_NAME).write_text(text)
        with pytest.raises(principals.PrincipalsError, match=match):
            principals.load(tmp_path)



def test_zenoh_tls_has_no_revocation_list_and_links_close_on_expiry(tmp_path: Path) -> None:
    """docs/security.md says revocation is the ACL's alone because zenoh's TLS settings hold no
    revocation list: when a zenoh upgrade adds one, this fails and drives-pki revoke should use it."""
    conf = zenoh.Config()
    for key in ("crl", "certificate_revocation_list", "root_ca_crl"):
        with pytest.raises(Exception, match="unknown key"):
            conf.insert_json5(f"transport/link/tls/{key}", '"x.pem"')
    pki.init(tmp_path)
    pki.issue(tmp_path, "alice", ["operator"])
    tls = make_zenoh_config("client", [], ["tls/127.0.0.1:1"], pki=tmp_path, identity="alice").get_json("transport/link/tls")
    assert '"close_link_on_expiration":true' in tls.replace(" ", "")
