"""A controller output held at a limit, seen in the data (a valve fully open or shut).

The gateway's ``saturated`` flag says so where the DCS exposes it; many maps have no such
point (an OPC UA server with the block's OUT but no limit flag), yet send the output
``op``. A PI in auto moves its output at every sample its error is not zero: the integral
term by ki e dt, the proportional one by kp times the error's change. An output that
stays where it is, sample after sample, while that law would have moved it by a visible
share of its range, is not being moved by the PI: it is clamped at a limit of its range
(or by the DCS's anti-windup, or held by a tracking mode). The loop is then treated as
one the gateway flags saturated (status ``saturated``: no RL step, the error not
integrated, identification's segment ended, the monitor's saturated share), from the
sample that shows it until the first sample whose output moves.

The rule, per loop, on accepted samples in auto that carry ``op`` and no flag:

* a *run* is the samples since the output last moved by more than :data:`OP_RTOL` of its
  scale (the largest of its magnitude and the range of outputs seen);
* over the run the PI law's change of the output is summed from the error and the gains
  in force (those the sample reports, else the tuner's), P on the error and I by the
  trapezoid: its form (P on the PV, an ideal or series PI) changes the P part only
  where the setpoint moves, and by no more than the move;
* the output is held once the run has :data:`HELD_SAMPLES` samples and that change is at
  least :data:`HELD_SHARE` of the scale; it stays held until the output moves.

Neither clause alone: a converged loop's output moves by less than the tolerance while
the law agrees (its change is as small), and a gateway that samples faster than the DCS
executes its PI, or reports the output through a deadband or in whole percent, sees it
still for a few samples while the law has it move by less than the quantum. A gateway
whose ``op`` is the valve's position feedback rather than the PI's output is read the
same way: a stuck valve shows as held too. Without ``op`` nothing is detected (a
reconstructed output follows the law by construction): the gateway's flag is then the
only sign.
"""

from __future__ import annotations

import math
from typing import TYPE_CHECKING

import numpy as np
import orjson

from service.engine.audit import audit_row
from service.engine.updates import MODE_VALUES

if TYPE_CHECKING:
    from service.engine.table import LoopTable

OP_RTOL = 1e-6
"""An output within this share of its scale of the run's first is unchanged (a DCS
reports a clamped output exactly; float32 storage moves it by 6e-8 of itself)."""
HELD_SAMPLES = 20
"""Samples a run lasts at least before the output counts as held: a gateway polling a
few times per execution of the DCS's PI sees its output still between executions."""
HELD_SHARE = 0.05
"""The PI law's change over the run, as a share of the output's scale, beyond which a
still output is held: above the quantum of an output reported in whole percent or
through an OPC UA deadband of a few percent, far below what an error that persists
with the output at a limit builds up (the integral grows without bound)."""
SCALE_FLOOR = 1e-9
"""The output's scale while it has only been seen at 0 (a valve shut from the first
sample): any change the law asks for then counts."""

F64 = ("oh_op", "oh_n", "oh_law", "oh_lo", "oh_hi")
"""Per loop: the run's output (NaN: no run), its samples, the PI law's change over it,
the lowest and highest output seen."""
BOOL = ("oh_held",)
"""Per loop: the output is held (the loop counts as saturated)."""
CLEAR = {
    "oh_op": math.nan, "oh_n": 0.0, "oh_law": 0.0, "oh_lo": math.nan, "oh_hi": math.nan,
    "oh_held": False,
}  # fmt: skip
"""Each array's value with no run and no output seen (a new loop; a snapshot from before
the rule)."""


def clear(tb: LoopTable, s) -> None:
    """No run, no output seen (a new loop)."""
    for name, value in CLEAR.items():
        getattr(tb, name)[s] = value


def end_runs(tb: LoopTable, s) -> None:
    """No run (a sample without ``op``, in manual or flagged): nothing held."""
    tb.oh_op[s] = math.nan
    tb.oh_n[s] = tb.oh_law[s] = 0.0
    tb.oh_held[s] = False


def scale(tb: LoopTable, slots) -> np.ndarray:
    """The output's scale (its units): the largest of its run's magnitude and its range."""
    return np.maximum(
        np.fmax(np.abs(tb.oh_op[slots]), tb.oh_hi[slots] - tb.oh_lo[slots]), SCALE_FLOOR
    )


def observe(
    tb: LoopTable, slots: np.ndarray, cols: dict[str, np.ndarray], last_t: np.ndarray,
    gap: np.ndarray, wall: float,
) -> np.ndarray:  # fmt: skip
    """Take accepted samples of distinct loops (before ``last_e`` moves on; ``cols`` as
    :func:`service.engine.rules.ingest` holds them, e sign-adjusted; ``gap``: a first
    sample, a new clock or a stale gap). Returns where the output is held; a hold that
    begins is counted and audited (reason ``output_held``)."""
    op, e, t = cols["op"], cols["e"], cols["t"]
    usable = ~np.isnan(op) & cols["auto"] & ~cols["saturated"]
    if not usable.any():  # the usual case of gateways that send no op: one test
        running = ~np.isnan(tb.oh_op[slots])
        if running.any():
            end_runs(tb, slots[running])
        return np.zeros(slots.size, bool)
    was = tb.oh_held[slots]
    tb.oh_lo[slots] = np.where(usable, np.fmin(tb.oh_lo[slots], op), tb.oh_lo[slots])
    tb.oh_hi[slots] = np.where(usable, np.fmax(tb.oh_hi[slots], op), tb.oh_hi[slots])
    ref, size = tb.oh_op[slots], scale(tb, slots)  # a run's scale: its output's and range's
    same = usable & ~gap & (np.abs(op - ref) <= OP_RTOL * size)  # NaN ref: False
    kp = np.where(np.isnan(cols["kp"]), tb.kp[slots], cols["kp"])
    ki = np.where(np.isnan(cols["ki"]), tb.ki[slots], cols["ki"])
    last_e = tb.last_e[slots]
    with np.errstate(invalid="ignore"):
        law = kp * (e - last_e) + ki * 0.5 * (e + last_e) * (t - last_t)
    tb.oh_law[slots] = np.where(same, tb.oh_law[slots] + law, 0.0)
    tb.oh_n[slots] = np.where(same, tb.oh_n[slots] + 1.0, 0.0)
    tb.oh_op[slots] = np.where(same, ref, np.where(usable, op, math.nan))
    held = same & (
        was | ((tb.oh_n[slots] >= HELD_SAMPLES) & (np.abs(tb.oh_law[slots]) >= HELD_SHARE * size))
    )
    tb.oh_held[slots] = held
    for i in np.flatnonzero(held & ~was).tolist():
        s = int(slots[i])
        tb.n_held[s] += 1
        detail = {
            "op": float(op[i]), "samples": int(tb.oh_n[s]), "law_change": float(tb.oh_law[s]),
            "op_range": [float(tb.oh_lo[s]), float(tb.oh_hi[s])],
        }  # fmt: skip
        gains = (float(tb.kp[s]), float(tb.ki[s]))
        tb._audit.append(
            audit_row(tb.ids[s], wall, float(t[i]), int(tb.seq[s]), MODE_VALUES[tb.mode[s]],
                      "output_held", gains, gains, orjson.dumps(detail).decode())
        )  # fmt: skip
    return held
