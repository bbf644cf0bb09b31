// xneck dashboard: forms over the REST API, live plots from the /api/live WebSocket, the viser
// view in an iframe. The API speaks SI (rad); this page shows degrees.
"use strict";

const DEG = 180 / Math.PI;
const WINDOW_S = 20;          // seconds shown by the live plots while they run
const HISTORY_S = 60;         // seconds kept: paused, the plots scroll back over the last minute
const MAX_POINTS = 2400;      // per series, browser-side decimation bound
let livePaused = false;       // the pause button: frames are still stored, the plots stand still
const $ = (sel) => document.querySelector(sel);
const stats = (window.xneckStats = { frames: 0, points: 0, lastStamp: null });

let config = null;
let runningId = null;
let replayId = null;  // the campaign a replay is republishing (health.replay), null if none runs
let replayShown = null;  // the replay the bar shows running, until its end is shown once

function token() { return $("#token").value.trim(); }
$("#token").value = localStorage.getItem("xneck-token") || "";
$("#token").addEventListener("change", () => localStorage.setItem("xneck-token", token()));

async function api(method, path, body) {
  const headers = {};
  if (method !== "GET") headers["Authorization"] = "Bearer " + token();
  if (body !== undefined) headers["Content-Type"] = "application/json";
  const r = await fetch(path, { method, headers, body: body === undefined ? undefined : JSON.stringify(body) });
  const text = await r.text();
  let data = null;
  try { data = text ? JSON.parse(text) : null; } catch (e) { data = text; }
  if (!r.ok) {
    let msg = `${r.status}`;
    if (data && data.detail) {
      msg += ": " + (Array.isArray(data.detail)
        ? data.detail.map((d) => `${(d.loc || []).join(".")}: ${d.msg}`).join("\n")
        : data.detail);
    }
    throw new Error(msg);
  }
  return data;
}

// The form's error line says why the last action through it failed; an action that succeeds
// clears it (audit of 2026-11-29: a refused replay's 409 stood under the Stop that then worked).
// The e-stop's refusals are in the sticky banner instead, with rules of their own (safety.js).
function showError(e) { $("#error").textContent = e ? String(e.message || e) : ""; }

// ---------------------------------------------------------------- live plots
// Legends show the newest values with their unit (uPlot shows the cursor's, "--" without one:
// showLatest), and the y range spans at least minSpan so that a still signal gets several ticks.
function makePlot(el, title, labels, colors, yLabel, minSpan = 2) {
  const unit = yLabel === "deg" ? "°" : ` ${yLabel}`;
  const value = (u, v) => (v === null || v === undefined ? "–" : v.toFixed(yLabel === "deg" ? 2 : 1) + unit);
  const series = [{ label: "t", value: (u, v) => (v === null || v === undefined ? "–" : v.toFixed(2) + " s") }]
    .concat(labels.map((l, i) => ({ label: l, stroke: colors[i], width: 1.5, points: { show: false }, value })));
  const data = [[]].concat(labels.map(() => []));
  const range = (u, lo, hi) => {  // at least minSpan, ends on a round step: ticks at both ends
    if (lo === null || hi === null) { lo = -minSpan / 2; hi = minSpan / 2; }
    const mid = (lo + hi) / 2, half = Math.max(hi - lo, minSpan) / 2;
    const raw = half / 2, mag = 10 ** Math.floor(Math.log10(raw));
    const step = [1, 2, 5, 10].map((k) => k * mag).find((x) => x >= raw);
    const lo2 = Math.floor((mid - half) / step) * step, hi2 = Math.ceil((mid + half) / step) * step;
    return [lo2, Math.round((hi2 - lo2) / step) % 2 ? hi2 + step : hi2];  // an even number of steps
  };
  const splits = (u, i, lo, hi) => [lo, (lo + hi) / 2, hi];  // three round ticks, whatever the height
  const plot = new uPlot({ title, width: el.clientWidth || 600, height: 170, series,
    scales: { x: { time: false }, y: { range } }, axes: [{ label: "t (s)" }, { label: yLabel, splits }] }, data, el);
  return { plot, data, lastX: null };
}

function showLatest(p) {
  if (!(p.plot.cursor.left >= 0) && p.data[0].length) p.plot.setLegend({ idx: p.data[0].length - 1 });
}

