"""What the monitor and verification show: performance figures, verification state, an
advisory loop's pending proposal and what holds the agent (``GET /loops/{id}``,
``/performance``); and the loop's samples last refused.

Figures are computed by :mod:`service.engine.monitor`; verdicts by
:mod:`service.engine.verify`. docs/tuner.md (Performance and verification) explains each.
"""

from __future__ import annotations

from pydantic import BaseModel, Field


class ResponseFigures(BaseModel):
    """Figures of one complete setpoint response (judged over 2 RL periods after the move)."""

    t: float = Field(description="Plant time (s) the response's judging window ended.")
    iae: float = Field(description="Integral of |e| over the window divided by |move|, s.")
    iae_tu: float | None = Field(description="The same in the loop's time units (time_unit_s).")
    overshoot_pct: float = Field(
        description="Largest excursion past the new setpoint, % of the move."
    )
    rise_s: float | None = Field(
        description="From 10 % to 90 % of the move, s (None: not reached)."
    )
    rise_tu: float | None
    settle_s: float | None = Field(
        description="Until the error stays within 5 % of the move, s (None: not settled)."
    )
    settle_tu: float | None
    mse: float | None = Field(
        description="Mean squared deviation from the paper's target trajectory (time "
        "constant 2 tau, dead time theta of the loop's model), agent units."
    )


class WindowFigures(BaseModel):
    """Figures of the recent window (exponential forgetting over 5 RL periods)."""

    error_mean: float = Field(description="Mean error sp - pv, engineering units.")
    error_var: float = Field(description="Error variance, engineering units squared.")
    noise_sigma: float = Field(description="Measurement noise estimated from quiet samples.")
    oscillation_index: float | None = Field(
        description="Regularity r = mean / (3 std) of the last 3 half-periods between "
        "zero crossings (the last 2 when the growing test flagged the loop; Thornhill "
        "et al. 2003; r > 1: regular). None: too few crossings."
    )
    oscillating: bool = Field(
        description="The last 3 half-periods regular, above the noise band, not decaying; "
        "or the last 2 regular, the newer lobe above the band and growing (1.5 times the "
        "older)."
    )
    manual_share: float = Field(description="Share of recent time in manual.")
    saturated_share: float = Field(description="Share of recent time saturated.")
    rejected_share: float = Field(description="Share of the last ~100 samples rejected.")
    output_held: float | None = Field(
        None,
        description="The controller output (engineering units) the data show held at a "
        "limit: unchanged while the PI law would have moved it by 5 % of its range (the loop "
        "counts as saturated until it moves); None: not held, or no op in the samples.",
    )
    pv_stalled: bool = Field(
        False,
        description="Without op in the samples: the PV has not followed the output the PI "
        "law gives for two blocks of the envelope's longest lag (a valve at a limit, a "
        "stuck valve or transmitter); the loop counts as saturated until it does.",
    )


class Fence(BaseModel):
    """After a rollback, the agent's steps stop halfway from the restored gains to the ones
    that failed (``guard.fence_periods``); a bound the failed change did not push is None."""

    kp_min: float | None
    kp_max: float | None
    ki_min: float | None
    ki_max: float | None
    until_t: float = Field(description="Plant time the fence stands until.")


class Verification(BaseModel):
    """Verify-or-rollback state of a loop."""

    enabled: bool
    margin: float | None = Field(description="A change fails past (1 + margin) x last-good IAE.")
    last_good_kp: float
    last_good_ki: float
    last_good_iae: float | None = Field(
        description="Their normalised IAE of upward setpoint moves, s (None: not yet)."
    )
    last_good_iae_down: float | None = Field(
        None, description="Of downward moves (a non-linear plant answers them differently)."
    )
    last_good_seq: int
    judged_seq: int = Field(description="Changes up to this seq have a verdict.")
    pending: bool = Field(description="The gains in force differ from the last-good gains.")
    held_until_t: float | None = Field(
        description="Plant time until which the agent is held after a rollback or a rejection."
    )
    fence: Fence | None = Field(
        None, description="The fence a rollback put up, while it stands (None: no fence)."
    )
    paused_until_t: float | None = Field(
        None,
        description="Plant time until which tuning pauses because the loop oscillates "
        "(status oscillating; extended while it does).",
    )
    detune_floor_kp: float | None = Field(
        None,
        description="An operator's detune of the last-good gains, adopted and not yet "
        "judged: no automatic rollback goes past it (None: none; docs/tuner.md, Verdicts).",
    )
    detune_floor_ki: float | None = None
    cut_short: int = Field(
        0,
        description="Setpoint responses the next move cut short (before the 2 RL periods a "
        "response is judged over) since the last complete one: none of them judges a change.",
    )
    unsettled_moves: int = Field(
        0,
        description="Setpoint moves since the last complete response that opened none: the "
        "loop had not settled from the move before (within 20 % of the move plus the noise).",
    )
    why: str | None = Field(
        None,
        description="While a change is pending: what its verdict waits for (responses cut "
        "short, moves on an unsettled loop, with their numbers, and the next step); None "
        "otherwise.",
    )


class Proposal(BaseModel):
    """An advisory loop's pending proposal (accept or reject it by its seq)."""

    seq: int
    kp: float
    ki: float
    dkp: float = Field(description="Change from the gains in force.")
    dki: float
    kp_in_force: float
    ki_in_force: float
    reason: str = Field(
        description="What made it: 'agent' (the agent's steps), 'model' (the tuning from "
        "an identified model), 'rollback' (back to the last-good gains) or 'reset' (the "
        "registered gains: an advisory loop's reset)."
    )
    made_t: float | None = Field(
        None, description="Plant time (s) it was made (None: a snapshot of before session 41)."
    )
    at_reach: bool = Field(
        False,
        description="It lies at its reach of the gains in force (3 guard steps): the "
        "agent's steps walk it no farther, it waits for a decision.",
    )
    refused: str | None = Field(
        None,
        description="Why it may not be accepted now (an accept is a 409): the plant "
        "is not the one it was made for, or the gains in force moved away from it.",
    )


class Performance(BaseModel):
    """``GET /loops/{id}/performance``."""

    loop_id: str
    time_unit_s: float | None = Field(description="Seconds per the loop's time unit.")
    last: ResponseFigures | None
    history: list[ResponseFigures] = Field(description="Recent complete responses, newest first.")
    window: WindowFigures
    verification: Verification


class Refused(BaseModel):
    """A loop's samples last refused, and why: the run of refusals for one reason up to
    now (a gateway's integrator sees here what the tuner's log and the global
    ``pitune_samples_rejected_total{reason}`` say of every loop at once)."""

    reason: str = Field(description="The reject reason (docs/protocol.md, Accounting).")
    detail: str = Field(description="The last refusal's detail, e.g. the sample's t.")
    count: int = Field(
        description="Samples refused for this reason since the run's first refusal (one "
        "for another reason starts a new run; samples taken between do not)."
    )
    since_wall: float = Field(description="Wall time (Unix s) of the run's first refusal.")
    last_wall: float = Field(description="Wall time (Unix s) of its last.")
