"""Several tuners sharing one PostgreSQL store, driven and watched from outside: the
members as processes, a sample load, a log of every gains message on the bus, and
the checks of a failover (used by ``pitune bench --instances N`` and the tests).

What a failover must keep (docs/deploy.md, High availability):

- every loop of a killed member is stepped again by another member within 10 s
  (:func:`failover_delays`);
- no gains message of a loop with a ``seq`` at or below one already published for that
  loop, whoever published it (:meth:`GainsLog.regressions`);
- every published message has its audit row in the store (:func:`missing_audit`:
  commit before publish).
"""

from __future__ import annotations

import collections
import threading
import time
from dataclasses import dataclass
from pathlib import Path

import httpx
import orjson
import psycopg
import zenoh

from service.procs import TunerProcess
from service.wire.protocol import Keys
from service.wire.session import session_config

KEYS = Keys()


@dataclass(frozen=True)
class Heard:
    """One gains message as heard on the bus."""

    at: float
    """Monotonic arrival time."""
    loop_id: str
    seq: int
    epoch: int | None
    instance_id: str
    t: float
    reason: str


class GainsLog:
    """Every gains message on the bus (per-loop and per-gateway keys), in arrival order."""

    def __init__(self, session: zenoh.Session) -> None:
        self.heard: list[Heard] = []
        self._lock = threading.Lock()
        self._subs = [
            session.declare_subscriber(KEYS.all_gains, self._on),
            session.declare_subscriber(KEYS.gateway_gains("*"), self._on),
        ]

    def _on(self, sample: zenoh.Sample) -> None:
        at = time.monotonic()
        msg = orjson.loads(sample.payload.to_bytes())
        with self._lock:
            for g in msg.get("gains", [msg]):
                self.heard.append(
                    Heard(at, g["loop_id"], g["seq"], g.get("epoch"), g["instance_id"],
                          g["t"], g.get("reason", "agent"))
                )  # fmt: skip

    def close(self) -> None:
        for sub in self._subs:
            sub.undeclare()

    def snapshot(self) -> list[Heard]:
        with self._lock:
            return list(self.heard)

    def owners(self) -> dict[str, str]:
        """Loop id -> the member that published its last message."""
        return {h.loop_id: h.instance_id for h in self.snapshot()}

    def regressions(self) -> list[tuple[Heard, int]]:
        """Messages whose seq is at or below one already heard for the same loop, with
        that earlier seq; not a repeat of the highest (same seq and epoch: a takeover
        sends each loop's last message again, which gateways drop)."""
        top: dict[str, tuple[int, int | None]] = {}
        bad = []
        for h in self.snapshot():
            before = top.get(h.loop_id, (0, None))
            if h.seq <= before[0] and (h.seq, h.epoch) != before:
                bad.append((h, before[0]))
            top[h.loop_id] = max(before, (h.seq, h.epoch), key=lambda k: k[0])
        return bad


def failover_delays(
    log: GainsLog, victim: str, loops: list[str], since: float
) -> dict[str, float | None]:
    """Seconds from ``since`` until each loop's first new message (a seq not heard
    before: not its last one sent again on the takeover) from another member than
    ``victim`` (None: not yet)."""
    first: dict[str, float] = {}
    wanted = set(loops)
    top: dict[str, int] = {}
    for h in log.snapshot():
        new = h.seq > top.get(h.loop_id, 0)
        top[h.loop_id] = max(top.get(h.loop_id, 0), h.seq)
        if new and h.at >= since and h.loop_id in wanted and h.instance_id != victim:
            first.setdefault(h.loop_id, h.at - since)
    return {loop_id: first.get(loop_id) for loop_id in loops}


def missing_audit(url: str, heard: list[Heard]) -> list[tuple[str, int]]:
    """(loop, seq) of published messages without their audit row in the store."""
    with psycopg.connect(url) as conn:
        rows = set(conn.execute("SELECT loop_id, seq FROM audit"))
    return sorted({(h.loop_id, h.seq) for h in heard} - rows)


