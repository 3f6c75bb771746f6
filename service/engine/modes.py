"""Mode codes: a loop's :class:`~service.wire.protocol.Mode` as a small integer in the
engine's arrays (the order of the enum)."""

from service.wire.protocol import Mode

_MODES = list(Mode)
_CODE = {m: i for i, m in enumerate(_MODES)}
AUTO, ADVISORY, FROZEN, SHADOW = (
    _CODE[m] for m in (Mode.auto, Mode.advisory, Mode.frozen, Mode.shadow)
)
PUBLISHING = (AUTO, ADVISORY)
"""The modes whose loops get gains messages (frozen and shadow loops get none)."""
