"""The repository's structure rules, checked on its own Python by parsing it (``ast``; nothing is
imported): composition instead of inheritance among the project's classes, small classes and
modules, no import circles, no binary files in git (docs/style.md, "Composition").

Pure functions over source texts (:func:`check_sources`) and a thin shell that reads the tree
(:func:`read_tree`, :func:`tracked_binaries`). ``python -m tests.contract.structure`` prints
every violation, allowlisted or not.
"""

from __future__ import annotations

import ast
import os
import subprocess
from dataclasses import dataclass, field
from pathlib import Path
from typing import Iterable, Mapping

ROOT = Path(__file__).resolve().parents[2]
MAX_ATTRIBUTES = 40
MAX_LINES = 600
#: Directories never walked: virtual environments, node packages, caches, build output.
SKIP_DIRS = frozenset({".venv", "venv", "node_modules", "__pycache__", ".git", "build", "dist", ".mypy_cache",
                       ".pytest_cache", ".hypothesis"})
#: Packages whose imports inside functions count too (a lazy import circle is still a circle).
LAZY_IMPORTS_COUNT_IN = ("bench",)


@dataclass
class Report:
    """Violations by rule; each entry is a short key (module, class or cycle) for allowlists."""

    mixins: list[str] = field(default_factory=list)          # "module.Class"
    multiple_bases: list[str] = field(default_factory=list)  # "module.Class"
    attributes: dict[str, int] = field(default_factory=dict)  # "module.Class" -> distinct self.X stores
    long_modules: dict[str, int] = field(default_factory=dict)  # "path" -> lines
    cycles: list[tuple[str, ...]] = field(default_factory=list)  # sorted module names of one circle
    lazy_cycles: list[tuple[str, ...]] = field(default_factory=list)
    binaries: list[str] = field(default_factory=list)        # tracked paths
    #: not a rule: each module's project imports at import time (relative ones resolved)
    imports: dict[str, set[str]] = field(default_factory=dict)

    def lines(self) -> list[str]:
        out = [f"mixin: {c}" for c in self.mixins]
        out += [f"more than one project base: {c}" for c in self.multiple_bases]
        out += [f"{n} attributes (> {MAX_ATTRIBUTES}): {c}" for c, n in sorted(self.attributes.items())]
        out += [f"{n} lines (> {MAX_LINES}): {p}" for p, n in sorted(self.long_modules.items())]
        out += [f"import circle: {' <-> '.join(c)}" for c in self.cycles]
        out += [f"import circle (imports in functions too): {' <-> '.join(c)}" for c in self.lazy_cycles]
        out += [f"binary file tracked: {p}" for p in self.binaries]
        return out


# ---- the tree (shell) ------------------------------------------------------------------------


def module_name(path: str) -> str:
    """``a/b/c.py`` -> ``a.b.c``; ``a/b/__init__.py`` -> ``a.b``."""
    parts = path[:-3].replace(os.sep, "/").split("/")
    if parts[-1] == "__init__":
        parts = parts[:-1]
    return ".".join(parts)


def read_tree(root: Path = ROOT) -> dict[str, str]:
    """Every ``.py`` file under ``root`` (relative path -> text), skipping :data:`SKIP_DIRS` and
    hidden directories."""
    out: dict[str, str] = {}
    for here, dirs, files in os.walk(root):
        dirs[:] = sorted(d for d in dirs if d not in SKIP_DIRS and not d.startswith(".") and not d.endswith(".egg-info"))
        for f in sorted(files):
            if f.endswith(".py"):
                p = Path(here, f)
                out[str(p.relative_to(root))] = p.read_text(encoding="utf-8")
    return out


def is_binary(data: bytes) -> bool:
    """A NUL or other control byte that text does not hold (tab, newlines, form feed and escape
    aside). Text in a legacy 8-bit encoding is text: vendors' EDS and ESI files come in
    ISO-8859-1, and the readers are tested on such files."""
    return any(b in _CONTROL for b in data)


_CONTROL = frozenset(range(0x20)) - {0x09, 0x0A, 0x0B, 0x0C, 0x0D, 0x1B}


