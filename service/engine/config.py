"""A loop's registration (what the engine tunes it with) and the engine's view of it.

A :class:`LoopConfig` is also what the store persists: what a loop was registered
with, with the safety bounds resolved to explicit engineering values.
"""

from __future__ import annotations

import argparse
import json
from typing import Annotated, Literal

from pydantic import BaseModel, ConfigDict, Field, field_validator, model_validator

from service.engine.figures import Proposal, Refused, Verification
from service.engine.id_view import Identification
from service.units import (
    AGENT_GAIN_RANGE,
    AGENT_TAU,
    DEFAULT_FORGETTING,
    EXCITATION_PERIODS,
    Scaling,
    ScalingSpec,
)
from service.wire.protocol import (
    MAX_MAGNITUDE,
    Gain,
    GatewayId,
    Hold,
    LoopId,
    LoopStatus,
    Mode,
    RejectReason,
)

Fraction = Annotated[float, Field(strict=True, gt=0.0, le=10.0, allow_inf_nan=False)]
ExcitationPeriods = Annotated[float, Field(strict=True, ge=0.0, le=1e6, allow_inf_nan=False)]
ExcitationStep = Annotated[float, Field(strict=True, gt=0.0, le=100.0, allow_inf_nan=False)]
Tolerance = Annotated[float, Field(strict=True, gt=1.0, le=100.0, allow_inf_nan=False)]
Action = Literal["reverse", "direct"]
ACTION_SIGN = {"reverse": 1.0, "direct": -1.0}
"""Sign the engine applies to a loop's error and setpoint (docs/tuner.md, Controller
action): the agent, trained on positive-gain plants, sees a direct-acting loop with its
PV and SP negated, i.e. a plant of gain +|K|."""
REGISTRATION_GAIN_MARGIN = 100.0
"""A hinted registration's gains may lie at most this factor outside the agent's gain
range (``AGENT_GAIN_RANGE`` in agent units, 1e-4..5000 with the default) under the hint;
further out the gains or the hint are wrong by orders of magnitude (typically ki per
minute given as per second, or k_hat in other units), and the registration is refused
rather than the default guard widened to match."""
Damping = Annotated[float, Field(strict=True, ge=0.0, le=100.0, allow_inf_nan=False)]
Margin = Annotated[float, Field(strict=True, gt=0.0, le=10.0, allow_inf_nan=False)]
Periods = Annotated[float, Field(strict=True, ge=0.0, le=1e6, allow_inf_nan=False)]


