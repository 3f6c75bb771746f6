"""The plant-wide hold: one switch that stops the tuner changing any loop (an upset, a
start-up, a DCS change window), instead of a ``PATCH mode frozen`` per loop and the
memory of each loop's mode to undo it.

While the engine's table holds it (``tb.hold.held``, set by
:meth:`TuningEngine.set_hold <service.engine.engine.TuningEngine.set_hold>`), the one
rule is applied in two places, where the tuner makes a change of its own:

* :func:`service.engine.rules.ingest`: no loop falls due, so the agent is not stepped
  (no published step, no advisory proposal, no shadow step: the hidden state stays as
  it is) and no period counts as ``quiet``; a period that ends while held is simply not
  stepped (no burst of queued steps at the release);
* :func:`service.engine.first_tuning.apply`: no model's tuning (first tuning, after a
  rescale, the envelope guard's, the model check's ``followed`` and ``checked``) is put
  in force or proposed, as for a frozen loop; the model itself is (identification goes
  on: a hint-free loop identified while held tunes from its gains of before, and the
  agent takes them on after the release).

Everything else goes on: samples are taken, identification, the monitor and
verification run. The guard's automatic rollback of a change made before the hold still
goes out (it restores the last-good gains: the undo an operator wants), and so do an
operator's own actions (reset, rollback, accept or reject a proposal, identify).
"""

from __future__ import annotations

import datetime
import unicodedata
from typing import Annotated

from pydantic import AfterValidator, BaseModel, ConfigDict, Field

from service.wire.protocol import Hold

REASON_CHARS = 200
"""Most characters of a hold's reason: one line of an operator's display."""


_HANGUL_FILLERS = frozenset("\u115f\u1160\u3164\uffa0")
"""The letters Unicode makes default-ignorable: shown as nothing."""


def _one_line(reason: str) -> str:
    """A reason is shown on every loop's view, in the log and on the wire: one line of
    printable characters (no newline, terminal escape or bidi override to forge lines or
    reorder text), and saying something: a letter or a digit, not a Hangul filler
    (printable too, as are blank-looking U+2800 and combining marks alone)."""
    bad = next((c for c in reason if not c.isprintable()), None)
    if bad is not None:
        where = reason.index(bad)
        raise ValueError(
            f"the reason must be printable text on one line: U+{ord(bad):04X} at {where}"
        )
    if not any(unicodedata.category(c)[0] in "LN" and c not in _HANGUL_FILLERS for c in reason):
        raise ValueError("the reason must say something: it has no letter or digit")
    return reason


HoldReason = Annotated[str, Field(min_length=1, max_length=REASON_CHARS), AfterValidator(_one_line)]


class HoldRequest(BaseModel):
    """The body of ``PUT /hold``."""

    model_config = ConfigDict(extra="forbid")

    reason: HoldReason = Field(
        description=f"Why the plant is held (1 to {REASON_CHARS} printable characters, a "
        "letter or digit among them), shown on every loop's view and in the log."
    )


class PlantHold(BaseModel):
    """Whether the plant is held, since when, by whom and why (``GET /hold``)."""

    held: bool = False
    since: float | None = Field(None, description="Unix time the hold was set (None: not held).")
    by: str | None = Field(
        None, description="Who set it: 'api' (the admin token), 'ui:<name>' (the console)."
    )
    reason: str | None = None


RELEASED = PlantHold()


def after_put(hold: PlantHold, reason: str, actor: str, wall: float) -> PlantHold:
    """The hold after a ``PUT /hold`` at wall time ``wall``: a new one, or, already held,
    the same with the new reason (who set it and since when are kept: the plant has been
    held since then, whoever explains it now)."""
    if hold.held:
        return hold.model_copy(update={"reason": reason})
    return PlantHold(held=True, since=wall, by=actor, reason=reason)


def utc(wall: float) -> str:
    """A wall time as people read it (UTC, to the second)."""
    moment = datetime.datetime.fromtimestamp(wall, datetime.UTC)
    return moment.isoformat(timespec="seconds").replace("+00:00", "Z")


def loop_hold(hold: PlantHold) -> Hold:
    """What every loop's view and state reply say while the plant is held."""
    return Hold(
        guard="plant",
        why=(
            f"the plant-wide hold, set by {hold.by} at {utc(hold.since or 0.0)}: "
            f"{hold.reason}. The tuner steps, proposes and puts in force no gains for any "
            "loop (the guard's rollbacks of changes made before it, and operators' own "
            "actions, still go out). Next: DELETE /hold to release it (GET /hold)"
        ),
    )
