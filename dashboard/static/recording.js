// The flight-recording viewer: asks a host's flight recorder (GET /api/recording/<host>) for the
// last seconds, the latest window a trigger froze, or a window frozen now, and draws one axis'
// cycles against the agent's clock: CiA 402 states, position and velocity (actual and target),
// torque, cycle period and working counter, with the trigger as a red line.
"use strict";
const RecordingPage = (() => {
  // recording_request.what, as offered to the operator
  const WHATS = [["last", "last seconds"], ["fault", "last fault"], ["reflex", "last reflex"], ["lost", "last lost"],
                 ["request", "last request"], ["any", "latest trigger of any kind"], ["now", "freeze now"]];

  function start() {
    const host = decodeURIComponent(location.pathname.split("/")[2]);
    const params = new URLSearchParams(location.search);
    document.getElementById("title").textContent = "flight recording: " + host;
    document.title = "recording " + host;
    const what = document.getElementById("what"), lastS = document.getElementById("last-s");
    const axisSel = document.getElementById("axis"), info = document.getElementById("rec-info");
    const svg = document.getElementById("recording");
    WHATS.forEach(([v, label]) => { const o = document.createElement("option"); o.value = v; o.textContent = label; what.appendChild(o); });
    what.value = params.get("what") || "last";
    let rec = null;
    const draw = () => {
      const c = rec && rec.drives[axisSel.value];
      if (!c) return;
      const t = rec.t.map((s) => rec.t0_ms + s * 1000);
      const col = (k) => c[k] || [];
      const mark = rec.trigger_cycle ? t[rec.trigger_cycle - rec.first_cycle] : undefined;
      Plot.draw(svg, t, [
        { name: "state", runs: c.states || [] },
        { name: "position", series: [{ name: "actual", values: col("position"), colour: "#1f4e9a" },
                                     { name: "target", values: col("target_position"), colour: "#8fb0e8" }] },
        { name: "velocity", series: [{ name: "actual", values: col("velocity"), colour: "#c05000" },
                                     { name: "target", values: col("target_velocity"), colour: "#f0b080" }] },
        { name: "torque", series: [{ name: "actual", values: col("torque"), colour: "#2a8a2a" }] },
        { name: "period (us)", series: [{ name: "period", values: (rec.cycle_channels.period_ns || []).map((v) => v / 1000), colour: "#555" }] },
        { name: "WKC", series: [{ name: "wkc", values: rec.cycle_channels.wkc || [], colour: "#7a2a8a" }] },
      ], { marker: mark });
    };
    axisSel.onchange = draw;
    const fetchIt = () => {
      info.textContent = "asking " + host + "'s flight recorder...";
      info.dataset.state = "fetching";
      const q = "?what=" + encodeURIComponent(what.value) + "&last_s=" + encodeURIComponent(lastS.value);
      fetch("/api/recording/" + encodeURIComponent(host) + q).then((r) => r.json()).then((d) => {
        if (d.error) { info.textContent = d.error; info.dataset.state = "error"; return; }
        rec = d;
        const want = axisSel.value || params.get("axis") || d.axis;
        axisSel.replaceChildren(...d.axes.map((a) => { const o = document.createElement("option"); o.value = a; o.textContent = a; return o; }));
        axisSel.value = d.axes.includes(want) ? want : d.axes[0];
        const trig = d.trigger_cycle ? ", trigger at cycle " + d.trigger_cycle + " (" +
          Plot.timeLabel(d.t0_ms + d.t[d.trigger_cycle - d.first_cycle] * 1000, 1) + " UTC)" : "";
        info.textContent = d.reason + (d.axis ? " on " + d.axis : "") + (d.detail ? ": " + d.detail : "") + " - " +
          d.n_cycles + " cycles of " + d.cycle_us + " us from " + Plot.timeLabel(d.t0_ms, 1) + " UTC" + trig;
        info.dataset.state = "shown";
        info.dataset.reason = d.reason;
        draw();
      }).catch((err) => { info.textContent = String(err); info.dataset.state = "error"; });
    };
    document.getElementById("fetch").onclick = fetchIt;
    if (params.get("what")) fetchIt();
  }

  return { start };
})();