function push(p, x, ys) {
  if (p.lastX !== null && x <= p.lastX) {
    if (x < p.lastX - 1) { for (const a of p.data) a.length = 0; }  // time went back: a new run
    else return;                                                   // repeat of the same sample
  }
  p.lastX = x;
  p.data[0].push(x);
  // One value per series of the plot, whatever the message held: any peer on the bus may publish,
  // and one force too many must not throw (it froze the live view, audit-d).
  for (let i = 1; i < p.data.length; i++) p.data[i].push(ys[i - 1] === undefined ? null : ys[i - 1]);
  while (p.data[0].length > MAX_POINTS || (p.data[0].length && p.data[0][0] < x - HISTORY_S)) {
    for (const a of p.data) a.shift();
  }
  stats.points++;
}

let forcePlot = null;
const jointPlots = [];
let dirty = false;

function buildPlots() {
  const nm = config.n_motors, nj = config.n_joints;
  const fcol = ["#1f77b4", "#ff7f0e", "#2ca02c", "#d62728", "#9467bd", "#8c564b"];
  forcePlot = makePlot($("#plot-forces"), "cable forces (applied)",
    Array.from({ length: nm }, (_, i) => `f${i + 1}`), fcol, "N", 5);
  for (let j = 0; j < nj; j++) {
    const div = document.createElement("div");
    $("#plot-joints").appendChild(div);
    jointPlots.push(makePlot(div, `joint ${j + 1}`, ["α^d", "α̂", "α_IP"],
      ["#2e7d32", "#1565c0", "#ef6c00"], "deg", 4));
  }
}

function onFrame(frame) {
  stats.frames++;
  const s = frame.series || {};
  try {
    showLiveCamera(s.camera);
    if (s.state) push(forcePlot, s.state.stamp_s, s.state.force_applied_N);
    if (s.status) {
      stats.lastStamp = s.status.stamp_s;
      // The console sends α_IP only while the camera is fresh (server.live.fresh_camera): without it, a gap.
      const ip = s.camera ? s.camera.alpha_ip_rad : null;
      jointPlots.forEach((p, j) => push(p, s.status.stamp_s,
        [s.status.alpha_d_rad[j] * DEG, s.status.alpha_hat_rad[j] * DEG,
         ip && ip[j] !== null ? ip[j] * DEG : null]));  // null: the camera missed this joint (a gap, not 0°)
      $("#live-info").textContent = `${s.status.law}, t = ${s.status.stamp_s.toFixed(2)} s` +
        (s.status.holding ? `, HOLD: ${s.status.hold_reason}` : "");
    }
    // A running campaign's progress; its end is the record's (pollStatus, showEnded): a late frame
    // saying "aborted" had replaced the end shown, message and all (CI of session 43).
    if (s.campaign && s.campaign.campaign_id === runningId && !["finished", "aborted", "interrupted"].includes(s.campaign.event))
      setProgress(s.campaign.progress, s.campaign.event);
  } finally {
    // Whatever a plot made of the frame, safety.js (the bridge's e-stop, "stream lost") and jog.js get it.
    dirty = true;
    window.dispatchEvent(new CustomEvent("xneck-frame", { detail: frame }));  // jog.js, console.js
  }
}

// Which camera the α_IP drawn is of, and why the console follows that one (server.live: "instance",
// "chosen"). The name comes from the bus (any peer names itself): written as text, cut to fit; the
// whole name is in the tooltip.
const CAMERA_CHOSEN = { campaign: "campaign's", stack: "stack's own", first: "first seen", current: "kept" };
const CAMERA_NAME_MAX = 32;
let liveCameraText = null;
function showLiveCamera(cam) {
  let text = "α_IP: no camera", name = "";
  if (cam) {
    name = typeof cam.instance === "string" ? cam.instance : "";
    const shown = !name ? "(unnamed)" : name.length > CAMERA_NAME_MAX ? name.slice(0, CAMERA_NAME_MAX - 1) + "…" : name;
    const why = Object.hasOwn(CAMERA_CHOSEN, cam.chosen) ? ` (${CAMERA_CHOSEN[cam.chosen]})` : "";
    text = `α_IP: camera ${shown}${why}`;
  }
  if (text + "\n" + name === liveCameraText) return;
  liveCameraText = text + "\n" + name;
  const el = $("#live-camera");
  el.textContent = text;
  el.title = name ? `The α_IP drawn is camera ${name}'s` : "The camera whose α_IP the joint plots draw, and why that one";
}

