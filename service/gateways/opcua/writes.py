"""The write side of the OPC UA gateway: the policy's decisions for the pending updates,
one Write and one Read-back request for those due, and what each result means
(docs/opcua.md, Writing gains; the rules are :func:`service.gateways.opcua.loops.decide`)."""

from __future__ import annotations

import logging
import math
import time
from collections import Counter, deque

from service.gateways.base import Gateway
from service.gateways.opcua.client import Item, LinkLost, OpcUaLink, RequestFailed
from service.gateways.opcua.loops import (
    POLICY_FIELDS,
    REL_TOL,
    WAIT,
    LoopRuntime,
    Pending,
    close_to,
    decide,
    node_value,
    number,
)

log = logging.getLogger("pitune.gateway.opcua")
Due = tuple[LoopRuntime, tuple[float, float]]
"""A loop whose pending update is to be written, and the (P, I) to write, block form."""


class GainWriter:
    """Writes the pending updates of :attr:`loops` through :attr:`link`; mixed into
    :class:`service.gateways.opcua.bridge.OpcUaGateway`, which holds these."""

    loops: list[LoopRuntime]
    link: OpcUaLink | None
    bus: Gateway
    stats: Counter[str]
    latencies: deque[float]
    # and its methods emit (record an event) and _apply (notified values)

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
            pending = lr.pending
            lr.finish()
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
        except RequestFailed as exc:  # not judged on the values now: never written
            self._refused_request([(lr, lr.pending) for lr, _ in due], exc)
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
        except RequestFailed as exc:  # nothing written; the session stays
            self._refused_request(taken, exc)
            return
        done = time.monotonic()
        for k, ((lr, target), (_, pending)) in enumerate(zip(due, taken, strict=True)):
            try:
                await self._verify(link, lr, target, pending, codes[2 * k : 2 * k + 2],
                                   back[2 * k : 2 * k + 2], before[k], done)  # fmt: skip
            except Exception:  # one loop's odd values must not stop the others, nor the bus
                self.stats["errors"] += 1
                log.exception("%s: the result of writing seq %d", lr.cfg.id, pending.update.seq)

    async def _verify(self, link, lr, target, pending, codes, back, before, done) -> None:
        """One loop's write result: finished with (written, refused, changed by the block
        or unverified); the samples from now on report the gains read back with its seq."""
        seq = pending.update.seq
        (cp, ci), read_back = codes, []
        for name, dv in zip(("p", "i"), back, strict=True):
            good = dv.StatusCode is None or dv.StatusCode.is_good()
            value = number(dv.Value.Value) if good and dv.Value is not None else None
            if value is None:  # not known: the next notification of the node says
                lr.values.pop(name, None)
            else:
                lr.values[name] = value
            read_back.append(value)
        lr.finish()
        self.bus.applied(pending.update)
        if cp.is_good() != ci.is_good():
            await self._undo_half(link, lr, seq, cp, ci, before)
        elif not cp.is_good():
            self.stats["refused_by_server"] += 1
            log.warning("%s: server refused the gains of seq %d: %s", lr.cfg.id, seq, cp.name)
            self.emit("refused", lr.cfg.id, seq, f"server:{cp.name}")
        elif None in read_back:  # e.g. Uncertain until the controller takes the value
            self.stats["unverified"] += 1
            log.warning("%s: seq %d written; read back as %s: unverified",
                        lr.cfg.id, seq, [dv.StatusCode.name for dv in back])  # fmt: skip
            self.emit("unverified", lr.cfg.id, seq)
        elif not close_to(tuple(read_back), target):
            self.stats["refused_read_back"] += 1
            log.warning("%s: seq %d read back as %s, not %s", lr.cfg.id, seq, read_back, target)
            self.emit("refused", lr.cfg.id, seq, "read_back")
        else:
            self.stats["written"] += 1
            self.latencies.append(done - pending.received)
            self.emit("written", lr.cfg.id, seq)

    def _refused_request(self, taken: list[tuple[LoopRuntime, Pending]], exc) -> None:
        """The server refused a whole request for these loops' updates: each is finished
        with, refused, and the session stays (a reconnect would meet the same fault)."""
        log.warning("server refused the request for %d loops: %s", len(taken), exc)
        for lr, pending in taken:
            lr.finish()
            self.bus.applied(pending.update)
            self.stats["refused_by_server"] += 1
            self.emit("refused", lr.cfg.id, pending.update.seq, f"server:{exc.reason}")

    async def _undo_half(self, link, lr: LoopRuntime, seq: int, cp, ci, before) -> None:
        """The server took one gain of the pair and refused the other: the one taken is
        written back, so the block never runs a pair nobody asked for."""
        name, bad = ("p", ci) if cp.is_good() else ("i", cp)
        self.stats["refused_partial"] += 1
        node, old = getattr(lr.cfg, name), before[0 if name == "p" else 1]
        vtype = lr.types.get(name)
        try:  # the value the node had is its type's
            codes, back = await link.write([(node, node_value(old, vtype), vtype)])
        except (LinkLost, RequestFailed) as exc:
            codes, back = [], []
            if isinstance(exc, LinkLost):
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


def _policy_nodes(loops) -> list[tuple[Item, str]]:
    """The nodes of the values the write policy judges by, of each loop."""
    return [
        (Item(lr.index, f), node)
        for lr in loops
        for f, node in lr.cfg.nodes().items()
        if f in POLICY_FIELDS
    ]
