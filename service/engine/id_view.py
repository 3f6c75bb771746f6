"""The identification's part of a loop's view (``GET /loops/{id}``): the models it
identified, the events they come from, the flags (service.engine.views builds it from
:class:`service.engine.id_state.IdState`)."""

from __future__ import annotations

from pydantic import BaseModel, Field

from service.engine.identify import LUMP_THETA


class IdentifiedModel(BaseModel):
    """An FOPTD model identified from closed-loop data (engineering units, seconds)."""

    k: float = Field(description="Process gain, PV units per output unit.")
    tau: float = Field(description="Time constant, s.")
    theta: float = Field(description="Dead time, s.")
    noise: float = Field(description="Residual rms, PV units (the measurement noise).")
    move: float = Field(
        description="Typical setpoint move of the events (an output step's: the PV change it "
        "makes), PV units."
    )
    r2: float = Field(description="Share of the PV's variance the model explains.")
    k_rse: float | None = Field(description="Relative standard error of K.")
    tau_rse: float | None = Field(
        description="Relative standard error of tau (of a lumped model: of tau + theta)."
    )
    integrating: bool = Field(description="An integrating model K/s e^-theta s fits better.")
    slope: float = Field(
        0.0,
        description="K of the integrating alternative K/s e^-theta s, PV units per output "
        "unit per s: the process's gain when 'integrating' (k, tau, theta then say nothing).",
    )
    theta_i: float = Field(0.0, description="The integrating alternative's dead time, s.")
    events: int = Field(description="Events whose response stands out of the noise.")
    prediction: float | None = Field(
        description="Rms error, in noise units, of the earlier events' model on the last."
    )
    confidence: float = Field(description="0..1: excitation x precision x consistency.")
    confident: bool
    lumped: bool = Field(
        False,
        description="Only setpoint or output ramps slower than the loop excited it: K and tau "
        f"+ theta are identified, theta is {LUMP_THETA:g} of that lag (assumed).",
    )


class IdentificationEvent(BaseModel):
    """A setpoint move (or an output step in manual) and the data up to the next, as
    identification saw it."""

    t0: float
    t1: float
    n: int = Field(description="Samples recorded.")
    move: float = Field(description="The setpoint move, PV units.")
    ramp_s: float | None = Field(0.0, description="Seconds it ramped (null: still ramping).")
    snr: float | None = Field(description="Modelled response over the noise (peak to peak).")
    excited: bool
    op_move: float = Field(
        0.0,
        description="The output step an operator made in manual that opened the event "
        "(output units; 0: a setpoint move's event).",
    )


class Identification(BaseModel):
    """What the loop's identification knows (``GET /loops/{id}``)."""

    state: str = Field(
        description="'identifying' (no scaling yet), 'checking' (a scaling in force, "
        "identification running), 'off'."
    )
    why: str = Field(
        description="Why the latest assessment is not confident ('' if it is), or why its "
        "confident model is not used (one like a model in 'refuted')."
    )
    model: IdentifiedModel | None = Field(description="The latest assessment's model.")
    in_force: IdentifiedModel | None = Field(
        description="The identified model the scaling in force comes from (None: the hint)."
    )
    in_force_t: float | None = Field(description="Plant time it was adopted.")
    apparent: dict[str, float] | None = Field(
        description="The latest model in the agent's units under the scaling in force: "
        "gain, tau, theta/tau (training box 0.25-1, 0.25-1, 0-1)."
    )
    events: list[IdentificationEvent] = Field(
        description="The events of the latest assessment (the current segment)."
    )
    mismatch: bool
    out_of_envelope: bool
    refuted: list[IdentifiedModel] = Field(
        [],
        description="Models whose tuning rang and was rolled back, oldest first: a model "
        "like one is not used again until POST /loops/{id}/identify "
        "(docs/identification.md, Data identification does not take).",
    )
