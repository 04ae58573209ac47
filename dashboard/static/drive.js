// One drive's page: its state, live plots of its status publications against the agent's time
// stamps, its events, and a link to its host's flight recording.
"use strict";
const DrivePage = (() => {
  // Plot windows (s) the operator can pick; 0: everything kept.
  const WINDOWS = [10, 60, 600, 0];

  function start() {
    const parts = location.pathname.split("/").map(decodeURIComponent);
    const host = parts[2], axis = parts[3];
    document.getElementById("title").textContent = host + "/" + axis;
    document.title = host + "/" + axis;
    const rec = document.getElementById("rec-link");
    rec.href = "/recording/" + encodeURIComponent(host) + "?axis=" + encodeURIComponent(axis);
    const events = document.getElementById("events");
    const stateEl = document.getElementById("state");
    const ferr = document.getElementById("ferr");
    const showDrive = (d) => {
      stateEl.textContent = Dashboard.stateText(d);
      stateEl.dataset.state = d.state;
      stateEl.dataset.display = d.display;
      stateEl.className = "state badge d-" + d.display;
      document.getElementById("error").textContent = d.error_code ? Dashboard.hex(d.error_code) + " " + d.error_text : "";
      // following error: known only from 0x60F4 or, in CSP while enabled, from the agent
      const known = d.following_error !== null && d.following_error !== undefined;
      ferr.textContent = known ? "following error " + d.following_error : "";
      ferr.dataset.value = known ? String(d.following_error) : "";
    };
    const win = document.getElementById("window");
    WINDOWS.forEach((w) => { const o = document.createElement("option"); o.value = String(w); o.textContent = w ? "last " + w + " s" : "all kept"; win.appendChild(o); });
    win.value = "60";
    const svg = document.getElementById("live");
    let last = null;
    const draw = () => {
      if (!last) return;
      const m = last.motion, w = +win.value;
      const t = m.t.map((s) => s * 1000);  // the agent's time stamp of each status (ms since the epoch)
      const from = w && t.length ? t[t.length - 1] - w * 1000 : -Infinity;
      const keep = t.map((v, i) => v >= from ? i : -1).filter((i) => i >= 0);
      const pick = (a) => keep.map((i) => a[i]);
      Plot.draw(svg, pick(t), [{ name: "position", series: [{ name: "position", values: pick(m.position), colour: "#1f4e9a" }] },
                               { name: "velocity", series: [{ name: "velocity", values: pick(m.velocity), colour: "#c05000" }] },
                               { name: "torque", series: [{ name: "torque", values: pick(m.torque), colour: "#2a8a2a" }] }],
                { hold: true });
    };
    win.onchange = draw;
    const url = "/api/drive/" + encodeURIComponent(host) + "/" + encodeURIComponent(axis);
    const refresh = () => fetch(url).then((r) => r.json()).then((d) => { last = d; draw(); });
    refresh();
    setInterval(refresh, 500);
    let commands = false;
    const buttons = document.getElementById("commands");
    const showButtons = (d) => { if (commands) { buttons.replaceChildren(); Dashboard.commandButtons(buttons, d); } };
    fetch("/api/fleet").then((r) => r.json()).then((f) => { commands = !!f.commands_enabled; return fetch(url); })
      .then((r) => r.json()).then((d) => { showDrive(d.drive); showButtons(d.drive); d.events.forEach((e) => Dashboard.eventItem(events, e)); });
    Dashboard.live((ch) => {
      ch.drives.filter((d) => d.host === host && d.axis === axis).forEach((d) => { showDrive(d); showButtons(d); });
      if (!ch.full) ch.events.filter((e) => e.host === host && e.axis === axis).forEach((e) => Dashboard.eventItem(events, e));
    });
  }

  return { start };
})();
