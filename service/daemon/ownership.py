"""The tuner's side of a cluster (a PostgreSQL store shared by several tuners): which
loops are in this tuner's engine, and keeping everything else out.

:class:`Ownership` is a part of :class:`~service.daemon.tuner.Tuner` (a mixin). Without
a cluster (an SQLite store) every method is a no-op or lets everything through, so the
single tuner behaves as before. With one (see :mod:`service.daemon.cluster`):

- the cluster's thread calls :meth:`adopt_shards` when it acquires shards (their loops
  are loaded from the store: gains, seq, last snapshot; each loop's last committed
  message the plant applies is sent again, as it may never have gone out),
  :meth:`drop_shards` when it releases or loses them, and :meth:`reload_loops` for
  loops changed through another member;
- every commit and snapshot carries the lease tokens of its loops' shards
  (:meth:`_fence`); a commit the store refuses (:class:`Fenced`: a lease lost) drops the
  lost shards' loops and commits the rest;
- gains go out only while the leases are valid by the local clock, with the shard's
  lease token as ``epoch`` (:meth:`_publishable`);
- the samples keys of the gateways whose shards it owns are followed from the moment
  their loops are in the engine until they leave it (:meth:`Bus.follow
  <service.daemon.bus.Bus.follow>`): Zenoh routes each gateway's batches to its owner
  only (:meth:`_gateway_rows`);
- samples and state queries of loops another member owns are left to it: not counted
  as rejected, not answered (:meth:`_foreign`).
"""

from __future__ import annotations

import logging
import time
from dataclasses import replace

import numpy as np

from service.daemon.shards import gateway_shard, gateways, shard_of
from service.daemon.store_pg import Fenced
from service.engine.saved import Saved
from service.wire.decode import Decoded, Rejection, refused
from service.wire.protocol import PUBLISHED_MODES, SCHEMA_VERSION, Mode, RejectReason

log = logging.getLogger("pitune.tuner")
ADOPT_CHUNK = 5000
"""Loops restored per turn at the table's lock when shards are adopted (~0.1-0.15 s of
``LoopTable.add_many`` on a busy box: the worker waits that long). Each turn waits for
the worker's next message group, up to ~0.3 s on a survivor behind with the dead
member's gateways (session 10: 27 s of a 75,000-loop takeover went to 75 such waits at
1,000 a turn)."""


