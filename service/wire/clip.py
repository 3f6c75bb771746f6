"""Text from the wire shown to people (log lines, a loop's ``refused`` view): clipped.

A sender picks a rejection's detail (a samples key, a batch's ``"v"``, a loop id): at
any length it would make one log line or view field that long (a 4 MB ``"v"``, one 4 MB
WARNING line). Escaping control characters (newlines, terminal escapes) is the log's,
which shows the clipped text with ``repr`` (:meth:`service.daemon.metrics.Metrics.reject`).
"""

from __future__ import annotations

DETAIL_MAX = 200
"""Most characters of wire text kept in a log line or view field."""


def clipped(text: str) -> str:
    """``text``, cut to :data:`DETAIL_MAX` characters, saying how long it was."""
    if len(text) <= DETAIL_MAX:
        return text
    return f"{text[:DETAIL_MAX]}... ({len(text):,} chars)"
