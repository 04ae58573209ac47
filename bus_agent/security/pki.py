"""A small certificate authority for the drive network (the ``cryptography`` library).

Layout of a PKI directory (``drives-pki init DIR``)::

    DIR/ca.pem  DIR/ca.key                 the CA (key 0600; keep it off the plant network)
    DIR/<name>.pem  DIR/<name>.key         one certificate and key (0600) per principal
    DIR/principals.toml                    names and roles (bus_agent.security.principals)
    DIR/ca.crl                             revoked serials, signed by the CA (for OPC UA peers)

Certificates: ECDSA P-256, CN = the principal's name (zenoh's ACL matches the first CN of the
peer's leaf certificate), key usage digitalSignature, extended key usage serverAuth and
clientAuth (routers and agents both listen and connect). subjectAltName holds the names and
addresses clients dial (``verify_name_on_connect``): ``localhost`` and ``127.0.0.1`` by default,
plus ``--san``. A node needs ca.pem, its own pem/key and principals.toml, never ca.key.

OPC UA (``issue(..., opcua=True)``, ``drives-pki issue --opcua``): the application and user
certificates of drives-opcua and its clients. OPC UA's Basic256Sha256 needs RSA, so these hold
an RSA 2048 key, the key usages OPC UA asks for (digitalSignature, nonRepudiation,
keyEncipherment, dataEncipherment) and the application URI ``urn:zenoh-drives:<name>``
(:func:`opcua_uri`) as a subjectAltName URI. They serve for Zenoh's TLS as well (the drives-opcua
server's principal uses one certificate for both).
"""

from __future__ import annotations

import datetime as dt
import ipaddress
import os
from dataclasses import dataclass
from pathlib import Path
from typing import Iterable, Sequence

from cryptography import x509
from cryptography.hazmat.primitives import hashes, serialization
from cryptography.hazmat.primitives.asymmetric import ec, rsa
from cryptography.x509.oid import ExtendedKeyUsageOID, NameOID

from bus_agent.security import principals as pfile
from bus_agent.security.roles import check_roles

CA_CERT, CA_KEY = "ca.pem", "ca.key"
DEFAULT_CA_DAYS = 3650
DEFAULT_DAYS = 365
#: subjectAltNames every certificate holds, so a loopback set-up needs no options.
DEFAULT_SANS = ("localhost", "127.0.0.1")
#: Back-dating of notBefore: clocks of the nodes may disagree a little.
CLOCK_SKEW = dt.timedelta(minutes=5)


class PkiError(RuntimeError):
    """A PKI operation that cannot be done (missing CA, existing name, bad SAN)."""


@dataclass(frozen=True)
class Paths:
    """Where a principal's files are."""

    cert: Path
    key: Path
    ca: Path


def paths(pki_dir: str | Path, name: str) -> Paths:
    d = Path(pki_dir)
    return Paths(d / f"{name}.pem", d / f"{name}.key", d / CA_CERT)


def opcua_uri(name: str) -> str:
    """The OPC UA application URI of an ``--opcua`` certificate of ``name`` (its SAN URI)."""
    return f"urn:zenoh-drives:{name}"


def _write_key(path: Path, key: ec.EllipticCurvePrivateKey | rsa.RSAPrivateKey) -> None:
    data = key.private_bytes(serialization.Encoding.PEM, serialization.PrivateFormat.PKCS8,
                             serialization.NoEncryption())
    # Created 0600 from the start: never readable by others, not even for an instant.
    fd = os.open(path, os.O_WRONLY | os.O_CREAT | os.O_EXCL, 0o600)
    with os.fdopen(fd, "wb") as f:
        f.write(data)


def _write_cert(path: Path, cert: x509.Certificate) -> None:
    path.write_bytes(cert.public_bytes(serialization.Encoding.PEM))


def _now() -> dt.datetime:
    return dt.datetime.now(dt.timezone.utc)


