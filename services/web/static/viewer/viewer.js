// The relighting viewer: OpenSeadragon 6 for deep zoom, a WebGL2 drawer of its own that shades RGBN
// fields in the style shaders.
//
// The server cuts every face into a pyramid of 256-px tiles of the light-independent fields
// (common/web/relight.py: the normals as solved and smoothed at the scales the styles need, the mean
// curvature, the display albedo and mask). OpenSeadragon (vendored: static/vendor/openseadragon/)
// does the navigation and the tile management: zoom, pan and their animation, which level the view
// needs, the queue of tile requests, the coarser tiles drawn until finer ones arrive, the cache and
// its eviction. What is ours:
//
// * RelightTileSource: the relight pyramid as an OpenSeadragon TileSource; a tile is downloaded as
//   an ArrayBuffer (HTTP gzip decodes it) into the data type RELIGHT_TILE (typed views of its
//   fields), which is what OpenSeadragon keeps in its tile cache;
// * RelightDrawer: an OpenSeadragon.DrawerBase subclass (type "tessera-relight") that accepts only
//   RELIGHT_TILE. The first time it draws a tile it uploads the tile's five textures and keeps them
//   as the drawer's private cache of that tile; OpenSeadragon frees them (internalCacheFree) when it
//   unloads the tile. Moving the light, changing a style's parameters or the contrast only changes
//   uniforms, so a frame is one draw call per tile OpenSeadragon asks for and no texture upload.
//
// The drawer also keeps the pyramid's one-tile top level (64 px, common/web/relight.TOP_PX), fetched
// as the viewer starts, as its "preview": drawn under the tiles until the view has all of them, it is
// the first picture whatever OpenSeadragon's queue holds.
//
// The style shaders are the files next to this one, named like the offline styles they mirror
// (common/render/recipes.py); the page carries their sources (no request of their own). Nothing is
// fetched from the network but this station.
"use strict";

