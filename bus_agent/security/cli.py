"""``drives-pki``: the drive network's certificate authority in three commands.

    drives-pki init DIR                                  # DIR/ca.pem, DIR/ca.key (0600), principals.toml
    drives-pki issue DIR NAME --role ROLE [--role ROLE] [--hosts H1,H2] [--days N] [--san NAME|IP]... [--replace]
    drives-pki list DIR [--json]
    drives-pki revoke DIR NAME                           # (or remove): denied by every router after its restart
    drives-pki user DIR NAME --role ROLE [--password-stdin]   # an OPC UA user (drives-opcua), password hashed
    drives-pki crl DIR                                   # rewrite DIR/ca.crl (also done by init and revoke)

Roles: router, agent (NAME = its host name), operator, maintenance, viewer, testbed (see
``bus_agent.security.roles.ROLES``). Certificates hold ``localhost`` and ``127.0.0.1`` as
subjectAltNames; ``--san`` adds the names and addresses clients dial (a router's). Routers
compile their ACL from DIR/principals.toml at start: restart them after issue or revoke.
``--hosts`` limits an operator's or maintainer's commands to those hosts (default: every host).
``--opcua`` issues an RSA certificate fit for OPC UA (drives-opcua's server, its clients' application
certificates, user certificates; ``bus_agent.security.pki``). ``user`` keeps a name, roles (viewer,
operator, maintenance) and a salted scrypt hash of the password in DIR/users.toml; the password is
asked twice on a terminal, or read as one line from stdin with ``--password-stdin``.

Exit codes: 0 done; 2 bad arguments or a refused operation (nothing written).
"""

from __future__ import annotations

import argparse
import getpass
import json
import sys
from typing import Any, Sequence

from bus_agent.security import pki, users
from bus_agent.security.principals import PrincipalsError, load_all
from bus_agent.security.roles import ROLES, allowed_ops
from bus_agent.security.users import USER_ROLES

EXIT_OK, EXIT_USAGE = 0, 2


def build_parser() -> argparse.ArgumentParser:
    p = argparse.ArgumentParser(prog="drives-pki", description="Certificates and roles for a secure drive network "
                                "(mutual TLS, ACL compiled from roles).")
    sub = p.add_subparsers(dest="cmd", required=True, metavar="COMMAND")
    i = sub.add_parser("init", help="create the CA in DIR")
    i.add_argument("dir", metavar="DIR")
    i.add_argument("--days", type=int, default=pki.DEFAULT_CA_DAYS, help="CA validity (default %(default)s)")
    i.add_argument("--name", default="zenoh-drives CA", help="the CA's common name")
    s = sub.add_parser("issue", help="issue NAME's certificate and key, recorded in DIR/principals.toml")
    s.add_argument("dir", metavar="DIR")
    s.add_argument("name", metavar="NAME", help="principal: the certificate's CN (an agent's host name)")
    s.add_argument("--role", action="append", required=True, choices=sorted(ROLES),
                   help="role (repeatable): " + "; ".join(f"{k}: {v}" for k, v in ROLES.items()))
    s.add_argument("--days", type=int, default=pki.DEFAULT_DAYS, help="validity (default %(default)s)")
    s.add_argument("--san", action="append", default=[], metavar="NAME|IP",
                   help="a name or address clients dial, added to localhost and 127.0.0.1 (repeatable)")
    s.add_argument("--hosts", type=_hosts, default=(), metavar="H1,H2",
                   help="commands to these hosts only (operator, maintenance; default: every host)")
    s.add_argument("--replace", action="store_true",
                   help="re-issue an existing principal (new key; the old certificate stays valid: revoke a leaked one)")
    s.add_argument("--opcua", action="store_true",
                   help="an RSA certificate with OPC UA's key usages and URI urn:zenoh-drives:NAME (drives-opcua)")
    c = sub.add_parser("crl", help="rewrite DIR/ca.crl (revoked serials, signed by the CA; valid a year)")
    c.add_argument("dir", metavar="DIR")
    u = sub.add_parser("user", help="add or change an OPC UA user (drives-opcua): roles and a hashed password")
    u.add_argument("dir", metavar="DIR")
    u.add_argument("name", metavar="NAME")
    u.add_argument("--role", action="append", required=True, choices=USER_ROLES,
                   help="role (repeatable): viewer reads; operator enables and moves; maintenance resets faults")
    u.add_argument("--password-stdin", action="store_true", help="read the password as one line from stdin")
    ls = sub.add_parser("list", help="the principals of DIR")
    ls.add_argument("dir", metavar="DIR")
    ls.add_argument("--json", action="store_true")
    for verb in ("revoke", "remove"):
        r = sub.add_parser(verb, help="revoke NAME: routers deny it after their restart, the name is never "
                           "issued again, its files here are deleted" + (" (same as revoke)" if verb == "remove" else ""))
        r.add_argument("dir", metavar="DIR")
        r.add_argument("name", metavar="NAME")
    return p


