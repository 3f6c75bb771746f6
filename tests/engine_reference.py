"""The sample rules written one sample at a time: the specification the engine's one
vectorised ingest path (``LoopTable.ingest``) is checked against, differentially.

Kept in the tests only: the engine has exactly one implementation of each rule.
"""

from __future__ import annotations

import math

import numpy as np
import orjson

from service.engine import (
    monitor,
    op_law,
    oscillation,
    output_limit,
    reported,
    rules,
    steady,
    verify,
    watch,
)
from service.engine.audit import audit_row
from service.engine.modes import AUTO, FROZEN
from service.engine.rules import GAIN_RTOL, MAX_AGENT_ERROR
from service.engine.table import LoopTable
from service.engine.updates import MODE_VALUES
from service.units import OBS_GAIN_RANGE, OBS_WINDOW, PAPER_MOVE, RAMP_GAP, RAMP_LONG
from service.wire.decode import decode_objects
from service.wire.protocol import RejectReason, Sample


class Rejected(Exception):
    def __init__(self, reason: RejectReason, detail: str) -> None:
        super().__init__(detail)
        self.reason = reason
        self.detail = detail


def ingest_one(table: LoopTable, s: int, sample: Sample, wall: float) -> bool:
    """The engine's vectorised path with one sample (counts a rejection on the loop, as
    the engine does); True if the loop fell due. Raises :class:`Rejected`."""
    rows = decode_objects([{**sample.model_dump(), "loop_id": table.ids[s]}]).rows
    due, rejections = rules.ingest(table, np.array([s]), rows, wall)
    if rejections:
        table.n_rejected[s] += 1
        _, reason, detail = rejections[0]
        raise Rejected(reason, detail)
    return bool(due[0])


def reference_ingest(table: LoopTable, s: int, sample: Sample, wall: float) -> bool:
    """The same rules, scalar: True if the loop fell due. Raises :class:`Rejected`."""
    try:
        return _ingest(table, s, sample, wall)
    except Rejected:
        table.n_rejected[s] += 1
        raise


