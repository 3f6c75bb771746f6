// The tuner page: health, traffic, inference, store, rejections (polled every 2 s).
"use strict";
(() => {
  const $ = (id) => document.getElementById(id);
  const kv = (el, pairs) => { el.innerHTML = pairs.map(([k, v]) => `<dt>${pitune.esc(k)}</dt><dd>${v}</dd>`).join(""); };
  const rate = (x) => (x === null || x === undefined ? "–" : `${pitune.num(x, 3)} /s`);
  const yes = (b) => (b ? "yes" : "<b class='bad'>no</b>");
  async function load() {
    let d;
    try { d = await pitune.getJSON("/ui/api/tuner"); } catch (e) { pitune.toast(`tuner: ${e.message}`, true); return; }
    const ok = d.alive && d.ready && d.store.ok;
    const h = $("health");
    h.textContent = ok ? "healthy" : (d.store.ok ? "not ready" : "store failing");
    h.className = `badge ${ok ? "s-tuning" : "s-stale"}`;
    kv($("t-health"), [["worker running", yes(d.alive)], ["bus ready", yes(d.bus_ready)], ["ready", yes(d.ready)],
      ["instance", pitune.esc(d.instance_id)], ["epoch", d.epoch], ["key prefix", pitune.esc(d.key_prefix)]]);
    kv($("t-traffic"), [["samples received", `${pitune.int(d.received)} (${rate(d.rates.received)})`],
      ["rejected", `${pitune.int(d.rejected_total)} (${rate(d.rates.rejected)})`],
      ["gains published", `${Object.entries(d.updates).map(([m, k]) => `${m} ${pitune.int(k)}`).join(", ")} (${rate(d.rates.updates)})`],
      ["queue depth", `<span id="queue-depth">${pitune.int(d.queue_depth)}</span> of ${pitune.int(d.queue_size)}`],
      ["state queries dropped", pitune.int(d.queries_dropped)], ["gains superseded in lanes", pitune.int(d.superseded)]]);
    const inf = d.inference;
    kv($("t-inference"), [["precision", pitune.esc(d.inference_precision)], ["batched steps", `${pitune.int(inf.batches)} (${rate(d.rates.batches)})`],
      ["mean", inf.mean_ms === null ? "–" : `${pitune.num(inf.mean_ms, 3)} ms`], ["median ≤", inf.p50_le_ms === null ? "–" : `${inf.p50_le_ms} ms`],
      ["p99 ≤", inf.p99_le_ms === null ? "–" : `${inf.p99_le_ms} ms`], ["loops per step", pitune.num(inf.loops_per_batch, 3)]]);
    kv($("t-store"), [["commits", d.store.ok ? "<span id='store-ok'>working</span>" : `<b class='bad'>${pitune.esc(d.store.failure)}</b>`],
      ["database", pitune.esc(d.store.path)], ["journal rows pending", pitune.int(d.store.journal_rows)],
      ["commit failures", pitune.int(d.store.commit_failures)], ["steps skipped", pitune.int(d.store.steps_skipped)]]);
    const rej = Object.entries(d.rejected).filter(([, k]) => k > 0);
    kv($("t-rejected"), rej.length ? rej.map(([r, k]) => [r, pitune.int(k)]) : [["none", ""]]);
    kv($("t-loops"), [["registered", pitune.int(d.loops.total)],
      ...Object.entries(d.loops.statuses).filter(([, k]) => k > 0).map(([s, k]) => [s, `<a href="/ui?status=${s}">${pitune.int(k)}</a>`]),
      ...Object.entries(d.loops.modes).map(([m, k]) => [`mode ${m}`, pitune.int(k)])]);
    kv($("t-process"), [["RSS", `${pitune.num(d.process.rss_mb, 4)} MB`], ["CPU time", `${pitune.num(d.process.cpu_s, 4)} s`],
      ["open files", d.process.open_fds], ["trend rings", d.trends_mb === null ? "not wired" : `${pitune.num(d.trends_mb, 3)} MB`]]);
    document.body.dataset.loaded = "1";
  }
  load();
  setInterval(() => { if (!document.hidden) load(); }, 2000);
})();
