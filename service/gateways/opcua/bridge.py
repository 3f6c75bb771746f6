"""The OPC UA gateway: PID blocks of a DCS on one side, the pitune bus on the other.

Samples. Every notification of a loop's PV (its source timestamp) makes one sample:
``t`` is that timestamp (seconds since the Unix epoch; the server timestamp if the
server gives no source timestamp), ``sp``, ``op`` and the rest are the values in force
at that time (notifications of one publish are applied in source-timestamp order),
``kp``/``ki`` the block's gains converted to the parallel form, ``auto`` whether the mode
is one of the map's auto values, ``saturated`` whether an output-at-limit flag is set.
Samples go out batched (``SampleBatch`` on ``{prefix}/samples``, every
``batch_interval_s``) with ``CongestionControl.BLOCK``. While no tuner's liveliness token
is present (tuner down, Zenoh router or link down) they are held in a buffer of at most
``buffer_max_samples`` (the oldest are dropped beyond, and counted) and sent when a tuner
is back, still in order per loop.

Gains. Updates come through :class:`service.gateways.base.Gateway` (sequence rule, batched
gains, state query whenever a tuner's token appears). An ``auto`` update becomes the
loop's pending write (a newer one replaces it); it is written, in the block's own form,
only when all hold at that moment:

* the OPC UA session is up;
* the loop is in auto (mode node's value among ``auto_values``): else it is dropped;
* tuning is enabled (the tuning-enable node is true, or the map's flag): else dropped;
* the values are within the map's hard limits: else dropped (never clipped);
* the block's gains are still those it had when the update arrived: else an operator
  (or the DCS) changed them meanwhile and the update is stale: dropped;
* ``min_write_interval_s`` has passed since the loop's last write: else it waits.

A write is one request for all due loops, then a read-back of the same nodes; the
values read back become the block's gains in force, reported in the next samples.
A refused write (bad status) or one the block changed (read-back differs) is logged and
counted; the tuner sees the gains in force in the samples and adopts them.
"""

from __future__ import annotations

import asyncio
import contextlib
import logging
import math
import time
from collections import Counter, deque
from collections.abc import Callable
from dataclasses import dataclass, field
from typing import Any

import httpx
import orjson
import zenoh

from service.gateways.base import SAMPLE_CONGESTION, Gateway, Update
from service.gateways.opcua.client import Change, Item, LinkLost, OpcUaLink, now_epoch
from service.gateways.opcua.forms import FormError
from service.gateways.opcua.sitemap import LoopMap, SiteMap
from service.wire.protocol import ENCODING, MAX_BATCH, Keys, Mode

log = logging.getLogger("pitune.gateway.opcua")
TICK_S = 0.02
"""How often gains are taken from the bus and due writes made."""
REL_TOL = 1e-5
"""Read-back and comparisons of gains: float32 nodes round to ~6e-8."""
WAIT = "wait"


def close_to(a: tuple[float, float] | None, b: tuple[float, float] | None) -> bool:
    if a is None or b is None:
        return False
    return all(math.isclose(x, y, rel_tol=REL_TOL, abs_tol=0.0) for x, y in zip(a, b, strict=True))


def _number(value: Any) -> float | None:
    if isinstance(value, bool) or not isinstance(value, int | float):
        return None
    value = float(value)
    return value if math.isfinite(value) else None


@dataclass
class Pending:
    update: Update
    received: float
    """time.monotonic() when the update was taken from the bus."""
    base: tuple[float, float] | None
    """The block's (P, I) when it arrived: a write goes out only if they still hold."""


@dataclass
class LoopRuntime:
    index: int
    cfg: LoopMap
    values: dict[str, Any] = field(default_factory=dict)
    types: dict[str, Any] = field(default_factory=dict)
    last_t: float | None = None
    pending: Pending | None = None
    last_write: float = -math.inf
    last_seq: int = 0

    @property
    def auto(self) -> bool:
        if self.cfg.mode is None:
            return True
        mode = self.values.get("mode")
        if isinstance(mode, float) and mode.is_integer():
            mode = int(mode)
        return any(mode == v and type(mode) is type(v) for v in self.cfg.auto_values)

    @property
    def enabled(self) -> bool:
        te = self.cfg.tuning_enable
        return te if isinstance(te, bool) else self.values.get("tuning_enable") is True

    @property
    def saturated(self) -> bool:
        v = self.values
        return v.get("at_high_limit") is True or v.get("at_low_limit") is True

    def block_gains(self) -> tuple[float, float] | None:
        p, i = _number(self.values.get("p")), _number(self.values.get("i"))
        return None if p is None or i is None else (p, i)

    def in_force(self) -> tuple[float, float] | None:
        gains = self.block_gains()
        if gains is None:
            return None
        try:
            return self.cfg.form.to_parallel(*gains)
        except FormError:
            return None


