"""``python -m schemas``: export the contract.

Subcommands:
  jsonschema [--out DIR]      JSON Schema of every message (one file each into DIR, or print)
  keys                        the key table
  markdown [--write|--check]  the generated contract section (print, refresh docs/contract.md,
                              or exit 1 if docs/contract.md is stale)
Exit codes: 0 ok, 1 stale (--check), 2 usage.
"""

from __future__ import annotations

import argparse
import json
import sys

from . import jsonschema, keys, markdown


def _cmd_jsonschema(args: argparse.Namespace) -> int:
    if args.out:
        for path in jsonschema.write_schemas(args.out):
            print(path)
    else:
        print(json.dumps(jsonschema.all_schemas(), indent=2))
    return 0


def _cmd_keys(args: argparse.Namespace) -> int:
    rows = [(k.pattern, k.kind, k.zenoh, k.message or "-", k.meaning) for k in keys.KEY_TABLE]
    head = ("KEY", "KIND", "ZENOH", "PAYLOAD", "MEANING")
    widths = [max(len(r[i]) for r in rows + [head]) for i in range(4)]
    for r in [head] + rows:
        print("  ".join(c.ljust(w) for c, w in zip(r[:4], widths)) + "  " + r[4])
    return 0


def _cmd_markdown(args: argparse.Namespace) -> int:
    if args.write:
        print(markdown.write_contract(args.path))
        return 0
    if args.check:
        try:
            text = open(args.path, encoding="utf-8").read()
        except OSError as exc:
            print(f"{args.path}: {exc}", file=sys.stderr)
            return 1
        if markdown.extract_section(text) != markdown.render_contract_markdown():
            print(f"{args.path} is stale: run `python -m schemas markdown --write`", file=sys.stderr)
            return 1
        return 0
    sys.stdout.write(markdown.render_contract_markdown())
    return 0


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(prog="python -m schemas", description="Export the wire contract.")
    sub = parser.add_subparsers(dest="cmd", required=True)
    p = sub.add_parser("jsonschema", help="JSON Schema of every message")
    p.add_argument("--out", metavar="DIR", help="write <type>.schema.json files into DIR instead of printing")
    p.set_defaults(func=_cmd_jsonschema)
    p = sub.add_parser("keys", help="print the key table")
    p.set_defaults(func=_cmd_keys)
    p = sub.add_parser("markdown", help="the generated contract section")
    g = p.add_mutually_exclusive_group()
    g.add_argument("--write", action="store_true", help="refresh the section in docs/contract.md")
    g.add_argument("--check", action="store_true", help="exit 1 if docs/contract.md is stale")
    p.add_argument("--path", default=str(markdown.CONTRACT_MD), help="file to write/check (default docs/contract.md)")
    p.set_defaults(func=_cmd_markdown)
    args = parser.parse_args(argv)
    return args.func(args)


if __name__ == "__main__":
    sys.exit(main())
