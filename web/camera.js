// The camera panel (issue 15): the latest camera frame with the markers the detector found drawn
// over it, α_IP per joint with its confidence ("missing" for a joint the camera did not measure,
// never a number), the detection health, and a clear "no camera" state. A camera moved since its
// calibration reports every joint missing: the card says why (health.moved_reason, from the camera
// process's health on the bus) until its base-plate references are back.
// Data: GET /api/camera (metadata, markers, α_IP, health) then GET /api/camera/frame.jpg; the
// overlay is drawn only when the JPEG's X-Frame-Seq is the frame the markers belong to.
(function () {
  "use strict";
  const POLL_MS = 300;
  // Marker colours of the bars, base up (twin/camera/layout.py): red, green, blue, yellow, cyan.
  const BAR_COLORS = ["#ff3b30", "#30d158", "#0a84ff", "#ffd60a", "#40e0ff"];
  const REF_COLOR = "#ff2dd4";  // base-plate reference markers (magenta)
  const DEG = 180 / Math.PI;
  const stats = { polls: 0, frames: 0, markers: 0, state: "none", key: null, damaged: null };
  const DAMAGED = ", picture damaged (not shown)";
  let dimmed = false;
  window.xneckCamera = stats;  // for tests and the curious

  const canvas = document.getElementById("camera-canvas");
  const stateEl = document.getElementById("camera-state");
  const alphaEl = document.getElementById("camera-alpha");
  const reasonEl = document.getElementById("camera-reason");
  if (!canvas || !stateEl || !alphaEl || !reasonEl) return;
  reasonEl.style.color = "#c62828";
  canvas.style.width = "100%";
  canvas.style.height = "auto";
  canvas.style.background = "#1f2933";
  const ctx = canvas.getContext("2d");

  // A text said on the canvas (no camera, no picture...) fitted to it at any panel width (user audit
  // of session 42: "no picture: twin-noise sends α_IP only" was cut at both ends): on one line in the
  // largest font up to a tenth of the canvas's height that fits 90 % of its width; where that font
  // would be under MIN_SCREEN_PX on screen (the canvas is scaled to its card), the words wrapped onto
  // lines in the font that is (or the largest that fits, for a word too long to fit at all).
  const MIN_SCREEN_PX = 12;
  const fontOf = (px) => `${px}px system-ui, sans-serif`;

  function wrap(words, px, maxWidth) {
    ctx.font = fontOf(px);
    const lines = [];
    for (const w of words) {
      const line = lines.length ? `${lines[lines.length - 1]} ${w}` : w;
      if (lines.length && ctx.measureText(line).width <= maxWidth) lines[lines.length - 1] = line;
      else lines.push(w);
    }
    return lines;
  }

  function fitText(text) {
    const maxWidth = 0.9 * canvas.width, maxHeight = 0.9 * canvas.height;
    const scale = canvas.clientWidth > 0 ? canvas.clientWidth / canvas.width : 1;  // screen px per canvas px
    let px = Math.max(1, Math.round(canvas.height / 10));
    ctx.font = fontOf(px);
    const width = ctx.measureText(text).width;
    if (width <= maxWidth) return { px, lines: [text] };
    const oneLine = Math.floor(px * maxWidth / width);
    if (oneLine * scale >= MIN_SCREEN_PX) return { px: oneLine, lines: [text] };
    px = Math.min(px, Math.ceil(MIN_SCREEN_PX / scale));
    const words = text.split(/\s+/).filter(Boolean);
    for (; px > 1; px--) {
      const lines = wrap(words, px, maxWidth);
      if (lines.length * 1.25 * px <= maxHeight && lines.every((l) => ctx.measureText(l).width <= maxWidth)) {
        return { px, lines };
      }
    }
    return { px: 1, lines: [text] };
  }

  function blank(text) {
    ctx.fillStyle = "#1f2933";
    ctx.fillRect(0, 0, canvas.width, canvas.height);
    ctx.fillStyle = "#cfd6dd";
    const { px, lines } = fitText(text);
    ctx.font = fontOf(px);
    ctx.textAlign = "center";
    ctx.textBaseline = "middle";
    const step = 1.25 * px;
    lines.forEach((line, k) => ctx.fillText(line, canvas.width / 2, canvas.height / 2 + (k - (lines.length - 1) / 2) * step));
  }

  function setState(state, text) {
    stats.state = state;
    stateEl.textContent = text;
    stateEl.style.color = state === "live" ? "#2e7d32" : state === "stale" ? "#ef6c00" : "#777";
  }

  function dim() {
    if (stats.frames > 0 && !dimmed) {  // the last picture stays, greyed: it is not now
      ctx.fillStyle = "rgba(31,41,51,0.6)";
      ctx.fillRect(0, 0, canvas.width, canvas.height);
      dimmed = true;
    }
  }

  // Why every joint is missing, when it is not the markers' fault; and a second camera on the bus
  // (health.warning: its α_IP was shown as this one's rate, and a campaign records only one).
  function showReason(reason, warning) {
    const said = [reason ? `every joint missing: ${reason}` : "", warning || ""].filter(Boolean);
    reasonEl.textContent = said.join("; ");
    reasonEl.hidden = said.length === 0;
  }

  function fmt(x, digits) { return x === null || x === undefined ? "–" : Number(x).toFixed(digits); }

  function showAlpha(alpha, missingFraction) {
    alphaEl.replaceChildren();
    if (!alpha) return;
    alpha.alpha_ip_rad.forEach((a, j) => {
      const row = document.createElement("div");
      const c = alpha.confidence[j];  // the publisher's grade; none, or a list of another length (any peer may publish)
      const conf = typeof c === "number" ? c : null;
      if (a === null) {
        row.textContent = `α${j + 1}  missing`;
        row.style.color = "#c62828";
      } else {
        row.textContent = `α${j + 1}  ${(a * DEG).toFixed(1)}°` + (conf === null ? "" : `  confidence ${conf.toFixed(2)}`);
      }
      const lost = missingFraction && missingFraction[j];
      if (lost) row.textContent += a === null ? `  (${Math.round(100 * lost)} % of the last 2 s)` : `  (missing in ${Math.round(100 * lost)} % of the last 2 s)`;
      alphaEl.appendChild(row);
    });
  }

  function drawOverlay(f) {
    const bars = new Map();
    f.marker_bar.forEach((bar, k) => {
      const p = [f.markers_px[2 * k], f.markers_px[2 * k + 1]];
      if (!bars.has(bar)) bars.set(bar, []);
      bars.get(bar).push(p);
    });
    const r = Math.max(6, f.width / 110);
    ctx.lineWidth = Math.max(2, f.width / 400);
    for (const [bar, pts] of bars) {
      const color = bar < 0 ? REF_COLOR : BAR_COLORS[bar % BAR_COLORS.length];
      ctx.strokeStyle = color;
      if (bar >= 0 && pts.length === 2) {  // the bar through its two markers
        ctx.setLineDash([r, r / 2]);
        ctx.beginPath();
        ctx.moveTo(pts[0][0], pts[0][1]);
        ctx.lineTo(pts[1][0], pts[1][1]);
        ctx.stroke();
        ctx.setLineDash([]);
      }
      for (const [x, y] of pts) {
        ctx.beginPath();
        ctx.arc(x, y, r, 0, 2 * Math.PI);
        ctx.stroke();
        ctx.beginPath();  // a cross at the sub-pixel centroid
        ctx.moveTo(x - r / 2, y); ctx.lineTo(x + r / 2, y);
        ctx.moveTo(x, y - r / 2); ctx.lineTo(x, y + r / 2);
        ctx.stroke();
      }
    }
    stats.markers = f.marker_bar.length;
  }

  async function loadFrame(f) {
    const r = await fetch(f.url, { cache: "no-store" });
    if (!r.ok) return;
    if (r.headers.get("X-Frame-Seq") !== String(f.seq)) return;  // a newer frame: its markers come next poll
    let bitmap;
    try { bitmap = await createImageBitmap(await r.blob()); } catch (e) {
      // A JPEG whose header is right and whose picture is not (any peer may publish): said as
      // such, not as the console being unreachable, fetched once, and the last picture greyed.
      stats.damaged = `${f.seq}@${f.capture_stamp_s}`;
      stateEl.textContent += DAMAGED;
      if (stats.frames > 0) dim(); else blank("picture damaged");
      return;
    }
    canvas.width = f.width;
    canvas.height = f.height;
    ctx.drawImage(bitmap, 0, 0, f.width, f.height);
    bitmap.close();
    drawOverlay(f);
    dimmed = false;
    stats.frames += 1;
    stats.key = `${f.seq}@${f.capture_stamp_s}`;
  }

  // A live camera's bridge clock (server/camera_feed.py clock_status): its uncertainty and the age of
  // its last sync; a stale or re-synchronising clock said in words.
  function clockText(c) {
    if (!c) return "";
    const u = c.uncertainty_us === null || c.uncertainty_us === undefined ? "?" : fmt(c.uncertainty_us / 1000, 1);
    if (c.resyncing) return `; clock of ${c.bridge} jumped: re-synchronising (no α_IP meanwhile)`;
    if (c.uncertain) return `; clock of ${c.bridge} ± ${u} ms after ${c.age_s} s without a sync: no α_IP until it answers`;
    if (c.stale) return `; clock STALE: no sync with ${c.bridge} for ${c.age_s} s (± ${u} ms)`;
    return `; clock ± ${u} ms, synced ${c.age_s} s ago`;
  }

  async function poll() {
    try {
      const r = await fetch("/api/camera", { cache: "no-store" });
      const s = await r.json();
      const h = s.health;
      if (!h) {
        setState("none", "no camera");
        if (stats.frames === 0) blank("no camera");
      } else {
        const missing = h.missing_joints.length ? `, missing joint ${h.missing_joints.join(", ")}` : "";
        const age = h.frame_age_s === null || h.frame_age_s === undefined ? "no picture" : `picture ${fmt(h.frame_age_s, 1)} s old`;
        if (h.fresh) {
          setState("live", `${h.source}: ${fmt(h.rate_hz, 0)} Hz${missing}, ${h.dropped} dropped, ${age}${clockText(h.clock)}`);
        } else {
          // Stale by the console's one rule (server.live.fresh_camera): the live frames carry no α_IP
          // then, and the joint plots draw a gap.
          setState("stale", `camera stale: ${h.source} silent for ${fmt(h.age_s, 0)} s`);
        }
      }
      showAlpha(h && h.fresh ? s.alpha : null, h ? h.missing_fraction : null);
      showReason(h ? h.moved_reason : null, h ? h.warning : null);
      if (!h || !h.fresh) {
        dim();
      } else if (s.frame && `${s.frame.seq}@${s.frame.capture_stamp_s}` === stats.damaged) {
        stateEl.textContent += DAMAGED;
      } else if (s.frame && `${s.frame.seq}@${s.frame.capture_stamp_s}` !== stats.key) {
        await loadFrame(s.frame);
      } else if (!s.frame && stats.frames === 0) {
        blank(`no picture: ${h.source} sends α_IP only`);  // e.g. the twin's white-noise camera
      }
    } catch (e) {
      setState("none", "no camera (console unreachable)");
      showReason(null);
    }
    stats.polls += 1;
    setTimeout(poll, POLL_MS);
  }

  blank("no camera");
  poll();
})();