@dataclass(frozen=True)
class Event:
    """What the gateway did (for tests and tools that wait on it instead of sleeping)."""

    kind: str
    """connected, lost, connect_failed, received, written, refused, applied_already."""
    loop_id: str | None = None
    seq: int | None = None
    detail: str = ""
    at: float = field(default_factory=time.monotonic)
    """When it happened (time.monotonic())."""


class OpcUaGateway:
    """Runs until ``stop`` is set: :meth:`run`. The Zenoh session is the caller's."""

    def __init__(
        self,
        site: SiteMap,
        session: zenoh.Session,
        *,
        record_events: bool = False,
        status_interval_s: float = 60.0,
    ) -> None:
        self.site = site
        self.session = session
        self.keys = Keys(site.bus.prefix)
        self.loops = [LoopRuntime(k, cfg) for k, cfg in enumerate(site.loops)]
        self.by_id = {lr.cfg.id: lr for lr in self.loops}
        self.stats: Counter[str] = Counter()
        self.latencies: deque[float] = deque(maxlen=1_000_000)
        """Seconds from taking an update off the bus to its verified write."""
        self.outbox: deque[dict] = deque()
        self.link: OpcUaLink | None = None
        self.events: asyncio.Queue[Event] | None = asyncio.Queue() if record_events else None
        self.history: list[Event] = []
        """Every event, when recording (tests)."""
        self.status_interval_s = status_interval_s
        self._registered = site.tuner.register_url is None
        self._last_flush = 0.0
        self.bus = Gateway(session, list(self.by_id), self.keys, gateway_id=site.bus.gateway_id)
        try:
            self.publisher = session.declare_publisher(
                self.keys.batch, encoding=ENCODING, congestion_control=SAMPLE_CONGESTION
            )
        except BaseException:
            self.bus.close()
            raise

    # -- events ----------------------------------------------------------------------
    def emit(self, kind: str, loop_id: str | None = None, seq: int | None = None, detail=""):
        if self.events is not None:
            event = Event(kind, loop_id, seq, detail)
            self.history.append(event)
            self.events.put_nowait(event)

    async def wait_event(self, predicate: Callable[[Event], bool], timeout: float = 10.0) -> Event:
        """The next recorded event matching ``predicate`` (earlier ones are consumed)."""
        assert self.events is not None, "record_events=False"
        async with asyncio.timeout(timeout):
            while True:
                ev = await self.events.get()
                if predicate(ev):
                    return ev

    # -- main ------------------------------------------------------------------------
    async def run(self, stop: asyncio.Event) -> None:
        tasks = [
            asyncio.create_task(self._supervise_link(stop), name="opcua-link"),
            asyncio.create_task(self._bus_loop(stop), name="bus"),
        ]
        try:
            done, _ = await asyncio.wait(
                [*tasks, asyncio.create_task(stop.wait())], return_when="FIRST_COMPLETED"
            )
            for task in tasks:
                if task in done and task.exception() is not None:
                    raise task.exception()
        finally:
            stop.set()
            for task in tasks:
                task.cancel()
            for task in tasks:
                with contextlib.suppress(asyncio.CancelledError, Exception):
                    await task
            self._flush(force=True)
            self.close()

    def close(self) -> None:
        """Undeclare the bus entities (idempotent)."""
        self.bus.close()
        with contextlib.suppress(zenoh.ZError):
            self.publisher.undeclare()

    # -- OPC UA side -----------------------------------------------------------------
    def _monitored(self) -> list[tuple[Item, str]]:
        return [(Item(lr.index, f), n) for lr in self.loops for f, n in lr.cfg.nodes().items()]

    async def _supervise_link(self, stop: asyncio.Event) -> None:
        server = self.site.server
        delay = server.reconnect_min_s
        sampling = {lr.index: lr.cfg.sampling_interval_ms for lr in self.loops}
        queues = {lr.index: lr.cfg.queue_size for lr in self.loops}
        publishing = server.publishing_interval_ms or min(sampling.values())
        monitored = self._monitored()
        while not stop.is_set():
            link = OpcUaLink(server)

            async def first_read(changes: list[Change]) -> None:
                # the gains in force are known now: register before sampling starts
                self._apply(changes, types=True)
                if not self._registered:
                    await self._register()

            try:
                await link.open(
                    monitored,
                    sampling_ms=sampling,
                    queue_size=queues,
                    publishing_ms=publishing,
                    before_subscribe=first_read,
                )
            except RegistrationError:
                await link.close()
                raise
            except asyncio.CancelledError:
                raise
            except Exception as exc:
                self.stats["connect_failures"] += 1
                log.warning("OPC UA connect to %s failed (%s: %s); retry in %.1f s",
                            server.url, type(exc).__name__, exc, delay)  # fmt: skip
                self.emit("connect_failed", detail=f"{type(exc).__name__}: {exc}")
                with contextlib.suppress(TimeoutError):
                    await asyncio.wait_for(stop.wait(), delay)
                delay = min(delay * 2.0, server.reconnect_max_s)
                continue
            delay = server.reconnect_min_s
            self.stats["connects"] += 1
            log.info("OPC UA session up: %s, %d nodes monitored", server.url, len(monitored))
            try:
                self.link = link
                self.emit("connected")
                while not stop.is_set():
                    self._apply(await link.events(timeout=0.5))
            except LinkLost as exc:
                self.stats["links_lost"] += 1
                log.warning("OPC UA session lost (%s); reconnecting", exc)
                self.emit("lost", detail=str(exc))
            finally:
                self.link = None
                await link.close()

    def _apply(self, changes: list[Change], *, types: bool = False) -> None:
        """Apply value changes in source-timestamp order; each PV change is a sample."""
        changes.sort(key=lambda c: (math.inf if c.t is None else c.t, c.item.field == "pv"))
        for ch in changes:
            lr = self.loops[ch.item.loop]
            name = ch.item.field
            if types and name in ("p", "i") and ch.good:
                lr.types[name] = ch.vtype
            if not ch.good:
                self.stats["bad_values"] += 1
                lr.values.pop(name, None)
                continue
            lr.values[name] = ch.value
            if name == "pv":
                self._sample(lr, ch.t)

    def _sample(self, lr: LoopRuntime, t: float | None) -> None:
        t = now_epoch() if t is None else t
        if lr.last_t is not None and t <= lr.last_t:
            self.stats["samples_not_newer"] += 1  # a repeated notification (reconnect)
            return
        sp, pv = _number(lr.values.get("sp")), _number(lr.values.get("pv"))
        if sp is None or pv is None:
            self.stats["samples_incomplete"] += 1
            return
        sample = {"loop_id": lr.cfg.id, "t": float(t), "sp": sp, "pv": pv,
                  "auto": lr.auto, "saturated": lr.saturated}  # fmt: skip
        gains = lr.in_force()
        if gains is not None:
            sample["kp"], sample["ki"] = gains
        lr.last_t = t
        if len(self.outbox) >= self.site.bus.buffer_max_samples:
            self.outbox.popleft()
            self.stats["samples_dropped"] += 1
        self.outbox.append(sample)
        self.stats["samples"] += 1

    # -- bus side --------------------------------------------------------------------
    async def _bus_loop(self, stop: asyncio.Event) -> None:
        next_status = time.monotonic() + self.status_interval_s
        while not stop.is_set():
            self._take_updates()
            await self._write_due()
            self._flush()
            if time.monotonic() >= next_status:
                next_status += self.status_interval_s
                log.warning("status: %s", self.status_line())
            with contextlib.suppress(TimeoutError):
                await asyncio.wait_for(stop.wait(), TICK_S)

    def status_line(self) -> str:
        s = self.stats
        return (f"{len(self.loops)} loops, OPC UA {'up' if self.link else 'down'}, tuner "
                f"{'up' if self.bus.tuner_up else 'down'}; samples {s['samples']} "
                f"(published {s['published']}, buffered {len(self.outbox)}, dropped "
                f"{s['samples_dropped']}); writes {s['written']}, refused "
                f"{sum(v for k, v in s.items() if k.startswith('refused'))}")  # fmt: skip

    def report(self) -> dict:
        """Counters and write latencies (s, update taken off the bus to verified write)."""
        lat = sorted(self.latencies)

        def pct(q: float) -> float | None:
            return lat[min(len(lat) - 1, int(q * len(lat)))] if lat else None

        return {"loops": len(self.loops), "counters": dict(self.stats),
                "buffered": len(self.outbox), "write_latency_s": {
                    "n": len(lat), "p50": pct(0.5), "p99": pct(0.99),
                    "max": lat[-1] if lat else None}}  # fmt: skip

    def _take_updates(self) -> None:
        now = time.monotonic()
        for update in self.bus.gains():
            lr = self.by_id[update.loop_id]
            if update.mode != Mode.auto:
                self.stats["advisory"] += 1
                continue
            if lr.pending is not None:
                self.stats["superseded"] += 1
            lr.pending = Pending(update, now, lr.block_gains())
            self.stats["received"] += 1
            self.emit("received", lr.cfg.id, update.seq, update.source.value)

    def _decide(self, lr: LoopRuntime, now: float) -> str | tuple[float, float]:
        """WAIT, a refusal reason, "applied" (nothing to write) or the (P, I) to write."""
        assert lr.pending is not None
        update = lr.pending.update
        if self.link is None:
            return WAIT
        if not lr.auto:
            return "manual"
        if not lr.enabled:
            return "tuning_disabled"
        try:
            target = lr.cfg.form.from_parallel(update.kp, update.ki)
        except FormError:
            return "invalid"
        if not lr.cfg.limits.allows(*target):
            return "beyond_limits"
        current = lr.block_gains()
        if current is None:
            return WAIT
        if close_to(current, target):
            return "applied"
        if lr.pending.base is not None and not close_to(current, lr.pending.base):
            return "stale"
        if now - lr.last_write < lr.cfg.min_write_interval_s:
            return WAIT
        return target

    async def _write_due(self) -> None:
        now = time.monotonic()
        due: list[tuple[LoopRuntime, Pending, tuple[float, float]]] = []
        for lr in self.loops:
            if lr.pending is None:
                continue
            decision = self._decide(lr, now)
            if decision == WAIT:
                continue
            pending, lr.pending = lr.pending, None
            seq = pending.update.seq
            if decision == "applied":
                self.stats["already_in_force"] += 1
                lr.last_seq = seq
                self.emit("applied_already", lr.cfg.id, seq)
            elif isinstance(decision, str):
                self.stats[f"refused_{decision}"] += 1
                log.info("%s: gains seq %d not written: %s", lr.cfg.id, seq, decision)
                self.emit("refused", lr.cfg.id, seq, decision)
            else:
                due.append((lr, pending, decision))
        link = self.link
        if not due or link is None:
            return
        writes = []
        for lr, _, (p, i) in due:
            lr.last_write = now
            writes += [(lr.cfg.p, p, lr.types.get("p")), (lr.cfg.i, i, lr.types.get("i"))]
        try:
            codes, back = await link.write(writes)
        except LinkLost as exc:
            # Unknown whether it went through: keep each update pending (unless a newer one
            # came); after the reconnect it is written only if the block still has the
            # gains it had (else it is stale, or already in force).
            for lr, pending, _ in due:
                if lr.pending is None:
                    lr.pending = pending
                lr.last_write = -math.inf
            self.stats["writes_interrupted"] += len(due)
            log.warning("write of %d loops interrupted: %s", len(due), exc)
            link.lost.set()
            return
        done = time.monotonic()
        for k, (lr, pending, target) in enumerate(due):
            seq = pending.update.seq
            (cp, ci), (bp, bi) = codes[2 * k : 2 * k + 2], back[2 * k : 2 * k + 2]
            read_back = []
            for name, dv in (("p", bp), ("i", bi)):
                good = dv.StatusCode is None or dv.StatusCode.is_good()
                value = dv.Value.Value if good and dv.Value is not None else None
                if _number(value) is not None:
                    lr.values[name] = value
                read_back.append(_number(value))
            lr.last_seq = seq
            if not (cp.is_good() and ci.is_good()):
                bad = cp if not cp.is_good() else ci
                self.stats["refused_by_server"] += 1
                log.warning("%s: server refused the gains of seq %d: %s", lr.cfg.id, seq, bad.name)
                self.emit("refused", lr.cfg.id, seq, f"server:{bad.name}")
            elif not close_to(tuple(read_back), target):  # type: ignore[arg-type]
                self.stats["refused_read_back"] += 1
                log.warning("%s: seq %d read back as %s, not %s", lr.cfg.id, seq, read_back, target)
                self.emit("refused", lr.cfg.id, seq, "read_back")
            else:
                self.stats["written"] += 1
                self.latencies.append(done - pending.received)
                self.emit("written", lr.cfg.id, seq)

    def _flush(self, *, force: bool = False) -> None:
        if not self.outbox or not self.bus.tuner_up or not self._registered:
            return  # held: no tuner to take them, or it does not know the loops yet
        now = time.monotonic()
        if not force and now - self._last_flush < self.site.bus.batch_interval_s:
            return
        self._last_flush = now
        while self.outbox:
            n = min(len(self.outbox), MAX_BATCH)
            chunk = [self.outbox.popleft() for _ in range(n)]
            try:
                self.publisher.put(orjson.dumps({"v": 1, "samples": chunk}))
            except zenoh.ZError as exc:
                self.outbox.extendleft(reversed(chunk))
                log.warning("publishing samples failed: %s", exc)
                return
            self.stats["published"] += n

    # -- registration ----------------------------------------------------------------
    async def _register(self) -> None:
        bodies = []
        for lr in self.loops:
            reg = lr.cfg.registration
            gains = lr.in_force()
            if reg is None:
                continue
            if gains is None:
                log.error("%s: gains unreadable, not registered", lr.cfg.id)
                continue
            body = {
                "id": lr.cfg.id,
                "kp": gains[0],
                "ki": gains[1],
                "sample_period_s": reg.sample_period_s or lr.cfg.sampling_interval_ms / 1000.0,
                "scaling": reg.scaling.model_dump(exclude_none=True),
                **reg.extra,
            }
            if self.site.bus.gateway_id is not None:
                body["gateway"] = self.site.bus.gateway_id
            bodies.append(body)
        if bodies:
            await asyncio.to_thread(register_loops, self.site, bodies)
        self._registered = True


