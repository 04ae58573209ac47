"""A tiny JSON Schema checker for exactly the subset schemas.jsonschema emits.

Used when the ``jsonschema`` package is not installed (the project adds no dependency for it).
Independent of the codec on purpose: it reads only the emitted schema. "integer" means a Python
int (not bool, not float), "number" a finite int or float, as decoded from msgpack.
"""

from __future__ import annotations

import math
import re
from typing import Any

SUPPORTED = {
    "$schema", "$id", "$defs", "$ref", "title", "description", "default", "type", "const", "enum",
    "minimum", "maximum", "minLength", "maxLength", "pattern", "properties", "required",
    "additionalProperties", "propertyNames", "items", "anyOf", "allOf", "if", "then", "maxProperties", "examples",
}


class Invalid(Exception):
    pass


def _type_ok(t: str, v: Any) -> bool:
    if t == "null":
        return v is None
    if t == "boolean":
        return isinstance(v, bool)
    if t == "integer":
        return isinstance(v, int) and not isinstance(v, bool)
    if t == "number":
        return (isinstance(v, int) and not isinstance(v, bool)) or (isinstance(v, float) and math.isfinite(v))
    if t == "string":
        return isinstance(v, str)
    if t == "array":
        return isinstance(v, list)
    if t == "object":
        return isinstance(v, dict) and all(isinstance(k, str) for k in v)
    raise AssertionError(f"unsupported type {t}")


def _eq(a: Any, b: Any) -> bool:
    return type(a) is type(b) and a == b if isinstance(a, bool) or isinstance(b, bool) else a == b


def check(schema: dict, value: Any, root: dict | None = None, path: str = "$") -> None:
    """Raise :class:`Invalid` if ``value`` does not satisfy ``schema``."""
    root = root if root is not None else schema
    unknown = set(schema) - SUPPORTED
    assert not unknown, f"checker does not support {unknown}"
    if "$ref" in schema:
        ref = schema["$ref"]
        assert ref.startswith("#/$defs/")
        check(root["$defs"][ref.split("/")[-1]], value, root, path)
    if "type" in schema and not _type_ok(schema["type"], value):
        raise Invalid(f"{path}: not {schema['type']}")
    if "const" in schema and not _eq(schema["const"], value):
        raise Invalid(f"{path}: not const {schema['const']!r}")
    if "enum" in schema and not any(_eq(e, value) for e in schema["enum"]):
        raise Invalid(f"{path}: not in enum")
    numeric = isinstance(value, (int, float)) and not isinstance(value, bool)
    if numeric and "minimum" in schema and value < schema["minimum"]:
        raise Invalid(f"{path}: below minimum")
    if numeric and "maximum" in schema and value > schema["maximum"]:
        raise Invalid(f"{path}: above maximum")
    if isinstance(value, str):
        if "minLength" in schema and len(value) < schema["minLength"]:
            raise Invalid(f"{path}: too short")
        if "maxLength" in schema and len(value) > schema["maxLength"]:
            raise Invalid(f"{path}: too long")
        # ECMA-262 '$' is the end of input; Python's also matches before a final newline.
        if "pattern" in schema and not re.search(schema["pattern"].replace("$", r"\Z"), value):
            raise Invalid(f"{path}: pattern mismatch")
    if isinstance(value, list) and "items" in schema:
        for i, item in enumerate(value):
            check(schema["items"], item, root, f"{path}[{i}]")
    if isinstance(value, dict):
        props = schema.get("properties", {})
        for name in schema.get("required", []):
            if name not in value:
                raise Invalid(f"{path}: missing {name}")
        if "maxProperties" in schema and len(value) > schema["maxProperties"]:
            raise Invalid(f"{path}: too many properties")
        for k, v in value.items():
            if "propertyNames" in schema:
                check(schema["propertyNames"], k, root, f"{path}.<key {k!r}>")
            if k in props:
                check(props[k], v, root, f"{path}.{k}")
            elif schema.get("additionalProperties") is False:
                raise Invalid(f"{path}: unexpected property {k!r}")
            elif isinstance(schema.get("additionalProperties"), dict):
                check(schema["additionalProperties"], v, root, f"{path}.{k}")
    if "anyOf" in schema:
        for sub in schema["anyOf"]:
            try:
                check(sub, value, root, path)
                break
            except Invalid:
                pass
        else:
            raise Invalid(f"{path}: matches none of anyOf")
    for sub in schema.get("allOf", []):
        check(sub, value, root, path)
    if "if" in schema:
        try:
            check(schema["if"], value, root, path)
        except Invalid:
            pass
        else:
            check(schema.get("then", {}), value, root, path)


def is_valid(schema: dict, value: Any) -> bool:
    try:
        check(schema, value)
    except Invalid:
        return False
    return True