// Running: the last WINDOW_S seconds. Paused: the whole last minute, to zoom in by dragging
// (double click zooms out again).
function drawLive(p) {
  p.plot.setData(p.data);
  const last = p.data[0].length ? p.data[0][p.data[0].length - 1] : 0;
  p.plot.setScale("x", { min: livePaused ? p.data[0][0] : last - WINDOW_S, max: last });
  showLatest(p);
}

function redraw() {
  if (dirty && forcePlot && !livePaused) {
    dirty = false;
    [forcePlot, ...jointPlots].forEach(drawLive);
  }
  requestAnimationFrame(redraw);
}

function connectLive() {
  // A console on the lab network wants the token for live data too; a browser WebSocket cannot
  // send headers, so it goes in the query (server/guard.py).
  const q = token() ? "?token=" + encodeURIComponent(token()) : "";
  const ws = new WebSocket(`${location.protocol === "https:" ? "wss" : "ws"}://${location.host}/api/live${q}`);
  ws.onmessage = (ev) => { try { onFrame(JSON.parse(ev.data)); } catch (e) { console.error(e); } };
  ws.onclose = () => setTimeout(connectLive, 1000);
}

// ---------------------------------------------------------------- campaigns
// The bar: the running campaign or replay, else the last campaign's end (outcome, message, when),
// kept until a new campaign or a replay starts (user audit of session 42: after an e-stop aborted a
// campaign it said "idle", or only "<id> aborted"). endedShown: the campaign whose end it shows.
let endedShown = null;
function setProgress(fraction, text, outcome = null) {
  const pct = Math.round(100 * (fraction || 0));
  $("#progress-bar").style.width = pct + "%";
  const el = $("#progress-text");
  el.textContent = outcome ? text : `${text || ""} ${pct}%`;
  el.title = outcome ? text : "";  // the whole message where the bar cuts it
  if (outcome) $(".progress").dataset.outcome = outcome; else delete $(".progress").dataset.outcome;
  if (!outcome) endedShown = null;
}

// An ended campaign's record (server/records.py) on the bar: its status styled as the table's.
const OUTCOME = { finished: "success", degraded: "warning", analysis_failed: "warning", interrupted: "warning" };
function showEnded(rec) {
  const pct = Math.round(100 * (rec.progress || 0));
  const when = rec.ended_at ? ` (ended ${rec.ended_at.slice(0, 19).replace("T", " ")} UTC)` : "";
  setProgress(rec.progress, `${rec.id} ${rec.status} at ${pct}%${rec.message ? ": " + rec.message : ""}${when}`,
    OUTCOME[rec.status] || "failure");
  endedShown = rec.id;
}

$("#trajectory").addEventListener("change", () => {
  $("#waypoints-box").hidden = $("#trajectory").value !== "__custom";
});

// The identification's analysis options only mean something for an identification campaign.
const kindSelect = $("#start-form").elements.kind;
const showAnalysis = () => { $("#analysis-box").hidden = kindSelect.value !== "identification"; };
kindSelect.addEventListener("change", showAnalysis);
showAnalysis();  // a browser may restore the form's kind on reload

$("#start-form").addEventListener("submit", async (ev) => {
  ev.preventDefault();
  showError(null);
  const f = new FormData(ev.target);
  const body = { kind: f.get("kind"), no_pulleys: f.get("no_pulleys") === "on" };
  // An empty seed is the default (under `xneck up`: the stack twin's own seed, which cannot change).
  if (f.get("seed") !== "" && f.get("seed") !== null) body.seed = Number(f.get("seed"));
  if (f.get("law")) body.law = Number(f.get("law"));
  for (const k of ["parameter_set", "target", "pace"]) if (f.get(k)) body[k] = f.get(k);
  if (body.kind === "identification") {
    if (f.get("estimator")) body.estimator = f.get("estimator");
    if (f.get("creep_time_s")) body.creep_time_s = Number(f.get("creep_time_s"));
  }
  const traj = f.get("trajectory");
  if (traj === "__custom") {
    try { body.waypoints = JSON.parse(f.get("waypoints")); } catch (e) { return showError("waypoints: not valid JSON: " + e.message); }
  } else if (traj) body.trajectory = traj;
  try {
    const rec = await api("POST", "/api/campaigns", body);
    runningId = rec.id;
    setProgress(0, `${rec.id} started`);
    showError(null);
    refreshList();
  } catch (e) { showError(e); }
});

