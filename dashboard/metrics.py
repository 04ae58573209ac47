"""Prometheus metrics of the fleet, from the dashboard's view, with the official client.

Naming follows the Prometheus conventions: a ``drives_`` prefix, base units (seconds), ``_total``
for counters, labels ``host``/``axis`` (and ``state``, ``op``, ``outcome`` from closed or small
vocabularies; no per-request labels). A custom collector reads :class:`~dashboard.view.FleetView`
at scrape time, so a drive or agent that disappears leaves no stale series.

Per drive: ``drives_drive_state{host,axis,state}`` (1 for the current CiA 402 state, 0 for the
others), ``drives_drive_error_code``, ``drives_drive_lost``, ``drives_drive_al_state{...,al_state}``,
``drives_drive_following_error_increments{host,axis,source}`` when known (source ``0x60F4``: the
drive's own, mapped; ``agent``: 0x607A written last minus 0x6064, cyclic synchronous position in
Operation enabled; see :func:`dashboard.view.following_error`), ``drives_drive_target_clamps_total``
(cycles the agent's output stage limited a target, docs/motion.md). Position units are the drive's
increments, not an SI unit: the suffix names them.
Per agent: ``drives_agent_up``, ``drives_cycle_period_seconds{host,quantile}`` (0.5, 0.99, 1 = max
of the agent's statistics window), ``drives_cycles_total``, ``drives_cycle_overruns_total``,
``drives_cycle_wkc_errors_total``, ``drives_commands_total{host,op,outcome}``,
``drives_dc_offset_seconds{host,quantile}`` (0.5, 0.99: frame-to-SYNC0 offset, only while a
slave of the agent runs DC SYNC0). Per fleet:
``drives_agents_up``, ``drives_agents_expected_offline``, ``drives_drives{state}``.
"""

from __future__ import annotations

from typing import Iterator

from prometheus_client import CollectorRegistry, generate_latest
from prometheus_client.core import CounterMetricFamily, GaugeMetricFamily, Metric
from prometheus_client.registry import Collector

from schemas.messages import AL_STATES, DRIVE_STATES

from .view import FleetView, dc_offset_us, following_error, summary

CONTENT_TYPE = "text/plain; version=0.0.4; charset=utf-8"


class FleetCollector(Collector):
    """Yields the metric families of one :class:`FleetView` at every scrape."""

    def __init__(self, view: FleetView) -> None:
        self.view = view

    def collect(self) -> Iterator[Metric]:
        statuses = self.view.statuses()
        agents = self.view.agents()
        state = GaugeMetricFamily("drives_drive_state", "CiA 402 state of the drive (1 = current)",
                                  labels=["host", "axis", "state"])
        error = GaugeMetricFamily("drives_drive_error_code", "0x603F error code (0 = none)", labels=["host", "axis"])
        lost = GaugeMetricFamily("drives_drive_lost", "1 when the slave does not answer", labels=["host", "axis"])
        al = GaugeMetricFamily("drives_drive_al_state", "EtherCAT AL state of the slave (1 = current)",
                               labels=["host", "axis", "al_state"])
        ferr = GaugeMetricFamily("drives_drive_following_error_increments", "following error (0x60F4 from the "
                                 "drive, else target written last minus 0x6064 from the agent in CSP), when known",
                                 labels=["host", "axis", "source"])
        clamps = CounterMetricFamily("drives_drive_target_clamps", "cycles in which the agent's output stage "
                                     "limited a target to the axis velocity/acceleration limits", labels=["host", "axis"])
        for (host, axis), st in sorted(statuses.items()):
            for s in DRIVE_STATES:
                state.add_metric([host, axis, s], 1.0 if st.state == s else 0.0)
            error.add_metric([host, axis], st.error_code)
            lost.add_metric([host, axis], 1.0 if st.lost else 0.0)
            for a in AL_STATES:
                al.add_metric([host, axis, a], 1.0 if st.al_state == a else 0.0)
            fe = following_error(st)
            if fe is not None:
                ferr.add_metric([host, axis, fe[1]], fe[0])
            clamps.add_metric([host, axis], getattr(st, "target_clamps", 0))
        yield from (state, error, lost, al, ferr, clamps)

        up = GaugeMetricFamily("drives_agent_up", "1 while the agent's liveliness token is present", labels=["host"])
        period = GaugeMetricFamily("drives_cycle_period_seconds", "measured cycle period over the agent's "
                                   "statistics window (quantile 1 = maximum)", labels=["host", "quantile"])
        cycles = CounterMetricFamily("drives_cycles", "cycles run since the agent started", labels=["host"])
        overruns = CounterMetricFamily("drives_cycle_overruns", "cycles started more than one period late",
                                       labels=["host"])
        wkc = CounterMetricFamily("drives_cycle_wkc_errors", "cycles with an unexpected working counter",
                                  labels=["host"])
        commands = CounterMetricFamily("drives_commands", "command replies by op and outcome",
                                       labels=["host", "op", "outcome"])
        dc_offset = GaugeMetricFamily("drives_dc_offset_seconds", "frame-to-SYNC0 offset (time since SYNC0 as the "
                                      "frame passed) over the agent's statistics window, while DC runs",
                                      labels=["host", "quantile"])
        for host, (alive, ag) in sorted(agents.items()):
            up.add_metric([host], 1.0 if alive else 0.0)
            if ag is None:
                continue
            for q, v in (("0.5", ag.period_p50_us), ("0.99", ag.period_p99_us), ("1", ag.period_max_us)):
                period.add_metric([host, q], v / 1e6)
            cycles.add_metric([host], ag.cycles)
            overruns.add_metric([host], ag.overruns)
            wkc.add_metric([host], ag.wkc_errors)
            for key, n in sorted((getattr(ag, "commands", {}) or {}).items()):
                op, _, outcome = key.partition(".")
                commands.add_metric([host, op, outcome], n)
            dc = dc_offset_us(ag)
            if dc is not None:
                for q, v in zip(("0.5", "0.99"), dc):
                    dc_offset.add_metric([host, q], v / 1e6)
        yield from (up, period, cycles, overruns, wkc, commands, dc_offset)

        snap = self.view.snapshot()
        counts = summary(snap["drives"], snap["hosts"])
        agents_up = GaugeMetricFamily("drives_agents_up", "agents alive")
        agents_up.add_metric([], counts["agents_up"])
        offline = GaugeMetricFamily("drives_agents_expected_offline", "expected agents (fleet file) not alive")
        offline.add_metric([], counts["agents_expected_offline"])
        by_state = GaugeMetricFamily("drives_drives", "drives by state ('offline': expected, not reported)",
                                     labels=["state"])
        for k, n in counts["by_state"].items():
            by_state.add_metric([k], n)
        yield from (agents_up, offline, by_state)


def registry_for(view: FleetView) -> CollectorRegistry:
    """A registry holding only the fleet collector (no process metrics of the dashboard itself)."""
    reg = CollectorRegistry(auto_describe=False)
    reg.register(FleetCollector(view))
    return reg


def render(registry: CollectorRegistry) -> bytes:
    """The text exposition format."""
    return generate_latest(registry)
