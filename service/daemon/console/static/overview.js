// Overview: one server-side page of loops at a time (filter, sort and search on the daemon).
"use strict";
(() => {
  const $ = (id) => document.getElementById(id);
  const body = document.querySelector("#loops tbody");
  const state = {offset: 0, limit: 100, q: "", status: "", mode: "", sort: "registered", desc: false};
  const params = new URLSearchParams(location.search);
  for (const k of ["q", "status", "mode", "sort"]) if (params.get(k)) state[k] = params.get(k);
  if (["1", "true"].includes(params.get("desc"))) state.desc = true;  // what query() writes
  $("search").value = state.q;
  for (const m of $("mode-filter").dataset.modes.split(" ")) $("mode-filter").add(new Option(m, m));
  $("mode-filter").value = state.mode;
  let seen = 0, timer = null, inflight = null;
  const HOLDS = {plant: "held: plant-wide hold", cooldown: "held: cool-down", model_check: "held: model check"};

  function query() {
    const p = new URLSearchParams({offset: state.offset, limit: state.limit, sort: state.sort});
    if (state.q) p.set("q", state.q);
    if (state.status) p.set("status", state.status);
    if (state.mode) p.set("mode", state.mode);
    if (state.desc) p.set("desc", "true");
    return p.toString();
  }

  function row(l) {
    const lc = l.last_change;
    const change = lc ? `${pitune.ago(lc.wall)} · ${pitune.esc(lc.reason)}` +
      (lc.dkp !== null ? ` <span class="muted">kp ${lc.dkp >= 0 ? "+" : ""}${(lc.dkp * 100).toFixed(1)}%</span>` : "") : "–";
    const v = l.verification || {};
    const verdict = v.oscillating ? ` <b class="bad">oscillating</b>` : (lc ? ` <span class="muted verdict">${v.pending ? "change pending" : "last-good"}</span>` : "");
    const href = `/ui/loops/${encodeURIComponent(l.id)}`;
    // the agent held while the status may read tuning (the loop page says until when)
    const hold = l.hold ? ` <span class="badge hold">${pitune.esc(HOLDS[l.hold] || l.hold)}</span>` : "";
    return `<tr data-id="${pitune.esc(l.id)}"><td><a href="${href}">${pitune.esc(l.id)}</a></td>` +
      `<td><span class="badge s-${l.status}" title="${pitune.esc(l.status_why || "")}">${l.status}</span>${hold}</td><td><span class="badge m-${l.mode}">${l.mode}</span></td>` +
      `<td class="num">${pitune.num(l.kp)}</td><td class="num">${pitune.num(l.ki)}</td><td>${change}${verdict}</td>` +
      `<td class="num">${pitune.num(l.rms_e, 3)}</td><td class="num">${pitune.num(l.last_sample_t, 6)}</td>` +
      `<td class="num">${pitune.int(l.counters.samples)}</td><td class="num">${pitune.int(l.counters.steps)}</td>` +
      `<td class="num">${pitune.int(l.counters.updates)}</td><td class="num">${pitune.int(l.counters.rejected)}</td>` +
      `<td>${pitune.esc(l.gateway || "")}</td></tr>`;
  }

  async function load() {
    const q = query();
    const mine = ++seen;
    const t0 = performance.now();
    if (inflight) inflight.abort();
    inflight = new AbortController();
    let data;
    try {
      const r = await fetch(`/ui/api/loops?${q}`, {cache: "no-store", signal: inflight.signal});
      if (!r.ok) throw new Error(`${r.status}`);
      data = await r.json();
    } catch (e) {
      if (e.name !== "AbortError") pitune.toast(`loading loops failed: ${e.message}`, true);
      return;
    }
    if (mine !== seen) return;
    body.innerHTML = data.items.length ? data.items.map(row).join("") :
      `<tr><td colspan="13" class="muted">${data.total ? "No loop matches." : "No loop registered yet."}</td></tr>`;
    $("total").textContent = `${pitune.int(data.matched)} of ${pitune.int(data.total)}`;
    const last = Math.min(data.offset + data.items.length, data.matched);
    $("range").textContent = data.matched ? `${pitune.int(data.offset + 1)}–${pitune.int(last)} of ${pitune.int(data.matched)}` : "0";
    $("prev").disabled = data.offset === 0;
    $("next").disabled = last >= data.matched;
    chips(data.statuses);
    $("timing").textContent = `server ${data.server_ms} ms, page ${(performance.now() - t0).toFixed(0)} ms`;
    document.querySelectorAll("#loops th").forEach((th) => {
      th.classList.toggle("sorted", th.dataset.sort === state.sort);
      th.classList.toggle("desc", th.dataset.sort === state.sort && state.desc);
    });
    const table = $("loops");
    table.dataset.q = q;          // what the rows show (tests wait on it)
    table.dataset.matched = data.matched;
    history.replaceState(null, "", `?${q}`);
  }

  function chips(statuses) {
    const sel = $("status-filter");
    if (sel.options.length === 1) {
      for (const s of Object.keys(statuses)) sel.add(new Option(s, s));
      sel.value = state.status;
    }
    $("chips").innerHTML = Object.entries(statuses).filter(([, n]) => n > 0).map(([s, n]) =>
      `<button type="button" class="chip s-${s}${state.status === s ? " on" : ""}" data-status="${s}">${s} ${pitune.int(n)}</button>`).join("");
  }

  function refilter() { state.offset = 0; load(); }
  let debounce = null;
  $("search").addEventListener("input", (e) => {
    clearTimeout(debounce);
    debounce = setTimeout(() => { state.q = e.target.value.trim(); refilter(); }, 120);
  });
  $("status-filter").addEventListener("change", (e) => { state.status = e.target.value; refilter(); });
  $("mode-filter").addEventListener("change", (e) => { state.mode = e.target.value; refilter(); });
  $("chips").addEventListener("click", (e) => {
    const s = e.target.dataset.status;
    if (!s) return;
    state.status = state.status === s ? "" : s;
    $("status-filter").value = state.status;
    refilter();
  });
  $("page-size").addEventListener("change", (e) => { state.limit = +e.target.value; refilter(); });
  $("prev").addEventListener("click", () => { state.offset = Math.max(0, state.offset - state.limit); load(); });
  $("next").addEventListener("click", () => { state.offset += state.limit; load(); });
  document.querySelector("#loops thead").addEventListener("click", (e) => {
    const key = e.target.dataset.sort;
    if (!key) return;
    if (state.sort === key) state.desc = !state.desc; else { state.sort = key; state.desc = false; }
    refilter();
  });
  const tick = () => { if ($("auto-refresh").checked && !document.hidden) load(); };
  timer = setInterval(tick, 2000);
  load();
})();
