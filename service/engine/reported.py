"""Gains reported in the samples that an operator set in the DCS (adopted by
:func:`service.engine.verify.adopted`): which are a detune, the floor of automatic
rollbacks, and which hold the loop because they lie outside the guard's bounds. The
per-loop arrays of both (``o_kp``, ``o_ki``, ``a_kp``, ``a_ki``) are verification's,
kept in its snapshot; the bounds as configured (:data:`F64`) are the table's."""

from __future__ import annotations

import math
from typing import TYPE_CHECKING

import numpy as np

from service.engine.monitor import GAIN_RTOL, same_gains

if TYPE_CHECKING:
    from service.engine.table import LoopTable


F64 = ["c_kp_min", "c_kp_max", "c_ki_min", "c_ki_max"]
"""The guard's bounds as configured (:func:`configure`), before a model in force narrows
the bounds in force to its band (``guard.model_band``): a detune below the band is no
sign of foreign gains."""


def configure(tb: LoopTable, slots: np.ndarray) -> None:
    """Keep the bounds just set from the loops' configs (before any band)."""
    for name in F64:
        getattr(tb, name)[slots] = getattr(tb, name[2:])[slots]


def held(tb: LoopTable, s) -> np.ndarray:
    """Where the gains in force are the gains last adopted from the gateway and lie
    outside the guard's bounds as configured (``s`` a slot or slots): status
    ``gains_out_of_bounds``. The tuner then neither steps the loop nor puts a model's
    tuning in force, judges none of its changes (so no rollback is published), and
    identification does not reconstruct its output from the gains reported. Such gains
    are an operator's deliberate choice outside what the engineer allowed the tuner, or
    samples that do not carry the DCS's gains (a site map that reports the integral time
    as ki): every gains message would then be written through the same wrong map. A
    session-36 review's case: Ti 18 s reported as ki (929x the registered ki); the
    identified model's gain came out 1,000x too small, and its tuning, written back as
    Ti, gave the loop a gain margin of 0.003. The hold ends when gains within the bounds
    are reported, the bounds are patched to hold them, or the loop is reset."""
    adopted = same_gains(tb.kp[s], tb.a_kp[s]) & same_gains(tb.ki[s], tb.a_ki[s])
    return adopted & outside(tb, s)


def within(tb: LoopTable, s: int, gains) -> tuple[float, float]:
    """``gains`` (kp, ki) clipped to slot ``s``'s bounds as configured: what a rollback
    restores. Not to the band a model in force narrows them to, which holds the agent
    near the model's tuning: a rollback from that tuning clipped to the band stopped at
    its edge, still unstable when the model was wrong (session 38: 1.5x below a tuning
    10x too high)."""
    return (float(np.clip(gains[0], tb.c_kp_min[s], tb.c_kp_max[s])),
            float(np.clip(gains[1], tb.c_ki_min[s], tb.c_ki_max[s])))  # fmt: skip


def outside(tb: LoopTable, s):
    """Where the gains in force lie outside the guard's bounds as configured."""
    kp, ki = tb.kp[s], tb.ki[s]
    inside_kp = (tb.c_kp_min[s] <= kp) & (kp <= tb.c_kp_max[s])
    return ~(inside_kp & (tb.c_ki_min[s] <= ki) & (ki <= tb.c_ki_max[s]))


def is_detune(old: tuple[float, float], new: tuple[float, float]) -> bool:
    """Whether gains ``new`` (kp, ki) detune ``old``: neither gain raised, the integral
    time kp/ki not shortened, and not the same gains. The controller's gain and phase
    lag then fall at every frequency, so the loop's margins can only grow on the plants
    the tuner assumes (what an operator does to calm a loop that rings: cutting kp alone
    shortens the integral time and may not)."""
    (kp0, ki0), (kp1, ki1) = old, new
    up = 1.0 + GAIN_RTOL
    return (
        kp1 <= kp0 * up and ki1 <= ki0 * up and ki1 * kp0 <= ki0 * kp1 * up
        and not bool(same_gains(kp0, kp1) & same_gains(ki0, ki1))
    )  # fmt: skip


def no_floor(tb: LoopTable, s) -> None:
    """No operator's detune bounds the loop's rollbacks (``s`` a slot or slots)."""
    tb.o_kp[s] = tb.o_ki[s] = math.nan
