"""The value rules of the wire contract and their checks: what a field's metadata allows, and the
functions the codec (:mod:`schemas.messages`) applies to every value it decodes or validates.

Pure: no message types here; :mod:`schemas.messages` defines the messages over these rules, and
the JSON Schema export and docs/contract.md read the same metadata.
"""

from __future__ import annotations

import re
import types
import typing
from dataclasses import dataclass, field
from typing import Any

import msgpack

from . import keys as _keys


class SchemaError(ValueError):
    """A payload that is not a valid message of this schema version."""


# ---- nested value rules ------------------------------------------------------------------
# Metadata keys of a field (or of an op argument, see OP_ARGS):
#   doc       one-line meaning
#   range     (lo, hi) inclusive, for int/float
#   choices   the allowed values
#   open      with choices: an open vocabulary; the choices are the values known today, and a
#             reader accepts any other lower-case word too (a newer writer may add values)
#   max_len   longest str in characters
#   name      str must be a legal key chunk (schemas.keys.validate_name); '' only where the
#             default is '' (or allow_empty is set)
#   items     rule for every element of a list (a Meta)
#   keys      rule for every key of a map (a Meta, type str)
#   values    rule for every value of a map (a Meta)
#   arg_value map values are JSON-like: nil, bool, int (64 bit), finite float, str, and
#             lists/maps of these (depth <= ARG_MAX_DEPTH)
# The codec, the JSON Schema export and docs/contract.md all read these.


@dataclass(frozen=True)
class Meta:
    """A rule for a nested value: its Python type and the same metadata keys as a field."""

    type: type
    meta: dict = field(default_factory=dict)



ARG_MAX_DEPTH = 8
ARG_INT = (-(2**63), 2**64 - 1)


_HINTS: dict[type, dict[str, type]] = {}


def _field_types(cls: type[Any]) -> dict[str, type]:
    """Base runtime type of every field (``list`` for ``list[str]``, ``X`` for ``X | None``)."""
    hints = _HINTS.get(cls)
    if hints is None:
        hints = {}
        for name, t in typing.get_type_hints(cls).items():
            if isinstance(t, types.UnionType) or typing.get_origin(t) is typing.Union:
                t = next(a for a in typing.get_args(t) if a is not type(None))
            hints[name] = typing.get_origin(t) or t
        _HINTS[cls] = hints
    return hints


def _base_type(cls: type[Any], name: str) -> type:
    return _field_types(cls)[name]


def _check_arg_value(where: str, value: Any, depth: int) -> Any:
    """A JSON-like msgpack value: nil, bool, 64-bit int, finite float, str, list, str-keyed map."""
    if isinstance(value, msgpack.ExtType):  # a namedtuple: must not pass as a list
        raise SchemaError(f"{where}: msgpack extension type {value.code} is not allowed")
    if value is None or isinstance(value, (bool, str)):
        return value
    if isinstance(value, int):
        if not ARG_INT[0] <= value <= ARG_INT[1]:
            raise SchemaError(f"{where}: integer {value} does not fit 64 bits")
        return value
    if isinstance(value, float):
        if value != value or value in (float("inf"), float("-inf")):
            raise SchemaError(f"{where}: must be a finite number")
        return value
    if depth >= ARG_MAX_DEPTH and isinstance(value, (list, tuple, dict)):
        raise SchemaError(f"{where}: nested deeper than {ARG_MAX_DEPTH} levels")
    if isinstance(value, (list, tuple)):
        return [_check_arg_value(f"{where}[{i}]", v, depth + 1) for i, v in enumerate(value)]
    if isinstance(value, dict):
        if not all(isinstance(k, str) for k in value):
            raise SchemaError(f"{where}: expected a map with string keys")
        return {k: _check_arg_value(f"{where}.{k}", v, depth + 1) for k, v in value.items()}
    raise SchemaError(
        f"{where}: {type(value).__name__} is not allowed (nil, bool, int, float, str, list or map)"
    )


def _integer(where: str, value: Any) -> int:
    """An integer as JSON Schema counts one: an int, or a float with no fractional part (8.0).

    JSON has one number type, so ``8`` and ``8.0`` are the same value to a JSON Schema validator
    and to a writer in JavaScript; the codec agrees and normalises the float to an int.
    """
    if isinstance(value, float) and value.is_integer():  # False for NaN and infinities
        return int(value)
    if isinstance(value, bool) or not isinstance(value, int):
        raise SchemaError(f"{where}: expected int, got {type(value).__name__}")
    return value


