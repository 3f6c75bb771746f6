"""The benchmark's run: register the loops, play them in real time over Zenoh, measure.

Samples go out batched on ``{prefix}/samples`` (as a gateway fronting many loops would)
or one message each with ``--per-loop``, with ``CongestionControl.BLOCK`` as a gateway
should; the gains come back batched for the ``bench`` gateway or one message per loop.
The update latency of a loop is from the wall time its sample that completed an RL step
was published to the arrival of the gains message for it (matched by loop and the
sample's plant time ``t``, which gains messages carry).
"""

from __future__ import annotations

import collections
import gc
import math
import os
import time
from dataclasses import dataclass

import numpy as np
import orjson
import zenoh

from service.bench.config import GATEWAY, BenchConfig
from service.bench.fleet import Fleet
from service.bench.probes import rejected, scrape, system_busy
from service.procs import TunerProcess
from service.wire.protocol import Keys
from service.wire.session import session_config


@dataclass
class Window:
    start: float
    end: float


def register(client, daemon: TunerProcess, bodies: list[dict], chunk: int = 5000) -> float:
    started = time.perf_counter()
    for i in range(0, len(bodies), chunk):
        r = client.post(f"{daemon.api}/loops/bulk", json=bodies[i : i + chunk], timeout=300)
        if r.status_code != 201:
            raise RuntimeError(f"bulk registration failed: {r.status_code} {r.text[:500]}")
    return time.perf_counter() - started


def settle_rss(daemon: TunerProcess, seconds: float = 2.0) -> float:
    time.sleep(seconds)
    return daemon.proc.rss_mb()


def drive(config: BenchConfig, fleet: Fleet, daemon: TunerProcess, client) -> dict:
    """Register the loops, play them in real time, measure."""
    memory = {"rss_idle_mb": daemon.proc.rss_mb()}
    probe = config.memory_probe if 0 < config.memory_probe < fleet.n else 0
    if probe:
        memory["register_s_first"] = register(client, daemon, fleet.registrations[:probe])
        memory[f"rss_{probe}_loops_mb"] = settle_rss(daemon)
    memory["register_s"] = register(client, daemon, fleet.registrations[probe:])
    memory[f"rss_{fleet.n}_loops_mb"] = settle_rss(daemon)
    if probe:
        grown = memory[f"rss_{fleet.n}_loops_mb"] - memory[f"rss_{probe}_loops_mb"]
        memory["rss_per_loop_kb"] = 1024.0 * grown / (fleet.n - probe)
    if config.pin:
        os.sched_setaffinity(0, config.cpus(1))

    keys = Keys()
    session = zenoh.open(session_config(mode="peer", connect=[daemon.zenoh]))
    inbox: collections.deque = collections.deque()
    try:
        sub = session.declare_subscriber(
            keys.gateway_gains(GATEWAY if config.gateways == 1 else "*")
            if config.batched_gains
            else keys.all_gains,
            lambda s: inbox.append((time.monotonic(), s.payload.to_bytes())),
        )
        _wait_for_tuner(session, keys, fleet.ids[0])
        gc.freeze()  # no full collections of the imported modules while timing
        try:
            return play(config, fleet, daemon, client, session, keys, inbox, memory)
        finally:
            sub.undeclare()
    finally:
        session.close()


def _wait_for_tuner(session, keys, loop_id: str, timeout: float = 10.0) -> None:
    """Until the tuner answers a state query: a round trip behind this session's gains
    subscription (declared first, so the tuner knows it), and the tuner's own
    subscriptions are up (declared before its queryable)."""
    deadline = time.monotonic() + timeout
    while time.monotonic() < deadline:
        if any(r.ok for r in session.get(keys.state(loop_id), timeout=1.0)):
            return
    raise RuntimeError("the tuner does not answer state queries on the bus")


def write_trace(path, rows) -> None:
    """The update latencies of the window as CSV: (publish time of the sample after the
    window's start, s; loop id; latency, s) a row, written in ms."""
    with open(path, "w") as out:
        out.write("t_s,loop_id,latency_ms\n")
        out.writelines(f"{t:.3f},{i},{1e3 * d:.2f}\n" for t, i, d in rows)


