// Comparison of 2-4 archived campaigns: a checkbox per row of the campaign list (added here, so
// app.js's table code stays as it is), then GET /api/campaigns/compare?ids=…&traces=true →
// Table 3 of the chosen runs (with their parameter sets and truths) and overlaid plots of α^d,
// α̂, α_IP per joint, e, e_α and the forces; one colour per run. Uses api(), $, renderTable of app.js.
"use strict";

(() => {
  const RUN_COLORS = ["#1565c0", "#c62828", "#2e7d32", "#6a1b9a"];
  const DASHES = [[], [6, 3], [2, 3], [10, 3, 2, 3], [1, 2], [8, 2]];
  const cmp = (window.xneckCompare = { chosen: new Set(), plots: [], shown: [] });

  function addCheckboxes() {
    const head = $("#campaigns thead tr");
    if (head && !head.querySelector(".cmp-col")) {
      const th = document.createElement("th"); th.className = "cmp-col"; th.textContent = "compare";
      head.prepend(th);
    }
    document.querySelectorAll("#campaigns tbody tr").forEach((tr) => {
      if (tr.querySelector(".cmp-pick")) return;
      const td = document.createElement("td");
      const box = document.createElement("input");
      box.type = "checkbox"; box.className = "cmp-pick"; box.value = tr.dataset.id;
      box.checked = cmp.chosen.has(tr.dataset.id);
      box.disabled = tr.querySelector(".status-running") !== null;
      box.addEventListener("change", () => {
        if (box.checked) cmp.chosen.add(box.value); else cmp.chosen.delete(box.value);
        updateButton();
      });
      td.append(box);
      tr.prepend(td);
    });
  }

  function updateButton() {
    const n = cmp.chosen.size;
    $("#compare-go").disabled = n < 2 || n > 4;
    $("#compare-go").textContent = `compare selected (${n})`;
  }

  // Series of several runs on one time axis: uPlot.join aligns the x values (gaps between them).
  function overlay(el, title, yLabel, runs) {
    const tables = [], series = [{ label: "t (s)" }];
    runs.forEach((r) => {
      if (!r.t.length) return;
      tables.push([r.t, ...r.ys]);
      r.labels.forEach((label, i) => series.push({ label, stroke: r.color, width: r.widths ? r.widths[i] : 1.2,
        dash: r.dashes ? r.dashes[i] : DASHES[i % DASHES.length], points: { show: !!r.points, size: 4 },
        spanGaps: !r.points, paths: r.points ? () => null : undefined }));
    });
    if (!tables.length) return null;
    const data = uPlot.join(tables);
    const div = document.createElement("div"); el.append(div);
    const plot = new uPlot({ title, width: el.clientWidth || 800, height: 190, series, scales: { x: { time: false } },
      axes: [{ label: "t (s)" }, { label: yLabel }], legend: { live: false } }, data, div);
    cmp.plots.push({ title, labels: series.slice(1).map((s) => s.label), plot });
    return plot;
  }

  async function compare() {
    const ids = [...cmp.chosen];
    const box = $("#compare-out");
    box.replaceChildren();
    cmp.plots.forEach((p) => p.plot.destroy()); cmp.plots = [];
    $("#compare-error").textContent = "";
    let res;
    try { res = await api("GET", `/api/campaigns/compare?traces=true&ids=${ids.map(encodeURIComponent).join(",")}`); }
    catch (e) { $("#compare-error").textContent = e.message || String(e); return; }
    box.append(renderTable(res.table));
    const runs = res.campaigns.map((c, k) => ({ ...c, color: RUN_COLORS[k % 4], tr: res.traces[c.id] }));
    const nj = runs[0].tr.alpha_d_deg.length;
    for (let j = 0; j < nj; j++) {
      const per = [];
      runs.forEach((r) => {
        per.push({ t: r.tr.t_s, ys: [r.tr.alpha_d_deg[j], r.tr.alpha_hat_deg[j]], color: r.color,
          labels: [`${r.id} α^d`, `${r.id} α̂`], dashes: [[6, 3], []], widths: [1, 1.6] });
        per.push({ t: r.tr.camera.t_s, ys: [r.tr.camera.alpha_ip_deg[j] || []], color: r.color,
          labels: [`${r.id} α_IP`], points: true });
      });
      overlay(box, `joint ${j + 1}: α^d (dashed), α̂, α_IP (dots)`, "deg", per);
    }
    const perJoint = (key, camera) => runs.map((r) => {
      const src = camera ? r.tr.camera : r.tr;
      return { t: src.t_s, ys: src[key], color: r.color, labels: src[key].map((_, j) => `${r.id} α${j + 1}`) };
    });
    overlay(box, "tracking error e = α^d − α̂ (joints: solid, dashed, dotted)", "deg", perJoint("e_deg", false));
    overlay(box, "estimation error e_α = α̂ − α_IP", "deg", perJoint("e_alpha_deg", true));
    overlay(box, "applied cable forces", "N", runs.map((r) => ({ t: r.tr.force.t_s, ys: r.tr.force.force_N,
      color: r.color, labels: r.tr.force.force_N.map((_, i) => `${r.id} f${i + 1}`) })));
    cmp.shown = ids;
  }

  window.addEventListener("xneck-config", () => {
    new MutationObserver(addCheckboxes).observe($("#campaigns tbody"), { childList: true });
    addCheckboxes();
    updateButton();
  });
  $("#compare-go").addEventListener("click", compare);
  $("#compare-clear").addEventListener("click", () => {
    cmp.chosen.clear();
    document.querySelectorAll(".cmp-pick").forEach((b) => { b.checked = false; });
    updateButton();
  });
})();
