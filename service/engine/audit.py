"""Audit rows: one per change of a loop's gains or configuration.

The engine produces them (agent steps, adoptions, resets), the daemon adds its own
(registrations, patches, deletions) and the store persists them in this column order.
"""

from __future__ import annotations

AUDIT_COLUMNS = "loop_id, wall_time, t, seq, mode, reason, kp_old, ki_old, kp_new, ki_new, detail"
AUDIT_TYPES = (str, float, float, int, str, str, float, float, float, float, str)
"""The Python type of each column (None allowed in those SQL allows NULL in)."""

AuditRow = tuple
"""Values in :data:`AUDIT_COLUMNS` order; build with :func:`audit_row`."""


def audit_row(
    loop_id: str,
    wall_time: float,
    t: float | None,
    seq: int,
    mode: str,
    reason: str,
    old: tuple[float, float] | None,
    new: tuple[float, float] | None,
    detail: str = "",
) -> AuditRow:
    kp_old, ki_old = old or (None, None)
    kp_new, ki_new = new or (None, None)
    return (loop_id, wall_time, t, seq, mode, reason, kp_old, ki_old, kp_new, ki_new, detail)