def _ingest(tb: LoopTable, s: int, sample: Sample, wall: float) -> bool:
    now = steady.now(tb, wall)
    tokens = min(tb.burst, tb.tokens[s] + max(now - tb.token_wall[s], 0.0) * tb.rate)
    tb.token_wall[s] = now
    if tokens < 1.0:
        tb.tokens[s] = tokens
        raise Rejected(RejectReason.flood, f"over {tb.rate:g} samples/s")
    tb.tokens[s] = tokens - 1.0
    t, last_t = sample.t, tb.last_t[s]
    if t <= last_t:  # False while last_t is NaN (no sample yet)
        if t == last_t:
            raise Rejected(RejectReason.duplicate, f"t={t} again")
        if not rules.new_clock(tb, s, t):
            raise Rejected(RejectReason.out_of_order, f"t={t} < last t={last_t}")
        old_t, last_t = last_t, math.nan  # re-anchored: a fresh decimation window
    e = sample.error
    if abs(e) * tb.e_scale[s] > MAX_AGENT_ERROR:
        raise Rejected(RejectReason.out_of_range, f"|e|={abs(e):g} is absurd for this loop")
    if math.isnan(last_t) and t <= tb.last_t[s]:  # a new clock: the plant times move too
        for name in rules.CLOCKED:
            getattr(tb, name)[s] += t - old_t
    tb.back_n[s] = 0.0
    if sample.kp is not None or sample.ki is not None:
        _adopt(tb, s, sample, wall)
    # a move must stand out of the measured noise too (rules.EXCITATION_NOISE_SIGMAS)
    warm = tb.o_k[s] >= oscillation.NOISE_WARM or sample.sp is None  # e only: from the start
    sigma = math.sqrt(max(float(tb.o_var[s]), 0.0)) if warm else 0.0
    noise = rules.EXCITATION_NOISE_SIGMAS * sigma
    # the ramp rule: a change the way of the last, within RAMP_GAP samples of it, continues
    # a ramp (its RL periods are not stepped; identification takes it as one event)
    ramping = False
    last = tb.sp_last[s]
    if sample.sp is not None and not math.isnan(last) and sample.sp != last:
        way = 1.0 if sample.sp > last else -1.0
        ramping = way == tb.sp_way[s] and tb.sp_since[s] < RAMP_GAP
        tb.sp_way[s], tb.sp_since[s] = way, 0.0
        if ramping:
            tb.ramp_t[s] = t
        else:  # a first change: a ramp may start here
            tb.ramp_from[s] = t
    else:
        tb.sp_since[s] += 1.0
    if sample.sp is not None:
        tb.sp_last[s] = sample.sp
    if sample.sp is None:  # only the error: a setpoint change shows as a jump of it
        size = abs(e - tb.last_e[s])
        step = max(tb.exc_step[s], math.sqrt(2.0) * noise)
        moved = not math.isnan(last_t) and size >= step
        if moved:
            tb.sp_anchor[s] = tb.last_e[s]
    else:
        ref = tb.sp_ref[s]
        size = abs(sample.sp - ref)
        moved = size >= max(tb.exc_step[s], noise)  # False for NaN
        if moved:
            anchor = tb.sp_anchor[s]
            # a run of moves: within one RL period of the last, in the same direction
            run_on = t - tb.move_t[s] <= tb.period[s] and (sample.sp > ref) == (ref > anchor)
            if not run_on or ref == anchor:
                tb.sp_anchor[s] = ref
            size = abs(sample.sp - tb.sp_anchor[s])
        if moved or math.isnan(ref):
            tb.sp_ref[s] = sample.sp
    if moved:
        if sample.auto and not sample.saturated:  # a move in manual excites nothing
            tb.excited_until[s] = t + tb.exc_window[s]
        tb.move_t[s] = t
        gain = PAPER_MOVE / (size * tb.e_scale[s])
        tb.obs_gain[s] = min(max(gain, OBS_GAIN_RANGE[0]), OBS_GAIN_RANGE[1])

    tb.n_samples[s] += 1
    tb.last_wall[s] = now
    gap = math.isnan(last_t) or t - last_t > tb.stale_gap[s]
    saturated = _held(tb, s, sample, e, last_t, gap, wall) or sample.saturated
    paused = not sample.auto or saturated
    resumed = (tb.manual[s] or tb.saturated[s]) and not paused
    tb.manual[s] = not sample.auto
    tb.saturated[s] = saturated
    tb.last_t[s] = t
    fresh = gap or resumed
    if tb.watch[s] and sample.sp is not None:
        sample = sample.model_copy(update={"saturated": saturated})
        _record(tb, s, sample, e, last_t, gap, fresh, wall, ramping)
    else:  # not recorded: the next sample goes on from no recorded one
        tb.prev_ok[s], tb.prev_meas[s] = False, sample.op is not None
    # performance monitoring is no sample rule: its one implementation, with one sample
    one = np.array([s])
    judged = monitor.observe(
        tb, one, np.array([t]), np.array([e]), tb.last_e[one], np.array([last_t]),
        np.array([moved]), np.array([fresh]), np.array([gap]), np.array([sample.auto]),
        np.array([saturated]),
    )  # fmt: skip
    if judged[0].size or judged[1].size:
        tb.to_judge.append(judged)
    if fresh:
        tb.next_due[s] = t + tb.period[s]  # a new decimation window
    elif not paused:
        tb.int_e[s] += 0.5 * (e + tb.last_e[s]) * (t - last_t) * tb.int_scale[s]
    tb.last_e[s] = e
    # the agent's error observation: the mean over the window before the period's end
    due, e_agent = tb.next_due[s], e * tb.e_scale[s]
    if tb.win_due[s] != due:  # another period's sums (NaN: none yet)
        tb.win_sum[s] = tb.win_n[s] = 0.0
    tb.win_due[s] = due
    if due - OBS_WINDOW * tb.period[s] <= t < due:
        tb.win_sum[s] += e_agent
        tb.win_n[s] += 1.0
    if not t >= due:  # NaN (no scaling yet: identifying): never due
        return False
    mixed = due - OBS_WINDOW * tb.period[s] <= tb.move_t[s] < due  # a move in the window
    tb.obs_e[s] = tb.win_sum[s] / tb.win_n[s] if tb.win_n[s] and not mixed else e_agent
    period = tb.period[s]
    tb.next_due[s] += period * (math.floor((t - tb.next_due[s]) / period) + 1.0)
    if tb.mode[s] == FROZEN or not sample.auto or saturated or tb.out_env[s] or not tb.scaled[s]:
        return False
    if reported.held(tb, s):  # gains reported outside the bounds
        return False
    if tb.hold.held:  # the plant-wide hold: neither stepped nor quiet
        return False
    # a ramp running, or a long one ended within the period (RAMP_LONG RL periods)
    running = tb.sp_since[s] < RAMP_GAP and tb.ramp_t[s] >= tb.ramp_from[s]
    ran = tb.ramp_t[s] - tb.ramp_from[s] if tb.ramp_from[s] > -math.inf else -math.inf
    long = ran >= RAMP_LONG * tb.period[s]
    if tb.gate_closed(s, t) or (t - tb.ramp_t[s] < tb.period[s] and (running or long)):
        tb.n_quiet[s] += 1
        return False
    return t >= tb.cool_until[s]  # held after a rollback (service.engine.verify)


