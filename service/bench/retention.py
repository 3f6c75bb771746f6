"""``pitune bench --retention``: a day (or more) of a site's audit history in minutes,
through the real tuner, to check the retention policy bounds the disk.

The tuner daemon runs as a child process on a fresh SQLite store, with its clock
accelerated ``--speed`` times (``clock_speed``, :mod:`service.daemon.clock`: the audit
rows' ``wall_time``, the retention horizon and the interval between retention passes),
and the load generator plays the plants' clock at the same speed: a loop sampled every
``--sample-period`` plant seconds sends a sample every ``period / speed`` real seconds.
Everything else is the production path: samples over Zenoh, the engine's RL steps,
journal commits, the worker's idle-time ``_retain`` -> ``Store.prune``, registrations
and deletions over the REST API. Nothing in the tuner is stubbed; what the acceleration
changes is only how many real seconds a plant second takes.

The simulated site (:class:`RetentionConfig`):

* ``loops`` site loops, sampled every ``sample_period`` s, plant time constants drawn
  from ``tau`` (RL period 5.5 tau): the bulk of the history;
* ``fast`` loops with tau = sample period = 1 s (an RL step every 5.5 s, 15,700 a day):
  they reach the default 10,000-row cap after 15 hours, so the row rule is exercised;
* churn: every ``churn_every`` plant seconds the previous ``churn`` loops are deleted
  and ``churn`` new ones (new ids) registered, as the issue's measurement did: the
  history of deleted loops must shrink to ``history_max_rows_deleted``.

The tuner archives what it prunes (``history_archive``, which does not change which rows
go): the archive plus the rows kept must be every row ever written (audit ids are
AUTOINCREMENT: 1..max), and no pruned row may be younger than the horizon and within
the row cap (:mod:`service.bench.retention_check`). Results: ``reports/retention.json``.
"""

from __future__ import annotations

import argparse
import collections
import heapq
import math
import os
import sys
import tempfile
import time
from dataclasses import asdict, dataclass, field
from pathlib import Path

import httpx
import orjson
import zenoh

from service.bench.config import GATEWAY, BenchConfig
from service.bench.fleet import Fleet
from service.bench.load import _wait_for_tuner, register
from service.bench.probes import scrape
from service.bench.retention_check import budget, check, db_bytes, settled, written_rows
from service.daemon.settings import Settings
from service.procs import ROOT, TunerProcess
from service.wire.protocol import Keys
from service.wire.session import session_config

POLICY = ("history_max_rows_per_loop", "history_max_age_days", "history_max_rows_deleted",
          "history_prune_interval_s")  # fmt: skip
"""The retention settings a run may override (the default policy otherwise)."""


def _default(name: str):
    return Settings.model_fields[name].default


@dataclass(frozen=True)
class RetentionConfig:
    loops: int = 10_000
    """Site loops."""
    hours: float = 24.0
    """Plant hours to run."""
    speed: float = 60.0
    """Plant (and tuner clock) seconds per real second."""
    sample_period: float = 60.0
    """Sample period of the site loops, plant seconds."""
    tau: tuple[float, float] = (60.0, 600.0)
    """Range of the site loops' time constants, seconds (RL period 5.5 tau)."""
    fast: int = 100
    """Loops with tau = sample period = ``fast_tau``, an RL step every 5.5 tau."""
    fast_tau: float = 1.0
    """Time constant and sample period of the fast and the churn loops, seconds."""
    churn: int = 50
    """Loops deleted and registered anew every ``churn_every`` plant seconds."""
    churn_every: float = 3600.0
    groups: int = 50
    """Phase groups per fleet (sample instants spread over one sample period)."""
    report_every: float = 3600.0
    """Plant seconds between two size readings."""
    max_minutes: float | None = None
    """Stop the load after this many real minutes (then settle and check what was
    reached); None: run the whole ``hours``."""
    history_max_rows_per_loop: int | None = _default("history_max_rows_per_loop")
    history_max_age_days: float | None = _default("history_max_age_days")
    history_max_rows_deleted: int = _default("history_max_rows_deleted")
    history_prune_interval_s: float = _default("history_prune_interval_s")
    seed: int = 0
    out: Path = ROOT / "reports" / "retention.json"
    daemon_log: Path | None = None
    workdir: Path | None = None
    """Keep the store here (default: a temporary folder, removed)."""

    def policy(self) -> dict:
        return {k: getattr(self, k) for k in POLICY}

    def env(self, archive: Path) -> dict[str, str]:
        """The daemon's environment: the clock speed, the archive, the policy's overrides."""
        env = {
            "PITUNE_CLOCK_SPEED": repr(self.speed),
            "PITUNE_HISTORY_ARCHIVE": str(archive),
            # The flood limit counts a loop's samples per second of the tuner's clock, read
            # once per batch of messages: a backlog of a fast loop's samples handled in one
            # batch would count as a burst at this speed (as in `pitune demo`, raise it).
            "PITUNE_MAX_SAMPLE_RATE_HZ": repr(1e6),
        }
        for name, value in self.policy().items():
            if value != _default(name):
                env[f"PITUNE_{name.upper()}"] = "null" if value is None else repr(value)
        return env


