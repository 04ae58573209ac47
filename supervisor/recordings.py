"""Flight recordings: fetch one from an agent, write it as CSV, read a CSV back.

An agent's flight recorder (``drives/@v1/<host>/agent/recording``) answers a ``recording_request``
with a ``recording``: consecutive cycles, one value list per channel. Here it becomes a long
("tidy") CSV, one row per cycle and axis, with the decoded CiA 402 state, preceded by ``#``
comment lines carrying what triggered it (pandas: ``read_csv(path, comment="#")``).
"""

from __future__ import annotations

import csv
import io
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import zenoh

from bus_agent.cia402.states import decode_statusword
from schemas import keys
from schemas.messages import RECORDING_CHANNELS, Recording, RecordingRequest, SchemaError, decode, encode

#: ``drivectl record --trigger`` words -> ``recording_request.what``.
TRIGGER_WORDS = {"last-fault": "fault", "last-reflex": "reflex", "last-lost": "lost", "last-request": "request",
                 "last": "any", "now": "now"}
#: CSV columns, in order: per row one cycle of one axis.
CSV_COLUMNS = ("cycle", "time_s", "axis", "state", "statusword", "controlword", "target_position",
               "target_velocity", "target_torque", "position", "velocity", "torque", "error_code",
               "mode_display", "period_us", "wkc")
_META = ("host", "reason", "axis", "detail", "trigger_cycle", "cycle_us", "first_cycle", "n_cycles", "time_origin_ns")


class RecordingError(RuntimeError):
    """The agent refused or did not answer (the text says which and why)."""


def fetch_recording(session: zenoh.Session, host: str, what: str = "last", last_s: float = 10.0,
                    timeout_s: float = 20.0) -> Recording:
    """Ask ``host``'s flight recorder (``what``: see ``schemas.messages.RECORDING_WHAT``)."""
    keys.validate_name(host, "host")
    payload = encode(RecordingRequest(what=what, last_s=last_s))
    errors: list[str] = []
    for reply in session.get(keys.agent_recording(host), payload=payload, timeout=timeout_s):
        if reply.ok is not None:
            try:
                return decode(reply.ok.payload.to_bytes(), Recording)
            except SchemaError as exc:
                errors.append(f"invalid recording from {host}: {exc}")
        elif reply.err is not None:
            text = reply.err.payload.to_string()
            if text != "Timeout":
                errors.append(text)
    raise RecordingError("; ".join(errors) or f"no answer from the flight recorder of {host} within "
                         f"{timeout_s:g} s (is its agent running and reachable?)")


@dataclass
class Table:
    """A recording as read from CSV: metadata and rows (dicts of column -> value)."""

    meta: dict[str, str] = field(default_factory=dict)
    rows: list[dict[str, Any]] = field(default_factory=list)

    @property
    def axes(self) -> list[str]:
        return list(dict.fromkeys(r["axis"] for r in self.rows))

    def column(self, axis: str, name: str) -> list[Any]:
        return [r[name] for r in self.rows if r["axis"] == axis]


def rows_of(rec: Recording) -> list[dict[str, Any]]:
    """One dict per cycle and axis (the CSV rows). Pure."""
    ch = rec.channels
    n = len(rec.axes)
    t0 = ch["time_ns"][0] if ch.get("time_ns") else 0
    out = []
    for i in range(rec.n_cycles):
        base = {"cycle": ch["cycle"][i] if "cycle" in ch else rec.first_cycle + i,
                "time_s": round((ch["time_ns"][i] - t0) / 1e9, 9) if "time_ns" in ch else i * rec.cycle_us / 1e6,
                "period_us": ch["period_ns"][i] / 1000 if "period_ns" in ch else "",
                "wkc": ch["wkc"][i] if "wkc" in ch else ""}
        for j, axis in enumerate(rec.axes):
            row = dict(base, axis=axis)
            for name, (scope, _) in RECORDING_CHANNELS.items():
                if scope == "drive" and name in ch:
                    row[name] = ch[name][i * n + j]
            row["state"] = decode_statusword(row.get("statusword", 0)).value
            out.append(row)
    return out


def write_csv(rec: Recording, path: str | Path) -> int:
    """Write ``rec`` as CSV; returns the number of rows."""
    rows = rows_of(rec)
    with open(path, "w", newline="") as f:
        for k in _META:
            f.write(f"# {k}: {str(getattr(rec, k)).replace(chr(10), ' ')}\n")
        w = csv.DictWriter(f, fieldnames=CSV_COLUMNS, extrasaction="ignore")
        w.writeheader()
        w.writerows(rows)
    return len(rows)


def read_csv(path: str | Path) -> Table:
    """Read a CSV written by :func:`write_csv`. Raises ValueError naming the problem."""
    text = Path(path).read_text()
    meta: dict[str, str] = {}
    body: list[str] = []
    for line in text.splitlines():
        if line.startswith("# ") and ":" in line and not body:
            k, _, v = line[2:].partition(":")
            meta[k.strip()] = v.strip()
        else:
            body.append(line)
    reader = csv.DictReader(io.StringIO("\n".join(body)))
    missing = [c for c in ("cycle", "axis", "statusword", "position", "velocity") if c not in (reader.fieldnames or ())]
    if missing:
        raise ValueError(f"{path}: not a flight recording CSV (missing column(s) {', '.join(missing)})")
    rows: list[dict[str, Any]] = []
    for n, raw in enumerate(reader, start=2 + len(meta)):
        row: dict[str, Any] = {}
        for k, v in raw.items():
            if k in ("axis", "state"):
                row[k] = v
            elif v in ("", None):
                row[k] = None
            else:
                try:
                    row[k] = float(v) if k in ("time_s", "period_us") else int(v)
                except ValueError:
                    raise ValueError(f"{path}, line {n}: column {k}: {v!r} is not a number") from None
        rows.append(row)
    return Table(meta, rows)
