// Trajectory editor: a waypoint table (degrees; the move to the next waypoint and the dwell in
// seconds), checked as the operator types by POST /api/trajectories/validate (the checks of a
// campaign start, the checker's own message), a preview of α^d(t), the library (load, save,
// delete) and "start as campaign". Uses api(), $, cell(), refreshList() and runningId of app.js.
"use strict";

(() => {
  const CHECK_DELAY_MS = 250;
  const COLORS = ["#1565c0", "#2e7d32", "#c62828", "#6a1b9a", "#ef6c00", "#00838f"];
  const ed = (window.xneckEditor = { checks: 0, last: null, rows: [] });
  let nJoints = 3, timer = null, plot = null;

  function body() {
    const rows = ed.rows;
    return {
      name: $("#traj-name").value.trim() || "user",
      waypoints_deg: rows.map((r) => r.alpha.map(Number)),
      durations_s: rows.slice(0, -1).map((r) => Number(r.move)),
      dwell_s: rows.map((r) => Number(r.dwell)),
    };
  }

  function input(value, onChange, cls) {
    const el = document.createElement("input");
    Object.assign(el, { type: "number", value, step: "any" });
    el.className = cls || "";
    el.addEventListener("input", () => { onChange(el.value); schedule(); });
    return el;
  }

  function render() {
    const tbody = $("#traj-table tbody");
    tbody.replaceChildren();
    ed.rows.forEach((r, k) => {
      const tr = document.createElement("tr");
      tr.dataset.k = k;
      tr.append(cell(String(k)));
      r.alpha.forEach((a, j) => {
        const td = document.createElement("td");
        td.append(input(a, (v) => { r.alpha[j] = v; }, `traj-a${j + 1}`));
        tr.append(td);
      });
      const move = document.createElement("td");
      if (k < ed.rows.length - 1) move.append(input(r.move, (v) => { r.move = v; }, "traj-move"));
      else move.textContent = "–";
      const dwell = document.createElement("td");
      dwell.append(input(r.dwell, (v) => { r.dwell = v; }, "traj-dwell"));
      const del = document.createElement("td");
      const b = document.createElement("button"); b.textContent = "✕"; b.title = "remove this waypoint";
      b.disabled = ed.rows.length <= 1;
      b.onclick = () => { ed.rows.splice(k, 1); render(); schedule(); };
      del.append(b);
      tr.append(move, dwell, del);
      tbody.append(tr);
    });
  }

  function load(t) {
    const k = t.waypoints_deg.length;
    const per = (v, n) => (Array.isArray(v) ? v : Array(n).fill(v));
    const moves = per(t.durations_s, k - 1), dwells = per(t.dwell_s, k);
    ed.rows = t.waypoints_deg.map((w, i) => ({ alpha: w.map(String), move: String(moves[i] ?? 2), dwell: String(dwells[i] ?? 0) }));
    if (t.name) $("#traj-name").value = t.name;
    render();
    schedule();
  }

  function say(text, ok) {
    const box = $("#traj-msg");
    box.textContent = text;
    box.className = ok ? "traj-ok" : "error";
  }

  function showPreview(p) {
    const el = $("#traj-preview");
    if (!p) { el.hidden = true; return; }
    el.hidden = false;
    const data = [p.t_s, ...p.alpha_deg];
    if (!plot || plot.series.length !== data.length) {
      if (plot) plot.destroy();
      plot = new uPlot({ title: "preview: α^d(t)", width: el.clientWidth || 600, height: 200,
        scales: { x: { time: false } },
        series: [{ label: "t (s)" }, ...p.alpha_deg.map((_, j) => ({ label: `α${j + 1} (°)`, stroke: COLORS[j % 6], width: 1.5, points: { show: false } }))],
        axes: [{ label: "t (s)" }, { label: "deg" }] }, data, el);
    } else plot.setData(data);
  }

  async function check() {
    ed.checks++;
    document.querySelectorAll("#traj-table tr.bad").forEach((tr) => tr.classList.remove("bad"));
    let v;
    try { v = await api("POST", "/api/trajectories/validate", body()); } catch (e) { return say(e.message || String(e), false); }
    ed.last = v;
    say(v.message, v.ok);
    showPreview(v.preview);
    const m = /waypoint (\d+)/.exec(v.ok ? "" : v.message);  // the checker names the waypoint: mark its row
    if (m) { const tr = document.querySelector(`#traj-table tr[data-k="${m[1]}"]`); if (tr) tr.classList.add("bad"); }
  }

  function schedule() { clearTimeout(timer); timer = setTimeout(check, CHECK_DELAY_MS); }

  async function refreshLibrary(select) {
    let list;
    try { list = (await api("GET", "/api/trajectories")).trajectories; } catch (e) { return; }
    const sel = $("#traj-library");
    sel.replaceChildren(...list.map((t) => new Option(t.builtin ? `${t.name} (built-in)` : t.name, t.name)));
    if (select) sel.value = select;
  }

  window.addEventListener("xneck-config", (ev) => {
    nJoints = ev.detail.n_joints;
    const head = $("#traj-table thead tr");
    head.replaceChildren(...["#", ...Array.from({ length: nJoints }, (_, j) => `α${j + 1} (°)`),
      "move to next (s)", "dwell (s)", ""].map((t) => { const th = document.createElement("th"); th.textContent = t; return th; }));
    const zero = Array(nJoints).fill("0");
    ed.rows = [{ alpha: [...zero], move: "2", dwell: "0.5" },
               { alpha: zero.map((_, j) => (j === 0 ? "20" : j === 1 ? "10" : "0")), move: "2", dwell: "0.5" },
               { alpha: [...zero], move: "2", dwell: "0.5" }];
    render();
    refreshLibrary();
  });

  $("#traj-add").addEventListener("click", () => {
    const last = ed.rows[ed.rows.length - 1];
    ed.rows.push({ alpha: [...last.alpha], move: last.move, dwell: last.dwell });
    render(); schedule();
  });
  $("#traj-load").addEventListener("click", async () => {
    try { load(await api("GET", `/api/trajectories/${encodeURIComponent($("#traj-library").value)}`)); }
    catch (e) { say(e.message || String(e), false); }
  });
  $("#traj-save").addEventListener("click", async () => {
    const name = $("#traj-name").value.trim();
    try {
      const r = await api("PUT", `/api/trajectories/${encodeURIComponent(name)}`, body());
      say(`saved ${r.name}: ${r.waypoints} waypoints, ${r.duration_s.toFixed(2)} s`, true);
      refreshLibrary(name);
    } catch (e) { say(e.message || String(e), false); }
  });
  $("#traj-delete").addEventListener("click", async () => {
    const name = $("#traj-library").value;
    if (!name || !confirm(`Delete ${name} from the library?`)) return;
    try { await api("DELETE", `/api/trajectories/${encodeURIComponent(name)}`); refreshLibrary(); }
    catch (e) { say(e.message || String(e), false); }
  });
  $("#traj-preview3d").addEventListener("click", async () => {
    try {
      const r = await api("POST", "/api/trajectories/preview3d", body());
      say(`previewing in the 3D view (violet ghost, ${r.duration_s.toFixed(1)} s)`, true);
    } catch (e) { say(e.message || String(e), false); }
  });
  $("#traj-start").addEventListener("click", async () => {
    try {
      const rec = await api("POST", "/api/campaigns", { kind: "control", waypoints: body() });
      runningId = rec.id;
      say(`campaign ${rec.id} started`, true);
      refreshList();
    } catch (e) { say(e.message || String(e), false); }
  });
})();
