"""Who may do what on drives-opcua: users, the service ruleset, client certificates.

- :class:`DrivesUserManager` logs a session in: anonymous; a name and password of
  ``users.toml`` (``drives-pki user``); or an X.509 user certificate issued by the deployment's CA
  to a principal of ``principals.toml`` (not revoked, within its dates). Roles come from those
  files; anything else is refused (BadUserAccessDenied).
- :class:`ServiceRules` is asyncua's permission ruleset: every session may browse, read and
  subscribe; only a logged-in user reaches Call (anonymous never does); nobody writes or changes
  the address space. It also makes the session's user known to the method being called
  (:data:`CURRENT_USER`): asyncua hands a method nothing but its arguments.
- :func:`guard_channels`: client application certificates must be issued by the CA.
"""

from __future__ import annotations

import contextvars
import datetime as dt
import logging
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

from asyncua import ua
from asyncua.crypto.permission_rules import PermissionRuleset, User, UserRole
from asyncua.server.user_managers import UserManager
from asyncua.common.utils import ServiceError
from asyncua.crypto.security_policies import SecurityPolicyNone
from cryptography import x509
from cryptography.x509.oid import NameOID

from bus_agent.security import principals as pfile
from bus_agent.security import users as ufile
from bus_agent.security.pki import CA_CERT

log = logging.getLogger("drives_opcua")


@dataclass
class DrivesUser(User):
    """An asyncua user with the project's roles and how it logged in (``password``, ``certificate``)."""

    roles: tuple[str, ...] = ()
    via: str = "anonymous"
    hosts: tuple[str, ...] = field(default=())  # a certificate principal's host scope (empty: every host)


ANONYMOUS = DrivesUser(role=UserRole.Anonymous, name=None)

#: The user of the session whose request is being served (set by :class:`ServiceRules` for each
#: request, in the connection's task, right before asyncua dispatches it).
CURRENT_USER: contextvars.ContextVar[DrivesUser | None] = contextvars.ContextVar("opcua_user", default=None)


#: The certificate of the X.509 identity token being activated (see :meth:`DrivesUserManager.install`).
_TOKEN_CERT: contextvars.ContextVar[bytes | None] = contextvars.ContextVar("opcua_token_cert", default=None)


class DrivesUserManager(UserManager):
    """Anonymous, password (``users.toml``) and CA-issued certificate users. Without a PKI
    directory, anonymous only."""

    def __init__(self, pki_dir: str | Path | None) -> None:
        self.pki = None if pki_dir is None else Path(pki_dir)
        self.users = ufile.load(self.pki) if self.pki else {}
        self.ca = x509.load_pem_x509_certificate((self.pki / CA_CERT).read_bytes()) if self.pki else None

    def install(self, iserver: Any) -> None:
        """Note which certificate an X.509 identity token proved (asyncua passes ``get_user`` the
        secure channel's client *application* certificate for anonymous tokens too: that one
        must not log anybody in)."""
        verify = iserver.verify_x509_token

        def verified(isession: Any, token: Any, signature: Any) -> bytes:
            der = verify(isession, token, signature)
            _TOKEN_CERT.set(der)
            return der

        iserver.verify_x509_token = verified

    def get_user(self, iserver: Any, username: str | None = None, password: str | None = None,
                 certificate: Any = None) -> User | None:
        token_cert = _TOKEN_CERT.get()
        _TOKEN_CERT.set(None)
        if username is not None:
            return self._password_user(username, password or "")
        if certificate and token_cert is not None and certificate == token_cert:
            return self._certificate_user(certificate)
        return ANONYMOUS

    def _password_user(self, username: str, password: str) -> DrivesUser | None:
        user = self.users.get(username)
        if user is None or not user.verify(password):
            log.warning("opcua: login refused for user %r (unknown name or wrong password)", username)
            return None
        log.info("opcua: %s logged in with a password (%s)", username, ", ".join(user.roles))
        return DrivesUser(role=UserRole.User, name=username, roles=user.roles, via="password")

    def _certificate_user(self, der: bytes) -> DrivesUser | None:
        if self.ca is None or self.pki is None:
            return None
        try:
            cert = x509.load_der_x509_certificate(der)
            problem = issued_by_ca(cert, self.ca)
        except ValueError as exc:
            problem = f"not a certificate: {exc}"
        if problem:
            log.warning("opcua: user certificate refused: %s", problem)
            return None
        cn = cert.subject.get_attributes_for_oid(NameOID.COMMON_NAME)
        name = str(cn[0].value) if cn else ""
        known, revoked = pfile.load_all(self.pki)  # read now: a revocation counts at the next login
        p = known.get(name)
        if p is None or name in revoked or (p.serial and p.serial != format(cert.serial_number, "x")):
            log.warning("opcua: user certificate of %r refused: not a current principal of %s", name, self.pki)
            return None
        roles = tuple(r for r in p.roles if r in ufile.USER_ROLES)
        if not roles:
            log.warning("opcua: user certificate of %r refused: roles %s are no user's", name, list(p.roles))
            return None
        log.info("opcua: %s logged in with a certificate (%s)", name, ", ".join(roles))
        return DrivesUser(role=UserRole.User, name=name, roles=roles, via="certificate", hosts=p.hosts)