def tracked_binaries(root: Path = ROOT) -> list[str]:
    """Files git tracks that are binary (:func:`is_binary`)."""
    done = subprocess.run(["git", "ls-files", "-z"], cwd=root, capture_output=True, check=True)
    out = []
    for name in done.stdout.decode().split("\0"):
        p = root / name
        if name and p.is_file() and is_binary(p.read_bytes()):
            out.append(name)
    return out


# ---- the checks (pure) -----------------------------------------------------------------------


@dataclass
class _Class:
    module: str
    name: str
    bases: list[str]   # resolved "module.Class" where the base is the project's, else ""
    stores: set[str]


def _is_type_checking(test: ast.expr) -> bool:
    return (isinstance(test, ast.Name) and test.id == "TYPE_CHECKING") or (
        isinstance(test, ast.Attribute) and test.attr == "TYPE_CHECKING")


def _module_level(body: list[ast.stmt]) -> Iterable[ast.stmt]:
    """Statements run at import time: the body, into if/try/with blocks, not under TYPE_CHECKING,
    not into functions or classes' methods."""
    for node in body:
        yield node
        if isinstance(node, ast.If):
            if not _is_type_checking(node.test):
                yield from _module_level(node.body)
            yield from _module_level(node.orelse)
        elif isinstance(node, ast.Try):
            for block in (node.body, node.orelse, node.finalbody, *[h.body for h in node.handlers]):
                yield from _module_level(block)
        elif isinstance(node, ast.With):
            yield from _module_level(node.body)
        elif isinstance(node, ast.ClassDef):
            yield from (n for n in _module_level(node.body) if isinstance(n, (ast.Import, ast.ImportFrom)))


def _absolute(module: str, is_package: bool, node: ast.ImportFrom) -> str:
    if not node.level:
        return node.module or ""
    base = module.split(".") if is_package else module.split(".")[:-1]
    base = base[:len(base) - (node.level - 1)] if node.level > 1 else base
    return ".".join(base + ([node.module] if node.module else []))


def _imports(module: str, is_package: bool, nodes: Iterable[ast.AST], modules: set[str]) -> set[str]:
    """The project modules these import statements load."""
    out: set[str] = set()
    for node in nodes:
        if isinstance(node, ast.Import):
            out.update(a.name for a in node.names if a.name in modules)
        elif isinstance(node, ast.ImportFrom):
            src = _absolute(module, is_package, node)
            for a in node.names:
                sub = f"{src}.{a.name}"
                if sub in modules:
                    out.add(sub)
                elif src in modules:
                    out.add(src)
    out.discard(module)
    return out


def _circles(graph: Mapping[str, set[str]]) -> list[tuple[str, ...]]:
    """Strongly connected components of more than one module (Tarjan), each sorted."""
    index: dict[str, int] = {}
    low: dict[str, int] = {}
    stack: list[str] = []
    on: set[str] = set()
    out: list[tuple[str, ...]] = []

    def visit(v: str) -> None:
        # iterative: a deep import chain must not hit the recursion limit
        work = [(v, iter(sorted(graph.get(v, ()))))]
        index[v] = low[v] = len(index)
        stack.append(v)
        on.add(v)
        while work:
            node, it = work[-1]
            nxt = next(it, None)
            if nxt is not None:
                if nxt not in index:
                    index[nxt] = low[nxt] = len(index)
                    stack.append(nxt)
                    on.add(nxt)
                    work.append((nxt, iter(sorted(graph.get(nxt, ())))))
                elif nxt in on:
                    low[node] = min(low[node], index[nxt])
                continue
            work.pop()
            if work:
                low[work[-1][0]] = min(low[work[-1][0]], low[node])
            if low[node] == index[node]:
                comp = []
                while True:
                    w = stack.pop()
                    on.discard(w)
                    comp.append(w)
                    if w == node:
                        break
                if len(comp) > 1:
                    out.append(tuple(sorted(comp)))

    for v in sorted(graph):
        if v not in index:
            visit(v)
    return sorted(out)


