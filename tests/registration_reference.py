"""A loop's registration written one loop at a time, with numpy's scalar writes: the
specification :meth:`LoopTable.add_many <service.engine.table.LoopTable.add_many>` (one
assignment per array for a chunk of loops) is checked against, field by field.

This is what ``LoopTable.add`` did before the chunked insert (session 10); kept in the
tests only: the engine has one implementation.
"""

from __future__ import annotations

import math
import sys

from service.engine import first_tuning, monitor, steady, verify
from service.engine.config import LoopConfig, resolve_bounds
from service.engine.id_state import IdState
from service.engine.modes import _CODE
from service.engine.refusals import REASONS
from service.engine.saved import Saved
from service.engine.table import _COUNTERS, LoopTable
from service.wire.protocol import RejectReason


def add_one(tb: LoopTable, config: LoopConfig, *, kp, ki, seq, saved: Saved | None, wall):
    """Register one loop, as the table's ``add`` did loop by loop."""
    if config.id in tb.slot_of:
        raise KeyError(f"loop {config.id!r} already registered")
    if not tb._free:
        tb.reserve(1)
    s = tb._free.pop()
    tb.ids[s] = config.id
    tb.slot_of[config.id] = s
    tb.version += 1
    tb.reg_kp[s], tb.reg_ki[s] = config.kp, config.ki
    tb.kp[s] = config.kp if kp is None else kp
    tb.ki[s] = config.ki if ki is None else ki
    tb.seq[s] = tb.auto_seq[s] = seq
    for name in _COUNTERS:
        getattr(tb, name)[s] = 0
    tb.n_refused[s] = 0
    tb.tokens[s], tb.token_wall[s] = tb.burst, steady.now(tb, wall)
    restored = None if saved is None else saved.ident
    tb.ident[s] = IdState() if restored is None else restored
    tb.rec[s], tb.rec_n[s], tb.rec_k[s], tb.rec_stride[s] = -1, 0, 0, 1
    tb.mismatch[s] = tb.out_env[s] = tb.prev_ok[s] = False
    tb.op_int[s] = tb.op_kp[s] = 0.0
    tb.prev_t[s] = tb.prev_sp[s] = tb.prev_pv[s] = tb.prev_op[s] = math.nan
    tb.id_sp[s] = math.nan
    monitor.clear(tb, s)
    verify.init(tb, s)
    _configure(tb, s, config)
    tb._restart(s)
    if saved is not None:
        _restore_runtime(tb, s, saved)
    return s


def _configure(tb: LoopTable, s: int, config: LoopConfig) -> None:
    tb.configs[config.id] = config
    identified = tb.ident[s].scaling
    sc = identified or config.resolved_scaling
    g = config.guard
    if identified is not None and config.scaling is None:
        g = resolve_bounds(g, identified, float(tb.reg_kp[s]), float(tb.reg_ki[s]))
    tb.stale_gap[s] = g.stale_periods * config.sample_period_s
    tb.forgetting[s] = config.forgetting
    tb.sign[s] = config.action_sign
    tb.max_rel[s] = g.max_rel_change
    tb.damp[s] = g.noise_damping
    tb.ms_max[s] = g.max_sensitivity
    tb.settle[s] = g.settle_steps
    tb.mc_factor[s] = g.model_check or 0.0
    tb.mode[s] = _CODE[config.mode]
    tb.gateways[s] = None if config.gateway is None else sys.intern(config.gateway)
    # a loop's own choice, else on without a hint and, with one, as the site says
    unset = config.scaling is None or tb.site.identify_hinted
    tb.watch[s] = unset if g.identify is None else g.identify
    tb.env_guard[s] = g.envelope_guard
    if not g.envelope_guard and tb.out_env[s]:  # the guard off resumes the loop
        tb.out_env[s], tb.ident[s].paused_by = False, None
    tb.scaled[s] = sc is not None
    model = tb.ident[s].in_force
    if model is not None:
        tau, theta = model.tau, model.theta
    else:
        tau, theta = (None if sc is None else monitor.hinted_tau(sc.rl_period_s)), 0.0
    tb.m_tau_cl[s] = math.nan if tau is None else 2.0 * tau
    tb.m_theta[s] = theta
    tb.period[s] = math.nan if sc is None else sc.rl_period_s
    tb.v_margin[s] = g.verify_margin if g.verify else math.nan
    tb.v_over[s] = g.verify_overshoot if g.verify else math.nan
    period = tb.period[s]
    tb.v_cool[s] = g.cooldown_periods * period if math.isfinite(period) else 0.0
    tb.v_fence[s] = g.fence_periods * period if math.isfinite(period) else 0.0
    if sc is None:
        tb.kp_unit[s] = tb.ki_unit[s] = tb.period[s] = tb.exc_step[s] = math.nan
        tb.u_scale[s] = tb.time_unit[s] = math.nan
        tb.e_scale[s] = tb.int_scale[s] = 0.0
        tb.exc_window[s] = math.inf
        tb.kp_min[s] = g.kp_min or 0.0
        tb.kp_max[s] = g.kp_max or math.inf
        tb.ki_min[s] = g.ki_min or 0.0
        tb.ki_max[s] = g.ki_max or math.inf
        return
    tb.kp_unit[s], tb.ki_unit[s] = sc.kp_per_agent, sc.ki_per_agent
    tb.e_scale[s], tb.u_scale[s], tb.time_unit[s] = sc.e_scale, sc.u_scale, sc.time_unit_s
    tb.int_scale[s] = sc.int_scale
    tb.period[s] = sc.rl_period_s
    tb.kp_min[s], tb.kp_max[s] = g.kp_min, g.kp_max
    tb.ki_min[s], tb.ki_max[s] = g.ki_min, g.ki_max
    tb.exc_step[s] = g.excitation_min_step / sc.e_scale
    tb.exc_window[s] = g.excitation_periods * sc.rl_period_s or math.inf
    if tb.ident[s].in_force is not None and g.model_band is not None:
        first_tuning.band(tb, s, tb.ident[s].in_force, g.model_band)


