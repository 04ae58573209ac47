"""A secure twin: mutual TLS on every link and the router's ACL, with certificates from the user's CA.

``drives-twin --pki DIR`` (``Twin(..., pki=DIR, identity=NAME)``) takes a directory made by
``drives-pki init`` and copies it into the twin's work directory; the twin issues the certificates
it needs into that copy, signed by DIR's CA (so DIR must hold ``ca.key``), and never writes DIR:

| principal | roles | who |
|---|---|---|
| each host's name | agent, testbed | that host's bus agent (its simulator's fault injection is under ``drives/@sim/<host>/``) |
| ``twin-router`` | router | the router |
| ``twin-control`` | testbed | the twin's own session for fault injection |
| ``twin-operator`` | operator | the twin's ``fleet``, unless ``identity`` names a principal of DIR |

The router's ACL is compiled from the copy's principals.toml, so every principal of DIR (an
operator, a viewer) connects to the twin with DIR and its own name as it would to the plant, and
is allowed exactly what its roles allow.
"""

from __future__ import annotations

import shutil
from pathlib import Path
from typing import Iterable

from bus_agent.security import pki as pki_mod
from bus_agent.security import principals

from .plan import PlanError

ROUTER = "twin-router"
CONTROL = "twin-control"
OPERATOR = "twin-operator"
AGENT_ROLES = ("agent", "testbed")


def tls_endpoint(ep: str) -> str:
    """The router's endpoint of a secure twin: ``tcp/`` becomes ``tls/``; other protocols: PlanError."""
    proto, _, addr = ep.partition("/")
    if proto not in ("tcp", "tls") or not addr:
        raise PlanError(f"--listen {ep!r}: with --pki the twin listens on tls/ (or tcp/, made tls/), not {proto}/")
    return f"tls/{addr}"


def twin_principals(hosts: Iterable[str], identity: str | None) -> dict[str, tuple[str, ...]]:
    """The principals the twin issues (name -> roles) for ``hosts``; PlanError on a name clash (pure)."""
    own = {ROUTER: ("router",), CONTROL: ("testbed",)}
    if identity is None:
        own[OPERATOR] = ("operator",)
    hosts = list(hosts)
    clash = sorted(set(hosts) & set(own))
    if clash:
        raise PlanError(f"host name(s) {clash} are the twin's own principals with --pki; rename the host(s)")
    if identity is not None and identity in hosts + [ROUTER, CONTROL]:
        raise PlanError(f"--identity {identity!r} is a principal the twin issues itself (an agent, its router or "
                        f"its control); name an operator of the PKI directory")
    return {**{h: AGENT_ROLES for h in hosts}, **own}


def prepare(pki_dir: str, into: str, hosts: Iterable[str], identity: str | None) -> str:
    """Copy ``pki_dir`` to ``into`` and issue the twin's principals there; the copy's path.
    PlanError naming what is missing (no CA key, ``identity`` not in the directory)."""
    src = Path(pki_dir)
    if not (src / pki_mod.CA_CERT).is_file():
        raise PlanError(f"--pki {pki_dir}: no {pki_mod.CA_CERT} there (make one with `drives-pki init {pki_dir}`)")
    if not (src / pki_mod.CA_KEY).is_file():
        raise PlanError(f"--pki {pki_dir}: no {pki_mod.CA_KEY}: the twin issues its router's and agents' "
                        f"certificates with the directory's CA (give it the directory `drives-pki init` made)")
    needed = twin_principals(hosts, identity)
    try:
        if identity is not None:  # checked in the user's directory: the messages name it
            pki_mod.check_identity(src, identity)
            if identity not in principals.load(src):
                raise PlanError(f"--identity {identity!r} is not in {src / principals.FILE_NAME}")
        shutil.copytree(src, into)
        for name, roles in needed.items():
            pki_mod.issue(into, name, roles, replace=True)
    except (pki_mod.PkiError, principals.PrincipalsError) as exc:
        raise PlanError(f"--pki {pki_dir}: {exc}") from None
    return into