@dataclass
class Source:
    """One fleet of loops sampled on its own clock, its ids renamed to ``prefix``."""

    fleet: Fleet
    period: float
    t0: float = 0.0
    """Plant time of its first sample (a churn generation starts mid-run)."""
    live: bool = True
    gains: int = 0


def _fleet(n: int, period: float, tau: tuple[float, float], groups: int, seed: int,
           ids: list[str]) -> Fleet:  # fmt: skip
    """``n`` bench loops sampled every ``period`` plant seconds, named ``ids``."""
    config = BenchConfig(loops=n, rate=1.0 / period, tau=tau, tick=period / groups, seed=seed)
    fleet = Fleet(config)
    old = fleet.ids
    fleet.ids = ids
    for body, new in zip(fleet.registrations, ids, strict=True):
        body["id"] = new
    for grp in fleet.groups:
        grp.ids = [ids[i] for i in grp.index]
    fleet.where = {ids[i]: fleet.where[old[i]] for i in range(n)}
    return fleet


def _churn_fleet(config: RetentionConfig, generation: int) -> Fleet:
    ids = [f"C{generation:04d}-{j:04d}" for j in range(config.churn)]
    tau = config.fast_tau
    return _fleet(config.churn, tau, (tau, tau), 2, config.seed + 1000 + generation, ids)


@dataclass
class Run:
    """The generator's state during a run."""

    config: RetentionConfig
    daemon: TunerProcess
    client: httpx.Client
    db: Path
    sources: dict[str, Source] = field(default_factory=dict)
    """By the ids' prefix: S (site), F (fast), C0001 (churn generation 1)."""
    churning: str | None = None
    """The key of the live churn generation."""
    inbox: collections.deque = field(default_factory=collections.deque)
    timeline: list[dict] = field(default_factory=list)
    deleted: list[str] = field(default_factory=list)
    published: int = 0
    late_max: float = 0.0
    backlog_max: float = 0.0
    reached: float = 0.0
    """Plant time of the last sample instant played."""
    generation: int = 1
    """The next churn generation."""
    """Longest wait for the tuner to drain its input before a churn, real seconds."""


def _take_gains(run: Run, inbox: collections.deque) -> None:
    while inbox:
        msg = orjson.loads(inbox.popleft())
        for gains in msg.get("gains", [msg]):
            src = run.sources.get(_key(gains["loop_id"]))
            if src is not None and src.live and gains["loop_id"] in src.fleet.where:
                src.gains += 1
                if gains.get("reason", "agent") == "agent" and gains["mode"] == "auto":
                    src.fleet.offer(gains["loop_id"], gains["kp"], gains["ki"])


def _key(loop_id: str) -> str:
    return loop_id.split("-")[0] if loop_id[0] == "C" else loop_id[0]


