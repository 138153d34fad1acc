// Catalogue page: search, filter and page through every fragment; edit metadata (sent as fragment.annotated).
"use strict";
(() => {
  const $ = (id) => document.getElementById(id);
  const PER_PAGE = 50;
  let page = 1, pages = 1, current = null, row = null;

  function query() {
    const p = new URLSearchParams({ page, per_page: PER_PAGE });
    for (const k of ["q", "state", "colour", "joins"]) if ($(k).value.trim()) p.set(k, $(k).value.trim());
    return p;
  }

  async function load() {
    const r = await Tessera.api("GET", `/api/catalogue?${query()}`);
    if (!r.ok) { $("feed-state").textContent = r.data.error || "The catalogue cannot be read."; return; }
    const d = r.data;
    pages = Math.max(1, Math.ceil(d.total / d.per_page));
    $("total").textContent = `(${d.total} of ${d.counts.total})`;
    $("page-of").textContent = `page ${d.page} of ${pages}`;
    $("prev").disabled = d.page <= 1; $("next").disabled = d.page >= pages;
    $("empty").hidden = d.total > 0;
    $("feed-state").textContent = !d.feed.following ? "Not following the event feed: edits and new fragments show after a restart."
      : d.feed.error ? `The broker cannot be reached (${d.feed.error}); showing what was indexed.` : "";
    $("fragments").tBodies[0].replaceChildren(...d.fragments.map((f) => {
      const img = f.has_thumb ? Tessera.el("img", { class: "thumb", alt: `${f.id}`, src: `/api/catalogue/${encodeURIComponent(f.id)}/thumb.png`, loading: "lazy" }) : "";
      const tr = Tessera.el("tr", { "data-fragment": f.id },
        Tessera.el("td", {}, img),
        Tessera.el("td", {}, Tessera.el("a", { href: `/fragments/${encodeURIComponent(f.id)}`, text: f.id })),
        Tessera.el("td", { text: f.inventory }), Tessera.el("td", { text: f.find_spot }),
        Tessera.el("td", { text: f.context }), Tessera.el("td", { text: f.date }),
        Tessera.el("td", {}, Tessera.el("span", { class: `tag state-${f.state}`, text: f.state })),
        Tessera.el("td", { class: "prob", text: `${f.confirmed} confirmed · ${f.pending} pending` }),
        Tessera.el("td", {}, f.colour ? Tessera.el("span", { class: `swatch ${f.colour}`, title: f.colour, text: f.colour }) : ""));
      tr.classList.toggle("current", f.id === current);
      tr.addEventListener("click", (ev) => { if (ev.target.tagName !== "A") select(f.id); });
      return tr;
    }));
  }

  async function select(fid) {
    current = fid;
    for (const tr of $("fragments").tBodies[0].rows) tr.classList.toggle("current", tr.dataset.fragment === fid);
    const r = await Tessera.api("GET", `/api/catalogue/${encodeURIComponent(fid)}`);
    if (!r.ok) { $("detail-title").textContent = r.data.error || fid; return; }
    row = r.data;
    $("detail-title").textContent = fid;
    const faces = Object.entries(row.faces).map(([face, f]) => `${face} ${f.width}×${f.height} px at ${Math.round(f.dpi)} dpi`);
    const links = [Tessera.el("a", { href: `/fragments/${encodeURIComponent(fid)}`, text: "open the fragment" })];
    if (faces.length) links.push(" · ", Tessera.el("a", { href: `/iiif/presentation/${encodeURIComponent(fid)}/manifest`, text: "IIIF manifest" }));
    const origin = row.imported ? ` · ${Tessera.imported(row.imported)}` : "";   // not scanned here: when and from what
    $("detail-links").replaceChildren(...links, ` · ${faces.join(" · ") || "no face yet"}${origin} · ${row.state}`);
    $("metadata").hidden = false;
    for (const input of $("metadata").querySelectorAll("[data-field]")) {
      input.value = row[input.dataset.field] || "";
      input.disabled = !Tessera.loggedIn();
    }
    $("save").disabled = !Tessera.loggedIn();
    $("save-message").textContent = Tessera.loggedIn() ? "" : "Log in (top right) to edit.";
    const rows = [];
    for (const e of row.sent || []) rows.push([e, e.delivered ? "sent, waiting for the feed" : "queued: the broker is unreachable, sent when back"]);
    for (const e of row.history || []) rows.push([e, "recorded"]);
    $("history").tBodies[0].replaceChildren(...rows.map(([e, state]) => Tessera.el("tr", { "data-state": state },
      Tessera.el("td", { text: Tessera.when(e.time) }), Tessera.el("td", { text: e.by }),
      Tessera.el("td", { text: Object.entries(e.changes).map(([k, v]) => `${k}: “${v}”`).join("; ") }),
      Tessera.el("td", { text: state }))));
  }

  $("metadata").addEventListener("submit", async (ev) => {
    ev.preventDefault();
    if (!row) return;
    const changes = {};
    for (const input of $("metadata").querySelectorAll("[data-field]")) {
      if (input.value.trim() !== (row[input.dataset.field] || "")) changes[input.dataset.field] = input.value.trim();
    }
    if (!Object.keys(changes).length) { $("save-message").textContent = "Nothing changed."; return; }
    $("save").disabled = true;
    const r = await Tessera.api("POST", `/api/catalogue/${encodeURIComponent(row.id)}/metadata`, { changes });
    $("save").disabled = false;
    $("save-message").textContent = r.ok ? (r.data.sent.delivered ? "Saved." : "Kept on this machine: sent when the broker is back.")
      : (r.data.error || "The edit was not sent.");
    await select(row.id);
    await load();
  });

  $("search").addEventListener("submit", (ev) => { ev.preventDefault(); page = 1; load(); });
  for (const k of ["state", "colour", "joins"]) $(k).addEventListener("change", () => { page = 1; load(); });
  $("prev").addEventListener("click", () => { if (page > 1) { page--; load(); } });
  $("next").addEventListener("click", () => { if (page < pages) { page++; load(); } });
  load();
  setInterval(() => { if (!document.hidden) load(); }, 5000);
})();
