"""The tuner daemon's core: the tuning engine wired to the store and the bus, with one
worker thread.

:class:`Tuner` is the daemon minus its HTTP server: ``start()`` restores the loops from
the store into the engine and opens the bus, ``stop()`` closes the bus, drains what was
received, snapshots and closes the store. The admin API calls its methods; tests can
run it in-process.

The worker drains the bus queue in batches: sample messages are decoded
(:mod:`service.wire.decode`) and handed to the engine (:mod:`service.engine`), which
says which loops fall due; due loops are stepped in one batched agent call at the end
of the batch (earlier if a due loop receives another sample). Gains and audit rows are
committed to the store (as one journal row per step batch, see
:mod:`service.daemon.store`) before the gains messages go out: one message per loop, or
one per gateway for loops registered with a gateway. The worker applies the journal to
the store's tables while it has nothing else to do. Nothing about tuning is decided
here: this module owns lifecycle, persistence policy and publishing.

Accounting: every sample received ends in exactly one counter, accepted (the loops'
``samples``) or rejected (by reason), and ``pitune_samples_received_total`` is counted
*after* the samples are judged, so once it reaches N those N are in their counters. A
message dropped unread (the inbox full: ``overload``; over
:data:`~service.wire.protocol.MAX_MESSAGE_BYTES`: ``too_large``) counts as one received
and one rejected sample whatever it held: not reading it is the point of dropping it.

Upkeep between messages (snapshots, the journal, retention):
:class:`service.daemon.upkeep.Upkeep`.

Committing a step and then publishing it: :class:`service.daemon.delivery.Delivery`.

"""

from __future__ import annotations

import contextlib
import logging
import math
import queue
import threading
import time

import torch
import zenoh

from service.agent.model import Agent, load_agent, untrained_agent
from service.daemon.admin import LoopAdmin, freeze_survivors
from service.daemon.bus import Bus, Inbox, Item, Kind
from service.daemon.clock import Clock
from service.daemon.delivery import Delivery
from service.daemon.handoff import Handoff
from service.daemon.heartbeat import Heartbeat
from service.daemon.lanes import LANE_DRAIN_S, Lane
from service.daemon.metrics import Metrics, RateLimitedLog
from service.daemon.ownership import Ownership
from service.daemon.pacing import LINGER_BYTES, LINGER_S, Pacer
from service.daemon.queries import StateQueries
from service.daemon.recent import Recent
from service.daemon.settings import UNTRAINED, Settings
from service.daemon.slotmemo import SlotMemo
from service.daemon.snapwriter import SnapshotWriter
from service.daemon.store import Store
from service.daemon.upkeep import Upkeep
from service.engine.engine import TuningEngine
from service.engine.site import SiteDefaults
from service.engine.updates import StepResult
from service.wire.decode import Rejection, decode_batch, decode_singles, joined
from service.wire.protocol import RejectReason

log = logging.getLogger("pitune.tuner")
_STOP = (None, "", None)
_WAKE = (None, "wake", None)
"""Queued to have the worker compute its wait again (a commit failed on an API thread:
the worker, asleep until its next snapshot, retries within COMMIT_RETRY_S instead)."""
FLUSH_AFTER_S = 0.002
"""Longest a due loop waits for more due loops to join its batch while a backlog drains."""


def load_configured_agent(settings: Settings) -> Agent:
    """The agent the settings ask for; the untrained one only with a loud warning."""
    if settings.agent_weights == UNTRAINED:
        log.warning("using an UNTRAINED agent (agent_weights=untrained): updates are noise")
        return untrained_agent(0)
    if settings.agent_weights:
        return load_agent(settings.agent_weights)
    try:
        return load_agent()
    except FileNotFoundError:
        log.warning(
            "\n%s\nNO TRAINED AGENT WEIGHTS FOUND (service/models/pitune_agent.pt): falling back "
            "to an UNTRAINED agent whose gain updates are noise. Pass --agent-weights.\n%s",
            "!" * 78,
            "!" * 78,
        )
        return untrained_agent(0)


SINGLES_GROUP = 2000
"""Most single-sample messages ingested in one vectorised pass."""
BATCHES_GROUP_BYTES = 1 << 20
"""Most payload bytes of batch messages ingested in one pass (~25,000 samples of a
gateway's batches): a backlog of batches costs the engine's per-pass work once, not once
a message (at 30,000 loops in batches of 75: ~0.6 ms a pass against ~2 µs a sample)."""


