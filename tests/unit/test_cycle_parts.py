"""The cycle is composed of parts (docs/agent-cycle.md, "The parts"): no mixins, no class with
more than 40 attributes, modules of at most 600 lines, no import circle among the cycle's modules."""

from __future__ import annotations

import ast
from pathlib import Path

import bus_agent.cycle

CYCLE_DIR = Path(bus_agent.cycle.__file__).parent
MODULES = sorted(CYCLE_DIR.glob("*.py"))


def _tree(path: Path) -> ast.Module:
    return ast.parse(path.read_text(), str(path))


def _self_attributes(cls: ast.ClassDef) -> set[str]:
    return {n.attr for n in ast.walk(cls) if isinstance(n, ast.Attribute) and isinstance(n.ctx, ast.Store)
            and isinstance(n.value, ast.Name) and n.value.id == "self"}


def _cycle_imports(path: Path) -> set[str]:
    out = set()
    for n in ast.walk(_tree(path)):
        if isinstance(n, ast.ImportFrom) and n.module and n.module.startswith("bus_agent.cycle."):
            out.add(n.module.rsplit(".", 1)[1])
    return out


def test_no_mixin_and_small_classes() -> None:
    for path in MODULES:
        for cls in (n for n in ast.walk(_tree(path)) if isinstance(n, ast.ClassDef)):
            assert not cls.name.endswith("Mixin") and cls.name != "CycleBase", f"{path.name}: {cls.name}"
            own = [b for b in cls.bases if isinstance(b, ast.Name) and b.id[:1].isupper()
                   and b.id not in ("Protocol", "LookupError", "BusError", "Exception")]
            assert len(own) <= 1, f"{path.name}: {cls.name} inherits from {len(own)} classes"
            attrs = _self_attributes(cls)
            assert len(attrs) <= 40, f"{path.name}: {cls.name} has {len(attrs)} attributes"


def test_modules_are_short() -> None:
    for path in MODULES:
        assert len(path.read_text().splitlines()) <= 600, path.name


def test_no_part_imports_the_cycle_and_no_circle() -> None:
    graph = {p.stem: _cycle_imports(p) for p in MODULES}
    assert not any("cycle" in deps for name, deps in graph.items() if name != "cycle")
    done: set[str] = set()

    def visit(name: str, path: tuple[str, ...]) -> None:
        assert name not in path, f"import circle: {' -> '.join(path + (name,))}"
        if name in done:
            return
        for dep in graph.get(name, ()):
            visit(dep, path + (name,))
        done.add(name)

    for name in graph:
        visit(name, ())
