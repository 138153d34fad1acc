// The relighting viewer: a tiled WebGL2 deep-zoom viewer that shades RGBN fields in the shader.
//
// The server cuts every face into a pyramid of 256-px tiles of the light-independent fields
// (common/web/relight.py: the normals as solved and smoothed at the scales the styles need, the mean
// curvature, the display albedo and mask). A tile is fetched once, uploaded once as five textures and
// kept; moving the light, changing a style's parameters or the contrast only changes uniforms, so a
// frame is one draw call per visible tile and no texture upload. The style shaders are the files
// next to this one, named like the offline styles they mirror (common/render/recipes.py).
//
// No framework, no build step, nothing from the network but this station.
"use strict";

const RelightViewer = (() => {
  const HERE = (document.currentScript && document.currentScript.src) ?
    document.currentScript.src.replace(/[^/]*$/, "") : "/static/viewer/";

  // light_vector of common/render/_util.py: azimuth counter-clockwise from +x (image right),
  // elevation above the image plane; x right, y up, z towards the viewer
  function lightVector(az, el) {
    const a = az * Math.PI / 180, e = el * Math.PI / 180;
    return [Math.cos(e) * Math.cos(a), Math.cos(e) * Math.sin(a), Math.sin(e)];
  }

  // the shader files, fetched once as soon as this script runs (in parallel with the page's
  // other requests)
  let sources = null;
  function shaderSources() {
    const text = (name) => fetch(HERE + name).then((r) => {
      if (!r.ok) throw new Error(`shader ${name}: HTTP ${r.status}`);
      return r.text();
    });
    if (!sources) sources = Promise.all(["tile.vert", "common.glsl", ...Object.keys(STYLES).map((n) => n + ".frag")].map(text));
    return sources;
  }

  // [lo, hi] or "none"/"auto"-less numbers as the shader's vec2 (x < 0 means "none")
  const range = (v) => Array.isArray(v) ? [Number(v[0]), Number(v[1])] : [-1, -1];

  // Every style: the offline style's parameters (same names, the viewer's defaults) and how they
  // become uniforms. "light" is [azimuth_deg, elevation_deg]; raking has its own two angles.
  const STYLES = {
    albedo: {
      label: "Colour", needsNormals: false,
      defaults: { exposure: "none" },
      uniforms: (p) => ({ u_exposure: ["2f", range(p.exposure)] }),
    },
    lambertian: {
      label: "Lambertian", needsNormals: true,
      defaults: { light: [135, 45], ambient: 0.15, colour: true, exposure: [0.3, 0.9], colour_exposure: "none" },
      uniforms: (p) => ({ u_ambient: ["1f", p.ambient], u_exposure: ["2f", range(p.exposure)],
                          u_colour_on: ["1i", p.colour ? 1 : 0], u_colour_exposure: ["2f", range(p.colour_exposure)] }),
    },
    raking: {
      label: "Raking light", needsNormals: true,
      defaults: { azimuth_deg: 135, elevation_deg: 12, ambient: 0.05, colour: false, exposure: [0.05, 0.4],
                  colour_exposure: "none" },
      uniforms: (p) => ({ u_ambient: ["1f", p.ambient], u_exposure: ["2f", range(p.exposure)],
                          u_colour_on: ["1i", p.colour ? 1 : 0], u_colour_exposure: ["2f", range(p.colour_exposure)] }),
    },
    specular: {
      label: "Specular enhancement", needsNormals: true,
      defaults: { light: [135, 45], kd: 0.6, ks: 0.6, exponent: 30, colour: true, exposure: [0.0, 0.8],
                  colour_exposure: "none", lightness: "none" },
      uniforms: (p) => ({ u_kd: ["1f", p.kd], u_ks: ["1f", p.ks], u_exponent: ["1f", p.exponent],
                          u_exposure: ["2f", range(p.exposure)], u_colour_on: ["1i", p.colour ? 1 : 0],
                          u_colour_exposure: ["2f", range(p.colour_exposure)],
                          u_lightness: ["2f", range(p.lightness)] }),
    },
    normal_unsharp: {
      label: "Normal unsharp masking", needsNormals: true,
      defaults: { light: [135, 45], gain: 3, colour: false, exposure: [0.3, 0.95] },
      uniforms: (p) => ({ u_gain: ["1f", p.gain], u_exposure: ["2f", range(p.exposure)],
                          u_colour_on: ["1i", p.colour ? 1 : 0] }),
    },
    exaggerated: {
      label: "Exaggerated shading", needsNormals: true,
      defaults: { light: [135, 45], contrast: 10, detail: 0.5, base_weight: 0.3, colour: false,
                  tones: [-0.3, 0.3], strength: 0.7, exposure: "none" },
      uniforms: (p) => ({ u_contrast: ["1f", p.contrast], u_detail: ["1f", p.detail],
                          u_base_weight: ["1f", p.base_weight], u_tones: ["2f", range(p.tones)],
                          u_colour_on: ["1i", p.colour ? 1 : 0], u_strength: ["1f", p.strength],
                          u_exposure: ["2f", range(p.exposure)] }),
    },
    mean_curvature: {
      label: "Curvature", needsNormals: true,
      defaults: { radius_mm: 5 },
      uniforms: (p) => ({ u_radius_mm: ["1f", p.radius_mm] }),
    },
  };

  class Viewer {
    // canvas: the WebGL canvas; overlay: a 2D canvas on top (scale bar, measurements, light)
    // base: URL of the face's relight API (…/relight), params: its params.json
    constructor(canvas, overlay, base, params) {
      this.canvas = canvas;
      this.overlay = overlay;
      this.base = base;
      this.info = params;
      this.tile = params.tile_px;
      this.levels = params.levels;
      this.pxPerMm = params.dpi / 25.4;
      this.style = "albedo";
      this.values = {};
      for (const [k, s] of Object.entries(STYLES)) this.values[k] = JSON.parse(JSON.stringify(s.defaults));
      this.light = [135, 45];
      this.background = [1, 1, 1];
      this.tiles = new Map();          // "L/r/c" -> {tex: [...], w, h} | "loading" | "failed"
      this.view = { cx: params.width / 2, cy: params.height / 2, zoom: 1 };
      this.measure = null;             // {a: [x, y], b: [x, y]} in level-0 pixels
      this.stats = { firstPictureMs: null, firstTileMs: null, completeMs: null, frames: 0, tilesLoaded: 0, uploadsLastFrame: 0 };
      this.onchange = null;
      this._scheduled = false;
    }

    async init() {
      this.stats.initMs = performance.now();
      const gl = this.canvas.getContext("webgl2", { antialias: false, preserveDrawingBuffer: true,
                                                     premultipliedAlpha: false, alpha: false });
      if (!gl) throw new Error("This browser has no WebGL2: the relighting viewer cannot run here.");
      this.gl = gl;
      this.stats.contextMs = performance.now();
      const names = Object.keys(STYLES);
      const [vert, common, ...frags] = await shaderSources();
      this.stats.sourcesMs = performance.now();
      // sources now, programs when a style is first drawn (compiling all of them would delay the
      // first picture); a style's compile error still shows at once: the page draws it first
      this.sources = {};
      names.forEach((n, i) => { this.sources[n] = [vert, "#version 300 es\n" + common + "\n" + frags[i]]; });
      this.programs = {};
      this.quad = gl.createBuffer();
      gl.bindBuffer(gl.ARRAY_BUFFER, this.quad);
      gl.bufferData(gl.ARRAY_BUFFER, new Float32Array([0, 0, 1, 0, 0, 1, 1, 1]), gl.STATIC_DRAW);
      this.vao = gl.createVertexArray();
      gl.bindVertexArray(this.vao);
      gl.enableVertexAttribArray(0);
      gl.vertexAttribPointer(0, 2, gl.FLOAT, false, 0, 0);
      this.resize();
      this.fit();
      this._observer = new ResizeObserver(() => { this.resize(); this.draw(); });
      this._observer.observe(this.canvas);
    }

    // let go of the GPU memory and the canvas (another face takes it)
    dispose() {
      this.disposed = true;
      if (this._observer) this._observer.disconnect();
      const gl = this.gl;
      if (!gl) return;
      for (const t of this.tiles.values()) if (t && t.tex) t.tex.forEach((x) => gl.deleteTexture(x));
      this.tiles.clear();
      for (const p of Object.values(this.programs || {})) gl.deleteProgram(p.p);
    }

    _program(vsrc, fsrc, name) {
      const gl = this.gl;
      const shader = (type, src) => {
        const s = gl.createShader(type);
        gl.shaderSource(s, src);
        gl.compileShader(s);
        if (!gl.getShaderParameter(s, gl.COMPILE_STATUS)) throw new Error(`${name}: ${gl.getShaderInfoLog(s)}`);
        return s;
      };
      const p = gl.createProgram();
      gl.attachShader(p, shader(gl.VERTEX_SHADER, vsrc));
      gl.attachShader(p, shader(gl.FRAGMENT_SHADER, fsrc));
      gl.bindAttribLocation(p, 0, "a_corner");
      gl.linkProgram(p);
      if (!gl.getProgramParameter(p, gl.LINK_STATUS)) throw new Error(`${name}: ${gl.getProgramInfoLog(p)}`);
      const loc = {};
      const n = gl.getProgramParameter(p, gl.ACTIVE_UNIFORMS);
      for (let i = 0; i < n; i++) {
        const u = gl.getActiveUniform(p, i);
        loc[u.name] = gl.getUniformLocation(p, u.name);
      }
      return { p, loc };
    }

    // ---- view --------------------------------------------------------------------------------
    resize() {
      const dpr = window.devicePixelRatio || 1;
      const w = Math.max(1, Math.round(this.canvas.clientWidth * dpr));
      const h = Math.max(1, Math.round(this.canvas.clientHeight * dpr));
      for (const c of [this.canvas, this.overlay]) {
        if (c.width !== w || c.height !== h) { c.width = w; c.height = h; }
      }
    }

    fit() {
      const { width, height } = this.info;
      this.view = { cx: width / 2, cy: height / 2,
                    zoom: Math.min(this.canvas.width / width, this.canvas.height / height) * 0.95 };
      this.draw();
    }

    // canvas pixels of a level-0 image point and back
    toCanvas(x, y) {
      const v = this.view;
      return [(x - v.cx) * v.zoom + this.canvas.width / 2, (y - v.cy) * v.zoom + this.canvas.height / 2];
    }
    toImage(px, py) {
      const v = this.view;
      return [(px - this.canvas.width / 2) / v.zoom + v.cx, (py - this.canvas.height / 2) / v.zoom + v.cy];
    }

    zoomAt(factor, px, py) {
      const [x, y] = this.toImage(px, py);
      const maxZoom = 16, minZoom = Math.min(this.canvas.width / this.info.width, this.canvas.height / this.info.height) / 4;
      this.view.zoom = Math.min(maxZoom, Math.max(minZoom, this.view.zoom * factor));
      this.view.cx = x - (px - this.canvas.width / 2) / this.view.zoom;
      this.view.cy = y - (py - this.canvas.height / 2) / this.view.zoom;
      this.draw();
    }

    pan(dx, dy) {
      this.view.cx -= dx / this.view.zoom;
      this.view.cy -= dy / this.view.zoom;
      this.draw();
    }

    // the level whose pixel is closest to, and not larger than, a canvas pixel
    level() {
      const L = Math.floor(Math.log2(1 / this.view.zoom) + 1e-6);
      return Math.min(this.levels.length - 1, Math.max(0, L));
    }

    visibleTiles(L) {
      const f = 2 ** L, t = this.tile, [lw, lh] = this.levels[L];
      const [x0, y0] = this.toImage(0, 0), [x1, y1] = this.toImage(this.canvas.width, this.canvas.height);
      const c0 = Math.max(0, Math.floor(x0 / f / t)), c1 = Math.min(Math.ceil(lw / t) - 1, Math.floor(x1 / f / t));
      const r0 = Math.max(0, Math.floor(y0 / f / t)), r1 = Math.min(Math.ceil(lh / t) - 1, Math.floor(y1 / f / t));
      const out = [];
      for (let r = r0; r <= r1; r++) for (let c = c0; c <= c1; c++) out.push([r, c]);
      return out;
    }

    // ---- style, light ------------------------------------------------------------------------
    setStyle(name, values) {
      if (!STYLES[name]) throw new Error(`unknown style ${name}`);
      this.style = name;
      values = values || {};
      Object.assign(this.values[name], values);
      const v = this.values[name];
      // the light stays where it was, unless the values give one
      if (name === "raking") {
        if (!("azimuth_deg" in values)) v.azimuth_deg = this.light[0];
        this.light = [v.azimuth_deg, v.elevation_deg];
      } else if ("light" in v) {
        if ("light" in values) this.light = v.light.slice(); else v.light = this.light.slice();
      }
      this.changed();
    }

    setValues(values) { Object.assign(this.values[this.style], values); this.changed(); }

    setLight(az, el) {
      az = ((az % 360) + 360) % 360;
      el = Math.max(0, Math.min(90, el));
      this.light = [az, el];
      const v = this.values[this.style];
      if (this.style === "raking") { v.azimuth_deg = az; v.elevation_deg = el; }
      else if ("light" in v) v.light = [az, el];
      this.changed();
    }

    lightVector() {
      const v = this.values[this.style];
      if (this.style === "raking") return lightVector(v.azimuth_deg, v.elevation_deg);
      return lightVector(...(v.light || this.light));
    }

    changed() {
      if (this.onchange) this.onchange(this);
      this.draw();
    }

    // ---- tiles --------------------------------------------------------------------------------
    _request(L, r, c) {
      const key = `${L}/${r}/${c}`;
      if (this.tiles.has(key)) return;
      this.tiles.set(key, "loading");
      fetch(`${this.base}/tiles/${L}/${r}_${c}`).then((resp) => {
        if (!resp.ok) throw new Error(`tile ${key}: HTTP ${resp.status}`);
        return resp.arrayBuffer();
      }).then((buf) => {
        if (this.disposed) return;
        this.tiles.set(key, this._upload(L, r, c, buf));
        this.stats.tilesLoaded += 1;
        this.draw();
      }).catch((e) => {
        this.tiles.set(key, "failed");
        if (this.onerror) this.onerror(e);
      });
    }

    _upload(L, r, c, buf) {
      const gl = this.gl, t = this.tile, [lw, lh] = this.levels[L];
      const w = Math.min(t, lw - c * t), h = Math.min(t, lh - r * t);
      const n = w * h;
      if (buf.byteLength !== n * 12 * 2 + n * 2 + n * 4) throw new Error(`tile ${L}/${r}/${c} has ${buf.byteLength} bytes`);
      const tex = (internal, format, type, data) => {
        const x = gl.createTexture();
        gl.bindTexture(gl.TEXTURE_2D, x);
        gl.pixelStorei(gl.UNPACK_ALIGNMENT, 1);
        gl.texImage2D(gl.TEXTURE_2D, 0, internal, w, h, 0, format, type, data);
        gl.texParameteri(gl.TEXTURE_2D, gl.TEXTURE_MIN_FILTER, gl.LINEAR);
        gl.texParameteri(gl.TEXTURE_2D, gl.TEXTURE_MAG_FILTER, gl.LINEAR);
        gl.texParameteri(gl.TEXTURE_2D, gl.TEXTURE_WRAP_S, gl.CLAMP_TO_EDGE);
        gl.texParameteri(gl.TEXTURE_2D, gl.TEXTURE_WRAP_T, gl.CLAMP_TO_EDGE);
        return x;
      };
      // the float16 part is three RGBA planes, one after the other
      const planes = [0, 1, 2].map((k) => new Uint16Array(buf, k * n * 8, n * 4));
      const textures = planes.map((p) => tex(gl.RGBA16F, gl.RGBA, gl.HALF_FLOAT, p));
      textures.push(tex(gl.R16F, gl.RED, gl.HALF_FLOAT, new Uint16Array(buf, n * 24, n)));
      textures.push(tex(gl.RGBA8, gl.RGBA, gl.UNSIGNED_BYTE, new Uint8Array(buf, n * 26, n * 4)));
      this.stats.uploadsLastFrame += 1;
      return { tex: textures, w, h, mag: gl.LINEAR };
    }

    // ---- drawing ------------------------------------------------------------------------------
    draw() {
      if (this._scheduled || !this.gl || this.disposed) return;
      this._scheduled = true;
      requestAnimationFrame(() => { this._scheduled = false; this.render(); });
    }

    // Draw now: the coarsest level first, then every finer loaded level up to the one the zoom
    // needs (missing tiles show the coarser picture until they arrive); request what is missing.
    render() {
      if (this.disposed) return;
      const gl = this.gl, t0 = performance.now();
      const W = this.canvas.width, H = this.canvas.height;
      gl.viewport(0, 0, W, H);
      const bg = this.background;
      gl.clearColor(bg[0], bg[1], bg[2], 1);
      gl.clear(gl.COLOR_BUFFER_BIT);
      const style = STYLES[this.info.has_normals || !STYLES[this.style].needsNormals ? this.style : "albedo"];
      const name = Object.keys(STYLES).find((k) => STYLES[k] === style);
      if (!this.programs[name]) this.programs[name] = this._program(...this.sources[name], name);
      const prog = this.programs[name];
      gl.useProgram(prog.p);
      gl.bindVertexArray(this.vao);
      const set = (u, kind, val) => {
        const l = prog.loc[u];
        if (l === undefined || l === null) return;
        if (kind === "1f") gl.uniform1f(l, val); else if (kind === "1i") gl.uniform1i(l, val);
        else if (kind === "2f") gl.uniform2f(l, val[0], val[1]); else if (kind === "3f") gl.uniform3f(l, ...val);
      };
      set("u_canvas", "2f", [W, H]);
      set("u_light", "3f", this.lightVector());
      set("u_background", "3f", bg);
      for (const [u, [kind, val]] of Object.entries(style.uniforms(this.values[name]))) set(u, kind, val);
      ["u_n01", "u_n23", "u_n3u", "u_curv", "u_colour"].forEach((u, i) => set(u, "1i", i));
      const target = this.level(), top = this.levels.length - 1, t = this.tile;
      const drawTile = (tile, L, r, c) => {
        const f = 2 ** L;
        // sharp texels when a texel covers 4+ canvas pixels (measuring), smooth otherwise
        const mag = this.view.zoom * f >= 4 ? gl.NEAREST : gl.LINEAR;
        tile.tex.forEach((x, i) => {
          gl.activeTexture(gl.TEXTURE0 + i);
          gl.bindTexture(gl.TEXTURE_2D, x);
          if (tile.mag !== mag) gl.texParameteri(gl.TEXTURE_2D, gl.TEXTURE_MAG_FILTER, mag);
        });
        tile.mag = mag;
        const [x0, y0] = this.toCanvas(c * t * f, r * t * f);
        const [x1, y1] = this.toCanvas((c * t + tile.w) * f, (r * t + tile.h) * f);
        gl.uniform4f(prog.loc.u_rect, x0, y0, x1, y1);
        gl.drawArrays(gl.TRIANGLE_STRIP, 0, 4);
      };
      const loaded = (L, r, c) => {
        const x = this.tiles.get(`${L}/${r}/${c}`);
        return x && typeof x !== "string" ? x : null;
      };
      // the top level (one tile) is always wanted: it stands in for anything not there yet
      if (!this.tiles.has(`${top}/0/0`)) this._request(top, 0, 0);
      let drawn = 0, missing = 0, stand = 0;
      // every canvas pixel is shaded once: a visible tile of the level the zoom needs, or where it
      // has not arrived, its nearest loaded ancestor cut to the tile's rectangle (scissor)
      for (const [r, c] of this.visibleTiles(target)) {
        const tile = loaded(target, r, c);
        if (tile) { drawTile(tile, target, r, c); drawn += 1; continue; }
        missing += 1;
        if (!this.tiles.has(`${target}/${r}/${c}`)) this._request(target, r, c);
        for (let L = target + 1; L <= top; L++) {
          const k = 2 ** (L - target), a = loaded(L, Math.floor(r / k), Math.floor(c / k));
          if (!a) continue;
          const f = 2 ** target;
          const [x0, y0] = this.toCanvas(c * t * f, r * t * f), [x1, y1] = this.toCanvas((c + 1) * t * f, (r + 1) * t * f);
          // the canvas pixels whose centres are in the tile (GL counts rows from the bottom)
          const px0 = Math.round(x0), px1 = Math.round(x1), py0 = Math.round(y0), py1 = Math.round(y1);
          gl.enable(gl.SCISSOR_TEST);
          gl.scissor(px0, H - py1, Math.max(0, px1 - px0), Math.max(0, py1 - py0));
          drawTile(a, L, Math.floor(r / k), Math.floor(c / k));
          gl.disable(gl.SCISSOR_TEST);
          stand += 1;
          break;
        }
      }
      const now = performance.now();
      if (drawn + stand > 0 && this.stats.firstPictureMs === null) this.stats.firstPictureMs = now;
      if (drawn > 0 && this.stats.firstTileMs === null) this.stats.firstTileMs = now;
      if (drawn > 0 && missing === 0 && this.stats.completeMs === null) this.stats.completeMs = now;
      this.stats.frames += 1;
      this.stats.lastFrameCpuMs = now - t0;
      this.stats.complete = missing === 0 && drawn > 0;
      this.stats.uploadsLastFrame = 0;
      this.drawOverlay();
    }

    // Mean time of n frames, each a full redraw with another light, finished on the GPU
    // (a 1-pixel readPixels waits for the frame): the relighting frame time.
    frameTime(n) {
      const gl = this.gl, px = new Uint8Array(4), [az0, el0] = this.light;
      const t0 = performance.now();
      for (let i = 0; i < n; i++) {
        this.light = [az0 + (360 * i) / n, el0];
        const v = this.values[this.style];
        if (this.style === "raking") v.azimuth_deg = this.light[0]; else if ("light" in v) v.light = this.light.slice();
        this.render();
        gl.readPixels(0, 0, 1, 1, gl.RGBA, gl.UNSIGNED_BYTE, px);
      }
      const ms = (performance.now() - t0) / n;
      this.setLight(az0, el0);
      return ms;
    }

    // RGBA bytes of a canvas rectangle, rows from the top (what the parity test compares)
    pixels(x, y, w, h) {
      const gl = this.gl, out = new Uint8Array(w * h * 4);
      gl.readPixels(x, this.canvas.height - y - h, w, h, gl.RGBA, gl.UNSIGNED_BYTE, out);
      const flipped = new Uint8Array(w * h * 4), row = w * 4;
      for (let j = 0; j < h; j++) flipped.set(out.subarray((h - 1 - j) * row, (h - j) * row), j * row);
      return flipped;
    }

    // ---- overlay: scale bar, measurement, light direction -------------------------------------
    scaleBar() {
      const pxPerMm = this.pxPerMm * this.view.zoom;
      const want = 120 / pxPerMm;
      const p = 10 ** Math.floor(Math.log10(want));
      const mm = [1, 2, 5, 10].map((k) => k * p).filter((v) => v <= want).pop() || p;
      return { mm, px: mm * pxPerMm };
    }

    measureMm() {
      if (!this.measure || !this.measure.b) return null;
      const [ax, ay] = this.measure.a, [bx, by] = this.measure.b;
      return Math.hypot(bx - ax, by - ay) / this.pxPerMm;
    }

    drawOverlay() {
      const o = this.overlay, g = o.getContext("2d"), dpr = window.devicePixelRatio || 1;
      g.clearRect(0, 0, o.width, o.height);
      g.font = `${13 * dpr}px sans-serif`;
      g.lineWidth = 2 * dpr;
      // scale bar, bottom left
      const { mm, px } = this.scaleBar();
      const x = 16 * dpr, y = o.height - 18 * dpr;
      g.fillStyle = "rgba(255,255,255,0.8)";
      g.fillRect(x - 6 * dpr, y - 22 * dpr, px + 12 * dpr, 30 * dpr);
      g.strokeStyle = "#000";
      g.beginPath(); g.moveTo(x, y - 6 * dpr); g.lineTo(x, y); g.lineTo(x + px, y); g.lineTo(x + px, y - 6 * dpr); g.stroke();
      g.fillStyle = "#000";
      g.fillText(`${mm >= 1 ? mm : mm.toPrecision(1)} mm`, x, y - 9 * dpr);
      // measurement
      if (this.measure) {
        const a = this.toCanvas(...this.measure.a), b = this.toCanvas(...(this.measure.b || this.measure.a));
        g.strokeStyle = "#e5007d";
        g.beginPath(); g.moveTo(...a); g.lineTo(...b); g.stroke();
        for (const p of [a, b]) { g.beginPath(); g.arc(p[0], p[1], 4 * dpr, 0, 2 * Math.PI); g.stroke(); }
        const d = this.measureMm();
        if (d !== null) {
          const label = `${d.toFixed(2)} mm`;
          g.fillStyle = "rgba(255,255,255,0.85)";
          const w = g.measureText(label).width;
          g.fillRect(b[0] + 8 * dpr, b[1] - 16 * dpr, w + 8 * dpr, 20 * dpr);
          g.fillStyle = "#e5007d";
          g.fillText(label, b[0] + 12 * dpr, b[1] - 2 * dpr);
        }
      }
      // light direction, top right: a disc with the light's position (RTIViewer's light sphere)
      if (STYLES[this.style].needsNormals && this.info.has_normals) {
        const r = 28 * dpr, cx = o.width - r - 12 * dpr, cy = r + 12 * dpr;
        const [az, el] = this.style === "raking" ?
          [this.values.raking.azimuth_deg, this.values.raking.elevation_deg] : this.light;
        const d = Math.cos(el * Math.PI / 180) * r;
        g.fillStyle = "rgba(255,255,255,0.8)"; g.strokeStyle = "#444";
        g.beginPath(); g.arc(cx, cy, r, 0, 2 * Math.PI); g.fill(); g.stroke();
        g.fillStyle = "#f5b800";
        g.beginPath(); g.arc(cx + d * Math.cos(az * Math.PI / 180), cy - d * Math.sin(az * Math.PI / 180), 5 * dpr, 0, 2 * Math.PI);
        g.fill(); g.stroke();
      }
    }
  }

  shaderSources();
  return { Viewer, STYLES, lightVector };
})();
