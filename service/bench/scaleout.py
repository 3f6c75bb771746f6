"""``pitune bench --instances N``: the load of ``pitune bench`` on N tuners sharing a
PostgreSQL store (a temporary server unless ``--postgres``), then a failover.

The loops are spread over ``--gateways`` gateways (at least 4 per instance: a member
owns whole gateways, so fewer gateways than members would leave members idle). The
measured window is :func:`service.bench.load.play`'s, with the members' metrics, CPU and
memory summed. Then one member is SIGKILLed under the same load, and the failover time
is the time until every loop it owned was stepped by another member (the issue's bar:
10 s), with the checks of :mod:`service.bench.cluster` (no seq regression, every
published message audited).
"""

from __future__ import annotations

import collections
import contextlib
import gc
import math
import os
import time
from dataclasses import replace
from pathlib import Path

import httpx

from service.bench.cluster import GainsLog, Members, missing_audit, open_session, wait_for
from service.bench.config import BenchConfig
from service.bench.fleet import Fleet
from service.bench.gateways import Generators, plans
from service.bench.load import Measured, _wait_for_tuner, summary, write_trace
from service.bench.pgserver import PgServer
from service.bench.probes import scrape, system_busy, tree_cpu_seconds
from service.wire.protocol import Keys

GATEWAYS_PER_INSTANCE = 4


class _Summed:
    """The members as one daemon for :func:`play`: APIs to scrape and CPU summed."""

    def __init__(self, members: Members) -> None:
        self.api = [p.api for p in members.procs]
        self._procs = [p.proc for p in members.procs]
        self.proc = self

    def cpu_seconds(self) -> float:
        return sum(self.each_cpu())

    def each_cpu(self) -> list[float]:
        """CPU seconds of each member so far (0 once stopped)."""
        return [p.cpu_seconds() if p.running else 0.0 for p in self._procs]

    def rss_mb(self) -> float:
        """The largest member's (the per-daemon memory line applies to each)."""
        return max((p.rss_mb() for p in self._procs if p.running), default=0.0)


def spread(config: BenchConfig) -> BenchConfig:
    return replace(config, gateways=max(config.gateways, GATEWAYS_PER_INSTANCE * config.instances))


def run(config: BenchConfig, workdir: Path) -> dict:
    """Start the store and the members, register, play, fail one over; the results."""
    server = None if config.postgres else PgServer()
    url = config.postgres or server.create_database()
    extra = ("--agent-weights", config.agent_weights) if config.agent_weights else ()
    logs = config.daemon_log or workdir  # with --instances, the members' log directory
    logs.mkdir(parents=True, exist_ok=True)
    members = Members(
        config.instances, url, logs,
        "--snapshot-interval", str(config.snapshot_interval),
        "--inference-threads", str(config.inference_threads),
        "--inference-workers", str(config.inference_workers),
        "--inference-precision", config.inference_precision, *extra,
    )  # fmt: skip
    try:
        members.start()
        return _drive(config, Fleet(config), members, url, None if server is None else server.pid)
    finally:
        members.stop()
        if server is not None:
            server.stop()


