"""Rows of the benchmark summary for the fleet side: the supervisor, operator trust, the
cross-host reflex, the reply path, security and drives-twin (pure, as :mod:`bench.summary`, whose
row machinery they use; the cycle-side rows are in :mod:`bench.summary` itself)."""

from __future__ import annotations

from typing import Any, Mapping

from bench.summary import Target, _ratio, at_most, picked


# ---- bench_supervisor -----------------------------------------------------------------------------

#: Fan-in: a drive enabled and disabled changes state at least twice (into operation_enabled and
#: back to switch_on_disabled); intermediate states may share one publication.
FANIN_CHANGES_PER_DRIVE_MIN = 2
#: A killed agent is reported gone within the Zenoh link lease (deploy/router.json5).
LINK_LEASE_S = 3.0
#: Two-phase enable of 4 x 16 drives: the supervisor's and the network's share (wall time minus the
#: slowest drive's own transition time) at most this many bare zenoh gets (issue 13).
SUPERVISOR_ENABLE_SIZE = "4x16"
SUPERVISOR_ENABLE_OVER_BARE_MAX = 10.0


def supervisor_figures(r: Mapping[str, Any]) -> dict[str, Any]:
    sizes = []
    for s in r["sizes"]:
        bare = s.get("get_rtt_bare", {})
        row = {"agents": s["agents"], "drives": s["drives"], "cycle_us": s["cycle_us"],
               "enable_wall_s_median": s.get("enable_wall_s_median"),
               "enable_overhead_s_median": s.get("enable_overhead_s_median"),
               "disable_wall_s_median": s.get("disable_wall_s_median"),
               "disable_overhead_s_median": s.get("disable_overhead_s_median"),
               "enable_cpu_ms_median": s.get("enable_cpu_ms_median"),
               "enable_cpu_ms_by_thread_median": s.get("enable_cpu_ms_by_thread_median"),
               "enable_statuses_median": s.get("enable_statuses_median"),
               "load_avg_1min_at_start": s.get("load_avg_1min_at_start"),
               "get_rtt_bare_ms": {k: bare.get(k) for k in ("p50_ms", "p99_ms")},
               "enable_overhead_over_bare_get_p50": _ratio((s.get("enable_overhead_s_median") or 0) * 1e3 or None,
                                                           bare.get("p50_ms")),
               "rounds_ok": sum(1 for x in s.get("rounds", []) if x["enable"]["ok"] and x["disable"]["ok"]),
               "rounds": len(s.get("rounds", []))}
        if "departure" in s:
            row["departure"] = s["departure"]
        if "fanin" in s:
            row["fanin"] = {k: s["fanin"].get(k) for k in (
                "drives_seen", "status_received", "state_changes_seen", "missed_by_seq", "supervisor_missed_by_seq",
                "cpu_pct_of_one_core", "commands_ok")}
        sizes.append(row)
    return {"sizes": sizes}


def supervisor_headline(r: Mapping[str, Any]) -> str:
    parts = []
    for s in r["sizes"]:
        bare = s.get("get_rtt_bare", {})
        text = (f"{_size(s)}: enable wall/overhead {_s(s.get('enable_wall_s_median'))}/"
                f"{_s(s.get('enable_overhead_s_median'))}, disable {_s(s.get('disable_wall_s_median'))}/"
                f"{_s(s.get('disable_overhead_s_median'))}, bare get p50 {bare.get('p50_ms')} ms")
        d = s.get("departure")
        if d:
            text += (f"; {d['reported']}/{d['killed_agents']} killed agents reported gone after "
                     f"{d['first_ms']}-{d['last_ms']} ms")
        f = s.get("fanin")
        if f:
            text += (f"; fan-in {f.get('status_received')} status, {f.get('state_changes_seen')} state changes, "
                     f"{f.get('missed_by_seq')} missed, watcher {f.get('cpu_pct_of_one_core')} % of a core")
        parts.append(text)
    return "; ".join(parts)


def _s(v: float | None) -> str:
    return "-" if v is None else f"{v * 1e3:.1f} ms" if v < 1 else f"{v:.2f} s"


def _size(s: Mapping[str, Any]) -> str:
    """``AxD``, and the transport unless plain TCP."""
    transport = s.get("transport", "tcp")
    return f"{s['agents']}x{s['drives'] // max(1, s['agents'])}" + ("" if transport == "tcp" else f" {transport}")


