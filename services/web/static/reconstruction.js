// Reconstruction page: clusters of confirmed joins drawn at their solved poses, live (long poll).
"use strict";
(() => {
  const $ = (id) => document.getElementById(id);
  const root = $("reconstruction");
  const SVG = "http://www.w3.org/2000/svg";
  let signature = "";

  function svg(tag, attrs, ...children) {
    const e = document.createElementNS(SVG, tag);
    for (const [k, v] of Object.entries(attrs || {})) e.setAttribute(k, v);
    for (const c of children) e.append(c);
    return e;
  }

  // p_cluster = R(angle) p + t, mm; SVG's matrix(a b c d e f) maps (x, y) to (a x + c y + e, b x + d y + f)
  function matrix(pose) {
    const a = pose.angle_deg * Math.PI / 180, c = Math.cos(a), s = Math.sin(a);
    return `matrix(${c} ${s} ${-s} ${c} ${pose.tx_mm} ${pose.ty_mm})`;
  }
  function apply(pose, p) {
    const a = pose.angle_deg * Math.PI / 180, c = Math.cos(a), s = Math.sin(a);
    return [c * p[0] - s * p[1] + pose.tx_mm, s * p[0] + c * p[1] + pose.ty_mm];
  }
  function corners(info) {
    const x0 = info.x_mm, y0 = info.y_mm, x1 = x0 + info.width_mm, y1 = y0 + info.height_mm;
    return [[x0, y0], [x1, y0], [x1, y1], [x0, y1]];
  }

  function piece(fid, pose, info, cls) {
    const g = svg("g", { class: `piece ${cls}`, "data-fragment": fid, transform: matrix(pose) });
    g.append(svg("title", {}, `${fid}${cls === "ghost" ? " (proposed)" : ""}`));
    g.append(svg("image", { href: info.thumb, x: info.x_mm, y: info.y_mm, width: info.width_mm, height: info.height_mm,
                            preserveAspectRatio: "none" }));
    // a next join's piece: its own outline dashed (the picture's box where the outline is not known)
    if (cls === "ghost") g.append(info.outline_mm && info.outline_mm.length > 2
      ? svg("polygon", { points: info.outline_mm.map((p) => p.join(",")).join(" "), class: "ghost-box" })
      : svg("rect", { x: info.x_mm, y: info.y_mm, width: info.width_mm, height: info.height_mm, class: "ghost-box" }));
    return g;
  }

  function drawCluster(c, data) {
    const frags = data.fragments, poses = {};
    for (const f of c.fragments) poses[f.fragment] = f;
    const centre = (fid, pose) => apply(pose || poses[fid], (frags[fid] || { centre_mm: [0, 0] }).centre_mm);
    const seen = new Set();   // the best proposal of each newcomer (the list is most probable first)
    const ghosts = c.next_joins.filter((n) => n.pose && frags[n.newcomer] && !seen.has(n.newcomer) && seen.add(n.newcomer)).slice(0, 3);
    // view box: every piece's corners at its pose (ghosts included)
    let lo = [Infinity, Infinity], hi = [-Infinity, -Infinity];
    const grow = (fid, pose) => {
      const info = frags[fid];
      for (const p of info ? corners(info).map((q) => apply(pose, q)) : [apply(pose, [0, 0])]) {
        lo = [Math.min(lo[0], p[0]), Math.min(lo[1], p[1])];
        hi = [Math.max(hi[0], p[0]), Math.max(hi[1], p[1])];
      }
    };
    for (const f of c.fragments) grow(f.fragment, f);
    for (const n of ghosts) grow(n.newcomer, n.pose);
    const pad = 5, w = hi[0] - lo[0] + 2 * pad, h = hi[1] - lo[1] + 2 * pad;
    const pic = svg("svg", { viewBox: `${lo[0] - pad} ${lo[1] - pad} ${w} ${h}`, class: "cluster-svg",
                             role: "img", "aria-label": `cluster ${c.id}` });
    const pieces = svg("g", { class: "pieces" }), lines = svg("g", { class: "joins" });
    for (const n of ghosts) pieces.append(piece(n.newcomer, n.pose, frags[n.newcomer], "ghost"));
    for (const f of c.fragments) if (frags[f.fragment]) pieces.append(piece(f.fragment, f, frags[f.fragment], "placed"));
    for (const j of c.joins) {
      const [a, b] = [centre(j.fragment_a), centre(j.fragment_b)];
      lines.append(svg("line", { x1: a[0], y1: a[1], x2: b[0], y2: b[1], class: j.residual_suspect ? "join suspect" : "join",
                                 "data-join": `${j.fragment_a}|${j.fragment_b}` },
        svg("title", {}, `${j.fragment_a} ↔ ${j.fragment_b}: ${j.residual_mm.toFixed(2)} mm, ${j.residual_deg.toFixed(2)}° off after the solve`)));
    }
    for (const lp of c.loops.filter((l) => l.conflicting)) {
      const pts = lp.fragments.map((f) => centre(f).join(",")).join(" ");
      lines.append(svg("polygon", { points: pts, class: "loop conflicting" },
        svg("title", {}, `conflicting loop ${lp.fragments.join(" → ")}: ${lp.residual_mm.toFixed(1)} mm, ${lp.residual_deg.toFixed(1)}°`)));
    }
    for (const n of ghosts) {
      const [a, b] = [centre(n.member), centre(n.newcomer, n.pose)];
      lines.append(svg("line", { x1: a[0], y1: a[1], x2: b[0], y2: b[1], class: "join proposed" }));
    }
    pic.append(pieces, lines);
    return pic;
  }

  function card(c, data) {
    const conflicting = c.loops.filter((l) => l.conflicting);
    const head = Tessera.el("div", { class: "row cluster-head" },
      Tessera.el("h2", { text: `Cluster ${c.root}` }),
      Tessera.el("span", { class: "muted", text: `${c.fragments.length} fragments · ${c.joins.length} joins · ${c.loops.length} loops` }),
      Tessera.el("span", { class: conflicting.length ? "bad-text conflicts" : "good-text conflicts",
                           text: conflicting.length ? `${conflicting.length} conflicting loop${conflicting.length > 1 ? "s" : ""}` : "loops consistent" }),
      Tessera.el("a", { class: "button export-png", href: c.exports.png, download: "", text: "PNG" }),
      Tessera.el("a", { class: "button export-tiff", href: c.exports.tiff, download: "", text: "TIFF 16-bit" }));
    const loops = Tessera.el("ul", { class: "loops" }, ...conflicting.map((lp) => Tessera.el("li", { class: "bad-text",
      text: `${lp.fragments.join(" → ")} → ${lp.fragments[0]}: closes ${lp.residual_mm.toFixed(1)} mm / ${lp.residual_deg.toFixed(1)}° off (χ² ${lp.chi2.toFixed(0)})` })),
      ...c.blamed.map(([a, b]) => Tessera.el("li", { class: "bad-text blamed",
      text: `set aside: ${a} ↔ ${b} (on the most conflicting loops, or confirmed last) — check it on the review page` })));
    const next = Tessera.el("ol", { class: "next-joins" }, ...c.next_joins.map((n) => Tessera.el("li", { "data-newcomer": n.newcomer,
                                                                                               "data-fit": n.fit ? "yes" : "" },
      Tessera.el("a", { href: `/review?fragment=${encodeURIComponent(n.newcomer)}`, text: `${n.member} ↔ ${n.newcomer}` }),
      Tessera.el("span", { class: "muted", text: ` ${(100 * n.probability).toFixed(0)}%${n.mutual === null || n.mutual === undefined ? "" : " · mutual " + n.mutual.toFixed(2)}${n.newcomer_cluster ? " · joins " + n.newcomer_cluster : ""}${n.fit ? " · also fits between " + n.faces.join(" and ") + " (P on its review)" : ""}` }))));
    return Tessera.el("section", { class: "card cluster", "data-cluster": c.id, "data-size": c.fragments.length,
                                   "data-joins": c.joins.length, "data-conflicts": conflicting.length },
      head, drawCluster(c, data), loops,
      Tessera.el("h3", { text: c.next_joins.length ? "Most probable next joins" : "No pending proposal along its edges" }), next);
  }

  function render(data) {
    const doc = data.document;
    const clusters = doc ? doc.clusters : [];
    $("clusters").replaceChildren(...clusters.map((c) => card(c, data)));
    $("recon-empty").hidden = clusters.length > 0;
    const n = clusters.reduce((s, c) => s + c.fragments.length, 0);
    const bad = clusters.reduce((s, c) => s + c.n_conflicting_loops, 0);
    $("recon-counts").textContent = `${clusters.length} cluster${clusters.length === 1 ? "" : "s"} · ${n} fragments` +
      (bad ? ` · ${bad} conflicting loop${bad > 1 ? "s" : ""}` : "");
    const msgs = [];
    if (doc && doc.unposed_joins.length) msgs.push(`${doc.unposed_joins.length} confirmed join(s) without a pose are not placed`);
    if (data.missing.length) msgs.push(`no front image yet for ${data.missing.join(", ")}`);
    if (data.docking) msgs.push("trying the next joins in their clusters' corners…");
    $("recon-message").textContent = msgs.join("; ");
    $("arriving").hidden = !data.arriving.length;
    $("arriving").replaceChildren(...data.arriving.map((v) => Tessera.el("li", { class: "muted",
      text: `${v.fragment_a} ↔ ${v.fragment_b} confirmed${v.by ? " by " + v.by : ""}: waiting for the matcher to record it` })));
  }

  async function load() {
    const r = await Tessera.api("GET", root.dataset.api);
    if (!r.ok) { $("recon-message").textContent = r.data.error || "The reconstruction cannot be read."; return false; }
    signature = r.data.signature;
    root.dataset.signature = signature;
    render(r.data);
    return true;
  }

  async function follow() {
    for (;;) {
      const r = await Tessera.api("GET", `${root.dataset.changes}?after=${encodeURIComponent(signature)}`);
      if (!r.ok) { await new Promise((res) => setTimeout(res, 3000)); continue; }
      if (r.data.changed && !document.hidden) await load();
      else if (r.data.changed) signature = "";   // reload when visible again
      if (document.hidden) await new Promise((res) => setTimeout(res, 2000));
    }
  }

  load().then(follow);
})();