class Load:
    """Batches of samples of ``loop_ids`` every ``interval`` seconds, plant time
    advancing ``dt`` per batch (a gateway scanning faster than real time), until
    stopped. The loops of ``gateways`` (gateway -> its loop ids) go on their gateway's
    samples key (revision 4), the others on the shared ``{prefix}/samples``."""

    def __init__(
        self,
        session: zenoh.Session,
        loop_ids: list[str],
        interval: float,
        dt: float,
        t0: float = 1000.0,
        gateways: dict[str, list[str]] | None = None,
    ) -> None:
        self.session, self.interval, self.dt = session, interval, dt
        self.t0 = t0
        gateways = gateways or {}
        batched = {i for ids in gateways.values() for i in ids}
        self.keyed = [(KEYS.gateway_samples(g), ids) for g, ids in gateways.items()]
        self.keyed.append((KEYS.batch, [i for i in loop_ids if i not in batched]))
        self.sent = 0
        self._stop = threading.Event()
        self._thread = threading.Thread(target=self._run, name="load", daemon=True)

    def start(self) -> Load:
        self._thread.start()
        return self

    def _run(self) -> None:
        t, k = self.t0, 0
        block = zenoh.CongestionControl.BLOCK
        next_at = time.monotonic()
        while not self._stop.is_set():
            e = 0.5 if k % 8 < 4 else -0.5
            for key, ids in self.keyed:
                samples = [{"loop_id": i, "t": t, "e": e} for i in ids]
                for j in range(0, len(samples), 2000):
                    payload = orjson.dumps({"v": 1, "samples": samples[j : j + 2000]})
                    self.session.put(key, payload, congestion_control=block)
                self.sent += len(samples)
            t, k = t + self.dt, k + 1
            next_at += self.interval
            self._stop.wait(max(0.0, next_at - time.monotonic()))

    def stop(self) -> None:
        self._stop.set()
        self._thread.join(timeout=10.0)


class Members:
    """``n`` tuners on the store ``url``, each its own process, API and Zenoh port."""

    def __init__(self, n: int, url: str, workdir: Path, *args: str, lease_s: float = 5.0):
        self.url = url
        self.procs = [
            TunerProcess(
                url,
                "--instance-id",
                f"m{i}",
                "--log-level",
                "info",
                *args,
                log=workdir / f"m{i}.log",
                env={"PITUNE_CLUSTER_LEASE_S": str(lease_s)},
            )  # fmt: skip
            for i in range(n)
        ]
        self.ids = [f"m{i}" for i in range(n)]

    def start(self, timeout: float = 120.0) -> None:
        for proc in self.procs:
            proc.start(timeout=timeout)

    @property
    def endpoints(self) -> list[str]:
        return [p.zenoh for p in self.procs]

    def by_id(self, instance_id: str) -> TunerProcess:
        return self.procs[self.ids.index(instance_id)]

    def cluster(self, via: int = 0) -> dict:
        return httpx.get(f"{self.procs[via].api}/cluster", timeout=10.0).json()

    def stop(self) -> None:
        for proc in self.procs:
            if proc.proc is not None and proc.proc.running:
                proc.stop()


def open_session(endpoints: list[str]) -> zenoh.Session:
    """A peer session connected to every member (the load's and the log's)."""
    return zenoh.open(session_config(mode="peer", connect=endpoints))


def wait_for(predicate, timeout: float, what: str, poll: float = 0.1):
    """Poll ``predicate`` until it returns something true; TimeoutError naming ``what``."""
    deadline = time.monotonic() + timeout
    while time.monotonic() < deadline:
        value = predicate()
        if value:
            return value
        time.sleep(poll)
    raise TimeoutError(f"timed out after {timeout:.0f} s waiting for {what}")


def counts(heard: list[Heard]) -> collections.Counter:
    """Messages per member."""
    return collections.Counter(h.instance_id for h in heard)
