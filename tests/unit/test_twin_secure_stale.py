"""A secure twin's principals and certificates (twin/secure.py), and finding what a SIGKILLed twin
left (twin/stale.py): owner records checked against the live process table, never a guess."""

from __future__ import annotations

import json
import os
import subprocess
import sys

import pytest

from bus_agent.security import pki, principals
from supervisor.fleetfile import parse
from twin import Twin
from twin.plan import PlanError, plan
from twin.secure import AGENT_ROLES, CONTROL, OPERATOR, ROUTER, prepare, tls_endpoint, twin_principals
from twin.stale import OWNER_FILE, WORKDIR_PREFIX, clean_stale, owner_gone, stale_workdirs, start_ticks, write_owner


def test_principals_per_host_and_the_twins_own():
    assert twin_principals(["c1", "c2"], None) == {"c1": AGENT_ROLES, "c2": AGENT_ROLES, ROUTER: ("router",),
                                                   CONTROL: ("testbed",), OPERATOR: ("operator",)}
    assert OPERATOR not in twin_principals(["c1"], "alice")  # the user's operator is the twin's fleet
    with pytest.raises(PlanError, match=r"host name\(s\) \['twin-router'\] are the twin's own principals"):
        twin_principals(["twin-router"], None)
    with pytest.raises(PlanError, match="--identity 'c1' is a principal the twin issues itself"):
        twin_principals(["c1"], "c1")


@pytest.mark.parametrize("ep, out", [("tcp/127.0.0.1:7447", "tls/127.0.0.1:7447"),
                                     ("tls/127.0.0.1:1", "tls/127.0.0.1:1"), ("udp/127.0.0.1:1", None),
                                     ("unixsock-stream/x", None), ("tcp/", None)])
def test_secure_endpoint_is_tls(ep, out):
    if out is None:
        with pytest.raises(PlanError, match="with --pki the twin listens on tls/"):
            tls_endpoint(ep)
    else:
        assert tls_endpoint(ep) == out


def test_agents_get_the_pki_and_their_host_name_as_identity():
    f = parse({"hosts": {"c1": {"axes": ["a"]}}})
    (p,) = plan(f, "sim", {"c1": "tcp/127.0.0.1:9"}, pki="/x/pki")
    assert p.agent_toml["zenoh"] == {"mode": "client", "connect": ["tcp/127.0.0.1:9"], "pki": "/x/pki"}


def test_prepare_issues_into_a_copy_and_leaves_the_users_directory_alone(tmp_path):
    d = tmp_path / "pki"
    pki.init(d)
    pki.issue(d, "alice", ["operator"])
    before = sorted(os.listdir(d))
    copy = prepare(str(d), str(tmp_path / "copy"), ["c1"], "alice")
    assert sorted(os.listdir(d)) == before
    known = principals.load(copy)
    assert known["c1"].roles == AGENT_ROLES and known[ROUTER].roles == ("router",) and "alice" in known
    for name in ("c1", ROUTER, CONTROL, "alice"):
        pki.check_identity(copy, name)  # every file there, valid, key 0600
    with pytest.raises(PlanError, match="certificate of 'bob' .*missing .*drives-pki issue .*/pki bob"):
        prepare(str(d), str(tmp_path / "copy2"), ["c1"], "bob")
    os.unlink(d / pki.CA_KEY)
    with pytest.raises(PlanError, match="no ca.key: the twin issues"):
        prepare(str(d), str(tmp_path / "copy3"), ["c1"], None)


def test_bad_pki_arguments_fail_before_anything_runs(tmp_path):
    fleet = {"hosts": {"c1": {"axes": ["a"]}}}
    with pytest.raises(PlanError, match="--identity needs --pki"):
        Twin(fleet, identity="alice")
    with pytest.raises(PlanError, match="--pki works with the sim backend only"):
        Twin(fleet, pki=tmp_path, backend="ecat")
    twin = Twin(fleet, pki=tmp_path / "nothing")
    with pytest.raises(PlanError, match="no ca.pem there"):
        twin.start()
    assert not os.path.exists(twin.workdir) and twin.router is None  # nothing started, nothing left


def _workdir(tmp_path, name: str, record: dict | None) -> str:
    d = tmp_path / f"{WORKDIR_PREFIX}{name}"
    d.mkdir()
    if record is not None:
        (d / OWNER_FILE).write_text(json.dumps(record))
    return str(d)


def test_only_workdirs_of_dead_owners_are_stale(tmp_path):
    dead = subprocess.run([sys.executable, "-c", "import os; print(os.getpid())"], capture_output=True, text=True)
    dead_pid = int(dead.stdout)
    me = os.getpid()
    _workdir(tmp_path, "live", {"pid": me, "start_ticks": start_ticks(me), "ecat": []})
    _workdir(tmp_path, "reused", {"pid": me, "start_ticks": (start_ticks(me) or 0) - 1, "ecat": []})  # pid reused
    _workdir(tmp_path, "dead", {"pid": dead_pid, "start_ticks": 1, "ecat": []})
    _workdir(tmp_path, "starting", None)  # no record yet: a twin between mkdtemp and write_owner
    (tmp_path / f"{WORKDIR_PREFIX}bad").mkdir()
    (tmp_path / f"{WORKDIR_PREFIX}bad" / OWNER_FILE).write_text("{not json")
    assert sorted(d.name for d, _ in stale_workdirs(str(tmp_path))) == [f"{WORKDIR_PREFIX}dead",
                                                                         f"{WORKDIR_PREFIX}reused"]
    assert not owner_gone({"pid": me, "start_ticks": start_ticks(me)})
    done = clean_stale(str(tmp_path))
    assert len(done) == 2 and all(line.startswith("removed work directory") for line in done)
    assert sorted(p.name for p in tmp_path.iterdir()) == [f"{WORKDIR_PREFIX}bad", f"{WORKDIR_PREFIX}live",
                                                          f"{WORKDIR_PREFIX}starting"]


def test_owner_record_names_this_process_and_its_namespaces(tmp_path):
    from twin.ecat import ecat_plan

    write_owner(str(tmp_path), {"h": ecat_plan("tw1", 1)})
    record = json.loads((tmp_path / OWNER_FILE).read_text())
    assert record == {"pid": os.getpid(), "start_ticks": start_ticks(os.getpid()),
                      "ecat": [{"netns": "tw1h1", "master": "tw11m", "sim": "tw11s"}]}
    assert start_ticks(2 ** 22 + 1) is None  # above pid_max: no such process
