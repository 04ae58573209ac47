"""Run a command as an unprivileged user (nobody) from a checkout that user cannot read.

A clone under a 0700 home (``/root/clone``) puts its venv, its editable install and maybe the
base interpreter (``~/.pyenv``) behind a directory nobody may not traverse. Nothing is made
readable on disk: the command runs in a private mount namespace (``unshare --mount``) in which
each such directory is covered by an empty tmpfs that holds only the trees the command needs,
bind-mounted read-only at their own paths (absolute paths, the venv's symlinks and the editable
finder keep working); everything else in that directory stays hidden. Then ``setpriv`` drops to
uid/gid 65534 without groups. Needs root (as setpriv does).
"""

from __future__ import annotations

import os
import shlex
import stat
import sys
from pathlib import Path
from typing import Iterable, Sequence

NOBODY = 65534


def _traversable(p: Path) -> bool:
    st = p.stat()
    if st.st_uid == NOBODY:
        return bool(st.st_mode & stat.S_IXUSR)
    if st.st_gid == NOBODY:
        return bool(st.st_mode & stat.S_IXGRP)
    return bool(st.st_mode & stat.S_IXOTH)


def hidden_under(paths: Iterable[Path]) -> dict[Path, list[Path]]:
    """For each directory nobody cannot traverse (the topmost on the way to a path): the paths
    needed below it (outermost only: a path inside another needed one comes with it)."""
    needed = sorted({Path(os.path.realpath(p)) for p in paths}, key=lambda p: len(p.parts))
    outer: list[Path] = []
    for p in needed:
        if not any(p == o or o in p.parents for o in outer):
            outer.append(p)
    plan: dict[Path, list[Path]] = {}
    for p in outer:
        for a in reversed(p.parents):  # from / down
            if a != p and not _traversable(a):
                plan.setdefault(a, []).append(p)
                break
    return plan


def unprivileged_argv(argv: Sequence[str], readable: Iterable[Path] = ()) -> list[str]:
    """``argv`` run as nobody, with ``readable`` (and this interpreter's venv and base install,
    and the checkout) readable to it whatever the permissions of the directories above them."""
    root = Path(__file__).resolve().parents[1]
    plan = hidden_under([root, Path(sys.prefix), Path(sys.base_prefix), *readable])
    lines = ["set -e", "stage=$(mktemp -d)"]
    k = 0
    for cover, inside in plan.items():
        staged = []
        for p in inside:
            lines += [f"mkdir $stage/{k}", f"mount --bind {shlex.quote(str(p))} $stage/{k}"]
            staged.append((k, p))
            k += 1
        lines.append(f"mount -t tmpfs -o mode=0755,size=1m drives-unprivileged {shlex.quote(str(cover))}")
        for n, p in staged:
            q = shlex.quote(str(p))
            lines += [f"mkdir -p {q}", f"mount --bind $stage/{n} {q}", f"mount -o remount,bind,ro {q}"]
    lines.append('exec setpriv --reuid=65534 --regid=65534 --clear-groups -- "$@"')
    return ["unshare", "--mount", "--propagation", "private", "--", "sh", "-c", "\n".join(lines), "sh", *argv]
