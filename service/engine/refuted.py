"""Models refuted on a loop: a model whose tuning rang is not used again.

A model's tuning that makes the loop ring (an ``oscillation`` or ``overshoot`` verdict on
the change that put it in force: :data:`service.engine.verify.REFUTING`) refutes the
model: the rollback restores the gains from before it and identification starts again
from new data (:func:`service.engine.watch.restart`, why :data:`~service.engine.watch.
REFUTED`). Where the plant looks like that model again under the gains rolled back to (a
valve whose gain is higher where the tuned loop drives it, or differs by direction; a
nonlinear process; dynamics a FOPTD model misses that show only at higher gains), the new
data gave the same model, whose tuning was applied, rang and was rolled back again, every
few setpoint moves (``tests/test_identify_refuted.py``'s ringing plant: 10 times in 30
moves hint-free, 8 times hinted). So the loop remembers the models refuted on it
(``IdState.refuted``, in the runtime snapshot; the last :data:`MAX_REFUTED`), and a
confident model like one of them (:func:`service.engine.model_check.refuted_like`) is
not used at all (:func:`declines`, from :func:`service.engine.watch._assess`):

* a loop without a scaling in force (registered without a hint) stays ``identifying`` at
  the gains rolled back to: no scaling, no gains published, the agent does not tune;
* a loop with one (its hint, or a model that differs) goes on as without the model: no
  mismatch flag, rescale, envelope verdict, followed or checked tuning, nor model check
  on it; the agent tunes on the scaling in force;
* the loop's ``why`` (the REST view's ``identification.why``) says so and what to do, and
  the first such model after each refutation is an audit row (reason ``refuted``).

``POST /loops/{id}/identify`` forgets them (:func:`~service.engine.watch.restart`: the
user's word that the plant changed, a valve repaired, or that models are to be tried
again); a loop registered again starts without them; a ``PATCH`` keeps them.
"""

from __future__ import annotations

import json
import math

from service.engine import identify, model_check, model_use
from service.engine.id_state import IdState, Refuted

MAX_REFUTED = 3
"""Refuted models a loop remembers (the oldest forgotten first): a loop whose models'
tunings ring again and again is not one a FOPTD model tunes, and the snapshot stays
small."""
LIKE_REFUTED = "a model like one whose tuning rang and was rolled back"
"""How the loop's ``why`` begins while a model like a refuted one is declined."""


def remembered(tb, s: int) -> list[Refuted]:
    """Slot ``s``'s refuted models with the one whose tuning a refuting verdict just rolled
    back (``IdState.tuned``; None in a snapshot from before it was kept), for the
    restart of its identification to keep."""
    st: IdState = tb.ident[s]
    t = float(tb.last_t[s])
    new = [] if st.tuned is None else [Refuted(st.tuned, t if math.isfinite(t) else None)]
    return [*st.refuted, *new][-MAX_REFUTED:]


def declines(tb, s: int, m: identify.Model, t: float, wall: float) -> bool:
    """Whether confident model ``m`` is like a model refuted on slot ``s`` and so not used:
    the loop's ``why`` says so, and the first time after the refutation an audit row
    (reason ``refuted``) records it."""
    r = model_check.refuted_like(tb, s, m)
    if r is None:
        return False
    st: IdState = tb.ident[s]
    at = "" if r.t is None else f" at t={r.t:.0f} s"
    meanwhile = (
        "the agent tunes on the scaling in force"
        if tb.scaled[s]
        else "the loop stays identifying at the gains rolled back to (tune it by hand, "
        "or register it with a scaling hint)"
    )
    st.why = (
        f"{LIKE_REFUTED}{at} (K {r.model.k:.3g}, tau {r.model.tau:.3g} s, theta "
        f"{r.model.theta:.3g} s): not used again; {meanwhile}. The plant may not be "
        "first-order at these gains (a valve's gain by opening or direction, a nonlinear "
        "process); POST /loops/{id}/identify tries models again"
    )
    if not r.told:
        r.told = True
        detail = {"model": m.as_dict(), "refuted": r.model.as_dict(), "refuted_t": r.t}
        model_use.audit(tb, s, t, wall, "refuted", json.dumps(detail, separators=(",", ":")))
    return True