def supervisor_targets(r: Mapping[str, Any]) -> list[Target]:
    out = []
    for s in r["sizes"]:
        size = _size(s)
        rounds = s.get("rounds", [])
        ok = sum(1 for x in rounds if x["enable"]["ok"] and x["disable"]["ok"])
        out.append(Target(f"{size}: enable/disable rounds ok", f"{ok}/{len(rounds)}", "all", bool(rounds) and
                          ok == len(rounds)))
        if size == SUPERVISOR_ENABLE_SIZE:
            bare = (s.get("get_rtt_bare") or {}).get("p50_ms")
            overhead = s.get("enable_overhead_s_median")
            out.append(at_most(f"{size}: two-phase enable overhead / bare get (p50)",
                               _ratio(overhead * 1e3 if overhead is not None else None, bare),
                               SUPERVISOR_ENABLE_OVER_BARE_MAX, " x"))
        d = s.get("departure")
        if d is not None:
            out.append(Target(f"{size}: killed agents reported gone (ms)", d["last_ms"],
                              f"all {d['killed_agents']} within the {LINK_LEASE_S:g} s link lease",
                              d["reported"] == d["killed_agents"] and d["last_ms"] is not None
                              and d["last_ms"] <= LINK_LEASE_S * 1e3))
        f = s.get("fanin")
        if f is None:
            continue
        need = FANIN_CHANGES_PER_DRIVE_MIN * s["drives"]
        measured = {k: f.get(k) for k in ("commands_ok", "drives_seen", "state_changes_seen", "missed_by_seq",
                                          "supervisor_missed_by_seq")}
        met = (f.get("commands_ok") is True and f.get("drives_seen") == s["drives"]
               and (f.get("state_changes_seen") or 0) >= need
               and f.get("missed_by_seq") == 0 and f.get("supervisor_missed_by_seq") == 0)
        out.append(Target(f"{size}: status fan-in", measured,
                          f"commands ok, every drive seen, >= {need} state changes, 0 missed", met))
    return out


# ---- bench_trust --------------------------------------------------------------------------------

#: The audit trail may add at most this much to the gateway's own CPU work per command (it runs
#: on the command and publish threads, never on the cycle).
AUDIT_RATIO_MAX = 1.0


trust_figures = picked("command_existing_us", "command_audit_us", "audit_ratio", "status_encode_us", "error_text_us",
                       "error_text_ratio", "loadavg_start")


def trust_headline(r: Mapping[str, Any]) -> str:
    return (f"16-drive command: audit {r.get('command_audit_us')} us next to the gateway's "
            f"{r.get('command_existing_us')} us ({r.get('audit_ratio')}x); error text {r.get('error_text_us')} us "
            f"per status next to {r.get('status_encode_us')} us encoding ({r.get('error_text_ratio')}x)")


def trust_targets(r: Mapping[str, Any]) -> list[Target]:
    ratio = r.get("audit_ratio")
    return [at_most("audit trail / existing per-command gateway work", ratio, AUDIT_RATIO_MAX)]


# ---- the cross-host reflex and the reply path (issue 13) -------------------------------------------

#: Cross-host group reflex, fault on h1 -> h2's member leaving operation_enabled (ms).
REFLEX_P50_MS_MAX = 2.0
REFLEX_P99_MS_MAX = 3.0


def reflex_figures(r: Mapping[str, Any]) -> dict[str, Any]:
    nxt = r.get("next_cycle") or {}
    return {**{k: r.get(k) for k in ("rounds", "fault_to_reflex", "fault_to_leave", "reflex_to_leave",
                                     "fault_to_status_in_sup", "bare_put", "ratios", "n_failures")},
            "next_cycle": {k: nxt.get(k) for k in ("fault_to_reflex", "fault_to_leave", "reflex_to_leave",
                                                   "n_failures")} if nxt else None}


def reflex_headline(r: Mapping[str, Any]) -> str:
    lv, rf, b = r.get("fault_to_leave") or {}, r.get("fault_to_reflex") or {}, r.get("bare_put") or {}
    rl = r.get("reflex_to_leave") or {}
    nl = (r.get("next_cycle") or {}).get("fault_to_leave") or {}
    return (f"fault on h1 -> h2's member leaves operation_enabled p50/p99 {lv.get('p50_ms')}/{lv.get('p99_ms')} ms "
            f"(reflex applied {rf.get('p50_ms')}/{rf.get('p99_ms')} ms, then {rl.get('p50_ms')}/{rl.get('p99_ms')} ms "
            f"to the drive seen leaving), bare put h1 -> h2 across the routers "
            f"{b.get('p50_ms')}/{b.get('p99_ms')} ms ({r.get('n_failures')} failed rounds)"
            + (f"; without the express exchange {nl.get('p50_ms')}/{nl.get('p99_ms')} ms" if nl else ""))


