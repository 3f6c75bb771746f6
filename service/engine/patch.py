"""``PATCH /loops/{id}``'s body: the fields of a loop's configuration an operator may change
in place, each checked as at registration (:mod:`service.engine.config`)."""

from __future__ import annotations

from typing import Annotated

from pydantic import BaseModel, ConfigDict, Field

from service.engine.config import (
    Damping,
    ExcitationPeriods,
    ExcitationStep,
    Fraction,
    LoopConfig,
    Margin,
    Periods,
    Tolerance,
    check_bounds,
    check_given_bounds,
)
from service.wire.protocol import Gain, GatewayId, Mode


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

    def apply(self, config: LoopConfig) -> LoopConfig:
        """The patched config; raises ValueError if the bounds become inconsistent."""
        top = self.model_dump(include={"mode", "forgetting"}, exclude_none=True)
        if "gateway" in self.model_fields_set:  # an explicit null is a change here
            top["gateway"] = self.gateway
        guard = config.guard.model_copy(
            update=self.model_dump(exclude={"mode", "forgetting", "gateway"}, exclude_none=True)
        )
        if config.scaling is None:
            check_given_bounds(guard, config.kp, config.ki)
        else:
            check_bounds(guard, config.kp, config.ki)
        return config.model_copy(update={**top, "guard": guard})
