"""The OPC UA gateway: PID blocks of a DCS on one side, the pitune bus on the other.

Samples. Every notification of a loop's PV (its source timestamp) makes one sample:
``t`` is that timestamp (seconds since the Unix epoch; the server timestamp if the
server gives no source timestamp; a repeated ``t``, or an older one among a
(re)connect's first PV values, makes no sample; other older ones do, in the order
received: the source clock stepped back), ``sp``, ``op`` and the rest are the values in force
at that time (notifications of one publish are applied in source-timestamp order),
``kp``/``ki`` the block's gains converted to the parallel form, ``auto`` whether the mode
is one of the map's auto values, ``saturated`` whether an output-at-limit flag is set.
Samples go out batched (``SampleBatch`` every ``batch_interval_s``) with
``CongestionControl.BLOCK``, on ``{prefix}/gateways/{gateway_id}/samples`` with a
``gateway_id`` (protocol revision 4: a per-gateway Zenoh user may publish there only;
:func:`~service.gateways.opcua.register.prepare` checks at start that the loops are
registered with it), else (or with ``shared_samples_key``) on ``{prefix}/samples``.
While no tuner's liveliness token is present (tuner down, Zenoh router or link down),
and on the gateway's key while no tuner subscribes to it (a cluster between two owners
of the gateway, a tuner before revision 4), they are held in a buffer of at most
``buffer_max_samples`` (the oldest are dropped beyond, and counted) and sent when a tuner
is back, still in order per loop and paced under the tuner's flood limit
(:mod:`service.gateways.backlog`; ``[tuner] max_sample_rate_hz``).

Gains. Updates come through :class:`service.gateways.base.Gateway` (sequence rule, batched
gains, state query whenever a tuner's token appears). An ``auto`` update becomes the
loop's pending write (a newer one replaces it); it is written, in the block's own form,
only when all hold at that moment:

* the OPC UA session is up;
* the loop is in auto (mode node's value among ``auto_values``): else it is dropped;
* tuning is enabled (the tuning-enable node is true, or the map's flag): else dropped;
* the values are within the map's hard limits: else dropped (never clipped);
* the block's gains convert to the parallel form (a negative gain does not): else dropped;
* the block's gains are still those the update follows (:meth:`LoopRuntime.base`: for a
  state reply, those of the gateway's last finished update, none after a start): else
  an operator (or the DCS) changed them meanwhile and the update is stale: dropped;
* ``min_write_interval_s`` has passed since the loop's last write: else it waits.

A write is one request for all due loops, then a read-back of the same nodes; the
values read back become the block's gains in force, reported in the next samples.
A refused write (bad status, or a fault of the whole request) or one the block changed
(read-back differs) is logged and counted; the tuner sees the gains in force in the
samples and adopts them. A read-back that is not a Good number is "unverified": the
gains in force are unknown until notified (:mod:`service.gateways.opcua.writes`).

``applied_seq`` (protocol revision 2): once the gateway is finished with an update --
written, found already in force, or refused (by the policy above or by the server) --
the loop's samples carry its seq, so the gains they report are known to be the block's
after that update: equal to it, the update is confirmed; different, they are an
operator's or the block's choice and the tuner adopts them. While an update waits (no
session, rate limit) the samples carry the previous seq (0 if none of the epoch), and
the tuner, seeing the gateway lag, takes nothing for an operator's change.
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

from service.gateways.backlog import Backlog
from service.gateways.base import SAMPLE_CONGESTION, Gateway
from service.gateways.opcua.client import Change, Item, LinkLost, OpcUaLink, now_epoch
from service.gateways.opcua.loops import Event, LoopRuntime, Pending, number
from service.gateways.opcua.register import prepare
from service.gateways.opcua.sitemap import SiteMap
from service.gateways.opcua.writes import GainWriter
from service.gateways.registration import RegistrationError
from service.wire.protocol import ENCODING, MAX_BATCH, Keys, Mode

log = logging.getLogger("pitune.gateway.opcua")
TICK_S = 0.02
"""How often gains are taken from the bus and due writes made."""
SESSION_STABLE_S = 10.0
"""A session lost sooner than this after it opened (a server that drops it at each write,
or closes sessions it cannot serve) is one outage with the failed connects: the
reconnect delay keeps doubling. Each reconnect re-reads and re-monitors every node
(10-20 s for 1,000 loops), so a server that drops sessions at once must not get one per
``reconnect_min_s``."""
UNHEARD_WARN_S = 10.0
"""Samples held this long for want of a subscriber on the gateway's samples key, while a
tuner is up, are logged as a WARNING: a cluster's owner change takes a second or two,
a tuner of revision 3 or earlier never subscribes."""
REPLAYED_PV_VALUES = 2
"""A (re)connect's first PV values, its initial read and its monitored item's first
notification, are the server's current value: one already sent before the loss, or (a
restarted server) a value stamped before it. Older than the loop's last sample, they
are not sent; later older ones are (the source clock stepped back)."""


class OpcUaGateway(GainWriter):
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
        self.outbox = Backlog(site.bus.buffer_max_samples, site.tuner.max_sample_rate_hz)
        self.link: OpcUaLink | None = None
        self.events: asyncio.Queue[Event] | None = asyncio.Queue() if record_events else None
        self.history: list[Event] = []
        """Every event, when recording (tests)."""
        self.status_interval_s = status_interval_s
        self._registered = site.tuner.register_url is None
        self._last_flush = 0.0
        gateway = site.bus.samples_gateway
        self.samples_key = self.keys.gateway_samples(gateway) if gateway else self.keys.batch
        self._unheard_since: float | None = None
        """Since when samples wait for a subscriber on the gateway's key (tuner up)."""
        self._unheard_told = False
        self.bus = Gateway(session, list(self.by_id), self.keys, gateway_id=site.bus.gateway_id)
        try:
            self.publisher = session.declare_publisher(
                self.samples_key, encoding=ENCODING, congestion_control=SAMPLE_CONGESTION
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
                for lr in self.loops:
                    lr.replays = REPLAYED_PV_VALUES
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
                delay = await _back_off(stop, delay, server.reconnect_max_s)
                continue
            up = time.monotonic()
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
            if time.monotonic() - up >= SESSION_STABLE_S:
                delay = server.reconnect_min_s  # reconnect at once
            else:
                log.warning("OPC UA session lasted %.1f s; reconnect in %.1f s",
                            time.monotonic() - up, delay)  # fmt: skip
                delay = await _back_off(stop, delay, server.reconnect_max_s)

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
        replay, lr.replays = lr.replays > 0, max(lr.replays - 1, 0)
        last = lr.last_t
        if last is not None and (t == last or (replay and t < last)):
            self.stats["samples_not_newer"] += 1  # re-delivered (a reconnect, a repeat)
            return
        sp, pv = number(lr.values.get("sp")), number(lr.values.get("pv"))
        if sp is None or pv is None:
            self.stats["samples_incomplete"] += 1
            return
        if last is not None and t < last:  # sent on: the tuner takes 10 increasing ones
            self.stats["samples_older"] += 1  # for a new plant clock (docs/protocol.md)
            log.warning("%s: source clock stepped back %.3f s (t %.3f after %.3f)",
                        lr.cfg.id, last - t, t, last)  # fmt: skip
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
        lost = self.outbox.append(lr.cfg.id, sample)
        if lost is not None:
            self.stats[lost] += 1
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
        tuner = "down" if not self.bus.tuner_up else "up" if self._unheard_since is None else (
            f"up, none subscribed to {self.samples_key}")  # fmt: skip
        return (f"{len(self.loops)} loops, OPC UA {'up' if self.link else 'down'}, tuner "
                f"{tuner}; samples {s['samples']} "
                f"(published {s['published']}, buffered {len(self.outbox)}, dropped "
                f"{s['samples_dropped']}, cut {s['samples_cut']}, not newer "
                f"{s['samples_not_newer']}, older "
                f"{s['samples_older']}); writes {s['written']}, unverified "
                f"{s['unverified']}, refused "
                f"{sum(v for k, v in s.items() if k.startswith('refused'))}; gains dropped "
                f"for an epoch ahead of this clock {self.bus.inbox.implausible}")  # fmt: skip

    def report(self) -> dict:
        """Counters and write latencies (s, update taken off the bus to verified write)."""
        lat = sorted(self.latencies)

        def pct(q: float) -> float | None:
            return lat[min(len(lat) - 1, int(q * len(lat)))] if lat else None

        counters = {**self.stats, "implausible_epochs": self.bus.inbox.implausible}
        return {"loops": len(self.loops), "counters": counters,
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
            lr.pending = Pending(update, now, lr.base(update))
            self.stats["received"] += 1
            self.emit("received", lr.cfg.id, update.seq, update.source.value)

    def _flush(self, *, force: bool = False) -> None:
        if not self.outbox or not self.bus.tuner_up or not self._registered:
            return  # held: no tuner to take them, or it does not know the loops yet
        if not self._heard():
            return  # held: no owner of the gateway subscribes (a cluster's handover)
        now = time.monotonic()
        if not force and now - self._last_flush < self.site.bus.batch_interval_s:
            return
        self._last_flush = now
        due = self.outbox.take(now)
        for i in range(0, len(due), MAX_BATCH):
            chunk = due[i : i + MAX_BATCH]
            try:
                self.publisher.put(orjson.dumps({"v": 1, "samples": chunk}))
            except zenoh.ZError as exc:
                self.outbox.put_back(due[i:])
                log.warning("publishing samples failed: %s", exc)
                return
            self.stats["published"] += len(chunk)

    def _heard(self) -> bool:
        """Whether a tuner subscribes to the samples key. Always on ``{prefix}/samples``
        (every tuner subscribes there; nothing changed for it). On the gateway's key only
        the member of a cluster owning the gateway does, once it has the loops: before,
        Zenoh would drop the batch on this side, so it stays in the buffer."""
        if self.site.bus.samples_gateway is None or self.publisher.matching_status.matching:
            if self._unheard_told:
                log.warning("samples flow again on %s", self.samples_key)
            self._unheard_since, self._unheard_told = None, False
            return True
        now = time.monotonic()
        if self._unheard_since is None:
            self._unheard_since = now
        elif not self._unheard_told and now - self._unheard_since >= UNHEARD_WARN_S:
            self._unheard_told = True
            log.warning("samples held for %.0f s: a tuner is up but none subscribes to %s "
                        "(a cluster with no member owning gateway %s yet, or a tuner before "
                        "protocol revision 4)", now - self._unheard_since, self.samples_key,
                        self.site.bus.samples_gateway)  # fmt: skip
        return False

    # -- registration ----------------------------------------------------------------
    async def _register(self) -> None:
        await asyncio.to_thread(prepare, self.site, self.loops)
        self._registered = True


async def _back_off(stop: asyncio.Event, delay: float, longest: float) -> float:
    """Wait ``delay`` (or until ``stop``); the next delay, doubled up to ``longest``."""
    with contextlib.suppress(TimeoutError):
        await asyncio.wait_for(stop.wait(), delay)
    return min(delay * 2.0, longest)