// Stops the running campaign, whoever started it (this page, another, REST, a script), or else
// the running replay (audit of 2026-11-28: both were beyond this button, which said nothing).
$("#stop").addEventListener("click", async () => {
  const id = runningId || replayId;
  if (!id) return showError("nothing is running: no campaign and no replay to stop");
  try { await api("POST", `/api/campaigns/${id}/stop`); showError(null); } catch (e) { showError(e); }
});
// In the sticky banner, not the form's error line (off screen when scrolled): safety.js.
$("#estop").addEventListener("click", () => window.xneckSafety.send(true, "dashboard"));
$("#estop-release").addEventListener("click", () => window.xneckSafety.send(false, "dashboard"));
$("#refresh").addEventListener("click", () => refreshList());

function cell(text) { const td = document.createElement("td"); td.textContent = text; return td; }

async function refreshList() {
  let list;
  try { list = await api("GET", "/api/campaigns?limit=50"); } catch (e) { return; }
  const tbody = $("#campaigns tbody");
  tbody.replaceChildren();
  for (const r of list) {
    const tr = document.createElement("tr");
    tr.dataset.id = r.id;
    tr.append(cell(r.id), cell(r.kind), cell(r.law), cell(r.trajectory));
    const st = cell(r.status); st.className = "status-" + r.status; tr.append(st);
    tr.append(cell(Math.round(100 * r.progress) + "%"), cell((r.created_at || "").slice(0, 19).replace("T", " ")));
    const actions = document.createElement("td");
    const show = document.createElement("button"); show.textContent = "results";
    show.onclick = () => showResults(r.id);
    const replay = document.createElement("button"); replay.textContent = "replay";
    replay.onclick = async () => {
      try { await api("POST", `/api/campaigns/${r.id}/replay`, { speed: 1.0 }); showError(null); } catch (e) { showError(e); }
    };
    const del = document.createElement("button"); del.textContent = "delete";
    del.onclick = async () => {
      if (!confirm(`Delete ${r.id}?`)) return;
      try { await api("DELETE", `/api/campaigns/${r.id}`); showError(null); refreshList(); } catch (e) { showError(e); }
    };
    actions.append(show, replay, del);
    if (r.status !== "running") {
      const a = document.createElement("a"); a.href = `/api/campaigns/${r.id}/mcap`; a.textContent = " MCAP";
      actions.append(a);
    }
    tr.append(actions);
    tbody.append(tr);
    // a list fetched before the campaign shown as ended ended does not make it run again
    if (r.status === "running" && r.id !== endedShown) { runningId = r.id; setProgress(r.progress, r.id); }
  }
  // While nothing runs, the bar shows the newest campaign's end (the records are the console's truth,
  // and an operator opening the page after an e-stop wants to know what it did): on a page loaded
  // after it ended, when the campaign shown was deleted, and when one started elsewhere ended
  // between two polls, never seen running (review of session 43: the bar kept an older end).
  if (!runningId && !replayId) {
    if (list.length && list[0].status !== "running") { if (list[0].id !== endedShown) showEnded(list[0]); }
    else if (endedShown) { setProgress(0, ""); $("#progress-text").textContent = "idle"; }  // none left
  }
}

function renderTable(t) {
  const wrap = document.createElement("div");
  const h = document.createElement("h3"); h.textContent = t.title; wrap.append(h);
  const table = document.createElement("table");
  const head = document.createElement("tr");
  t.columns.forEach((c) => { const th = document.createElement("th"); th.textContent = c; head.append(th); });
  table.append(head);
  t.rows.forEach((row) => {
    const tr = document.createElement("tr");
    // counts as they are (18743 instants, not 18740): four digits for measured values only
    row.forEach((v) => tr.append(cell(v === null ? "–" : typeof v === "number" && !Number.isInteger(v)
      ? Number(v.toPrecision(4)) : v)));
    table.append(tr);
  });
  wrap.append(table);
  if (t.note) { const p = document.createElement("small"); p.textContent = t.note; wrap.append(p); }
  return wrap;
}