def _group(items: list[Item]):
    """The items as (kind, payload), with runs of single-sample messages and runs of batch
    messages as (Kind.sample or Kind.batch, [(key, payload), ...])."""
    run: list[tuple[str, bytes]] = []
    run_kind, size = None, 0
    for kind, key, payload in items:
        if run and (
            kind is not run_kind or len(run) >= SINGLES_GROUP or size >= BATCHES_GROUP_BYTES
        ):
            yield run_kind, run
            run, size = [], 0
        if kind is Kind.sample or kind is Kind.batch:
            run.append((key, payload))
            run_kind = kind
            size += len(payload) if kind is Kind.batch else 0
        else:
            yield kind, payload
    if run:
        yield run_kind, run


class Tuner(StateQueries, Ownership, LoopAdmin, Upkeep, Delivery):
    def __init__(self, settings: Settings, agent: Agent | None = None) -> None:
        self.settings = settings
        self.clock = Clock(settings.clock_speed)
        """Every wall time the tuner keeps or acts on (see :mod:`service.daemon.clock`)."""
        self.keys = settings.keys
        self.metrics = Metrics()
        self.heartbeat = Heartbeat(self.metrics.registry)
        self.agent = agent if agent is not None else load_configured_agent(settings)
        self.engine = TuningEngine(
            self.agent,
            max_rate_hz=settings.max_sample_rate_hz,
            inference_workers=settings.inference_workers,
            inference_precision=settings.inference_precision,
            on_reject=self._on_reject,
            monitoring=settings.monitoring,
            clock=self.clock.steady,
            site=SiteDefaults(
                settings.identify_hinted_loops, settings.auto_rescale, settings.identify_cpu_share
            ),
        )
        self.table = self.engine.table
        self.handoff = Handoff(self.table.lock)
        """Turns at the table's lock for the cluster's thread between the worker's messages."""
        self.slot_memo = SlotMemo(self.table)
        """The slots of a gateway's batches (:meth:`_gateway_rows`)."""
        self.recent = Recent(table=self.table)
        """Recent samples and published gains of each loop, for the console's trends."""
        self._skipped = 0
        self.inbox = Inbox(settings.queue_size, settings.queue_bytes)
        self.pacer = Pacer()
        """The worker's busy share: a busy worker waits for more batches (pacing.py)."""
        self.epoch: int | None = None
        """The store's epoch of this run (set by :meth:`start`)."""
        self.epochs: dict[str, tuple[int, int]] = {}
        """Loop id -> (epoch, seq) of its last committed gains (Ownership.epoch_of)."""
        self.lanes: dict[str | None, Lane] = {}
        self._lanes_lock = threading.Lock()
        self._parked: dict[str, list[tuple[float, float, zenoh.Query]]] = {}
        """State queries with ``after_t`` waiting for their loop's sample: loop id ->
        [(after_t, monotonic deadline, query)]."""
        self.queries_dropped = 0
        """State queries dropped unanswered because the inbox was full."""
        self._next_prune = self.clock.monotonic()  # a first pass when the worker is idle
        self.pruned = 0
        """Audit rows deleted by the retention policy since start."""
        self.metrics.totals(
            {
                "pitune_state_queries_dropped": (
                    "State queries dropped unanswered (input queue full).",
                    lambda: self.queries_dropped,
                ),
                "pitune_gains_superseded": (
                    "Gains messages replaced in a blocked lane by a newer one of their loop.",
                    lambda: self.superseded,
                ),
                **self.upkeep_totals(),
                "pitune_gains_fenced": (
                    "Committed gains messages not published: this member's leases may have "
                    "run out (it was paused); the loops' new owner sends each loop's last "
                    "committed message again if the plant applies it (pitune_gains_resent).",
                    lambda: self.gains_fenced,
                ),
                "pitune_gains_resent": (
                    "Committed gains messages sent again when this member took their loops "
                    "over: each loop's last, if the plant applies it (its previous owner may "
                    "not have published it); gateways that had it drop it by (epoch, seq).",
                    lambda: self.gains_resent,
                ),
                "pitune_samples_foreign": (
                    "Samples of loops another member of the cluster owns, left to it.",
                    lambda: self.foreign_samples,
                ),
                "pitune_queue_bytes": (
                    "Payload bytes waiting in the input queue.",
                    lambda: self.inbox.nbytes,
                ),
                "pitune_identify_owed_waiting": (
                    "Loops owed a model assessment, waiting for the identification budget "
                    "(identify_cpu_share).",
                    lambda: self.table.fits.waiting,
                ),
                "pitune_identify_deferred": (
                    "Model assessments deferred for the identification budget.",
                    lambda: self.table.fits.deferred,
                ),
                "pitune_identify_fit_seconds": (
                    "CPU seconds the model fits took (identification).",
                    lambda: self.table.fits.spent_s,
                ),
            }
        )
        self.store: Store | None = None
        self.bus: Bus | None = None
        self._worker: threading.Thread | None = None
        self._snapshot_todo: list[str] = []
        self._held: list[StepResult] = []
        """Steps whose commit failed: published once a commit succeeds."""
        self._store_failing_since: float | None = None
        self._store_error, self._retry_at = "", 0.0
        self._failure_log = RateLimitedLog(log)

    # -- lifecycle --------------------------------------------------------------------
    def start(self) -> Tuner:
        """Open the store and restore its loops (with a PostgreSQL store: join the
        cluster, which loads the loops of the shards this tuner wins), then the bus."""
        if self.settings.postgres:
            from service.daemon.cluster import Cluster
            from service.daemon.store_pg import PgStore

            self.store = PgStore(self.settings.db_path)
            self.cluster = Cluster(self, self.settings.db_path)
            self.deleted_here = set()
            self.snapshot_writer = SnapshotWriter(self._writer_snapshot)
        else:
            self.store = Store(self.settings.db_path)
        wall = self.clock.wall()
        self.epoch = self.store.next_epoch(wall, "reset" if self.settings.epoch_reset else "refuse")
        self.sync_hold()  # a hold set before this start: in force before any sample
        if self.cluster is None:
            with self.table.lock:
                self._restore_many(self.store.load(), wall)
                self.metrics.set_loop_counts(self.table.mode_counts())
            self.metrics.loops_unloadable.set(len(self.store.unloadable))
            log.info("restored %d loops from %s", len(self.table), self.store.location)
        # Everything allocated so far (modules, torch, the restored table) lives as long as
        # the process: keep it out of the cyclic GC's full collections (~100 ms each).
        freeze_survivors()
        self.bus = Bus(self.settings, self.inbox, self._overload, self.metrics.bus_connected.set)
        try:
            self.bus.open()
        except BaseException:
            if self.snapshot_writer is not None:
                self.snapshot_writer.close()
            self.store.close()
            raise
        self._worker = threading.Thread(target=self._run, name="pitune-worker", daemon=True)
        self._worker.start()
        if self.cluster is not None:
            self.cluster.start()
            self.cluster.ready.wait(timeout=self.cluster.lease_s)
        log.info(
            "tuner %s (epoch %d) up: prefix %r, listen %s, connect %s, inference %s",
            self.settings.instance_id,
            self.epoch,
            self.settings.key_prefix,
            self.settings.zenoh_listen,
            self.settings.zenoh_connect,
            self.table.inference_precision,
        )
        return self

    def stop(self) -> None:
        """Stop receiving, handle what was already received, publish what is committed
        (at most LANE_DRAIN_S), close the bus, snapshot, leave the cluster (its loops
        move to the other members at once), close the store."""
        if self.cluster is not None:
            self.cluster.halt()
        if self.bus is not None:
            self.bus.stop_receiving()
        if self._worker is not None:
            self.inbox.put(_STOP)
            self._worker.join(timeout=30.0)
            self._worker = None
        deadline = time.monotonic() + LANE_DRAIN_S
        for lane in list(self.lanes.values()):
            if not lane.drain(max(0.0, deadline - time.monotonic())):
                log.warning("gains for %s not all published at stop", lane.gateway or "loops")
        if self.bus is not None:
            self.bus.close()
        for lane in list(self.lanes.values()):
            lane.close(timeout=1.0)
        if self.store is not None:
            self.snapshot()  # every loop: what the snapshot writer had queued is older
            if self.snapshot_writer is not None:
                self.snapshot_writer.close()
            if self.cluster is not None:
                self.cluster.leave()
            self.store.close()
            self.store = None
        log.info("tuner %s stopped", self.settings.instance_id)

    def __enter__(self) -> Tuner:
        return self.start()

    def __exit__(self, *exc: object) -> None:
        self.stop()

    @property
    def alive(self) -> bool:
        return self._worker is not None and self._worker.is_alive()

    @property
    def worker_stuck(self) -> str | None:
        """Why the worker looks stuck: in one iteration past ``store_failure_exit_s``."""
        age, bound = self.heartbeat.age(), self.settings.store_failure_exit_s
        if age <= bound:
            return None
        return f"worker stuck in one iteration for {age:.0f} s (> store_failure_exit_s {bound:g} s)"

    @property
    def bus_ready(self) -> bool:
        """Samples can arrive and gains can leave: the session is open and, if this tuner
        connects to routers or peers, one is connected (see :attr:`Bus.connected`)."""
        return self.bus is not None and self.bus.connected

    @property
    def ready(self) -> bool:
        """The worker runs and the bus is ready (``/readyz``)."""
        return self.alive and self.bus_ready

    # -- worker -----------------------------------------------------------------------
    def _run(self) -> None:
        # Thread counts of OpenMP and MKL (torch's tanh/sigmoid go through MKL VML) are
        # per thread: set them where inference runs, or MKL forks a team of threads per op
        # that, on a busy box, waits for CPU time (a step of 5 loops took ~90 ms).
        torch.set_num_threads(self.settings.inference_threads)
        interval = self.settings.snapshot_interval_s
        next_snapshot = time.monotonic() + interval
        while True:
            self.heartbeat.idle()
            try:
                if self._store_failing_since is not None:  # until the next retry
                    wait = self._retry_at - time.monotonic()
                elif self._prune_todo:
                    wait = 0.0
                else:  # the next snapshot, or its next chunk (paced), or retention pass
                    at = self._snapshot_at if self._snapshot_todo else next_snapshot
                    wait = min(at - time.monotonic(), self.clock.until(self._next_prune))
                    if self.store.journal_rows:  # now, unless its writes fail (retry_at)
                        wait = min(wait, self._write_retry_at - time.monotonic())
                if self._parked:  # the earliest after_t query to answer anyway
                    first = min(d for q in self._parked.values() for _, d, _ in q)
                    wait = min(wait, first - time.monotonic())
                owed = self.table.fits.wait_s(self.clock.wall())  # assessments owed
                if owed is not None and self._store_failing_since is None:
                    wait = min(wait, owed)
                items = [self.inbox.get(timeout=max(0.0, wait))]
            except queue.Empty:
                items = []
            self.heartbeat.busy()
            if items:
                linger = LINGER_S if self.pacer.lingering else 0.0
                self.inbox.more(items, self.settings.max_batch, linger, LINGER_BYTES)
            stop = any(item is _STOP for item in items)
            began = time.perf_counter()
            try:
                self._handle([item for item in items if item is not _STOP and item is not _WAKE])
                if self._store_failing_since is not None and not stop:
                    continue  # no journal or snapshot work on a failing store
                self._apply_journal()
                if self.inbox.empty() and self.table.fits.wait_s(self.clock.wall()) == 0.0:
                    self._identify_idle()
                if stop:
                    self.snapshot()
                elif self._snapshot_todo and time.monotonic() >= self._snapshot_at:
                    self._snapshot_some()
                elif not self._snapshot_todo and time.monotonic() >= next_snapshot:
                    next_snapshot = time.monotonic() + interval
                    self._start_snapshot(interval)
                elif self.inbox.empty() or self._prune_overdue():
                    self._retain()
            except Exception:
                log.exception("worker iteration failed; continuing")
            self.pacer.worked(time.perf_counter() - began)
            if stop:
                return

    def _wake(self) -> None:
        if self._worker is not None and threading.current_thread() is not self._worker:
            self.inbox.put(_WAKE)

    def _handle(self, items: list[Item]) -> None:
        self.metrics.queue_depth.set(self.inbox.qsize())
        if not items:
            if self._store_failing_since is not None:
                with self.table.lock:
                    self._commit(None)  # retry, even without traffic
            if self._parked:
                with self.table.lock:
                    self._answer_parked()
            return
        wall = self.clock.wall()
        engine = self.engine
        flush_at = math.inf
        with engine.lock:
            engine.stepping = self._store_failing_since is None
            for kind, payload in _group(items):
                self.handoff.let_in()
                if kind is Kind.query or kind is Kind.gateway_query:
                    self._flush(wall)  # the reply reflects every sample handled before it
                    self.answer(payload, gateway=kind is Kind.gateway_query)
                    continue
                if kind is Kind.sample:
                    decoded = self._own_rows(
                        decode_singles([(self.keys.loop_id(k), p) for k, p in payload])
                    )
                else:  # the shared samples key, or one gateway's (revision 4)
                    decoded = joined([self._gateway_rows(decode_batch(p), k) for k, p in payload])
                self._ingest(decoded, wall)
                # received last: once it reaches N, those N samples are in their counters
                self.metrics.samples_received.inc(decoded.received)
                # Batch the due loops, but never hold one back for long behind a backlog.
                if not engine.due:
                    flush_at = math.inf
                elif flush_at == math.inf:
                    flush_at = time.perf_counter() + FLUSH_AFTER_S
                elif time.perf_counter() >= flush_at:
                    self._flush(wall)
                    flush_at = math.inf
            self._flush(wall)
            self._commit(None)
            if self._parked:
                self._answer_parked()

    def _ingest(self, decoded, wall: float) -> None:
        """Samples into the engine. Should the engine fail (a defect), the samples it had
        not judged yet are counted as rejected ``internal`` and the worker goes on with
        the next message: one bad message never takes the others with it."""
        engine, tb = self.engine, self.table
        self.recent.safely(self.recent.add_samples, decoded)  # the console's trends
        before = sum(engine.rejected.values()) + int(tb.n_samples.sum())
        try:
            for result in engine.ingest_decoded(decoded, wall=wall):
                self._stepped(result)
        except Exception as exc:
            judged = sum(engine.rejected.values()) + int(tb.n_samples.sum()) - before
            lost = max(decoded.received - judged, 0)
            log.exception(
                "handling %d samples failed; %d counted as internal", decoded.received, lost
            )
            if lost:
                self.metrics.samples_rejected.labels(RejectReason.internal.value).inc(lost)
                engine.rejected[RejectReason.internal] += lost
            del exc

    def _on_reject(self, rejection: Rejection) -> None:
        self.metrics.reject(rejection.reason, rejection.loop_id, rejection.detail, rejection.count)

    def _flush(self, wall: float) -> None:
        result = self.engine.flush(wall)
        if self.engine.skipped != self._skipped:
            # A step could be neither committed nor published, and the next one would
            # start from gains the gateway never got: skipped until the store works again.
            self.metrics.steps_skipped.inc(self.engine.skipped - self._skipped)
            self._skipped = self.engine.skipped
        if result is not None:
            self._stepped(result)

    def _identify_idle(self) -> None:
        """Model assessments the identification budget owes, made while no samples wait
        (:mod:`service.engine.fit_budget`); their decisions published like any."""
        with self.engine.lock:
            for result in self.engine.catch_up(self.clock.wall()):
                self._stepped(result)
            self._commit(None)

    def _stepped(self, result: StepResult) -> None:
        self.metrics.inference_seconds.observe(result.inference_s)
        self.metrics.inference_batch_size.observe(len(result))
        self._commit(result)

    def _overload(self, item: Item, why: str) -> None:
        """A message the bus callback did not queue (a Zenoh thread: never blocks)."""
        kind, key = item[0], item[1]
        if kind is Kind.query or kind is Kind.gateway_query:
            self.queries_dropped += 1  # not a sample: no sample counter
            self._failure_log.warning("query", f"input queue full: state query {key!r} dropped")
            with contextlib.suppress(zenoh.ZError):
                item[2].drop()  # the querier gets no reply rather than waiting its timeout
            return
        reason = RejectReason.too_large if why == "too_large" else RejectReason.overload
        detail = f"{kind.name} message dropped unread ({why})"
        self.metrics.reject(reason, None, detail)
        self.metrics.samples_received.inc()  # after its counter, as in _handle