def _received(run: Run, timeout: float = 300.0) -> None:
    """Until the tuner has received every sample published (its backlog drained)."""
    start = time.monotonic()
    while scrape(run.client, run.daemon.api)["pitune_samples_received_total"] < run.published:
        if time.monotonic() - start > timeout:
            raise TimeoutError(f"the tuner is still {timeout:.0f} s behind the samples")
        time.sleep(0.01)
    run.backlog_max = max(run.backlog_max, time.monotonic() - start)


def _churn(run: Run, generation: int, at: float | None) -> list[tuple]:
    """Delete the churn loops of the live generation; with ``at`` (plant time), register
    the next one; the sample instants of its loops."""
    if run.churning is not None:
        src = run.sources[run.churning]
        src.live = False  # as a gateway would: stop sending, then delete
        _received(run)
        for loop_id in src.fleet.ids:
            r = run.client.delete(f"{run.daemon.api}/loops/{loop_id}")
            if r.status_code != 204:
                raise RuntimeError(f"delete {loop_id}: {r.status_code} {r.text[:300]}")
        run.deleted += src.fleet.ids
        run.churning = None
    if at is None or not run.config.churn:
        return []
    fleet = _churn_fleet(run.config, generation)
    register(run.client, run.daemon, fleet.registrations)
    run.churning = f"C{generation:04d}"
    run.sources[run.churning] = Source(fleet, run.config.fast_tau, t0=at)
    return [(at + grp.offset, run.churning, g, 0) for g, grp in enumerate(fleet.groups)]


def _reading(run: Run, sim: float, real: float) -> dict:
    """The store's size now (cheap: no table scan while the generator waits)."""
    m = scrape(run.client, run.daemon.api)
    written = written_rows(run.db)
    pruned = int(m.get("pitune_audit_pruned_total", 0))
    return {
        "plant_h": round(sim / 3600.0, 3),
        "real_s": round(real, 1),
        **db_bytes(run.db),
        "audit_written": written,
        "audit_pruned": pruned,
        "audit_rows": written - pruned,
        "load_avg": os.getloadavg()[0],
    }


def play(run: Run, session, keys: Keys) -> dict:
    """Sample every source on its clock, ``speed`` times real time, for ``hours``."""
    cfg = run.config
    end = cfg.hours * 3600.0
    heap = []  # (plant time due, source key, group, k)
    for key, src in run.sources.items():
        heap += [(src.t0 + grp.offset, key, g, 0) for g, grp in enumerate(src.fleet.groups)]
    heapq.heapify(heap)
    start = time.monotonic()
    deadline = math.inf if cfg.max_minutes is None else start + 60.0 * cfg.max_minutes
    stopped = "completed"
    try:
        due = _play(run, session, keys, heap, start, deadline)
    except (httpx.HTTPError, TimeoutError) as exc:  # the tuner too slow to answer: stop
        stopped, due = f"error: {exc!r}", run.reached
    if due < end:
        stopped = stopped if stopped != "completed" else "time budget (--max-minutes)"
    if not stopped.startswith("error"):
        _churn(run, run.generation, None)  # the last generation goes too
    _take_gains(run, run.inbox)
    run.timeline.append(_reading(run, min(due, end), time.monotonic() - start))
    return {"real_s": time.monotonic() - start, "plant_s": min(due, end), "stopped": stopped}