const RelightViewer = (() => {
  const OSD = OpenSeadragon;

  // light_vector of common/render/_util.py: azimuth counter-clockwise from +x (image right),
  // elevation above the image plane; x right, y up, z towards the viewer
  function lightVector(az, el) {
    const a = az * Math.PI / 180, e = el * Math.PI / 180;
    return [Math.cos(e) * Math.cos(a), Math.cos(e) * Math.sin(a), Math.sin(e)];
  }

  // the light l turned by the rotation that takes the axis z to the way the surface faces, c (unit): a
  // near-flat face tilted as a whole is lit relative to its own plane (common.render.enhance.levelled_light
  // of a constant field, Rodrigues' formula)
  function levelledLight(l, c) {
    const ux = -c[1], uy = c[0], cz = Math.max(c[2], 1e-3), k = (ux * l[0] + uy * l[1]) / (1 + cz);
    const out = [l[0] * cz + uy * l[2] + ux * k, l[1] * cz - ux * l[2] + uy * k, l[2] * cz + (ux * l[1] - uy * l[0])];
    const n = Math.hypot(...out);
    return out.map((v) => v / n);
  }

  // the shader files' sources, which the page carries in a JSON data block (services/web/fragment.py)
  function shaderSources() {
    const block = document.getElementById("viewer-shaders");
    if (!block) throw new Error("This page does not carry the viewer's shaders (#viewer-shaders).");
    const files = JSON.parse(block.textContent);
    return ["tile.vert", "common.glsl", ...Object.keys(STYLES).map((n) => n + ".frag")].map((name) => {
      if (typeof files[name] !== "string") throw new Error(`shader ${name} is missing from the page`);
      return files[name];
    });
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
      label: "Lambertian", needsNormals: true, levelled: true,
      defaults: { light: [135, 45], ambient: 0.15, colour: true, exposure: [0.3, 0.9], colour_exposure: "none" },
      uniforms: (p) => ({ u_ambient: ["1f", p.ambient], u_exposure: ["2f", range(p.exposure)],
                          u_colour_on: ["1i", p.colour ? 1 : 0], u_colour_exposure: ["2f", range(p.colour_exposure)] }),
    },
    raking: {
      label: "Raking light", needsNormals: true, levelled: true,
      defaults: { azimuth_deg: 135, elevation_deg: 12, ambient: 0.05, colour: false, exposure: [0.05, 0.4],
                  colour_exposure: "none" },
      uniforms: (p) => ({ u_ambient: ["1f", p.ambient], u_exposure: ["2f", range(p.exposure)],
                          u_colour_on: ["1i", p.colour ? 1 : 0], u_colour_exposure: ["2f", range(p.colour_exposure)] }),
    },
    specular: {
      label: "Specular enhancement", needsNormals: true, levelled: true,
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

  // ---- the relight pyramid as an OpenSeadragon tile source ------------------------------------

  // The data type of a downloaded tile in OpenSeadragon's cache: {w, h, planes: three Uint16Array
  // (float16 RGBA: n|n0, n1|n2, n3|nu), curv: Uint16Array (float16 H), colour: Uint8Array (RGBA)}.
  const RELIGHT_TILE = "tessera-relight-tile";

  // typed views of a tile's bytes (format: common/web/relight.py), checked against its size
  function unpackTile(buf, w, h, name) {
    const n = w * h;
    if (buf.byteLength !== n * 12 * 2 + n * 2 + n * 4) throw new Error(`tile ${name} has ${buf.byteLength} bytes`);
    // the float16 part is three RGBA planes, one after the other
    return { w, h, planes: [0, 1, 2].map((k) => new Uint16Array(buf, k * n * 8, n * 4)),
             curv: new Uint16Array(buf, n * 24, n), colour: new Uint8Array(buf, n * 26, n * 4) };
  }

  // OpenSeadragon numbers levels from a 1-pixel image up (its maxLevel is full resolution); the
  // relight pyramid from full resolution (0) down, each level the one before halved, rounding up,
  // which is OpenSeadragon's own level size. Only the pyramid's levels are offered (minLevel).
  class RelightTileSource extends OSD.TileSource {
    constructor(base, params) {
      const [width, height] = params.levels[0];
      const maxLevel = Math.ceil(Math.log2(Math.max(width, height, 2)));
      super({ width, height, tileSize: params.tile_px, tileOverlap: 0,
              minLevel: maxLevel - (params.levels.length - 1), maxLevel });
      this.base = base;
      this.levels = params.levels;
    }

    relightLevel(level) { return this.maxLevel - level; }

    getTileUrl(level, x, y) { return `${this.base}/tiles/${this.relightLevel(level)}/${y}_${x}`; }

    // the tile's bytes with fetch (the same request as the page's preload of the top level)
    downloadTileStart(job) {
      const t = job.tile, L = this.relightLevel(t.level), size = this.tilePixels(L, t.y, t.x);
      const name = `${L}/${t.y}/${t.x}`, abort = job.userData.abort = new AbortController();
      fetch(job.src, { signal: abort.signal }).then((r) => {
        if (!r.ok) throw new Error(`tile ${name}: HTTP ${r.status}`);
        return r.arrayBuffer();
      }).then((buf) => job.finish(unpackTile(buf, size[0], size[1], name), null, RELIGHT_TILE))
        .catch((e) => { if (!abort.signal.aborted) job.fail(String(e.message || e), null); });
    }

    // OpenSeadragon has failed the job itself
    downloadTileAbort(job) { job.userData.abort.abort(); }

    // [w, h] in pixels of tile (row r, column c) of relight level L
    tilePixels(L, r, c) {
      const [lw, lh] = this.levels[L], t = this.getTileWidth();
      return [Math.min(t, lw - c * t), Math.min(t, lh - r * t)];
    }
  }

  // ---- the drawer ---------------------------------------------------------------------------

  class RelightDrawer extends OSD.DrawerBase {
    // options.relight: the Viewer below (style, light, values; stats)
    constructor(options) {
      super(options);
      this.relight = this.options.relight;
      const gl = this.canvas.getContext("webgl2", { antialias: false, preserveDrawingBuffer: true,
                                                     premultipliedAlpha: false, alpha: false });
      this.gl = gl;
      this.programs = {};
      this.quad = gl.createBuffer();
      gl.bindBuffer(gl.ARRAY_BUFFER, this.quad);
      gl.bufferData(gl.ARRAY_BUFFER, new Float32Array([0, 0, 1, 0, 0, 1, 1, 1]), gl.STATIC_DRAW);
      this.vao = gl.createVertexArray();
      gl.bindVertexArray(this.vao);
      gl.enableVertexAttribArray(0);
      gl.vertexAttribPointer(0, 2, gl.FLOAT, false, 0, 0);
    }

    // the private cache (the textures) is made in the drawing loop, from the tile's cached
    // RELIGHT_TILE: one upload when a tile is first drawn
    get defaultOptions() { return { usePrivateCache: true, preloadCache: false }; }

    getType() { return "tessera-relight"; }

    getSupportedDataFormats() { return [RELIGHT_TILE]; }

    static isSupported() {
      return !!document.createElement("canvas").getContext("webgl2");
    }

    canRotate() { return false; }

    // the drawer picks its own filtering (sharp texels when zoomed far in, see draw)
    setImageSmoothingEnabled() {}

    _createDrawingElement() {
      const canvas = OSD.makeNeutralElement("canvas"), size = this._canvasSize();
      canvas.width = size[0];
      canvas.height = size[1];
      return canvas;
    }

    _canvasSize() {
      const c = this.viewport.getContainerSize(), dpr = OSD.pixelDensityRatio;
      return [Math.max(1, Math.round(c.x * dpr)), Math.max(1, Math.round(c.y * dpr))];
    }

    destroy() {
      this.destroyInternalCache();     // the tiles' textures, while the context is there
      if (this.preview && this.preview.tex) this.internalCacheFree(this.preview.tex);
      const gl = this.gl;
      for (const p of Object.values(this.programs)) gl.deleteProgram(p.p);
      gl.deleteBuffer(this.quad);
      gl.deleteVertexArray(this.vao);
      super.destroy();
      this.container.removeChild(this.canvas);
      // the GPU memory now, not when the canvas is collected (browsers cap live contexts)
      const lose = gl.getExtension("WEBGL_lose_context");
      if (lose) lose.loseContext();
    }

    // five textures of a tile: three RGBA16F, one R16F, one RGBA8
    internalCacheCreate(cache) {
      return this._upload(cache.data);
    }

    _upload(d) {
      const gl = this.gl;
      const tex = (internal, format, type, data) => {
        const x = gl.createTexture();
        gl.bindTexture(gl.TEXTURE_2D, x);
        gl.pixelStorei(gl.UNPACK_ALIGNMENT, 1);
        gl.texImage2D(gl.TEXTURE_2D, 0, internal, d.w, d.h, 0, format, type, data);
        gl.texParameteri(gl.TEXTURE_2D, gl.TEXTURE_MIN_FILTER, gl.LINEAR);
        gl.texParameteri(gl.TEXTURE_2D, gl.TEXTURE_MAG_FILTER, gl.LINEAR);
        gl.texParameteri(gl.TEXTURE_2D, gl.TEXTURE_WRAP_S, gl.CLAMP_TO_EDGE);
        gl.texParameteri(gl.TEXTURE_2D, gl.TEXTURE_WRAP_T, gl.CLAMP_TO_EDGE);
        return x;
      };
      const textures = d.planes.map((p) => tex(gl.RGBA16F, gl.RGBA, gl.HALF_FLOAT, p));
      textures.push(tex(gl.R16F, gl.RED, gl.HALF_FLOAT, d.curv));
      textures.push(tex(gl.RGBA8, gl.RGBA, gl.UNSIGNED_BYTE, d.colour));
      this.relight.stats.uploads += 1;
      this.relight.stats.gpuTiles += 1;
      return { tex: textures, mag: gl.LINEAR };
    }

    internalCacheFree(data) {
      if (!this.gl.isContextLost()) data.tex.forEach((x) => this.gl.deleteTexture(x));
      data.tex = [];
      this.relight.stats.gpuTiles -= 1;
    }

    _program(name) {
      if (this.programs[name]) return this.programs[name];
      const gl = this.gl, [vsrc, fsrc] = this.relight.sources[name];
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
      return (this.programs[name] = { p, loc });
    }

    // Draw the tiles OpenSeadragon asks for (coarser ones first, where finer ones have not arrived)
    // with the current style's shader, each as a quad at its place in the view.
    draw(tiledImages) {
      const v = this.relight, gl = this.gl, t0 = performance.now();
      const [W, H] = this._canvasSize();
      if (this.canvas.width !== W || this.canvas.height !== H) { this.canvas.width = W; this.canvas.height = H; }
      gl.viewport(0, 0, W, H);
      const bg = v.background;
      gl.clearColor(bg[0], bg[1], bg[2], 1);
      gl.clear(gl.COLOR_BUFFER_BIT);
      const name = v.info.has_normals || !STYLES[v.style].needsNormals ? v.style : "albedo";
      const prog = this._program(name);
      gl.useProgram(prog.p);
      gl.bindVertexArray(this.vao);
      const set = (u, kind, val) => {
        const l = prog.loc[u];
        if (l === undefined || l === null) return;
        if (kind === "1f") gl.uniform1f(l, val); else if (kind === "1i") gl.uniform1i(l, val);
        else if (kind === "2f") gl.uniform2f(l, val[0], val[1]); else if (kind === "3f") gl.uniform3f(l, ...val);
      };
      set("u_canvas", "2f", [W, H]);
      set("u_light", "3f", v.lightVector());
      set("u_background", "3f", bg);
      for (const [u, [kind, val]] of Object.entries(STYLES[name].uniforms(v.values[name]))) set(u, kind, val);
      ["u_n01", "u_n23", "u_n3u", "u_curv", "u_colour"].forEach((u, i) => set(u, "1i", i));
      const view = v.currentView(), target = v.level();
      let drawn = 0, stand = 0, complete = tiledImages.length > 0;
      // one quad of a tile's textures at its footprint: tile (r, c) of relight level L, w x h pixels
      const quad = (tex, L, r, c, w, h) => {
        const t = this.relight.info.tile_px, f = 2 ** L;
        // sharp texels when a texel covers 4+ canvas pixels (measuring), smooth otherwise
        const mag = view.zoom * f >= 4 ? gl.NEAREST : gl.LINEAR;
        tex.tex.forEach((x, i) => {
          gl.activeTexture(gl.TEXTURE0 + i);
          gl.bindTexture(gl.TEXTURE_2D, x);
          if (tex.mag !== mag) gl.texParameteri(gl.TEXTURE_2D, gl.TEXTURE_MAG_FILTER, mag);
        });
        tex.mag = mag;
        // the tile's exact footprint in level-0 pixels (its level's pixels are 2^L of them)
        const [x0, y0] = v.toCanvas(c * t * f, r * t * f, view);
        const [x1, y1] = v.toCanvas((c * t + w) * f, (r * t + h) * f, view);
        gl.uniform4f(prog.loc.u_rect, x0, y0, x1, y1);
        gl.drawArrays(gl.TRIANGLE_STRIP, 0, 4);
        if (L === target) drawn += 1; else stand += 1;
      };
      // the top level under everything until the view's tiles are all there: the first picture, and
      // the backdrop where finer tiles have not come (not after: it would shade every pixel twice)
      const p = this.preview;
      if (p && !(tiledImages.length > 0 && tiledImages.every((i) => i.getFullyLoaded()))) {
        if (!p.tex) p.tex = this._upload(p.data);
        quad(p.tex, p.level, 0, 0, p.data.w, p.data.h);
      }
      for (const image of tiledImages) {
        const source = image.source;
        for (const { tile } of image.getTilesToDraw()) {
          const cache = this.getDataToDraw(tile);
          if (!cache) continue;
          const L = source.relightLevel(tile.level), [w, h] = source.tilePixels(L, tile.y, tile.x);
          quad(cache, L, tile.y, tile.x, w, h);
        }
        complete = complete && image.getFullyLoaded();
      }
      v.drawn(drawn, stand, complete && drawn > 0, performance.now() - t0);
    }
  }
  // registered under its type, as OpenSeadragon finds drawers (OpenSeadragon.determineDrawer)
  OSD.TesseraRelightDrawer = RelightDrawer;

  // ---- the viewer: OpenSeadragon + the drawer, the style and light, the overlay ----------------

  class Viewer {
    // element: the (empty) element OpenSeadragon fills; overlay: a 2D canvas on top (scale bar,
    // measurements, light); base: URL of the face's relight API (…/relight), params: its params.json
    constructor(element, overlay, base, params) {
      this.element = element;
      this.overlay = overlay;
      this.base = base;
      this.info = params;
      this.levels = params.levels;
      this.pxPerMm = params.dpi / 25.4;
      this.style = "albedo";
      this.values = {};
      for (const [k, s] of Object.entries(STYLES)) this.values[k] = JSON.parse(JSON.stringify(s.defaults));
      this.light = [135, 45];
      this.background = [1, 1, 1];
      this.measure = null;             // {a: [x, y], b: [x, y]} in level-0 pixels
      this.stats = { firstPictureMs: null, firstTileMs: null, completeMs: null, frames: 0, tilesLoaded: 0,
                    uploads: 0, gpuTiles: 0 };   // tiles uploaded (ever), tiles whose textures are on the GPU now
      this.onchange = null;
      this.onerror = null;
      // resolved when the first view has every tile it needs
      this.complete = new Promise((resolve) => { this._complete = resolve; });
    }

    async init() {
      this.stats.initMs = performance.now();
      if (!RelightDrawer.isSupported()) throw new Error("This browser has no WebGL2: the relighting viewer cannot run here.");
      // the one-tile top level is the first picture and the backdrop until the view's tiles are all
      // there (the drawer's preview): its bytes are on their way while OpenSeadragon starts (the page
      // preloads the same URL), not queued behind the level the view needs, which OpenSeadragon fetches
      const top = this.levels.length - 1, [tw, th] = this.levels[top];
      const preview = fetch(`${this.base}/tiles/${top}/0_0`).then((r) => {
        if (!r.ok) throw new Error(`tile ${top}/0/0: HTTP ${r.status}`);
        return r.arrayBuffer();
      }).then((buf) => unpackTile(buf, tw, th, `${top}/0/0`));
      const source = new RelightTileSource(this.base, this.info);
      const [vert, common, ...frags] = shaderSources();
      this.stats.sourcesMs = performance.now();
      // sources now, programs when a style is first drawn (compiling all of them would delay the
      // first picture); a style's compile error still shows at once: the page draws it first
      this.sources = {};
      Object.keys(STYLES).forEach((n, i) => { this.sources[n] = [vert, "#version 300 es\n" + common + "\n" + frags[i]]; });
      this.osd = OSD({
        element: this.element,
        drawer: "tessera-relight",
        drawerOptions: { "tessera-relight": { relight: this } },
        // the page has its own buttons and keys (a 1:1, measuring); OpenSeadragon's would load
        // their pictures from prefixUrl, and its keys (r rotates, f flips) mean other things here
        showNavigationControl: false,
        keyboardNavEnabled: false,
        // the wheel is the page's (zoomAt: proportional to the wheel's delta, smooth on touchpads);
        // a click does not zoom: a click is how light and measuring start
        gestureSettingsMouse: { scrollToZoom: false, clickToZoom: false, dblClickToZoom: false },
        gestureSettingsPen: { clickToZoom: false },
        // zoom: from a quarter of the fitted face to 16 screen pixels an image pixel (measuring)
        maxZoomPixelRatio: 16,
        minZoomImageRatio: 0.2,
        visibilityRatio: 0.2,
        preserveImageSizeOnResize: true,
        // the tiles' CPU copies and textures (~1.5 MB each, twice): a full-HD view needs ~60
        maxImageCacheCount: 120,
        // ask for every tile a view lacks at once (OpenSeadragon asks for one a frame by default,
        // made for 60 frames a second; a frame here can take 100 ms on a CPU rasteriser), the
        // level the view needs first, not every coarser level on the way (the preloaded one-tile
        // top level stands in meanwhile): its tiles come ~0.5 s sooner (docs/web.md)
        maxTilesPerFrame: 32,
        immediateRender: true,
        // a tile of a level being cut when a face is first opened may take tens of seconds
        timeout: 300000,
      });
      this.drawer = this.osd.drawer;
      this.canvas = this.drawer.canvas;
      preview.then((d) => { if (this.osd) { this.drawer.preview = { data: d, level: top }; this.draw(); } })
        .catch((e) => { if (this.onerror) this.onerror(e); });
      this.stats.contextMs = performance.now();
      this.osd.addHandler("tile-loaded", () => { this.stats.tilesLoaded += 1; });
      this.osd.addHandler("tile-load-failed", (e) => { if (this.onerror) this.onerror(new Error(e.message)); });
      this.osd.addHandler("update-viewport", () => this.drawOverlay());
      // a drag pans with the pointer, not a spring behind it: the image point under the pointer
      // stays under it (OpenSeadragon animates a mouse drag's pan unless flicking is on)
      this.osd.addHandler("canvas-drag", (e) => {
        e.preventDefaultAction = true;
        this.osd.viewport.panBy(this.osd.viewport.deltaPointsFromPixels(e.delta.negate()), true);
      });
      const opened = new Promise((resolve, reject) => {
        this.osd.addOnceHandler("open", resolve);
        this.osd.addOnceHandler("open-failed", (e) => reject(new Error(e.message)));
      });
      this.osd.open(source);
      await opened;
      this.fit(true);
    }

    // let go of OpenSeadragon, its cache, the GPU memory and the canvas (another face takes it)
    dispose() {
      if (this.osd) this.osd.destroy();
      this.osd = null;
    }

    // ---- view: image (level-0) pixels and canvas pixels ---------------------------------------
    // OpenSeadragon's viewport coordinates have the image's width as 1; zoom here is canvas
    // (device) pixels per image pixel. `view` is where the view is going (OpenSeadragon's target),
    // currentView() where an animation is now: what is drawn, what the pointer is over.
    _view(current) {
      const vp = this.osd.viewport, c = vp.getCenter(current), W = this.info.width;
      return { cx: c.x * W, cy: c.y * W,
               zoom: vp.getZoom(current) * vp.getContainerSize().x * OSD.pixelDensityRatio / W };
    }
    get view() { return this._view(false); }
    currentView() { return this._view(true); }

    // go to a view at once (no animation) and draw it
    set view(v) { this._goTo(v, true); }

    _goTo(v, immediately) {
      const vp = this.osd.viewport, W = this.info.width;
      vp.zoomTo(v.zoom * W / (vp.getContainerSize().x * OSD.pixelDensityRatio), null, immediately);
      vp.panTo(new OSD.Point(v.cx / W, v.cy / W), immediately);
      this.draw();
    }

    fit(immediately) {
      const { width, height } = this.info, c = this.canvas;
      this._goTo({ cx: width / 2, cy: height / 2,
                   zoom: Math.min(c.width / width, c.height / height) * 0.95 }, immediately);
    }

    // one image pixel per canvas pixel, about the centre
    oneToOne() { this._goTo({ ...this.view, zoom: 1 }, false); }

    // canvas pixels of a level-0 image point and back, in a view (default: the current one)
    toCanvas(x, y, view) {
      const v = view || this.currentView();
      return [(x - v.cx) * v.zoom + this.canvas.width / 2, (y - v.cy) * v.zoom + this.canvas.height / 2];
    }
    toImage(px, py, view) {
      const v = view || this.currentView();
      return [(px - this.canvas.width / 2) / v.zoom + v.cx, (py - this.canvas.height / 2) / v.zoom + v.cy];
    }

    // zoom by factor about a canvas point, animated by OpenSeadragon: the image point now under it stays
    zoomAt(factor, px, py) {
      const vp = this.osd.viewport, [x, y] = this.toImage(px, py);
      vp.zoomBy(factor, new OSD.Point(x / this.info.width, y / this.info.width));
      vp.applyConstraints();
    }

    // move the image by (dx, dy) canvas pixels
    pan(dx, dy, immediately) {
      const vp = this.osd.viewport, z = this.view.zoom * this.info.width;
      vp.panBy(new OSD.Point(-dx / z, -dy / z), immediately);
      if (!immediately) vp.applyConstraints();
    }

    // the relight level (0 = full resolution) OpenSeadragon draws at the current zoom: the
    // coarsest whose pixel still covers at least minPixelRatio (0.5) canvas pixels... read the
    // other way, the finest that is not smaller than half a canvas pixel
    level() {
      const zoom = this.currentView().zoom;
      const L = Math.ceil(Math.log2(this.osd.minPixelRatio / zoom) - 1e-9);
      return Math.min(this.levels.length - 1, Math.max(0, L));
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
      const l = this.style === "raking" ? lightVector(v.azimuth_deg, v.elevation_deg) : lightVector(...(v.light || this.light));
      const c = this.info.surface_normal;   // a near-flat face's direction (common/web/relight.py), else null
      return STYLES[this.style].levelled && c ? levelledLight(l, c) : l;
    }

    changed() {
      if (this.onchange) this.onchange(this);
      this.draw();
    }

    // ---- drawing ------------------------------------------------------------------------------
    // at OpenSeadragon's next frame (uniforms only: the tiles' textures are there)
    draw() { if (this.osd) this.osd.forceRedraw(); }

    // Draw now: OpenSeadragon updates the view (and asks for the tiles it needs), then the
    // drawer draws (what the tests and the frame-time measurement call).
    render() {
      const osd = this.osd;
      osd.viewport.update();
      osd.world.update(true);
      osd.world.draw();
      this.drawOverlay();
    }

    // the drawer's report of a frame: tiles of the level the view needs, coarser stand-ins, and
    // whether every tile the view needs was there (OpenSeadragon's "fully loaded")
    drawn(drawn, stand, complete, ms) {
      const now = performance.now(), s = this.stats;
      if (drawn + stand > 0 && s.firstPictureMs === null) s.firstPictureMs = now;
      if (drawn > 0 && s.firstTileMs === null) s.firstTileMs = now;
      if (complete && s.completeMs === null) { s.completeMs = now; this._complete(); }
      s.frames += 1;
      s.lastFrameCpuMs = ms;
      s.complete = complete;
    }

    // Mean time of n frames, each a full redraw with another light, finished on the GPU
    // (a 1-pixel readPixels waits for the frame): the relighting frame time.
    frameTime(n) {
      const gl = this.drawer.gl, px = new Uint8Array(4), [az0, el0] = this.light;
      const t0 = performance.now();
      for (let i = 0; i < n; i++) {
        this.light = [az0 + (360 * i) / n, el0];
        const v = this.values[this.style];
        if (this.style === "raking") v.azimuth_deg = this.light[0]; else if ("light" in v) v.light = this.light.slice();
        this.osd.world.draw();
        gl.readPixels(0, 0, 1, 1, gl.RGBA, gl.UNSIGNED_BYTE, px);
      }
      const ms = (performance.now() - t0) / n;
      this.setLight(az0, el0);
      return ms;
    }

    // RGBA bytes of a canvas rectangle, rows from the top (what the parity test compares)
    pixels(x, y, w, h) {
      const gl = this.drawer.gl, out = new Uint8Array(w * h * 4);
      gl.readPixels(x, this.canvas.height - y - h, w, h, gl.RGBA, gl.UNSIGNED_BYTE, out);
      const flipped = new Uint8Array(w * h * 4), row = w * 4;
      for (let j = 0; j < h; j++) flipped.set(out.subarray((h - 1 - j) * row, (h - j) * row), j * row);
      return flipped;
    }

    // ---- overlay: scale bar, measurement, light direction -------------------------------------
    scaleBar() {
      const pxPerMm = this.pxPerMm * this.currentView().zoom;
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
      const o = this.overlay, dpr = window.devicePixelRatio || 1;
      if (o.width !== this.canvas.width || o.height !== this.canvas.height) {
        o.width = this.canvas.width; o.height = this.canvas.height;
      }
      const g = o.getContext("2d");
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
      g.fillText(`${mm >= 1 ? mm : mm.toPrecision(1)} mm${this.info.dpi_nominal ? " (nominal)" : ""}`, x, y - 9 * dpr);
      // measurement
      if (this.measure) {
        const a = this.toCanvas(...this.measure.a), b = this.toCanvas(...(this.measure.b || this.measure.a));
        g.strokeStyle = "#e5007d";
        g.beginPath(); g.moveTo(...a); g.lineTo(...b); g.stroke();
        for (const p of [a, b]) { g.beginPath(); g.arc(p[0], p[1], 4 * dpr, 0, 2 * Math.PI); g.stroke(); }
        const d = this.measureMm();
        if (d !== null) {
          const label = `${d.toFixed(2)} mm${this.info.dpi_nominal ? " (nominal)" : ""}`;
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

  return { Viewer, STYLES, lightVector };
})();
