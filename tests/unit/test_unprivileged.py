"""tests/unprivileged.py: which directories hide what an unprivileged run needs (pure planning
over real directories; the run itself is in tests/system/test_twin_plugin.py)."""

from __future__ import annotations

import shutil
import tempfile
from pathlib import Path

import pytest

from tests.unprivileged import hidden_under, unprivileged_argv


@pytest.fixture
def base():
    """A directory anyone may traverse (pytest's own tmp_path lies under a 0700 directory)."""
    d = Path(tempfile.mkdtemp(prefix="unpriv-"))
    d.chmod(0o755)
    yield d
    shutil.rmtree(d, ignore_errors=True)


def test_a_0700_home_hides_the_clone_and_its_venv_once(base):
    tmp_path = base
    home = tmp_path / "home"
    (home / "clone" / ".venv").mkdir(parents=True)
    (home / ".pyenv" / "3.11").mkdir(parents=True)
    open_dir = tmp_path / "shared"
    open_dir.mkdir()
    tmp_path.chmod(0o755)
    home.chmod(0o700)
    plan = hidden_under([home / "clone", home / "clone" / ".venv", home / ".pyenv" / "3.11", open_dir])
    assert plan == {home: [home / "clone", home / ".pyenv" / "3.11"]}


def test_a_readable_checkout_needs_no_cover(base):
    tmp_path = base
    (tmp_path / "clone").mkdir()
    tmp_path.chmod(0o755)
    assert hidden_under([tmp_path / "clone"]) == {}


def test_the_command_runs_as_nobody_in_a_private_mount_namespace():
    argv = unprivileged_argv(["python", "-c", "pass"])
    assert argv[:5] == ["unshare", "--mount", "--propagation", "private", "--"]
    assert argv[-3:] == ["python", "-c", "pass"]
    assert "exec setpriv --reuid=65534 --regid=65534 --clear-groups" in argv[7]