class Ownership:
    cluster = None
    foreign_samples = 0
    """Samples of loops another member owns, left to it."""
    gains_fenced = 0
    """Committed gains messages not published: the leases may have run out, or their
    loops' leases were taken (:meth:`Delivery._send
    <service.daemon.delivery.Delivery._send>`, :meth:`drop_shards`)."""
    gains_resent = 0
    """Committed gains messages sent again by this member when it took their loops over
    (:meth:`_resend`)."""
    deleted_here: set[str]
    """Loops deleted through this member since :meth:`reload_loops` began its store read
    (in a cluster; under the table's lock)."""
    gateway_shards: dict[str, str] = {}
    """Loop id -> shard of the stored loops registered with a gateway, held here or not
    (in a cluster: :meth:`load_gateway_shards`, kept by :meth:`reload_loops`): a loop not
    held here is another member's by its gateway's shard, not by its id's bucket."""

    # -- called by the cluster's thread -------------------------------------------------
    def load_gateway_shards(self) -> None:
        """Read :attr:`gateway_shards` from the store; the cluster calls it once it
        listens for changes (a change committed later reaches :meth:`reload_loops`)."""
        self.gateway_shards = self.store.gateway_shards()

    def adopt_shards(self, shards: list[str], token: int) -> dict:
        """Load the shards' loops from the store into the engine (they resume from their
        committed gains and seq and their last snapshot) and send their last messages
        again (:meth:`_resend`); how long each part took.

        Shard by shard: its loops loaded, then inserted a chunk at a time under the
        table's lock (the worker runs between chunks), then its gateway's samples
        followed, so the first gateways' loops resume while the others' load."""
        began = time.perf_counter()
        loops, load_s, wait_s = 0, 0.0, 0.0
        wall = time.time()
        for shard in sorted(shards):
            loading = time.perf_counter()
            stored = self.store.load([shard])
            last = self.store.last_messages([shard])
            load_s += time.perf_counter() - loading
            loops += len(stored)
            for start in range(0, len(stored), ADOPT_CHUNK):
                chunk = stored[start : start + ADOPT_CHUNK]
                saved = self.store.saved_many(chunk)  # outside the lock (or parsed ahead)
                waiting = time.perf_counter()
                with self.handoff.hold():  # at the worker's next message
                    wait_s += time.perf_counter() - waiting
                    slot_of = self.table.slot_of
                    fresh = [k for k, loop in enumerate(chunk) if loop.config.id not in slot_of]
                    self._restore_many([chunk[k] for k in fresh], wall, [saved[k] for k in fresh])
                    self.cluster.adopted(shard, token, [loop.config.id for loop in chunk])
                    self._resend([chunk[k] for k in fresh], last)  # before any step of theirs
            if stored:
                with self.table.lock:
                    self.metrics.set_loop_counts(self.table.mode_counts())
            self.bus.follow(gateways([shard]))  # its loops are in: their samples can come
        self.metrics.loops_unloadable.set(len(self.store.unloadable))
        return {
            "loops": loops,
            "load_s": load_s,
            "insert_s": time.perf_counter() - began - load_s,
            "lock_wait_s": wait_s,  # (of insert_s: the turns at the table's lock awaited)
        }

    def _resend(self, stored: list, last: dict[str, tuple]) -> None:
        """Send again, as committed, the last message of each adopted loop that is one the
        plant applies (``last``: :meth:`PgStore.last_messages
        <service.daemon.store_pg.PgStore.last_messages>`): ``auto``, an accepted proposal,
        a rollback or reset in ``auto``. Its previous owner committed it, but may have been
        paused between the commit and the put and then lost its leases, and so dropped it
        (:attr:`gains_fenced`); the new owner's next messages are computed from those gains.
        It goes out under its recorded ``(epoch, seq)``, so a gateway that took it already
        drops it (docs/protocol.md, Sequence rule), and ahead of the loop's next message in
        its lane (the worker is held while this runs). Frozen and shadow loops get none."""
        batches: dict[str | None, list[dict]] = {}
        for loop in stored:
            found = last.get(loop.config.id)
            if found is None or loop.config.mode not in PUBLISHED_MODES:
                continue
            t, reason, kp_old, ki_old = found
            batches.setdefault(loop.config.gateway, []).append(
                {
                    "v": SCHEMA_VERSION, "loop_id": loop.config.id, "seq": loop.seq,
                    "t": 0.0 if t is None else t, "dkp": loop.kp - kp_old, "dki": loop.ki - ki_old,
                    "kp": loop.kp, "ki": loop.ki, "mode": Mode.auto.value, "reason": reason,
                    "instance_id": self.settings.instance_id, "epoch": loop.epoch,
                    "why": f"reason={reason} resent=takeover",
                }
            )  # fmt: skip
        for gateway, batch in batches.items():
            self._lane(gateway).submit(batch)
            self.gains_resent += len(batch)

    def drop_shards(self, shards: set[str], *, commit: bool) -> None:
        """Take the shards' loops out of the engine. ``commit``: their pending changes
        are committed and their state snapshotted first (a release, leases still held);
        else (leases lost) the pending changes are discarded: the new owner continues
        from what was committed."""
        self.bus.unfollow(gateways(shards))
        with self.table.lock:
            ids = [i for i, s in list(self.cluster.shard_of.items()) if s in shards]
            if commit:
                self._commit(None)
                self._write_snapshot(ids)
            else:
                gone = set(ids)
                gains, audit = self.table.drain_changes()
                self.table.requeue(
                    [g for g in gains if g[3] not in gone], [a for a in audit if a[0] not in gone]
                )
                # and their committed messages not out yet, which the new owner sends again
                # (their loops' last, _resend): they must not go out under a new token of
                # the shard, should this member take it back before its lanes get to them
                # (a lane's batch on its way is checked put by put: Delivery._send)
                lanes = list(self.lanes.values())
                self.gains_fenced += sum(lane.discard(gone) for lane in lanes)
            for loop_id in ids:
                if loop_id in self.table.slot_of:
                    self.engine.remove(loop_id)
                    self.recent.forget(loop_id)
                self.epochs.pop(loop_id, None)
            self.cluster.forget(ids)
            self.cluster.dropped(shards)
            self.metrics.set_loop_counts(self.table.mode_counts())

    def reload_loops(self, loop_ids: list[str]) -> None:
        """Loops registered, patched or deleted through another member: each as stored
        now, in the engine if this member owns its shard, out of it otherwise.

        The store is read outside the table's lock (the worker runs meanwhile), so a loop
        deleted through this member during the read may come back in it: it is not
        restored (it was, until the delete's own NOTIFY took it out again)."""
        with self.table.lock:
            self.deleted_here.clear()  # deletes from here on may postdate the read
        stored = {s.config.id: s for s in self.store.load(ids=loop_ids)}
        moved = {i for i, loop in stored.items() if self._comes_from_another_shard(loop)}
        floor = self._floor(moved)
        wall = time.time()
        leaving: list[str] = []
        arriving = []  # (added at once: a bulk registration through another member)
        with self.table.lock:
            for loop_id in loop_ids:
                loop = stored.get(loop_id)
                shard = None if loop is None else shard_of(loop_id, loop.config.gateway)
                if loop is not None and loop.config.gateway:
                    self.gateway_shards[loop_id] = shard
                else:
                    self.gateway_shards.pop(loop_id, None)
                local = loop_id in self.table.slot_of
                if shard is None or not self.cluster.owns(shard):
                    if local:
                        leaving.append(loop_id)
                    continue
                if not local:
                    if loop_id in self.deleted_here:
                        continue
                    arriving.append(loop)
                elif self.table.configs[loop_id] != loop.config:
                    self.table.reconfigure(loop.config)
                self.cluster.adopted(
                    shard, self.cluster.held[shard], [loop_id], floor if loop_id in moved else None
                )
            self._restore_many(arriving, wall)
            for loop_id in leaving:  # deleted, or moved to another gateway's shard
                self.engine.remove(loop_id)
                self.recent.forget(loop_id)
                self.epochs.pop(loop_id, None)
            self.cluster.forget(leaving)
            self.metrics.set_loop_counts(self.table.mode_counts())

    def _comes_from_another_shard(self, loop) -> bool:
        """A stored loop of a shard this member owns, not in it here yet, with messages
        out already (seq > 0): its gateway was patched, or its id registered again."""
        shard = shard_of(loop.config.id, loop.config.gateway)
        return (
            bool(loop.seq)
            and self.cluster.owns(shard)
            and (self.cluster.shard_of.get(loop.config.id) != shard)
        )

    def _floor(self, loop_ids) -> int | None:
        """The least epoch of the messages of loops come from another shard: a fresh one,
        above the token they went out under (:meth:`Cluster.token
        <service.daemon.cluster.Cluster.token>`); None without such loops."""
        return self.store.next_epoch(time.time(), "keep") if loop_ids else None

    def _restore_many(self, stored: list, wall: float, saved: list[Saved | None] | None = None):
        """Stored loops into the engine at once (``saved``: their snapshots, parsed ahead;
        None: parsed here), with the epochs their gains were committed under."""
        self.epochs.update((lp.config.id, (lp.epoch, lp.seq)) for lp in stored if lp.epoch)
        self.engine.add_many(
            [loop.config for loop in stored],
            kp=[loop.kp for loop in stored],
            ki=[loop.ki for loop in stored],
            seq=[loop.seq for loop in stored],
            saved=self.store.saved_many(stored) if saved is None else saved,
            wall=wall,
        )

    def _claim(self, configs) -> None:
        """Before registering loops: take the leases of their shards no member holds
        (called without the table's lock: the cluster's thread takes it after its own)."""
        if self.cluster is not None:
            self.cluster.claim({shard_of(c.id, c.gateway) for c in configs})

    # -- used by the worker -------------------------------------------------------------
    def _fence(self, loop_ids) -> tuple[str, dict[str, int]]:
        """The lease tokens a write of these loops needs (in a cluster)."""
        return self.cluster.fence(loop_ids)

    def _fenced(self, exc: Fenced, gains: list, audit: list) -> None:
        """A commit refused for leases the store did not find held: renew them now, and
        drop the loops of the shards another member took; put the other loops' changes
        back to be committed again. Leases that only ran out (the store was unreachable
        for longer than the lease, nobody took them) are renewed as they are, same token:
        the worker's first commit after an outage came before the renewal and dropped
        every loop, which the member then loaded again from older snapshots. (Raises
        psycopg.Error if the renewal fails: nothing done, a failing commit.)"""
        shards = {s for s in exc.shards if not s.startswith("loop:")}
        lost = self.cluster.revive(shards) if shards else set()
        if lost or len(shards) < len(exc.shards):
            log.warning("commit fenced: %s; dropping those loops", exc)
        else:
            log.info("leases had run out (%s), nobody took them: renewed, committing again", exc)
        self.cluster.lose(lost)
        ids = set(self.cluster.shard_of)
        self.table.requeue([g for g in gains if g[3] in ids], [a for a in audit if a[0] in ids])
        self.drop_shards(lost, commit=False)

    def _epoch_now(self, loop_id: str) -> int | None:
        """The epoch a message of the loop goes out under now: this run's, or in a cluster
        its shard's lease token (or its floor); None: not this member's loop."""
        return self.epoch if self.cluster is None else self.cluster.token(loop_id)

    def epoch_of(self, loop_id: str) -> int | None:
        """The epoch of the loop's state: the one its gains were last committed (and
        published) under, which a state reply carries. With the current one, a reply
        after a restart or a failover ordered above the gateway's last message of the same
        seq, and the gateway wrote the stored gains over an operator's change made
        meanwhile. None recorded (a row of an older version): the current one."""
        last = self.epochs.get(loop_id)
        return last[0] if last else self._epoch_now(loop_id)

    def _row_epoch(self, loop_id: str, seq: int) -> int | None:
        """The epoch a committed gains row of the loop is recorded under: its last row's
        when the seq has not moved (a change not published: an operator's, adopted),
        else the one its message goes out under now. Under this run's, an adoption after
        a restart or a failover made a gateway's state query take it for news, and write
        it over a change the operator made again while the gateway was away."""
        last = self.epochs.get(loop_id)
        return last[0] if last and last[1] == seq else self._epoch_now(loop_id)

    def _publishable(self, messages: list[dict], gateways: list) -> list[tuple[dict, object]]:
        """(message, gateway) of the messages this member may publish, with their epoch."""
        out = []
        for message, gateway in zip(messages, gateways, strict=True):
            epoch = self._epoch_now(message["loop_id"])
            if epoch is not None:
                message["epoch"] = epoch
                out.append((message, gateway))
        return out

    def _foreign(self, loop_id: str | None) -> bool:
        """A loop another member answers for: stored with a gateway whose shard another
        member owns, or else (no gateway, or unknown) in a bucket another member owns.
        False without a cluster."""
        if self.cluster is None or loop_id is None or loop_id in self.table.slot_of:
            return False
        shard = self.gateway_shards.get(loop_id) or shard_of(loop_id, None)
        return not self.cluster.owns(shard)

    def _gateway_rows(self, decoded: Decoded, key: str) -> Decoded:
        """The decoded samples of a batch from the shared samples key (:meth:`_own_rows`)
        or a gateway's. On a gateway's, a loop registered with another gateway (or none)
        is rejected ``wrong_gateway``: its owner may be another member, which never hears
        this key; a key whose gateway id is not one (the subscription's wildcard lets any
        through) is rejected whole, ``bad_key``. In a cluster, a batch of a gateway this
        member no longer owns (queued before it released the shard) is left to the new
        owner, as foreign samples."""
        if key == self.keys.batch:
            return self._own_rows(decoded)
        gateway = self.keys.gateway_id(key)
        if gateway is None:
            return refused(decoded, RejectReason.bad_key, f"not a gateway's samples key: {key!r}")
        rows = decoded.rows
        if self.cluster is not None and not self.cluster.owns(gateway_shard(gateway)):
            self.foreign_samples += decoded.received
            return Decoded(rows.take(np.zeros(len(rows), bool)), [], 0)
        slots = self.slot_memo.slots(rows.loop_ids)
        wrong = (slots >= 0) & (self.table.gateways[slots] != gateway)
        detail = f"not registered with gateway {gateway!r}"
        # the samples refused as they were read are another gateway's loop's too: booked
        # as they came, any gateway could fill that loop's refusals (security review R2)
        earlier = [self._foreign_loop(r, gateway, detail) for r in decoded.rejected]
        if not wrong.any():
            return Decoded(rows, earlier, decoded.received, slots)
        rejected = [
            Rejection(int(rows.index[j]), rows.loop_ids[j], RejectReason.wrong_gateway, detail)
            for j in np.flatnonzero(wrong).tolist()
        ]
        return Decoded(rows.take(~wrong), earlier + rejected, decoded.received, slots[~wrong])

    def _foreign_loop(self, rejection: Rejection, gateway: str, detail: str) -> Rejection:
        """``rejection`` as ``wrong_gateway`` where it names a loop registered here with
        another gateway than ``gateway`` (or none), else as it is."""
        slot = self.table.slot_of.get(rejection.loop_id) if rejection.loop_id else None
        if slot is None or self.table.gateways[slot] == gateway:
            return rejection
        return replace(rejection, reason=RejectReason.wrong_gateway, detail=detail)

    def _own_rows(self, decoded: Decoded) -> Decoded:
        """The decoded samples without those of loops another member owns."""
        if self.cluster is None:
            return decoded
        rows = decoded.rows
        slot_of = self.table.slot_of
        foreign = np.fromiter(
            (i not in slot_of and self._foreign(i) for i in rows.loop_ids), bool, len(rows)
        )
        n = int(foreign.sum())
        if not n:
            return decoded
        self.foreign_samples += n
        return Decoded(rows.take(~foreign), decoded.rejected, decoded.received - n)