async function showResults(id) {
  document.querySelectorAll("#campaigns tr").forEach((tr) => tr.classList.toggle("selected", tr.dataset.id === id));
  const box = $("#results");
  box.replaceChildren();
  let res;
  try { res = await api("GET", `/api/campaigns/${id}/results`); } catch (e) { return showError(e); }
  showError(null);
  const h = document.createElement("h3");
  h.textContent = `${res.id}: ${res.status}` + (res.identification_status ? ` (${res.identification_status})` : "");
  box.append(h);
  const reasons = (res.quality && res.quality.reasons) || [];
  if (res.status !== "finished" && res.status !== "running" && (reasons.length || res.message)) {
    const why = document.createElement("p"); why.className = "outcome-reasons";
    why.textContent = reasons.length ? `degraded: ${reasons.join("; ")}` : res.message;
    box.append(why);
  }
  res.tables.forEach((t) => box.append(renderTable(t)));
  if (res.identification_status === "identified") box.append(saveSetForm(res.id));
  res.figures.forEach((src) => { const img = document.createElement("img"); img.src = src; img.alt = src; box.append(img); });
  const a = document.createElement("a"); a.href = res.mcap; a.textContent = "download MCAP (opens in Foxglove)";
  box.append(document.createElement("br"), a);
}

// An identification's estimates as a parameter set of the console (POST .../parameter-set): the
// set `xneck identify --out` writes, then chosen active under Workspace like any set.
function saveSetForm(id) {
  const form = document.createElement("form"); form.className = "save-set";
  const name = document.createElement("input");
  name.name = "name"; name.value = `${id}-set`.slice(-64); name.maxLength = 64; name.pattern = "[A-Za-z0-9_.\\-]{1,64}";
  name.title = "Name of the new parameter set (letters, digits, _ . -); an existing set is never replaced";
  const button = document.createElement("button"); button.type = "submit"; button.textContent = "save as parameter set";
  const said = document.createElement("span"); said.className = "save-set-result";
  const warned = document.createElement("p"); warned.className = "save-set-warning";
  form.append(name, button, said, warned);
  form.addEventListener("submit", async (ev) => {
    ev.preventDefault();
    said.textContent = "identifying the archive again…"; warned.textContent = "";
    try {
      const out = await api("POST", `/api/campaigns/${id}/parameter-set`, { name: name.value.trim() });
      const kept = Object.keys(out.kept_base);
      said.textContent = `saved as ${out.name} (${Object.keys(out.used).length} values identified` +
        (kept.length ? `, ${kept.length} kept at ${out.base_parameter_set}'s` : "") + "): choose it under Workspace";
      // Why the set is not to be trusted (α_IP stamped off the encoders): also the first line of its
      // TOML, but a lab that chooses it here never reads that file.
      warned.textContent = typeof out.warning === "string" && out.warning ? `warning: ${out.warning}` : "";
      pollActiveSet();
    } catch (e) { said.textContent = "not saved: " + (e.message || e); }
  });
  return form;
}

// The e-stop as the bridge reports it (its latched state in every MotorState), not as this page
// last asked: a malformed message or another console may have engaged it.
function showEstop(e) {
  const box = $("#estop-state");
  const disabled = e.engaged || e.drive === "disabled";
  box.hidden = !disabled;
  box.textContent = disabled ? `${e.engaged ? "E-STOP ENGAGED" : "DRIVES DISABLED"}: ${e.reason || "no reason given"}` +
    (e.source === "console" ? " (as sent by this console; no bridge reports)" : "") : "";
}

// How old the bridge's latest motor state is: a bridge that is listed alive but states nothing
// (hung, or its bus link gone) must not look like a live one.
function bridgeAge(b) {
  if (!b || b.state_age_s === null || b.state_age_s === undefined) return "bridge: no motor state yet";
  const age = b.state_age_s;
  if (age > 1.0) return `BRIDGE SILENT for ${age.toFixed(1)} s (last drive ${b.drive})`;
  return `bridge: state ${(age * 1e3).toFixed(0)} ms ago, drive ${b.drive}` +
    (b.drive === "hold" && b.hold_reason ? ` (${b.hold_reason})` : "");
}

// ``text`` cut to ``n`` characters, an ellipsis marking the cut (the whole text is in /api/system/health).
function clip(text, n) {
  return text.length > n ? `${text.slice(0, n - 1)}…` : text;
}

