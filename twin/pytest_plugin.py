"""pytest plugin: a simulated twin of a fleet per test (or per session), for networked integration tests.

Installed with the package (entry point ``drives_twin`` in the ``pytest11`` group) and off unless
a test asks for one of its fixtures; importing it costs nothing (the twin is imported on first use).

Fixtures:

- ``drives_twin`` -- a factory: ``twin = drives_twin(fleet)`` with a fleet file path or the same
  content as a dict (``{"hosts": {"c1": {"axes": ["a", "b"]}}}``) starts a :class:`twin.Twin`,
  returns it once every drive answers, and stops it at the end of the test. The twin has
  ``endpoint``, a connected ``fleet`` (``supervisor.Fleet``) and ``fault(ref, code)``,
  ``unplug(ref)``, ``plug(ref)``, ``cut(host)``, ``restore(host)``, ``kill_agent(host)``,
  ``restart_agent(host)``, ``kill_router()``, ``restart_router()``,
  ``wait_state(ref, state, timeout_s)`` (refs ``"host/axis"``).
- ``drives_twin_session`` -- the same factory, session-scoped: a twin started with the same fleet
  and backend is shared by every test that asks for it, and stopped at the end of the session.

Backend (``sim``: in-process drive models, no root; ``ecat``: pysoem against ``ecat-sim`` per host
namespace, root): ``drives_twin(fleet, backend="ecat")``, else the test's marker
``@pytest.mark.drives_twin(backend="ecat")``, else the option ``--drives-twin-backend``, else the
ini value ``drives_twin_backend``, else ``sim``. A secure twin (mutual TLS, the router's ACL, the
twin's ``fleet`` an operator; ``twin.secure``) the same way: ``pki=DIR`` (and ``identity=NAME``)
as argument or marker keyword, ``--drives-twin-pki DIR`` / ``--drives-twin-identity NAME``, ini
``drives_twin_pki`` / ``drives_twin_identity``; DIR is a directory made by ``drives-pki init``. Without root the ecat backend skips the test, or
fails it when the environment variable ``CI`` is true (a CI run must not skip silently).

A child of the twin that exits without being asked (a crashed agent) fails the test at teardown
with the child's last output.
"""

from __future__ import annotations

import json
import os
from typing import TYPE_CHECKING, Any, Callable, Iterator, Mapping

import pytest

if TYPE_CHECKING:
    from twin.twin import Twin

BACKENDS = ("sim", "ecat")
_CI_TRUE = ("1", "true", "yes")


def pytest_addoption(parser: pytest.Parser) -> None:
    group = parser.getgroup("drives-twin", "simulated drive fleets (zenoh-drives)")
    group.addoption("--drives-twin-backend", choices=BACKENDS, default=None,
                    help="backend of drives_twin fixtures: sim (default, no root) or ecat (root)")
    group.addoption("--drives-twin-pki", default=None, metavar="DIR",
                    help="drives-pki directory: drives_twin fixtures run secure twins (mutual TLS, ACL)")
    group.addoption("--drives-twin-identity", default=None, metavar="NAME",
                    help="with a PKI: the principal of the twins' fleet (default twin-operator, role operator)")
    parser.addini("drives_twin_backend", "backend of drives_twin fixtures: sim or ecat", default="sim")
    parser.addini("drives_twin_pki", "drives-pki directory of drives_twin fixtures (empty: insecure)", default="")
    parser.addini("drives_twin_identity", "with a PKI: the principal of the twins' fleet", default="")


def pytest_configure(config: pytest.Config) -> None:
    config.addinivalue_line("markers", "drives_twin(backend='sim'|'ecat', pki=DIR, identity=NAME): backend "
                            "and PKI of this test's drives_twin twins")


def _chosen(request: pytest.FixtureRequest, name: str, asked: Any) -> Any:
    """``asked``, else the test's marker's ``name``, else ``--drives-twin-NAME``, else the ini value."""
    marker = request.node.get_closest_marker("drives_twin") if request.scope == "function" else None
    return (asked or (marker.kwargs.get(name) if marker else None)
            or request.config.getoption(f"--drives-twin-{name}") or request.config.getini(f"drives_twin_{name}"))


def _backend(request: pytest.FixtureRequest, asked: str | None) -> str:
    backend = _chosen(request, "backend", asked)
    if backend not in BACKENDS:
        raise pytest.UsageError(f"drives_twin backend {backend!r} is not one of {', '.join(BACKENDS)}")
    return str(backend)


def _require(backend: str) -> None:
    """The ecat backend's prerequisites: fail under CI=true, skip elsewhere."""
    if backend != "ecat":
        return
    from twin.ecat import prerequisites

    why = prerequisites()
    if why is None:
        return
    if os.environ.get("CI", "").lower() in _CI_TRUE:
        pytest.fail(f"drives_twin: {why} (CI=true: not skipped)", pytrace=False)
    pytest.skip(f"drives_twin: {why}; run as root (e.g. sudo) or use the sim backend")


class _Twins:
    """The twins one fixture started; stops them all, then reports children that died unasked."""

    def __init__(self, request: pytest.FixtureRequest) -> None:
        self.request = request
        self.twins: dict[str, "Twin"] = {}

    def __call__(self, fleet: str | os.PathLike[str] | Mapping[str, Any], *, backend: str | None = None,
                 listen: str | None = None, ready_timeout_s: float = 60.0,
                 pki: str | os.PathLike[str] | None = None, identity: str | None = None) -> "Twin":
        from twin.twin import Twin

        chosen = _backend(self.request, backend)
        _require(chosen)
        pki = _chosen(self.request, "pki", pki) or None
        identity = (identity or _chosen(self.request, "identity", None) or None) if pki else identity
        what = json.dumps(fleet, sort_keys=True) if isinstance(fleet, Mapping) else os.fspath(fleet)
        key = f"{chosen}:{pki}:{identity}:{what}"
        if self.request.scope == "session" and key in self.twins:
            return self.twins[key]
        twin = Twin(fleet, backend=chosen, listen=listen, ready_timeout_s=ready_timeout_s, pki=pki, identity=identity)
        self.twins[key if self.request.scope == "session" else str(len(self.twins))] = twin
        return twin.start()

    def close(self) -> None:
        died: list[str] = []
        for twin in self.twins.values():
            twin.stop()
            died += twin.unexpected_exits
        if died:
            pytest.fail("drives_twin: " + "\n".join(died), pytrace=False)


def _factory(request: pytest.FixtureRequest) -> Iterator[Callable[..., "Twin"]]:
    twins = _Twins(request)
    try:
        yield twins
    finally:
        twins.close()


@pytest.fixture
def drives_twin(request: pytest.FixtureRequest) -> Iterator[Callable[..., "Twin"]]:
    """Factory of twins stopped at the end of the test: ``twin = drives_twin(fleet)``."""
    yield from _factory(request)


@pytest.fixture(scope="session")
def drives_twin_session(request: pytest.FixtureRequest) -> Iterator[Callable[..., "Twin"]]:
    """Factory of twins shared by the session (same fleet and backend: same twin)."""
    yield from _factory(request)
