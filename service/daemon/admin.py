"""The tuner's admin operations, which the REST API calls: list, view, register, patch,
reset, identify, delete loops, and read their history.

:class:`LoopAdmin` is a part of :class:`~service.daemon.tuner.Tuner` (a mixin). Every
change is committed to the store (with its audit row) before the engine's table takes
it, under the table's lock, so the worker never sees a change the store lacks.
"""

from __future__ import annotations

import collections
import contextlib
import gc
from collections.abc import Callable

import orjson

from service.daemon.holds import PlantHolds
from service.daemon.schemas import HistoryPage, LoopsPage
from service.daemon.shards import shard_of
from service.daemon.verdicts import SCAN, annotate
from service.engine import views
from service.engine.audit import AuditRow, audit_row
from service.engine.config import LoopConfig, LoopView
from service.engine.figures import Performance
from service.engine.patch import LoopPatch
from service.engine.updates import StepResult

NAMED_TAKEN = 5
"""Taken ids a registration's 409 names at most (with their gateways)."""
METRICS_LOCK_WAIT_S = 1.0
"""Longest a scrape waits for the loop table (the worker holds it for milliseconds)."""


class Conflict(Exception):
    """The loop already exists, or the operation conflicts with the loop's state
    (``gateways``: a registration's taken ids -> their loops' gateways, :func:`_taken`)."""

    def __init__(self, detail: str, gateways: dict[str, str | None] | None = None) -> None:
        super().__init__(detail)
        self.gateways = gateways or {}


class UnknownLoop(LookupError):
    """No loop with this id."""


class OwnedElsewhere(LookupError):
    """Another member of the cluster owns the loop (the API forwards it there)."""


class StoreUnavailable(Exception):
    """The store fails to commit: the change would be neither recorded nor published."""


def freeze_survivors() -> None:
    """Move the objects that survived so far out of the cyclic GC's reach.

    Under a stream of 10,000 samples/s the GC runs full collections every few seconds;
    each scans every long-lived tracked object (modules, caches the HTTP stack builds on
    its first requests, ...): ~100 ms per collection, a stall of the sample stream. The
    tuner freezes what exists at start-up, after a bulk registration and after every
    periodic snapshot, so the full collections the sample stream triggers only see
    recent objects. Frozen objects are still freed by reference counting, and a full
    collection runs first (cheap: it scans only what is not frozen yet), so no cyclic
    garbage is frozen.
    """
    gc.collect()
    gc.freeze()


