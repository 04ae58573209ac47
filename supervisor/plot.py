"""``drivectl plot``: a flight recording (CSV) as a PNG, drawn with matplotlib (Agg, no display).

Per axis two panels sharing the time axis: position (actual and target) and velocity over the
CiA 402 states drawn as coloured bands; below, the statusword (0x6041) bits as a raster, one row
per named bit. The trigger, when the recording has one, is a vertical line.
"""

from __future__ import annotations

from pathlib import Path
from typing import Sequence

from bus_agent.cia402.states import State, StatuswordBit

from .recordings import Table, read_csv

#: Band colour of every state (faults red, enabled green, the way up in blues).
STATE_COLOURS = {
    State.NOT_READY_TO_SWITCH_ON.value: "#dddddd",
    State.SWITCH_ON_DISABLED.value: "#eeeeee",
    State.READY_TO_SWITCH_ON.value: "#dbe9f6",
    State.SWITCHED_ON.value: "#b9d4ee",
    State.OPERATION_ENABLED.value: "#c9ecc9",
    State.QUICK_STOP_ACTIVE.value: "#ffe2a8",
    State.FAULT_REACTION_ACTIVE.value: "#ffb3a8",
    State.FAULT.value: "#ff8080",
    State.UNKNOWN.value: "#bbbbbb",
}
#: At most this many axes in one picture (``--axis`` picks others).
MAX_AXES = 8


def state_bands(times: Sequence[float], states: Sequence[str]) -> list[tuple[float, float, str]]:
    """Runs of one state: (start time, end time, state). Pure."""
    bands: list[tuple[float, float, str]] = []
    for t, s in zip(times, states):
        if bands and bands[-1][2] == s:
            bands[-1] = (bands[-1][0], t, s)
        else:
            bands.append((t, t, s))
    return bands


def plot_recording(table: Table, out: str | Path, axes: Sequence[str] = ()) -> list[str]:
    """Draw ``table`` into ``out`` (PNG); returns the axes drawn. Raises ValueError."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt
    from matplotlib.patches import Patch

    chosen = list(axes) or table.axes[:MAX_AXES]
    unknown = [a for a in chosen if a not in table.axes]
    if unknown:
        raise ValueError(f"axis {', '.join(unknown)} not in the recording (axes: {', '.join(table.axes)})")
    if not chosen:
        raise ValueError("the recording has no rows")
    bits = [b for b in StatuswordBit]
    fig, panels = plt.subplots(2 * len(chosen), 1, figsize=(12, 4.2 * len(chosen)), sharex=True,
                               gridspec_kw={"height_ratios": [3, 1.4] * len(chosen)}, squeeze=False)
    trigger = int(table.meta.get("trigger_cycle", "0") or 0)
    for k, axis in enumerate(chosen):
        t = table.column(axis, "time_s")
        cycles = table.column(axis, "cycle")
        states = table.column(axis, "state")
        top, raster = panels[2 * k][0], panels[2 * k + 1][0]
        for start, end, s in state_bands(t, states):
            top.axvspan(start, end if end > start else start + 1e-3, color=STATE_COLOURS.get(s, "#bbbbbb"), lw=0)
        top.plot(t, table.column(axis, "position"), color="#1f4e9a", lw=1.2, label="position 0x6064")
        if table.rows and table.rows[0].get("target_position") is not None:
            top.plot(t, table.column(axis, "target_position"), color="#1f4e9a", lw=0.8, ls="--",
                     label="target 0x607A")
        vel = top.twinx()
        vel.plot(t, table.column(axis, "velocity"), color="#c05000", lw=1.0, label="velocity 0x606C")
        vel.set_ylabel("velocity")
        top.set_ylabel("position")
        title = f"{table.meta.get('host', '?')}/{axis}"
        if table.meta.get("reason") and table.meta.get("reason") != "last":
            title += f" - {table.meta['reason']}: {table.meta.get('detail', '')}"
        top.set_title(title, fontsize=10, loc="left")
        seen = [s for s in dict.fromkeys(states)]
        handles = [Patch(color=STATE_COLOURS.get(s, "#bbbbbb"), label=s) for s in seen]
        lines = top.get_lines() + vel.get_lines()
        top.legend(handles=[*lines, *handles], fontsize=7, loc="upper left", ncol=2)
        sw = table.column(axis, "statusword")
        matrix = [[(w >> b.value) & 1 for w in sw] for b in bits]
        raster.imshow(matrix, aspect="auto", interpolation="nearest", cmap="Greys", vmin=0, vmax=1,
                      extent=(t[0], t[-1] if len(t) > 1 else t[0] + 1e-3, len(bits) - 0.5, -0.5))
        raster.set_yticks(range(len(bits)), [b.name.lower().replace("operation_mode_specific", "oms")
                                             for b in bits], fontsize=6)
        raster.set_ylabel("0x6041", fontsize=8)
        if trigger and trigger in cycles:
            tt = t[cycles.index(trigger)]
            for p in (top, raster):
                p.axvline(tt, color="red", lw=1.0)
    panels[-1][0].set_xlabel("time since the first recorded cycle (s)")
    fig.tight_layout()
    fig.savefig(out, dpi=90)
    plt.close(fig)
    return chosen


def plot_file(csv_path: str | Path, out: str | Path, axes: Sequence[str] = ()) -> list[str]:
    """``drivectl plot FILE --out PNG``: read the CSV, draw it."""
    return plot_recording(read_csv(csv_path), out, axes)
