"""Roles and the Zenoh ACL they compile to (pure: principals in, an ``access_control`` dict out).

The policy is written once, here, as data; ``compile_acl`` turns the principals of a CA (their
names are the certificates' common names, the identity zenoh's ACL matches) into zenoh 1.x
``access_control`` settings with ``default_permission: deny``. Rules are evaluated per link by
the session that loads them (the router; also any agent that listens): the subject is the
directly connected peer's certificate CN.

Zenoh facts this relies on (checked by tests/system/test_security.py, not assumed):
- a rule matches a message only if one of its key expressions *includes* the message's key;
- wildcards never match a verbatim chunk (``@v1``, ``@sup``, ``@sim``), so every verbatim form
  is spelled out;
- a denied query gets no reply at all; a denied put or declaration is dropped silently.

Identity on commands: a principal may query only command keys that end in
``@sup/<its own name>`` (:func:`schemas.keys.drive_cmd` with ``principal``); the agent reads the
requester from there.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any, Iterable, Mapping, Protocol, Sequence

from schemas import keys
from schemas.messages import AGENT_OPS, DRIVE_OPS


class RoleError(ValueError):
    """An unknown role or a role combination that makes no sense."""


#: The motion ops (issue 10: ``bus_agent/motion``), granted here ahead of the agents that serve
#: them: a grant for an op nobody serves opens nothing.
MOTION_OPS = ("move", "jog", "home", "stop")
#: Drive ops (``.../drive/<axis>/cmd/<op>``) each commanding role may send. Every op of the
#: contract must appear here (tests/unit/test_security_roles.py): a new op is denied to everyone
#: until somebody decides who may send it.
ROLE_DRIVE_OPS: Mapping[str, tuple[str, ...]] = {
    "operator": ("enable", "switch_on", "shutdown", "disable", "quick_stop", "halt", "set_mode", "lease", "release",
                 *MOTION_OPS),
    "maintenance": ("fault_reset", "quick_stop", "disable", "set_mode", "stop"),
}
#: Agent ops (``.../agent/cmd/<op>``) each commanding role may send.
ROLE_AGENT_OPS: Mapping[str, tuple[str, ...]] = {
    "maintenance": ("nmt",),
}
#: What a role may read: "all" (status, events, agent status, agent and supervisor tokens, the
#: agents' flight recordings) or "status" (status, events, agent status and agent tokens).
ROLE_READ: Mapping[str, str] = {"operator": "all", "maintenance": "all", "viewer": "status"}


def _ops_text(role: str) -> str:
    return ", ".join((*ROLE_DRIVE_OPS.get(role, ()), *ROLE_AGENT_OPS.get(role, ())))


#: Roles and what they are for (``drives-pki issue --role``).
ROLES: Mapping[str, str] = {
    "router": "a drives-router: links to other routers, forwards everything it was let in",
    "agent": "a bus agent; its principal name is its host name: publishes, serves and holds a token only there",
    "operator": f"{_ops_text('operator')}; reads everything",
    "maintenance": f"{_ops_text('maintenance')}; reads everything",
    "viewer": "reads drive status, events and agent status only",
    "testbed": "simulator fault injection: serves and queries drives/@sim/** (test beds only)",
}

ALL_MESSAGES = ("put", "delete", "declare_subscriber", "query", "declare_queryable", "reply", "liveliness_token",
                "declare_liveliness_subscriber", "liveliness_query")
#: Declarations a session must receive to send anything: a client sends a put or query only
#: once its router declared a matching subscriber or queryable.
DECLARATIONS = ("declare_subscriber", "declare_queryable", "declare_liveliness_subscriber", "liveliness_token")

#: Keys everyone with "status" read access may read (subscribe, get, and receive).
READ_STATUS = (keys.ALL_DRIVE_STATUS, keys.ALL_DRIVE_EVENTS, keys.ALL_AGENT_STATUS)
#: What "all" readers may read beyond READ_STATUS and agent tokens.
READ_ALL_EXTRA = (keys.ALL_SUPERVISORS, keys.agent_recording("*"))
#: Command keys with any principal (declarations egress, router links).
ANY_CMD = (keys.drive_cmd("*", "*", "*", "*"), keys.agent_cmd("*", "*", "*"))
#: Every key form of the project (router links, declarations egress).
EVERY_KEY = (f"{keys.ROOT}/**", keys.ALL_SUPERVISORS, *ANY_CMD, keys.ALL_SIM)


def check_roles(roles: Sequence[str]) -> tuple[str, ...]:
    """Validate a principal's roles; raises :class:`RoleError`."""
    if not roles:
        raise RoleError(f"no role given (roles: {', '.join(ROLES)})")
    for r in roles:
        if r not in ROLES:
            raise RoleError(f"unknown role {r!r} (roles: {', '.join(ROLES)})")
    if len(set(roles)) != len(roles):
        raise RoleError(f"role listed twice in {list(roles)}")
    if "router" in roles and len(roles) > 1:
        raise RoleError("a router certificate holds the router role only")
    return tuple(roles)


class PrincipalLike(Protocol):
    """A principal as the compiler needs it (``bus_agent.security.principals.Principal``)."""

    @property
    def name(self) -> str: ...

    @property
    def roles(self) -> tuple[str, ...]: ...

    @property
    def hosts(self) -> tuple[str, ...]: ...