def _self_stores(cls: ast.ClassDef) -> set[str]:
    """Distinct ``self.X`` assigned in the class's own methods (first parameter as ``self``)."""
    out: set[str] = set()
    for fn in cls.body:
        if not isinstance(fn, (ast.FunctionDef, ast.AsyncFunctionDef)) or not fn.args.args:
            continue
        me = fn.args.args[0].arg
        for node in ast.walk(fn):
            targets: list[ast.expr] = []
            if isinstance(node, ast.Assign):
                targets = list(node.targets)
            elif isinstance(node, (ast.AugAssign, ast.AnnAssign)):
                targets = [node.target]
            while targets:
                t = targets.pop()
                if isinstance(t, (ast.Tuple, ast.List)):
                    targets.extend(t.elts)
                elif isinstance(t, ast.Starred):
                    targets.append(t.value)
                elif isinstance(t, ast.Attribute) and isinstance(t.value, ast.Name) and t.value.id == me:
                    out.add(t.attr)
    return out


def _dotted(e: ast.expr) -> str | None:
    if isinstance(e, ast.Name):
        return e.id
    if isinstance(e, ast.Attribute):
        head = _dotted(e.value)
        return f"{head}.{e.attr}" if head else None
    if isinstance(e, ast.Subscript):  # Generic[T], Base[int]
        return _dotted(e.value)
    return None


def check_sources(sources: Mapping[str, str], lazy_in: Iterable[str] = LAZY_IMPORTS_COUNT_IN) -> Report:
    """Every rule but the binary files over ``sources`` (relative path -> Python text)."""
    report = Report()
    trees = {p: ast.parse(text, filename=p) for p, text in sources.items()}
    names = {p: module_name(p) for p in sources}
    modules = set(names.values())
    classes: dict[str, _Class] = {}
    graph: dict[str, set[str]] = {}
    lazy_graph: dict[str, set[str]] = {}
    lazy_roots = tuple(lazy_in)
    for p, tree in trees.items():
        mod, pkg = names[p], p.endswith("__init__.py")
        n_lines = len(sources[p].splitlines())
        if n_lines > MAX_LINES:
            report.long_modules[p] = n_lines
        top = list(_module_level(tree.body))
        graph[mod] = _imports(mod, pkg, top, modules)
        if mod.split(".")[0] in lazy_roots:
            lazy_graph[mod] = _imports(mod, pkg, ast.walk(tree), modules)
        # names this module binds to the project's classes: local ones and imported ones
        bound: dict[str, str] = {}
        for node in ast.walk(tree):
            if isinstance(node, ast.ImportFrom):
                src = _absolute(mod, pkg, node)
                for a in node.names:
                    bound[a.asname or a.name] = f"{src}.{a.name}"
            elif isinstance(node, ast.Import):
                for a in node.names:
                    bound[a.asname or a.name.split(".")[0]] = a.asname and a.name or a.name.split(".")[0]
        local = {c.name for c in tree.body if isinstance(c, ast.ClassDef)}
        for node in ast.walk(tree):
            if not isinstance(node, ast.ClassDef):
                continue
            bases = []
            for b in node.bases:
                d = _dotted(b)
                if d is None:
                    bases.append("")
                    continue
                head, _, rest = d.partition(".")
                if head in local and not rest:
                    bases.append(f"{mod}.{head}")
                elif head in bound:
                    bases.append(bound[head] + (f".{rest}" if rest else ""))
                else:
                    bases.append("")
            classes[f"{mod}.{node.name}"] = _Class(mod, node.name, bases, _self_stores(node))
    for key, c in sorted(classes.items()):
        if c.name.endswith("Mixin"):
            report.mixins.append(key)
        own = [b for b in c.bases if b in classes]
        if len(own) > 1:
            report.multiple_bases.append(key)
        stores: set[str] = set()
        seen: set[str] = set()
        todo = [key]
        while todo:
            k = todo.pop()
            if k in seen or k not in classes:
                continue
            seen.add(k)
            stores |= classes[k].stores
            todo.extend(classes[k].bases)
        if len(stores) > MAX_ATTRIBUTES:
            report.attributes[key] = len(stores)
    report.imports = graph
    report.cycles = _circles(graph)
    report.lazy_cycles = [c for c in _circles(lazy_graph) if c not in report.cycles]
    return report


def check_tree(root: Path = ROOT) -> Report:
    """:func:`check_sources` over the tree, plus the binary files git tracks."""
    report = check_sources(read_tree(root))
    report.binaries = tracked_binaries(root)
    return report


def main() -> int:
    lines = check_tree().lines()
    print("\n".join(lines) if lines else "no violation")
    return 1 if lines else 0


if __name__ == "__main__":
    raise SystemExit(main())
