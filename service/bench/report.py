"""The benchmark's verdict and outputs: the issue's bar, the JSON file, the printed table."""

from __future__ import annotations

import json
import operator
import time
from pathlib import Path

from service.bench.config import BenchConfig

BAR = {
    "lost": 0,
    "rejected": 0,
    "latency_p99_ms": 50.0,
    "daemon_rss_mb": 1024.0,
    "rss_per_loop_kb": 4.0,
    "inference_ms": 20.0,
    "failover_s": 10.0,
    "seq_regressions": 0,
    "messages_without_audit": 0,
}


def judge(r: dict) -> dict:
    """Each line of the issue's bar: value, limit, met (None when not measured)."""
    inf = r.get("inference") or {}

    def line(name: str, value, ok=operator.lt):
        limit = BAR[name]
        return {
            "value": value,
            "limit": limit,
            "met": None if value is None else bool(ok(value, limit)),
        }

    return {
        "samples_lost": line("lost", r["samples"]["lost"], operator.eq),
        "samples_rejected": line("rejected", r["samples"]["rejected"], operator.eq),
        "latency_p99_ms": line("latency_p99_ms", r["updates"]["latency_ms"]["p99"]),
        # the single tuner's memory bar (10,000 loops): a cluster member's memory grows
        # with its share of the loops (docs/deploy.md, Sizing), so no line for it
        **(
            {}
            if r.get("failover")
            else {"daemon_rss_mb": line("daemon_rss_mb", r["daemon"]["rss_max_mb"])}
        ),
        "rss_per_loop_kb": line("rss_per_loop_kb", r["daemon"].get("rss_per_loop_kb")),
        "inference_ms": line("inference_ms", inf.get("fast_policy_ms_median")),
        **_cluster_lines(r.get("failover"), line),
    }


def _cluster_lines(failover: dict | None, line) -> dict:
    """The bar lines of a failover (``--instances``): none for one tuner."""
    if failover is None:
        return {}
    return {
        "failover_s": line("failover_s", failover["failover_s"]),
        "seq_regressions": line("seq_regressions", failover["seq_regressions"], operator.eq),
        "messages_without_audit": line(
            "messages_without_audit", failover["messages_without_audit"], operator.eq
        ),
    }


def write(config: BenchConfig, result: dict) -> Path:
    config.out.mkdir(parents=True, exist_ok=True)
    tag = f"{config.loops}x{config.rate:g}hz{'-aligned' if config.aligned else ''}"
    tag += "-perloop" if config.per_loop else "-perloopgains" if config.per_loop_gains else ""
    tag += f"-{config.instances}instances" if config.instances > 1 else ""
    path = config.out / f"{time.strftime('%Y%m%d-%H%M%S')}-{tag}.json"
    path.write_text(json.dumps(result, indent=2, default=float) + "\n")
    return path


def _f(value, fmt: str = "{:.1f}") -> str:
    return "n/a" if value is None else fmt.format(value)


