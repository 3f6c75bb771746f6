// The tuner page: health, traffic, inference, store, rejections (polled every 2 s), and the
// plant-wide hold's control and record (on each change the hold's stream brings).
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

  // -- the plant-wide hold: hold all tuning with a reason, release, the recent record ------
  const HISTORY_SHOWN = 20;  // of the last 100 GET /hold/history keeps
  const form = $("hold-form"), reason = $("hold-reason"), error = $("hold-error");
  const MAX = Number(reason.dataset.max);
  // Python's str.isprintable (the server's rule): no "Other" or "Separator" but the space
  const NOT_PRINTABLE = /(?! )[\p{C}\p{Z}]/u;
  function problem(text) {
    const chars = [...text];  // code points, as the server counts them
    if (!chars.length) return "a reason is required";
    if (chars.length > MAX) return `at most ${MAX} characters (${chars.length})`;
    const bad = chars.findIndex((c) => NOT_PRINTABLE.test(c));
    if (bad >= 0) return `printable text on one line only: U+${chars[bad].codePointAt(0).toString(16).toUpperCase().padStart(4, "0")} at ${bad}`;
    return "";  // whether it says something (a letter or digit): the server's rule, its 422 shown
  }
  const refused = (msg) => { error.textContent = msg; reason.setAttribute("aria-invalid", msg ? "true" : "false"); };
  $("hold-hint").textContent = pitune.loggedIn ? "" : "Log in (the API token) to hold or release: without a session both are refused.";
  form.addEventListener("submit", async (e) => {
    e.preventDefault();
    const text = reason.value, why = problem(text);
    refused(why);
    if (why) return;
    try {
      await pitune.act("/ui/api/hold", {reason: text});
      reason.value = "";
      pitune.toast("plant-wide hold set");
    } catch (err) { refused(`refused (${err.message})`); }
  });
  $("hold-release").addEventListener("click", async () => {
    if (!confirm("Release the plant-wide hold? The tuner changes gains again from each loop's next RL period.")) return;
    try {
      await pitune.act("/ui/api/hold/release");
      refused("");
      pitune.toast("plant-wide hold released");
    } catch (err) { refused(`refused (${err.message})`); }
  });
  let asked = 0;
  async function history() {
    const mine = ++asked;
    let events;
    try { events = await pitune.getJSON("/hold/history"); } catch (e) { pitune.toast(`hold history: ${e.message}`, true); return; }
    if (mine !== asked) return;  // a later change's record is on its way
    document.querySelector("#hold-history tbody").innerHTML = events.length ? events.slice(0, HISTORY_SHOWN).map((h) =>
      `<tr data-action="${pitune.esc(h.action)}"><td>${pitune.when(h.wall_time)}</td><td>${pitune.esc(h.action)}</td>` +
      `<td>${pitune.esc(h.by)}</td><td>${pitune.esc(h.reason)}</td></tr>`).join("") :
      `<tr><td colspan="4" class="muted">never held</td></tr>`;
  }
  pitune.onHold((h) => {  // each change: the buttons and the record (the stream says when)
    $("hold-all").textContent = h.held ? "Change the reason" : "Hold all tuning";
    $("hold-release").hidden = !h.held;
    history();
  });
})();
