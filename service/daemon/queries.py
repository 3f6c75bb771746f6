"""The tuner's answers to state queries on the bus: per loop (``after_t`` queries wait
for their loop's sample, at most AFTER_T_WAIT_S), wildcard, and per gateway
(one StateBatch). In a cluster, a member answers for the loops it owns only.

:class:`StateQueries` is a part of :class:`~service.daemon.tuner.Tuner` (a mixin): it
runs on the worker thread with the engine's lock held.
"""

from __future__ import annotations

import contextlib
import math
import time

import zenoh

from service.daemon.bus import JSON, reply
from service.daemon.shards import shard_of
from service.engine.views import hold
from service.wire.protocol import ErrorReply, StateBatch, StateReply, encode

AFTER_T_WAIT_S = 1.0
"""Longest a state query with ``after_t`` waits for its loop's sample."""


class StateQueries:
    """State replies from the engine's table (mixed into the Tuner)."""

    def answer(self, query: zenoh.Query, gateway: bool) -> None:
        """A state query: of loops (a key, or a wildcard) or of a gateway's loops."""
        if self.store_failure is not None:
            # the table holds steps not committed yet (held, unpublished): a reply would
            # hand the gateway gains that may never exist; it asks again on its schedule
            query.drop()
        elif gateway:
            self._answer_gateway(query)
        else:
            self._answer(query)

    def _answer(self, query: zenoh.Query) -> None:
        key = str(query.key_expr)
        loop_id = self.keys.loop_id(key)
        if loop_id is not None and loop_id in self.table.slot_of:
            try:
                after_t = _after_t(query)
            except ValueError as exc:  # answered at once, it would pass for the awaited state
                reply(query, encode(ErrorReply(loop_id=loop_id, error=str(exc))), error=True)
                return
            if after_t is not None and not self._reflects(loop_id, after_t):
                deadline = time.monotonic() + AFTER_T_WAIT_S
                self._parked.setdefault(loop_id, []).append((after_t, deadline, query))
                return
            reply(query, encode(self._state(loop_id)))
            return
        if "*" in key:  # e.g. a reconnecting gateway asking for all its loops at once
            asked = zenoh.KeyExpr(key)
            for loop_id in list(self.table.slot_of):
                state_key = self.keys.state(loop_id)
                if asked.intersects(zenoh.KeyExpr(state_key)):
                    query.reply(state_key, encode(self._state(loop_id)), encoding=JSON)
            query.drop()
            return
        if self._foreign(loop_id):  # another member of the cluster answers
            query.drop()
            return
        error = ErrorReply(loop_id=_chunk(key, f"{self.keys.prefix}/loops/"), error="unknown loop")
        reply(query, encode(error), error=True)

    def _reflects(self, loop_id: str, after_t: float) -> bool:
        t = self.table.last_t[self.table.slot(loop_id)]
        return not math.isnan(t) and t >= after_t

    def _answer_parked(self) -> None:
        """Answer the parked ``after_t`` queries whose sample came, or whose wait is over
        (the reply's ``last_t`` then says the sample was not handled: rejected or lost)."""
        now = time.monotonic()
        if self.store_failure is not None:  # not answered while commits fail (answer)
            return
        for loop_id in list(self._parked):
            waiting = self._parked.pop(loop_id)
            if loop_id not in self.table.slot_of:  # deleted meanwhile
                for _, _, query in waiting:
                    error = ErrorReply(loop_id=loop_id, error="unknown loop")
                    with contextlib.suppress(zenoh.ZError):  # the querier may be gone
                        reply(query, encode(error), error=True)
                continue
            still = []
            for after_t, deadline, query in waiting:
                if now >= deadline or self._reflects(loop_id, after_t):
                    with contextlib.suppress(zenoh.ZError):  # the querier may be gone
                        reply(query, encode(self._state(loop_id)))
                else:
                    still.append((after_t, deadline, query))
            if still:
                self._parked[loop_id] = still

    def _answer_gateway(self, query: zenoh.Query) -> None:
        """One StateBatch with every loop registered with the gateway in the key."""
        gateway = self.keys.gateway_id(str(query.key_expr))
        if gateway is None:
            key = str(query.key_expr)
            error = ErrorReply(
                loop_id=_chunk(key, f"{self.keys.prefix}/gateways/"),
                error="not a gateway's state key",
            )
            reply(query, encode(error), error=True)
            return
        if self.cluster is not None and not self.cluster.owns(shard_of("", gateway)):
            query.drop()  # the gateway's owner answers
            return
        tb = self.table
        states = [
            self._state(loop_id) for loop_id, s in tb.slot_of.items() if tb.gateways[s] == gateway
        ]
        epoch = self.epoch if self.cluster is None else self.cluster.held.get(shard_of("", gateway))
        batch = StateBatch(
            gateway=gateway, instance_id=self.settings.instance_id, epoch=epoch or self.epoch,
            states=states,
        )  # fmt: skip
        reply(query, encode(batch))

    def _state(self, loop_id: str) -> StateReply:
        tb = self.table
        s = tb.slot(loop_id)
        return StateReply(
            loop_id=loop_id,
            kp=float(tb.kp[s]),
            ki=float(tb.ki[s]),
            mode=tb.mode_of(s),
            status=tb.status(s, self.clock.wall()),
            seq=int(tb.seq[s]),
            last_t=_finite(tb.last_t[s]),
            instance_id=self.settings.instance_id,
            # that of the loop's last gains message (Ownership.epoch_of): a reply of the same
            # seq under a later epoch (a restart, a failover) would undo an operator's change
            epoch=self.epoch_of(loop_id) or self.epoch,
            rl_period_s=_finite(tb.period[s]),
            next_due_t=_finite(tb.next_due[s]),
            gateway=tb.gateways[s],
            hold=hold(tb, s),
            oscillating=bool(tb.o_osc[s]),
        )


def _finite(x: float) -> float | None:
    return None if math.isnan(x) else float(x)


def _chunk(key: str, head: str) -> str:
    """The id chunk of ``key`` after ``head`` (``{prefix}/loops/``), valid or not, for an
    ErrorReply's ``loop_id``; the whole key where it has none."""
    rest = key[len(head) :] if key.startswith(head) else ""
    return rest.split("/")[0] or key


def _after_t(query: zenoh.Query) -> float | None:
    """The query's ``after_t`` parameter (None: absent); ValueError if it is not a
    finite number."""
    try:
        raw = query.parameters.get("after_t")
    except Exception:  # noqa: BLE001 - a malformed selector is no parameter
        return None
    if raw is None:
        return None
    try:
        value = float(raw)
    except ValueError:
        value = math.nan
    if not math.isfinite(value):
        raise ValueError(f"bad after_t: {raw!r} (a finite number of plant seconds)")
    return value
