// Jog: one slider per joint sends the target pose to POST /api/jog (the controller moves there by
// its gentle approach and holds it). While a slider is dragged the newest target goes at most
// every SEND_PERIOD_MS (the server refuses faster, 429); releasing it sends where it stopped, and
// the neck holds there. "hold here" stops the move where the neck is. A target the console refuses
// (409, 422, 503) leaves the sliders where the neck goes: the last target accepted or, with none
// standing (none yet, "hold here", a campaign since), α̂. Uses api(), $, DEG and runningId of app.js.
"use strict";

(() => {
  const SEND_PERIOD_MS = 300;
  // target: the last target accepted (deg) while it stands, null when none does.
  // ended: why the last jog accepted was cut short (a process death; "" if it was not).
  const jog = (window.xneckJog = { sent: 0, accepted: 0, last: null, error: "", alphaHat: null, target: null,
                                   ended: "" });
  let sliders = [];
  let timer = null, lastSent = 0, inFlight = false, pending = false;

  function target() { return sliders.map((s) => Number(s.value)); }
  const degrees = (alpha) => `[${alpha.map((a) => a.toFixed(1)).join(", ")}]°`;

  function show(alpha) {  // the sliders and their values at alpha (deg)
    alpha.forEach((a, j) => {
      if (!sliders[j]) return;
      sliders[j].value = a.toFixed(1);
      sliders[j].nextSibling.textContent = Number(sliders[j].value).toFixed(1) + "°";
    });
  }

  function say(text, isError) {
    $("#jog-status").textContent = isError ? "" : text;
    $("#jog-error").textContent = isError ? text : "";
    jog.error = isError ? text : "";
  }

  async function send() {
    clearTimeout(timer); timer = null;
    if (inFlight) { pending = true; return; }
    inFlight = true; pending = false; lastSent = Date.now(); jog.sent++;
    const alpha = target();
    try {
      const r = await api("POST", "/api/jog", { alpha_deg: alpha });
      jog.accepted++; jog.last = r; jog.target = alpha; jog.ended = "";
      say(`→ ${degrees(alpha)} in ${r.duration_s.toFixed(1)} s (${r.jog_id})`, false);
    } catch (e) {
      if (String(e.message).startsWith("429")) pending = true;  // too fast: the newest target goes next
      else refused(alpha, e);
    } finally {
      inFlight = false;
      if (pending) schedule();
    }
  }

  // Audit of 2026-11-29: a refused target stayed on the sliders as if the neck were going there.
  // Unless a newer target waits to be sent (a drag goes on), they go back to where it goes.
  function refused(alpha, e) {
    const back = pending || timer !== null ? null : jog.target || jog.alphaHat;
    if (back) show(back);
    say(`refused ${degrees(alpha)}: ${e.message || e}` + (back ? ` — back to ${degrees(target())}, ` +
      (jog.target ? "the last target accepted" : "where the neck is") : ""), true);
  }

  function schedule() {
    clearTimeout(timer);
    timer = setTimeout(send, Math.max(0, SEND_PERIOD_MS - (Date.now() - lastSent)));
  }

  function build(config) {
    const box = $("#jog-sliders");
    box.replaceChildren();
    sliders = [];
    for (let j = 0; j < config.n_joints; j++) {
      const row = document.createElement("label");
      row.className = "jog-row";
      const name = document.createElement("span"); name.textContent = `α${j + 1}`;
      const s = document.createElement("input");
      Object.assign(s, { type: "range", min: -config.alpha_max_deg, max: config.alpha_max_deg, step: 0.5, value: 0 });
      s.id = `jog-${j + 1}`;
      const val = document.createElement("output"); val.textContent = "0.0°";
      const hat = document.createElement("small"); hat.className = "jog-hat"; hat.id = `jog-hat-${j + 1}`;
      s.addEventListener("input", () => { val.textContent = Number(s.value).toFixed(1) + "°"; schedule(); });
      s.addEventListener("change", () => { clearTimeout(timer); send(); });  // released: where it stopped
      row.append(name, s, val, hat);
      box.append(row);
      sliders.push(s);
    }
    $("#jog-limits").textContent = `±${config.alpha_max_deg}°`;
  }

  window.addEventListener("xneck-config", (ev) => build(ev.detail));

  window.addEventListener("xneck-frame", (ev) => {
    const st = (ev.detail.series || {}).status;
    if (!st) return;
    const first = jog.alphaHat === null;
    jog.alphaHat = st.alpha_hat_rad.map((a) => a * DEG);
    jog.alphaHat.forEach((a, j) => {
      const el = document.getElementById(`jog-hat-${j + 1}`);
      if (el) el.textContent = `α̂ ${a.toFixed(1)}°`;
    });
    if (first) show(jog.alphaHat);  // start from where the neck is, not from zero
    if (runningId !== null) jog.target = null;  // a campaign has the neck: no jog target stands
  });

  // A jog a death of the controller or the bridge cut short (health.jog.ended, the cause xneck up
  // told the console): said here, not only in the header, and its target no longer stands (the
  // bridge holds the neck where it was). Said once per jog; a newer jog's answer replaces it.
  let endedSaid = "";
  window.addEventListener("xneck-health", (ev) => {
    const last = ev.detail.jog;
    if (!last || !last.ended || !jog.last || last.jog_id !== jog.last.jog_id || endedSaid === last.jog_id) return;
    endedSaid = last.jog_id;
    jog.target = null;
    jog.ended = last.ended;
    say(`jog ${last.jog_id} to ${degrees(last.to_deg)} cut short: ${last.ended}`, true);
  });

  $("#jog-hold").addEventListener("click", async () => {
    clearTimeout(timer); timer = null; pending = false;
    try {
      const r = await api("POST", "/api/jog/stop");
      jog.target = null;  // the neck holds where it is
      say(`holding (${r.stopped.join(", ") || "nothing moving"})`, false);
    }
    catch (e) { say(e.message || String(e), true); }
  });
})();