class Guard(BaseModel):
    """Per-loop safety limits. Unset bounds default to the agent's training range."""

    model_config = ConfigDict(extra="forbid")

    kp_min: Gain | None = None
    kp_max: Gain | None = None
    ki_min: Gain | None = Field(None, description="Per second, like ki.")
    ki_max: Gain | None = Field(None, description="Per second, like ki.")
    max_rel_change: Fraction = Field(
        0.5,
        description="Largest relative change per update: each gain stays within "
        "[old / (1 + r), old * (1 + r)].",
    )
    noise_damping: Damping = Field(
        2.0,
        description="Noise damping of the agent's steps: each step's change of the gains "
        "is scaled by e^2 / (e^2 + (d sigma)^2), e the error the agent reads at the end of "
        "the RL period and sigma the measured noise (the monitor's estimate; below 1 % of "
        "pv_scale a loop counts as noise-free and is never damped), d this setting (2: "
        "docs/tuner.md, Robustness measures); 0 turns it off.",
    )
    settle_steps: Periods = Field(
        20.0,
        description="Settling: from this many agent steps into an episode on, each step's "
        "change of the gains is scaled by this / n (n the steps so far), down to a tenth, "
        "until the agent keeps asking for a large change (a plant that moved): full steps "
        "again (docs/tuner.md, Robustness measures 7). 0 turns it off.",
    )
    max_sensitivity: Damping = Field(
        1.6,
        description="Robustness guard: with an identified model (guard.identify), each "
        "agent step's gains are scaled down together until the loop's largest sensitivity "
        "on the model is at most this (and its gain margin at least Ms / (Ms - 1)); 1.6: "
        "the best fixed gains of the training box reach 1.35, SIMC's 1.27, the textbook "
        "range is 1.2-2. 0 turns it off. Without a model it does nothing.",
    )
    stale_periods: Annotated[float, Field(strict=True, ge=1.0, le=1e6)] = Field(
        5.0, description="Tuning pauses after this many sample periods without a sample."
    )
    excitation_periods: ExcitationPeriods = Field(
        EXCITATION_PERIODS,
        description="Excitation gate: the agent steps only in the RL periods that end "
        "within this many RL periods of a setpoint change (it learns from setpoint "
        "responses and detunes a loop that nobody moves); 0 turns the gate off.",
    )
    excitation_min_step: ExcitationStep = Field(
        0.2,
        description="Smallest setpoint change that counts, in agent units (multiples of "
        "pv_scale). Gateways sending only e: a jump of e between two samples.",
    )
    identify: bool | None = Field(
        None,
        description="Identify the loop's FOPTD model from its closed-loop data (needs sp "
        "and pv in the samples). A loop registered without scaling is tuned only once "
        "identified; a hinted loop's hint is checked against the model. Default (null): "
        "on for a loop registered without scaling; for a hinted one the tuner's "
        "identify_hinted_loops (on: its hint is checked; memory and CPU per loop on the "
        "move, docs/identification.md).",
    )
    hint_tolerance: Tolerance = Field(
        2.0,
        description="The identified K or tau disagreeing with the scaling in force by more "
        "than this factor flags the loop (status hint_mismatch, audit 'mismatch').",
    )
    auto_rescale: bool | None = Field(
        None,
        description="On a mismatch, rescale the loop to the identified model (audit "
        "'rescaled') and restart its episode, instead of only flagging it. Default "
        "(null): the tuner's auto_rescale (off).",
    )
    model_tuning: bool = Field(
        True,
        description="When identification puts a model in force for a loop without a hint, "
        "raise gains well below the model's SIMC tuning (tau_c = 2 tau) to it in one "
        "change (reason 'model', verified like any change) instead of letting the agent "
        "walk them up by max_rel_change per update; after a rescale or an envelope pause, "
        "set gains well off it either way to it (docs/identification.md).",
    )
    model_band: Tolerance | None = Field(
        1.5,
        description="While an identified model is in force (a loop registered without a "
        "hint, or rescaled), keep the agent's gains within this factor either way of the "
        "model's SIMC tuning (tau_c = 2 tau), inside the bounds: on a noisy loop the agent "
        "walks them far below it (docs/identification.md, Model band). null: off.",
    )
    model_check: Tolerance | None = Field(
        1.5,
        description="With an identified model in force, hold an agent step whose gains the "
        "model predicts to do the paper's step test worse than this factor times its SIMC "
        "tuning and worse than the gains in force (counter model_holds, guard=model); when "
        "a newer confident model shows the plant moved (K or tau 3 standard errors off) and "
        "predicts the gains in force that much worse, put its tuning in force (reason "
        "'model'; docs/identification.md, Model check, The envelope guard). null: off.",
    )
    envelope_guard: bool = Field(
        True,
        description="Pause tuning (status out_of_envelope) while the identified dynamics, "
        "in agent units, lie outside the agent's training box by the envelope margin, or "
        "the process looks integrating. Switched off, a loop it paused resumes at once.",
    )
    verify: bool = Field(
        True,
        description="Verify every change of the gains on the next setpoint response and "
        "roll back (auto) or propose rolling back (advisory) one that made the loop worse "
        "or made it oscillate (docs/tuner.md, Performance and verification).",
    )
    verify_margin: Margin = Field(
        0.4,
        description="A change fails when its response's IAE per unit move exceeds the "
        "last-good gains' (same direction of move) by more than this share (0.4: no false "
        "rollback in 1,000 good changes with 2 % noise, every doubled IAE fails, and room "
        "for a non-linear plant's operating points: docs/tuner.md).",
    )
    verify_overshoot: Margin = Field(
        0.5,
        description="A change also fails when its response overshoots the new setpoint by "
        "more than this share of the move, beyond 3 noise sigmas (0.5: a quarter-decay "
        "response; one response in about 8,600 of the robustness suite with the hints "
        "checked crossed it, a load step inside it, and the loops the agent drove to ring "
        "on a wrong, trusted hint did: docs/tuner.md, Verdicts). 10: off.",
    )
    cooldown_periods: Periods = Field(
        8.0,
        description="RL periods the agent is held after a rollback or a rejected proposal.",
    )
    fence_periods: Periods = Field(
        40.0,
        description="RL periods after a rollback for overshoot or oscillation (or an "
        "operator's) during which the agent's steps stop short of the gains undone (0.8 of "
        "them, or halfway from the restored ones when nearer), on each gain the undone "
        "change moved: it does not climb straight back to gains that rang; 0: no fence.",
    )


