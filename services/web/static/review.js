// Review page: the queue of pending proposals, pictures of the proposed join, verdicts by keyboard.
"use strict";
(() => {
  const $ = (id) => document.getElementById(id);
  const VIEWS = ["joined-colour", "joined-relief", "pair-colour", "pair-relief"];
  let items = [], index = -1, filter = document.querySelector(".review").dataset.fragment || "";
  const skipped = new Set();
  // the conservator's correction of the proposed pose: B turned about its centre (deg), moved (mm)
  // one step of the pose controls, in mm and degrees alike: fine to coarse, X (or the step button) cycles it; a pose
  // off by centimetres along the crack (RePAIR's near misses: 8–16 mm, docs/matching.md) is a few coarse steps
  const STEPS = [0.5, 2, 5];
  let step = 0;
  let adjust = { turn_deg: 0, shift_x_mm: 0, shift_y_mm: 0 };
  // the candidate poses of the current proposal, as adjustments of its pose with a label, fetched when it is
  // selected: its own pose first, then — where the pair's newcomer fits a corner of a confirmed cluster — that
  // fit, then the docking's others, best first; `shown` is the one on screen
  const ZERO = { turn_deg: 0, shift_x_mm: 0, shift_y_mm: 0 };
  let candidates = null, shown = 0;
  // keys pressed while a verdict is being sent wait here and are played in order once it has returned (they were
  // dropped): each with the proposal on screen when it was pressed and the correction then shown, so a verdict key
  // goes to that proposal, at that pose, never to the one the page has moved on to, which the conservator has not seen
  const MAX_WAITING_KEYS = 16;
  let sending = false;
  const waiting = [];

  function adjusted() { return adjust.turn_deg !== 0 || adjust.shift_x_mm !== 0 || adjust.shift_y_mm !== 0; }

  // the query of a joined picture of p at adjustment a (px: drawn at most that many pixels across). The pose the
  // proposal stands at is in it: a decided proposal's moves to its verdict's pose once the matcher records it, and
  // the browser must not show the picture it cached of the one before
  function joinedQuery(p, a, px) {
    const at = p.pose ? [["at", [p.pose.angle_deg, p.pose.tx_mm, p.pose.ty_mm].map((v) => v.toFixed(4)).join(",")]] : [];
    const moved = a.turn_deg !== 0 || a.shift_x_mm !== 0 || a.shift_y_mm !== 0;
    const args = [...at, ...(moved ? Object.entries(a).map(([k, v]) => [k, v.toFixed(3)]) : []), ...(px ? [["px", px]] : [])];
    return args.length ? "?" + new URLSearchParams(args) : "";
  }

  // the candidate poses side by side, small (up to STRIP of them), so the right one is found at a glance rather
  // than by stepping with P: on RePAIR it is among them for a third of the true pairs, and first for a fifth
  const STRIP = 8, STRIP_PX = 160;
  function showStrip(p) {
    const strip = $("pose-candidates");
    strip.replaceChildren();
    $("pose-candidates-title").hidden = !candidates || candidates.length < 2;
    if (!candidates || candidates.length < 2) return;
    candidates.slice(0, STRIP).forEach((c, k) => {
      const b = document.createElement("button");
      b.type = "button";
      b.title = `${c.label ? c.label + ", " : ""}candidate pose ${k + 1} of ${candidates.length}`;
      const img = document.createElement("img");
      img.alt = b.title;
      img.src = `/api/review/picture/${p.id}/joined-colour.png${joinedQuery(p, c.adjust, STRIP_PX)}`;
      b.append(img);
      b.addEventListener("click", () => {
        b.blur();   // the page's keys (C, R, P, the pose's) act on the page, not on this button
        if (items[index] !== p) return;
        shown = k;
        adjust = { ...c.adjust };
        showPictures(p);
      });
      strip.append(b);
    });
    markStrip();
  }

  function markStrip() {
    const c = candidates && candidates[shown];
    const same = c && ["turn_deg", "shift_x_mm", "shift_y_mm"].every((k) => c.adjust[k] === adjust[k]);
    [...$("pose-candidates").children].forEach((b, k) => b.classList.toggle("current", !!same && k === shown));
  }

  function showPictures(p) {
    const q = joinedQuery(p, adjust);
    for (const v of VIEWS) {
      const img = $(v);
      img.alt = `${v} of ${p.fragment_a} and ${p.fragment_b}`;
      img.src = `/api/review/picture/${p.id}/${v}.png${v.startsWith("joined") ? q : ""}`;
    }
    const c = candidates && candidates[shown];
    const same = c && ["turn_deg", "shift_x_mm", "shift_y_mm"].every((k) => c.adjust[k] === adjust[k]);
    const which = same && candidates.length > 1
      ? `${c.label ? c.label + ", " : ""}candidate pose ${shown + 1} of ${candidates.length}: ` : "";
    $("pose-adjust").textContent = adjusted()
      ? `${which}B turned ${adjust.turn_deg.toFixed(1)}°, moved (${adjust.shift_x_mm.toFixed(1)}, ${adjust.shift_y_mm.toFixed(1)}) mm — the verdict keeps this pose`
      : (candidates && candidates.length === 1 ? "no other candidate pose" : "");
    markStrip();
  }

  async function loadCandidates(p) {
    const r = await Tessera.api("GET", `/api/review/alternatives/${p.id}`);
    if (items[index] !== p) return;
    const alts = r.ok ? r.data.alternatives : [];
    candidates = [{ adjust: ZERO, label: p.verdict_pose ? `the pose kept with the ${p.verdict} verdict` : "" },
      ...alts.map((a) => ({ adjust: a, label: "" }))];
    if (r.ok && r.data.proposed) {   // a decided proposal stands at its verdict's pose: the matcher's is one step away
      const a = { turn_deg: r.data.proposed.turn_deg, shift_x_mm: r.data.proposed.shift_x_mm, shift_y_mm: r.data.proposed.shift_y_mm };
      candidates.splice(1, 0, { adjust: a, label: "the matcher's proposed pose" });
    }
    const fit = r.ok ? r.data.cluster : null;
    if (fit) {   // offered, not shown first: in review sessions it was the right pose less often than the pair's
      const a = { turn_deg: fit.turn_deg, shift_x_mm: fit.shift_x_mm, shift_y_mm: fit.shift_y_mm };
      candidates.splice(1, 0, { adjust: a, label: `fitted into the corner of ${fit.faces.join(" and ")}` });
    } else if (r.ok && r.data.docking) {    // the reconstruction is still docking: ask again
      setTimeout(() => { if (items[index] === p && shown === 0) loadCandidates(p); }, 3000);
    }
    if (!adjusted()) shown = 0;
    showStrip(p);
    showPictures(p);
  }

  // step through the candidate poses (P, shift+P backwards)
  async function otherPose(step) {
    const p = items[index];
    if (!p || !p.pose) return;
    if (!candidates) await loadCandidates(p);
    if (items[index] !== p || !candidates) return;
    const n = candidates.length;
    shown = ((shown + step) % n + n) % n;
    adjust = { ...candidates[shown].adjust };
    showPictures(p);
  }

  function nudge(turn, dx, dy) {
    const p = items[index];
    if (!p || !p.pose) return;
    if (turn === null) {   // back to the proposed pose
      adjust = { ...ZERO };
      shown = candidates ? Math.max(0, candidates.findIndex((c) => c.adjust === ZERO)) : 0;
    }
    else {
      adjust.turn_deg = Math.round((adjust.turn_deg + turn) * 1000) / 1000;
      adjust.shift_x_mm = Math.round((adjust.shift_x_mm + dx) * 1000) / 1000;
      adjust.shift_y_mm = Math.round((adjust.shift_y_mm + dy) * 1000) / 1000;
    }
    showPictures(p);
  }

  function nextStep() {
    step = (step + 1) % STEPS.length;
    $("pose-step").textContent = `step ${STEPS[step]}`;
  }

  function pct(p) { return `${(100 * p).toFixed(p >= 0.995 || p < 0.005 ? 1 : 0)}%`; }
  // the probability and, where stored, the mutual proximity the queue is ordered by
  function odds(p) {
    const mutual = p.mutual === null || p.mutual === undefined ? "" : ` · mutual proximity ${p.mutual.toFixed(3)}`;
    return `probability ${pct(p.probability)}${mutual}`;
  }

  function select(i) {
    const fresh = i !== index;
    if (fresh) {
      adjust = { ...ZERO }; candidates = null; shown = 0;
      $("pose-candidates").replaceChildren();
      $("pose-candidates-title").hidden = true;
    }
    index = i;
    [...$("queue").children].forEach((li, k) => li.classList.toggle("current", k === i));
    const p = items[i];
    const enabled = !!p && Tessera.loggedIn();   // a decided pair may be decided again (latest verdict counts)
    for (const b of ["confirm-button", "reject-button"]) $(b).disabled = !enabled;
    $("skip-button").disabled = !p;
    for (const b of document.querySelectorAll("#pose-controls button")) b.disabled = !p || !p.pose;
    if (!p) {
      $("proposal-title").textContent = items.length ? "Select a proposal" : "Nothing to review";
      $("proposal-meta").textContent = "";
      for (const v of VIEWS) { $(v).removeAttribute("src"); }
      $("pose-adjust").textContent = "";
      return;
    }
    $("proposal-title").textContent = `${p.fragment_a} ↔ ${p.fragment_b}`;
    const pose = !p.pose ? "no pose yet"
      : `pose ${p.pose.angle_deg.toFixed(1)}°, (${p.pose.tx_mm.toFixed(1)}, ${p.pose.ty_mm.toFixed(1)}) mm`
        + (p.verdict_pose ? ` (kept with the ${p.verdict} verdict: confirming again keeps it)` : "");
    $("proposal-meta").textContent = `${odds(p)} · ${p.status} · ${pose} · model ${p.model_version}`;
    showPictures(p);
    if (fresh && p.pose) loadCandidates(p);
    if (!Tessera.loggedIn()) $("review-message").textContent = "Log in (top right) to confirm or reject.";
  }

  async function loadQueue(keepId) {
    const url = filter ? `/api/review/fragment/${encodeURIComponent(filter)}` : "/api/review/queue";
    const r = await Tessera.api("GET", url);
    if (!r.ok) { $("review-message").textContent = r.data.error || "The proposals cannot be read."; return; }
    items = (r.data.proposals || []).filter((p) => !skipped.has(p.id) || p.id === keepId);
    // a fragment's list holds its decided proposals too
    $("queue-title").textContent = filter ? `Proposals of ${filter}` : "Pending proposals";
    if (r.data.counts) $("counts").textContent = `(${r.data.counts.pending} pending · ${r.data.counts.confirmed} confirmed · ${r.data.counts.rejected} rejected)`;
    $("queue").replaceChildren(...items.map((p, k) => {
      const li = Tessera.el("li", { "data-proposal": p.id, title: `${p.status} · ${odds(p)}` },
        Tessera.el("span", { text: `${p.fragment_a} ↔ ${p.fragment_b}` }),
        Tessera.el("span", { class: "prob", text: `${pct(p.probability)}${p.status !== "pending" ? " · " + p.status : ""}` }));
      li.addEventListener("click", () => select(k));
      return li;
    }));
    $("queue-empty").hidden = items.length > 0;
    let i = items.findIndex((p) => p.id === keepId);
    if (i < 0) i = items.findIndex((p) => p.status === "pending");
    select(i >= 0 ? i : (items.length ? 0 : -1));
  }

  async function loadHistory() {
    const r = await Tessera.api("GET", "/api/review/history");
    if (!r.ok) return;
    const rows = [];
    for (const v of r.data.sent || []) rows.push([v, v.delivered ? "sent, waiting for the matcher" : "queued: the broker is unreachable, sent when back"]);
    for (const v of r.data.history || []) rows.push([v, "recorded"]);
    $("history").tBodies[0].replaceChildren(...rows.map(([v, state]) => Tessera.el("tr", { "data-state": state },
      Tessera.el("td", { text: Tessera.when(v.time) }),
      Tessera.el("td", { text: `${v.fragment_a} ↔ ${v.fragment_b}` }),
      Tessera.el("td", { class: `verdict-${v.verdict}`, text: v.verdict }),
      Tessera.el("td", { text: v.by || "" }),
      Tessera.el("td", { text: state }))));
  }

  // ``p``, ``adj``: the proposal and correction of a key that waited (by default those on screen)
  async function verdict(kind, p = items[index], adj = adjust) {
    if (!p) return;
    if (kind === "skip") {
      skipped.add(p.id);
      $("review-message").textContent = `Skipped ${p.fragment_a} ↔ ${p.fragment_b}.`;
      const next = items.findIndex((q, k) => k > index && q.status === "pending" && !skipped.has(q.id));
      select(next >= 0 ? next : index);
      return;
    }
    // not the buttons' state: a waiting key's proposal may no longer be on screen (the page then may show none)
    if (sending || !Tessera.loggedIn()) return;
    sending = true;
    $("confirm-button").disabled = $("reject-button").disabled = true;
    $("proposal").setAttribute("aria-busy", "true");   // until the proposal is shown again at the pose kept
    try { await sendVerdict(p, kind, adj); } finally {
      sending = false;
      $("proposal").setAttribute("aria-busy", "false");
      playWaiting();
    }
  }

  async function sendVerdict(p, kind, adj) {
    const r = await Tessera.api("POST", "/api/review/verdict", { proposal: p.id, verdict: kind, adjust: adj });
    if (!r.ok) {
      $("review-message").textContent = r.data.error || `refused (${r.status})`;
      select(index);
      return;
    }
    $("review-message").textContent = `${kind === "confirmed" ? "Confirmed" : "Rejected"} ${p.fragment_a} ↔ ${p.fragment_b}.`;
    // keys waiting for this proposal were pressed with the pose this verdict kept on screen, where it now stands
    // (below): their correction is in that pose
    for (const w of waiting) if (w.proposal && w.proposal.id === p.id) w.adjust = { ...ZERO };
    if (!filter) skipped.add(p.id);   // the queue moves on; a fragment's list keeps every proposal
    await loadHistory();
    // the proposal now stands at the pose the verdict kept: the correction is in it, so it is selected afresh
    // (adjustment back to zero: kept, it would be applied twice; candidate poses fetched relative to the new pose)
    const onScreen = items[index];
    index = -1;
    if (onScreen && onScreen.id !== p.id) {   // a waiting key's verdict for a proposal the page has left: it stays put
      await loadQueue(onScreen.id);
      return;
    }
    await loadQueue(filter ? p.id : undefined);
    if (filter) {   // on to the next undecided proposal of this fragment, if any
      const next = items.findIndex((q, k) => k > index && q.status === "pending");
      if (next >= 0) select(next);
    }
  }

  // what a key does: a verdict (for a proposal), a change of the pose shown, or a move in the queue; null: not ours
  function keyAction(k, shift) {
    const arrow = { arrowleft: [-1, 0], arrowright: [1, 0], arrowup: [0, -1], arrowdown: [0, 1] }[k];
    if (shift && arrow) return { pose: () => nudge(0, arrow[0] * STEPS[step], arrow[1] * STEPS[step]) };   // move B
    if (k === "[" || k === "]") return { pose: () => nudge(k === "]" ? STEPS[step] : -STEPS[step], 0, 0) };   // turn B
    if (k === "x") return { move: nextStep };
    if (k === "0") return { pose: () => nudge(null) };
    if (k === "p") return { pose: () => otherPose(shift ? -1 : 1) };
    if (k === "c" || k === "y") return { verdict: "confirmed" };
    if (k === "r" || k === "n") return { verdict: "rejected" };
    if (k === "s" || k === "arrowright") return { move: () => verdict("skip") };
    if (k === "arrowdown" || k === "j") return { move: () => { if (index + 1 < items.length) select(index + 1); } };
    if (k === "arrowup" || k === "k") return { move: () => { if (index > 0) select(index - 1); } };
    return null;
  }

  // a key's action for the proposal ``p`` on screen when it was pressed: a change of pose only while it is still
  // shown (another proposal's pose was never seen); moves from wherever the page is, as had they come after the answer
  function play(action, p, adj) {
    if (action.verdict) verdict(action.verdict, p, adj);
    else if (action.pose) { if (p && items[index] && items[index].id === p.id) action.pose(); }
    else action.move();
  }

  function playWaiting() {
    while (waiting.length && !sending) {   // a verdict played sends, and the rest wait for its answer in turn
      const w = waiting.shift();
      play(w.action, w.proposal, w.adjust);
    }
  }

  $("confirm-button").addEventListener("click", () => verdict("confirmed"));
  $("reject-button").addEventListener("click", () => verdict("rejected"));
  $("skip-button").addEventListener("click", () => verdict("skip"));
  $("other-pose").addEventListener("click", (ev) => otherPose(ev.shiftKey ? -1 : 1));
  for (const b of document.querySelectorAll("#pose-controls button[data-nudge]")) {
    b.addEventListener("click", () => {
      const [turn, dx, dy] = (b.dataset.nudge || "").split(",").map(Number);
      nudge(b.dataset.nudge === "reset" ? null : turn * STEPS[step], dx * STEPS[step], dy * STEPS[step]);
    });
  }
  $("pose-step").addEventListener("click", nextStep);
  $("fragment-filter").addEventListener("submit", (ev) => {
    ev.preventDefault();
    filter = $("filter-id").value.trim();
    skipped.clear();
    history.replaceState(null, "", filter ? `/review?fragment=${encodeURIComponent(filter)}` : "/review");
    loadQueue();
  });
  document.addEventListener("keydown", (ev) => {
    if (Tessera.typingInField(ev) || ev.ctrlKey || ev.metaKey || ev.altKey) return;
    const action = keyAction(ev.key.toLowerCase(), ev.shiftKey);
    if (!action) return;
    ev.preventDefault();
    if (!sending) { play(action, items[index], adjust); return; }
    if (waiting.length >= MAX_WAITING_KEYS) {
      $("review-message").textContent = "Still sending the verdict: that key was not kept (too many keys waiting).";
      return;
    }
    waiting.push({ action, proposal: items[index], adjust: { ...adjust } });
  });
  loadQueue();
  loadHistory();
  setInterval(() => { const p = items[index]; loadQueue(p && p.id); loadHistory(); }, 10000);
})();
