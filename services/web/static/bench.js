// Bench page: pre-scan, scan, the operator's step-by-step instructions, today's fragments (live).
"use strict";
(() => {
  const $ = (id) => document.getElementById(id);
  const STAGES = ["scanned", "normals", "features", "matched", "rendered"];
  const MARK = { done: "✓", waiting: "…", failed: "✗", kept: "⇡", "n/a": "–" };
  const TITLE = { done: "done", waiting: "waiting", failed: "failed", kept: "kept on this machine; sent when the lab is back",
                  "n/a": "n/a: colour only, no normals" };
  const CLASS = { "n/a": "na" };   // a state as a CSS class name (no "/")
  let seq = null, current = null, prescanShownFor = null;
  // one request at a time, in order: an action asked for while another is on its way (Enter for the
  // next step while the scan request is still answering) is sent after it, not dropped; the same
  // action asked for again while it is on its way (a double click) is sent once
  let queue = Promise.resolve(), inFlight = null;

  function fragmentId() { return $("fragment-id").value.trim(); }

  function showError(err) {
    $("bench-error").hidden = !err;
    if (err) {
      $("bench-error-text").textContent = err.message || String(err);
      $("bench-error-detail").textContent = err.detail || "";
    }
  }

  // answers arrive out of order: a scan's answer, read as the capture waits at step 1, can overtake
  // the long poll's, read a moment before (it also lists today's fragments). Drawing the older one
  // took the page back from the step (to "Starting the capture…" or the pre-scan's state), where the
  // operator's Enter was ignored and the station waited for step 1 for good. So no answer older than
  // the state shown is drawn; one from another session (the station restarted, its seq start again)
  // always is
  function newer(st) {
    return !current || st.session !== current.session || st.seq >= current.seq;
  }

  function render(st) {
    const finished = st.phase === "done" && (!current || current.phase !== "done");
    current = st;
    if (finished) $("fragment-id").select();   // ready for the next label
    const waiting = st.phase === "waiting" && st.step;
    const running = ["scanning", "waiting", "saving", "prescanning"].includes(st.phase);
    $("step").hidden = !waiting;
    if (waiting) {
      $("step-count").textContent = `Step ${st.step.index} of ${st.step.total}`;
      $("step-face").textContent = `${st.step.face} face · ${st.step.rotation}°`;
      $("instruction").textContent = st.step.instruction;
      $("proceed-button").disabled = !Tessera.loggedIn();
    }
    const total = st.scans_total || 0;
    $("progress").hidden = !(total && (running || st.phase === "done"));
    const done = st.phase === "done" ? total : Math.max(0, (st.scans_done || 1) - 1);
    $("progress-bar").style.width = total ? `${Math.round(100 * done / total)}%` : "0";
    $("bench-message").textContent = waiting ? "" : (st.message || "");
    $("bench-message").className = "message" + (st.phase === "done" && st.delivery && !st.delivery.sent ? " notice" : "");
    showError(st.phase === "error" ? st.error : null);
    const canWrite = Tessera.loggedIn() && st.phase !== "none";
    $("scan-button").disabled = !canWrite || running;
    $("prescan-button").disabled = !canWrite || running;
    $("empty-glass-button").disabled = !canWrite || running;
    $("cancel-button").disabled = !canWrite;
    $("login-needed").hidden = Tessera.loggedIn();
    if (st.fragment && (st.phase === "idle" || st.phase === "error") && prescanShownFor !== `${st.fragment}:${st.seq}`) {
      prescanShownFor = `${st.fragment}:${st.seq}`;
      const img = $("prescan-image");
      img.onload = () => { $("prescan").hidden = false; };
      img.onerror = () => { $("prescan").hidden = true; };
      img.src = `/api/bench/prescan.png?t=${st.seq}`;
    }
    if (running && st.phase !== "prescanning") $("prescan").hidden = true;
  }

  function renderFragments(rows) {
    const body = $("fragments").tBodies[0];
    body.replaceChildren(...rows.map((r) => {
      const tr = Tessera.el("tr", { "data-fragment": r.fragment });
      const link = Tessera.el("a", { href: `/review?fragment=${encodeURIComponent(r.fragment)}`, text: r.fragment });
      tr.append(Tessera.el("td", {}, link));
      for (const s of STAGES) {
        const state = (r.stages || {})[s] || "waiting";
        const cell = Tessera.el("td", { "data-stage": s, "data-state": state });
        const title = (r.errors || {})[s] ? `${TITLE[state]}: ${r.errors[s]}` : (s === "scanned" && r.scanned_at ? `scanned ${Tessera.clock(r.scanned_at)}` : TITLE[state]);
        cell.append(Tessera.el("span", { class: `st ${CLASS[state] || state}`, text: MARK[state] || "?", title }));
        tr.append(cell);
      }
      return tr;
    }));
  }

  // the live poll must outlive anything: a request that never answers is given up after
  // POLL_TIMEOUT_MS (the server answers a long poll within seconds) and a failure to draw one answer
  // is logged, so the page never freezes on a step the station has left
  const POLL_TIMEOUT_MS = 30000, ACTION_TIMEOUT_MS = 120000;
  async function poll() {
    for (;;) {
      const url = seq === null ? "/api/bench" : `/api/bench?after=${seq}`;
      const r = await Tessera.api("GET", url, undefined, { timeoutMs: POLL_TIMEOUT_MS });
      let drawn = false;
      if (r.ok) {
        try {
          if (newer(r.data.bench)) render(r.data.bench);
          seq = current.seq;   // wait for a change from what is shown, whichever answer brought it
          renderFragments(r.data.fragments || []);
          drawn = true;
        } catch (e) { console.error("bench: could not show the station's state", e); }
      } else {
        $("bench-message").textContent = r.data.error || "The station does not answer.";
      }
      if (!drawn) await new Promise((res) => setTimeout(res, 2000));
    }
  }

  function act(url, body) {
    const key = url + JSON.stringify(body);
    if (key === inFlight) return queue;
    queue = queue.then(async () => {
      inFlight = key;
      try {
        // a request that never answers must not hold the actions behind it (the scanner's own
        // pre-scan answers within seconds; a real one well inside ACTION_TIMEOUT_MS)
        const r = await Tessera.api("POST", url, body, { timeoutMs: ACTION_TIMEOUT_MS });
        if (!r.ok) showError({ message: r.data.error || `refused (${r.status})` });
        else if (newer(r.data.bench)) render(r.data.bench);   // the long poll may have shown a newer state
      } catch (e) {   // a failed action must not stop the ones queued behind it
        console.error("bench: action failed", url, e);
      } finally { inFlight = null; }
    });
    return queue;
  }

  $("fragment-form").addEventListener("submit", (ev) => {
    ev.preventDefault();
    if (!fragmentId()) { showError({ message: "Enter the fragment's ID first (type it or scan its label)." }); return; }
    act("/api/bench/scan", { fragment: fragmentId() });
  });
  $("prescan-button").addEventListener("click", () => {
    if (!fragmentId()) { showError({ message: "Enter the fragment's ID first (type it or scan its label)." }); return; }
    $("bench-message").textContent = "Pre-scanning the glass…";
    act("/api/bench/prescan", { fragment: fragmentId() });
  });
  $("empty-glass-button").addEventListener("click", () => act("/api/bench/empty-glass", {}));
  $("proceed-button").addEventListener("click", () => {
    if (current && current.step) act("/api/bench/proceed", { step: current.step.index });
  });
  $("cancel-button").addEventListener("click", () => act("/api/bench/cancel", {}));
  document.addEventListener("keydown", (ev) => {
    if (ev.key === "Enter" && current && current.phase === "waiting" && !Tessera.typingInField(ev)) {
      ev.preventDefault();
      $("proceed-button").click();
    }
  });
  poll();
})();
