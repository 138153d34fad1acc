// The fragment page: faces, the relighting viewer's controls, measuring, joins and downloads.
"use strict";
(() => {
  const root = document.getElementById("fragment-page");
  const $ = (id) => document.getElementById(id);
  const el = Tessera.el;
  const STYLES = RelightViewer.STYLES;
  let viewer = null, info = null, mode = "light";
  const autoDone = new Set();   // styles whose contrast was picked once on this face

  function message(text) {
    const m = $("viewer-message");
    m.textContent = text || "";
    m.hidden = !text;
  }

  // ---- the fragment: faces, joins, proposals, downloads ------------------------------------------
  async function load() {
    // the faces are in the page: the viewer starts at once; the rest of the fragment follows
    const faces = JSON.parse(root.dataset.faces || "[]");
    let firstView = null;
    if (!faces.length) { message("This fragment has no RGBN face on storage yet."); }
    else {
      const bar = $("faces");
      bar.replaceChildren();
      for (const f of faces) {
        const b = el("button", { type: "button", text: f.face[0].toUpperCase() + f.face.slice(1), "data-face": f.face });
        b.addEventListener("click", () => openFace(f));
        bar.append(b);
      }
      const want = new URLSearchParams(location.search).get("face");
      firstView = openFace(faces.find((f) => f.face === want) || faces[0]).then((shown) => shown && viewer.complete);
    }
    const r = await Tessera.api("GET", root.dataset.api);
    if (!r.ok) { if (faces.length) message(r.data.error || `The fragment's joins could not be loaded (HTTP ${r.status}).`); return; }
    info = r.data;
    const link = (p) => el("li", {},
      el("a", { href: p.other_url, text: p.other }), ` · ${(100 * p.probability).toFixed(0)} %`,
      p.pose ? ` · ${p.pose.angle_deg.toFixed(1)}°, (${p.pose.tx_mm.toFixed(1)}, ${p.pose.ty_mm.toFixed(1)}) mm` : "",
      " · ", el("a", { href: p.review_url, text: p.status === "confirmed" ? "verdict" : "review" }));
    $("joins").replaceChildren(...info.joins.map(link));
    $("joins-empty").hidden = info.joins.length > 0;
    $("proposals").replaceChildren(...info.proposals.map(link));
    $("proposals-empty").hidden = info.proposals.length > 0;
    if (!info.proposals_available) $("proposals-empty").textContent = "The proposal store is not available on this station.";
    about(info.catalogue);
    // the first listing exports the files, which reads whole faces: after the first view is drawn,
    // so a face opened for the first time does not share the server with it
    if (firstView) await Promise.race([firstView, new Promise((r) => setTimeout(r, 60000))]);
    downloads(info.downloads);
  }

  // metadata from the catalogue (find-spot, context, date, notes), where the station has one
  async function about(url) {
    const dl = $("about");
    if (!url) { dl.replaceChildren(el("dd", { class: "muted", text: "No catalogue on this station." })); return; }
    const r = await Tessera.api("GET", url);
    if (!r.ok) { dl.replaceChildren(el("dd", { class: "muted", text: r.data.error || "Not in the catalogue." })); return; }
    const rows = [["Inventory", r.data.inventory], ["Find-spot", r.data.find_spot], ["Context", r.data.context],
                  ["Date", r.data.date], ["Notes", r.data.notes], ["State", r.data.state],
                  ["Origin", Tessera.imported(r.data.imported)]];
    dl.replaceChildren(...rows.filter(([, v]) => v).flatMap(([k, v]) => [el("dt", { text: k }), el("dd", { text: String(v) })]));
    $("catalogue-link").href = `/fragments?q=${encodeURIComponent(root.dataset.fragment)}`;
  }

  // tessera export's files, from the archive's downloads (the first request exports them: seconds)
  async function downloads(url) {
    const ul = $("downloads");
    if (!url) { ul.replaceChildren(); $("downloads-empty").hidden = false; return; }
    const r = await Tessera.api("GET", url);
    if (!r.ok) { ul.replaceChildren(el("li", { class: "muted", text: r.data.error || `Not available (HTTP ${r.status}).` })); return; }
    const kb = (n) => n > 1e6 ? `${(n / 1e6).toFixed(1)} MB` : `${Math.max(1, Math.round(n / 1e3))} kB`;
    ul.replaceChildren(el("li", {}, el("a", { href: r.data.zip, text: "All files (zip)", download: "" })),
      ...r.data.files.map((f) => el("li", {}, el("a", { href: f.url, text: f.name, download: "" }), ` · ${kb(f.bytes)}`)));
  }

  async function openFace(face) {
    for (const b of $("faces").children) b.classList.toggle("active", b.dataset.face === face.face);
    let p = face.params;   // in the page when the server has them already
    if (!p) {
      const r = await Tessera.api("GET", face.relight + "/params.json");
      if (!r.ok) { message(r.data.error || `This face cannot be shown (HTTP ${r.status}).`); return; }
      p = face.params = r.data;
    }
    // a capture with no scale of its own (hand-held, RTI) has a guessed dpi: every length on the page is too
    const nominal = p.dpi_nominal ? " (nominal: the capture has no scale of its own)" : "";
    // the piece's size (its mask's extent); the picture's when it differs (a scan crop holds the lamp's shadow too)
    const mm = (px) => (px / p.dpi * 25.4).toFixed(1);
    const box = p.piece_px || [0, 0, p.width, p.height], bw = box[2] - box[0], bh = box[3] - box[1];
    const whole = bw === p.width && bh === p.height ? "" : ` (picture ${mm(p.width)} × ${mm(p.height)} mm)`;
    $("face-info").textContent = `${mm(bw)} × ${mm(bh)} mm${whole} · ` +
      `${p.width} × ${p.height} px · ${p.dpi} dpi${nominal}${p.has_normals ? "" : " · colour only (no normals: no relighting)"}`;
    const style = viewer ? viewer.style : (p.has_normals ? "raking" : "albedo");
    const light = viewer ? viewer.light : null;
    if (viewer) viewer.dispose();
    viewer = new RelightViewer.Viewer($("gl"), $("overlay"), face.relight, p);   // OpenSeadragon fills #gl
    window.tesseraViewer = viewer;     // for the browser tests and the curious
    viewer.onerror = (e) => message(String(e.message || e));
    viewer.onchange = syncControls;
    try {
      await viewer.init();
    } catch (e) {
      message(String(e.message || e));
      return;
    }
    fillStyles(p.has_normals);
    autoDone.clear();
    viewer.setStyle(style);
    if (light) viewer.setLight(...light);
    buildStyleControls();
    firstContrast();
    return true;
  }

  // ---- controls ------------------------------------------------------------------------------
  function fillStyles(hasNormals) {
    const sel = $("style");
    sel.replaceChildren(...Object.entries(STYLES).filter(([, s]) => hasNormals || !s.needsNormals)
      .map(([k, s]) => el("option", { value: k, text: s.label })));
  }

  // one input per parameter of the current style (numbers, booleans, [low, high] ranges)
  const shown = (v) => Number(Number(v).toPrecision(4));   // what an input shows (the value keeps its digits)

  function buildStyleControls() {
    const box = $("style-controls");
    box.replaceChildren();
    const values = viewer.values[viewer.style];
    for (const [key, val] of Object.entries(values)) {
      if (key === "light" || key === "azimuth_deg" || key === "elevation_deg") continue;
      const name = key.replace(/_/g, " ");
      if (typeof val === "boolean") {
        const c = el("input", { type: "checkbox", checked: val, "data-param": key });
        c.addEventListener("change", () => viewer.setValues({ [key]: c.checked }));
        box.append(el("label", {}, c, ` ${name}`));
      } else if (typeof val === "number") {
        const c = el("input", { type: "number", value: shown(val), step: "any", "data-param": key });
        c.addEventListener("input", () => { if (c.value !== "" && isFinite(c.value)) viewer.setValues({ [key]: Number(c.value) }); });
        box.append(el("label", { text: `${name} ` }, c));
      } else if (Array.isArray(val) || val === "none") {
        const isNone = val === "none";
        const lo = el("input", { type: "number", value: isNone ? "" : shown(val[0]), step: "any", "data-param": key + ".0", placeholder: "low" });
        const hi = el("input", { type: "number", value: isNone ? "" : shown(val[1]), step: "any", "data-param": key + ".1", placeholder: "high" });
        const set = () => {
          if (lo.value === "" && hi.value === "") viewer.setValues({ [key]: "none" });
          else if (isFinite(lo.value) && isFinite(hi.value)) viewer.setValues({ [key]: [Number(lo.value), Number(hi.value)] });
        };
        lo.addEventListener("input", set); hi.addEventListener("input", set);
        box.append(el("label", { text: `${name} ` }, lo, hi));
      }
    }
    syncControls();
  }

  function syncControls() {
    if (!viewer) return;
    $("style").value = viewer.style;
    const [az, el_] = viewer.style === "raking" ?
      [viewer.values.raking.azimuth_deg, viewer.values.raking.elevation_deg] : viewer.light;
    $("azimuth").value = az; $("azimuth-out").textContent = Math.round(az);
    $("elevation").value = el_; $("elevation-out").textContent = Math.round(el_);
    const d = viewer.measureMm();
    $("measure-readout").textContent = d === null ? "" : `${d.toFixed(2)} mm${viewer.info.dpi_nominal ? " (nominal)" : ""}`;
  }

  async function autoContrast() {
    const s = viewer.style, values = JSON.parse(JSON.stringify(viewer.values[s]));
    const url = `${viewer.base}/auto?style=${encodeURIComponent(s)}&values=${encodeURIComponent(JSON.stringify(values))}`;
    $("auto-contrast").disabled = true;
    const r = await Tessera.api("GET", url);
    $("auto-contrast").disabled = false;
    if (!r.ok) { message(r.data.error || `Auto contrast failed (HTTP ${r.status}).`); return; }
    message("");
    // only if nothing changed while the server measured (another style, another light)
    if (viewer.style === s && JSON.stringify(viewer.values[s]) === JSON.stringify(values)) {
      viewer.setValues(r.data.resolved);
      buildStyleControls();
    }
  }

  // the contrast the offline style picks, the first time a style is shown on this face
  function firstContrast() {
    if (!autoDone.has(viewer.style)) { autoDone.add(viewer.style); autoContrast(); }
  }
  // ... and again when the light has stopped moving, if the person wants it to follow
  let followTimer = null;
  function lightMoved() {
    clearTimeout(followTimer);
    if ($("auto-follow").checked) followTimer = setTimeout(autoContrast, 250);
  }

  $("style").addEventListener("change", () => { viewer.setStyle($("style").value); buildStyleControls(); firstContrast(); });
  for (const id of ["azimuth", "elevation"]) {
    $(id).addEventListener("input", () => viewer.setLight(Number($("azimuth").value), Number($("elevation").value)));
    $(id).addEventListener("change", lightMoved);
  }
  $("auto-contrast").addEventListener("click", autoContrast);
  $("fit").addEventListener("click", () => viewer.fit());
  $("one-to-one").addEventListener("click", () => viewer.oneToOne());

  function setMode(m) {
    mode = m;
    $("viewer").dataset.mode = m;
    for (const b of document.querySelectorAll(".tools button")) b.classList.toggle("active", b.dataset.mode === m);
  }
  for (const b of document.querySelectorAll(".tools button")) b.addEventListener("click", () => setMode(b.dataset.mode));
  setMode("light");

  // ---- pointer: light, measure; pan and zoom are OpenSeadragon's ---------------------------------
  // A drag with the left button does what the tool says. In the pan tool, or with Shift, the drag
  // goes on to OpenSeadragon, which pans (its "canvas-drag", viewer.js). The middle and right buttons
  // pan here (OpenSeadragon drags with the primary button only). The listeners are on the viewer's
  // box in the capture phase, so a light or measuring drag is taken before OpenSeadragon sees it.
  const area = $("viewer");
  let drag = null;
  const canvasXY = (e) => {
    const r = viewer.canvas.getBoundingClientRect(), dpr = window.devicePixelRatio || 1;
    return [(e.clientX - r.left) * dpr, (e.clientY - r.top) * dpr];
  };
  // RTIViewer's light sphere: the pointer's offset from the centre of the view is the light's
  // projection on the image plane (the rim = grazing, the centre = from the viewer)
  function lightFrom(e) {
    const [x, y] = canvasXY(e), c = viewer.canvas, half = Math.min(c.width, c.height) / 2;
    const dx = (x - c.width / 2) / half, dy = -(y - c.height / 2) / half;
    const r = Math.min(1, Math.hypot(dx, dy));
    viewer.setLight(Math.atan2(dy, dx) * 180 / Math.PI, Math.acos(r) * 180 / Math.PI);
  }
  area.addEventListener("contextmenu", (e) => e.preventDefault());
  area.addEventListener("pointerdown", (e) => {
    if (!viewer || !viewer.osd) return;
    const m = e.button === 1 || e.button === 2 ? "pan" : e.button === 0 && !e.shiftKey && mode !== "pan" ? mode : null;
    if (!m) return;                    // OpenSeadragon's: a pan
    e.stopPropagation();
    area.setPointerCapture(e.pointerId);
    drag = { m, last: canvasXY(e) };
    if (m === "light") lightFrom(e);
    if (m === "measure") { viewer.measure = { a: viewer.toImage(...drag.last), b: null }; viewer.draw(); }
  }, { capture: true });
  area.addEventListener("pointermove", (e) => {
    if (!drag) return;
    const p = canvasXY(e);
    if (drag.m === "pan") viewer.pan(p[0] - drag.last[0], p[1] - drag.last[1], true);
    else if (drag.m === "light") lightFrom(e);
    else if (drag.m === "measure") { viewer.measure.b = viewer.toImage(...p); viewer.draw(); syncControls(); }
    drag.last = p;
  });
  const end = () => { if (drag && drag.m === "light") lightMoved(); drag = null; syncControls(); };
  area.addEventListener("pointerup", end);
  area.addEventListener("pointercancel", end);
  // the wheel zooms about the pointer, in proportion to the wheel's turn (a touchpad's small steps
  // too); OpenSeadragon animates it
  area.addEventListener("wheel", (e) => {
    if (!viewer || !viewer.osd) return;
    e.preventDefault();
    e.stopPropagation();
    viewer.zoomAt(Math.exp(-e.deltaY * 0.0015), ...canvasXY(e));
  }, { passive: false, capture: true });
  document.addEventListener("keydown", (e) => {
    if (!viewer || !viewer.osd || e.target.closest("input, select, textarea")) return;
    const k = e.key.toLowerCase(), step = 80, c = viewer.canvas;
    if (k === "l") setMode("light"); else if (k === "p") setMode("pan"); else if (k === "m") setMode("measure");
    else if (k === "f") viewer.fit(); else if (k === "1") viewer.oneToOne();
    else if (k === "+" || k === "=") viewer.zoomAt(1.25, c.width / 2, c.height / 2);
    else if (k === "-") viewer.zoomAt(0.8, c.width / 2, c.height / 2);
    else if (e.key === "ArrowLeft") viewer.pan(step, 0); else if (e.key === "ArrowRight") viewer.pan(-step, 0);
    else if (e.key === "ArrowUp") viewer.pan(0, step); else if (e.key === "ArrowDown") viewer.pan(0, -step);
    else return;
    e.preventDefault();
  });

  load();
})();
