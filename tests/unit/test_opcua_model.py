"""drives-opcua's pure parts: argument checks, role checks, events, outcomes, users and logins."""

from __future__ import annotations

import dataclasses

import pytest
from asyncua import ua
from asyncua.crypto.permission_rules import UserRole

from bus_agent.security import pki, users
from drives_opcua import auth, model
from schemas.messages import DriveStatus
from supervisor.results import CommandResult, DriveResult, Report

MOVE = model.METHODS["MoveAbsolute"]


def status(**kw) -> DriveStatus:
    base = dict(host="h1", axis="a0", seq=1, time_ns=1, cycle=1, state="switch_on_disabled", statusword=0x40,
                controlword=0, goal="disabled", halt=False, mode=8, mode_display=8, position=0, velocity=0,
                torque=0, error_code=0)
    base.update(kw)
    return DriveStatus(**base)


def test_arguments_checked_for_count_type_and_range() -> None:
    assert model.check_arguments(MOVE, [ua.Variant(1.5, ua.VariantType.Double), ua.Variant(2.0, ua.VariantType.Double)]) == [1.5, 2.0]
    cases = [
        ([ua.Variant("far", ua.VariantType.String), ua.Variant(1.0, ua.VariantType.Double)], 0, ua.StatusCodes.BadTypeMismatch, "Position"),
        ([ua.Variant(1.0, ua.VariantType.Double), ua.Variant(0.0, ua.VariantType.Double)], 1, ua.StatusCodes.BadOutOfRange, "Velocity"),
        ([ua.Variant(float("nan"), ua.VariantType.Double), ua.Variant(1.0, ua.VariantType.Double)], 0, ua.StatusCodes.BadOutOfRange, "Position"),
        ([ua.Variant(1.0, ua.VariantType.Double)], 1, ua.StatusCodes.BadArgumentsMissing, "Velocity"),
        ([ua.Variant(1.0, ua.VariantType.Double)] * 3, 2, ua.StatusCodes.BadTooManyArguments, "3 arguments"),
        ([ua.Variant(True, ua.VariantType.Boolean), ua.Variant(1.0, ua.VariantType.Double)], 0, ua.StatusCodes.BadTypeMismatch, "Boolean"),
    ]
    for args, index, code, text in cases:
        with pytest.raises(model.ArgumentProblem, match=text) as err:
            model.check_arguments(MOVE, args)
        assert (err.value.index, err.value.status) == (index, code)
    assert model.check_arguments(model.METHODS["Enable"], []) == []


def test_roles_follow_the_project_role_table() -> None:
    assert model.may_call(["operator"], "enable") and model.may_call(["operator"], "move")
    assert not model.may_call(["operator"], "fault_reset")
    assert model.may_call(["maintenance"], "fault_reset") and not model.may_call(["maintenance"], "enable")
    assert not any(model.may_call(["viewer"], m.op) for m in model.METHODS.values())
    # Every method's op is one some role may send (else nobody could ever call it).
    assert all(model.roles_for(m.op) for m in model.METHODS.values())


def test_alarms_on_fault_and_lost_edges_only() -> None:
    ok = status()
    fault = status(state="fault", error_code=0x7500, error_text="communication")
    assert [(k, s) for k, s, _ in model.drive_alarms(ok, fault)] == [("fault", 800)]
    assert "0x7500" in model.drive_alarms(ok, fault)[0][2]
    assert model.drive_alarms(fault, dataclasses.replace(fault, seq=2)) == []  # still in fault: no repeat
    assert [k for k, _, _ in model.drive_alarms(fault, ok)] == ["fault_cleared"]
    lost = status(lost=True, state="unknown")
    assert [k for k, _, _ in model.drive_alarms(ok, lost)] == ["lost"]
    assert [k for k, _, _ in model.drive_alarms(lost, ok)] == ["found"]
    assert [k for k, _, _ in model.drive_alarms(None, fault)] == ["fault"]  # first seen in fault
    assert model.drive_alarms(fault, dataclasses.replace(fault, state="unknown", lost=True))[0][0] == "lost"