// The bridge's own counters (its Health, about 1 Hz): what a commissioning engineer watches.
function bridgeHealth(procs) {
  const b = procs.processes.find((p) => p.kind === "bridge" && p.health);
  if (!b) return "";
  const r = b.health.received, n = (x) => (x === undefined ? "–" : x);
  const refused = Object.values(b.health.rejected || {}).reduce((a, x) => a + x, 0);
  // the periods a stalled tick skipped (bridge.node.pace): one overrun may have lost hundreds
  const skipped = r.periods_skipped ? ` (${r.periods_skipped} periods skipped)` : "";
  return `bridge ${b.instance}: ${n(r.ticks)} ticks, ${n(r.overruns)} overruns${skipped}, ${n(r.holds)} holds, ` +
    `${n(r.clamped)} clamped, ${n(r.rate_limited)} rate-bounded, ${refused} refused` +
    // cut: a long reason wrapped the header and pushed the e-stop button down (CI of session 40)
    (b.health.last_reject_reason ? ` (last: ${clip(b.health.last_reject_reason, 80)})` : "") +
    (b.health.age_s > 3 ? ` — counters ${b.health.age_s.toFixed(0)} s old` : "");
}

// Without bus credentials, anyone on the network who reaches these endpoints may link to the
// bridge and publish e-stops and commands (docs/safety.md, "Who may link to the bridge").
function busOpen(bus) {
  if (!bus || !bus.open) return "";
  return `BUS OPEN: no credentials, anyone on the network may link (${[...bus.exposed, ...bus.remote].join(", ")}); ` +
    "set XNECK_ZENOH_CREDENTIALS";
}

// A viewer's console (its bus user is a viewer, docs/safety.md "Viewers") watches: the bus drops
// what it would publish and its routes that act answer 403. Its e-stop button would do nothing,
// so it says so instead of looking like one that works.
function busViewer(bus) {
  if (!bus || bus.role !== "viewer") return "";
  return `VIEWER (bus user ${bus.user}): this console cannot act on the robot, no e-stop, campaign or jog; ` +
    "use an operator's console or the e-stop button";
}

// Deaths, hangs and restarts of the stack's processes xneck up reported (server.process_faults):
// said in the header for 10 min (its restart window), then as a count beside the processes alive.
const PROCESS_FAULT_SHOWN_S = 600;

function processFaults(f) {
  if (!f || !f.count || f.last_age_s === null || f.last_age_s >= PROCESS_FAULT_SHOWN_S) return "";
  const ago = f.last_age_s < 60 ? `${f.last_age_s.toFixed(0)} s` : `${(f.last_age_s / 60).toFixed(0)} min`;
  return `STACK: ${clip(f.last_reason, 160)} — ${ago} ago` +
    (f.count > 1 ? ` (${f.count} process faults since this console started)` : "");
}

function showViewer(text) {
  $("#bus-viewer").hidden = !text;
  $("#bus-viewer").textContent = text;
  for (const id of ["#estop", "#estop-release"]) {
    const b = $(id);
    if (b.dataset.title === undefined) b.dataset.title = b.title;
    b.disabled = Boolean(text);
    b.title = text || b.dataset.title;
  }
}

