// pitune console: shared helpers (no framework, no build step).
"use strict";
const pitune = (() => {
  const csrf = document.querySelector('meta[name="pitune-csrf"]').content;
  const loggedIn = document.body.dataset.loggedIn === "1";
  const esc = (s) => String(s ?? "").replace(/[&<>"']/g, (c) => ({"&": "&amp;", "<": "&lt;", ">": "&gt;", '"': "&quot;", "'": "&#39;"}[c]));
  const num = (x, digits = 4) => {
    if (x === null || x === undefined || Number.isNaN(x)) return "–";
    if (x === 0) return "0";
    const a = Math.abs(x);
    if (a >= 1e5 || a < 1e-3) return x.toExponential(digits - 1);
    return x.toPrecision(digits).replace(/\.?0+$/, "");
  };
  // Axis tick labels (uPlot's `values`): as num, with the fewest significant digits that
  // render every tick as its value; uPlot's own labels round small gains (ki
  // 0.00505..0.00512) to one repeated "0.005".
  const ticks = (u, splits) => {
    const tol = 1e-6 * Math.max(...splits.map(Math.abs));  // float noise in the splits
    for (let d = 1; ; d++) {
      const out = splits.map((v) => num(v, d));
      if (d >= 15 || out.every((s, i) => Math.abs(Number(s) - splits[i]) <= tol)) return out;
    }
  };
  const int = (x) => (x === null || x === undefined ? "–" : Number(x).toLocaleString("en-US"));
  const ago = (wallS) => {
    if (!wallS) return "–";
    const s = Math.max(0, Date.now() / 1000 - wallS);
    if (s < 60) return `${s.toFixed(0)} s ago`;
    if (s < 3600) return `${(s / 60).toFixed(0)} min ago`;
    if (s < 86400) return `${(s / 3600).toFixed(1)} h ago`;
    return new Date(wallS * 1000).toISOString().slice(0, 16).replace("T", " ");
  };
  const when = (wallS) => new Date(wallS * 1000).toISOString().slice(0, 19).replace("T", " ");
  let toastTimer = null;
  const toast = (msg, bad = false) => {
    const el = document.getElementById("toast");
    el.textContent = msg;
    el.className = bad ? "show bad" : "show";
    clearTimeout(toastTimer);
    toastTimer = setTimeout(() => { el.className = ""; }, 4000);
  };
  async function getJSON(url) {
    const r = await fetch(url, {headers: {Accept: "application/json"}, cache: "no-store"});
    if (!r.ok) throw new Error(`${r.status} ${r.statusText}`);
    return r.json();
  }
  // A state-changing request: the session cookie goes along (same origin), the CSRF token in a header.
  async function act(url, body) {
    const r = await fetch(url, {
      method: "POST",
      headers: {"Content-Type": "application/json", "X-CSRF-Token": csrf},
      body: body === undefined ? "" : JSON.stringify(body),
    });
    let detail = "";
    try { detail = (await r.json()).detail; } catch (e) { /* not JSON */ }
    if (!r.ok) {
      const msg = typeof detail === "string" ? detail : JSON.stringify(detail);
      throw new Error(`${r.status}: ${msg || r.statusText}`);
    }
    return detail === undefined ? null : detail;
  }
  // The plant-wide hold: the banner on every page, live. Pages follow the hold's stream;
  // a loop page's own stream carries the hold (loop.js calls showHold). A page's own
  // parts take each change with onHold.
  let plant = null;
  const holdWatchers = [];
  function showHold(h) {
    if (plant && JSON.stringify(h) === JSON.stringify(plant)) return;
    plant = h;
    const banner = document.getElementById("hold-banner");
    banner.hidden = !h.held;
    banner.dataset.by = h.held ? h.by : "";
    banner.replaceChildren();  // text nodes only: a reason is never markup
    if (h.held) {
      const title = document.createElement("strong");
      title.textContent = "Plant-wide hold: all tuning held";
      const reason = document.createElement("span");
      reason.id = "hold-banner-reason";
      reason.textContent = h.reason;
      const tuner = document.createElement("a");
      tuner.href = "/ui/tuner";
      tuner.textContent = "release it on the tuner page";
      banner.append(title, ` since ${when(h.since)} UTC, set by ${h.by}: `, reason,
        ". No loop's gains change while held (rollbacks of earlier changes and operators' own actions excepted); ",
        tuner, ".");
    }
    for (const fn of holdWatchers) fn(h);
  }
  const onHold = (fn) => { holdWatchers.push(fn); if (plant) fn(plant); };
  function followHold() {
    const es = new EventSource("/ui/api/hold/stream");
    es.onmessage = (e) => showHold(JSON.parse(e.data));
    es.addEventListener("bye", () => { es.close(); followHold(); });  // (as a loop page's)
  }
  if (document.body.dataset.holdStream === "1") followHold();
  return {csrf, loggedIn, esc, num, ticks, int, ago, when, toast, getJSON, act, showHold, onHold, followHold};
})();
