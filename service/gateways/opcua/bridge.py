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
* the block's gains convert to the parallel form (a negative gain does not): else dropped;
* the block's gains are still those it had when the update arrived: else an operator
  (or the DCS) changed them meanwhile and the update is stale: dropped;
* ``min_write_interval_s`` has passed since the loop's last write: else it waits.

A write is one request for all due loops, then a read-back of the same nodes; the
values read back become the block's gains in force, reported in the next samples.
A refused write (bad status) or one the block changed (read-back differs) is logged and
counted; the tuner sees the gains in force in the samples and adopts them.

``applied_seq`` (protocol revision 2): once the gateway is finished with an update --
written, found already in force, or refused (by the policy above or by the server) --
the loop's samples carry its seq, so the gains they report are known to be the block's
after that update: equal to it, the update is confirmed; different, they are an
operator's or the block's choice and the tuner adopts them. While an update waits (no
session, rate limit) the samples carry the previous seq, and the tuner, seeing the
gateway lag, takes nothing for an operator's change.
"""

from __future__ import annotations

import asyncio
import contextlib
import logging
import math
import time
from collections import Counter, deque
from collections.abc import Callable

import orjson
import zenoh

from service.gateways.base import SAMPLE_CONGESTION, Gateway
from service.gateways.opcua.client import Change, Item, LinkLost, OpcUaLink, now_epoch
from service.gateways.opcua.loops import (
    POLICY_FIELDS,
    REL_TOL,
    WAIT,
    Event,
    LoopRuntime,
    Pending,
    close_to,
    decide,
    number,
)
from service.gateways.opcua.register import register_loops, registration_bodies
from service.gateways.opcua.sitemap import SiteMap
from service.gateways.registration import RegistrationError
from service.wire.protocol import ENCODING, MAX_BATCH, Keys, Mode

log = logging.getLogger("pitune.gateway.opcua")
Due = tuple[LoopRuntime, tuple[float, float]]
"""A loop whose pending update is to be written, and the (P, I) to write, block form."""
TICK_S = 0.02
"""How often gains are taken from the bus and due writes made."""


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
        sp, pv = number(lr.values.get("sp")), number(lr.values.get("pv"))
        if sp is None or pv is None:
            self.stats["samples_incomplete"] += 1
            return
        sample = {"loop_id": lr.cfg.id, "t": float(t), "sp": sp, "pv": pv,
                  "auto": lr.auto, "saturated": lr.saturated}  # fmt: skip
        op = number(lr.values.get("op"))
        if op is not None:  # identification's input, and an output held at a limit shows
            sample["op"] = op
        gains = lr.in_force()
        if gains is not None:
            sample["kp"], sample["ki"] = gains
        applied = self.bus.applied_seq(lr.cfg.id)
        if applied is not None:  # the gains above are what the block holds after it
            sample["applied_seq"] = applied
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
                # never written; an auto update published before it still is: the tuner
                # counts it in force (a loop switched to advisory keeps its gains)
                self.stats["advisory"] += 1
                continue
            if lr.pending is not None:
                self.stats["superseded"] += 1
            lr.pending = Pending(update, now, lr.block_gains())
            self.stats["received"] += 1
            self.emit("received", lr.cfg.id, update.seq, update.source.value)

    def _decided(self, loops: list[LoopRuntime], now: float) -> list[Due]:
        """The policy for each loop's pending update: those finished with (refused, or
        already in force) are reported and dropped; the (loop, target) to write are
        returned, their updates still pending."""
        due = []
        for lr in loops:
            if lr.pending is None:
                continue
            decision = decide(lr, self.link is not None, now, self.bus.tuner_up)
            if decision == WAIT:
                continue
            if not isinstance(decision, str):
                due.append((lr, decision))
                continue
            pending, lr.pending = lr.pending, None
            seq = pending.update.seq
            self.bus.applied(pending.update)  # finished with, nothing written
            if decision == "applied":
                self.stats["already_in_force"] += 1
                self.emit("applied_already", lr.cfg.id, seq)
            else:
                self.stats[f"refused_{decision}"] += 1
                log.info("%s: gains seq %d not written: %s", lr.cfg.id, seq, decision)
                self.emit("refused", lr.cfg.id, seq, decision)
        return due

    async def _write_due(self) -> None:
        now = time.monotonic()
        due = self._decided(self.loops, now)
        link = self.link
        if not due or link is None:
            return
        # Judged again on the block's values read now: a notification of a switch to
        # manual, or of an operator's new gains, may still be a publishing interval away.
        try:
            self._apply(await link.read_items(_policy_nodes(lr for lr, _ in due)))
        except LinkLost as exc:  # the updates stay pending, judged again after a reconnect
            log.warning("reading %d loops before writing failed: %s", len(due), exc)
            link.lost.set()
            return
        due = self._decided([lr for lr, _ in due], now)
        if not due:
            return
        writes, before = [], []
        for lr, (p, i) in due:
            lr.last_write = now
            before.append(lr.block_gains())
            writes += [(lr.cfg.p, p, lr.types.get("p")), (lr.cfg.i, i, lr.types.get("i"))]
        taken = [(lr, lr.pending) for lr, _ in due]
        for lr, _ in due:
            lr.pending = None
        try:
            codes, back = await link.write(writes)
        except LinkLost as exc:
            # Unknown whether it went through: keep each update pending (unless a newer one
            # came); after the reconnect it is written only if the block still has the
            # gains it had (else it is stale, or already in force).
            for lr, pending in taken:
                if lr.pending is None:
                    lr.pending = pending
                lr.last_write = -math.inf
            self.stats["writes_interrupted"] += len(due)
            log.warning("write of %d loops interrupted: %s", len(due), exc)
            link.lost.set()
            return
        done = time.monotonic()
        for k, ((lr, target), (_, pending)) in enumerate(zip(due, taken, strict=True)):
            seq = pending.update.seq
            (cp, ci), (bp, bi) = codes[2 * k : 2 * k + 2], back[2 * k : 2 * k + 2]
            read_back = []
            for name, dv in (("p", bp), ("i", bi)):
                good = dv.StatusCode is None or dv.StatusCode.is_good()
                value = dv.Value.Value if good and dv.Value is not None else None
                if number(value) is not None:
                    lr.values[name] = value
                read_back.append(number(value))
            # finished with: written, refused or changed by the block; the samples from
            # now on report the gains read back with applied_seq = seq
            self.bus.applied(pending.update)
            if cp.is_good() != ci.is_good():
                await self._undo_half(link, lr, seq, cp, ci, before[k])
            elif not cp.is_good():
                self.stats["refused_by_server"] += 1
                log.warning("%s: server refused the gains of seq %d: %s", lr.cfg.id, seq, cp.name)
                self.emit("refused", lr.cfg.id, seq, f"server:{cp.name}")
            elif not close_to(tuple(read_back), target):  # type: ignore[arg-type]
                self.stats["refused_read_back"] += 1
                log.warning("%s: seq %d read back as %s, not %s", lr.cfg.id, seq, read_back, target)
                self.emit("refused", lr.cfg.id, seq, "read_back")
            else:
                self.stats["written"] += 1
                self.latencies.append(done - pending.received)
                self.emit("written", lr.cfg.id, seq)

    async def _undo_half(self, link, lr: LoopRuntime, seq: int, cp, ci, before) -> None:
        """The server took one gain of the pair and refused the other: the one taken is
        written back, so the block never runs a pair nobody asked for."""
        name, bad = ("p", ci) if cp.is_good() else ("i", cp)
        self.stats["refused_partial"] += 1
        node, old = getattr(lr.cfg, name), before[0 if name == "p" else 1]
        try:
            codes, back = await link.write([(node, old, lr.types.get(name))])
        except LinkLost as exc:
            codes, back = [], []
            link.lost.set()
            log.error("%s: restoring %s after a partial write failed: %s", lr.cfg.id, name, exc)
        value = number(back[0].Value.Value) if back and back[0].Value is not None else None
        if value is not None:
            lr.values[name] = back[0].Value.Value
        restored = bool(codes) and codes[0].is_good() and value is not None
        restored = restored and math.isclose(value, old, rel_tol=REL_TOL)
        (log.warning if restored else log.error)(
            "%s: server refused %s of seq %d (%s) and took the other; %s",
            lr.cfg.id, "I" if name == "p" else "P", seq, bad.name,
            f"{name.upper()} written back to {old:g}" if restored
            else f"{name.upper()} could NOT be written back to {old:g}: the block holds a "
            "pair pitune did not ask for",
        )  # fmt: skip
        if not restored:
            self.stats["partial_not_undone"] += 1
        self.emit("refused", lr.cfg.id, seq, f"server:partial:{bad.name}")

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
        bodies = registration_bodies(self.site, self.loops)
        if bodies:
            await asyncio.to_thread(register_loops, self.site, bodies)
        self._registered = True


def _policy_nodes(loops) -> list[tuple[Item, str]]:
    """The nodes of the values the write policy judges by, of each loop."""
    return [
        (Item(lr.index, f), node)
        for lr in loops
        for f, node in lr.cfg.nodes().items()
        if f in POLICY_FIELDS
    ]
