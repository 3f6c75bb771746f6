"""Load measurement of the OPC UA gateway: N loops on one gateway at 1 s sampling.

``python -m service.gateways.opcua.bench --loops 1000 --duration 120`` starts, each as
its own process on loopback: the tuner (fresh database), the simulated DCS with N FOPTD
PID blocks (``pitune plant opcua --many-foptd N``, setpoint steps every ``--sp-period``
so that the tuner steps them), and the gateway, which registers the N loops in bulk
(batched gains). After ``--duration`` simulated seconds (real time: speed 1) the DCS
stops, and the script reports:

* samples: the DCS's scans x N against the samples the gateway published (lost = the
  difference, the initial read of each block aside) and those the tuner accepted;
* gains: updates received and written, refusals, and the write latency (from the
  update taken off the bus to its verified write) p50 / p99 / max;
* CPU (% of one core, over the run) and RSS of the gateway and of the DCS.

Prints a JSON summary; ``--out FILE`` writes it too.
"""

from __future__ import annotations

import argparse
import json
import re
import tempfile
import time
import tomllib
from pathlib import Path

import httpx
import tomli_w

from service.procs import Proc, TunerProcess, clean_env, pitune
from service.wire.session import free_port

TOKEN = "bench-token"


def run_bench(args: argparse.Namespace, workdir: Path) -> dict:
    # the default flood limit, which the gateway paces a backlog under (not 10/s, which
    # rejected 14,400 samples of a one-minute backlog: docs/opcua.md, Measured)
    tuner = TunerProcess(workdir / "pitune.db", "--log-level", "warning",
                         log=workdir / "tuner.log", token=TOKEN)  # fmt: skip
    procs: list[Proc] = []
    try:
        tuner.start(timeout=180)
        raw_map = workdir / "dcs-map.toml"
        dcs = Proc("dcs", pitune("plant", "opcua", "--many-foptd", str(args.loops),
                                 "--duration", f"{args.duration:g}", "--sp-period",
                                 f"{args.sp_period:g}", "--port", str(free_port()),
                                 "--allow-insecure", "--write-map", str(raw_map),
                                 "--wait-for-gateway", "--progress", "0"),
                   log=workdir / "dcs.log")  # fmt: skip
        procs.append(dcs)
        dcs.wait_ready(raw_map.exists, timeout=180)
        site = tomllib.loads(raw_map.read_text())
        site["bus"] = {"connect": [tuner.zenoh], "gateway_id": "bench"}
        site["tuner"] = {"register_url": tuner.api, "timeout_s": 120}
        for loop in site["loops"]:
            loop["min_write_interval_s"] = 0.0
            if not args.with_op:
                del loop["op"]  # optional: the bench measures the map without it by default
            loop["registration"]["extra"] = {"guard": {"max_rel_change": 0.5}}
        site_file = workdir / "site.toml"
        site_file.write_text(tomli_w.dumps(site))
        report = workdir / "gateway.json"
        argv = pitune("gateway", "opcua", "--map", str(site_file), "--report", str(report),
                      "--status-interval", "30")  # fmt: skip
        env = clean_env(PITUNE_API_TOKEN=TOKEN)
        gateway = Proc("gateway", argv, log=workdir / "gateway.log", env=env)
        procs.append(gateway)
        started = time.monotonic()
        dcs.wait_ready(lambda: "plant clock started" in dcs.tail(5), timeout=300)
        clock = time.monotonic()
        cpu0 = {p.name: p.cpu_seconds() for p in (gateway, dcs)}
        rss: dict[str, float] = {"gateway": 0.0, "dcs": 0.0}
        dcs_cpu = (0.0, 1.0)
        while dcs.running:
            try:
                for p in (gateway, dcs):
                    rss[p.name] = max(rss[p.name], p.rss_mb())
                dcs_cpu = (dcs.cpu_seconds() - cpu0["dcs"], time.monotonic() - clock)
            except OSError:  # exited meanwhile
                pass
            time.sleep(1.0)
        wall = time.monotonic() - clock
        cpu = {"gateway": (gateway.cpu_seconds() - cpu0["gateway"]) / wall * 100}
        time.sleep(2.0)  # the last samples and writes in flight
        cpu_dcs_line = dcs.tail(3)
        gateway.stop()
        with tuner.http() as http:
            http.timeout = httpx.Timeout(120.0)
            views, offset = [], 0
            while True:
                page = http.get("/loops", params={"offset": offset, "limit": 100}).json()
                views += page["items"]
                offset += len(page["items"])
                if offset >= page["total"] or not page["items"]:
                    break
        out = json.loads(report.read_text())
        m = re.search(r"after (\d+) scans \(worst scan started ([\d.]+) s late\)", cpu_dcs_line)
        scans, late = (int(m.group(1)), float(m.group(2))) if m else (None, None)
        c = out["counters"]
        accepted = sum(v["counters"]["samples"] for v in views)
        rejected = sum(v["counters"]["rejected"] for v in views)
        updates = sum(v["counters"]["updates"] for v in views)
        expected = None if scans is None else scans * args.loops
        return {
            "loops": args.loops,
            "duration_s": args.duration,
            "startup_s": round(clock - started, 1),
            "dcs_scans": scans,
            "dcs_worst_scan_late_s": late,
            "samples_expected": expected,
            "samples_published": c.get("published", 0),
            # the initial read of each block is one sample more than the scans
            "samples_lost": None
            if expected is None
            else expected + args.loops - c.get("published", 0),
            "samples_accepted_by_tuner": accepted,
            "samples_rejected_by_tuner": rejected,
            "updates_published_by_tuner": updates,
            "samples_dropped_in_buffer": c.get("samples_dropped", 0),
            "updates_received": c.get("received", 0),
            "writes": c.get("written", 0),
            "refused": {k: v for k, v in c.items() if k.startswith("refused")},
            "write_latency_s": out["write_latency_s"],
            "gateway_cpu_pct_of_core": round(cpu["gateway"], 1),
            "gateway_rss_mb_max": round(rss["gateway"], 1),
            "dcs_cpu_pct_of_core": round(dcs_cpu[0] / dcs_cpu[1] * 100, 1),
            "dcs_rss_mb_max": round(rss["dcs"], 1),
        }
    finally:
        for p in reversed(procs):
            p.stop()
        tuner.stop()


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--loops", type=int, default=1000)
    parser.add_argument("--duration", type=float, default=120.0, help="simulated = wall s")
    parser.add_argument("--sp-period", type=float, default=30.0)
    parser.add_argument(
        "--with-op", action="store_true", help="also monitor each block's OUT (sent as op)"
    )
    parser.add_argument("--workdir", type=Path, default=None)
    parser.add_argument("--out", type=Path, default=None)
    args = parser.parse_args(argv)
    with tempfile.TemporaryDirectory() as tmp:
        workdir = args.workdir or Path(tmp)
        workdir.mkdir(parents=True, exist_ok=True)
        result = run_bench(args, workdir)
    text = json.dumps(result, indent=2)
    print(text)
    if args.out:
        args.out.write_text(text + "\n")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