def _held(tb: LoopTable, s: int, sample: Sample, e: float, last_t, gap: bool, wall) -> bool:
    """service.engine.output_limit.observe, one sample: whether the output is held (seen
    in op, or in the PV)."""
    free = sample.auto and not sample.saturated
    if free and sample.op is not None:
        return _no_pv_run(tb, s) or _op_held(tb, s, sample, e, last_t, gap, wall)
    tb.oh_op[s], tb.oh_n[s], tb.oh_law[s], tb.oh_held[s] = math.nan, 0.0, 0.0, False
    if free and tb.scaled[s]:
        return _pv_stalled(tb, s, sample, e, last_t, gap, wall)
    return _no_pv_run(tb, s)


def _op_held(tb: LoopTable, s: int, sample: Sample, e: float, last_t, gap: bool, wall) -> bool:
    """The op rule (service.engine.output_limit._op_rule), one sample with op."""
    op = sample.op
    tb.oh_lo[s] = op if math.isnan(tb.oh_lo[s]) else min(tb.oh_lo[s], op)
    tb.oh_hi[s] = op if math.isnan(tb.oh_hi[s]) else max(tb.oh_hi[s], op)

    def scale() -> float:
        return max(abs(tb.oh_op[s]) if not math.isnan(tb.oh_op[s]) else 0.0,
                   tb.oh_hi[s] - tb.oh_lo[s], output_limit.SCALE_FLOOR)  # fmt: skip

    was = bool(tb.oh_held[s])
    if gap or math.isnan(tb.oh_op[s]) or abs(op - tb.oh_op[s]) > output_limit.OP_RTOL * scale():
        tb.oh_op[s], tb.oh_n[s], tb.oh_law[s], tb.oh_held[s] = op, 0.0, 0.0, False
        return False
    kp = tb.kp[s] if sample.kp is None else sample.kp
    ki = tb.ki[s] if sample.ki is None else sample.ki
    last_e = tb.last_e[s]
    tb.oh_law[s] += kp * (e - last_e) + ki * 0.5 * (e + last_e) * (sample.t - last_t)
    tb.oh_n[s] += 1.0
    big = abs(tb.oh_law[s]) >= output_limit.HELD_SHARE * scale()
    tb.oh_held[s] = was or (tb.oh_n[s] >= output_limit.HELD_SAMPLES and big)
    if tb.oh_held[s] and not was:
        tb.n_held[s] += 1
        detail = {"seen": "op", "op": op, "samples": int(tb.oh_n[s]),
                  "law_change": float(tb.oh_law[s]),
                  "op_range": [float(tb.oh_lo[s]), float(tb.oh_hi[s])]}  # fmt: skip
        gains = (float(tb.kp[s]), float(tb.ki[s]))
        tb._audit.append(audit_row(tb.ids[s], wall, sample.t, int(tb.seq[s]),
                                   MODE_VALUES[tb.mode[s]], "output_held", gains, gains,
                                   orjson.dumps(detail).decode()))  # fmt: skip
    return bool(tb.oh_held[s])


def _no_pv_run(tb: LoopTable, s: int) -> bool:
    tb.ps_ef[s], tb.ps_push[s], tb.ps_sp[s] = 0.0, 0.0, math.nan
    tb.ps_sign[s] = tb.ps_stalls[s] = 0.0
    tb.ps_held[s] = False
    return False


