// The dashboard's own page code: a live table fed by server-sent events (/api/stream) and
// small canvas plots. No third-party code; works offline.
"use strict";
const Dashboard = (() => {
  const hex = (v) => (v === null || v === undefined) ? "" : "0x" + v.toString(16).toUpperCase().padStart(4, "0");
  const cell = (text, cls) => { const td = document.createElement("td"); td.textContent = text ?? ""; if (cls) td.className = cls; return td; };
  const rowId = (p, h, a) => p + "-" + h + (a === undefined ? "" : "-" + a);
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

  function driveRow(tbody, d, rows) {
    const id = rowId("drive", d.host, d.axis);
    let tr = rows.get(id);
    if (!tr) {
      tr = document.createElement("tr");
      tr.id = id;
      rows.set(id, tr);
      if (!tbody.lastElementChild || tbody.lastElementChild.id < id) tbody.appendChild(tr);
      else tbody.insertBefore(tr, Array.from(tbody.children).find((r) => r.id > id) || null);
    }
    tr.replaceChildren(
      (() => { const td = cell(d.host); return td; })(),
      (() => { const td = document.createElement("td"); const a = document.createElement("a");
               a.href = "/drive/" + encodeURIComponent(d.host) + "/" + encodeURIComponent(d.axis);
               a.textContent = d.axis; td.appendChild(a); return td; })(),
      cell(d.state, "state"), cell(d.mode, "num"), cell(d.position, "num"), cell(d.following_error, "num"),
      cell(d.error_code ? hex(d.error_code) + " " + d.error_text : ""), cell(d.al_state),
      cell(d.lost ? "LOST" : ""), cell(d.lease_holder));
    tr.dataset.state = d.state;
    tr.dataset.lost = d.lost ? "1" : "0";
    tr.className = d.state === "offline" ? "offline alarm" : (d.alarm ? "alarm" : "");
    // Page clock at arrival minus the agent's clock at the status (one machine, or NTP): the lag.
    const at = performance.timeOrigin + performance.now();
    window.dashboardUpdates[d.host + "/" + d.axis] = { state: d.state, at: at, lag_ms: d.time_ns ? at - d.time_ns / 1e6 : null };
  }

  function agentRow(tbody, h) {
    const id = rowId("agent", h.host);
    let tr = document.getElementById(id);
    if (!tr) { tr = document.createElement("tr"); tr.id = id; tbody.appendChild(tr); }
    const us = (v) => v === undefined ? "" : v.toFixed(0);
    tr.replaceChildren(cell(h.host), cell(h.alive ? h.state : "offline", "state"), cell(h.backend),
      cell(h.period_p50_us === undefined ? "" : us(h.period_p50_us) + " / " + us(h.period_p99_us) + " / " + us(h.period_max_us), "num"),
      cell(h.overruns, "num"), cell(h.wkc_errors, "num"),
      cell(h.dc_offset_p50_us === undefined || h.dc_offset_p50_us === null ? "" :
           us(h.dc_offset_p50_us) + " / " + us(h.dc_offset_p99_us), "num dc"));
    tr.dataset.state = h.alive ? h.state : "offline";
    tr.className = h.alive ? (h.state === "running" ? "" : "alarm") : "offline alarm";
  }

  function eventItem(list, e) {
    const li = document.createElement("li");
    const t = new Date(e.time_ns / 1e6).toISOString().substring(11, 23);
    li.textContent = t + " " + e.host + "/" + e.axis + " " + e.kind + " " + e.detail +
      (e.kind === "transition" ? " -> " + e.to_state : "") + (e.error_code ? " " + hex(e.error_code) : "");
    if (e.alarm) li.className = "alarm";
    list.insertBefore(li, list.firstChild);
    while (list.children.length > 200) list.removeChild(list.lastChild);
  }

  function summaryText(drives) {
    const rows = Array.from(drives.children);
    const alarms = rows.filter((r) => r.classList.contains("alarm")).length;
    return rows.length + " drive(s), " + alarms + " need attention";
  }

  function fleetPage() {
    const drives = document.querySelector("#drives tbody");
    const agents = document.querySelector("#agents tbody");
    const events = document.getElementById("events");
    const rows = new Map();
    live((ch) => {
      ch.hosts.forEach((h) => agentRow(agents, h));
      // Rows arrive sorted on the first message: appending keeps the table sorted cheaply.
      ch.drives.sort((a, b) => (a.host + "/" + a.axis < b.host + "/" + b.axis ? -1 : 1));
      ch.drives.forEach((d) => driveRow(drives, d, rows));
      ch.events.forEach((e) => eventItem(events, e));
      document.getElementById("summary").textContent = summaryText(drives);
    });
  }

  // ---- plots ------------------------------------------------------------------------------

  function plot(canvas, t, series, marker) {
    const ctx = canvas.getContext("2d");
    const W = canvas.width, H = canvas.height, left = 70, gap = 8;
    ctx.clearRect(0, 0, W, H);
    ctx.font = "11px sans-serif";
    if (!t.length) { ctx.fillText("no samples yet", left, 20); return; }
    const t0 = t[0], t1 = Math.max(t[t.length - 1], t0 + 1e-3);
    const x = (v) => left + (v - t0) / (t1 - t0) * (W - left - 10);
    const band = (H - gap * (series.length + 1)) / series.length;
    series.forEach((s, k) => {
      const top = gap + k * (band + gap);
      let lo = Math.min(...s.values), hi = Math.max(...s.values);
      if (hi === lo) { hi += 1; lo -= 1; }
      const y = (v) => top + band - (v - lo) / (hi - lo) * band;
      ctx.strokeStyle = "#ccc"; ctx.strokeRect(left, top, W - left - 10, band);
      ctx.fillStyle = "#333"; ctx.fillText(s.name, 4, top + 12);
      ctx.fillText(String(hi), 4, top + 26); ctx.fillText(String(lo), 4, top + band);
      ctx.strokeStyle = s.colour; ctx.beginPath();
      s.values.forEach((v, i) => { if (i) ctx.lineTo(x(t[i]), y(v)); else ctx.moveTo(x(t[i]), y(v)); });
      ctx.stroke();
    });
    if (marker !== undefined) { ctx.strokeStyle = "red"; ctx.beginPath(); ctx.moveTo(x(marker), 0); ctx.lineTo(x(marker), H); ctx.stroke(); }
    canvas.dataset.samples = String(t.length);
  }

  function drivePage() {
    const parts = location.pathname.split("/").map(decodeURIComponent);
    const host = parts[2], axis = parts[3];
    document.getElementById("title").textContent = host + "/" + axis;
    document.title = host + "/" + axis;
    const events = document.getElementById("events");
    const stateEl = document.getElementById("state");
    const ferr = document.getElementById("ferr");
    const showDrive = (d) => {
      stateEl.textContent = d.state; stateEl.dataset.state = d.state;
      // following error: known only from 0x60F4 or, in CSP while enabled, from the agent
      const known = d.following_error !== null && d.following_error !== undefined;
      ferr.textContent = known ? "following error " + d.following_error : "";
      ferr.dataset.value = known ? String(d.following_error) : "";
    };
    const canvas = document.getElementById("live");
    const refresh = () => fetch("/api/drive/" + encodeURIComponent(host) + "/" + encodeURIComponent(axis))
      .then((r) => r.json()).then((d) => {
        const m = d.motion;
        plot(canvas, m.t, [{ name: "position", values: m.position, colour: "#1f4e9a" },
                           { name: "velocity", values: m.velocity, colour: "#c05000" },
                           { name: "torque", values: m.torque, colour: "#2a8a2a" }]);
      });
    refresh();
    setInterval(refresh, 500);
    fetch("/api/drive/" + encodeURIComponent(host) + "/" + encodeURIComponent(axis)).then((r) => r.json())
      .then((d) => { showDrive(d.drive); d.events.forEach((e) => eventItem(events, e)); });
    live((ch) => {
      ch.drives.filter((d) => d.host === host && d.axis === axis).forEach(showDrive);
      if (!ch.full) ch.events.filter((e) => e.host === host && e.axis === axis).forEach((e) => eventItem(events, e));
    });
    const info = document.getElementById("rec-info");
    const rec = (what) => {
      info.textContent = "fetching...";
      fetch("/api/recording/" + encodeURIComponent(host) + "?what=" + what + "&last_s=10&axis=" + encodeURIComponent(axis))
        .then((r) => r.json()).then((d) => {
          if (d.error) { info.textContent = d.error; return; }
          const c = d.drives[axis];
          info.textContent = d.reason + (d.detail ? ": " + d.detail : "") + " (" + d.n_cycles + " cycles)";
          const mark = d.trigger_cycle ? d.t[d.trigger_cycle - d.first_cycle] : undefined;
          plot(document.getElementById("recording"), d.t,
               [{ name: "statusword", values: c.statusword, colour: "#555" },
                { name: "position", values: c.position, colour: "#1f4e9a" },
                { name: "velocity", values: c.velocity, colour: "#c05000" }], mark);
        });
    };
    document.getElementById("rec-last").onclick = () => rec("last");
    document.getElementById("rec-fault").onclick = () => rec("fault");
  }

  return { fleetPage, drivePage, plot };
})();
