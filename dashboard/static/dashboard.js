// The dashboard's own page code: the fleet grouped by host, fed by server-sent events
// (/api/stream); an attention banner; command buttons with a confirmation when the dashboard
// sends commands. No third-party code; works offline.
"use strict";
const Dashboard = (() => {
  const hex = (v) => (v === null || v === undefined) ? "" : "0x" + v.toString(16).toUpperCase().padStart(4, "0");
  const cell = (text, cls) => { const td = document.createElement("td"); td.textContent = text ?? ""; if (cls) td.className = cls; return td; };
  const rowId = (p, h, a) => p + "-" + h + (a === undefined ? "" : "-" + a);
  const driveUrl = (h, a) => "/drive/" + encodeURIComponent(h) + "/" + encodeURIComponent(a);
  const us = (v) => (v === undefined || v === null) ? "" : v.toFixed(0);
  // Buttons per drive when commands are on (the ops of POST /api/command/<op> that need no argument).
  const COMMANDS = [["enable", "Enable"], ["disable", "Disable"], ["quick_stop", "Quick stop"], ["fault_reset", "Fault reset"]];
  // Buttons per host (its selector host/*), for stopping a whole machine.
  const HOST_COMMANDS = [["quick_stop", "Quick stop"], ["disable", "Disable"]];
  // Arrival time of every drive row update, for the page-side latency measurement (bench).
  window.dashboardUpdates = {};

  function live(onChanges) {
    let version = 0;
    const conn = document.getElementById("conn");
    const es = new EventSource("/api/stream");
    es.onopen = () => { conn.textContent = "live"; conn.classList.add("live"); };
    es.onerror = () => { conn.textContent = "reconnecting"; conn.classList.remove("live"); };
    es.onmessage = (msg) => {
      const ch = JSON.parse(msg.data);
      version = ch.version;
      onChanges(ch);
    };
    return () => version;
  }

  // The state as the page shows it: a lost drive says lost, with its last known state.
  const stateText = (d) => d.display === "lost" ? "lost" + (d.last_state ? " (was " + d.last_state + ")" : "") : d.state;

  function eventItem(list, e) {
    const li = document.createElement("li");
    const t = new Date(e.time_ns / 1e6).toISOString().substring(11, 23);
    li.textContent = t + " " + e.host + "/" + e.axis + " " + e.kind + " " + e.detail +
      (e.kind === "transition" ? " -> " + e.to_state : "") + (e.error_code ? " " + hex(e.error_code) : "");
    if (e.alarm) li.className = "alarm";
    list.insertBefore(li, list.firstChild);
    while (list.children.length > 200) list.removeChild(list.lastChild);
  }

  // ---- commands: a confirmation dialog, then one POST ------------------------------------------

  function confirmThen(text, send) {
    const dlg = document.getElementById("confirm");
    document.getElementById("confirm-text").textContent = text;
    const yes = document.getElementById("confirm-yes"), no = document.getElementById("confirm-no");
    const close = () => { yes.onclick = null; no.onclick = null; dlg.close(); };
    yes.onclick = () => { close(); send(); };
    no.onclick = close;
    dlg.showModal();
  }

  function sendCommand(op, selector) {
    const out = document.getElementById("cmd-result");
    out.textContent = op + " " + selector + ": sending...";
    out.dataset.outcome = "pending";
    return fetch("/api/command/" + op, { method: "POST", headers: { "Content-Type": "application/json" },
                                          body: JSON.stringify({ selector: selector }) })
      .then((r) => r.json()).then((res) => {
        if (res.error) { out.textContent = op + " " + selector + ": " + res.error; out.dataset.outcome = "error"; return; }
        const parts = (res.results || []).map((r) => r.host + "/" + r.axis + " " + r.outcome + (r.error ? " (" + r.error + ")" : ""));
        out.textContent = op + " " + selector + ": " + (res.ok ? "ok" : "not ok") + " - " + parts.join(", ") +
          ((res.errors || []).length ? " - " + res.errors.join("; ") : "");
        out.dataset.outcome = res.ok ? "ok" : "failed";
      })
      .catch((err) => { out.textContent = op + " " + selector + ": " + err; out.dataset.outcome = "error"; });
  }

  function button(parent, op, label, question, selector) {
    const b = document.createElement("button");
    b.textContent = label;
    b.className = "cmd";
    b.dataset.op = op;
    b.onclick = () => confirmThen(question(), () => sendCommand(op, selector));
    parent.appendChild(b);
    return b;
  }

  // One drive's buttons; the question names the drive, its state and error code as shown now.
  function commandButtons(parent, d) {
    for (const [op, label] of COMMANDS) {
      button(parent, op, label, () => label + " " + d.host + "/" + d.axis + "?\nNow: " + stateText(d) +
        (d.error_code ? ", error " + hex(d.error_code) + " " + d.error_text : "") + ".", d.host + "/" + d.axis)
        .disabled = d.display === "offline";
    }
  }

  // ---- the fleet page ---------------------------------------------------------------------

  function fleetPage() {
    const container = document.getElementById("drives");
    const events = document.getElementById("events");
    const drives = new Map();   // "host/axis" -> row data
    const hosts = new Map();    // host -> agent row data
    const rows = new Map();     // element id -> tr
    let commands = false;

    function hostSection(host) {
      const id = rowId("host", host);
      let sec = document.getElementById(id);
      if (sec) return sec;
      sec = document.createElement("section");
      sec.id = id;
      sec.className = "host";
      sec.dataset.host = host;
      sec.innerHTML = '<h2><span class="hostname"></span> <span class="agent-state"></span> ' +
        '<a class="rec-link">flight recording</a></h2><div class="conflict"></div>' +
        '<table class="health"><thead><tr><th>agent</th><th>backend</th><th>cycles</th><th>cycle (us)</th>' +
        '<th>period p50 / p99 / max (us)</th><th>overruns</th><th>WKC errors</th><th>DC offset p50 / p99 (us)</th>' +
        '</tr></thead><tbody></tbody></table>' +
        '<table class="drives"><thead><tr><th>axis</th><th>state</th><th>mode</th><th>position</th><th>velocity</th>' +
        '<th>following error</th><th>error</th><th>AL</th><th>lease</th>' + (commands ? '<th>commands</th>' : '') +
        '</tr></thead><tbody></tbody></table>';
      sec.querySelector(".hostname").textContent = host;
      if (commands) {
        const span = document.createElement("span");
        span.className = "host-commands";
        for (const [op, label] of HOST_COMMANDS) {
          button(span, op, label + " all", () => label + " every drive of " + host + " (" + host + "/*)?", host + "/*");
        }
        sec.querySelector("h2").appendChild(span);
      }
      sec.querySelector(".rec-link").href = "/recording/" + encodeURIComponent(host);
      const before = Array.from(container.children).find((s) => s.dataset.host > host) || null;
      container.insertBefore(sec, before);
      return sec;
    }

    function agentRow(h) {
      hosts.set(h.host, h);
      const sec = hostSection(h.host);
      const id = rowId("agent", h.host);
      let tr = document.getElementById(id);
      if (!tr) { tr = document.createElement("tr"); tr.id = id; sec.querySelector(".health tbody").appendChild(tr); }
      const state = h.alive ? h.state : "offline";
      tr.replaceChildren(cell(state, "state"), cell(h.backend), cell(h.cycles, "num"), cell(h.cycle_us, "num"),
        cell(h.period_p50_us === undefined ? "" : us(h.period_p50_us) + " / " + us(h.period_p99_us) + " / " + us(h.period_max_us), "num"),
        cell(h.overruns, "num"), cell(h.wkc_errors, "num"),
        cell(h.dc_offset_p50_us === undefined || h.dc_offset_p50_us === null ? "" :
             us(h.dc_offset_p50_us) + " / " + us(h.dc_offset_p99_us), "num dc"));
      tr.dataset.state = state;
      const bad = !h.alive || state !== "running" || !!h.conflict;
      tr.className = h.alive ? (bad ? "alarm" : "") : "offline alarm";
      sec.dataset.state = state;
      sec.classList.toggle("offline", !h.alive);
      sec.classList.toggle("conflict", !!h.conflict);
      const badge = sec.querySelector(".agent-state");
      badge.textContent = state + (h.alive ? "" : (h.expected ? " (expected)" : ""));
      badge.dataset.state = state;
      sec.querySelector(".conflict").textContent = h.conflict ? "host-name conflict: " + h.conflict : "";
    }

    function driveRow(d) {
      drives.set(d.host + "/" + d.axis, d);
      const tbody = hostSection(d.host).querySelector(".drives tbody");
      const id = rowId("drive", d.host, d.axis);
      let tr = rows.get(id);
      if (!tr) {
        tr = document.createElement("tr");
        tr.id = id;
        rows.set(id, tr);
        tbody.insertBefore(tr, Array.from(tbody.children).find((r) => r.dataset.axis > d.axis) || null);
      }
      const axis = document.createElement("td");
      const a = document.createElement("a");
      a.href = driveUrl(d.host, d.axis);
      a.textContent = d.axis;
      axis.appendChild(a);
      const state = cell(stateText(d), "state");
      state.dataset.display = d.display;
      tr.replaceChildren(axis, state, cell(d.mode, "num"), cell(d.position, "num"), cell(d.velocity, "num"),
        cell(d.following_error, "num"), cell(d.error_code ? hex(d.error_code) + " " + d.error_text : "", "error"),
        cell(d.al_state), cell(d.lease_holder));
      if (commands) { const td = cell("", "commands"); commandButtons(td, d); tr.appendChild(td); }
      tr.dataset.host = d.host;
      tr.dataset.axis = d.axis;
      tr.dataset.state = d.state;
      tr.dataset.display = d.display;
      tr.dataset.lost = d.lost ? "1" : "0";
      tr.className = "d-" + d.display + (d.display === "offline" ? " offline" : "") + (d.alarm ? " alarm" : "");
      // Page clock at arrival minus the agent's clock at the status (one machine, or NTP): the lag.
      const at = performance.timeOrigin + performance.now();
      window.dashboardUpdates[d.host + "/" + d.axis] = { state: d.state, at: at, lag_ms: d.time_ns ? at - d.time_ns / 1e6 : null };
    }

    // What needs an operator: faults, lost drives, offline hosts (and drives), host-name conflicts.
    function attention() {
      const items = [];
      for (const h of hosts.values()) {
        if (h.conflict) items.push(["conflict", h.host, "host-name conflict on " + h.host + ": " + h.conflict]);
        if (!h.alive) items.push(["offline", h.host, "host " + h.host + " offline" + (h.expected ? " (expected in the fleet)" : "")]);
      }
      for (const d of drives.values()) {
        const ref = d.host + "/" + d.axis;
        if (d.display === "fault") items.push(["fault", ref, ref + " " + d.state + (d.error_code ? " " + hex(d.error_code) + " " + d.error_text : "")]);
        else if (d.display === "lost") items.push(["lost", ref, ref + " " + stateText(d)]);
        else if (d.display === "offline" && (hosts.get(d.host) || {}).alive) items.push(["offline", ref, ref + " not reported by its agent"]);
      }
      const banner = document.getElementById("attention");
      const list = banner.querySelector("ul");
      list.replaceChildren(...items.map(([kind, ref, text]) => {
        const li = document.createElement("li");
        li.dataset.kind = kind;
        li.dataset.ref = ref;
        li.className = kind;
        li.textContent = text;
        return li;
      }));
      banner.hidden = items.length === 0;
      banner.dataset.count = String(items.length);
      const n = drives.size, bad = Array.from(drives.values()).filter((d) => d.alarm).length;
      document.getElementById("summary").textContent = hosts.size + " host(s), " + n + " drive(s), " + bad + " need attention";
    }

    fetch("/api/fleet").then((r) => r.json()).then((f) => {
      commands = !!f.commands_enabled;
      const mode = document.getElementById("mode");
      mode.textContent = commands ? "commands as " + f.identity : "read-only";
      mode.dataset.commands = commands ? "1" : "0";
      live((ch) => {
        ch.hosts.forEach(agentRow);
        ch.drives.forEach(driveRow);
        ch.events.forEach((e) => eventItem(events, e));
        attention();
      });
    });
  }

  return { fleetPage, live, eventItem, hex, driveUrl, stateText, commandButtons };
})();
