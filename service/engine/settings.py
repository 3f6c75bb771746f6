"""A chunk of loops' configs written into the table's arrays (what :meth:`LoopTable.add_many
<service.engine.table.LoopTable.add_many>` and :meth:`reconfigure
<service.engine.table.LoopTable.reconfigure>` set from a :class:`LoopConfig`).

The values are gathered from the configs in one pass (Python floats, as computed one
loop at a time before: the arrays hold exactly the same numbers) and written with one
numpy assignment per array: a failover inserts 75,000 loops, and ~35 scalar writes per
loop through numpy's indexing were most of the ~0.2 ms a loop cost.
"""

from __future__ import annotations

import math
import sys
from collections.abc import Sequence
from typing import TYPE_CHECKING

import numpy as np

from service.engine import first_tuning, monitor, reported, verify
from service.engine.config import LoopConfig, resolve_bounds
from service.engine.modes import _CODE

if TYPE_CHECKING:
    from service.engine.table import LoopTable

_NAN, _INF = math.nan, math.inf
_FLOATS = (
    "stale_gap", "forgetting", "sign", "max_rel", "damp", "ms_max", "settle",
    "kp_unit", "ki_unit", "e_scale", "u_scale", "time_unit", "int_scale", "period",
    "kp_min", "kp_max", "ki_min", "ki_max", "exc_step", "exc_window", "mc_factor",
)  # fmt: skip
"""The table's float64 arrays a config sets, in the order :func:`_row` returns them."""
_FLAGS = ("watch", "env_guard", "scaled")
"""Its bool arrays, after the floats in a row."""


def configure(tb: LoopTable, slots: np.ndarray, configs: Sequence[LoopConfig]) -> None:
    """The settings of ``configs`` into the loops at ``slots`` (aligned; their identification
    state, ``tb.ident``, in place first: a scaling it put in force overrides the hint)."""
    if not configs:
        return
    for config in configs:
        tb.configs[config.id] = config
    slot_list = slots.tolist()
    rows = [_row(tb, s, c) for s, c in zip(slot_list, configs, strict=True)]
    columns = list(zip(*rows, strict=True))
    for name, values in zip((*_FLOATS, *_FLAGS), columns, strict=False):
        getattr(tb, name)[slots] = values
    # the envelope guard switched off resumes a loop it paused: with the guard off no
    # model is judged against the envelope, so nothing else would ever resume it
    for s in slots[tb.out_env[slots] & ~tb.env_guard[slots]].tolist():
        tb.out_env[s], tb.ident[s].paused_by = False, None
    mode, gateway, tau, theta, verifying, margin, over, cooldown, fence = columns[
        len(_FLOATS) + len(_FLAGS) :
    ]
    tb.mode[slots] = mode
    tb.recorder.reserve(int(np.count_nonzero(tb.watch)))  # here, not in the worker's path
    gateways = np.empty(len(slot_list), object)  # (a list of str would make a str array)
    gateways[:] = gateway
    tb.gateways[slots] = gateways
    # the target trajectory's model (identified, else the hint's tau with no dead time)
    monitor.configure(tb, slots, np.array(tau, np.float64), np.array(theta, np.float64))
    verify.configure(
        tb, slots, np.array(verifying, bool), np.array(margin), np.array(over),
        np.array(cooldown), np.array(fence),
    )  # fmt: skip
    reported.configure(tb, slots)
    # a model in force narrows the bounds just set to its band (rare: identified loops)
    for s, config in zip(slot_list, configs, strict=True):
        model, factor = tb.ident[s].in_force, config.guard.model_band
        if model is not None and factor is not None:
            first_tuning.band(tb, s, model, factor)


def _row(tb: LoopTable, s: int, config: LoopConfig) -> tuple:
    """One loop's values of :data:`_FLOATS`, :data:`_FLAGS`, then mode, gateway, the
    monitor's model (tau, theta; NaN tau: none) and verification (on, margin, cool-down)."""
    state = tb.ident[s]
    identified = state.scaling
    sc = identified or config.resolved_scaling
    g = config.guard
    if identified is not None and config.scaling is None:
        # bounds the user left unset follow the identified model
        g = resolve_bounds(g, identified, float(tb.reg_kp[s]), float(tb.reg_ki[s]))
    if sc is None:  # identifying: no unit mapping yet, never due
        units = (_NAN, _NAN, 0.0, _NAN, _NAN, 0.0, _NAN)
        bounds = (g.kp_min or 0.0, g.kp_max or _INF, g.ki_min or 0.0, g.ki_max or _INF)
        excitation = (_NAN, _INF)
        hinted = _NAN
    else:
        period = sc.rl_period_s
        units = (
            sc.kp_per_agent, sc.ki_per_agent, sc.e_scale, sc.u_scale, sc.time_unit_s,
            sc.int_scale, period,
        )  # fmt: skip
        bounds = (g.kp_min, g.kp_max, g.ki_min, g.ki_max)
        excitation = (
            g.excitation_min_step / sc.e_scale,
            g.excitation_periods * period or _INF,
        )
        hinted = monitor.hinted_tau(period)
    model = state.in_force
    return (
        g.stale_periods * config.sample_period_s, config.forgetting, config.action_sign,
        g.max_rel_change, g.noise_damping, g.max_sensitivity, g.settle_steps, *units, *bounds,
        *excitation,
        g.model_check or 0.0,
        tb.site.identifies(config), g.envelope_guard,
        sc is not None,
        _CODE[config.mode],
        # one string per gateway, however many loops it fronts
        None if config.gateway is None else sys.intern(config.gateway),
        hinted if model is None else model.tau, 0.0 if model is None else model.theta,
        g.verify, g.verify_margin, g.verify_overshoot, g.cooldown_periods, g.fence_periods,
    )  # fmt: skip
