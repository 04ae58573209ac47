"""``python -m schemas``: jsonschema, keys, markdown."""

from __future__ import annotations

import json
import subprocess
import sys

import pytest

from schemas import __main__ as cli
from schemas import jsonschema as js
from schemas import keys, markdown


def test_jsonschema_prints_all(capsys):
    assert cli.main(["jsonschema"]) == 0
    assert json.loads(capsys.readouterr().out) == js.all_schemas()


def test_jsonschema_out_writes_one_file_per_message(tmp_path, capsys):
    assert cli.main(["jsonschema", "--out", str(tmp_path)]) == 0
    assert sorted(p.name for p in tmp_path.iterdir()) == sorted(f"{t}.schema.json" for t in js.all_schemas())


def test_keys_prints_the_table(capsys):
    assert cli.main(["keys"]) == 0
    out = capsys.readouterr().out
    for k in keys.KEY_TABLE:
        assert k.pattern in out


def test_markdown_print_check_and_write(tmp_path, capsys):
    assert cli.main(["markdown"]) == 0
    assert capsys.readouterr().out == markdown.render_contract_markdown()
    p = tmp_path / "c.md"
    assert cli.main(["markdown", "--check", "--path", str(p)]) == 1
    p.write_text(f"{markdown.BEGIN}\nstale\n{markdown.END}\n")
    assert cli.main(["markdown", "--check", "--path", str(p)]) == 1
    assert "stale" in capsys.readouterr().err
    assert cli.main(["markdown", "--write", "--path", str(p)]) == 0
    assert cli.main(["markdown", "--check", "--path", str(p)]) == 0


def test_usage_errors_exit_2():
    with pytest.raises(SystemExit) as exc:
        cli.main([])
    assert exc.value.code == 2


def test_module_entry_point_runs():
    r = subprocess.run([sys.executable, "-m", "schemas", "keys"], capture_output=True, text=True,
                       timeout=60, cwd=markdown.REPO_ROOT)
    assert r.returncode == 0 and "drives/@v1/<host>/agent" in r.stdout
