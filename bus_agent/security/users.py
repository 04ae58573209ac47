"""``users.toml``: OPC UA users who log in with a name and a password (``drives-pki user``).

People at an OPC UA client (UaExpert, a SCADA) log in to drives-opcua either with an X.509 user
certificate of the CA (a principal of principals.toml) or with a name and a password kept here,
in the same PKI directory::

    [users.olga]
    roles = ["operator"]
    password = "scrypt$16384$8$1$<salt, base64>$<key, base64>"

Only a salted hash is stored: scrypt (``hashlib.scrypt``, RFC 7914) with a random 16-byte salt
per user and n=2**14, r=8, p=1 (the parameters travel with each hash, so they can be raised
later without breaking older entries). The file is written 0600 and atomically.

The roles are those a person can have (:data:`USER_ROLES`): what each may do is the project's
role table (``bus_agent.security.roles``). Pure apart from reading and writing the file.
"""

from __future__ import annotations

import base64
import hashlib
import hmac
import os
import secrets
import tomllib
from dataclasses import dataclass
from pathlib import Path
from typing import Iterable

from bus_agent.security.principals import _toml_list, _toml_str
from bus_agent.security.roles import ROLE_READ
from schemas.keys import InvalidKey, validate_name

FILE_NAME = "users.toml"
#: Roles a password user may hold: the people's roles (reading and commanding ones).
USER_ROLES = tuple(ROLE_READ)
#: scrypt cost: n (CPU/memory, a power of 2), r (block size), p (parallelism); about 50 ms.
SCRYPT_N, SCRYPT_R, SCRYPT_P = 2**14, 8, 1
SALT_BYTES, KEY_BYTES = 16, 32
MIN_PASSWORD_LEN = 8


class UsersError(ValueError):
    """users.toml cannot be read, holds something invalid, or a user cannot be written."""


@dataclass(frozen=True)
class PasswordUser:
    """A user of ``users.toml``: name, roles and the stored hash (``scrypt$n$r$p$salt$key``)."""

    name: str
    roles: tuple[str, ...]
    password: str

    def verify(self, password: str) -> bool:
        """True when ``password`` is this user's (constant-time comparison of the derived keys)."""
        try:
            algo, n, r, p, salt, key = self.password.split("$")
            if algo != "scrypt":
                return False
            want = base64.b64decode(key)
            got = hashlib.scrypt(password.encode(), salt=base64.b64decode(salt), n=int(n), r=int(r), p=int(p),
                                 maxmem=256 * int(n) * int(r) + 2**20, dklen=len(want))
        except (ValueError, TypeError):
            return False
        return hmac.compare_digest(got, want)


def hash_password(password: str) -> str:
    """The stored form of ``password``: scrypt with a new random salt."""
    salt = secrets.token_bytes(SALT_BYTES)
    key = hashlib.scrypt(password.encode(), salt=salt, n=SCRYPT_N, r=SCRYPT_R, p=SCRYPT_P,
                         maxmem=256 * SCRYPT_N * SCRYPT_R + 2**20, dklen=KEY_BYTES)
    return "$".join(("scrypt", str(SCRYPT_N), str(SCRYPT_R), str(SCRYPT_P),
                     base64.b64encode(salt).decode(), base64.b64encode(key).decode()))


def _check(name: str, roles: Iterable[str], where: str) -> tuple[str, tuple[str, ...]]:
    try:
        validate_name(name, "user name")
    except InvalidKey as exc:
        raise UsersError(f"{where}: {exc}") from None
    roles = tuple(roles)
    bad = [r for r in roles if r not in USER_ROLES]
    if not roles or bad:
        raise UsersError(f"{where}: user {name!r}: roles {list(roles)}: a user has one or more of "
                         f"{', '.join(USER_ROLES)}")
    return name, roles


def load(pki_dir: str | Path) -> dict[str, PasswordUser]:
    """The users of ``DIR/users.toml`` ({} when there is none); raises :class:`UsersError`."""
    path = Path(pki_dir) / FILE_NAME
    try:
        with path.open("rb") as f:
            data = tomllib.load(f)
    except FileNotFoundError:
        return {}
    except (OSError, tomllib.TOMLDecodeError) as exc:
        raise UsersError(f"{path}: cannot read: {exc}") from None
    if set(data) - {"users"} or not isinstance(data.get("users", {}), dict):
        raise UsersError(f"{path}: expected [users.NAME] tables only")
    out: dict[str, PasswordUser] = {}
    for name, entry in data.get("users", {}).items():
        if not isinstance(entry, dict) or set(entry) != {"roles", "password"}:
            raise UsersError(f"{path}: users.{name}: expected exactly roles and password")
        if not isinstance(entry["roles"], list) or not isinstance(entry["password"], str):
            raise UsersError(f"{path}: users.{name}: roles is a list of names, password a string")
        name, roles = _check(name, entry["roles"], str(path))
        out[name] = PasswordUser(name, roles, entry["password"])
    return out


def save(pki_dir: str | Path, users: Iterable[PasswordUser]) -> None:
    """Replace ``DIR/users.toml`` atomically, created 0600."""
    path = Path(pki_dir) / FILE_NAME
    lines = ["# Written by drives-pki user: OPC UA users (name, roles, scrypt hash of the password).", ""]
    for u in sorted(users, key=lambda u: u.name):
        lines += [f"[users.{_toml_str(u.name)}]", f"roles = {_toml_list(u.roles)}",
                  f"password = {_toml_str(u.password)}", ""]
    tmp = path.with_suffix(".toml.tmp")
    if tmp.exists():
        tmp.unlink()
    fd = os.open(tmp, os.O_WRONLY | os.O_CREAT | os.O_EXCL, 0o600)
    with os.fdopen(fd, "w") as f:
        f.write("\n".join(lines))
    os.replace(tmp, path)


def set_user(pki_dir: str | Path, name: str, roles: Iterable[str], password: str) -> PasswordUser:
    """Add ``name`` or replace its roles and password; raises :class:`UsersError` (nothing written)."""
    d = Path(pki_dir)
    if not d.is_dir():
        raise UsersError(f"{d}: no such directory (create the CA with `drives-pki init {d}`)")
    name, roles = _check(name, roles, str(d / FILE_NAME))
    if len(password) < MIN_PASSWORD_LEN:
        raise UsersError(f"password of {name!r}: at least {MIN_PASSWORD_LEN} characters")
    users = load(d)
    user = PasswordUser(name, roles, hash_password(password))
    users[name] = user
    save(d, users.values())
    return user
