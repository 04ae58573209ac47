"""The composed owners and their parts (docs/architecture.md, "Parts, and the data between them"):
a part never imports its owner, and no part reads another object's private state. The general
rules (no mixins, <= 40 attributes, <= 600 lines, no circles) are test_structure.py's."""

from __future__ import annotations

import ast

import pytest

from tests.contract.structure import ROOT, Report, check_sources, read_tree

#: owner module -> its parts (the tables of docs/agent-cycle.md, agent-gateway.md, supervisor.md);
#: the cycle's parts are every other module of its package
OWNERS = {
    "bus_agent.cycle.cycle": None,
    "bus_agent.gateway.gateway": ("settings", "handoff", "commands", "publisher", "peers", "hostclaim", "recording",
                                  "requests", "leases"),
    "supervisor.fleet": ("link", "view", "commands", "leases", "events", "orchestration", "motion", "selectors",
                         "results"),
}
#: pysoem's register access and os._exit are named with an underscore but are public API
FOREIGN_PRIVATE = {"_fprd", "_fpwr", "_exit"}
PRIVATE_READ_PACKAGES = ("bus_agent/cycle", "bus_agent/gateway", "supervisor", "bus_agent/bus", "bus_agent/motion")


@pytest.fixture(scope="module")
def report() -> Report:
    return check_sources(read_tree())


def _parts(owner: str, report: Report) -> list[str]:
    package = owner.rpartition(".")[0]
    parts = OWNERS[owner]
    if parts is None:
        return sorted(m for m in report.imports if m.rpartition(".")[0] == package and m != owner)
    return [f"{package}.{p}" for p in parts]


def private_reads(tree: ast.AST) -> list[str]:
    """``x._name`` where ``x`` is not ``self``/``cls`` (a plain name, or an attribute such as
    ``self.part``): another object's private state."""
    return [f"{ast.unparse(n)} (line {n.lineno})" for n in ast.walk(tree)
            if isinstance(n, ast.Attribute) and n.attr.startswith("_") and not n.attr.startswith("__")
            and n.attr not in FOREIGN_PRIVATE
            and (isinstance(n.value, ast.Attribute)
                 or isinstance(n.value, ast.Name) and n.value.id not in ("self", "cls"))]


@pytest.mark.parametrize("owner", sorted(OWNERS))
def test_no_part_imports_its_owner(owner: str, report: Report) -> None:
    parts = _parts(owner, report)
    assert parts and all(p in report.imports for p in parts), parts  # a renamed part fails here
    assert [p for p in parts if owner in report.imports[p]] == []


@pytest.mark.parametrize("package", PRIVATE_READ_PACKAGES)
def test_no_part_reads_another_objects_private_state(package: str) -> None:
    found = {str(p.relative_to(ROOT)): private_reads(ast.parse(p.read_text(), str(p)))
             for p in sorted((ROOT / package).glob("*.py"))}
    assert {k: v for k, v in found.items() if v} == {}


def test_the_rules_can_fail() -> None:
    assert private_reads(ast.parse("def f(part):\n    return part._state\n")) == ["part._state (line 2)"]
    assert private_reads(ast.parse("def f(self):\n    return self.part._state\n")) == ["self.part._state (line 2)"]
    assert private_reads(ast.parse("def f(self):\n    return self._state, s._fprd\n")) == []
    # a relative import of the owner counts (supervisor's modules import each other relatively)
    r = check_sources({"supervisor/fleet.py": "", "supervisor/view.py": "from .fleet import Fleet\n"})
    assert "supervisor.fleet" in r.imports["supervisor.view"]