class LoopAdmin(PlantHolds):
    """Admin operations on the engine's table and the store (mixed into the Tuner), the
    plant-wide hold's among them."""

    # -- admin operations (the REST API) ----------------------------------------------
    def loop_ids(self) -> list[str]:
        with self.table.lock:
            return list(self.table.slot_of)

    @contextlib.contextmanager
    def _committing(self):
        """A change the store must commit before the table takes it: StoreUnavailable
        (503) while commits fail, or when this one cannot be committed (database locked,
        disk full); integrity errors pass, for :func:`_taken_in_store`."""
        if self.store_failure is not None:
            raise StoreUnavailable(self.store_failure)
        try:
            yield
        except self.store.integrity_errors:
            raise
        except self.store.commit_errors as exc:
            detail = f"the store cannot commit ({self.store.location}): {exc}"
            raise StoreUnavailable(detail) from None

    def _committed(self, result: StepResult | None) -> None:
        """An operator's decision committed (then published), or StoreUnavailable (503)
        if its commit failed: it is held, and goes out only if the store commits again
        before the tuner gives up (``store_failure_exit_s``), so it is not reported done."""
        self._commit(result)
        if self.store_failure is not None:
            raise StoreUnavailable(
                f"{self.store_failure}; the change is held, not committed: it is published "
                "if the store commits again, and lost if the tuner exits first"
            )

    def _known(self, loop_id: str) -> None:
        if loop_id not in self.table.slot_of:
            raise UnknownLoop(loop_id)

    def refresh_status_counts(self) -> None:
        """Loops per status into the metrics (statuses change with time: done per scrape).
        Waits at most METRICS_LOCK_WAIT_S for the table: a worker stuck holding it (a
        blocked store statement) must not hang the scrape that would show it stuck; the
        gauges keep their last values then."""
        if not self.table.lock.acquire(timeout=METRICS_LOCK_WAIT_S):
            return
        try:
            counts = self.table.status_counts(self.clock.wall())
            monitor = views.monitor_summary(self.table)
        finally:
            self.table.lock.release()
        self.metrics.set_status_counts(counts)
        self.metrics.set_monitor(*monitor)

    def view(self, loop_id: str) -> LoopView:
        with self.table.lock:
            self._known(loop_id)
            return self.table.view(loop_id, self.clock.wall())

    def views(self, offset: int, limit: int) -> LoopsPage:
        """A page of loops in registration order; parsed outside the table lock."""
        with self.engine.lock:
            total = len(self.engine)
            raw = self.engine.raw_views(offset, limit)
        items = [view.parse() for view in raw]
        return LoopsPage(items=items, total=total, offset=offset, limit=limit)

    def register(self, config: LoopConfig, actor: str = "api") -> LoopView:
        """OwnedElsewhere in a cluster where another member owns the loop's shard; ``actor``
        (the admin token's ``api``, or ``gateway:<id>``) in the audit row's detail."""
        wall = self.clock.wall()
        self._claim([config])
        if self.cluster is not None and not self.cluster.owns(shard_of(config.id, config.gateway)):
            raise OwnedElsewhere(config.id)
        with self.table.lock:
            if config.id in self.table.slot_of:
                raise _taken(self._gateways([config.id]))
            self._insert([config], wall, actor)
            return self.table.view(config.id, wall)

    def register_many(self, configs: list[LoopConfig], actor: str = "api") -> list[str]:
        """Register several loops at once, all or none (Conflict if any id is taken,
        ValueError if one is given twice)."""
        wall = self.clock.wall()
        ids = [c.id for c in configs]
        twice = sorted(i for i, n in collections.Counter(ids).items() if n > 1)
        if twice:
            raise ValueError(f"loop ids given twice in the request: {twice[:5]!r}")
        self._claim(configs)
        with self.table.lock:
            taken = [i for i in ids if i in self.table.slot_of]
            if taken:
                raise _taken(self._gateways(taken[:NAMED_TAKEN]))
            self._insert(configs, wall, actor)
        freeze_survivors()
        return ids

    def _gateways(self, ids: list[str]) -> dict[str, str | None]:
        """The gateway of each of these registered loops (None: registered without one)."""
        return {i: self.table.gateways[self.table.slot_of[i]] or None for i in ids}

    def _insert(self, configs: list[LoopConfig], wall: float, actor: str) -> None:
        """Store and add new loops, each continuing the seq of an earlier loop of its id.
        In a cluster, loops of shards another member owns are only stored: their owner
        loads them when the commit's notification reaches it."""
        last = self.store.last_seqs([c.id for c in configs])
        seqs = [last.get(c.id, 0) for c in configs]
        audit = [_registered(c, wall, seq, actor) for c, seq in zip(configs, seqs, strict=True)]
        shards = [shard_of(c.id, c.gateway) for c in configs]
        with self._committing(), _taken_in_store(self.store, [c.id for c in configs]):
            self.store.insert_loops(configs, audit, seqs)
        owned = [
            i for i, shard in enumerate(shards) if self.cluster is None or self.cluster.owns(shard)
        ]
        self.engine.add_many([configs[i] for i in owned], seq=[seqs[i] for i in owned], wall=wall)
        if self.cluster is not None:  # an id registered again: its messages went out before
            floor = self._floor([i for i in owned if seqs[i]])
            for i in owned:
                held = self.cluster.held[shards[i]]
                self.cluster.adopted(shards[i], held, [configs[i].id], floor if seqs[i] else None)
        self.metrics.set_loop_counts(self.table.mode_counts())

    def patch(self, loop_id: str, patch: LoopPatch, actor: str = "api") -> LoopView:
        """ValueError if the patch makes the bounds inconsistent; ``actor`` (the REST API,
        or ``ui:<name>`` from the console) is recorded in the audit row's detail."""
        wall = self.clock.wall()
        with self.table.lock:
            self._known(loop_id)
            s = self.table.slot(loop_id)
            config = patch.apply(self.table.configs[loop_id])
            gains = (float(self.table.kp[s]), float(self.table.ki[s]))
            with self._committing():
                self.store.update_config(
                    config,
                    audit_row(
                        loop_id, wall, None, int(self.table.seq[s]), config.mode.value,
                        "patched", gains, gains,
                        _with_actor(patch.model_dump_json(exclude_unset=True), actor),
                    ),
                )  # fmt: skip
            self.table.reconfigure(config)
            self.metrics.set_loop_counts(self.table.mode_counts())
            return self.table.view(loop_id, wall)

    def identify(self, loop_id: str, actor: str = "api") -> LoopView:
        """``POST /loops/{id}/identify``: identification from scratch (the identified
        scaling is dropped; a hint-free loop stops tuning until a new model is confident;
        the models refuted on it forgotten).
        StoreUnavailable while commits fail."""
        wall = self.clock.wall()
        with self.table.lock:
            self._known(loop_id)
            if self.store_failure is not None:
                raise StoreUnavailable(self.store_failure)
            self.engine.identify(loop_id, wall, actor)
            self._committed(None)  # its audit row
            self._write_snapshot([loop_id])  # identification state is in the snapshot
            return self.table.view(loop_id, wall)

    def reset(self, loop_id: str, actor: str = "api") -> LoopView:
        """Zero hidden state and integral; the registered gains, published unless the loop
        is frozen (see :meth:`LoopTable.reset`). StoreUnavailable while commits fail."""
        wall = self.clock.wall()
        with self.table.lock:
            self._known(loop_id)
            if self.store_failure is not None:
                raise StoreUnavailable(self.store_failure)
            self._committed(self.engine.reset(loop_id, wall, actor=actor))
            return self.table.view(loop_id, wall)

    def delete(self, loop_id: str, actor: str = "api") -> None:
        wall = self.clock.wall()
        with self.table.lock:
            self._known(loop_id)
            s = self.table.slot(loop_id)
            gains = (float(self.table.kp[s]), float(self.table.ki[s]))
            mode = self.table.mode_of(s).value
            if self.snapshot_writer is not None:  # no snapshot of it lands after the delete
                self.snapshot_writer.discard([loop_id])
            with self._committing():
                self.store.delete_loop(
                    loop_id,
                    audit_row(
                        loop_id,
                        wall,
                        None,
                        int(self.table.seq[s]),
                        mode,
                        "deleted",
                        gains,
                        None,
                        _with_actor("{}", actor),
                    ),
                )
            self.engine.remove(loop_id)
            self.recent.forget(loop_id)
            self.epochs.pop(loop_id, None)  # registered again, it starts afresh
            if self.cluster is not None:  # (its count in GET /cluster)
                self.cluster.forget([loop_id])
                self.deleted_here.add(loop_id)  # (a NOTIFY's older read must not restore it)
            self.metrics.set_loop_counts(self.table.mode_counts())

    def history(self, loop_id: str, offset: int, limit: int) -> HistoryPage:
        """Also for a deleted loop, as long as it has history; each change with its
        verdict (:mod:`service.daemon.verdicts`)."""
        with self.table.lock:
            s = self.table.slot_of.get(loop_id)
            judged = None if s is None else int(self.table.v_seq[s])
        if offset + limit <= SCAN:  # the newer rows hold the verdicts of the page's
            total, items = self.store.history(loop_id, 0, offset + limit)
            annotate(items, judged)
            items = items[offset:]
        else:
            total, items = self.store.history(loop_id, offset, limit)
            annotate(items, judged)
        if not total and s is None:
            raise UnknownLoop(loop_id)
        return HistoryPage(items=items, total=total, offset=offset, limit=limit)

    def performance(self, loop_id: str) -> Performance:
        with self.table.lock:
            self._known(loop_id)
            return self.engine.performance(loop_id)

    def rollback(self, loop_id: str, actor: str = "api") -> LoopView:
        """Restore the last-good gains now (auto: published; advisory: proposed).
        Conflict when there is nothing to restore or the mode publishes nothing."""
        return self._decide(loop_id, lambda wall: self.engine.rollback(loop_id, wall, actor))

    def accept(self, loop_id: str, seq: int, actor: str = "api") -> LoopView:
        """Accept an advisory loop's pending proposal ``seq``: published as an ``auto``
        message for the gateway to apply. Conflict if ``seq`` is not the pending one."""
        return self._decide(loop_id, lambda wall: self.engine.accept(loop_id, seq, wall, actor))

    def reject(self, loop_id: str, seq: int, actor: str = "api") -> LoopView:
        """Reject an advisory loop's pending proposal ``seq`` (recorded, nothing sent)."""
        return self._decide(loop_id, lambda wall: self.engine.reject(loop_id, seq, wall, actor))

    def _decide(self, loop_id: str, decide: Callable[[float], StepResult | None]) -> LoopView:
        """An operator's decision: committed (and snapshotted) before it is published."""
        wall = self.clock.wall()
        with self.table.lock:
            self._known(loop_id)
            if self.store_failure is not None:
                raise StoreUnavailable(self.store_failure)
            try:
                result = decide(wall)
            except ValueError as exc:
                raise Conflict(str(exc)) from None
            self._committed(result)
            return self.table.view(loop_id, wall)