async function pollStatus() {
  try {
    const h = await api("GET", "/api/system/health");
    const procs = await api("GET", "/api/system/processes");
    const faults = h.process_faults && h.process_faults.count ? ` (${h.process_faults.count} process faults)` : "";
    $("#sys").textContent = `mode ${h.mode}, pace ${h.pace}` +
      ` — alive: ${procs.processes.map((p) => p.kind).join(", ") || "none"}${faults} — ${bridgeAge(h.bridge)}`;
    const fault = processFaults(h.process_faults);  // text: the reason comes from a request
    window.dispatchEvent(new CustomEvent("xneck-health", { detail: h }));  // jog.js: a jog a death cut short
    $("#process-faults").hidden = !fault;
    $("#process-faults").textContent = fault;
    $("#bridge-health").textContent = bridgeHealth(procs);  // text: the reject reason comes from the bus
    const open = busOpen(h.bus);
    $("#bus-open").hidden = !open;
    $("#bus-open").textContent = open;
    showViewer(busViewer(h.bus));
    const changed = (h.bus && h.bus.changed_since_start) || [];
    $("#bus-changed").hidden = !changed.length;
    $("#bus-changed").textContent = changed.length ? `BUS SETTINGS CHANGED since this console started ` +
      `(${changed.join(", ")}): not in force until the stack and the bridge restart` : "";
    // While live frames bring the bridge's states, they alone show its e-stop: the poll's copy
    // of the same state may be older or newer than the last frame, and mixing the two made the
    // banner blink off and on right after an engage.
    const safety = window.xneckSafety;
    if (!(safety && safety.liveStateFresh())) showEstop(h.estop);
    if (!runningId && h.running_campaign_id) {  // started elsewhere: followed as this page's own
      runningId = h.running_campaign_id;
      refreshList();
    }
    const replay = h.replay && h.replay.running ? h.replay : null;
    replayId = replay ? replay.campaign_id : null;
    if (!runningId && replay) { setProgress(replay.progress, `replay of ${replay.campaign_id}`); replayShown = replay.campaign_id; }
    else if (!runningId && replayShown) {
      // How it ended, once, from its last status: a replay stopped half-way had read "replay ended: 100%".
      const last = h.replay, pct = last ? Math.floor(100 * (last.progress || 0)) : 100;
      if (!last) setProgress(1, "replay ended:");
      else if (last.error) setProgress(last.progress, `replay of ${last.campaign_id} failed at ${pct}%: ${last.error}`, "failure");
      else if (last.total && last.published >= last.total) setProgress(1, `replay of ${last.campaign_id} ended at 100%`, "success");
      else setProgress(last.progress, `replay of ${last.campaign_id} stopped at ${pct}%`, "warning");
      replayShown = null;
    }
    if (runningId && h.running_campaign_id !== runningId) {
      const rec = await api("GET", `/api/campaigns/${runningId}`);
      if (rec.status !== "running") { runningId = null; showEnded(rec); refreshList(); showResults(rec.id); }
      else setProgress(rec.progress, `${rec.id} ${rec.status}`);
    } else if (runningId) {
      // The record may end before the health says so: its end then, not "<id> stopped by the user 3%"
      // as if it ran on (a race the browser test met in session 44). Not one a controller still
      // runs unrecorded after a console restart (running_on): the health follows it, Stop stops it.
      const rec = await api("GET", `/api/campaigns/${runningId}`);
      if (rec.status !== "running" && !rec.running_on) { runningId = null; showEnded(rec); refreshList(); showResults(rec.id); }
      else setProgress(rec.progress, `${rec.id} ${rec.message}`);
    }
  } catch (e) { $("#sys").textContent = "server unreachable"; }
}

// ---------------------------------------------------------------- workspace maps
// The maps follow the ACTIVE parameter set: a poll notices when it changes (here or from another
// client) and reloads them; the server computes them once per set (a few seconds) and caches them.
// tried: the set of the last load, shown or failed, so a failing set is not retried every poll.
const ws = (window.xneckWorkspace = { tried: null, shownKey: null, loading: null, loads: 0 });

function figureEl(f) {
  const fig = document.createElement("figure");
  const img = document.createElement("img");
  img.src = f.url; img.alt = f.caption; img.loading = "lazy";
  const link = document.createElement("a"); link.href = f.url; link.target = "_blank"; link.append(img);
  const cap = document.createElement("figcaption"); cap.textContent = f.caption;
  fig.append(link, cap);
  return fig;
}

function fmt(x, digits = 3) { return x === null || x === undefined ? "–" : Number(x.toPrecision(digits)).toString(); }

function renderWorkspaceSummary(s) {
  const k = s.joint_stiffness_N_m_per_rad, rest = s.straight_neck;
  const pct = (x) => (x === null || x === undefined ? "–" : (100 * x).toFixed(1) + " %");
  const rows = [
    ["parameter set", s.parameter_set],
    ["cable forces", `${fmt(s.f_min_N)} N ≤ f ≤ ${fmt(s.f_max_N)} N`],
    ["wrench-feasible", `${pct(s.feasible_fraction)} of |α_i| ≤ ${fmt(s.grid.alpha_max_deg)}°, ` +
      `${pct(s.feasible_fraction_within_joint_limit)} within the joint limit ±${fmt(s.joint_limit_deg)}°`],
    ["joint stiffness K_ii over the feasible set (N·m/rad)", k.min
      ? k.min.map((lo, i) => `K${i + 1}${i + 1}: ${fmt(lo)} … ${fmt(k.max[i])}`).join(",  ") : "no feasible configuration"],
    ["straight neck, lowest → highest tension (N·m/rad)", rest.feasible
      ? rest.stiffness_lowest_tension_N_m_per_rad.map((lo, i) =>
          `K${i + 1}${i + 1}: ${fmt(lo)} → ${fmt(rest.stiffness_highest_tension_N_m_per_rad[i])}`).join(",  ")
      : "not wrench-feasible"],
    ["grid", `${s.grid.points_per_axis}³ = ${s.grid.configurations} configurations, ${fmt(s.grid.step_deg)}° steps`],
  ];
  const tbody = $("#ws-summary tbody");
  tbody.replaceChildren();
  for (const [name, value] of rows) {
    const tr = document.createElement("tr");
    const th = document.createElement("th"); th.textContent = name;
    tr.append(th, cell(value));
    tbody.append(tr);
  }
}

