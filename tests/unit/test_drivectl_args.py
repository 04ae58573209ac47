"""drivectl's command line without a network: global options anywhere, typed endpoints, errors."""

from __future__ import annotations

import json

import pytest

from supervisor import cli
from supervisor.cli.common import merge_globals


def parse(*argv: str):
    return merge_globals(cli.build_parser().parse_args(list(argv)))


@pytest.mark.parametrize("argv", [
    ("--json", "--timeout", "2", "-c", "tcp/127.0.0.1:1", "status"),
    ("status", "--json", "--timeout", "2", "-c", "tcp/127.0.0.1:1"),
    ("--json", "status", "--timeout", "2", "--connect", "tcp/127.0.0.1:1"),
])
def test_global_options_before_or_after_the_verb(argv: tuple[str, ...]) -> None:
    a = parse(*argv)
    assert a.verb == "status" and a.json is True and a.timeout == 2.0 and a.connect == ["tcp/127.0.0.1:1"]


def test_repeated_options_on_both_sides_accumulate() -> None:
    a = parse("-c", "tcp/10.0.0.1:7447", "-v", "enable", "h1/*", "-c", "tcp/10.0.0.2:7447", "-v")
    assert a.connect == ["tcp/10.0.0.1:7447", "tcp/10.0.0.2:7447"] and a.verbose == 2
    assert a.selectors == ["h1/*"]


def test_defaults_without_options() -> None:
    a = parse("status")
    assert (a.json, a.timeout, a.connect, a.verbose) == (False, 5.0, None, 0)


@pytest.mark.parametrize("ep", ["foo", "tcp/", "tcp/host", "tcp/host:0", "tcp/host:99999", "carrier/x:1"])
def test_malformed_endpoint_is_a_usage_error(ep: str, capsys: pytest.CaptureFixture[str]) -> None:
    assert cli.main(["--connect", ep, "status"]) == cli.EXIT_USAGE
    assert "endpoint" in capsys.readouterr().err


def test_usage_errors_are_json_in_json_mode(capsys: pytest.CaptureFixture[str]) -> None:
    assert cli.main(["frobnicate", "--json"]) == cli.EXIT_USAGE
    body = json.loads(capsys.readouterr().out)
    assert body["ok"] is False and body["error"] == "usage" and "frobnicate" in body["message"]