def issued_by_ca(cert: x509.Certificate, ca: x509.Certificate) -> str:
    """'' when ``cert`` is signed by ``ca`` and within its dates, else what is wrong."""
    try:
        cert.verify_directly_issued_by(ca)
    except Exception as exc:  # ValueError, TypeError or InvalidSignature: not ours either way
        return f"{cert.subject.rfc4514_string()} is not issued by {ca.subject.rfc4514_string()} ({type(exc).__name__})"
    now = dt.datetime.now(dt.timezone.utc)
    if not cert.not_valid_before_utc <= now <= cert.not_valid_after_utc:
        return f"{cert.subject.rfc4514_string()} is not valid now (until {cert.not_valid_after_utc:%Y-%m-%d})"
    return ""


def _ids(*names: str) -> frozenset[ua.NodeId]:
    return frozenset(ua.NodeId(getattr(ua.ObjectIds, f"{n}Request_Encoding_DefaultBinary")) for n in names)


#: What every session may do: look, read, subscribe (and close what it opened).
READ_SERVICES = _ids("Read", "Browse", "BrowseNext", "TranslateBrowsePathsToNodeIds", "RegisterNodes",
                     "UnregisterNodes", "CreateSubscription", "ModifySubscription", "DeleteSubscriptions",
                     "TransferSubscriptions", "CreateMonitoredItems", "ModifyMonitoredItems",
                     "DeleteMonitoredItems", "SetMonitoringMode", "SetPublishingMode", "Publish", "Republish",
                     "CloseSession", "CloseSecureChannel", "GetEndpoints", "FindServers", "HistoryRead")
#: What a logged-in user may do besides: call methods (each method checks the user's roles).
CALL_SERVICES = _ids("Call")


class ServiceRules(PermissionRuleset):
    """Anonymous: read services only; users: read services and Call; nobody: Write, node or
    reference management. Records the request's user in :data:`CURRENT_USER`."""

    def check_validity(self, user: Any, action_type_id: ua.NodeId, body: Any) -> bool:
        is_user = isinstance(user, DrivesUser) and user.role == UserRole.User and bool(user.roles)
        CURRENT_USER.set(user if is_user else None)
        if action_type_id in READ_SERVICES:
            return True
        return is_user and action_type_id in CALL_SERVICES


def guard_channels(policies: Any, ca: x509.Certificate) -> int:
    """Make every secure policy factory of a started asyncua server refuse, at OpenSecureChannel,
    a client application certificate not issued by ``ca`` (BadCertificateUntrusted). Channels
    without security carry no certificate that is used, so they stay open to anonymous readers.
    Returns how many factories were guarded."""
    guarded = 0
    for factory in policies:
        if factory.cls is SecurityPolicyNone:
            continue
        create = factory.create

        def checked(peer_certificate: bytes | None, create: Any = create) -> Any:
            problem = "no client certificate" if not peer_certificate else ""
            if peer_certificate:
                try:
                    problem = issued_by_ca(x509.load_der_x509_certificate(peer_certificate), ca)
                except ValueError as exc:
                    problem = f"not a certificate: {exc}"
            if problem:
                log.warning("opcua: secure channel refused: client certificate %s", problem)
                raise ServiceError(ua.StatusCodes.BadCertificateUntrusted)
            return create(peer_certificate)

        factory.create = checked
        guarded += 1
    return guarded
