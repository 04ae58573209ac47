"""The repository's docs and comments point only to files a clone has (issue 9)."""

from __future__ import annotations

import re
import subprocess
from pathlib import Path

ROOT = Path(__file__).resolve().parents[2]
#: Paths outside the repository that earlier docs pointed to.
OUTSIDE = re.compile(r"\.\./shared|/work/shared|shared/docs/|\.\./seeds|/work/seeds")


def test_no_file_points_outside_the_repository() -> None:
    files = subprocess.run(["git", "ls-files"], cwd=ROOT, capture_output=True, text=True, check=True).stdout.split()
    offenders = []
    for name in files:
        if name == "tests/contract/test_docs_standalone.py":
            continue
        path = ROOT / name
        try:
            text = path.read_text(encoding="utf-8")
        except (UnicodeDecodeError, FileNotFoundError, IsADirectoryError):
            continue
        offenders += [f"{name}:{i}: {line.strip()}" for i, line in enumerate(text.splitlines(), 1)
                      if OUTSIDE.search(line)]
    assert not offenders, "references to files a clone does not have:\n" + "\n".join(offenders)
