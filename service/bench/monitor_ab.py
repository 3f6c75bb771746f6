"""``pitune bench --monitor-ab N``: what the performance monitoring costs the daemon.

N pairs of ordinary benchmark runs (the same load, seed and options), one with the
monitoring on and one with it off (the daemon's setting ``monitoring``: no figures,
no oscillation detector, no verdicts), interleaved and the order alternated within
pairs (on-off, off-on, ...) so a drift of the machine's load falls on both sides.

The measure is the daemon's own CPU time (user + system, ``/proc/<pid>/stat``) per
sample it accepted over the same window: on a machine shared with other work, its
CPU *share* moves with the others' load (the scheduler), its CPU *seconds per sample*
much less (only through caches and frequency). The cost of the monitoring is each
pair's ratio on / off minus one; the result is the median over the pairs, with the
smallest and largest beside it.
"""

from __future__ import annotations

import dataclasses
import json
import statistics
import tempfile
import time
from pathlib import Path

import httpx

from service.bench.config import BenchConfig
from service.bench.fleet import Fleet
from service.bench.load import drive

LIMIT_PCT = 20.0
"""The issue's line: monitoring adds under 20 % to the daemon's CPU at 10,000 loops."""


def cpu_us_per_sample(result: dict) -> float:
    """Daemon CPU microseconds per accepted sample over a run's window."""
    return 1e4 * result["daemon"]["cpu_percent"] / result["samples"]["accepted_per_s"]


def one_run(config: BenchConfig, monitoring: bool, start_daemon) -> dict:
    env = {} if monitoring else {"PITUNE_MONITORING": "false"}
    with tempfile.TemporaryDirectory(prefix="pitune-bench-ab-") as tmp:
        daemon = start_daemon(config, Path(tmp), env=env)
        try:
            with httpx.Client(timeout=30) as client:
                result = drive(config, Fleet(config), daemon, client)
        finally:
            daemon.stop()
    return {
        "monitoring": monitoring,
        "cpu_us_per_sample": cpu_us_per_sample(result),
        "cpu_percent": result["daemon"]["cpu_percent"],
        "accepted_per_s": result["samples"]["accepted_per_s"],
        "lost": result["samples"]["lost"],
        "rejected": result["samples"]["rejected"],
        "latency_p99_ms": result["updates"]["latency_ms"]["p99"],
        "machine_busy_percent": result["machine_cpu"]["busy_percent"],
        "load_average_end": result["load_average"]["end"],
    }


def run(config: BenchConfig, pairs: int, start_daemon) -> dict:
    """``pairs`` on/off pairs; the runs and the summary (see the module docstring)."""
    runs, ratios = [], []
    for p in range(pairs):
        order = (True, False) if p % 2 == 0 else (False, True)
        pair = {m: one_run(config, m, start_daemon) for m in order}
        runs += [{"pair": p, **pair[m]} for m in order]
        ratios.append(pair[True]["cpu_us_per_sample"] / pair[False]["cpu_us_per_sample"])
        print(f"pair {p + 1}/{pairs}: on {pair[True]['cpu_us_per_sample']:.2f} / off "
              f"{pair[False]['cpu_us_per_sample']:.2f} us per sample ({ratios[-1] - 1:+.1%})",
              flush=True)  # fmt: skip
    added = [100.0 * (r - 1.0) for r in ratios]
    median = statistics.median(added)
    return {
        "config": json.loads(json.dumps(dataclasses.asdict(config), default=str)),
        "runs": runs,
        "added_cpu_pct": {"median": median, "min": min(added), "max": max(added), "pairs": added},
        "bar": {"limit_pct": LIMIT_PCT, "met": median < LIMIT_PCT},
    }


def main(config: BenchConfig, pairs: int, start_daemon) -> int:
    result = run(config, pairs, start_daemon)
    config.out.mkdir(parents=True, exist_ok=True)
    path = config.out / f"{time.strftime('%Y%m%d-%H%M%S')}-{config.loops}-monitor-ab.json"
    path.write_text(json.dumps(result, indent=2) + "\n")
    a = result["added_cpu_pct"]
    print(f"monitoring adds {a['median']:+.1f} % to the daemon's CPU per sample (median of "
          f"{pairs} pairs; {a['min']:+.1f} to {a['max']:+.1f} %): "
          f"{'met' if result['bar']['met'] else 'NOT MET'} (limit {LIMIT_PCT:g} %)")  # fmt: skip
    print(f"written to {path}")
    return 0 if all(r["lost"] == 0 and r["rejected"] == 0 for r in result["runs"]) else 1
