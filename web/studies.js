// The Studies card (issue 19): start a Monte Carlo / identification / design study on Dask, watch
// its progress live, read its summary (metrics per law, Spearman sensitivities) and figures.
// Data: /api/studies (POST needs the token, as every mutating route), /api/studies/{id}.
(function () {
  "use strict";
  const POLL_MS = 1000;
  const card = document.getElementById("studies");
  if (!card || typeof api !== "function") return;
  const el = (id) => document.getElementById(id);
  const form = { kind: el("st-kind"), samples: el("st-samples"), vary: el("st-vary"), laws: el("st-laws"),
                 truth: el("st-truth"), seed: el("st-seed"), estimator: el("st-estimator") };
  const list = el("st-list").querySelector("tbody");
  const out = el("st-out");
  const errorEl = el("st-error");
  let selected = null;
  let timer = null;
  let live = false;  // a study was running at the last poll
  window.xneckStudies = { polls: 0 };

  function showError(e) { errorEl.textContent = e ? String(e.message || e) : ""; }
  function fmt(x) { return x === null || x === undefined ? "–" : Number(x).toPrecision(3); }

  function body() {
    const kind = form.kind.value;
    const b = { kind, samples: Number(form.samples.value) || 1, seed: Number(form.seed.value) || 0,
                vary: form.vary.value.split("\n").map((s) => s.trim()).filter(Boolean), truth: form.truth.value };
    if (kind === "control") b.laws = form.laws.value.split(/[ ,]+/).filter(Boolean).map(Number);
    if (kind === "identification") b.estimator = form.estimator.value;
    return b;
  }

  async function start() {
    showError(null);
    try {
      const r = await api("POST", "/api/studies", body());
      selected = r.id;
      await refresh();
    } catch (e) { showError(e); }
  }

  function row(s) {
    const tr = document.createElement("tr");
    const pct = Math.round(100 * s.fraction);
    [s.id, s.kind, s.state + (s.error ? ": " + s.error : ""), `${s.runs_done}/${s.runs_total}`].forEach((t) => {
      const td = document.createElement("td"); td.textContent = t; tr.appendChild(td);
    });
    const bar = document.createElement("td");
    const p = document.createElement("progress"); p.max = 100; p.value = pct; bar.appendChild(p);
    tr.appendChild(bar);
    tr.style.cursor = "pointer";
    if (s.id === selected) tr.style.fontWeight = "bold";
    tr.addEventListener("click", () => { selected = s.id; refresh(); });
    return tr;
  }

  function summaryTable(summary) {
    const table = document.createElement("table");
    table.className = "ws-summary";
    const head = table.insertRow();
    // n: the runs a statistic is over (finished, finite value) of the law's runs (every outcome)
    ["", "metric", "median", "p5", "p95", "n of runs"].forEach((t) => { const th = document.createElement("th"); th.textContent = t; head.appendChild(th); });
    Object.entries(summary.metrics).forEach(([law, metrics]) => {
      Object.entries(metrics).forEach(([name, s]) => {
        if (!s) return;
        const tr = table.insertRow();
        [lawName(law), name, fmt(s.median), fmt(s.p5), fmt(s.p95), s.of === undefined ? s.n : `${s.n} of ${s.of}`]
          .forEach((t) => { tr.insertCell().textContent = t; });
      });
    });
    return table;
  }

  function lawName(law) { return law === "0" ? "design" : `law ${law}`; }

  // What became of each law's runs ("law 1: 150 finished, 50 diverged"): the statistics are over the finished ones.
  function outcomesPerLaw(summary) {
    const div = document.createElement("div");
    div.className = "st-outcomes";
    Object.entries(summary.outcomes_per_law || {}).forEach(([law, counts]) => {
      const line = document.createElement("div");
      line.textContent = `${lawName(law)}: ` + Object.entries(counts).map(([o, n]) => `${n} ${o}`).join(", ");
      div.appendChild(line);
    });
    return div;
  }

  function showStudy(p) {
    out.replaceChildren();
    const head = document.createElement("div");
    head.textContent = `${p.id}: ${p.state}, ${p.runs_done}/${p.runs_total} runs` + (p.message ? ` (${p.message})` : "");
    out.appendChild(head);
    if (p.summary) {
      if (p.summary_stale) {  // rows added since it was written (a study resumed, then the console stopped)
        const note = document.createElement("div");
        note.className = "st-stale";
        note.textContent = `summary of ${p.summary.runs_done} runs, ${p.runs_done} on disk: being recomputed`;
        out.appendChild(note);
      }
      out.appendChild(outcomesPerLaw(p.summary));
      out.appendChild(summaryTable(p.summary));
      const figs = document.createElement("div");
      figs.className = "ws-figures";
      p.figures.forEach((url) => {
        const img = document.createElement("img");
        img.src = `${url}?v=${p.summary.runs_done}-${p.runs_done}`; img.alt = url.split("/").pop(); img.style.maxWidth = "100%";
        figs.appendChild(img);
      });
      out.appendChild(figs);
    }
  }

  async function refresh() {
    window.xneckStudies.polls += 1;
    try {
      const r = await api("GET", "/api/studies");
      list.replaceChildren(...r.studies.map(row));
      if (!selected && r.studies.length) selected = r.studies[0].id;
      const shown = selected ? await api("GET", `/api/studies/${selected}`) : null;
      if (shown) showStudy(shown);
      // Live progress while a study runs: the list's word or the shown study's (either may lag the other).
      live = r.studies.some((s) => s.state === "running") || (shown !== null && shown.state === "running");
      clearTimeout(timer);
      if (live) timer = setTimeout(refresh, POLL_MS);
      else if (shown !== null && shown.summary_stale) timer = setTimeout(refresh, 2 * POLL_MS);  // until it is redrawn
    } catch (e) {
      showError(e);
      clearTimeout(timer);
      if (live) timer = setTimeout(refresh, 5 * POLL_MS);  // one failed poll (a busy console) does not end live progress
    }
  }

  el("st-start").addEventListener("click", start);
  el("st-refresh").addEventListener("click", refresh);
  form.kind.addEventListener("change", () => {
    form.laws.disabled = form.kind.value !== "control";
    // an identification on the model truth finds the file it started from: robot, as the API's default
    form.truth.value = form.kind.value === "identification" ? "robot" : "model";
  });
  refresh();
})();
