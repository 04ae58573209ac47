"""Shared test policy: prerequisites fail loudly in CI and skip with a how-to outside it."""

from __future__ import annotations

import os

import pytest

IN_CI = os.environ.get("CI", "").lower() in ("1", "true", "yes")


def require(condition: bool, what: str, how: str) -> None:
    """Fail in CI, skip elsewhere, when a prerequisite (root, veth, netns) is missing."""
    if condition:
        return
    if IN_CI:
        pytest.fail(f"CI prerequisite missing: {what} ({how})", pytrace=False)
    pytest.skip(f"{what} missing; to run this test: {how}")


def require_root() -> None:
    require(os.geteuid() == 0, "root privileges (veth pairs, raw sockets, netns)",
            "run the suite as root, e.g. `sudo make test`")
