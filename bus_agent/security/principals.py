"""``principals.toml``: who holds a certificate of this CA, and in which roles.

Written only by ``drives-pki`` (issue, remove), read by every secure session: the router (and
any session that listens) compiles its ACL from it (:func:`bus_agent.security.roles.compile_acl`).
One table per principal::

    [principals.alice]
    roles = ["operator"]
    serial = "5f3c..."
    not_after = "2027-12-01T16:00:00Z"
    sans = []

Pure apart from reading and writing the file. Bad content raises :class:`PrincipalsError`
naming the principal and the key.
"""

from __future__ import annotations

import json
import os
import tomllib
from dataclasses import dataclass
from pathlib import Path
from typing import Any, Iterable, Mapping

from bus_agent.security.roles import ROLES, RoleError, check_roles
from schemas.keys import InvalidKey, validate_name

FILE_NAME = "principals.toml"


class PrincipalsError(ValueError):
    """principals.toml cannot be read or holds something invalid."""


@dataclass(frozen=True)
class Principal:
    """One certificate holder: its name (the certificate's CN) and roles."""

    name: str
    roles: tuple[str, ...]
    serial: str = ""
    not_after: str = ""
    sans: tuple[str, ...] = ()

    def __post_init__(self) -> None:
        try:
            validate_name(self.name, "principal")
            check_roles(self.roles)
        except (InvalidKey, RoleError) as exc:
            raise PrincipalsError(f"principal {self.name!r}: {exc}") from None


def parse(data: Mapping[str, Any], where: str = FILE_NAME) -> dict[str, Principal]:
    """Principals from parsed TOML; raises :class:`PrincipalsError`."""
    unknown = set(data) - {"principals"}
    if unknown:
        raise PrincipalsError(f"{where}: unknown key {sorted(unknown)[0]!r} (expected [principals.NAME] tables)")
    table = data.get("principals", {})
    if not isinstance(table, Mapping):
        raise PrincipalsError(f"{where}: principals must be a table of [principals.NAME]")
    out: dict[str, Principal] = {}
    for name, entry in table.items():
        if not isinstance(entry, Mapping):
            raise PrincipalsError(f"{where}: principals.{name} must be a table")
        extra = set(entry) - {"roles", "serial", "not_after", "sans"}
        if extra:
            raise PrincipalsError(f"{where}: principals.{name}.{sorted(extra)[0]}: unknown key")
        roles = entry.get("roles")
        if not isinstance(roles, list) or not all(isinstance(r, str) for r in roles):
            raise PrincipalsError(f"{where}: principals.{name}.roles must be a list of role names "
                                  f"({', '.join(ROLES)})")
        sans = entry.get("sans", [])
        if not isinstance(sans, list) or not all(isinstance(s, str) for s in sans):
            raise PrincipalsError(f"{where}: principals.{name}.sans must be a list of strings")
        out[name] = Principal(name, tuple(roles), str(entry.get("serial", "")), str(entry.get("not_after", "")),
                              tuple(sans))
    return out


def load(pki_dir: str | Path) -> dict[str, Principal]:
    """Read ``DIR/principals.toml``; raises :class:`PrincipalsError`."""
    path = Path(pki_dir) / FILE_NAME
    try:
        with path.open("rb") as f:
            data = tomllib.load(f)
    except FileNotFoundError:
        raise PrincipalsError(f"{path}: missing (create the CA with `drives-pki init {pki_dir}`)") from None
    except OSError as exc:
        raise PrincipalsError(f"{path}: cannot read: {exc.strerror}") from None
    except tomllib.TOMLDecodeError as exc:
        raise PrincipalsError(f"{path}: TOML syntax error: {exc}") from None
    return parse(data, str(path))


def _toml_str(s: str) -> str:
    return json.dumps(s)  # a JSON string of printable characters is a TOML basic string


def dumps(principals: Iterable[Principal]) -> str:
    """TOML text of ``principals`` (sorted by name)."""
    lines = ["# Written by drives-pki (issue, remove): who holds a certificate of this CA and in which roles.",
             "# Routers compile their ACL from this file at start: restart them after a change.", ""]
    for p in sorted(principals, key=lambda p: p.name):
        lines += [f"[principals.{_toml_str(p.name)}]",
                  f"roles = [{', '.join(_toml_str(r) for r in p.roles)}]",
                  f"serial = {_toml_str(p.serial)}",
                  f"not_after = {_toml_str(p.not_after)}",
                  f"sans = [{', '.join(_toml_str(s) for s in p.sans)}]", ""]
    return "\n".join(lines)


def save(pki_dir: str | Path, principals: Iterable[Principal]) -> None:
    """Replace ``DIR/principals.toml`` atomically (written aside, then renamed)."""
    path = Path(pki_dir) / FILE_NAME
    tmp = path.with_suffix(".toml.tmp")
    tmp.write_text(dumps(principals))
    os.replace(tmp, path)
