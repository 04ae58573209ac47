"""Hypothesis strategies for valid messages, built from the field metadata (schemas.messages)."""

from __future__ import annotations

import dataclasses
from typing import Any

from hypothesis import strategies as st

from schemas import messages as m
from schemas.values import _base_type

NAME_FIRST = "abcXYZ019_"
NAME_REST = NAME_FIRST + ".-"
names = st.builds(lambda a, b: a + b, st.sampled_from(NAME_FIRST), st.text(NAME_REST, max_size=12))


def value(t: type, meta: Any, allow_empty: bool = False) -> st.SearchStrategy:
    """A valid value of type ``t`` under rule metadata ``meta``."""
    if "choices" in meta:
        return st.sampled_from(meta["choices"])
    if t is bool:
        return st.booleans()
    if t is int:
        lo, hi = meta.get("range", (-(2**63), 2**63 - 1))
        return st.integers(lo, hi)
    if t is float:
        lo, hi = meta.get("range", (-1e12, 1e12))
        return st.floats(lo, hi, allow_nan=False, allow_infinity=False) | st.integers(int(lo) + 1, int(hi))
    if t is str:
        if meta.get("name"):
            return (st.just("") | names) if allow_empty else names
        if meta.get("member"):
            return st.builds(lambda h, a: f"{h}/{a}", names, names)
        return st.text(min_size=meta.get("min_len", 0), max_size=meta.get("max_len", 30))
    if t is list:
        item = meta.get("items")
        return st.lists(value(item.type, item.meta) if item else st.integers(), max_size=4)
    if t is dict:
        k, v = meta.get("keys"), meta.get("values")
        return st.dictionaries(value(k.type, k.meta) if k else st.text(max_size=8),
                               value(v.type, v.meta) if v else st.integers(), max_size=4)
    raise AssertionError(t)


def args_for(op: str) -> st.SearchStrategy:
    spec = m.OP_ARGS.get(op, {})
    required = {n: value(a.type, a.meta) for n, a in spec.items() if a.required}
    optional = {n: value(a.type, a.meta) for n, a in spec.items() if not a.required}
    return st.fixed_dictionaries(required, optional=optional)


def message(cls: type) -> st.SearchStrategy:
    """A valid instance of message class ``cls``; optional fields sometimes left at the default."""
    fields: dict[str, st.SearchStrategy] = {}
    optional: dict[str, st.SearchStrategy] = {}
    for f in dataclasses.fields(cls):
        if cls is m.CommandRequest and f.name in ("op", "args"):
            continue
        s = value(_base_type(cls, f.name), f.metadata, allow_empty=f.default == "")
        if f.default is dataclasses.MISSING and f.default_factory is dataclasses.MISSING:
            fields[f.name] = s
        else:
            optional[f.name] = s
    base = st.fixed_dictionaries(fields, optional=optional)
    if cls is m.CommandRequest:
        ops = st.sampled_from(m.DRIVE_OPS + m.AGENT_OPS)
        return ops.flatmap(lambda op: st.builds(lambda kw, a: cls(op=op, args=a, **kw), base, args_for(op)))
    return base.map(lambda kw: cls(**kw))


any_message = st.one_of(*(message(c) for c in m.MESSAGE_TYPES))

msgpack_values = st.recursive(
    st.none() | st.booleans() | st.integers(-(2**63), 2**64 - 1) | st.floats() | st.text(max_size=10)
    | st.binary(max_size=10),
    lambda children: st.lists(children, max_size=4) | st.dictionaries(st.text(max_size=6), children, max_size=4),
    max_leaves=20,
)