def init(pki_dir: str | Path, name: str = "zenoh-drives CA", days: int = DEFAULT_CA_DAYS) -> Path:
    """Create the CA in ``pki_dir`` (made 0700 if new) and an empty principals.toml.
    Refuses to overwrite an existing CA. Returns the CA certificate path."""
    d = Path(pki_dir)
    if (d / CA_KEY).exists() or (d / CA_CERT).exists():
        raise PkiError(f"{d} already holds a CA ({CA_CERT}/{CA_KEY}); use another directory")
    d.mkdir(mode=0o700, parents=True, exist_ok=True)
    key = ec.generate_private_key(ec.SECP256R1())
    subject = x509.Name([x509.NameAttribute(NameOID.COMMON_NAME, name)])
    now = _now()
    cert = (x509.CertificateBuilder().subject_name(subject).issuer_name(subject).public_key(key.public_key())
            .serial_number(x509.random_serial_number())
            .not_valid_before(now - CLOCK_SKEW).not_valid_after(now + dt.timedelta(days=days))
            .add_extension(x509.BasicConstraints(ca=True, path_length=0), critical=True)
            .add_extension(x509.KeyUsage(digital_signature=False, content_commitment=False, key_encipherment=False,
                                         data_encipherment=False, key_agreement=False, key_cert_sign=True,
                                         crl_sign=True, encipher_only=False, decipher_only=False), critical=True)
            .add_extension(x509.SubjectKeyIdentifier.from_public_key(key.public_key()), critical=False)
            .sign(key, hashes.SHA256()))
    _write_key(d / CA_KEY, key)
    _write_cert(d / CA_CERT, cert)
    if not (d / pfile.FILE_NAME).exists():
        pfile.save(d, [])
    write_crl(d)
    return d / CA_CERT


#: The CA's certificate revocation list (PEM), rewritten by init and revoke: OPC UA clients and
#: servers (node-opcua, UaExpert) want one for every issuer they trust.
CA_CRL = "ca.crl"
CRL_DAYS = 365


def write_crl(pki_dir: str | Path) -> Path:
    """Write ``DIR/ca.crl``: the serials of every revoked principal, signed by the CA, valid
    :data:`CRL_DAYS` (``drives-pki crl DIR`` renews it)."""
    d = Path(pki_dir)
    ca_cert, ca_key = _load_ca(d)
    now = _now()
    builder = (x509.CertificateRevocationListBuilder().issuer_name(ca_cert.subject)
               .last_update(now - CLOCK_SKEW).next_update(now + dt.timedelta(days=CRL_DAYS)))
    for r in pfile.load_all(d)[1].values() if (d / pfile.FILE_NAME).exists() else ():
        if r.serial:
            builder = builder.add_revoked_certificate(
                x509.RevokedCertificateBuilder().serial_number(int(r.serial, 16)).revocation_date(now).build())
    crl = builder.sign(ca_key, hashes.SHA256())
    (d / CA_CRL).write_bytes(crl.public_bytes(serialization.Encoding.PEM))
    return d / CA_CRL


def _san(text: str) -> x509.GeneralName:
    try:
        return x509.IPAddress(ipaddress.ip_address(text))
    except ValueError:
        pass
    labels = text.split(".")
    if not text or len(text) > 253 or not all(
            label and len(label) <= 63 and label.replace("-", "").isalnum() and label.isascii()
            for label in labels):
        raise PkiError(f"--san {text!r} is neither an IP address nor a DNS name")
    return x509.DNSName(text)


def _load_ca(d: Path) -> tuple[x509.Certificate, ec.EllipticCurvePrivateKey]:
    try:
        cert = x509.load_pem_x509_certificate((d / CA_CERT).read_bytes())
        key = serialization.load_pem_private_key((d / CA_KEY).read_bytes(), password=None)
    except FileNotFoundError:
        raise PkiError(f"{d} holds no CA: create it with `drives-pki init {d}`") from None
    if not isinstance(key, ec.EllipticCurvePrivateKey):
        raise PkiError(f"{d / CA_KEY}: not an EC key")
    return cert, key


