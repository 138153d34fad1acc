// Status page: broker, services, workers per host, in flight, parked failures with re-run.
"use strict";
(() => {
  const $ = (id) => document.getElementById(id);
  const td = (text, cls) => Tessera.el("td", cls ? { text: String(text ?? ""), class: cls } : { text: String(text ?? "") });
  const fill = (id, rows) => $(id).tBodies[0].replaceChildren(...rows);
  const dur = (s) => s < 90 ? `${Math.round(s)} s` : s < 5400 ? `${Math.round(s / 60)} min` : `${(s / 3600).toFixed(1)} h`;

  async function rerun(job) {
    const r = await Tessera.api("POST", "/api/status/rerun", { job });
    $("status-message").textContent = r.ok
      ? (r.data.rerun.length ? `Re-queued ${r.data.rerun.length} job(s).` : "Nothing to re-run (already re-queued?).")
      : (r.data.error || `refused (${r.status})`);
    refresh();
  }

  async function refresh() {
    const r = await Tessera.api("GET", "/api/status");
    if (!r.ok) {
      $("broker-line").textContent = r.data.error || "The broker cannot be reached.";
      $("broker-line").className = "message error";
      return;
    }
    const s = r.data;
    $("broker-line").className = "message";
    $("broker-line").textContent = `Broker on ${s.host} (pid ${s.pid}), up ${dur(s.uptime_s)} · ${s.completed} jobs done · ` +
      `${s.jobs_per_s} jobs/s over the last minute · ${s.outbox} message(s) waiting in this machine's outbox`;
    const workers = {}, inflight = {};
    for (const list of Object.values(s.workers || {})) for (const w of list) workers[w.service] = (workers[w.service] || 0) + 1;
    for (const j of s.in_flight || []) inflight[j.service] = (inflight[j.service] || 0) + 1;
    fill("services", Object.entries(s.queues || {}).map(([svc, n]) => Tessera.el("tr", { "data-service": svc },
      td(svc), td(n), td(workers[svc] || 0, workers[svc] ? "" : "err"), td(inflight[svc] || 0))));
    const hostRows = [];
    for (const [host, list] of Object.entries(s.workers || {}))
      for (const w of list) hostRows.push(Tessera.el("tr", {}, td(host), td(w.service), td(w.pid), td(w.job || "idle"), td(dur(w.up_s))));
    fill("hosts", hostRows);
    fill("inflight", (s.in_flight || []).map((j) => Tessera.el("tr", {}, td(j.job), td(j.service), td(j.fragment), td(j.worker),
      td(dur(j.running_s)), td(j.attempt), td(j.progress ? `${Math.round(100 * (j.progress[0] || 0))}% ${j.progress[1] || ""}` : ""))));
    fill("parked", (s.parked || []).map((j) => {
      const b = Tessera.el("button", { type: "button", class: "small rerun", text: "Re-run", disabled: !Tessera.loggedIn() });
      b.addEventListener("click", () => rerun(j.job));
      return Tessera.el("tr", { "data-job": j.job }, td(j.job), td(j.service), td(j.fragment), td(j.attempts), td(j.error, "err"), Tessera.el("td", {}, b));
    }));
    $("rerun-all").hidden = !(s.parked || []).length;
    $("rerun-all").disabled = !Tessera.loggedIn();
  }
  $("rerun-all").addEventListener("click", () => rerun("all"));
  refresh();
  setInterval(refresh, 2000);
})();