def _pv_stalled(tb: LoopTable, s: int, sample: Sample, e: float, last_t, gap: bool, wall):
    """The PV rule (service.engine.output_limit._pv_rule), one usable sample."""
    o = output_limit
    t = sample.t
    sp = math.nan if sample.sp is None else sample.sp
    es, us, block = tb.e_scale[s], tb.u_scale[s], o.BLOCK * tb.time_unit[s]
    ea, last_ea = e * es, tb.last_e[s] * es
    dt = 0.0 if gap else t - last_t
    same_sp = not gap and sp == tb.ps_sp[s]
    alpha = min(1.0, dt / (o.FILTER * block)) if same_sp else 1.0
    ef = tb.ps_ef[s] + alpha * (ea - tb.ps_ef[s])
    nv = tb.ps_nv[s]
    if same_sp:  # the noise: half the mean square change between samples
        change = (ea - last_ea) * (ea - last_ea) / 2.0
        nv = change if math.isnan(nv) else nv + o.NOISE_WEIGHT * (change - nv)
        tb.ps_nv[s] = nv
    sign = tb.ps_sign[s]
    on = same_sp and sign != 0.0 and math.copysign(1.0, ef) == sign and abs(ef) >= 0.5 * o.BAND
    tb.ps_ef[s], tb.ps_sp[s] = ef, sp
    if not on:
        tb.ps_push[s] = tb.ps_sign[s] = tb.ps_stalls[s] = 0.0
        tb.ps_held[s] = False
        if abs(ef) >= o.BAND:  # a run starts
            tb.ps_sign[s], tb.ps_t0[s], tb.ps_ef0[s] = math.copysign(1.0, ef), t, ef
            tb.ps_prev[s] = math.nan
        return False
    kp = tb.kp[s] if sample.kp is None else sample.kp
    ki = tb.ki[s] if sample.ki is None else sample.ki
    tb.ps_push[s] += ki * 0.5 * (e + tb.last_e[s]) * dt * us
    if t - tb.ps_t0[s] < block:
        return bool(tb.ps_held[s])
    # the block's end: did the PV follow the push of the block before?
    push = tb.ps_push[s] + kp * (ef - tb.ps_ef0[s]) / es * us
    expected = o.SHARE * o.LOW_GAIN * sign * tb.ps_prev[s]
    moved = sign * (tb.ps_ef0[s] - ef)
    sd = math.sqrt(max(nv, 0.0) * dt / (o.FILTER * block))
    was = bool(tb.ps_held[s])
    stalled = expected >= o.NOISE_SIGMAS * sd and moved < o.FOLLOW * expected  # NaN: False
    tb.ps_stalls[s] = tb.ps_stalls[s] + 1.0 if stalled else 0.0
    tb.ps_held[s] = tb.ps_stalls[s] >= o.STALLS
    tb.ps_prev[s], tb.ps_ef0[s], tb.ps_t0[s], tb.ps_push[s] = push, ef, t, 0.0
    if tb.ps_held[s] and not was:
        tb.n_held[s] += 1
        detail = {"seen": "pv", "error": float(ef / es), "block_s": float(block),
                  "expected_pv": float(expected / es), "moved_pv": float(moved / es)}  # fmt: skip
        gains = (float(tb.kp[s]), float(tb.ki[s]))
        tb._audit.append(audit_row(tb.ids[s], wall, t, int(tb.seq[s]),
                                   MODE_VALUES[tb.mode[s]], "output_held", gains, gains,
                                   orjson.dumps(detail).decode()))  # fmt: skip
    return bool(tb.ps_held[s])


