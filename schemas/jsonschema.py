"""JSON Schema (draft 2020-12) of every message, generated from the dataclass fields.

One schema per message type describes its wire map: ``v`` and ``type`` as constants, every field
with its type and the rule metadata of :mod:`schemas.messages` (``range`` -> ``minimum`` /
``maximum``, ``choices`` -> ``enum``, ``max_len`` -> ``maxLength``, ``name`` -> ``pattern``,
``doc`` -> ``description``, an open vocabulary -> ``pattern`` + ``examples``) and required fields.
Only ``command_request`` (strict) forbids other properties; it also carries the per-op argument
rules (:data:`schemas.messages.OP_ARGS`) as ``if``/``then``.

The wire format is msgpack; JSON Schema describes the JSON form of the decoded value, and the
codec agrees with a standard validator (the ``jsonschema`` package, draft 2020-12) on every map
that has a JSON form:

- "integer" is JSON Schema's: an int or a float with no fractional part (``8.0``); the codec
  accepts both for an int field and normalises to int.
- "number" is a finite int or float. NaN, infinities, bytes and extension types have no JSON
  form; the codec rejects them wherever it reads a value (see :mod:`schemas.messages`).
- patterns end with :data:`END`, which is the end of input in ECMA-262 and in Python's ``re``
  alike, so no dialect accepts a trailing newline the codec rejects.
"""

from __future__ import annotations

import dataclasses
import json
from pathlib import Path
from typing import Any

from . import keys as _keys
from .messages import (
    AGENT_OPS,
    ARG_INT,
    ARG_MAX_DEPTH,
    DRIVE_OPS,
    MESSAGE_TYPES,
    OP_ARGS,
    SCHEMA_VERSION,
    CommandRequest,
    Meta,
)
from .values import _base_type

DIALECT = "https://json-schema.org/draft/2020-12/schema"
#: End of input in every regex dialect a validator may use. ECMA-262's ``$`` (what the JSON Schema
#: spec names) is the end of input; Python's ``re`` (what the ``jsonschema`` package applies) also
#: matches ``$`` before a final newline, so ``^a$`` would accept ``"a\n"``. The lookahead is a
#: no-op in ECMA-262 and closes that gap in Python, so the patterns mean what the codec checks.
END = r"$(?!\n)"
_NAME = _keys.NAME_PATTERN.strip("^$")
NAME_PATTERN = f"^{_NAME}{END}"
NAME_OR_EMPTY_PATTERN = f"^(?:{_NAME})?{END}"
MEMBER_PATTERN = f"^{_NAME}/{_NAME}{END}"

_JSON_TYPES = {bool: "boolean", int: "integer", float: "number", str: "string", list: "array", dict: "object"}

#: JSON-like argument values (nil, bool, int, float, str, lists and maps of these).
ARG_VALUE_DEF = {
    "description": f"nil, bool, 64-bit int, finite float, str, or lists/maps of these "
                   f"(at most {ARG_MAX_DEPTH} levels deep)",
    "anyOf": [
        {"type": "null"},
        {"type": "boolean"},
        {"type": "integer", "minimum": ARG_INT[0], "maximum": ARG_INT[1]},
        {"type": "number"},
        {"type": "string"},
        {"type": "array", "items": {"$ref": "#/$defs/arg_value"}},
        {"type": "object", "additionalProperties": {"$ref": "#/$defs/arg_value"}},
    ],
}

OPEN_WORD_PATTERN = f"^[a-z][a-z0-9_]{{0,31}}{END}"


