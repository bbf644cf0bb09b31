// Operator safety in the page: the e-stop stays in view (sticky header) and Escape engages it
// from anywhere in the page; its state and reason are the bridge's own (its latched e-stop in
// every MotorState of the live stream, not what this page asked); and the page says when it has
// lost the live stream, or when the bridge or the controller went silent, so a frozen plot is
// never read as live.
// Uses api(), $ and showEstop() of app.js.
"use strict";

(() => {
  const STREAM_LOST_MS = 2000;   // no live frame for this long: the stream is lost
  const BRIDGE_SILENT_MS = 1500; // frames but no new motor state: the bridge is silent
  const CONTROLLER_SILENT_MS = 1500; // frames but no new controller status: the controller is hung or gone
  const safety = (window.xneckSafety = { lastFrame: 0, lastState: 0, stateStamp: null, escapes: 0, banner: "",
                                         notSent: "", lastStatus: 0, statusStamp: null });
  // True while the live stream brings new motor states: they then show the e-stop (app.js).
  safety.liveStateFresh = () => safety.lastState > 0 && Date.now() - safety.lastState <= BRIDGE_SILENT_MS;

  // An e-stop (or release) the console refused stays said in the sticky banner until one is
  // sent: the 250 ms refresh below had wiped it within a tick, and the button's error went to the
  // form, off screen (audit of 2026-11-28).
  safety.sendFailed = (what, e) => { safety.notSent = `${what} NOT SENT: ${e.message || e}`; render(); };
  safety.sent = () => { safety.notSent = ""; render(); };
  safety.send = async (engaged, reason) => {
    try { await api("POST", "/api/system/estop", { engaged, reason }); safety.sent(); }
    catch (e) { safety.sendFailed(engaged ? "E-STOP" : "E-STOP RELEASE", e); }
  };
  const engage = (reason) => safety.send(true, reason);

  document.addEventListener("keydown", (ev) => {
    if (ev.key !== "Escape") return;
    ev.preventDefault();
    safety.escapes++;
    engage("dashboard: Escape key");
  }, true);  // capture: an input or a slider with focus does not swallow it

  window.addEventListener("xneck-frame", (ev) => {
    const now = Date.now();
    safety.lastFrame = now;
    const ss = (ev.detail.series || {}).status;
    if (ss && ss.stamp_s !== safety.statusStamp) { safety.statusStamp = ss.stamp_s; safety.lastStatus = now; }
    const st = (ev.detail.series || {}).state;
    if (st && st.stamp_s !== safety.stateStamp) {
      safety.stateStamp = st.stamp_s; safety.lastState = now;
      showEstop({ engaged: st.estop_engaged, reason: st.estop_reason, drive: st.drive, source: "bridge" });
    }
  });

  function render() {
    const now = Date.now(), box = $("#live-lost");
    let text = "";
    if (safety.lastFrame && now - safety.lastFrame > STREAM_LOST_MS) {
      text = `LIVE STREAM LOST ${((now - safety.lastFrame) / 1000).toFixed(0)} s ago: the plots and the 3D view are frozen`;
    } else if (safety.lastState && now - safety.lastState > BRIDGE_SILENT_MS) {
      text = `NO MOTOR STATE from the bridge for ${((now - safety.lastState) / 1000).toFixed(0)} s: the drives' state is unknown`;
    } else if (safety.lastStatus && now - safety.lastStatus > CONTROLLER_SILENT_MS) {
      // A hung controller's last α̂ and α^d looked live (audit of 2026-11-28: SIGSTOP for 8 s)
      text = `NO CONTROLLER STATUS for ${((now - safety.lastStatus) / 1000).toFixed(0)} s: α̂, α^d and the ` +
        `jog panel are frozen (the controller is hung or gone)`;
    }
    if (safety.notSent) text = text ? `${safety.notSent} · ${text}` : safety.notSent;
    safety.banner = text;
    box.hidden = !text;
    box.textContent = text;  // a hidden banner keeps no old text to be read as present
  }
  setInterval(render, 250);
})();

