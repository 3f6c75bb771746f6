"""Whether the output a gateway sends (``op``) is the PI law's output with the gains it
reports: identification fits the process from ``op`` to ``pv``, so an ``op`` in other
units than the gains (a DCS's dimensionless %/% gain sent as ``kp`` with the PV in bar
and the output in %) gives a model whose gain is off by that factor, confident, and a
first tuning off by it too (session 38's review: ``op`` 10x the law's, K fitted 0.2 for
2, a first tuning 10x too high, the loop unstable).

In auto, each sample's change of ``op`` is set against the law's change over the same
interval, ``kp (e - e_prev) + ki e dt`` (the bumpless increment form, so a change of the
gains between samples costs nothing), both summed over the segment identification
records; ``op`` = ``a`` x the law's output gives the running sums in the ratio ``a``. A
sample that moves the setpoint adds to neither: a DCS whose proportional term acts on
the PV alone (no kick at a setpoint step; a common default) differs from the law on the
error there only; nor does a sample in manual, saturated or without ``op`` (the sums
are of changes, so one left out leaves them consistent, and a segment's manual output
steps are fitted with the auto data the sums judged). They start again with the
segment.

:func:`refusal` is identification's: once the sums hold :data:`MIN_SAMPLES` samples and
the law explains ``op`` (:data:`MIN_R2`), a ratio whose size is outside 1/:data:`MAX_RATIO`
to :data:`MAX_RATIO` refuses the segment, saying why (a negative one: ``op`` inverted).
A law that does not explain ``op`` (derivative action, a filtered PV in the DCS, noise)
refuses nothing, and
neither does a ratio near -1: the loop registered with the other controller action,
which identification names (its model's gain has the wrong sign).
"""

from __future__ import annotations

from typing import TYPE_CHECKING

import numpy as np

if TYPE_CHECKING:
    from service.engine.table import LoopTable

F64 = ("ol_x", "ol_y", "ol_xx", "ol_xy", "ol_yy", "ol_n")
"""Per loop: the law's and ``op``'s summed changes since the check started, the sums of
their squares and product over the samples since, and those samples' count."""
MIN_SAMPLES = 20
"""Samples the sums must hold before they judge (a setpoint response's first ones)."""
MIN_R2 = 0.5
"""Share of ``op``'s changes the law (scaled) must explain for its ratio to count."""
MAX_RATIO = 2.0
"""``op`` at more than this factor of the law's output (or less than its inverse) is in
other units (the bar's hint tolerance, 2x, for the same reason: K would be that far off)."""


def clear(tb: LoopTable, s) -> None:
    """The check starts again (a new loop; ``s``: a slot or a slot array)."""
    for name in F64:
        getattr(tb, name)[s] = 0.0


def observe(tb: LoopTable, s, restart, use, kp, ki, e, e_prev, dt, op, op_prev) -> None:
    """One sample of each loop ``s`` (distinct slots, aligned arrays, engineering units):
    ``restart`` where the check starts again (a new segment), ``use`` where the sample's
    change counts (in auto, not saturated, ``op`` sent now and before, the setpoint
    unmoved)."""
    clear(tb, s[restart])
    use = use & ~restart
    law = kp * (e - e_prev) + ki * e * dt
    x = np.where(use, tb.ol_x[s] + law, tb.ol_x[s])
    y = np.where(use, tb.ol_y[s] + (op - op_prev), tb.ol_y[s])
    tb.ol_x[s], tb.ol_y[s] = x, y
    tb.ol_xx[s] += np.where(use, x * x, 0.0)
    tb.ol_xy[s] += np.where(use, x * y, 0.0)
    tb.ol_yy[s] += np.where(use, y * y, 0.0)
    tb.ol_n[s] += use


def refusal(tb: LoopTable, s: int) -> str | None:
    """Why loop ``s``'s ``op`` may not be used for identification (None: it may)."""
    xx, xy, yy = float(tb.ol_xx[s]), float(tb.ol_xy[s]), float(tb.ol_yy[s])
    if tb.ol_n[s] < MIN_SAMPLES or not (xx > 0.0 and yy > 0.0):
        return None
    ratio = xy / xx
    if xy * xy < MIN_R2 * xx * yy or 1.0 / MAX_RATIO <= abs(ratio) <= MAX_RATIO:
        return None  # (near -1: the other action, identification's message)
    if ratio < 0.0:
        what = f"op moves against the PI law's output (x{ratio:.2g}): op inverted"
    else:
        what = f"op is {ratio:.3g}x the PI law's output with the gains reported"
    return (
        f"{what}: op in other units than the gains (or another sign)? the model would be "
        "off by that factor; not identified from op (send op in the gains' units, or none)"
    )
