"""PID-block gain forms and their conversion to pitune's parallel form.

pitune speaks the parallel form in engineering units, ``u = kp e + ki ∫e dt`` with
``ki`` per **second** (docs/protocol.md, Units). DCS PID blocks show their tuning in
other forms; a block's form is two independent choices plus the spans of the block's
scaling:

Proportional term (:class:`PTerm`)

* ``gain``: the controller gain. In engineering units if both spans are 1 (the default),
  else dimensionless (%/% of span, as DeltaV, Experion, 800xA, PCS 7 and Centum show it):
  ``kp = gain * op_span / pv_span``.
* ``band``: proportional band in % of span, ``PB = 100 / gain`` (Foxboro, Yokogawa's
  ``P`` on some blocks, older analog controllers): ``kp = (100 / PB) * op_span / pv_span``.

Integral term (:class:`ITerm`)

* ``ki_per_s``, ``ki_per_min``: an independent integral gain (parallel, "non-interacting
  independent" form), in the same scaling as the proportional gain:
  ``ki = i * op_span / pv_span`` per second, or that over 60 per minute.
* ``reset_s``, ``reset_min``: the ideal (standard, ISA) form's integral time Ti, seconds
  or minutes per repeat: ``ki = kp / Ti``.
* ``repeats_per_s``, ``repeats_per_min``: the ideal form's reset rate 1 / Ti:
  ``ki = kp * R`` (per second) or ``kp * R / 60`` (per minute).

The series (interacting) form equals the ideal form when the derivative time is zero;
pitune tunes PI loops only, so a block with derivative action must not be mapped (its
series/ideal conversions would also need Td). Every conversion is exact up to
rounding and round-trips (``tests/test_opcua_forms.py``).
"""

from __future__ import annotations

import math
from enum import StrEnum

from pydantic import BaseModel, ConfigDict, Field


class PTerm(StrEnum):
    gain = "gain"
    band = "band"


class ITerm(StrEnum):
    ki_per_s = "ki_per_s"
    ki_per_min = "ki_per_min"
    reset_s = "reset_s"
    reset_min = "reset_min"
    repeats_per_s = "repeats_per_s"
    repeats_per_min = "repeats_per_min"


class FormError(ValueError):
    """A gain value that has no parallel equivalent (zero, negative, not finite)."""


def _positive(name: str, value: float) -> float:
    value = float(value)
    if not (math.isfinite(value) and value > 0.0):
        raise FormError(f"{name} must be a positive finite number, got {value!r}")
    return value


class GainForm(BaseModel):
    """How one PID block shows its P and I terms (see the module docstring)."""

    model_config = ConfigDict(extra="forbid", frozen=True)

    p: PTerm = PTerm.gain
    i: ITerm = ITerm.reset_min
    pv_span: float = Field(1.0, gt=0.0, allow_inf_nan=False, description="PV range, eng. units")
    op_span: float = Field(1.0, gt=0.0, allow_inf_nan=False, description="OP range, eng. units")

    @property
    def _scale(self) -> float:
        """Engineering kp per unit of normalised gain."""
        return self.op_span / self.pv_span

    def to_parallel(self, p_value: float, i_value: float) -> tuple[float, float]:
        """The block's (P, I) values as pitune's (kp, ki per second)."""
        p_value, i_value = _positive("P", p_value), _positive("I", i_value)
        gain = 100.0 / p_value if self.p is PTerm.band else p_value
        kp = gain * self._scale
        match self.i:
            case ITerm.ki_per_s:
                ki = i_value * self._scale
            case ITerm.ki_per_min:
                ki = i_value * self._scale / 60.0
            case ITerm.reset_s:
                ki = kp / i_value
            case ITerm.reset_min:
                ki = kp / (60.0 * i_value)
            case ITerm.repeats_per_s:
                ki = kp * i_value
            case ITerm.repeats_per_min:
                ki = kp * i_value / 60.0
        return kp, ki

    def from_parallel(self, kp: float, ki: float) -> tuple[float, float]:
        """pitune's (kp, ki per second) as the block's (P, I) values."""
        kp, ki = _positive("kp", kp), _positive("ki", ki)
        gain = kp / self._scale
        p_value = 100.0 / gain if self.p is PTerm.band else gain
        match self.i:
            case ITerm.ki_per_s:
                i_value = ki / self._scale
            case ITerm.ki_per_min:
                i_value = 60.0 * ki / self._scale
            case ITerm.reset_s:
                i_value = kp / ki
            case ITerm.reset_min:
                i_value = kp / ki / 60.0
            case ITerm.repeats_per_s:
                i_value = ki / kp
            case ITerm.repeats_per_min:
                i_value = 60.0 * ki / kp
        return p_value, i_value

    def describe(self) -> str:
        p = "PB %" if self.p is PTerm.band else "gain"
        scaled = (
            ""
            if self.pv_span == self.op_span == 1.0
            else f", spans PV {self.pv_span:g} OP {self.op_span:g}"
        )
        return f"{p} + {self.i.value}{scaled}"