def guard_option(text: str) -> dict:
    """A command line's ``--guard``: a JSON object of guard settings, checked as a loop's
    guard (``pitune evaluate --robust``, ``pitune bench``), so that a wrong one is refused
    with its reason before anything runs."""
    try:
        settings = json.loads(text)
        Guard.model_validate(settings)  # a list or a wrong value: a ValidationError
    except ValueError as exc:  # (JSONDecodeError and ValidationError are ValueErrors)
        raise argparse.ArgumentTypeError(f"not a loop's guard settings: {exc}") from None
    return settings


class LoopConfig(BaseModel):
    """Registration of a loop (body of ``POST /loops``)."""

    model_config = ConfigDict(
        extra="forbid",
        json_schema_extra={
            "examples": [
                {
                    "id": "LIC-101",
                    "kp": 0.5,
                    "ki": 0.01,
                    "sample_period_s": 1.0,
                    "scaling": {"k_hat": 1.2, "tau_hat": 30.0, "pv_scale": 10.0},
                },
                {"id": "TIC-7", "kp": 2.0, "ki": 0.02, "sample_period_s": 5.0},
            ]
        },
    )

    id: LoopId
    kp: Gain = Field(description="Registered proportional gain, engineering units.")
    ki: Gain = Field(description="Registered integral gain, engineering units per second.")
    sample_period_s: Annotated[float, Field(strict=True, gt=0.0, le=1e6)] = Field(
        description="The gateway's sample clock, seconds (staleness is measured in it)."
    )
    scaling: ScalingSpec | None = Field(
        None,
        description="The model hint (section 5.4 scaling). Absent: the loop starts "
        "'identifying' and is tuned once its model is identified from its data.",
    )
    mode: Mode = Mode.auto
    action: Action = Field(
        "reverse",
        description="Controller action, as set in the DCS's PID block: 'reverse' (the "
        "output falls as the PV rises: a process of positive gain, e.g. heating, a level "
        "filled by the manipulated flow) or 'direct' (the output rises with the PV: a "
        "process of negative gain, e.g. cooling, a level drained by the manipulated "
        "flow). kp, ki and k_hat are magnitudes either way, as in the block; samples "
        "carry sp and pv (or e = sp - pv) as measured.",
    )
    forgetting: Annotated[float, Field(strict=True, gt=0.0, le=1.0)] = Field(
        DEFAULT_FORGETTING,
        description="Forgetting factor of the agent's hidden state (the paper's gamma).",
    )
    guard: Guard = Guard()
    gateway: GatewayId | None = Field(
        None,
        description="Gateway fronting the loop: its gains go out batched with the other "
        "loops of that gateway on {prefix}/gateways/{gateway}/gains (GainsBatch) instead of "
        "one message on {prefix}/loops/{id}/gains.",
    )

    @model_validator(mode="after")
    def _resolve_bounds(self) -> LoopConfig:
        if self.scaling is None:  # bounds left unset resolve once the model is identified
            check_given_bounds(self.guard, self.kp, self.ki)
            return self
        self.guard = resolve_bounds(self.guard, self.scaling.resolve(), self.kp, self.ki)
        check_bounds(self.guard, self.kp, self.ki)
        return self

    @property
    def action_sign(self) -> float:
        """+1 reverse, -1 direct: see :data:`ACTION_SIGN`."""
        return ACTION_SIGN[self.action]

    @property
    def resolved_scaling(self) -> Scaling | None:
        return None if self.scaling is None else self.scaling.resolve()


NEEDS_IDENTIFICATION = (
    "a loop without scaling is tuned only once its model is identified: give a model hint "
    "(scaling) or leave guard.identify on"
)


