"""docs/contract.md and README.md carry the contract markers, and their sections match the generated contract."""

from __future__ import annotations

import dataclasses

import pytest

import schemas
from schemas import keys, markdown
from schemas import messages as m

ROOT = markdown.REPO_ROOT


def test_docs_contract_is_current():
    text = (ROOT / "docs" / "contract.md").read_text(encoding="utf-8")
    section = markdown.extract_section(text)
    assert section is not None, "docs/contract.md lacks the contract markers"
    assert section == schemas.render_contract_markdown(), (
        "docs/contract.md is stale: run `.venv/bin/python -m schemas markdown --write`"
    )


def test_readme_contract_is_current():
    section = markdown.extract_section((ROOT / "README.md").read_text(encoding="utf-8"))
    assert section is not None, (
        "README.md lacks the contract markers: run `.venv/bin/python -m schemas markdown --write --path README.md`"
    )
    assert section == schemas.render_contract_markdown(), (
        "README.md contract section is stale: run `.venv/bin/python -m schemas markdown --write --path README.md`"
    )


def test_generated_text_lists_every_key_message_field_and_arg():
    text = schemas.render_contract_markdown()
    for k in keys.KEY_TABLE:
        assert f"`{k.pattern}`" in text and k.meaning in text
    for cls in m.MESSAGE_TYPES:
        assert f"#### `{cls.TYPE}` ({cls.__name__})" in text
        for f in dataclasses.fields(cls):
            assert f"| `{f.name}` |" in text
    for op, spec in m.OP_ARGS.items():
        for name in spec:
            assert f"| `{op}` | `{name}` |" in text
    assert "| `statusword` | int | required | 0..65535 | 0x6041 |" in text
    assert "`lease_holder` | str | `''` | at most 64 chars; legal name or ''" in text


def test_write_contract_creates_then_replaces_only_the_section(tmp_path):
    p = tmp_path / "contract.md"
    markdown.write_contract(p)
    assert markdown.extract_section(p.read_text()) == markdown.render_contract_markdown()
    p.write_text(f"intro\n{markdown.BEGIN}\nold\n{markdown.END}\noutro\n")
    markdown.write_contract(p)
    text = p.read_text()
    assert text.startswith("intro\n") and text.endswith(f"{markdown.END}\noutro\n")
    assert markdown.extract_section(text) == markdown.render_contract_markdown()


@pytest.mark.parametrize("text", ["no markers", f"{markdown.BEGIN} only"])
def test_extract_section_without_markers(text):
    assert markdown.extract_section(text) is None
