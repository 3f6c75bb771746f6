"""What the benchmark reads from outside the daemon: its metrics, the machine's CPU."""

from __future__ import annotations

import os
import platform
import time
from pathlib import Path

import httpx
from prometheus_client.parser import text_string_to_metric_families


def scrape(client: httpx.Client, api: str | list[str]) -> dict[str, float]:
    """The daemon's metrics as {name{labels}: value}; of several daemons (the members of
    a cluster), summed."""
    out: dict[str, float] = {}
    for one in [api] if isinstance(api, str) else api:
        text = client.get(f"{one}/metrics").text
        for family in text_string_to_metric_families(text):
            for s in family.samples:
                labels = ",".join(f"{k}={v}" for k, v in sorted(s.labels.items()))
                name = f"{s.name}{{{labels}}}" if labels else s.name
                out[name] = out.get(name, 0.0) + s.value
    return out


def system_busy() -> tuple[float, float]:
    """(busy, total) CPU seconds of the whole machine so far, from /proc/stat."""
    fields = [int(v) for v in Path("/proc/stat").read_text().split("\n", 1)[0].split()[1:]]
    idle = fields[3] + fields[4]  # idle + iowait
    tick = os.sysconf("SC_CLK_TCK")
    return (sum(fields[:8]) - idle) / tick, sum(fields[:8]) / tick


def tree_cpu_seconds(pid: int) -> float:
    """CPU seconds of a process and its live children, plus its exited children's
    (a PostgreSQL server: the postmaster and its backends), from ``/proc``."""
    tick, total = os.sysconf("SC_CLK_TCK"), 0.0
    for stat in Path("/proc").glob("[0-9]*/stat"):
        try:
            fields = stat.read_text().rsplit(")", 1)[1].split()
        except OSError:  # gone meanwhile
            continue
        if stat.parent.name == str(pid):
            total += sum(int(f) for f in fields[11:15])
        elif fields[1] == str(pid):
            total += int(fields[11]) + int(fields[12])
    return total / tick


def rejected(metrics: dict[str, float]) -> float:
    return sum(v for k, v in metrics.items() if k.startswith("pitune_samples_rejected_total{"))


def machine_info() -> dict:
    model = "unknown"
    try:
        for line in Path("/proc/cpuinfo").read_text().splitlines():
            if line.startswith("model name"):
                model = line.split(":", 1)[1].strip()
                break
    except OSError:
        pass
    mem = os.sysconf("SC_PAGE_SIZE") * os.sysconf("SC_PHYS_PAGES") / 2**30
    return {
        "cpu": model,
        "cpus": os.cpu_count(),
        "memory_gb": round(mem, 1),
        "python": platform.python_version(),
        "platform": platform.platform(),
        "load_average_start": list(os.getloadavg()),
        "time": time.strftime("%Y-%m-%dT%H:%M:%S%z"),
    }