def _record(
    tb: LoopTable, s: int, sample: Sample, e: float, last_t, gap, fresh, wall, ramping
) -> None:
    """Identification's sample rule (service.engine.watch.record), one sample."""
    t, sp = sample.t, sample.sp
    pv = sp - e
    measured = sample.op is not None
    # after a gap, a stretch not recorded, or where op is sent after samples without it
    anew = (fresh and (gap or not tb.prev_ok[s])) or (measured and not tb.prev_meas[s])
    # the gains the sample reports in force, else the tuner's
    kp = tb.kp[s] if sample.kp is None else sample.kp
    ki = tb.ki[s] if sample.ki is None else sample.ki
    if measured:  # the reconstruction goes on bumpless from the output sent
        integral = sample.op - kp * e
    elif anew:
        integral = ki * e * 0.0
    else:  # the PI's integral term: bumpless kp change, backward Euler
        integral = tb.op_int[s] - (kp - tb.op_kp[s]) * tb.last_e[s] + ki * e * (t - last_t)
    tb.op_int[s], tb.op_kp[s] = integral, kp
    op = kp * e + integral if sample.op is None else sample.op
    before = tb.id_sp[s]
    by_hand = not sample.auto and measured
    if by_hand:  # an operator's output step is a move; the setpoint, the one before manual
        step = watch._step(op, tb.prev_op[s], tb.oh_hi[s] - tb.oh_lo[s])
        moved = not anew and abs(op - tb.prev_op[s]) > step
        sp = sp if math.isnan(before) else before
    elif fresh and not anew:  # back in auto from manual with op: the setpoint may track
        moved = False
    else:  # a ramp's later changes are samples of the event its first change opened
        moved = not math.isnan(before) and sp != before and not ramping
    tb.id_sp[s] = sp
    foreign = bool(reported.held(tb, s)) and not measured
    broken = anew or (not sample.auto and not measured) or sample.saturated or foreign
    why = watch.broken_why(sample.auto, sample.saturated, measured, foreign)
    # whether op is the law's output (service.engine.op_law), one sample
    if anew:  # a new segment: the sums start again
        for name in op_law.F64:
            getattr(tb, name)[s] = 0.0
    elif not broken and sample.auto and measured and sp == tb.prev_sp[s] and tb.prev_meas[s]:
        tb.ol_x[s] += kp * (e - tb.last_e[s]) + ki * e * (t - last_t)
        tb.ol_y[s] += op - tb.prev_op[s]
        x, y = tb.ol_x[s], tb.ol_y[s]
        tb.ol_xx[s] += x * x
        tb.ol_xy[s] += x * y
        tb.ol_yy[s] += y * y
        tb.ol_n[s] += 1.0
    row = (t, sp, pv, op)
    if tb.rec[s] >= 0 and broken:
        watch._close(tb, s, t, wall, final=True, why=f"segment ended: {why}")
    elif tb.rec[s] >= 0 and moved:
        starts = tb.ident[s].starts
        if tb.rec_n[s] - starts[-1] >= watch.MIN_EVENT_SAMPLES:
            watch._close(tb, s, t, wall)
            starts = tb.ident[s].starts
            starts.append(int(tb.rec_n[s]))
        watch._append(tb, s, row, move=True)
    elif tb.rec[s] < 0 and moved and not broken:
        watch._open(tb, s, row)
    elif tb.rec[s] < 0 and moved:
        tb.ident[s].why = f"{'output step' if by_hand else 'setpoint move'} not usable: {why}"
    elif tb.rec[s] >= 0:  # recording: after a move a row per sample, then wider rows
        k, held = int(tb.rec_k[s]), int(tb.rec_m[s])
        tb.rec_k[s] += 1
        head = int(tb.rec_n[s]) - 1 - int(tb.rec_ev[s]) < watch.HEAD_ROWS
        if held >= (1 if head else int(tb.rec_stride[s])):
            watch._append(tb, s, row)
        else:  # averaged into the last kept row
            data, last = tb.recorder.data[tb.rec[s]], int(tb.rec_n[s]) - 1
            data[2, last] += (pv - data[2, last]) / (held + 1)
            data[3, last] += (op - data[3, last]) / (held + 1)
            tb.rec_m[s] = held + 1
        # an assessment during the event, 16, 24, 32, 48, 64... samples after the move
        if watch.check_due(k) and watch.closely(tb, s):
            watch._close(tb, s, t, wall)
    tb.prev_t[s], tb.prev_sp[s], tb.prev_pv[s], tb.prev_op[s] = t, sp, pv, op
    tb.prev_ok[s], tb.prev_meas[s] = not broken, measured


def _close(a: float, b: float) -> bool:
    return abs(a - b) <= GAIN_RTOL * max(abs(a), abs(b))


def _adopt(tb: LoopTable, s: int, sample: Sample, wall: float) -> None:
    kp = tb.kp[s] if sample.kp is None else sample.kp
    ki = tb.ki[s] if sample.ki is None else sample.ki
    applied = -1 if sample.applied_seq is None else sample.applied_seq
    if tb.mode[s] == AUTO and 0 <= applied < tb.auto_seq[s]:
        return  # the gateway has not applied the last auto update yet: it stays pending
    if _close(kp, tb.kp[s]) and _close(ki, tb.ki[s]):
        tb.pending[s] = False
        return
    current = tb.mode[s] == AUTO and applied == tb.seq[s]  # then a difference is an operator's
    if not current and tb.pending[s] and _close(kp, tb.prev_kp[s]) and _close(ki, tb.prev_ki[s]):
        return
    tb.pending[s] = False
    old = (tb.kp[s], tb.ki[s])
    tb.kp[s], tb.ki[s] = kp, ki
    verify.adopted(tb, s, old)
    tb._gains_dirty.add(s)
    tb._audit.append(
        audit_row(
            tb.ids[s], wall, sample.t, int(tb.seq[s]), tb.mode_of(s).value,
            "adopted", old, (kp, ki), rules.adopted_detail(tb, s),
        )
    )  # fmt: skip
