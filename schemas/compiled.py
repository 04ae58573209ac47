"""A compiled field checker per message class: the codec's fast path (issue 13).

:func:`compile_checker` turns a class's field rows (name, type, metadata) into one Python
function, generated once, that takes a field map and returns the checked fields in declaration
order, defaults filled in. Each field gets an inline test of the common case (a value of exactly
the field's type inside its range, choices and length; an empty list or map; a map of plain
names to in-range integers); a name, member or open-vocabulary string passes inline once the full
check has accepted it for that field (remembered, at most :data:`SEEN_MAX` per field). Any other
value goes through :func:`schemas.values._check_value`, the one full check, so what is accepted,
how it is normalised and every error text stay those of the full check. Pure; knows no message
type; builds no key.
"""

from __future__ import annotations

import dataclasses
from typing import Any, Callable

from .values import SchemaError, _check_value

#: Strings one field accepted, remembered up to this many per field (names, states and ids repeat
#: in every status and reply: the full check runs once per distinct value).
SEEN_MAX = 512

#: The remembered strings, per message type and field (for tests and diagnostics).
SEEN: dict[str, dict[str, set]] = {}

#: Marker of a field absent from the map.
_MISSING = object()

#: Metadata keys a plain string field may have and still be checked inline.
_PLAIN_STR = frozenset({"doc", "max_len", "min_len"})


@dataclasses.dataclass(frozen=True)
class Row:
    """One field as the checker sees it."""

    name: str
    where: str            # "<type>.<field>", the prefix of its error texts
    t: type               # base runtime type (list for list[str])
    meta: Any             # the field's metadata mapping
    allow_empty: bool     # a name field whose default is "" accepts ""
    default: Any          # dataclasses.MISSING when the field is required
    factory: Any          # default_factory, or dataclasses.MISSING


Checker = Callable[[dict, dict], dict]


def _scalar_test(var: str, t: type, meta: Any, consts: dict, tag: str) -> str | None:
    """An inline boolean expression accepting a common, valid ``var`` of type ``t``, or None.

    None means: no inline form (the caller remembers strings, or always takes the full check)."""
    rng, choices = meta.get("range"), meta.get("choices")
    if t is bool:
        return f"type({var}) is bool"
    if t in (int, float):
        test = f"type({var}) is {t.__name__}"
        if t is float:
            test += f" and -_INF < {var} < _INF"  # false for NaN and the infinities
        if rng is not None:
            consts[f"_LO{tag}"], consts[f"_HI{tag}"] = rng
            test += f" and _LO{tag} <= {var} <= _HI{tag}"
        if choices is not None:
            consts[f"_CH{tag}"] = frozenset(choices)
            test += f" and {var} in _CH{tag}"
        return test
    if t is str:
        if choices is not None and not meta.get("open"):
            consts[f"_CH{tag}"] = frozenset(choices)
            return f"type({var}) is str and {var} in _CH{tag}"
        if set(meta) <= _PLAIN_STR:
            test = f"type({var}) is str"
            if "max_len" in meta:
                test += f" and len({var}) <= {int(meta['max_len'])}"
            if "min_len" in meta:
                test += f" and len({var}) >= {int(meta['min_len'])}"
            return test
    return None


def _field_code(i: int, row: Row, consts: dict, seen_sets: dict[str, set]) -> list[str]:
    """Source lines checking field ``row`` of the map ``body`` into ``out``."""
    tag = str(i)
    consts[f"_W{tag}"] = row.where
    lines = [f"    x = body.get({row.name!r}, _MISSING)", "    if x is _MISSING:"]
    if row.default is dataclasses.MISSING and row.factory is dataclasses.MISSING:
        lines.append(f"        raise SchemaError(_W{tag} + ': required field missing')")
    elif row.factory is not dataclasses.MISSING:
        consts[f"_F{tag}"] = row.factory
        lines.append(f"        out[{row.name!r}] = _F{tag}()")
    else:
        consts[f"_D{tag}"] = row.default
        lines.append(f"        out[{row.name!r}] = _D{tag}")
    test = _scalar_test("x", row.t, row.meta, consts, tag)
    learn = False
    if test is None and row.t is str:
        seen: set[str] = set()
        consts[f"_S{tag}"] = seen_sets[row.name] = seen
        consts[f"_L{tag}"] = _learner(seen)
        test, learn = f"type(x) is str and x in _S{tag}", True
    elif row.t in (list, dict):
        test = f"type(x) is {row.t.__name__} and not x"
        if row.t is dict and row.meta.get("keys") is not None and row.meta.get("values") is not None:
            k, v = row.meta["keys"], row.meta["values"]
            ktest = _scalar_test("k", k.type, k.meta, consts, tag + "k")
            vtest = _scalar_test("v", v.type, v.meta, consts, tag + "v")
            if ktest and vtest:
                test = f"type(x) is dict and all({ktest} and {vtest} for k, v in x.items())"
    if test is None:
        test = "False"
    consts[f"_M{tag}"], consts[f"_T{tag}"] = row.meta, row.t
    full = f"_check_value(_W{tag}, _T{tag}, _M{tag}, x, {row.allow_empty!r})"
    lines += [f"    elif {test}:", f"        out[{row.name!r}] = x", "    else:"]
    if learn:
        lines += [f"        out[{row.name!r}] = x = {full}", f"        _L{tag}(x)"]
    else:
        lines.append(f"        out[{row.name!r}] = {full}")
    return lines


def _learner(seen: set) -> Callable[[Any], None]:
    def learn(value: Any) -> None:
        if type(value) is str:
            if len(seen) >= SEEN_MAX:
                seen.clear()
            seen.add(value)
    return learn


def compile_checker(type_name: str, rows: tuple[Row, ...]) -> Checker:
    """The checker of one message class: ``check(body, out)`` puts every field of ``body``,
    checked and normalised, into ``out`` (in declaration order; a missing optional field gets its
    default) and returns ``out``; raises :class:`SchemaError` at the first bad field, with the
    full check's text. Fields of ``body`` that are not in ``rows`` are ignored here."""
    consts: dict[str, Any] = {"SchemaError": SchemaError, "_check_value": _check_value,
                              "_MISSING": _MISSING, "_INF": float("inf")}
    lines = ["def check(body, out):"]
    seen_sets = SEEN.setdefault(type_name, {})
    for i, row in enumerate(rows):
        lines += _field_code(i, row, consts, seen_sets)
    lines.append("    return out")
    namespace: dict[str, Any] = dict(consts)
    exec(compile("\n".join(lines), f"<checker of {type_name}>", "exec"), namespace)  # noqa: S102
    check: Checker = namespace["check"]
    return check