async function loadWorkspace(expectedSet = null) {
  if (ws.loading) return ws.loading;  // one load at a time; the poll retries if the set changed meanwhile
  ws.tried = expectedSet;
  ws.loading = (async () => {
    $("#ws-error").textContent = "";
    $("#ws-status").textContent = "computing the maps of the active parameter set (a few seconds the first time)…";
    try {
      const s = await api("GET", "/api/workspace");
      renderWorkspaceSummary(s);
      if (s.key !== ws.shownKey) $("#ws-figures").replaceChildren(...s.figures.map(figureEl));
      ws.tried = s.parameter_set; ws.shownKey = s.key; ws.loads++;
      $("#ws-status").textContent = `maps of ${s.parameter_set}` +
        (s.cached ? " (cached)" : ` (computed in ${s.render_s.toFixed(1)} s)`);
    } catch (e) {
      $("#ws-status").textContent = "";
      $("#ws-error").textContent = "workspace: " + (e.message || e);
      ws.shownKey = null;
      $("#ws-figures").replaceChildren();
      $("#ws-summary tbody").replaceChildren();
    } finally { ws.loading = null; }
  })();
  return ws.loading;
}

async function pollActiveSet() {
  let p;
  try { p = await api("GET", "/api/params"); } catch (e) { return; }
  const sel = $("#ws-active");
  if (sel.options.length !== p.parameter_sets.length || [...sel.options].some((o, i) => o.value !== p.parameter_sets[i])) {
    sel.replaceChildren(...p.parameter_sets.map((n) => new Option(n, n)));
  }
  if (document.activeElement !== sel) sel.value = p.active;
  if (p.active !== ws.tried && !ws.loading) loadWorkspace(p.active);
}

$("#ws-active").addEventListener("change", async () => {
  const name = $("#ws-active").value;
  try {
    await api("PUT", "/api/params/active", { name });
  } catch (e) {
    $("#ws-error").textContent = "active parameter set: " + (e.message || e);
    return pollActiveSet();
  }
  $("#ws-active").blur();
  loadWorkspace(name);
});

$("#ws-refresh").addEventListener("click", () => { ws.shownKey = null; loadWorkspace($("#ws-active").value || null); });

$("#ws-2x").addEventListener("toggle", async () => {
  const box = $("#ws-2x-figures");
  if (!$("#ws-2x").open || box.childElementCount) return;
  box.textContent = "drawing the 2-X figures (several seconds the first time)…";
  try {
    const s = await api("GET", "/api/workspace?design=2x");
    box.replaceChildren(...s.figures.map(figureEl));
  } catch (e) { box.textContent = "2-X figures: " + (e.message || e); }
});

async function main() {
  config = await api("GET", "/api/config");
  const traj = $("#trajectory");
  traj.append(new Option("default for the kind", ""));
  config.trajectories.forEach((t) => traj.append(new Option(t, t)));
  traj.append(new Option("custom waypoints…", "__custom"));
  const ps = $("#parameter-set");
  config.parameter_sets.forEach((n) => ps.append(new Option(n, n, false, n === config.active_parameter_set)));
  if (config.viser_port) $("#viser").src = `${location.protocol}//${location.hostname}:${config.viser_port}/`;
  buildPlots();
  window.dispatchEvent(new CustomEvent("xneck-config", { detail: config }));  // jog.js, trajectories.js, compare.js
  connectLive();
  requestAnimationFrame(redraw);
  refreshList();
  setInterval(pollStatus, 1000);
  pollActiveSet();
  setInterval(pollActiveSet, 3000);
}

// After every script of the page ran: jog.js, trajectories.js... listen for xneck-config, which main() sends.
window.addEventListener("DOMContentLoaded", () => main().catch(showError));