def _check_value(where: str, t: type, meta: Any, value: Any, allow_empty: bool) -> Any:
    """Check ``value`` against type ``t`` and rule metadata; return it normalised."""
    if isinstance(value, msgpack.ExtType):  # a namedtuple: must not pass as a list
        raise SchemaError(f"{where}: msgpack extension type {value.code} is not allowed")
    if t is bool:
        if not isinstance(value, bool):
            raise SchemaError(f"{where}: expected bool, got {type(value).__name__}")
    elif t is int:
        value = _integer(where, value)
    elif t is float:
        if isinstance(value, bool) or not isinstance(value, (int, float)):
            raise SchemaError(f"{where}: expected number, got {type(value).__name__}")
        try:
            value = float(value)
        except OverflowError:
            raise SchemaError(f"{where}: number too large") from None
        if value != value or value in (float("inf"), float("-inf")):
            raise SchemaError(f"{where}: must be a finite number")
    elif t is str:
        if not isinstance(value, str):
            raise SchemaError(f"{where}: expected str, got {type(value).__name__}")
        if "max_len" in meta and len(value) > meta["max_len"]:
            raise SchemaError(f"{where}: longer than {meta['max_len']} characters")
        if "min_len" in meta and len(value) < meta["min_len"]:
            raise SchemaError(f"{where}: shorter than {meta['min_len']} characters")
        if meta.get("name") and not (value == "" and (allow_empty or meta.get("allow_empty"))):
            if not _keys.is_name(value):
                raise SchemaError(
                    f"{where}: {value!r} is not a legal name (1-64 of [A-Za-z0-9_.-], "
                    "not starting with '.' or '-')"
                )
        if meta.get("member"):
            host, sep, axis = value.partition("/")
            if not (sep and _keys.is_name(host) and _keys.is_name(axis)):
                raise SchemaError(f"{where}: {value!r} is not 'host/axis' of legal names")
    elif t is dict:
        if not isinstance(value, dict) or not all(isinstance(k, str) for k in value):
            raise SchemaError(f"{where}: expected a map with string keys")
        kmeta, vmeta = meta.get("keys"), meta.get("values")
        out = {}
        for k, v in value.items():
            if kmeta is not None:
                _check_value(f"{where}: key {k!r}", kmeta.type, kmeta.meta, k, allow_empty=False)
            if vmeta is not None:
                v = _check_value(f"{where}[{k!r}]", vmeta.type, vmeta.meta, v, allow_empty=False)
            elif meta.get("arg_value"):
                v = _check_arg_value(f"{where}.{k}", v, 1)
            out[k] = v
        value = out
    elif t is list:
        if not isinstance(value, (list, tuple)):
            raise SchemaError(f"{where}: expected a list, got {type(value).__name__}")
        imeta = meta.get("items")
        if imeta is None:
            value = list(value)
        elif imeta.type is int and set(imeta.meta) <= {"range", "doc"} and _int_list(value, imeta.meta):
            value = list(value)  # long numeric lists (recordings): checked at C speed
        else:
            value = [_check_value(f"{where}[{i}]", imeta.type, imeta.meta, v, allow_empty=False)
                     for i, v in enumerate(value)]
    if "range" in meta:
        lo, hi = meta["range"]
        if not lo <= value <= hi:
            raise SchemaError(f"{where}: {value!r} out of range [{lo}, {hi}]")
    if "choices" in meta and value not in meta["choices"] and not (
            meta.get("open") and isinstance(value, str) and _OPEN_WORD.match(value)):
        raise SchemaError(f"{where}: {value!r} is not one of {', '.join(map(str, meta['choices']))}")
    return value


def _int_list(value: Any, meta: dict) -> bool:
    """True when every item is a plain int within ``meta['range']`` (else the slow path names it)."""
    if not value:
        return True
    if not set(map(type, value)) <= {int}:
        return False
    lo, hi = meta.get("range", ARG_INT)
    return lo <= min(value) and max(value) <= hi


_OPEN_WORD = re.compile(r"[a-z][a-z0-9_]{0,31}\Z")
