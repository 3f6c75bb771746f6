// A loop's page: live trends (uPlot, fed by server-sent events), state, audit log, actions.
"use strict";
(() => {
  const $ = (id) => document.getElementById(id);
  const root = $("loop");
  const id = root.dataset.loopId;
  const enc = encodeURIComponent(id);
  const MAX_POINTS = 5000;  // kept in the page (the daemon's ring holds the last 256)
  const S = {t: [], sp: [], pv: [], op: [], kp: [], ki: []};
  let G = [];  // published gains decisions {t, kp, ki, reason}
  let n = 0, gn = 0, view = null, live = null, lastSeq = null, lastMode = null;

  // -- charts --------------------------------------------------------------------------
  const width = (el) => Math.max(320, el.clientWidth - 4);
  const common = (el, h) => ({width: width(el), height: h, scales: {x: {time: false}}, legend: {live: true}, cursor: {drag: {x: true, y: false}}});
  const pvEl = $("trend-pv"), gEl = $("trend-gains");
  const pvChart = new uPlot({
    ...common(pvEl, 260),
    scales: {x: {time: false}, y: {}, op: {}},
    series: [
      {label: "t (s)"},
      {label: "SP", stroke: "#d35400", width: 1.5, spanGaps: true},
      {label: "PV", stroke: "#1f6fb2", width: 1.5, spanGaps: true},
      {label: "output", stroke: "#7f8c8d", width: 1, scale: "op", spanGaps: true},
    ],
    axes: [{}, {label: "SP, PV"}, {scale: "op", side: 1, grid: {show: false}, label: "output"}],
  }, [[], [], [], []], pvEl);
  const gChart = new uPlot({
    ...common(gEl, 220),
    scales: {x: {time: false}, kp: {}, ki: {}},
    series: [
      {label: "t (s)"},
      {label: "kp (DCS)", stroke: "#16a085", width: 1.5, scale: "kp", spanGaps: true},
      {label: "ki (DCS)", stroke: "#8e44ad", width: 1.5, scale: "ki", spanGaps: true},
      {label: "kp (published)", stroke: "#16a085", dash: [6, 4], width: 1, scale: "kp", spanGaps: true, paths: uPlot.paths.stepped({align: 1})},
      {label: "ki (published)", stroke: "#8e44ad", dash: [6, 4], width: 1, scale: "ki", spanGaps: true, paths: uPlot.paths.stepped({align: 1})},
    ],
    axes: [{}, {scale: "kp", label: "kp", values: pitune.ticks}, {scale: "ki", side: 1, grid: {show: false}, label: "ki (kp/s)", values: pitune.ticks}],
  }, [[], [], [], [], []], gEl);
  window.pituneTrend = {pv: pvChart, gains: gChart, samples: S};
  window.addEventListener("resize", () => {
    pvChart.setSize({width: width(pvEl), height: 260});
    gChart.setSize({width: width(gEl), height: 220});
  });

  function append(rec) {
    if (!rec) return;
    for (let i = 0; i < rec.t.length; i++) {
      const t = rec.t[i];
      if (t === null) continue;
      const last = S.t.length ? S.t[S.t.length - 1] : -Infinity;
      if (t === last) continue;
      if (t < last) {  // a new plant clock (the tuner took it: a restarted gateway): start over
        for (const k in S) S[k].length = 0;
        G = [];
      }
      for (const k of ["t", "sp", "pv", "op", "kp", "ki"]) S[k].push(rec[k][i]);
    }
    if (S.t.length > MAX_POINTS) for (const k in S) S[k].splice(0, S.t.length - MAX_POINTS);
    for (const g of rec.gains) if (g.t !== null) G.push(g);
    if (G.length > 500) G = G.slice(-500);
    n = rec.n; gn = rec.gn;
    draw();
  }

  function draw() {
    const hasOp = S.op.some((v) => v !== null);
    $("op-label").hidden = !hasOp;
    pvChart.setSeries(3, {show: hasOp});
    pvChart.setData([S.t, S.sp, S.pv, S.op]);
    // gains chart: the samples' times plus the decisions' times, decisions held until the next
    // (decisions before the first sample only set the value the steps start from)
    const t0 = S.t.length ? S.t[0] : -Infinity;
    const xs = Array.from(new Set([...S.t, ...G.map((g) => g.t).filter((t) => t >= t0)])).sort((a, b) => a - b);
    const at = new Map(S.t.map((t, i) => [t, i]));
    const gs = [...G].sort((a, b) => a.t - b.t);
    const kp = [], ki = [], pkp = [], pki = [];
    let j = -1;
    for (const x of xs) {
      while (j + 1 < gs.length && gs[j + 1].t <= x) j++;
      const i = at.get(x);
      kp.push(i === undefined ? null : S.kp[i]);
      ki.push(i === undefined ? null : S.ki[i]);
      pkp.push(j >= 0 ? gs[j].kp : null);
      pki.push(j >= 0 ? gs[j].ki : null);
    }
    gChart.setData([xs, kp, ki, pkp, pki]);
    const last = S.t.length ? S.t[S.t.length - 1] : null;
    const c = $("trend-count");
    c.textContent = S.t.length ? `${S.t.length} samples, last at t = ${pitune.num(last, 7)} s; ${gn} gains decisions since the daemon started` : "no samples yet";
    c.dataset.points = S.t.length;
    c.dataset.lastT = last ?? "";
  }

  // -- state -----------------------------------------------------------------------------
  const kv = (el, pairs) => {
    el.innerHTML = pairs.map(([k, v]) => `<dt>${pitune.esc(k)}</dt><dd>${v}</dd>`).join("");
  };
  // the bounds a rollback's fence puts on the agent's steps, and until when
  const fenceText = (f) => {
    if (!f) return "none";
    const side = (name, lo, hi) =>
      [lo !== null ? `${pitune.num(lo, 6)} ≤` : "", hi !== null || lo !== null ? name : "",
       hi !== null ? `≤ ${pitune.num(hi, 6)}` : ""].filter(Boolean).join(" ");
    const sides = [side("kp", f.kp_min, f.kp_max), side("ki", f.ki_min, f.ki_max)].filter(Boolean);
    return `${sides.join(", ")} until t = ${pitune.num(f.until_t, 7)}`;
  };

  function showLive() {
    if (!live) return;
    const st = $("status");
    st.textContent = live.status; st.className = `badge s-${live.status}`;
    // what holds a loop that is not tuning, with the numbers, and the next step
    st.title = live.status_why || "";
    const sw = $("status-why");
    sw.hidden = !live.status_why; sw.textContent = live.status_why || "";
    // what the status may not say: the agent held (a tuning loop whose gains stay), and
    // an oscillation under another status (a loop held for gains out of bounds)
    const h = live.hold, hd = $("hold");
    hd.hidden = !h;
    hd.dataset.guard = h ? h.guard : "";
    hd.textContent = !h ? "" : h.guard === "plant" ? "held: plant-wide hold" :
      h.guard === "cooldown" ? `held: cool-down until t = ${pitune.num(h.until_t, 7)}` :
      `held by the model check since t = ${pitune.num(h.since_t, 7)}`;
    hd.title = h ? h.why : "";
    $("oscillating").hidden = !live.oscillating || live.status === "oscillating";
    const md = $("mode");
    md.textContent = live.mode; md.className = `badge m-${live.mode}`;
    md.dataset.mode = live.mode;
    kv($("now"), [
      ["kp", pitune.num(live.kp, 6)], ["ki (kp/s)", pitune.num(live.ki, 6)], ["seq", live.seq],
      ["last sample t", pitune.num(live.last_sample_t, 7)], ["samples", pitune.int(live.samples)],
      ["RL steps", pitune.int(live.steps)], ["updates", pitune.int(live.updates)],
      ["quiet periods", pitune.int(live.quiet)], ["rejected", pitune.int(live.rejected)],
      ["RL period (s)", view ? pitune.num(view.rl_period_s) : "–"],
      ["gateway", pitune.esc(view?.config.gateway || "(per-loop gains)")],
    ]);
    document.querySelectorAll("#mode-buttons button").forEach((b) => {
      b.classList.toggle("on", b.dataset.mode === live.mode);
    });
    if (live.seq !== lastSeq || live.mode !== lastMode) {
      lastSeq = live.seq; lastMode = live.mode;
      loadHistory(); loadView();
    }
  }

  function showView() {
    const v = view, cfg = v.config, g = cfg.guard, sc = v.scaling, idn = v.identification;
    kv($("config"), [
      ["registered kp", pitune.num(cfg.kp, 6)], ["registered ki", pitune.num(cfg.ki, 6)],
      ["sample period (s)", pitune.num(cfg.sample_period_s)], ["forgetting", pitune.num(cfg.forgetting)],
      ["kp bounds", `${pitune.num(g.kp_min)} … ${pitune.num(g.kp_max)}`],
      ["ki bounds", `${pitune.num(g.ki_min)} … ${pitune.num(g.ki_max)}`],
      ["max rel. change", pitune.num(g.max_rel_change)], ["excitation periods", pitune.num(g.excitation_periods)],
      ["int e (agent)", pitune.num(v.int_e)], ["hidden norm", pitune.num(v.hidden_norm)],
    ]);
    const pairs = [];
    if (cfg.scaling) pairs.push(["hint", `K ${pitune.num(cfg.scaling.k_hat)}, τ ${pitune.num(cfg.scaling.tau_hat)} s, PV scale ${pitune.num(cfg.scaling.pv_scale)}`]);
    if (sc) for (const [k, x] of Object.entries(sc)) if (typeof x === "number") pairs.push([k, pitune.num(x)]);
    if (!sc) pairs.push(["scaling", "none yet (identifying)"]);
    if (idn) {
      pairs.push(["identification", pitune.esc(idn.state) + (idn.why ? ` <span class="muted">(${pitune.esc(idn.why)})</span>` : "")]);
      const m = idn.model;
      // an integrating process's FOPTD numbers say nothing: its own K (per s) and dead time
      if (m && m.integrating) pairs.push(["identified", `<b>integrating</b>: K ${pitune.num(m.slope)} /s, θ ${pitune.num(m.theta_i)} s, r² ${pitune.num(m.r2, 3)}`]);
      else if (m) pairs.push(["identified", `K ${pitune.num(m.k)}, τ ${pitune.num(m.tau)} s, θ ${pitune.num(m.theta)} s, r² ${pitune.num(m.r2, 3)}, confidence ${pitune.num(m.confidence, 2)}` +
        // slow ramps only: the lag is measured, its split assumed
        (m.lumped ? ` <b>lumped</b>: τ + θ ${pitune.num(m.tau + m.theta)} s, split assumed` : "")]);
      if (idn.mismatch) pairs.push(["hint", "<b>mismatch</b>"]);
      if (idn.out_of_envelope) pairs.push(["envelope", "<b>outside the training box</b>"]);
    }
    kv($("scaling"), pairs);
    const vf = v.verification, pr = v.proposal;
    if (vf) kv($("verify"), [
      ["verification", vf.enabled ? `on, margin ${pitune.num(vf.margin)}` : "off"],
      ["last-good kp", pitune.num(vf.last_good_kp, 6)], ["last-good ki", pitune.num(vf.last_good_ki, 6)],
      ["last-good IAE (s)", pitune.num(vf.last_good_iae)],
      ["change pending", vf.pending ? "<b>yes</b>" : "no"], ["judged up to seq", vf.judged_seq],
      // responses the next move cut short judge nothing: why a change stays pending
      ["responses cut short", pitune.int(vf.cut_short)], ["moves on an unsettled loop", pitune.int(vf.unsettled_moves)],
      ...(vf.why ? [["verdict waits", `<span id="verify-why">${pitune.esc(vf.why)}</span>`]] : []),
      ["agent held until t", pitune.num(vf.held_until_t, 7)],
      ["fence after a rollback", fenceText(vf.fence)],
    ]);
    $("proposal-box").hidden = !pr;
    if (pr) {
      $("proposal-box").dataset.seq = pr.seq;
      // how old it is, whether it waits at its reach, and why it may not be accepted now:
      // a proposal made before the plant changed must not look as fresh as a new one
      const age = pr.made_t == null || v.last_sample_t == null ? ""
        : `, made at t = ${pitune.num(pr.made_t, 7)} s (${pitune.num(v.last_sample_t - pr.made_t, 4)} s ago)`;
      $("proposal-text").innerHTML = `#${pr.seq} (${pitune.esc(pr.reason)}): kp ${pitune.num(pr.kp_in_force, 5)} → <b>${pitune.num(pr.kp, 5)}</b>, ` +
        `ki ${pitune.num(pr.ki_in_force, 5)} → <b>${pitune.num(pr.ki, 5)}</b>${age}` +
        (pr.at_reach ? "; at its reach of the gains in force (waits for a decision)" : "") +
        (pr.refused ? `<br><b>may not be accepted now:</b> <span class="proposal-refused">${pitune.esc(pr.refused)}</span>` : "");
    }
    const form = $("guard-form");
    if (!form.dataset.dirty) for (const el of form.elements) if (el.name) el.value = g[el.name] ?? "";
  }

  async function loadView() {
    try { view = await pitune.getJSON(`/loops/${enc}`); showView(); showLive(); } catch (e) { /* gone: the stream says so */ }
  }

  // Who made a change: the audit detail's "actor" (JSON detail) or its "actor=..." suffix.
  function actor(detail) {
    try { const d = JSON.parse(detail); if (d && typeof d === "object") return d.actor || ""; } catch (e) { /* text */ }
    const m = /(?:^|; )actor=(\S+)$/.exec(detail || "");
    return m ? m[1] : "";
  }

  async function loadHistory() {
    let page;
    try { page = await pitune.getJSON(`/loops/${enc}/history?limit=50`); } catch (e) { return; }
    $("history-total").textContent = `${page.total} entries, newest first`;
    const gains = (o, nw) => (o === null || o === undefined ? pitune.num(nw, 5) : (o === nw ? pitune.num(nw, 5) : `${pitune.num(o, 5)} → ${pitune.num(nw, 5)}`));
    document.querySelector("#history tbody").innerHTML = page.items.map((a) =>
      `<tr data-reason="${pitune.esc(a.reason)}"><td>${pitune.when(a.wall_time)}</td><td class="num">${pitune.num(a.t, 7)}</td><td class="num">${a.seq}</td>` +
      `<td>${pitune.esc(a.reason)}</td><td>${pitune.esc(a.mode)}</td><td class="num">${gains(a.kp_old, a.kp_new)}</td>` +
      `<td class="num">${gains(a.ki_old, a.ki_new)}</td><td>${pitune.esc(actor(a.detail) || (a.reason === "agent" ? "agent" : "–"))}</td>` +
      `<td class="verdict">${pitune.esc(a.verdict || "")}</td>` +
      `<td class="detail">${pitune.esc(a.detail.length > 120 ? a.detail.slice(0, 120) + "…" : a.detail)}</td></tr>`).join("");
  }

  // -- actions ---------------------------------------------------------------------------
  $("actions-hint").textContent = pitune.loggedIn ? "" : "Log in (the API token) to act: without a session every action is refused.";
  for (const m of root.dataset.modes.split(" ")) {
    const b = document.createElement("button");
    b.type = "button"; b.textContent = m; b.dataset.mode = m; b.id = `mode-${m}`;
    b.addEventListener("click", () => run(`mode → ${m}`, `/ui/api/loops/${enc}/patch`, {mode: m}));
    $("mode-buttons").appendChild(b);
  }
  $("reset").addEventListener("click", () => {
    if (confirm(`Reset ${id} to its registered gains and a fresh agent state?`)) run("reset", `/ui/api/loops/${enc}/reset`);
  });
  $("rollback").addEventListener("click", () => {
    if (confirm(`Roll ${id} back to its last-good gains?`)) run("rollback", `/ui/api/loops/${enc}/rollback`);
  });
  for (const [button, decision] of [["approve", "accept"], ["reject", "reject"]]) {
    $(button).addEventListener("click", () => {
      const seq = $("proposal-box").dataset.seq;
      run(`proposal ${seq} ${decision}`, `/ui/api/loops/${enc}/proposals/${seq}/${decision}`);
    });
  }
  const form = $("guard-form");
  form.addEventListener("input", () => { form.dataset.dirty = "1"; });
  form.addEventListener("submit", (e) => {
    e.preventDefault();
    const patch = {};
    for (const el of form.elements) {
      if (!el.name || el.value.trim() === "") continue;
      const x = Number(el.value);
      if (!Number.isFinite(x)) { pitune.toast(`${el.name}: not a number`, true); return; }
      if (view && view.config.guard[el.name] === x) continue;
      patch[el.name] = x;
    }
    if (!Object.keys(patch).length) { pitune.toast("nothing changed"); return; }
    run("limits", `/ui/api/loops/${enc}/patch`, patch).then(() => { delete form.dataset.dirty; });
  });

  async function run(what, url, body) {
    try {
      const v = await pitune.act(url, body);
      if (v && v.config) { view = v; showView(); }
      pitune.toast(`${id}: ${what} done`);
      loadHistory();
    } catch (e) {
      pitune.toast(`${id}: ${what} refused (${e.message})`, true);
    }
  }

  // -- data ------------------------------------------------------------------------------
  async function start() {
    try {
      const first = await pitune.getJSON(`/ui/api/loops/${enc}/recent`);
      live = first.live;
      pitune.showHold(first.plant);
      append(first.recent);
      if (!first.recent) $("trend-count").textContent = "trends need the daemon's ring of recent samples (not wired)";
    } catch (e) { pitune.toast(`loading failed: ${e.message}`, true); }
    await loadView();
    loadHistory();
    connect();
    setInterval(loadView, 10000);
  }

  // One stream lasts a few seconds (the daemon's shutdown never waits on it); at its end
  // ("bye") the next one starts where it left off. Errors: EventSource retries by itself.
  function connect() {
    const es = new EventSource(`/ui/api/loops/${enc}/stream?n=${n}&gn=${gn}`);
    es.onmessage = (e) => {
      const d = JSON.parse(e.data);
      if (d.recent) append(d.recent);
      live = d.live; showLive();
      pitune.showHold(d.plant);
      $("live").textContent = "● live";
      $("live").className = "live";
    };
    es.addEventListener("bye", () => { es.close(); connect(); });
    es.addEventListener("gone", () => { es.close(); $("live").textContent = "loop deleted"; pitune.followHold(); });
    es.onerror = () => { $("live").textContent = "reconnecting…"; $("live").className = "muted"; };
  }
  start();
})();