def _restore_runtime(tb: LoopTable, s: int, saved: Saved) -> None:
    if saved.hidden.size == tb.hidden[s].size:
        tb.hidden[s] = saved.hidden.reshape(tb.hidden[s].shape)
    rt = saved.runtime
    tb.last_t[s] = math.nan if rt["last_t"] is None else rt["last_t"]
    tb.next_due[s] = math.nan if rt["next_due"] is None else rt["next_due"]
    tb.last_e[s], tb.int_e[s] = rt["last_e"], rt["int_e"]
    tb.manual[s], tb.saturated[s] = rt["manual"], rt["saturated"]
    sp_ref = rt.get("sp_ref")
    tb.sp_ref[s] = math.nan if sp_ref is None else sp_ref
    until = rt.get("excited_until")
    tb.excited_until[s] = -math.inf if until is None else until
    tb.obs_gain[s] = rt.get("obs_gain", 1.0)
    anchor, move_t = rt.get("sp_anchor"), rt.get("move_t")
    tb.sp_anchor[s] = math.nan if anchor is None else anchor
    tb.move_t[s] = -math.inf if move_t is None else move_t
    for name in ("settle_n", "settle_kp", "settle_ki"):  # absent before settling
        getattr(tb, name)[s] = rt.get(name) or 0.0
    if saved.hidden.size != tb.hidden[s].size:  # a new episode: settling starts again
        tb.unsettle(s)
    for name, value in zip(_COUNTERS, rt["counters"], strict=False):
        getattr(tb, name)[s] = value
    for name, n in (rt.get("refused") or {}).items():  # by reason (since session 41)
        if name in {r.value for r in REASONS}:
            tb.n_refused[s, REASONS.index(RejectReason(name))] = n
    flight = rt.get("in_flight")  # the last update in flight again: at the seq, or one on
    if flight is not None:
        at_seq, at_kp, at_ki, pending, prev_kp, prev_ki = flight
        if at_seq == tb.seq[s] and prev_kp is not None and prev_ki is not None:
            tb.pending[s], tb.prev_kp[s], tb.prev_ki[s] = pending, prev_kp, prev_ki
        elif at_seq == tb.seq[s] - 1 and at_kp is not None and at_ki is not None:
            tb.pending[s], tb.prev_kp[s], tb.prev_ki[s] = True, at_kp, at_ki
    ident = rt.get("ident")
    if ident is not None:
        tb.mismatch[s], tb.out_env[s] = ident["mismatch"], ident["out_env"]
    if "verify" in rt:
        for name, value in rt["verify"].items():
            if hasattr(tb, name) and name not in ("v_margin", "v_over", "v_cool", "v_fence"):
                default = -math.inf if name in verify._MINUS_INF else math.nan
                getattr(tb, name)[s] = default if value is None else value
        figures = rt.get("figures") or {}
        last = figures.get("last")
        if last:
            names = ("f_t", "f_iae", "f_over", "f_rise", "f_settle", "f_mse", "f_move")
            for name, v in zip(names, last, strict=False):  # (f_move: since session 35)
                getattr(tb, name)[s] = math.nan if v is None else v
        cut = figures.get("cut") or (0.0, None, 0.0, None)  # (since session 40)
        tb.c_cut[s], tb.c_cut_s[s] = cut[0], math.nan if cut[1] is None else cut[1]
        tb.c_early[s], tb.c_left[s] = cut[2], math.nan if cut[3] is None else cut[3]
        hist = figures.get("hist") or []
        n = min(len(hist), monitor.HISTORY)
        if n:
            rows = [[r[0] - tb.f_t[s], *r[1:]] for r in hist[:n]]
            tb.f_hist[s, :n] = rows
        tb.f_hist_n[s] = n