class RegistrationError(RuntimeError):
    pass


def register_loops(site: SiteMap, bodies: list[dict]) -> int:
    """``POST /loops/bulk``; if some ids are taken, each loop alone (409: already known).
    Retries connection failures for ``timeout_s``. Returns how many were new."""
    import os

    url = site.tuner.register_url
    token = os.environ.get(site.tuner.token_env)
    headers = {"Authorization": f"Bearer {token}"} if token else {}
    deadline = time.monotonic() + site.tuner.timeout_s
    with httpx.Client(base_url=url, headers=headers, timeout=30.0) as client:

        def call(method: str, path: str, **kw) -> httpx.Response:
            while True:
                try:
                    return client.request(method, path, **kw)
                except httpx.TransportError as exc:
                    if time.monotonic() > deadline:
                        raise RegistrationError(f"tuner API at {url} unreachable: {exc}") from exc
                    time.sleep(0.5)

        new = 0
        for start in range(0, len(bodies), 10_000):
            chunk = bodies[start : start + 10_000]
            r = call("POST", "/loops/bulk", json=chunk)
            if r.status_code == 409:
                for body in chunk:
                    one = call("POST", "/loops", json=body)
                    if one.status_code not in (201, 409):
                        raise RegistrationError(
                            f"{body['id']}: HTTP {one.status_code} {one.text[:300]}"
                        )
                    new += one.status_code == 201
            elif not r.is_success:
                raise RegistrationError(f"bulk registration: HTTP {r.status_code} {r.text[:300]}")
            else:
                new += len(chunk)
    log.warning("registered %d new loops with %s (%d known)", new, url, len(bodies) - new)
    return new