def issue(pki_dir: str | Path, name: str, roles: Sequence[str], *, days: int = DEFAULT_DAYS,
          sans: Iterable[str] = (), hosts: Sequence[str] = (), valid_from: dt.datetime | None = None,
          replace: bool = False, opcua: bool = False) -> pfile.Principal:
    """Issue ``name``'s certificate and key, signed by the CA of ``pki_dir``, and record it in
    principals.toml. ``sans`` are added to :data:`DEFAULT_SANS`. ``hosts`` limits its commands
    to those hosts (the ACL's rules name them; empty: every host). ``valid_from`` (tests: an
    expired certificate) defaults to now. ``replace`` re-issues an existing name (new key; the
    old certificate stays valid until it expires: to shut a key out, :func:`revoke` it).
    ``opcua``: an RSA certificate fit for OPC UA (see the module docstring).
    Raises :class:`PkiError` (nothing is written then), also for a revoked name."""
    d = Path(pki_dir)
    try:
        p = pfile.Principal(name, tuple(roles), hosts=tuple(hosts))
        check_roles(p.roles)
    except (pfile.PrincipalsError, ValueError) as exc:
        raise PkiError(str(exc)) from None
    if name in ("ca", "principals"):
        raise PkiError(f"name {name!r} is reserved (its files would clash with the CA's)")
    if not 1 <= days <= 36500:
        raise PkiError(f"--days {days} must be 1..36500")
    ca_cert, ca_key = _load_ca(d)
    known, revoked = pfile.load_all(d)
    if name in revoked:
        raise PkiError(f"{name!r} was revoked ({revoked[name].revoked_at}) and cannot be issued again: zenoh's ACL "
                       "knows a peer by its certificate's common name only, so the revoked certificate would be "
                       "let in again; choose a new name")
    files = paths(d, name)
    if (name in known or files.key.exists() or files.cert.exists()) and not replace:
        raise PkiError(f"{name!r} already exists in {d}: renew it with --replace (a new key), or revoke it "
                       "(`drives-pki revoke`) and issue under a new name")
    san_list = list(dict.fromkeys([*DEFAULT_SANS, *sans]))
    general = [_san(s) for s in san_list]
    start = valid_from or _now()
    if opcua:
        general.append(x509.UniformResourceIdentifier(opcua_uri(name)))
    key: ec.EllipticCurvePrivateKey | rsa.RSAPrivateKey = (
        rsa.generate_private_key(public_exponent=65537, key_size=2048) if opcua else ec.generate_private_key(ec.SECP256R1()))
    cert = (x509.CertificateBuilder()
            .subject_name(x509.Name([x509.NameAttribute(NameOID.COMMON_NAME, name)]))
            .issuer_name(ca_cert.subject).public_key(key.public_key())
            .serial_number(x509.random_serial_number())
            .not_valid_before(start - CLOCK_SKEW).not_valid_after(start + dt.timedelta(days=days))
            .add_extension(x509.BasicConstraints(ca=False, path_length=None), critical=True)
            .add_extension(x509.KeyUsage(digital_signature=True, content_commitment=opcua, key_encipherment=opcua,
                                         data_encipherment=opcua, key_agreement=False, key_cert_sign=False,
                                         crl_sign=False, encipher_only=False, decipher_only=False), critical=True)
            .add_extension(x509.ExtendedKeyUsage([ExtendedKeyUsageOID.SERVER_AUTH, ExtendedKeyUsageOID.CLIENT_AUTH]),
                           critical=False)
            .add_extension(x509.SubjectAlternativeName(general), critical=False)
            .add_extension(x509.AuthorityKeyIdentifier.from_issuer_public_key(ca_key.public_key()), critical=False)
            .sign(ca_key, hashes.SHA256()))
    for f in (files.key, files.cert):
        if f.exists():
            f.unlink()
    _write_key(files.key, key)
    _write_cert(files.cert, cert)
    principal = pfile.Principal(name, p.roles, format(cert.serial_number, "x"),
                                _stamp(cert.not_valid_after_utc), tuple(san_list), p.hosts)
    known[name] = principal
    pfile.save(d, known.values(), revoked.values())
    return principal