def test_outcome_of_a_command_and_of_an_orchestration() -> None:
    res = CommandResult("disable", "r", (DriveResult("h1", "a0", "done"), DriveResult("h1", "a1", "failed", error="x")))
    assert model.outcome(res, "h1", "a1") == ("failed", "x")
    assert model.outcome(res, "h2", "a0")[0] == "missing"
    rep = Report("enable", False, reason="phase 1 refused", final=(DriveResult("h1", "a0", "rejected", error="busy"),))
    assert model.outcome(rep, "h1", "a0") == ("rejected", "busy")
    assert model.outcome(Report("enable", False, reason="why"), "h1", "a0") == ("missing", "why")


def test_drive_values_follow_the_table() -> None:
    values = dict(zip(model.DRIVE_VARIABLES, model.drive_values(status(error_code=5, lost=True))))
    assert values["ErrorCode"] == 5 and values["Lost"] is True and values["State"] == "switch_on_disabled"
    assert set(model.DRIVE_INITIAL) == set(model.DRIVE_VARIABLES)
    host = dict(zip(model.HOST_VARIABLES, model.host_values(model.HostView(False, None))))
    assert host["AgentState"] == model.OFFLINE and host["Alive"] is False


def test_password_users_hashed_and_checked(tmp_path) -> None:
    pki.init(tmp_path)
    u = users.set_user(tmp_path, "olga", ["operator"], "correct horse")
    assert "correct horse" not in (tmp_path / users.FILE_NAME).read_text()
    assert (tmp_path / users.FILE_NAME).stat().st_mode & 0o077 == 0
    loaded = users.load(tmp_path)["olga"]
    assert loaded.roles == ("operator",) and loaded.verify("correct horse") and not loaded.verify("correct hors")
    assert users.set_user(tmp_path, "olga", ["operator"], "correct horse").password != u.password  # new salt
    for name, roles, pw, text in (("bob", ["agent"], "long enough", "roles"), ("bob", ["viewer"], "short", "8"),
                                  ("bad name", ["viewer"], "long enough", "user name")):
        with pytest.raises(users.UsersError, match=text):
            users.set_user(tmp_path, name, roles, pw)
    assert set(users.load(tmp_path)) == {"olga"}


def test_logins(tmp_path) -> None:
    pki.init(tmp_path)
    pki.issue(tmp_path, "carl", ["operator"], opcua=True)
    pki.issue(tmp_path, "h1", ["agent"], opcua=True)
    pki.issue(tmp_path, "gone", ["operator"], opcua=True)
    gone_cert = (tmp_path / "gone.pem").read_bytes()
    pki.revoke(tmp_path, "gone")
    users.set_user(tmp_path, "olga", ["operator"], "correct horse")
    other = tmp_path / "other"
    pki.init(other)
    pki.issue(other, "carl", ["operator"], opcua=True)
    um = auth.DrivesUserManager(tmp_path)

    def der(path) -> bytes:
        from cryptography import x509
        from cryptography.hazmat.primitives import serialization
        return x509.load_pem_x509_certificate(path if isinstance(path, bytes) else path.read_bytes()).public_bytes(
            serialization.Encoding.DER)

    assert um.get_user(None) is auth.ANONYMOUS
    olga = um.get_user(None, username="olga", password="correct horse")
    assert olga.name == "olga" and olga.roles == ("operator",) and olga.role == UserRole.User
    assert um.get_user(None, username="olga", password="wrong") is None
    assert um.get_user(None, username="nobody", password="x") is None

    def token(cert: bytes):
        auth._TOKEN_CERT.set(cert)  # what the wrapped verify_x509_token records
        return um.get_user(None, certificate=cert)

    carl = token(der(tmp_path / "carl.pem"))
    assert carl.name == "carl" and carl.via == "certificate" and carl.roles == ("operator",)
    assert token(der(other / "carl.pem")) is None           # another CA
    assert token(der(gone_cert)) is None                     # revoked
    assert token(der(tmp_path / "h1.pem")) is None           # an agent is no user
    # A secure channel's application certificate with an anonymous token logs nobody in.
    assert um.get_user(None, certificate=der(tmp_path / "carl.pem")) is auth.ANONYMOUS


