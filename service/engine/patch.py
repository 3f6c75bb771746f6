"""``PATCH /loops/{id}``'s body: the fields of a loop's configuration an operator may change
in place, each checked as at registration (:mod:`service.engine.config`)."""

from __future__ import annotations

from typing import Annotated

from pydantic import BaseModel, ConfigDict, Field, ValidationError, model_validator

from service.engine.config import (
    NEEDS_IDENTIFICATION,
    Damping,
    ExcitationPeriods,
    ExcitationStep,
    Fraction,
    LoopConfig,
    Margin,
    Periods,
    Tolerance,
)
from service.wire.protocol import Gain, GatewayId, Mode

NULL_IS_DEFAULT = frozenset(
    {"kp_min", "kp_max", "ki_min", "ki_max", "identify", "auto_rescale", "gateway"}
)
"""Fields whose null is a value: the default again (bounds from the scaling, the site's
identification settings, one gains message per loop)."""


class LoopPatch(BaseModel):
    """Body of ``PATCH /loops/{id}``: fields to change, others untouched."""

    model_config = ConfigDict(extra="forbid")

    mode: Mode | None = None
    forgetting: Annotated[float, Field(strict=True, gt=0.0, le=1.0)] | None = None
    kp_min: Gain | None = None
    kp_max: Gain | None = None
    ki_min: Gain | None = None
    ki_max: Gain | None = None
    max_rel_change: Fraction | None = None
    noise_damping: Damping | None = None
    settle_steps: Periods | None = None
    max_sensitivity: Damping | None = None
    stale_periods: Annotated[float, Field(strict=True, ge=1.0, le=1e6)] | None = None
    excitation_periods: ExcitationPeriods | None = None
    excitation_min_step: ExcitationStep | None = None
    identify: bool | None = None
    hint_tolerance: Tolerance | None = None
    auto_rescale: bool | None = None
    envelope_guard: bool | None = None
    verify: bool | None = None
    verify_margin: Margin | None = None
    verify_overshoot: Margin | None = None
    cooldown_periods: Periods | None = None
    fence_periods: Periods | None = None
    gateway: GatewayId | None = Field(
        None, description="Set a gateway (batched gains), or null: one message per loop again."
    )

    @model_validator(mode="after")
    def _null_only_where_it_means_the_default(self) -> LoopPatch:
        valued = self.model_fields_set - NULL_IS_DEFAULT
        nulls = sorted(f for f in valued if getattr(self, f) is None)
        if nulls:
            raise ValueError(
                f"null is not a value of {', '.join(nulls)}: leave a field out to keep it "
                f"(null restores the default only for {', '.join(sorted(NULL_IS_DEFAULT))})"
            )
        return self

    def apply(self, config: LoopConfig) -> LoopConfig:
        """The patched config, checked as at registration: a bound set to null follows the
        scaling (or the identified model) again; ValueError if the bounds become
        inconsistent or a loop without scaling would never be identified."""
        given = {f: getattr(self, f) for f in self.model_fields_set}
        top = {f: given.pop(f) for f in ("mode", "forgetting", "gateway") if f in given}
        guard = config.guard.model_dump() | given
        if config.scaling is None and guard["identify"] is False:
            raise ValueError(NEEDS_IDENTIFICATION)
        try:
            return LoopConfig.model_validate(config.model_dump() | top | {"guard": guard})
        except ValidationError as exc:  # one line for the operator, not pydantic's dump
            rules = "; ".join(e["msg"].removeprefix("Value error, ") for e in exc.errors())
            raise ValueError(f"{rules} (nothing changed)") from None