def _stamp(t: dt.datetime) -> str:
    return t.strftime("%Y-%m-%dT%H:%M:%SZ")


def revoke(pki_dir: str | Path, name: str) -> pfile.Revoked:
    """Revoke ``name``: move it from the principals to the revoked names of principals.toml
    (routers compile an explicit deny of its common name; the name cannot be issued again) and
    delete its key and certificate here. Routers admit it until they restart with the new file
    (the ACL is static); its certificate keeps passing TLS (zenoh 1.10 has no revocation list),
    and the ACL denies every message from and to it."""
    d = Path(pki_dir)
    known, revoked = pfile.load_all(d)
    if name in revoked:
        raise PkiError(f"{name!r} is already revoked ({revoked[name].revoked_at})")
    if name not in known:
        raise PkiError(f"{name!r} is not a principal of {d} (see `drives-pki list {d}`)")
    entry = pfile.Revoked(name, known.pop(name).serial, _stamp(_now()))
    revoked[name] = entry
    pfile.save(d, known.values(), revoked.values())
    write_crl(d)
    files = paths(d, name)
    for f in (files.key, files.cert):
        if f.exists():
            f.unlink()
    return entry


#: ``drives-pki remove`` is ``revoke``: removing a name without revoking it would let its
#: certificate back in as soon as the name is issued again.
remove = revoke


@dataclass(frozen=True)
class CertInfo:
    """A principal as listed: roles from principals.toml, facts from its certificate."""

    principal: pfile.Principal
    cert_present: bool
    not_after: dt.datetime | None
    expired: bool
    key_mode: int | None  # permission bits of the key file, None if absent


def inspect(pki_dir: str | Path) -> list[CertInfo]:
    """Every principal of ``pki_dir`` with what its files say."""
    d = Path(pki_dir)
    now = _now()
    out = []
    for name, p in sorted(pfile.load(d).items()):
        files = paths(d, name)
        not_after = None
        if files.cert.exists():
            not_after = x509.load_pem_x509_certificate(files.cert.read_bytes()).not_valid_after_utc
        mode = files.key.stat().st_mode & 0o777 if files.key.exists() else None
        out.append(CertInfo(p, files.cert.exists(), not_after, bool(not_after and not_after <= now), mode))
    return out


def check_identity(pki_dir: str | Path, name: str) -> Paths:
    """The files a session of ``name`` needs, checked before zenoh sees them (zenoh's own
    errors on a bad TLS file are late and vague). Raises :class:`PkiError`."""
    files = paths(pki_dir, name)
    for f, what in ((files.ca, "CA certificate"), (files.cert, f"certificate of {name!r}"),
                    (files.key, f"key of {name!r}")):
        if not f.is_file():
            raise PkiError(f"{what} {f} missing (issue it with `drives-pki issue {pki_dir} {name} --role ROLE`)")
    try:
        cert = x509.load_pem_x509_certificate(files.cert.read_bytes())
    except ValueError as exc:
        raise PkiError(f"{files.cert}: not a PEM certificate: {exc}") from None
    now = _now()
    if cert.not_valid_after_utc <= now:
        raise PkiError(f"certificate {files.cert} of {name!r} expired on {cert.not_valid_after_utc:%Y-%m-%d %H:%M}Z: "
                       "re-issue it (`drives-pki issue --replace`)")
    cn = cert.subject.get_attributes_for_oid(NameOID.COMMON_NAME)
    if not cn or cn[0].value != name:
        raise PkiError(f"certificate {files.cert} is for {cn[0].value if cn else 'no CN'!r}, not {name!r}")
    mode = files.key.stat().st_mode & 0o077
    if mode:
        raise PkiError(f"key {files.key} is readable by others (mode {files.key.stat().st_mode & 0o777:o}): "
                       f"chmod 600 {files.key}")
    return files