def table(r: dict) -> str:
    c, s, u, d, g = r["config"], r["samples"], r["updates"], r["daemon"], r["generator"]
    lat, mach, inf = u["latency_ms"], r["machine"], r.get("inference") or {}
    mode = "aligned (worst case)" if c["aligned"] else "spread"
    if c["per_loop"]:
        msg = "per-loop messages"
    else:
        gains = "per-loop gains" if c.get("per_loop_gains") else "batched gains"
        msg = f"batches of <= {c['batch_size']}, {gains}"
    rows = [
        ("loops x rate", f"{c['loops']} x {c['rate']:g}/s, {mode}, {msg}"),
        ("window", f"{c['duration']:g} s after {c['warmup']:g} s warm-up"),
        ("samples published / accepted",
         f"{s['published_per_s']:.0f}/s / {s['accepted_per_s']:.0f}/s"),
        ("samples lost / rejected (run)",
         f"{s['lost']:.0f} / {s['rejected']:.0f} of {s['published']}"),
        ("gains in window",
         f"{u['gains_in_window']} ({u['per_s']:.1f}/s), {u['unmatched']} unmatched"),
        ("update latency p50 / p99 / max",
         f"{_f(lat['p50'])} / {_f(lat['p99'])} / {_f(lat['max'])} ms"),
        ("daemon batch step (mean)", f"{_f(u['inference_mean_ms'], '{:.2f}')} ms for "
                                     f"{_f(u['inference_loops_mean'])} loops on average"),
        ("daemon CPU", f"{d['cpu_percent']:.0f} % of one core"),
        ("daemon RSS max / end", f"{d['rss_max_mb']:.0f} / {d['rss_end_mb']:.0f} MB"),
        ("RSS per loop", f"{_f(d.get('rss_per_loop_kb'), '{:.2f}')} KB"),
        ("generator CPU / worst lag", f"{g['cpu_percent']:.0f} % / {g['late_max_ms']:.1f} ms"),
        ("other processes' CPU", f"{r['machine_cpu']['others_percent']:.0f} % (machine "
                                 f"{r['machine_cpu']['busy_percent']:.0f} % busy of "
                                 f"{r['machine_cpu']['capacity_percent']:.0f} %)"),
    ]  # fmt: skip
    ident = r.get("identification") or {}
    if ident.get("fit_cpu_percent") or ident.get("deferred"):  # loops identified
        rows.append(
            (
                "identification fits / deferred",
                f"{ident['fit_cpu_percent']:.1f} % of one core / {ident['deferred']:.0f} "
                f"assessments ({ident['owed_at_end']:.0f} loops owed one at the end)",
            )
        )
    if inf:
        rows.append(
            (
                f"inference, {inf['loops']} due loops",
                f"FastPolicy {inf['fast_policy_ms_median']:.1f} ms (min "
                f"{inf['fast_policy_ms_min']:.1f}), {inf.get('precision', 'float32')}, "
                f"{inf['workers']} worker(s); agent.act {inf['agent_act_ms_median']:.1f} ms",
            )
        )
    if r.get("failover", {}).get("error"):
        rows.append(("failover (SIGKILL)", f"not measured: {r['failover']['error']}"))
    elif r.get("failover"):
        f = r["failover"]
        sizes = ", ".join(f"{m['instance_id']} {m['loops']}" for m in r["cluster"]["members"])
        each = " + ".join(f"{x:.0f}" for x in d.get("members_cpu_percent", []))
        store = r.get("store_cpu_percent")
        rows.append(("members CPU / PostgreSQL CPU",
                     f"{each} % / {_f(store, '{:.0f}')} % of one core"))  # fmt: skip
        rows += [
            ("instances (loops each)", f"{c['instances']} on PostgreSQL ({sizes}), "
                                       f"{c['gateways']} gateways"),
            ("failover (SIGKILL)", f"{f['victim']}'s {f['victim_loops']} loops held by the "
                                   f"others after {_f(f['failover_s'], '{:.2f}')} s; "
                                   f"{f['seq_regressions']} seq regressions, "
                                   f"{f['messages_without_audit']} unaudited of "
                                   f"{f['messages']} messages"),
        ]  # fmt: skip
        if f.get("takeover", {}).get("loops"):
            t = f["takeover"]
            rows.append(("failover: lease / load / insert",
                         f"{t['lease_wait_s']:.2f} s until taken; {t['loops']} loops loaded "
                         f"in {t['load_s']:.2f} s, inserted in {t['insert_s']:.2f} s"))  # fmt: skip
    rows += [
        ("machine", f"{mach['cpu']}, {mach['cpus']} CPUs, {mach['memory_gb']} GB"),
        ("load average start / end", f"{_load(mach['load_average_start'])} / "
                                     f"{_load(r['load_average']['end'])}"),
    ]  # fmt: skip
    width = max(len(k) for k, _ in rows)
    lines = [f"{k:<{width}}  {v}" for k, v in rows]
    lines.append("")
    lines.append("bar:")
    for name, b in r["bar"].items():
        mark = {True: "met", False: "NOT MET", None: "not measured"}[b["met"]]
        lines.append(f"  {name:<18} {_f(b['value'], '{:.2f}'):>10}  limit {b['limit']:<7} {mark}")
    return "\n".join(lines)


def _load(values: list[float]) -> str:
    return " ".join(f"{v:.2f}" for v in values)
