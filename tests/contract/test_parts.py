"""The composed owners and their parts (docs/architecture.md, "Parts, and the data between them"):
a part never imports its owner, and no part reads another object's private state. The general
rules (no mixins, <= 40 attributes, <= 600 lines, no circles) are test_structure.py's."""

from __future__ import annotations

import ast
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[2]
#: owner module -> the package of its parts
OWNERS = {"bus_agent.cycle.cycle": "bus_agent/cycle", "bus_agent.gateway.gateway": "bus_agent/gateway",
          "supervisor.fleet": "supervisor"}
#: pysoem's register access and os._exit are named with an underscore but are public API
FOREIGN_PRIVATE = {"_fprd", "_fpwr", "_exit"}


def _modules(package: str) -> list[Path]:
    return sorted((ROOT / package).glob("*.py"))


def _module_imports(tree: ast.Module) -> set[str]:
    """Module-level imports (not inside functions, not under ``if TYPE_CHECKING``)."""
    out: set[str] = set()
    for n in tree.body:
        if isinstance(n, ast.ImportFrom) and n.module:
            out.add(n.module)
            out.update(f"{n.module}.{a.name}" for a in n.names)
        elif isinstance(n, ast.Import):
            out.update(a.name for a in n.names)
    return out


def private_reads(tree: ast.AST) -> list[str]:
    """``x._name`` where ``x`` is a plain name other than self/cls (another object's private state)."""
    return [f"{n.value.id}.{n.attr} (line {n.lineno})" for n in ast.walk(tree)
            if isinstance(n, ast.Attribute) and isinstance(n.value, ast.Name)
            and n.attr.startswith("_") and not n.attr.startswith("__")
            and n.value.id not in ("self", "cls") and n.attr not in FOREIGN_PRIVATE]


@pytest.mark.parametrize("owner,package", sorted(OWNERS.items()))
def test_no_part_imports_its_owner(owner: str, package: str) -> None:
    for path in _modules(package):
        if path.stem == owner.rsplit(".", 1)[1]:
            continue
        imports = _module_imports(ast.parse(path.read_text(), str(path)))
        assert owner not in imports, f"{path.relative_to(ROOT)} imports its owner {owner}"


@pytest.mark.parametrize("package", sorted(set(OWNERS.values()) | {"bus_agent/bus", "bus_agent/motion"}))
def test_no_part_reads_another_objects_private_state(package: str) -> None:
    found = {str(p.relative_to(ROOT)): private_reads(ast.parse(p.read_text(), str(p))) for p in _modules(package)}
    assert {k: v for k, v in found.items() if v} == {}


def test_the_private_read_rule_can_fail() -> None:
    assert private_reads(ast.parse("def f(part):\n    return part._state\n")) == ["part._state (line 2)"]
    assert private_reads(ast.parse("def f(self):\n    return self._state, s._fprd\n")) == []