@dataclass(frozen=True)
class Grant:
    """Messages allowed on keys in one flow for one principal (one ACL rule)."""

    flow: str                       # ingress (from the peer) or egress (to it)
    messages: tuple[str, ...]
    key_exprs: tuple[str, ...]


def _both(messages_in: tuple[str, ...], messages_out: tuple[str, ...], kes: tuple[str, ...]) -> list[Grant]:
    return [Grant("ingress", messages_in, kes), Grant("egress", messages_out, kes)]


def grants(name: str, roles: Iterable[str], hosts: Sequence[str] = ()) -> list[Grant]:
    """What principal ``name`` with ``roles`` may send (ingress) and receive (egress); ``hosts``
    limits its commands to those hosts (empty: every host). Reading stays fleet-wide: a
    supervisor subscribes to every host's status with one wildcard, which a per-host rule would
    not include."""
    roles = tuple(roles)
    out: list[Grant] = [Grant("egress", DECLARATIONS, EVERY_KEY)]
    read = {ROLE_READ[r] for r in roles if r in ROLE_READ}
    if read:
        kes = READ_STATUS + (keys.ALL_ALIVE,) + (READ_ALL_EXTRA if "all" in read else ())
        out += _both(("declare_subscriber", "query", "declare_liveliness_subscriber", "liveliness_query"),
                     ("put", "delete", "reply", "liveliness_token"), kes)
    # The host is a chunk of the command key: a scoped principal's rules name its hosts instead of '*'.
    targets = tuple(hosts) or ("*",)
    cmd_kes = tuple(keys.drive_cmd(h, "*", op, name) for r in roles for op in ROLE_DRIVE_OPS.get(r, ()) for h in targets) + \
        tuple(keys.agent_cmd(h, op, name) for r in roles for op in ROLE_AGENT_OPS.get(r, ()) for h in targets)
    if cmd_kes:
        out += _both(("query",), ("reply",), tuple(dict.fromkeys(cmd_kes)))
        # Its own supervisor token (leases are bound to it) and nobody else's.
        out.append(Grant("ingress", ("liveliness_token",), (keys.supervisor_alive(name),)))
    for role in roles:
        if role == "router":
            out += _both(ALL_MESSAGES, ALL_MESSAGES, EVERY_KEY)
        elif role == "agent":
            own = (keys.host_tree(name), keys.drive_cmd(name, "*", "*", "*"), keys.agent_cmd(name, "*", "*"))
            out.append(Grant("ingress", ("put", "delete", "reply", "declare_queryable"), own))
            out.append(Grant("ingress", ("liveliness_token",), (keys.alive(name),)))
            # Egress checks the query's own key: supervisors fan out with '*' for the host.
            out.append(Grant("egress", ("query",), (*own, *READ_STATUS, *ANY_CMD)))
            # Cross-host groups: other drives' status and agents' tokens; supervisors' tokens (leases).
            out += _both(("declare_subscriber",), ("put", "delete"), (keys.ALL_DRIVE_STATUS,))
            out += _both(("declare_liveliness_subscriber", "liveliness_query"), ("liveliness_token",),
                         (keys.ALL_ALIVE, keys.ALL_SUPERVISORS))
        elif role == "testbed":
            out += _both(("query", "declare_queryable", "reply"), ("query", "reply"), (keys.ALL_SIM,))
    return out


def compile_acl(principals: Iterable[PrincipalLike], revoked: Iterable[str] = ()) -> dict[str, Any]:
    """zenoh ``access_control`` settings: default deny, one subject and policy per principal;
    ``revoked`` names get an explicit deny of everything (default deny would refuse them anyway:
    the rule says so in the ACL a router loads, and holds if a policy ever names them)."""
    rules: list[dict[str, Any]] = []
    subjects: list[dict[str, Any]] = []
    policies: list[dict[str, Any]] = []
    for p in sorted(principals, key=lambda p: p.name):
        check_roles(p.roles)
        ids = []
        for i, g in enumerate(grants(p.name, p.roles, p.hosts)):
            rid = f"{p.name}:{i}"
            rules.append({"id": rid, "messages": list(g.messages), "flows": [g.flow], "permission": "allow",
                          "key_exprs": list(g.key_exprs)})
            ids.append(rid)
        sid = f"cn:{p.name}"
        subjects.append({"id": sid, "cert_common_names": [p.name]})
        policies.append({"id": f"policy:{p.name}", "rules": ids, "subjects": [sid]})
    names = sorted(set(revoked))
    if names:
        rules.append({"id": "revoked", "messages": list(ALL_MESSAGES), "flows": ["ingress", "egress"],
                      "permission": "deny", "key_exprs": list(EVERY_KEY)})
        subjects.append({"id": "cn:revoked", "cert_common_names": names})
        policies.append({"id": "policy:revoked", "rules": ["revoked"], "subjects": ["cn:revoked"]})
    return {"enabled": True, "default_permission": "deny", "rules": rules, "subjects": subjects,
            "policies": policies}


def allowed_ops(roles: Iterable[str]) -> tuple[str, ...]:
    """Drive and agent ops a principal with ``roles`` may send (for messages and docs)."""
    ops = [op for r in roles for op in (*ROLE_DRIVE_OPS.get(r, ()), *ROLE_AGENT_OPS.get(r, ()))]
    return tuple(op for op in (*DRIVE_OPS, *AGENT_OPS) if op in ops)
