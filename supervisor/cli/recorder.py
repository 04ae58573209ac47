"""Flight recorder verbs: ``record`` (an agent's recording into a CSV) and ``plot`` (CSV -> PNG)."""

from __future__ import annotations

import argparse
import json
from typing import Callable

from rich.console import Console

from ..recordings import TRIGGER_WORDS, RecordingError, fetch_recording, write_csv
from .common import EXIT_FAILED, EXIT_OK, UsageError, open_fleet, positive_s


def _record(args: argparse.Namespace, console: Console) -> int:
    what = TRIGGER_WORDS[args.trigger] if args.trigger else "last"
    with open_fleet(args) as fleet:
        try:
            rec = fetch_recording(fleet.session, args.host, what, args.last or 10.0,
                                  timeout_s=max(args.timeout, 20.0))
        except RecordingError as exc:
            if args.json:
                print(json.dumps({"ok": False, "error": "failed", "message": str(exc), "exit_code": EXIT_FAILED}))
            else:
                console.print(f"record {args.host} FAILED: {exc}", style="bold red", markup=False, highlight=False)
            return EXIT_FAILED
    rows = write_csv(rec, args.out)
    summary = {"ok": True, "host": rec.host, "reason": rec.reason, "axis": rec.axis, "detail": rec.detail,
               "trigger_cycle": rec.trigger_cycle, "first_cycle": rec.first_cycle, "cycles": rec.n_cycles,
               "seconds": rec.n_cycles * rec.cycle_us / 1e6, "axes": rec.axes, "rows": rows, "out": args.out}
    if args.json:
        print(json.dumps(summary, indent=1))
    else:
        console.print(f"{rec.host}: {rec.n_cycles} cycles ({summary['seconds']:g} s) of {len(rec.axes)} drive(s), "
                      f"{rec.reason}{' ' + rec.axis if rec.axis else ''}{': ' + rec.detail if rec.detail else ''}"
                      f" -> {args.out}", markup=False, highlight=False)
    return EXIT_OK


def _plot(args: argparse.Namespace, console: Console) -> int:
    from ..plot import plot_file  # matplotlib only for this verb
    try:
        drawn = plot_file(args.file, args.out, args.axis)
    except (OSError, ValueError) as exc:
        raise UsageError(f"plot {args.file}: {exc}") from None
    console.print(f"{args.file}: {', '.join(drawn)} -> {args.out}", markup=False, highlight=False)
    return EXIT_OK


def register(add_verb: Callable[..., argparse.ArgumentParser]) -> None:
    """Declare this module's verbs."""
    r = add_verb("record", "fetch a flight recording of an agent into a CSV file", _record, selectors=False)
    r.add_argument("host", help="agent host name")
    what = r.add_mutually_exclusive_group()
    what.add_argument("--last", type=positive_s, metavar="S", help="the last S seconds (default 10)")
    what.add_argument("--trigger", choices=tuple(TRIGGER_WORDS), help="the latest window frozen by a fault, "
                      "reflex, lost slave or request (last: any), or freeze one now")
    r.add_argument("--out", required=True, metavar="FILE.csv")
    p = add_verb("plot", "draw a flight recording CSV as a PNG (states, statusword bits, motion)", _plot,
                 selectors=False)
    p.add_argument("file", metavar="FILE.csv")
    p.add_argument("--out", required=True, metavar="FILE.png")
    p.add_argument("--axis", action="append", default=[], help="only this axis (repeat; default the first 8)")