def reflex_targets(r: Mapping[str, Any]) -> list[Target]:
    lv = r.get("fault_to_leave") or {}
    return [at_most("cross-host reflex p50 (ms)", lv.get("p50_ms"), REFLEX_P50_MS_MAX),
            at_most("cross-host reflex p99 (ms)", lv.get("p99_ms"), REFLEX_P99_MS_MAX),
            Target("reflex rounds without failure", r.get("n_failures"), 0, r.get("n_failures") == 0)]


def replies_figures(r: Mapping[str, Any]) -> dict[str, Any]:
    return {"drives": r.get("drives"), "loadavg_start": r.get("loadavg_start")}


def replies_headline(r: Mapping[str, Any]) -> str:
    parts = []
    for n, f in (r.get("drives") or {}).items():
        parts.append(f"{n} drives: gateway {f['gateway_us']} us ({f['gateway_over_bare']}x bare msgpack), collector "
                     f"{f['collector_us']} us ({f['collector_over_bare']}x), publish pass {f['publish_pass_us']} us "
                     f"({f['publish_pass_over_bare']}x)"
                     + (f", status decode {f['status_decode_us']} us ({f['status_decode_over_bare']}x)"
                        if "status_decode_us" in f else ""))
    return "CPU per command: " + "; ".join(parts)


# ---- bench_security ------------------------------------------------------------------------------

security_figures = picked("enable", "fanin", "summary")


def security_headline(r: Mapping[str, Any]) -> str:
    e, f, sm = r.get("enable", {}), r.get("fanin", {}), r.get("summary", {})
    tcp, tls = e.get("tcp", {}), e.get("tls", {})
    return (f"enable 16 drives p50 tcp {tcp.get('wall_ms_p50')} / tls {tls.get('wall_ms_p50')} ms "
            f"({sm.get('enable_wall_p50_ratio')} x); fan-in {f.get('drives')} drives: missed {sm.get('fanin_missed')}, "
            f"watcher CPU per message {sm.get('fanin_watcher_cpu_per_msg_ratio')} x (min-of-N "
            f"{sm.get('fanin_watcher_cpu_per_msg_ratio_min_of_n')} x, paired rounds p10-p90 "
            f"{sm.get('fanin_watcher_cpu_per_msg_ratio_paired_p10_p90')}), router CPU {sm.get('fanin_router_cpu_ratio')} x")


def security_targets(r: Mapping[str, Any]) -> list[Target]:
    sm = r.get("summary", {})
    limit = sm.get("target_ratio_max", 1.2)
    out = []
    for key, name in (("enable_wall_p50_ratio", "TLS+ACL / TCP: 16-drive enable wall p50"),
                      ("fanin_watcher_cpu_per_msg_ratio", "TLS+ACL / TCP: fan-in watcher CPU per message")):
        v = sm.get(key)
        out.append(at_most(name, v, limit))
    missed = sm.get("fanin_missed", {})
    out.append(Target("fan-in missed, both transports", missed, 0,
                      bool(missed) and all(m == 0 for m in missed.values())))
    return out


# ---- bench_twin -----------------------------------------------------------------------------------

#: drives-twin of 10 simulated hosts (2 drives each): ready, every drive answering, within this.
TWIN_READY_10_S_MAX = 10.0
#: The twin's own process at rest (link relays, its supervisor, the child monitor), 10 hosts,
#: percent of one core: what the twin adds to the processes it runs.
TWIN_OWN_CPU_PCT_MAX = 5.0

twin_figures = picked("axes_per_host", "sizes", "loadavg_start", "loadavg_end")


def _twin_size(r: Mapping[str, Any], n: str) -> tuple[Mapping[str, Any], Mapping[str, Any]]:
    size = (r.get("sizes") or {}).get(n) or {}
    return size.get("twin") or {}, size.get("bare") or {}


def twin_headline(r: Mapping[str, Any]) -> str:
    parts = []
    for n in r.get("sizes") or {}:
        twin, bare = _twin_size(r, n)
        parts.append(f"{n} hosts: ready {twin.get('ready_s')} s (bare processes {bare.get('ready_s')} s), CPU at rest "
                     f"{twin.get('cpu_pct_total')} % (bare {bare.get('cpu_pct_total')} %; the twin's own process "
                     f"{twin.get('cpu_pct_twin_process')} %)")
    return "; ".join(parts)


