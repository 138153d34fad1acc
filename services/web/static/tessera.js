// Shared helpers of the station pages (no framework, no build step, no network beyond this station).
"use strict";
const Tessera = (() => {
  const csrf = () => (document.querySelector('meta[name="csrf-token"]') || {}).content || "";
  const loggedIn = () => document.body.dataset.loggedIn === "yes";

  // ``timeoutMs``: give up a request that has not answered by then (answered as "does not answer")
  async function api(method, url, body, { timeoutMs } = {}) {
    const opts = { method, headers: { "Accept": "application/json" }, credentials: "same-origin" };
    if (timeoutMs) opts.signal = AbortSignal.timeout(timeoutMs);
    if (method !== "GET") {
      opts.headers["Content-Type"] = "application/json";
      opts.headers["X-CSRF-Token"] = csrf();
      opts.body = JSON.stringify(body || {});
    }
    let resp;
    try {
      resp = await fetch(url, opts);
    } catch (e) {
      return { ok: false, status: 0, data: { error: "The station does not answer. Check that it is running and the network is connected." } };
    }
    let data = {};
    try { data = await resp.json(); } catch (e) { data = {}; }
    if (resp.status === 401 && !data.error) data.error = "Log in to do this.";
    return { ok: resp.ok, status: resp.status, data };
  }

  function el(tag, attrs, ...children) {
    const e = document.createElement(tag);
    for (const [k, v] of Object.entries(attrs || {})) {
      if (k === "class") e.className = v; else if (k === "text") e.textContent = v;
      else if (k.startsWith("data-")) e.setAttribute(k, v); else e[k] = v;
    }
    for (const c of children) e.append(c);
    return e;
  }

  function clock(t) {
    if (!t) return "";
    const d = new Date(t * 1000);
    return d.toLocaleTimeString([], { hour: "2-digit", minute: "2-digit", second: "2-digit" });
  }

  function when(t) {
    if (!t) return "";
    const d = new Date(t * 1000);
    const today = new Date();
    return d.toDateString() === today.toDateString() ? clock(t) : d.toLocaleString();
  }

  // how an imported fragment came (a catalogue row's `imported`: time ISO, by, file): "imported <when> from <file> (<by>)"
  function imported(imp) {
    if (!imp) return "";
    const t = Date.parse(imp.time || "");
    return ["imported", isNaN(t) ? "" : when(t / 1000), imp.file ? `from ${imp.file}` : "", imp.by ? `(${imp.by})` : ""]
      .filter(Boolean).join(" ");
  }

  function typingInField(ev) {
    const t = ev.target;
    return t && (t.tagName === "INPUT" || t.tagName === "TEXTAREA" || t.isContentEditable);
  }

  return { api, el, clock, when, imported, loggedIn, typingInField };
})();
