"""A loop's stored snapshot, parsed: what :meth:`LoopTable.add
<service.engine.table.LoopTable.add>` restores.

Parsing (the runtime JSON, the identification state) is most of a restore's cost and
needs none of the table's state, so a cluster member taking over shards parses their
snapshots before it takes the table's lock (:meth:`Ownership.adopt_shards
<service.daemon.ownership.Ownership.adopt_shards>`): the worker waits only for the
array writes.
"""

from __future__ import annotations

import json
from dataclasses import dataclass

import numpy as np

from service.engine import watch


@dataclass(frozen=True)
class Saved:
    """A snapshot row parsed; restored once (its identification state is the loop's
    from then on)."""

    hidden: np.ndarray
    """The agent's hidden state, float32, flat (restored only if its size still fits)."""
    runtime: dict
    """What :meth:`LoopTable.snapshot <service.engine.table.LoopTable.snapshot>` wrote."""
    ident: watch.IdState | None
    """The identification state (None: a snapshot from before identification)."""

    @classmethod
    def parse(cls, hidden: bytes, runtime: str) -> Saved:
        rt = json.loads(runtime)
        ident = rt.get("ident")
        return cls(
            np.frombuffer(hidden, np.float32),
            rt,
            None if ident is None else watch.IdState.load(ident),
        )
