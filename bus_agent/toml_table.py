"""Reading a TOML table for the configuration: typed getters whose errors name the key, and an
error for every key left over (a misspelt key is never silently ignored)."""

from __future__ import annotations

import dataclasses
from typing import Any, Mapping


class ConfigError(ValueError):
    """An invalid configuration; the message names the key (``drives[2].identity.vendor_id``)."""


class Table:
    """A TOML table being consumed: typed getters that name the key; leftovers are errors."""

    def __init__(self, data: Mapping[str, Any], path: str) -> None:
        if not isinstance(data, Mapping):
            raise ConfigError(f"{path or 'top level'}: expected a table, got {type(data).__name__}")
        self.data = dict(data)
        self.path = path

    def key(self, name: str) -> str:
        return f"{self.path}.{name}" if self.path else name

    def get(self, name: str, types: type | tuple[type, ...], default: Any = dataclasses.MISSING) -> Any:
        if name not in self.data:
            if default is dataclasses.MISSING:
                raise ConfigError(f"{self.key(name)}: required key missing")
            return default
        v = self.data.pop(name)
        if isinstance(v, bool) and bool not in (types if isinstance(types, tuple) else (types,)):
            raise ConfigError(f"{self.key(name)}: expected {type_names(types)}, got a boolean")
        if not isinstance(v, types):
            raise ConfigError(f"{self.key(name)}: expected {type_names(types)}, got {type(v).__name__} {v!r}")
        if isinstance(types, tuple) and float in types and isinstance(v, int):
            v = float(v)
        return v

    def table(self, name: str) -> "Table":
        return Table(self.get(name, dict, {}), self.key(name))

    def strings(self, name: str) -> tuple[str, ...]:
        v = self.get(name, list, [])
        for i, s in enumerate(v):
            if not isinstance(s, str):
                raise ConfigError(f"{self.key(name)}[{i}]: expected a string, got {s!r}")
        return tuple(v)

    def done(self) -> None:
        if self.data:
            raise ConfigError(f"{self.key(sorted(self.data)[0])}: unknown key")


def type_names(types: type | tuple[type, ...]) -> str:
    ts = types if isinstance(types, tuple) else (types,)
    names = {int: "an integer", float: "a number", str: "a string", bool: "a boolean", list: "an array", dict: "a table"}
    return " or ".join(names.get(t, t.__name__) for t in ts)
