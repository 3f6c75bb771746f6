"""``python -m service.bench.takeover``: what a cluster member's takeover of a dead
member's loops costs per loop, part by part, without the cluster around it (less
sensitive to a busy machine than ``pitune bench --instances``' failover time).

A temporary PostgreSQL server (:class:`~service.bench.pgserver.PgServer`) gets
``--loops`` of the bench's loops (:class:`~service.bench.fleet.Fleet`, on 4 gateways),
each with a runtime snapshot of a loop that ran ``--steps`` samples through the engine.
Then, as :meth:`Ownership.adopt_shards <service.daemon.ownership.Ownership.adopt_shards>`
does: ``load`` (the query and the configs parsed), ``parse`` (the snapshots parsed),
``insert`` (into the engine's table, a chunk at a time), each in µs per loop (the best of
``--repeat`` runs), and the insert loop by loop for comparison.
"""

from __future__ import annotations

import argparse
import json
import os
import time

from service.bench.config import BenchConfig
from service.bench.fleet import Fleet
from service.bench.pgserver import PgServer
from service.daemon.ownership import ADOPT_CHUNK
from service.daemon.shards import gateway_shard
from service.daemon.store_pg import PgStore
from service.engine import LoopConfig, TuningEngine
from service.engine.config import Registration

GATEWAYS = 4


def _runtimes(fleet: Fleet, steps: int) -> list[tuple[bytes, str]]:
    """Snapshots of the first loops of ``fleet`` after ``steps`` samples each (a few
    hundred distinct ones, reused round-robin: a runtime's size, not its values, is what
    a takeover's cost depends on)."""
    engine = TuningEngine()
    group = fleet.groups[0]
    for loop_id in group.ids:
        engine.register(Registration.model_validate(fleet.registrations[int(loop_id[1:])]))
    for k in range(steps):
        t, samples = fleet.scan(0, k, 1000.0)
        for update in engine.ingest(samples, wall=t):
            fleet.offer(update.loop_id, update.kp, update.ki)
    return [(hidden, runtime) for _, hidden, runtime in engine.snapshot()]


def _fill(store: PgStore, fleet: Fleet, runtimes: list[tuple[bytes, str]]) -> None:
    configs = [LoopConfig.model_validate(r) for r in fleet.registrations]
    for i in range(0, len(configs), 5000):
        chunk = configs[i : i + 5000]
        store.insert_loops(chunk, [], [7] * len(chunk))
    rows = [
        (c.id, *runtimes[i % len(runtimes)]) for i, c in enumerate(configs)
    ]  # fmt: skip
    for i in range(0, len(rows), 2000):
        store.snapshot(rows[i : i + 2000])


def _best(repeat: int, run) -> float:
    best = float("inf")
    for _ in range(repeat):
        began = time.perf_counter()
        run()
        best = min(best, time.perf_counter() - began)
    return best


def measure(loops: int, steps: int, repeat: int) -> dict:
    fleet = Fleet(BenchConfig(loops=loops, rate=1.0, gateways=GATEWAYS))
    shards = sorted({gateway_shard(r["gateway"]) for r in fleet.registrations})
    runtimes = _runtimes(fleet, steps)
    server = PgServer()
    try:
        store = PgStore(server.create_database())
        try:
            _fill(store, fleet, runtimes)
            stored = store.load(shards)
            saved = store.saved_many(stored)

            def insert(chunked: bool) -> None:
                engine = TuningEngine()
                for i in range(0, len(stored), ADOPT_CHUNK):
                    part, ahead = stored[i : i + ADOPT_CHUNK], saved[i : i + ADOPT_CHUNK]
                    if chunked:
                        engine.add_many(
                            [s.config for s in part], kp=[s.kp for s in part],
                            ki=[s.ki for s in part], seq=[s.seq for s in part], saved=ahead,
                        )  # fmt: skip
                        continue
                    for s, x in zip(part, ahead, strict=True):
                        engine.restore(s.config, kp=s.kp, ki=s.ki, seq=s.seq, saved=x)

            seconds = {
                "load": _best(repeat, lambda: store.load(shards)),
                "parse": _best(repeat, lambda: store.saved_many(stored)),
                "insert": _best(repeat, lambda: insert(True)),
                "insert_one_by_one": _best(1, lambda: insert(False)),
            }
        finally:
            store.close()
    finally:
        server.stop()
    return {
        "loops": loops,
        "runtime_bytes": sum(len(r) for _, r in runtimes) / len(runtimes),
        "us_per_loop": {k: round(1e6 * v / loops, 1) for k, v in seconds.items()},
        "load_average": list(os.getloadavg()),
    }


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--loops", type=int, default=20000)
    parser.add_argument("--steps", type=int, default=300, help="samples per loop run first")
    parser.add_argument("--repeat", type=int, default=3)
    args = parser.parse_args()
    print(json.dumps(measure(args.loops, args.steps, args.repeat), indent=1))


if __name__ == "__main__":
    main()