def twin_targets(r: Mapping[str, Any]) -> list[Target]:
    twin10, _ = _twin_size(r, "10")
    left = [(_twin_size(r, n)[0]).get("left_after_stop") for n in r.get("sizes") or {}]
    return [at_most("drives-twin ready, 10 hosts", twin10.get("ready_s"), TWIN_READY_10_S_MAX, " s"),
            at_most("the twin's own process at rest, 10 hosts, % of a core", twin10.get("cpu_pct_twin_process"),
                    TWIN_OWN_CPU_PCT_MAX),
            at_most("processes left after SIGTERM, every size", max(left) if left and None not in left else None, 0)]


# ---- bench.chaos ----------------------------------------------------------------------------------


def chaos_figures(r: Mapping[str, Any]) -> dict[str, Any]:
    return {"seed": r["seed"], "seconds": r["seconds"], "backend": r["backend"], "counts": r["counts"],
            "monitors": {n: {k: m[k] for k in ("checked", "skipped", "violations")} for n, m in r["monitors"].items()},
            "violations_total": r["violations_total"], "harness_errors": len(r.get("harness_errors") or [])}


def chaos_headline(r: Mapping[str, Any]) -> str:
    c = r["counts"]
    broken = [f"{n} {m['violations']}" for n, m in r["monitors"].items() if m["violations"]]
    return (f"seed {r['seed']}, {r['seconds']:g} s ({r['backend']}): {c['commands']} commands ({c['malformed']} "
            f"malformed), {c['faults_injected']} injections ({', '.join(f'{k} {v}' for k, v in c['injections'].items())}), "
            f"{sum(m['checked'] for m in r['monitors'].values())} cases checked by {len(r['monitors'])} monitors; "
            f"violations: {', '.join(broken) if broken else 'none'}")


def chaos_targets(r: Mapping[str, Any]) -> list[Target]:
    broken = ", ".join(f"{n} {m['violations']}" for n, m in r["monitors"].items() if m["violations"])
    return [at_most("violations, every monitor", r["violations_total"], 0, note=broken),
            at_most("harness errors (a part the twin could not bring back)", len(r.get("harness_errors") or []), 0)]


# ---- bench_opcua ----------------------------------------------------------------------------------

#: Issue 25: an OPC UA value changes within 500 ms of the status it comes from (worst round).
OPCUA_CHANGE_MS_MAX = 500.0
#: drives-opcua at rest with 1024 drives (every drive's heartbeat), % of one core.
OPCUA_CPU_PCT_MAX = 25.0
#: Its CPU per status taken in at rest (the Fleet's decoding included).
OPCUA_CPU_US_PER_STATUS_MAX = 250.0


opcua_figures = picked("drives", "fleet", "publishing_interval_ms", "server_ready_s", "statuses_per_s_idle",
                       "server_cpu_idle_pct", "server_cpu_us_per_status", "server_cpu_changes_pct",
                       "fault_to_client_ms", "fault_to_subscriber_ms", "client_over_subscriber_p50", "missed")


def opcua_headline(r: Mapping[str, Any]) -> str:
    c, z = r.get("fault_to_client_ms") or {}, r.get("fault_to_subscriber_ms") or {}
    return (f"{r.get('drives')} drives: fault to OPC UA client p50/max {c.get('p50')}/{c.get('max')} ms (a plain "
            f"Fleet subscriber {z.get('p50')}/{z.get('max')} ms, x{r.get('client_over_subscriber_p50')}; publishing "
            f"interval {r.get('publishing_interval_ms')} ms); server CPU {r.get('server_cpu_idle_pct')} % at rest "
            f"({r.get('statuses_per_s_idle')} statuses/s, {r.get('server_cpu_us_per_status')} us each)")


def opcua_targets(r: Mapping[str, Any]) -> list[Target]:
    return [at_most("fault to the OPC UA client's data change, max", (r.get("fault_to_client_ms") or {}).get("max"),
                    OPCUA_CHANGE_MS_MAX, " ms"),
            at_most("drives-opcua CPU at rest, % of one core", r.get("server_cpu_idle_pct"), OPCUA_CPU_PCT_MAX),
            at_most("drives-opcua CPU per status taken in", r.get("server_cpu_us_per_status"),
                    OPCUA_CPU_US_PER_STATUS_MAX, " us"),
            at_most("rounds whose fault never reached the client", r.get("missed"), 0)]
