"""Static checks of the whole tree: pyflakes (unused imports, undefined names) and mypy (types)."""

from __future__ import annotations

import hashlib
import os
import subprocess
import sys
import tempfile
from pathlib import Path

ROOT = Path(__file__).resolve().parents[2]


def test_pyflakes_clean():
    done = subprocess.run([sys.executable, "-m", "pyflakes", "schemas", "bus_agent", "supervisor", "dashboard", "twin", "drives_opcua", "examples", "bench", "tests"],
                          cwd=ROOT, capture_output=True, text=True, timeout=120)
    assert done.returncode == 0, done.stdout + done.stderr


def test_mypy_clean():
    # outside the tree, per user and per checkout: two checkouts sharing one cache corrupt it
    tree = hashlib.sha1(str(ROOT).encode()).hexdigest()[:10]
    cache = Path(tempfile.gettempdir()) / f"zenoh-drives-mypy-{os.getuid()}-{tree}"
    done = subprocess.run([sys.executable, "-m", "mypy", "--no-error-summary", "--cache-dir", str(cache)],
                          cwd=ROOT, capture_output=True, text=True, timeout=300)
    assert done.returncode == 0, done.stdout + done.stderr
