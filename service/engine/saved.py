"""A loop's stored snapshot: its runtime state written as JSON (:func:`runtimes_of`),
the row parsed (:class:`Saved`) and restored into the table (:func:`restore_runtime`,
from :meth:`LoopTable.add <service.engine.table.LoopTable.add>`).

Parsing (the runtime JSON, the identification state) is most of a restore's cost and
needs none of the table's state, so a cluster member taking over shards parses their
snapshots before it takes the table's lock (:meth:`Ownership.adopt_shards
<service.daemon.ownership.Ownership.adopt_shards>`): the worker waits only for the
array writes.
"""

from __future__ import annotations

import json
import math
from dataclasses import dataclass

import numpy as np
import orjson

from service.engine import monitor, verify, watch


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


_SCALARS = (
    "last_t", "last_e", "int_e", "next_due", "sp_ref", "excited_until", "obs_gain",
    "sp_anchor", "move_t", "manual", "saturated",
)  # fmt: skip
"""The runtime snapshot's per-loop scalars (arrays of the table of the same names)."""


def runtimes_of(tb, slots: np.ndarray, counters: list[str]) -> list[str]:
    """The runtime state of the loops at ``slots`` as the snapshot's JSON, one string
    each (``counters``: the table's counters a snapshot keeps, in order).

    Each of the table's arrays is read once for all the loops (``tolist``: Python
    numbers), and orjson writes NaN and inf as null (JSON has neither): reading each
    value of each loop with numpy's scalar indexing was a third to half of the periodic
    snapshot's cost (~40 µs a loop with the store's write, ~20 % of a core for a
    150,000-loop member at the default interval)."""
    scalars = [getattr(tb, name)[slots].tolist() for name in _SCALARS]
    counts = zip(*(getattr(tb, n)[slots].tolist() for n in counters), strict=True)
    flags = zip(tb.mismatch[slots].tolist(), tb.out_env[slots].tolist(), strict=True)
    return [
        orjson.dumps(
            {
                **dict(zip(_SCALARS, values, strict=True)),
                "counters": list(count),
                "ident": {**tb.ident[s].dump(), "mismatch": mismatch, "out_env": out_env},
                "verify": ver,
                "figures": figures,
            },
            option=orjson.OPT_SERIALIZE_NUMPY,
        ).decode()
        for s, values, count, (mismatch, out_env), ver, figures in zip(
            slots.tolist(),
            zip(*scalars, strict=True),
            counts,
            flags,
            verify.dumps(tb, slots),
            monitor.dumps(tb, slots),
            strict=True,
        )
    ]


def restore_runtime(tb, s: int, saved: Saved, counters: list[str]) -> None:
    """The snapshot's runtime state into loop ``s`` of the table ``tb`` (its identification
    state is restored by :meth:`LoopTable.add <service.engine.table.LoopTable.add>`)."""
    if saved.hidden.size == tb.hidden[s].size:
        tb.hidden[s] = saved.hidden.reshape(tb.hidden[s].shape)
    rt = saved.runtime
    tb.last_t[s] = math.nan if rt["last_t"] is None else rt["last_t"]
    tb.next_due[s] = math.nan if rt["next_due"] is None else rt["next_due"]
    tb.last_e[s], tb.int_e[s] = rt["last_e"], rt["int_e"]
    tb.manual[s], tb.saturated[s] = rt["manual"], rt["saturated"]
    sp_ref = rt.get("sp_ref")  # absent in snapshots from before the excitation gate
    tb.sp_ref[s] = math.nan if sp_ref is None else sp_ref
    until = rt.get("excited_until")
    tb.excited_until[s] = -math.inf if until is None else until
    tb.obs_gain[s] = rt.get("obs_gain", 1.0)  # absent before the normalisation
    anchor, move_t = rt.get("sp_anchor"), rt.get("move_t")  # absent before runs of moves
    tb.sp_anchor[s] = math.nan if anchor is None else anchor
    tb.move_t[s] = -math.inf if move_t is None else move_t
    # snapshots from before a counter was added list fewer: those stay 0
    for name, value in zip(counters, rt["counters"], strict=False):
        getattr(tb, name)[s] = value
    ident = rt.get("ident")  # absent in snapshots from before identification
    if ident is not None:
        tb.mismatch[s], tb.out_env[s] = ident["mismatch"], ident["out_env"]
    if "verify" in rt:  # absent in snapshots from before verification
        verify.load(tb, s, rt["verify"])
        monitor.load(tb, s, rt.get("figures") or {})