def _drive(config: BenchConfig, fleet: Fleet, members: Members, url: str, pg: int | None) -> dict:
    daemon = _Summed(members)
    memory = {"rss_idle_mb": daemon.rss_mb()}
    started = time.perf_counter()
    with httpx.Client(timeout=600) as client:
        for i in range(0, fleet.n, 5000):
            member = members.procs[(i // 5000) % len(members.procs)]
            r = client.post(f"{member.api}/loops/bulk", json=fleet.registrations[i : i + 5000])
            if r.status_code != 201:
                raise RuntimeError(f"bulk registration failed: {r.status_code} {r.text[:500]}")
            if i == 0:  # the first chunk's member claimed every gateway: let them spread
                n = min(5000, fleet.n)
                wait_for(lambda n=n: _balanced(members, n), 120.0, "the first loops spread")
        memory["register_s"] = time.perf_counter() - started
        wait_for(lambda: _balanced(members, fleet.n), 120.0, "the loops spread over the members")
        memory[f"rss_{fleet.n}_loops_mb"] = daemon.rss_mb()
        gateways = collections.defaultdict(list)
        for body in fleet.registrations:
            gateways[body["gateway"]].append(body["id"])
        session = open_session(members.endpoints)
        try:
            _wait_for_tuner(session, Keys(), fleet.ids[0])
            gc.freeze()
            result = _measure(config, fleet, gateways, members, daemon, client, memory, pg)
            result["cluster"] = members.cluster()
            try:
                result["failover"] = _failover(config, fleet, gateways, members, session, url)
            except Exception as exc:  # noqa: BLE001 - the window's results still count
                keys = ("failover_s", "seq_regressions", "messages_without_audit")
                result["failover"] = {"error": repr(exc), **dict.fromkeys(keys)}
        finally:
            session.close()
    return result


def _plans(config: BenchConfig, fleet: Fleet, gateways: dict, members: Members, **timing):
    return plans(
        gateways,
        config.generators or config.instances,
        endpoints=members.endpoints,
        period=fleet.period,
        groups=len(fleet.groups),
        batch_size=config.batch_size,
        columns=config.sample_form == "columns",
        **timing,
    )


def _measure(config, fleet, gateways, members, daemon: _Summed, client, memory, pg) -> dict:
    """The load for ``warmup + duration`` from the generator processes; the members'
    metrics, CPU (each, and the PostgreSQL server's when it is the bench's own: ``pg``
    its pid) and memory over the window."""
    window = (config.warmup, config.warmup + config.duration)
    generators = Generators(
        _plans(config, fleet, gateways, members, window=window, end=window[1], t0=1000.0)
    ).start()
    try:
        start = generators.go()
        rss_max = 0.0
        _until(start + window[0])
        m0, cpu0, sys0, wall0, pg0 = _probe(client, daemon, pg)
        while time.monotonic() < start + window[1]:
            rss_max = max(rss_max, daemon.rss_mb())
            _until(min(time.monotonic() + 1.0, start + window[1]))
        m1, cpu1, sys1, wall1, pg1 = _probe(client, daemon, pg)
        heard = generators.results(timeout=60.0)
    finally:
        generators.kill()
    deadline = time.monotonic() + 10.0  # the members should have received everything
    while time.monotonic() < deadline:
        if scrape(client, daemon.api)["pitune_samples_received_total"] >= heard["published"]:
            break
        time.sleep(0.1)
    m2 = scrape(client, daemon.api)
    if config.trace:
        write_trace(config.trace, heard["trace"])
    measured = Measured(
        published=heard["published"],
        published_window=heard["published_window"],
        latencies_s=heard["latencies"],
        gains=heard["gains"],
        unmatched=heard["unmatched"],
        generator_cpu_s=heard["cpu_s"],
        late_max_s=heard["late_max_s"],
    )
    span = wall1 - wall0
    each = [100.0 * (b - a) / span for a, b in zip(cpu0, cpu1, strict=True)]
    result = summary(
        config,
        measured,
        (m0, m1, m2),
        span,
        daemon_cpu_s=sum(cpu1) - sum(cpu0),
        machine=(sys0, sys1),
        daemon={
            "rss_max_mb": rss_max,
            "rss_end_mb": daemon.rss_mb(),
            "members_cpu_percent": each,
            **memory,
        },
    )
    result["store_cpu_percent"] = None if pg is None else 100.0 * (pg1 - pg0) / span
    return result


def _probe(client, daemon: _Summed, pg: int | None) -> tuple:
    """(metrics, CPU seconds of each member, machine CPU, monotonic time, PostgreSQL CPU)."""
    return (
        scrape(client, daemon.api),
        daemon.each_cpu(),
        system_busy(),
        time.monotonic(),
        tree_cpu_seconds(pg) if pg else None,
    )


def _until(when: float) -> None:
    time.sleep(max(0.0, when - time.monotonic()))


def _balanced(members: Members, n: int) -> bool:
    with contextlib.suppress(httpx.HTTPError):
        view = members.cluster()
        loops = [m["loops"] for m in view["members"] if m["live"]]
        return view["unowned_loops"] == 0 and sum(loops) == n and min(loops) > 0
    return False


def _loops_in_engines(members: Members, alive: list[int]) -> float:
    """Loops in the engines of the members ``alive`` (0 while one does not answer: an
    overloaded member answers late)."""
    try:
        with httpx.Client(timeout=5.0) as client:
            metrics = scrape(client, [members.procs[i].api for i in alive])
    except httpx.HTTPError:
        return 0.0
    return sum(v for k, v in metrics.items() if k.startswith("pitune_loops{"))


def _failover(config, fleet: Fleet, gateways: dict, members: Members, session, url: str) -> dict:
    """SIGKILL the member owning the most loops, under the same load (real time); the
    failover time is until the others have all its loops in their engines again
    (leases taken, loops loaded from the store). A loop is stepped again when it next
    falls due (its RL period, 27-165 s at the default ``--tau``): the tests check the
    first step after a takeover with fast loops. Every message heard is checked."""
    log = GainsLog(session)
    # plant time far past the window's: the samples are in order for every loop
    generators = Generators(
        _plans(config, fleet, gateways, members, window=(0.0, 0.0), end=math.inf, t0=1e7)
    ).start()
    try:
        generators.go()
        time.sleep(3.0)  # a few batches through, so the load is the steady one
        view = members.cluster()
        victim = max((m for m in view["members"] if m["live"]), key=lambda m: m["loops"])
        index = members.ids.index(victim["instance_id"])
        alive = [i for i in range(len(members.procs)) if i != index]
        killed_at, killed_wall = time.monotonic(), time.time()
        members.procs[index].proc.kill()
        try:
            wait_for(
                lambda: _loops_in_engines(members, alive) >= fleet.n,
                60.0,
                "the killed member's loops in the others' engines",
                poll=0.05,
            )
            failover_s = time.monotonic() - killed_at
        except TimeoutError:
            failover_s = None
        time.sleep(5.0)  # the moved loops' first steps, under the checks below
        adopted = [a for i in alive for a in members.cluster(via=i)["adoptions"]
                   if a["at"] >= killed_wall]  # fmt: skip
    finally:
        generators.kill()
        log.close()
    heard = log.snapshot()
    return {
        "victim": victim["instance_id"],
        "victim_loops": victim["loops"],
        "failover_s": failover_s,
        "takeover": _takeover(adopted, killed_wall),
        "seq_regressions": len(log.regressions()),
        "messages": len(heard),
        "messages_without_audit": len(missing_audit(url, heard)),
        "load_average": list(os.getloadavg()),
    }


def _takeover(adopted: list[dict], killed_wall: float) -> dict:
    """Where the failover's time went: until the first acquisition (the lease running
    out, then the next tick), loading the loops from the store, inserting them into the
    engines (summed over the acquisitions of the survivors)."""
    if not adopted:
        return {"lease_wait_s": None, "loops": 0, "load_s": None, "insert_s": None,
                "lock_wait_s": None}  # fmt: skip
    return {
        "lease_wait_s": min(a["at"] for a in adopted) - killed_wall,
        "loops": sum(a["loops"] for a in adopted),
        "load_s": sum(a["load_s"] for a in adopted),
        "insert_s": sum(a["insert_s"] for a in adopted),
        "lock_wait_s": sum(a.get("lock_wait_s", 0.0) for a in adopted),
    }