def play(
    config: BenchConfig, fleet: Fleet, daemon: TunerProcess, client, session, keys, inbox, memory
) -> dict:
    period, n_groups = fleet.period, len(fleet.groups)
    t0 = 1000.0  # plant time of the first sample
    start = time.monotonic() + 0.2
    window = Window(start + config.warmup, start + config.warmup + config.duration)
    total = config.warmup + config.duration
    latencies: list[float] = []
    stats = collections.Counter()
    stats.trace = []
    late_max = 0.0
    rss_max, next_rss = 0.0, 0.0
    cpu0 = gen0 = m0 = None
    # Samples must not be lost: block rather than drop when the transport is congested
    # (Zenoh's default for puts is to drop), as a gateway should.
    block = zenoh.CongestionControl.BLOCK

    def publish(key: str, payload: bytes) -> None:
        session.put(key, payload, congestion_control=block)

    batch_key = keys.batch
    m = 0
    while True:
        g, k = m % n_groups, m // n_groups
        due = start + k * period + fleet.groups[g].offset
        if due - start >= total:
            break
        now = time.monotonic()
        if cpu0 is None and now >= window.start:
            cpu0, gen0, m0 = (
                daemon.proc.cpu_seconds(),
                time.process_time(),
                scrape(client, daemon.api),
            )
            sys0 = system_busy()
            wall0 = time.monotonic()
        if now >= next_rss:
            rss = daemon.proc.rss_mb()
            if window.start <= now < window.end:
                rss_max = max(rss_max, rss)
            next_rss = now + 1.0
        _drain(inbox, fleet, t0, window, latencies, stats)
        now = time.monotonic()
        if due > now:
            time.sleep(due - now)
        else:
            late_max = max(late_max, now - due)
        t, samples = fleet.scan(g, k, t0)
        sent = time.monotonic()
        if config.per_loop:
            for s in samples:
                loop_id = s.pop("loop_id")
                publish(keys.sample(loop_id), orjson.dumps(s))
        else:
            for i in range(0, len(samples), config.batch_size):
                publish(
                    batch_key, orjson.dumps({"v": 1, "samples": samples[i : i + config.batch_size]})
                )
        fleet.stamp(g, k, sent)
        stats["published"] += len(samples)
        if window.start <= sent < window.end:
            stats["published_window"] += len(samples)
        m += 1
    wall1 = time.monotonic()
    cpu1, gen1, m1 = daemon.proc.cpu_seconds(), time.process_time(), scrape(client, daemon.api)
    sys1 = system_busy()
    rss_end = daemon.proc.rss_mb()
    # drain: the daemon should have received everything; the last gains arrive shortly
    deadline = time.monotonic() + 10.0
    while time.monotonic() < deadline:
        m2 = scrape(client, daemon.api)
        if m2["pitune_samples_received_total"] >= stats["published"]:
            break
        time.sleep(0.1)
    time.sleep(1.0)
    _drain(inbox, fleet, t0, window, latencies, stats)
    m2 = scrape(client, daemon.api)

    span = wall1 - wall0
    if config.trace:
        write_trace(config.trace, stats.trace)
    return summary(
        config,
        Measured(
            published=stats["published"],
            published_window=stats["published_window"],
            latencies_s=np.asarray(latencies),
            gains=stats["gains"],
            unmatched=stats["unmatched"],
            generator_cpu_s=gen1 - gen0,
            late_max_s=late_max,
        ),
        (m0, m1, m2),
        span,
        daemon_cpu_s=cpu1 - cpu0,
        machine=(sys0, sys1),
        daemon={"rss_max_mb": rss_max, "rss_end_mb": rss_end, **memory},
    )


@dataclass
class Measured:
    """What the load generator measured (one process, or several summed)."""

    published: int
    published_window: int
    latencies_s: np.ndarray
    """Update latencies of the samples published in the window, seconds."""
    gains: int
    unmatched: int
    generator_cpu_s: float
    """CPU seconds of the generator(s) over the window."""
    late_max_s: float