def test_service_rules() -> None:
    rules = auth.ServiceRules()
    call = ua.NodeId(ua.ObjectIds.CallRequest_Encoding_DefaultBinary)
    read = ua.NodeId(ua.ObjectIds.ReadRequest_Encoding_DefaultBinary)
    write = ua.NodeId(ua.ObjectIds.WriteRequest_Encoding_DefaultBinary)
    olga = auth.DrivesUser(role=UserRole.User, name="olga", roles=("viewer",), via="password")
    assert rules.check_validity(auth.ANONYMOUS, read, None) and auth.CURRENT_USER.get() is None
    assert not rules.check_validity(auth.ANONYMOUS, call, None)
    assert rules.check_validity(olga, call, None) and auth.CURRENT_USER.get() is olga
    assert not rules.check_validity(olga, write, None)


def test_drives_pki_user_and_crl_commands(tmp_path, monkeypatch, capsys) -> None:
    import io

    from bus_agent.security import cli

    pki.init(tmp_path)
    monkeypatch.setattr("sys.stdin", io.StringIO("a long password\n"))
    assert cli.main(["user", str(tmp_path), "olga", "--role", "operator", "--password-stdin"]) == 0
    assert users.load(tmp_path)["olga"].verify("a long password")
    monkeypatch.setattr("sys.stdin", io.StringIO("short\n"))
    assert cli.main(["user", str(tmp_path), "bob", "--role", "viewer", "--password-stdin"]) == 2
    assert "at least 8" in capsys.readouterr().err and "bob" not in users.load(tmp_path)
    pki.issue(tmp_path, "gone", ["viewer"])
    serial = int(pki.pfile.load(tmp_path)["gone"].serial, 16)
    pki.revoke(tmp_path, "gone")
    from cryptography import x509

    crl = x509.load_pem_x509_crl((tmp_path / pki.CA_CRL).read_bytes())
    assert crl.get_revoked_certificate_by_serial_number(serial) is not None
    assert cli.main(["crl", str(tmp_path)]) == 0


def test_drives_opcua_refuses_an_ec_server_certificate_before_the_fleet(tmp_path, capsys) -> None:
    from drives_opcua import cli

    pki.init(tmp_path)
    pki.issue(tmp_path, "opcua", ["operator", "maintenance"])  # EC: no --opcua
    # Exit 2 saying how to fix it, before any Zenoh session (nothing listens on this port).
    assert cli.main(["--connect", "tcp/127.0.0.1:9", "--pki", str(tmp_path)]) == 2
    assert "--opcua" in capsys.readouterr().err


def test_method_arguments_become_the_contracts_command_args() -> None:
    from schemas.messages import validate_args

    args = MOVE.command_args([12.5, 3.0])
    assert args == {"to": 12.5, "velocity": 3.0} and validate_args("move", args)
    assert model.METHODS["Halt"].command_args([]) == {"on": True}
    # The accepted range is the contract's: an accepted value always encodes.
    high = MOVE.arguments[0].high
    validate_args("move", MOVE.command_args(model.check_arguments(MOVE, [high, 1.0])))
    with pytest.raises(model.ArgumentProblem):
        model.check_arguments(MOVE, [high * 10, 1.0])


def test_fleet_acting_for_names_the_user_in_every_request_of_the_block() -> None:
    import threading

    from schemas import keys
    from supervisor.fleet import Fleet

    f = Fleet(connect=["tcp/127.0.0.1:9"], name="gw")  # never opened: requests are only built
    assert f._request("enable", None, 5.0).on_behalf_of == ""
    with f.acting_for("olga"):
        req = f._request("move", {"to": 1.0}, 5.0)
        assert (req.on_behalf_of, req.supervisor) == ("olga", "gw")
        other: list[str] = []
        t = threading.Thread(target=lambda: other.append(f._request("halt", {"on": True}, 5.0).on_behalf_of))
        t.start()
        t.join()
        assert other == [""]  # another thread's commands are not olga's
    assert f._request("enable", None, 5.0).on_behalf_of == ""
    with pytest.raises(keys.InvalidKey):
        with f.acting_for("not a name"):
            pass