def _taken(gateways: dict[str, str | None], where: str = "") -> Conflict:
    """The 409 of a registration whose ids are taken: each with its loop's gateway, for a
    gateway to tell its own loop from another gateway's (:class:`~service.daemon.schemas.
    Taken`)."""
    named = ", ".join(
        f"{i!r} (gateway {g!r})" if g else f"{i!r} (no gateway)" for i, g in gateways.items()
    )
    where = where or ("loop" if len(gateways) == 1 else "loops") + " already registered"
    return Conflict(f"{where}: {named}" if named else where, gateways)


@contextlib.contextmanager
def _taken_in_store(store, ids: list[str]):
    """An id free in the table but taken in the store is a row that failed to load (or,
    in a cluster, a loop another member owns)."""
    try:
        yield
    except store.integrity_errors:
        where = (
            "loop id taken in the store: by a stored loop that failed to load (see the "
            "log), or, in a cluster, by a loop another member owns"
        )
        taken = list(store.gateways_of(ids).items())[:NAMED_TAKEN]
        raise _taken(dict(taken), where) from None


def _registered(config: LoopConfig, wall: float, seq: int, actor: str) -> AuditRow:
    """The audit entry of a registration: no old gains, the registered ones as new, the
    config and who registered it as the detail."""
    return audit_row(
        config.id, wall, None, seq, config.mode.value, "registered",
        None, (config.kp, config.ki), _with_actor(config.model_dump_json(), actor),
    )  # fmt: skip


def _with_actor(detail: str, actor: str) -> str:
    """A JSON object's text with the ``actor`` key added (audit details of changes)."""
    return orjson.dumps({**orjson.loads(detail), "actor": actor}).decode()