class Registration(LoopConfig):
    """A new registration (``POST /loops``, ``/loops/bulk``): a :class:`LoopConfig` that
    also passes the sanity rules below. Configs loaded from the store are not judged
    again: a rule added later must not stop a tuner from loading the loops it has."""

    @field_validator("kp", "ki", mode="before")
    @classmethod
    def _magnitude(cls, value: object, info) -> object:
        if isinstance(value, int | float) and not isinstance(value, bool):
            if value < 0:
                raise ValueError(
                    f"{info.field_name} is a magnitude, as in the DCS's PID block: a loop "
                    "whose output must rise with the PV is registered with positive gains "
                    "and action 'direct'"
                )
            if value == 0 and info.field_name == "ki":
                raise ValueError(
                    "ki = 0 (a P-only loop) is not tuned: pitune tunes PI loops and a "
                    "P-only loop keeps an offset the agent was never trained on. Give the "
                    "DCS block an integral first, e.g. ki = kp / tau_hat (reset time = the "
                    "process time constant), and register that"
                )
        return value

    @model_validator(mode="after")
    def _sane(self) -> Registration:
        scaling = self.resolved_scaling
        if scaling is None:
            if self.guard.identify is False:
                raise ValueError(NEEDS_IDENTIFICATION)
            return self
        tau_s = scaling.time_unit_s * AGENT_TAU
        if tau_s < self.sample_period_s:
            raise ValueError(
                f"the hinted time constant {tau_s:g} s is shorter than the sample period "
                f"{self.sample_period_s:g} s (RL period {scaling.rl_period_s:g} s): a process "
                "faster than its sampling shows no dynamics to tune from. Check tau_hat "
                "(seconds) and sample_period_s"
            )
        lo, hi = AGENT_GAIN_RANGE
        lo, hi = lo / REGISTRATION_GAIN_MARGIN, hi * REGISTRATION_GAIN_MARGIN
        for name, gain, unit in (
            ("kp", self.kp, scaling.kp_per_agent),
            ("ki", self.ki, scaling.ki_per_agent),
        ):
            if not lo <= gain / unit <= hi:
                raise ValueError(
                    f"{name} = {gain:g} is {gain / unit:.3g} in the agent's units under this "
                    f"hint, outside {lo:g}..{hi:g} ({REGISTRATION_GAIN_MARGIN:g}x the agent's "
                    f"range): the gain or the hint is off by orders of magnitude (ki is per "
                    f"second; k_hat in PV units per output unit). Under this hint {name} "
                    f"lies within {lo * unit:.3g}..{hi * unit:.3g}"
                )
        return self


def resolve_bounds(guard: Guard, scaling: Scaling, kp: float, ki: float) -> Guard:
    """Fill unset bounds from the agent's training range, widened to hold (kp, ki).

    Extreme scalings map the range beyond the largest gain the wire carries (k_hat and
    tau_hat of 1e-6 put ki_max at 1.25e13): the upper bounds are clamped to it, and the
    result validated, so that the stored config always loads again.
    """
    if None not in (guard.kp_min, guard.kp_max, guard.ki_min, guard.ki_max):
        return guard  # (a stored config's: validating it again was a fifth of its load)
    lo, hi = AGENT_GAIN_RANGE
    defaults = {
        "kp_min": min(lo * scaling.kp_per_agent, kp),
        "kp_max": min(max(hi * scaling.kp_per_agent, kp), MAX_MAGNITUDE),
        "ki_min": min(lo * scaling.ki_per_agent, ki),
        "ki_max": min(max(hi * scaling.ki_per_agent, ki), MAX_MAGNITUDE),
    }
    unset = {k: v for k, v in defaults.items() if getattr(guard, k) is None}
    return Guard.model_validate({**guard.model_dump(), **unset})


def check_given_bounds(guard: Guard, kp: float, ki: float) -> None:
    """:func:`check_bounds` for the bounds that are set (a loop without scaling)."""
    inf = float("inf")
    full = guard.model_copy(
        update={
            "kp_min": guard.kp_min if guard.kp_min is not None else 0.0,
            "kp_max": guard.kp_max if guard.kp_max is not None else inf,
            "ki_min": guard.ki_min if guard.ki_min is not None else 0.0,
            "ki_max": guard.ki_max if guard.ki_max is not None else inf,
        }
    )
    check_bounds(full, kp, ki)


def check_bounds(guard: Guard, kp: float, ki: float) -> None:
    if not guard.kp_min < guard.kp_max or not guard.ki_min < guard.ki_max:
        raise ValueError(
            f"bounds must satisfy min < max: kp {guard.kp_min:.4g}..{guard.kp_max:.4g}, "
            f"ki {guard.ki_min:.4g}..{guard.ki_max:.4g}"
        )
    if not (guard.kp_min <= kp <= guard.kp_max and guard.ki_min <= ki <= guard.ki_max):
        raise ValueError(
            f"the registered gains must lie within the bounds: kp = {kp:.4g} in "
            f"{guard.kp_min:.4g}..{guard.kp_max:.4g}, ki = {ki:.4g} in "
            f"{guard.ki_min:.4g}..{guard.ki_max:.4g}"
        )