def _play(run: Run, session, keys: Keys, heap: list, start: float, deadline: float) -> float:
    """The load until the plant time ``end`` or the real ``deadline``; the plant time
    reached."""
    cfg = run.config
    end = cfg.hours * 3600.0
    t0 = 1000.0  # plant time of the first sample
    next_churn = cfg.churn_every
    next_reading = 0.0
    block = zenoh.CongestionControl.BLOCK
    while heap:
        due, key, g, k = heapq.heappop(heap)
        run.reached = due
        if due >= end or time.monotonic() > deadline:
            return due
        while due >= next_churn:  # plant time passed a churn instant
            at = next_churn if next_churn + cfg.churn_every <= end else None
            for entry in _churn(run, run.generation, at):
                heapq.heappush(heap, entry)
            next_churn += cfg.churn_every
            run.generation += 1
        if due >= next_reading:
            run.timeline.append(_reading(run, due, time.monotonic() - start))
            print(f"  {run.timeline[-1]}", flush=True)
            next_reading += cfg.report_every
        src = run.sources[key]
        if not src.live:
            continue
        _take_gains(run, run.inbox)
        wait = start + due / cfg.speed - time.monotonic()
        if wait > 0:
            time.sleep(wait)
        else:
            run.late_max = max(run.late_max, -wait)
        _, samples = src.fleet.scan(g, k, t0 + src.t0)
        for i in range(0, len(samples), 2000):
            session.put(keys.batch, orjson.dumps({"v": 1, "samples": samples[i : i + 2000]}),
                        congestion_control=block)  # fmt: skip
        run.published += len(samples)
        heapq.heappush(heap, (due + src.period, key, g, k + 1))
    return end


def execute(config: RetentionConfig) -> dict:
    """The whole run: daemon up, loops registered, play, settle, stop, check."""
    with tempfile.TemporaryDirectory(prefix="pitune-retention-") as tmp:
        work = config.workdir or Path(tmp)
        work.mkdir(parents=True, exist_ok=True)
        db, archive = work / "retention.db", work / "pruned.jsonl"
        for stale in (db, archive, Path(f"{db}-wal"), Path(f"{db}-shm")):
            stale.unlink(missing_ok=True)
        daemon = TunerProcess(
            db, "--instance-id", "retention", "--log-level", "warning",
            log=config.daemon_log or work / "daemon.log", env=config.env(archive),
        )  # fmt: skip
        daemon.start(timeout=90.0)
        try:
            with httpx.Client(timeout=300) as client:
                run = Run(config, daemon, client, db)
                result = _drive(run)
                wait = _settle_timeout(config)
                result["settle_s"] = settled(db, config, run.deleted, timeout=wait)
                asked = time.monotonic()
                marker = _marker(run)
        finally:
            result_exit = daemon.stop()
        # the tuner's clock when it stopped, at the latest: after every retention pass
        end_wall = marker + config.speed * (time.monotonic() - asked)
        result.update(daemon_exit=result_exit, end_slack_s=end_wall - marker)
        result.update(check(db, archive, config, run.deleted, end_wall))
        result["budget"] = budget(config, result)
    return result


def _settle_timeout(config: RetentionConfig) -> float:
    """Two retention passes after the last deletion, in real seconds, plus the passes'
    own time."""
    return 2.0 * config.history_prune_interval_s / config.speed + 120.0


def _drive(run: Run) -> dict:
    cfg = run.config
    site = [f"S{i:05d}" for i in range(cfg.loops)]
    run.sources["S"] = Source(
        _fleet(cfg.loops, cfg.sample_period, cfg.tau, cfg.groups, cfg.seed, site), cfg.sample_period
    )
    if cfg.fast:
        fast = [f"F{i:04d}" for i in range(cfg.fast)]
        tau = cfg.fast_tau
        run.sources["F"] = Source(_fleet(cfg.fast, tau, (tau, tau), 2, cfg.seed + 1, fast), tau)
    registered = time.monotonic()
    for src in run.sources.values():
        register(run.client, run.daemon, src.fleet.registrations)
    _churn(run, 0, 0.0)
    register_s = time.monotonic() - registered
    keys = Keys()
    session = zenoh.open(session_config(mode="peer", connect=[run.daemon.zenoh]))
    try:
        sub = session.declare_subscriber(
            keys.gateway_gains(GATEWAY), lambda s: run.inbox.append(s.payload.to_bytes())
        )
        try:
            _wait_for_tuner(session, keys, next(iter(run.sources["S"].fleet.ids)))
            timing = play(run, session, keys)
            _take_gains(run, run.inbox)
        finally:
            sub.undeclare()
    finally:
        session.close()
    m = scrape(run.client, run.daemon.api)
    return {
        **timing,
        "register_s": register_s,
        "samples_published": run.published,
        "samples_received": m.get("pitune_samples_received_total"),
        "samples_rejected": sum(v for k, v in m.items() if k.startswith("pitune_samples_rejected")),
        "samples_rejected_by_reason": {
            k.split("reason=")[1].rstrip("}"): v
            for k, v in m.items()
            if k.startswith("pitune_samples_rejected_total{") and v
        },
        "gains_received": sum(s.gains for s in run.sources.values()),
        "generator_late_max_s": run.late_max,
        "tuner_backlog_max_s": run.backlog_max,
        "timeline": run.timeline,
    }


