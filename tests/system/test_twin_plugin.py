"""The pytest plugin used as a user would: a separate test directory (not this repository's), the
installed package's ``pytest11`` entry point loading the plugin (no ``-p``, no conftest), its
fixtures starting real twins."""

from __future__ import annotations

import os
import shutil
import subprocess
import sys
import tempfile
import textwrap
from importlib.metadata import entry_points
from pathlib import Path

import pytest

from tests.unprivileged import unprivileged_argv

pytestmark = [pytest.mark.timeout(180)]

USER_TESTS = '''
import pytest

FLEET = {"hosts": {"c1": {"axes": ["a", "b"]}, "c2": {"axes": ["x"]}}, "groups": {"g": ["c1/a", "c2/x"]}}


def test_group_reflex_across_hosts(drives_twin):
    twin = drives_twin(FLEET)
    assert twin.endpoint.startswith("tcp/127.0.0.1:")
    assert twin.fleet.groups() == {"g": ["c1/a", "c2/x"]}
    assert twin.fleet.enable("@g").ok
    twin.fault("c2/x", 0x2310)
    assert twin.wait_state("c2/x", "fault", 10).error_code == 0x2310
    twin.wait_state("c1/a", "switch_on_disabled", 10)   # quick stop, then disabled
    assert twin.fleet.status("c1/b").state == "switch_on_disabled"  # not in the group: untouched


def test_shared_twin_is_shared(drives_twin_session):
    assert drives_twin_session(FLEET) is drives_twin_session(FLEET)


def test_shared_twin_cut(drives_twin_session):
    twin = drives_twin_session(FLEET)
    twin.cut("c2")
    assert twin.fleet.wait_until(lambda f: "c2" not in f.hosts(), 15)
    twin.restore("c2")
    twin.wait_answering(["c2"], 30)


@pytest.mark.drives_twin(backend="ecat")
def test_marker_chooses_ecat(drives_twin):
    twin = drives_twin({"hosts": {"e1": {"axes": ["a"]}}})
    assert twin.backend == "ecat"


def test_secure_twin_operator_enables_and_viewer_is_denied(drives_twin, tmp_path):
    import subprocess, sys
    from supervisor.fleet import Fleet
    pki = tmp_path / "pki"   # made as a user makes it: drives-pki init, one viewer issued
    for argv in (["init", str(pki)], ["issue", str(pki), "vic", "--role", "viewer"]):
        subprocess.run([sys.executable, "-m", "bus_agent.security.cli", *argv], check=True, capture_output=True)
    twin = drives_twin({"hosts": {"s1": {"axes": ["a", "b", "c"]}}}, pki=pki)
    assert twin.endpoint.startswith("tls/127.0.0.1:") and twin.fleet.identity == "twin-operator"
    assert twin.fleet.enable("s1/a").ok
    assert twin.wait_state("s1/a", "operation_enabled", 10)
    twin.fault("s1/b", 0x2310)   # fault injection as the twin's testbed principal
    assert twin.wait_state("s1/b", "fault", 10).error_code == 0x2310
    with Fleet(connect=[twin.endpoint], pki=str(pki), identity="vic") as viewer:
        assert viewer.wait_until(lambda f: f.status("s1/c") is not None, 10)   # a viewer may watch
        report = viewer.enable("s1/c")
        assert not report.ok and "denied" in report.reason, report
    assert twin.fleet.status("s1/c").state == "switch_on_disabled"   # the viewer changed nothing
    assert not (pki / "twin-router.pem").exists()                   # the user's directory is not written


def test_crash_fails_at_teardown(drives_twin):
    import os, signal
    twin = drives_twin({"hosts": {"k1": {"axes": ["a"]}}})
    os.kill(twin.agents["k1"].pid, signal.SIGKILL)
    twin.fleet.wait_until(lambda f: "k1" not in f.hosts(), 15)
'''


def test_entry_point_is_registered():
    eps = [ep for ep in entry_points(group="pytest11") if ep.name == "drives_twin"]
    assert [ep.value for ep in eps] == ["twin.pytest_plugin"]


def test_plugin_from_a_separate_directory(tmp_path):
    (tmp_path / "test_user.py").write_text(textwrap.dedent(USER_TESTS))
    env = {k: v for k, v in os.environ.items() if k not in ("PYTHONPATH", "PYTEST_ADDOPTS", "PYTEST_PLUGINS")}
    env["CI"] = "false"  # the ecat test decides skip vs run by root, not CI
    done = subprocess.run([sys.executable, "-m", "pytest", "-q", "-rA", "-p", "no:cacheprovider", str(tmp_path)],
                          cwd=tmp_path, env=env, capture_output=True, text=True, timeout=170)
    out = done.stdout + done.stderr
    assert "PASSED test_user.py::test_group_reflex_across_hosts" in out, out
    assert "PASSED test_user.py::test_shared_twin_is_shared" in out, out
    assert "PASSED test_user.py::test_shared_twin_cut" in out, out
    assert "PASSED test_user.py::test_secure_twin_operator_enables_and_viewer_is_denied" in out, out
    if os.geteuid() == 0:
        assert "PASSED test_user.py::test_marker_chooses_ecat" in out, out
    else:
        assert "SKIPPED" in out and "the ecat backend needs root" in out, out
    # the crash nobody asked for: the test passes, its teardown errors with the agent's exit
    assert "PASSED test_user.py::test_crash_fails_at_teardown" in out, out
    assert "ERROR test_user.py::test_crash_fails_at_teardown" in out, out
    assert "bus-agent k1 exited unexpectedly (exit code -9)" in out, out
    assert done.returncode == 1, out


def test_ecat_without_root_fails_under_ci():
    """The usual rule: a missing prerequisite fails under CI=true (run unprivileged via setpriv,
    also from a checkout nobody may read: tests/unprivileged.py)."""
    tmp_path = Path(tempfile.mkdtemp(prefix="twin-plugin-"))  # not under root's private pytest dir
    tmp_path.chmod(0o777)
    (tmp_path / "test_user.py").write_text("def test_e(drives_twin):\n"
                                          "    drives_twin({'hosts': {'e1': {'axes': ['a']}}}, backend='ecat')\n")
    env = {k: v for k, v in os.environ.items() if k not in ("PYTHONPATH",)}
    argv = [sys.executable, "-m", "pytest", "-q", "-rfs", "-p", "no:cacheprovider", str(tmp_path)]
    if os.geteuid() == 0:
        argv = unprivileged_argv(argv, readable=[tmp_path])
    for ci, expect in (("true", "1 failed"), ("", "1 skipped")):
        done = subprocess.run(argv, cwd=tmp_path, env={**env, "CI": ci, "HOME": str(tmp_path)},
                              capture_output=True, text=True, timeout=60)
        out = done.stdout + done.stderr
        assert expect in out and "the ecat backend needs root" in out, out
    shutil.rmtree(tmp_path, ignore_errors=True)