def value_schema(t: type, meta: Any, allow_empty: bool = False) -> dict:
    """Schema of one value of Python type ``t`` under rule metadata ``meta``."""
    out: dict[str, Any] = {}
    if meta.get("doc"):
        out["description"] = meta["doc"]
    out["type"] = _JSON_TYPES[t]
    if "choices" in meta and meta.get("open"):
        # open vocabulary: today's values as examples, any lower-case word accepted
        out["examples"] = list(meta["choices"])
        out["pattern"] = OPEN_WORD_PATTERN
    elif "choices" in meta:
        out["enum"] = list(meta["choices"])
    if "range" in meta:
        out["minimum"], out["maximum"] = meta["range"]
    if "min_len" in meta:
        out["minLength"] = meta["min_len"]
    if "max_len" in meta:
        out["maxLength"] = meta["max_len"]
    if meta.get("name"):
        out["pattern"] = NAME_OR_EMPTY_PATTERN if (allow_empty or meta.get("allow_empty")) else NAME_PATTERN
    if meta.get("member"):
        out["pattern"] = MEMBER_PATTERN
    if t is list and isinstance(meta.get("items"), Meta):
        out["items"] = value_schema(meta["items"].type, meta["items"].meta)
    if t is dict:
        if isinstance(meta.get("keys"), Meta):
            out["propertyNames"] = value_schema(meta["keys"].type, meta["keys"].meta)
        if isinstance(meta.get("values"), Meta):
            out["additionalProperties"] = value_schema(meta["values"].type, meta["values"].meta)
        elif meta.get("arg_value"):
            out["additionalProperties"] = {"$ref": "#/$defs/arg_value"}
    return out


def _default(f: dataclasses.Field) -> Any:
    if f.default is not dataclasses.MISSING:
        return f.default
    if f.default_factory is not dataclasses.MISSING:
        return f.default_factory()
    return dataclasses.MISSING


def _op_rules() -> list[dict]:
    """``if op == X then args follow OP_ARGS[X]`` for every op."""
    rules = []
    for op in DRIVE_OPS + AGENT_OPS:
        spec = OP_ARGS.get(op, {})
        args_schema: dict[str, Any] = {
            "type": "object",
            "properties": {name: value_schema(a.type, a.meta) for name, a in spec.items()},
            "additionalProperties": False,
        }
        for name, a in spec.items():
            if a.default is not None:
                args_schema["properties"][name]["default"] = a.default
        required = [name for name, a in spec.items() if a.required]
        then: dict[str, Any] = {"properties": {"args": args_schema}}
        if required:
            args_schema["required"] = required
            then["required"] = ["args"]
        rules.append({"if": {"properties": {"op": {"const": op}}, "required": ["op"]}, "then": then})
    return rules


def message_schema(cls: type[Any]) -> dict:
    """The JSON Schema of message class ``cls`` (one of :data:`schemas.messages.MESSAGE_TYPES`)."""
    props: dict[str, Any] = {
        "v": {"description": "schema version", "type": "integer", "const": SCHEMA_VERSION},
        "type": {"description": "message type", "type": "string", "const": cls.TYPE},
    }
    required = ["v", "type"]
    for f in dataclasses.fields(cls):
        default = _default(f)
        prop = value_schema(_base_type(cls, f.name), f.metadata, allow_empty=default == "")
        if default is dataclasses.MISSING:
            required.append(f.name)
        else:
            prop["default"] = default
        props[f.name] = prop
    doc = " ".join((cls.__doc__ or "").strip().split("\n\n")[0].split())
    schema: dict[str, Any] = {
        "$schema": DIALECT,
        "$id": f"urn:zenoh-drives:schemas:v{SCHEMA_VERSION}:{cls.TYPE}",
        "title": cls.__name__,
        "description": doc,
        "type": "object",
        "properties": props,
        "required": required,
        # the evolution rule (docs/contract.md): only commands reject fields they do not know
        "additionalProperties": not cls.STRICT,
    }
    if cls is CommandRequest:
        schema["allOf"] = _op_rules()
        schema["$defs"] = {"arg_value": ARG_VALUE_DEF}
    return schema


def all_schemas() -> dict[str, dict]:
    """Message type name -> JSON Schema, for every message type."""
    return {cls.TYPE: message_schema(cls) for cls in MESSAGE_TYPES}


def write_schemas(out_dir: str | Path) -> list[Path]:
    """Write ``<type>.schema.json`` for every message into ``out_dir``; return the paths."""
    out = Path(out_dir)
    out.mkdir(parents=True, exist_ok=True)
    paths = []
    for name, schema in all_schemas().items():
        path = out / f"{name}.schema.json"
        path.write_text(json.dumps(schema, indent=2, sort_keys=False) + "\n", encoding="utf-8")
        paths.append(path)
    return paths
