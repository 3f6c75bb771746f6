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

from service.engine import monitor, output_limit, refusals, verify
from service.engine.id_state import IdState
from service.engine.monitor import ABSENT, put


@dataclass(frozen=True)
class Saved:
    """A snapshot row parsed; restored once (its identification state is the loop's
    from then on)."""

    hidden: np.ndarray
    """The agent's hidden state, float32, flat (restored only if its size still fits)."""
    runtime: dict
    """What :meth:`LoopTable.snapshot <service.engine.table.LoopTable.snapshot>` wrote."""
    ident: IdState | None
    """The identification state (None: a snapshot from before identification)."""

    @classmethod
    def parse(cls, hidden: bytes, runtime: str) -> Saved:
        try:
            rt = orjson.loads(runtime)
        except orjson.JSONDecodeError:  # NaN or Infinity: a snapshot written by json.dumps
            rt = json.loads(runtime)
        ident = rt.get("ident")
        return cls(
            np.frombuffer(hidden, np.float32),
            rt,
            None if ident is None else IdState.load(ident),
        )


_SCALARS = (
    "last_t", "last_e", "int_e", "next_due", "sp_ref", "excited_until", "obs_gain",
    "sp_anchor", "move_t", "manual", "saturated", "settle_n", "settle_kp", "settle_ki",
    *output_limit.CLEAR,
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
    flights = zip(*(getattr(tb, name)[slots].tolist() for name in _IN_FLIGHT), strict=True)
    counts = zip(*(getattr(tb, n)[slots].tolist() for n in counters), strict=True)
    flags = zip(tb.mismatch[slots].tolist(), tb.out_env[slots].tolist(), strict=True)
    return [
        orjson.dumps(
            {
                **dict(zip(_SCALARS, values, strict=True)),
                "in_flight": flight,
                "counters": list(count),
                "ident": {**tb.ident[s].dump(), "mismatch": mismatch, "out_env": out_env},
                "verify": ver,
                "figures": figures,
                "refused": refused,
            },
            option=orjson.OPT_SERIALIZE_NUMPY,
        ).decode()
        for s, values, flight, count, (mismatch, out_env), ver, figures, refused in zip(
            slots.tolist(),
            zip(*scalars, strict=True),
            flights,
            counts,
            flags,
            verify.dumps(tb, slots),
            monitor.dumps(tb, slots),
            refusals.dumps(tb, slots),
            strict=True,
        )
    ]


def restore_runtimes(tb, slots: np.ndarray, saved: list[Saved], counters: list[str]) -> None:
    """The snapshots' runtime state into the loops at ``slots`` of the table ``tb``
    (aligned; their identification state is restored by :meth:`LoopTable.add_many
    <service.engine.table.LoopTable.add_many>`), one assignment per array. A value a
    snapshot from an older version lacks keeps what the loop was registered with."""
    if not saved:
        return
    size = tb.hidden[0].size
    fits = [i for i, x in enumerate(saved) if x.hidden.size == size]
    if fits:
        hidden = np.stack([saved[i].hidden for i in fits]).reshape(-1, *tb.hidden.shape[1:])
        tb.hidden[slots[fits]] = hidden
    rts = [x.runtime for x in saved]
    for name, default in _RESTORED:
        put(getattr(tb, name), slots, [rt.get(name, ABSENT) for rt in rts], default)
    _restore_in_flight(tb, slots, rts)
    # an agent memory of another size is not restored: its episode starts again
    tb.unsettle(slots[[i for i, x in enumerate(saved) if x.hidden.size != size]])
    # snapshots from before a counter was added list fewer: those stay 0
    for k, name in enumerate(counters):
        put(getattr(tb, name), slots, [_at(rt["counters"], k) for rt in rts], 0)
    refusals.load(tb, slots, [rt.get("refused") or {} for rt in rts])  # (absent before 41)
    # absent in snapshots from before identification
    idents = [rt.get("ident") or {} for rt in rts]
    for name in ("mismatch", "out_env"):
        put(getattr(tb, name), slots, [d.get(name, ABSENT) for d in idents], False)
    # absent in snapshots from before verification
    checked = [i for i, rt in enumerate(rts) if "verify" in rt]
    if checked:
        verify.load(tb, slots[checked], [rts[i]["verify"] for i in checked])
        monitor.load(tb, slots[checked], [rts[i].get("figures") or {} for i in checked])


_RESTORED = (
    ("last_t", math.nan), ("next_due", math.nan), ("last_e", math.nan), ("int_e", math.nan),
    ("manual", False), ("saturated", False), ("sp_ref", math.nan),
    ("excited_until", -math.inf), ("obs_gain", math.nan), ("sp_anchor", math.nan),
    ("move_t", -math.inf), ("settle_n", 0.0), ("settle_kp", 0.0), ("settle_ki", 0.0),
    *output_limit.CLEAR.items(),
)  # fmt: skip
"""The runtime snapshot's scalars restored, with the value of a null (the ones absent in
older snapshots: sp_ref before the excitation gate, excited_until, sp_anchor and move_t
before runs of moves, obs_gain before the normalisation, the settling's before it, keep
the registration's; the output-limit run's before it, none)."""


_IN_FLIGHT = ("seq", "kp", "ki", "pending", "prev_kp", "prev_ki")
"""What says whether the last update published may still be in flight: the seq and gains
at the snapshot, and its in-flight flag with the gains that update replaced."""


def _restore_in_flight(tb, slots: np.ndarray, rts: list[dict]) -> None:
    """The last update published is in flight again after a restore, as it may be: the
    gateway's next samples may still report the gains it replaced, which must not be taken
    for an operator's (and adopted, dropping a rollback's fence). The gains restored are
    the store's, whose seq may be the snapshot's (its flag and the gains it replaced are
    restored) or one later (published since: in flight, replacing the snapshot's gains);
    further on, what it replaced is unknown and the flag stays off, as registered."""
    for s, rt in zip(slots.tolist(), rts, strict=True):
        saved = rt.get("in_flight")
        if saved is None:  # a snapshot from before it was kept
            continue
        seq, kp, ki, pending, prev_kp, prev_ki = saved
        if seq == tb.seq[s] and None not in (prev_kp, prev_ki):
            tb.pending[s], tb.prev_kp[s], tb.prev_ki[s] = pending, prev_kp, prev_ki
        elif seq == tb.seq[s] - 1 and None not in (kp, ki):
            tb.pending[s], tb.prev_kp[s], tb.prev_ki[s] = True, kp, ki


def _at(values: list, k: int):
    return values[k] if k < len(values) else ABSENT
