// Live error plots beside the joint plots: the tracking error e = α^d − α̂ (the controller's
// status) and the estimation error e_α = α̂ − α_IP at each new camera frame (α̂ of the newest
// status: within a live frame, 33 ms, of the capture; the archive's metrics interpolate). Uses
// makePlot, push, drawLive, livePaused and DEG of app.js.
"use strict";

(() => {
  const COLORS = ["#1565c0", "#2e7d32", "#c62828", "#6a1b9a", "#ef6c00", "#00838f"];
  const live = (window.xneckErrors = { e: null, ea: null, lastCamera: null });
  let dirty = false;

  window.addEventListener("xneck-config", (ev) => {
    const nj = ev.detail.n_joints;
    const labels = Array.from({ length: nj }, (_, j) => `α${j + 1}`);
    for (const [key, id, title] of [["e", "plot-e", "tracking error e = α^d − α̂"],
                                    ["ea", "plot-ealpha", "estimation error e_α = α̂ − α_IP"]]) {
      const div = document.createElement("div"); div.id = id;
      $("#plots").append(div);
      live[key] = makePlot(div, title, labels, COLORS, "deg", 1);
    }
  });

  window.addEventListener("xneck-frame", (ev) => {
    const s = ev.detail.series || {};
    if (!live.e || !s.status) return;
    push(live.e, s.status.stamp_s, s.status.e_rad.map((e) => e * DEG));
    const cam = s.camera;
    if (cam && cam.stamp_s !== live.lastCamera) {
      live.lastCamera = cam.stamp_s;
      push(live.ea, cam.stamp_s, cam.alpha_ip_rad.map((ip, j) => (ip === null ? null : (s.status.alpha_hat_rad[j] - ip) * DEG)));
    }
    dirty = true;
  });

  (function draw() {
    if (dirty && !livePaused) {
      dirty = false;
      [live.e, live.ea].forEach(drawLive);
    }
    requestAnimationFrame(draw);
  })();
})();

// Pause / resume of the live plots (app.js's livePaused): paused, they show the last minute.
(() => {
  const btn = document.createElement("button");
  btn.id = "live-pause"; btn.type = "button"; btn.textContent = "pause";
  btn.title = "Freeze the live plots and scroll back over the last minute (drag to zoom, double click to zoom out)";
  btn.addEventListener("click", () => {
    livePaused = !livePaused;
    btn.textContent = livePaused ? "resume" : "pause";
    if (livePaused) [forcePlot, ...jointPlots, window.xneckErrors.e, window.xneckErrors.ea].filter(Boolean).forEach(drawLive);
  });
  window.addEventListener("xneck-config", () => $("#plots h2").append(" ", btn));
})();
