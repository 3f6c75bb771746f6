"""The agent's training box, and a model seen through a loop's scaling against it.

The envelope guard (:mod:`service.engine.watch`) pauses a loop whose identified model lies
beyond the box by :data:`ENVELOPE_MARGIN` (and resumes it within :data:`RESUME_MARGIN`);
the robustness guard (:mod:`service.engine.stepping`) acts on loops whose model lies
outside the box itself.
"""

from __future__ import annotations

from service.engine import identify
from service.units import AGENT_GAIN, Scaling

TRAINING_BOX = {"gain": (0.25, 1.0), "tau": (0.25, 1.0), "theta_ratio": (0.0, 1.0)}
"""The agent's training box (service/learn/env.py), agent units."""
ENVELOPE_MARGIN = 1.5
"""Factor beyond the training box (gain and tau; theta/tau up to 1.5) at which a loop is
out of the agent's envelope."""
RESUME_MARGIN = ENVELOPE_MARGIN / (1.0 + identify.MAX_REL_SE)
"""Factor beyond the training box's gain and tau (about 1.36) within which a paused loop's
confident model must come back to resume it: a tenth inside the edge, the precision a
confident model's K needs. Without it a plant at the edge flapped: with hints 3x off
(apparent gain or tau 0.1667, the edge) successive models of one plant differed by
0.01-0.6 %, and the loop paused and resumed at almost every assessment (12 pauses in 3 h).
Not theta/tau's, which resumes within the leaving edge: no scaling moves it and its
precision is not measured, and with this margin a plant at theta/tau 1.4 paused by one
model at 1.55 stayed paused for good under models at its true 1.4."""


def apparent(scaling: Scaling, m: identify.Model) -> dict[str, float]:
    return {
        "gain": scaling.apparent_gain(m.k),
        "tau": scaling.apparent_tau(m.tau),
        "theta_ratio": m.theta / m.tau,
    }


def as_seen(scaling: Scaling, m: identify.Model) -> dict:
    """A model as the envelope guard judges it, in its audit rows and a paused loop's
    why: an integrator's K (PV units per output unit per second) and dead time (s), else
    its :func:`apparent` gain, tau and theta/tau."""
    if m.integrating:
        return {"integrating": True, "k_per_s": m.slope, "theta_s": m.theta_i}
    return apparent(scaling, m)


def toward_box(app: dict[str, float], k_margin: float, tau_margin: float) -> dict:
    """Apparent gain and tau moved toward the box's centre by the given relative margins."""
    mid = AGENT_GAIN

    def shrink(x: float, r: float) -> float:
        return x / (1 + r) if x > mid else x * (1 + r)

    return {**app, "gain": shrink(app["gain"], k_margin), "tau": shrink(app["tau"], tau_margin)}


def in_box(scaling: Scaling, m: identify.Model) -> bool:
    """Whether a model, seen through ``scaling``, lies inside the training box itself (no
    margin): the robustness guard checks the loops outside it (service.engine.stepping)."""
    app = apparent(scaling, m)
    return (
        TRAINING_BOX["gain"][0] <= app["gain"] <= TRAINING_BOX["gain"][1]
        and TRAINING_BOX["tau"][0] <= app["tau"] <= TRAINING_BOX["tau"][1]
        and app["theta_ratio"] <= TRAINING_BOX["theta_ratio"][1]
    )


def edges(margin: float = ENVELOPE_MARGIN) -> dict[str, tuple[float, float]]:
    """The envelope's edges, agent units: gain and tau within ``margin`` of the training
    box, theta/tau always within :data:`ENVELOPE_MARGIN` (see :data:`RESUME_MARGIN`)."""
    return {
        "gain": (TRAINING_BOX["gain"][0] / margin, TRAINING_BOX["gain"][1] * margin),
        "tau": (TRAINING_BOX["tau"][0] / margin, TRAINING_BOX["tau"][1] * margin),
        "theta_ratio": (0.0, TRAINING_BOX["theta_ratio"][1] * ENVELOPE_MARGIN),
    }


def in_envelope(app: dict[str, float], margin: float = ENVELOPE_MARGIN) -> bool:
    """Whether apparent K, tau and theta/tau lie within :func:`edges` of ``margin``
    (:data:`ENVELOPE_MARGIN`; a paused loop resumes within :data:`RESUME_MARGIN`)."""
    return all(lo <= app[k] <= hi for k, (lo, hi) in edges(margin).items())