class Counters(BaseModel):
    samples: int = Field(description="Samples accepted.")
    rejected: int = Field(description="Samples rejected (known loop, bad content).")
    steps: int = Field(description="RL steps taken.")
    updates: int = Field(description="Gains messages published.")
    quiet: int = Field(
        0, description="RL periods skipped by the excitation gate (no setpoint change)."
    )
    faults: int = Field(
        0,
        description="Due RL steps left out because the loop's numbers went non-finite "
        "(audit reason 'fault'); the other loops of the batch were stepped.",
    )
    identified: int = Field(
        0, description="Models adopted from identification (first scaling or a rescale)."
    )
    mismatches: int = Field(
        0, description="Times the identified model was found to disagree with the scaling."
    )
    envelope_pauses: int = Field(0, description="Times tuning paused as out_of_envelope.")
    oscillation_pauses: int = Field(
        0, description="Times tuning paused because the loop oscillated (status oscillating)."
    )
    output_holds: int = Field(
        0, description="Times the data showed the output held at a limit (status saturated)."
    )
    model_holds: int = Field(
        0,
        description="Agent steps held by the model check (guard.model_check): gains the "
        "identified model predicted to track much worse than its own tuning.",
    )


class LoopView(BaseModel):
    """A loop as ``GET /loops/{id}`` shows it."""

    config: LoopConfig
    scaling: Scaling | None = Field(
        description="The unit mapping in force (the hint's, or the identified model's); "
        "None while identifying."
    )
    rl_period_s: float | None = Field(description="Plant seconds between two gain updates.")
    kp: float
    ki: float
    mode: Mode
    status: LoopStatus
    status_why: str | None = Field(
        None,
        description="For any status but tuning: what holds the loop, with the numbers, and "
        "the operator's next step (docs/tuner.md, Status and holds).",
    )
    seq: int
    last_sample_t: float | None
    int_e: float = Field(description="Integral of the error since reset, agent units.")
    hidden_norm: float = Field(description="Norm of the agent's hidden state (0 after reset).")
    counters: Counters
    refused: Refused | None = Field(
        None, description="The samples last refused, and why (None: none since the start)."
    )
    refused_counts: dict[RejectReason, int] = Field(
        default_factory=dict,
        description="Samples refused by reason since the loop was registered (kept across "
        "restarts as far as the last snapshot, as counters.rejected, whose total they "
        "split; a loop registered before session 41: since the upgrade), the reasons with "
        "any: e.g. {'flood': 12, 'out_of_order': 3}. wrong_gateway is counted globally "
        "only, not on the loop it names.",
    )
    identification: Identification | None = None
    verification: Verification | None = Field(
        None, description="Last-good gains and the verification state (verify-or-rollback)."
    )
    proposal: Proposal | None = Field(
        None, description="An advisory loop's pending proposal (accept or reject it by seq)."
    )
    hold: Hold | None = Field(
        None,
        description="What holds the agent's steps while the status may still read "
        "'tuning': the cool-down after a change of the tuner's own, or the model check "
        "(None: neither).",
    )
    oscillating: bool = Field(
        False,
        description="The oscillation detector flags the loop now, whatever its status "
        "(one held for gains out of bounds, in manual, quiet, ...; performance.window).",
    )


class Configs:
    """Loop configs by id, held as compact JSON without the fields at their defaults (a
    parsed :class:`LoopConfig` costs ~2.4 KB per loop; its full JSON ~0.5 KB, this ~0.25
    KB). Reading one parses it: only the admin API does."""

    def __init__(self) -> None:
        self._json: dict[str, bytes] = {}

    def __getitem__(self, loop_id: str) -> LoopConfig:
        return LoopConfig.model_validate_json(self._json[loop_id])

    def raw(self, loop_id: str) -> bytes:
        """The config's JSON, unparsed (to parse it outside the table's lock)."""
        return self._json[loop_id]

    def __setitem__(self, loop_id: str, config: LoopConfig) -> None:
        self._json[loop_id] = config.model_dump_json(exclude_defaults=True).encode()

    def __delitem__(self, loop_id: str) -> None:
        del self._json[loop_id]

    def __contains__(self, loop_id: object) -> bool:
        return loop_id in self._json

    def __len__(self) -> int:
        return len(self._json)
