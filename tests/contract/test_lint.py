"""Static check of the whole tree: no unused imports, undefined names or dead f-strings."""

from __future__ import annotations

import subprocess
import sys
from pathlib import Path

ROOT = Path(__file__).resolve().parents[2]


def test_pyflakes_clean():
    done = subprocess.run([sys.executable, "-m", "pyflakes", "schemas", "bus_agent", "supervisor", "bench", "tests"],
                          cwd=ROOT, capture_output=True, text=True, timeout=120)
    assert done.returncode == 0, done.stdout + done.stderr
