"""The verdict of each change in a loop's history (``GET /loops/{id}/history``).

The engine writes a verdict row when it judges changes (reason ``verified``,
``rollback`` or ``verdict``, with the seqs judged in its JSON detail: see
:mod:`service.engine.verify`); a change row (an agent step of an ``auto`` loop, a reset,
an adoption, an accepted proposal, a model's first tuning) takes the verdict of the
oldest newer verdict row whose seqs cover its seq, else ``pending`` past the loop's
judged seq (an adoption shares the seq of the update it replaced: the update's verdict
row comes between them). An agent step the model check held changed nothing (its
reason says ``verdict=none``; it keeps the seq of the change before it): no verdict.
Nor does a reset outside ``auto``: an ``advisory`` loop's is a proposal (session 41: it
showed the verdict of the change before it, ``rollback_proposed``), a ``frozen`` or
``shadow`` loop's changes the agent state only (no gains published, the seq unchanged);
told by its mode, which rows stored before session 41 have too.
"""

from __future__ import annotations

import orjson

from service.daemon.schemas import AuditEntry
from service.engine.stepping import NO_VERDICT

CHANGES = frozenset({"agent", "reset", "adopted", "accepted", "model"})
"""Audit reasons of a change of the gains in force (an advisory or shadow 'agent' or
'model' row is a proposal: no verdict; 'model': the first tuning from an identified
model, service/engine/first_tuning.py)."""
PROPOSALS = frozenset({"agent", "model", "reset"})
"""Change reasons that are proposals outside ``auto`` (or, a reset of a ``shadow`` or
``frozen`` loop, change nothing)."""
HELD = f"verdict={NO_VERDICT}"
"""The word of a held agent step's reason (:func:`service.engine.stepping._why`)."""
SCAN = 5000
"""Newest rows read to find the verdict rows of a page (a page deeper in the history
shows the verdicts recorded within the rows it reads)."""


def annotate(items: list[AuditEntry], judged_seq: int | None) -> None:
    """Set ``verdict`` on the change rows of ``items`` (newest first, contiguous), given
    the loop's judged seq (None: the loop is deleted, nothing is pending)."""
    covers: list[tuple[int, int, str]] = []
    for item in items:  # newest first: a change's verdict row comes before it
        if item.reason in ("verified", "rollback", "verdict"):
            detail = orjson.loads(item.detail)
            first, last = detail.get("seqs", (0, -1))
            covers.append((first, last, detail.get("verdict", "verified")))
            continue
        if item.reason not in CHANGES or (item.reason in PROPOSALS and item.mode != "auto"):
            continue
        if item.reason == "agent" and HELD in item.detail.split():
            continue
        # the first verdict after the change that covers its seq (an operator's change
        # shares the seq of the update it replaced, judged before it)
        for first, last, verdict in reversed(covers):
            if first <= item.seq <= last:
                item.verdict = verdict
                break
        else:
            if judged_seq is not None and item.seq > judged_seq:
                item.verdict = "pending"