def summary(
    config: BenchConfig,
    measured: Measured,
    metrics: tuple[dict, dict, dict],
    span: float,
    *,
    daemon_cpu_s: float,
    machine: tuple,
    daemon: dict,
) -> dict:
    """The results of a run: ``metrics`` are the daemon's (the members' summed) at the
    window's start, its end and after the drain; ``span`` the window's wall seconds."""
    m0, m1, m2 = metrics
    sys0, sys1 = machine
    lat = measured.latencies_s * 1e3
    received = m2["pitune_samples_received_total"]
    n_rejected = rejected(m2)
    accepted_window = (m1["pitune_samples_received_total"] - rejected(m1)) - (
        m0["pitune_samples_received_total"] - rejected(m0)
    )
    inf_count = (
        m1["pitune_inference_batch_seconds_count"] - m0["pitune_inference_batch_seconds_count"]
    )
    inf_sum = m1["pitune_inference_batch_seconds_sum"] - m0["pitune_inference_batch_seconds_sum"]
    gen_cpu = measured.generator_cpu_s
    return {
        "samples": {
            "published": measured.published,
            "received": received,
            "rejected": n_rejected,
            "rejected_by_reason": {
                k.split("reason=")[1].rstrip("}"): v
                for k, v in m2.items()
                if k.startswith("pitune_samples_rejected_total{") and v
            },
            "lost": measured.published - received,
            "published_per_s": measured.published_window / config.duration,
            "accepted_per_s": accepted_window / span,
        },
        "updates": {
            "gains_received": measured.gains,
            "gains_in_window": len(lat),
            "unmatched": measured.unmatched,
            "per_s": len(lat) / config.duration,
            "latency_ms": _percentiles(lat),
            "inference_calls": inf_count,
            "inference_mean_ms": 1e3 * inf_sum / inf_count if inf_count else None,
            "inference_loops_mean": (
                (m1["pitune_inference_batch_loops_sum"] - m0["pitune_inference_batch_loops_sum"])
                / inf_count
                if inf_count
                else None
            ),
        },
        "daemon": {"cpu_percent": 100.0 * daemon_cpu_s / span, **daemon},
        # identification's fits in the window (the budget: identify_cpu_share)
        "identification": {
            "fit_cpu_percent": 100.0 * _delta(m0, m1, "pitune_identify_fit_seconds_total") / span,
            "deferred": _delta(m0, m1, "pitune_identify_deferred_total"),
            "owed_at_end": m1.get("pitune_identify_owed_waiting", 0.0),
        },
        "generator": {
            "cpu_percent": 100.0 * gen_cpu / span,
            "late_max_ms": 1e3 * measured.late_max_s,
        },
        "load_average": {"end": list(os.getloadavg())},
        "machine_cpu": {
            # all CPUs together, in "% of one core" like the per-process figures
            "busy_percent": 100.0 * (sys1[0] - sys0[0]) / span,
            "others_percent": 100.0 * ((sys1[0] - sys0[0]) - daemon_cpu_s - gen_cpu) / span,
            "capacity_percent": 100.0 * (sys1[1] - sys0[1]) / span,
        },
    }


def _delta(m0: dict, m1: dict, name: str) -> float:
    return m1.get(name, 0.0) - m0.get(name, 0.0)


def _drain(inbox, fleet: Fleet, t0: float, window: Window, latencies: list, stats) -> None:
    while inbox:
        received, payload = inbox.popleft()
        msg = orjson.loads(payload)
        for gains in msg.get("gains", [msg]):  # a GainsBatch, or one GainsMessage
            _take(gains, received, fleet, t0, window, latencies, stats)


def _take(msg: dict, received: float, fleet: Fleet, t0: float, window: Window, latencies, stats):
    stats["gains"] += 1
    if msg.get("reason", "agent") == "agent":
        sent = fleet.sent_time(msg["loop_id"], msg["t"], t0)
        if math.isnan(sent):
            stats["unmatched"] += 1
        elif window.start <= sent < window.end:
            latencies.append(received - sent)
            stats.trace.append((sent - window.start, msg["loop_id"], received - sent))
        if msg["mode"] == "auto":
            fleet.offer(msg["loop_id"], msg["kp"], msg["ki"])


def _percentiles(lat_ms: np.ndarray) -> dict:
    if not lat_ms.size:
        return {"p50": None, "p99": None, "max": None, "mean": None}
    return {
        "p50": float(np.percentile(lat_ms, 50)),
        "p99": float(np.percentile(lat_ms, 99)),
        "max": float(lat_ms.max()),
        "mean": float(lat_ms.mean()),
    }