def _marker(run: Run) -> float:
    """Register a loop: its audit row's wall_time is a reading of the tuner's clock."""
    body = {**run.sources["S"].fleet.registrations[0], "id": "END"}
    r = run.client.post(f"{run.daemon.api}/loops", json=body)
    if r.status_code != 201:
        raise RuntimeError(f"marker: {r.status_code} {r.text[:300]}")
    (entry,) = run.client.get(f"{run.daemon.api}/loops/END/history").json()["items"]
    return entry["wall_time"]


def add_arguments(parser: argparse.ArgumentParser) -> None:
    """The retention run's options (with ``--retention``; ``--loops`` and ``--seed`` are
    the bench's)."""
    d = RetentionConfig()
    g = parser.add_argument_group("retention run (--retention)")
    a = g.add_argument
    a("--retention", action="store_true",
      help="accelerated retention run: disk use of the audit history over --hours")  # fmt: skip
    a("--hours", type=float, default=d.hours, help="plant hours (default 24)")
    a("--speed", type=float, default=d.speed, help="plant seconds per real second (default 60)")
    a("--sample-period", type=float, default=d.sample_period,
      help="site loops' sample period, plant s (default 60)")  # fmt: skip
    a("--site-tau", type=float, nargs=2, default=d.tau, metavar=("MIN", "MAX"),
      help="site loops' time constants, s (default 60 600)")  # fmt: skip
    a("--fast-loops", type=int, default=d.fast, help="loops stepped every 5.5 s (default 100)")
    a("--churn", type=int, default=d.churn, help="loops deleted and re-registered (default 50)")
    a("--churn-every", type=float, default=d.churn_every,
      help="plant seconds between churns (default 3600)")  # fmt: skip
    a("--max-minutes", type=float, default=None,
      help="stop the load after this many real minutes, then check what was reached")  # fmt: skip
    a("--report", type=Path, default=d.out, help="where the JSON goes")


def retention_config(args: argparse.Namespace) -> RetentionConfig:
    return RetentionConfig(
        loops=args.loops, hours=args.hours, speed=args.speed, sample_period=args.sample_period,
        tau=tuple(args.site_tau), fast=args.fast_loops, churn=args.churn,
        churn_every=args.churn_every, seed=args.seed, out=args.report,
        max_minutes=args.max_minutes,
        daemon_log=args.daemon_log,
    )  # fmt: skip


def main(args: argparse.Namespace) -> int:
    config = retention_config(args)
    if config.loops < 1 or config.hours <= 0 or config.speed <= 0:
        print("pitune bench --retention: --loops, --hours, --speed must be positive",
              file=sys.stderr)  # fmt: skip
        return 2
    result = execute(config)
    result["config"] = orjson.loads(orjson.dumps(asdict(config), default=str))
    config.out.parent.mkdir(parents=True, exist_ok=True)
    config.out.write_bytes(orjson.dumps(result, option=orjson.OPT_INDENT_2) + b"\n")
    print(orjson.dumps({k: result[k] for k in ("verdict", "budget")},
                       option=orjson.OPT_INDENT_2).decode())  # fmt: skip
    print(f"written to {config.out}")
    return 0 if result["verdict"]["ok"] else 1