def _hosts(text: str) -> tuple[str, ...]:
    hosts = tuple(h.strip() for h in text.split(","))
    if not all(hosts):
        raise argparse.ArgumentTypeError(f"{text!r}: expected host names separated by commas, e.g. h1,h2")
    return hosts


def _password(from_stdin: bool) -> str:
    """The new password: one line of stdin, or asked twice without echo on a terminal."""
    if from_stdin:
        return sys.stdin.readline().rstrip("\r\n")
    if not sys.stdin.isatty():
        raise users.UsersError("no terminal to ask the password on: give --password-stdin and pipe it in")
    first = getpass.getpass("password: ")
    if getpass.getpass("again: ") != first:
        raise users.UsersError("the two passwords differ; nothing written")
    return first


def _list(d: str, as_json: bool) -> int:
    infos = pki.inspect(d)
    rows: list[dict[str, Any]] = [{"name": c.principal.name, "roles": list(c.principal.roles),
             "ops": list(allowed_ops(c.principal.roles)),
             "not_after": c.not_after.strftime("%Y-%m-%dT%H:%M:%SZ") if c.not_after else None,
             "expired": c.expired, "cert": c.cert_present,
             "key_mode": None if c.key_mode is None else f"{c.key_mode:o}", "sans": list(c.principal.sans),
             "hosts": list(c.principal.hosts) or "all"}
            for c in infos]
    revoked = [{"name": r.name, "serial": r.serial, "revoked_at": r.revoked_at}
               for r in sorted(load_all(d)[1].values(), key=lambda r: r.name)]
    if as_json:
        print(json.dumps({"principals": rows, "revoked": revoked}, indent=1))
        return EXIT_OK
    print(f"{'name':<20} {'roles':<22} {'hosts':<12} {'not after':<21} {'key':<5} sans")
    for row in rows:
        status = "EXPIRED" if row["expired"] else (row["not_after"] or "no certificate")
        hosts = row["hosts"] if isinstance(row["hosts"], str) else ",".join(row["hosts"])
        print(f"{row['name']:<20} {','.join(row['roles']):<22} {hosts:<12} {status:<21} {row['key_mode'] or '-':<5} "
              f"{','.join(row['sans'])}")
    for r in revoked:
        print(f"{r['name']:<20} REVOKED {r['revoked_at']} (serial {r['serial']})")
    return EXIT_OK


def main(argv: Sequence[str] | None = None) -> int:
    args = build_parser().parse_args(argv)
    try:
        if args.cmd == "init":
            path = pki.init(args.dir, name=args.name, days=args.days)
            print(f"drives-pki: CA created: {path} (key {args.dir}/{pki.CA_KEY}, mode 600: keep it off the "
                  "plant network)")
        elif args.cmd == "issue":
            p = pki.issue(args.dir, args.name, args.role, days=args.days, sans=args.san, hosts=args.hosts,
                          replace=args.replace, opcua=args.opcua)
            files = pki.paths(args.dir, p.name)
            print(f"drives-pki: issued {p.name} ({', '.join(p.roles)}; commands to "
                  f"{', '.join(p.hosts) or 'every host'}) until {p.not_after}: {files.cert}, {files.key}; "
                  f"sans {', '.join(p.sans)}. Restart the routers to load the new principals.toml.")
        elif args.cmd == "user":
            user = users.set_user(args.dir, args.name, args.role, _password(args.password_stdin))
            print(f"drives-pki: user {user.name} ({', '.join(user.roles)}) written to {args.dir}/{users.FILE_NAME}; "
                  "drives-opcua reads it at start")
        elif args.cmd == "crl":
            print(f"drives-pki: wrote {pki.write_crl(args.dir)}")
        elif args.cmd == "list":
            return _list(args.dir, args.json)
        elif args.cmd in ("revoke", "remove"):
            r = pki.revoke(args.dir, args.name)
            print(f"drives-pki: revoked {r.name} (serial {r.serial}). Copy principals.toml to every router and restart "
                  "them: until then they still admit it.")
    except (pki.PkiError, PrincipalsError, users.UsersError, OSError) as exc:
        print(f"drives-pki: {exc}", file=sys.stderr)
        return EXIT_USAGE
    return EXIT_OK


if __name__ == "__main__":
    sys.exit(main())
