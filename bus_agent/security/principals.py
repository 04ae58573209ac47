"""``principals.toml``: who holds a certificate of this CA, and in which roles.

Written only by ``drives-pki`` (issue, remove), read by every secure session: the router (and
any session that listens) compiles its ACL from it (:func:`bus_agent.security.roles.compile_acl`).
One table per principal, and one per revoked name::

    [principals.alice]
    roles = ["operator"]
    serial = "5f3c..."
    not_after = "2027-12-01T16:00:00Z"
    sans = []
    hosts = ["h1", "h2"]          # optional: commands to these hosts only (default: every host)

    [revoked.bob]
    serial = "7a01..."
    revoked_at = "2026-12-01T19:00:00Z"

A revoked name stays revoked: zenoh's ACL knows a peer by its certificate's common name only,
so a new certificate of that name would let the revoked one in again.

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

from bus_agent.security.roles import ROLE_AGENT_OPS, ROLE_DRIVE_OPS, ROLES, RoleError, check_roles
from schemas.keys import InvalidKey, validate_name

FILE_NAME = "principals.toml"


class PrincipalsError(ValueError):
    """principals.toml cannot be read or holds something invalid."""


#: Roles that send commands: the ones a host scope (``hosts``) applies to.
COMMAND_ROLES = tuple(dict.fromkeys((*ROLE_DRIVE_OPS, *ROLE_AGENT_OPS)))


@dataclass(frozen=True)
class Principal:
    """One certificate holder: its name (the certificate's CN) and roles; ``hosts`` limits its
    commands to those hosts (empty: every host)."""

    name: str
    roles: tuple[str, ...]
    serial: str = ""
    not_after: str = ""
    sans: tuple[str, ...] = ()
    hosts: tuple[str, ...] = ()

    def __post_init__(self) -> None:
        try:
            validate_name(self.name, "principal")
            check_roles(self.roles)
            for h in self.hosts:
                validate_name(h, "host")
        except (InvalidKey, RoleError) as exc:
            raise PrincipalsError(f"principal {self.name!r}: {exc}") from None
        if self.hosts and not set(self.roles) & set(COMMAND_ROLES):
            raise PrincipalsError(f"principal {self.name!r}: hosts limit commands, and roles {list(self.roles)} send "
                                  f"none (only {', '.join(COMMAND_ROLES)} take hosts)")
        if len(set(self.hosts)) != len(self.hosts):
            raise PrincipalsError(f"principal {self.name!r}: host listed twice in {list(self.hosts)}")


@dataclass(frozen=True)
class Revoked:
    """A name whose certificate was revoked (``drives-pki revoke``): denied everything, never re-issued."""

    name: str
    serial: str = ""
    revoked_at: str = ""


def _strings(value: Any, what: str) -> tuple[str, ...]:
    if not isinstance(value, list) or not all(isinstance(s, str) for s in value):
        raise PrincipalsError(f"{what} must be a list of strings")
    return tuple(value)


def _tables(data: Mapping[str, Any], section: str, where: str, fields: set[str]) -> dict[str, Mapping[str, Any]]:
    table = data.get(section, {})
    if not isinstance(table, Mapping):
        raise PrincipalsError(f"{where}: {section} must be a table of [{section}.NAME]")
    for name, entry in table.items():
        if not isinstance(entry, Mapping):
            raise PrincipalsError(f"{where}: {section}.{name} must be a table")
        extra = set(entry) - fields
        if extra:
            raise PrincipalsError(f"{where}: {section}.{name}.{sorted(extra)[0]}: unknown key")
    return dict(table)


def parse_all(data: Mapping[str, Any], where: str = FILE_NAME) -> tuple[dict[str, Principal], dict[str, Revoked]]:
    """Principals and revoked names from parsed TOML; raises :class:`PrincipalsError`."""
    unknown = set(data) - {"principals", "revoked"}
    if unknown:
        raise PrincipalsError(f"{where}: unknown key {sorted(unknown)[0]!r} (expected [principals.NAME] and "
                              "[revoked.NAME] tables)")
    out: dict[str, Principal] = {}
    for name, entry in _tables(data, "principals", where, {"roles", "serial", "not_after", "sans", "hosts"}).items():
        roles = entry.get("roles")
        if not isinstance(roles, list) or not all(isinstance(r, str) for r in roles):
            raise PrincipalsError(f"{where}: principals.{name}.roles must be a list of role names "
                                  f"({', '.join(ROLES)})")
        out[name] = Principal(name, tuple(roles), str(entry.get("serial", "")), str(entry.get("not_after", "")),
                              _strings(entry.get("sans", []), f"{where}: principals.{name}.sans"),
                              _strings(entry.get("hosts", []), f"{where}: principals.{name}.hosts"))
    revoked = {name: Revoked(name, str(entry.get("serial", "")), str(entry.get("revoked_at", "")))
               for name, entry in _tables(data, "revoked", where, {"serial", "revoked_at"}).items()}
    both = sorted(set(out) & set(revoked))
    if both:
        raise PrincipalsError(f"{where}: {both[0]!r} is both a principal and revoked")
    return out, revoked


def parse(data: Mapping[str, Any], where: str = FILE_NAME) -> dict[str, Principal]:
    """Principals from parsed TOML; raises :class:`PrincipalsError`."""
    return parse_all(data, where)[0]


def load_all(pki_dir: str | Path) -> tuple[dict[str, Principal], dict[str, Revoked]]:
    """Read ``DIR/principals.toml``: principals and revoked names; raises :class:`PrincipalsError`."""
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
    return parse_all(data, str(path))


def load(pki_dir: str | Path) -> dict[str, Principal]:
    """Read the principals of ``DIR/principals.toml``; raises :class:`PrincipalsError`."""
    return load_all(pki_dir)[0]


def _toml_str(s: str) -> str:
    return json.dumps(s)  # a JSON string of printable characters is a TOML basic string


def _toml_list(items: Iterable[str]) -> str:
    return f"[{', '.join(_toml_str(s) for s in items)}]"


def dumps(principals: Iterable[Principal], revoked: Iterable[Revoked] = ()) -> str:
    """TOML text of ``principals`` and ``revoked`` (each sorted by name)."""
    lines = ["# Written by drives-pki (issue, revoke): who holds a certificate of this CA and in which roles.",
             "# Routers compile their ACL from this file at start: restart them after a change.", ""]
    for p in sorted(principals, key=lambda p: p.name):
        lines += [f"[principals.{_toml_str(p.name)}]",
                  f"roles = {_toml_list(p.roles)}",
                  f"serial = {_toml_str(p.serial)}",
                  f"not_after = {_toml_str(p.not_after)}",
                  f"sans = {_toml_list(p.sans)}"]
        lines += [f"hosts = {_toml_list(p.hosts)}"] if p.hosts else []
        lines.append("")
    for r in sorted(revoked, key=lambda r: r.name):
        lines += [f"[revoked.{_toml_str(r.name)}]", f"serial = {_toml_str(r.serial)}",
                  f"revoked_at = {_toml_str(r.revoked_at)}", ""]
    return "\n".join(lines)


def save(pki_dir: str | Path, principals: Iterable[Principal], revoked: Iterable[Revoked] = ()) -> None:
    """Replace ``DIR/principals.toml`` atomically (written aside, then renamed)."""
    path = Path(pki_dir) / FILE_NAME
    tmp = path.with_suffix(".toml.tmp")
    tmp.write_text(dumps(principals, revoked))
    os.replace(tmp, path)
