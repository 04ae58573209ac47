"""The structure rules over the repository's own Python (tests/contract/structure.py): no mixins,
at most one project base per class, at most 40 attributes per class, at most 600 lines per
module, no import circles (module-level imports; in bench/ imports inside functions too), no
binary files in git. Known violations are listed below, one entry each; a new one fails."""

from __future__ import annotations

import pytest

from tests.contract.structure import MAX_ATTRIBUTES, MAX_LINES, Report, check_sources, check_tree, is_binary

ALLOWED_MIXINS: set[str] = set()
ALLOWED_MULTIPLE_BASES: set[str] = set()
ALLOWED_ATTRIBUTES: set[str] = set()
ALLOWED_LONG_MODULES: set[str] = set()
ALLOWED_CYCLES: set[tuple[str, ...]] = set()
ALLOWED_BINARIES: set[str] = set()


@pytest.fixture(scope="module")
def report() -> Report:
    return check_tree()


def test_no_mixins(report):
    assert set(report.mixins) - ALLOWED_MIXINS == set()


def test_at_most_one_project_base(report):
    assert set(report.multiple_bases) - ALLOWED_MULTIPLE_BASES == set()


def test_at_most_40_attributes_per_class(report):
    assert {c: n for c, n in report.attributes.items() if c not in ALLOWED_ATTRIBUTES} == {}


def test_at_most_600_lines_per_module(report):
    assert {p: n for p, n in report.long_modules.items() if p not in ALLOWED_LONG_MODULES} == {}


def test_no_import_circles(report):
    assert set(report.cycles) - ALLOWED_CYCLES == set()


def test_no_lazy_import_circles_in_bench(report):
    assert report.lazy_cycles == []


def test_no_binary_files_tracked(report):
    assert set(report.binaries) - ALLOWED_BINARIES == set()


def test_the_allowlists_hold_only_known_violations(report):
    """An entry whose violation is gone is taken off (so the list only shrinks)."""
    assert ALLOWED_MIXINS - set(report.mixins) == set()
    assert ALLOWED_MULTIPLE_BASES - set(report.multiple_bases) == set()
    assert ALLOWED_ATTRIBUTES - set(report.attributes) == set()
    assert ALLOWED_LONG_MODULES - set(report.long_modules) == set()
    assert ALLOWED_BINARIES - set(report.binaries) == set()


# ---- the checker on small synthetic sources ------------------------------------------------------


def _class_with(n: int, name: str = "Big", base: str = "") -> str:
    stores = "\n".join(f"        self.a{i} = {i}" for i in range(n))
    return f"class {name}{f'({base})' if base else ''}:\n    def __init__(self):\n{stores}\n"


def test_a_mixin_and_two_project_bases_are_found():
    r = check_sources({"p/__init__.py": "", "p/a.py": "class A:\n    pass\nclass FooMixin:\n    pass\n",
                       "p/b.py": "from p.a import A, FooMixin\nimport p.a as pa\n"
                                 "class B(A, FooMixin):\n    pass\nclass C(pa.A, Exception):\n    pass\n"
                                 "class D(dict, Exception):\n    pass\n"})
    assert r.mixins == ["p.a.FooMixin"]
    assert r.multiple_bases == ["p.b.B"]


def test_attributes_are_counted_with_the_project_bases():
    tuple_stores = "    def set(self, x):\n        self.t, (self.u, *self.v) = x\n        self.t += 1\n"
    src = _class_with(30, "Base") + "\n" + _class_with(11, "Child", "Base").replace("self.a", "self.b")
    src += "\n" + _class_with(37, "Small") + tuple_stores  # 37 + t, u, v = 40
    r = check_sources({"m.py": src})
    assert r.attributes == {"m.Child": 41}
    assert check_sources({"m.py": _class_with(MAX_ATTRIBUTES)}).attributes == {}
    assert check_sources({"m.py": _class_with(MAX_ATTRIBUTES + 1)}).attributes == {"m.Big": MAX_ATTRIBUTES + 1}


def test_long_modules_are_found():
    assert check_sources({"ok.py": "x = 1\n" * MAX_LINES}).long_modules == {}
    assert check_sources({"long.py": "x = 1\n" * (MAX_LINES + 1)}).long_modules == {"long.py": MAX_LINES + 1}


def test_import_circles_count_module_level_imports_only():
    sources = {"p/__init__.py": "", "p/a.py": "from p import b\n",
               "p/b.py": "from typing import TYPE_CHECKING\nif TYPE_CHECKING:\n    from p.a import X\n"
                         "def f():\n    from p import a\n"}
    assert check_sources(sources).cycles == []
    sources["p/b.py"] = "try:\n    from .a import X\nexcept ImportError:\n    pass\n"
    assert check_sources(sources).cycles == [("p.a", "p.b")]
    three = {"x.py": "import y\n", "y.py": "import z\n", "z.py": "from x import f\n", "w.py": "import x\n"}
    assert check_sources(three).cycles == [("x", "y", "z")]


def test_imports_inside_functions_count_in_bench():
    sources = {"bench/__init__.py": "", "bench/a.py": "from bench.b import f\n",
               "bench/b.py": "def f():\n    from bench.a import g\n",
               "lib/__init__.py": "", "lib/a.py": "from lib.b import f\n", "lib/b.py": "def f():\n    from lib import a\n"}
    r = check_sources(sources)
    assert r.cycles == [] and r.lazy_cycles == [("bench.a", "bench.b")]


def test_binary_data_is_told_from_text():
    assert not is_binary("UTF-8 text: Ä µs\n".encode())
    assert is_binary(b"PK\x03\x04\x00\x00")
    assert not is_binary("Latin-1 text, as vendors' EDS files: \xc4\r\n".encode("latin-1"))
    assert is_binary(b"\x7fELF\x02\x01\x01\x00")
