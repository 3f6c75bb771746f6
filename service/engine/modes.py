"""Mode codes: a loop's :class:`~service.wire.protocol.Mode` as a small integer in the
engine's arrays (the order of the enum)."""

from service.wire.protocol import PUBLISHED_MODES, Mode

_MODES = list(Mode)
_CODE = {m: i for i, m in enumerate(_MODES)}
AUTO, ADVISORY, FROZEN, SHADOW = (
    _CODE[m] for m in (Mode.auto, Mode.advisory, Mode.frozen, Mode.shadow)
)
PUBLISHING = tuple(sorted(_CODE[m] for m in PUBLISHED_MODES))
"""The codes of :data:`~service.wire.protocol.PUBLISHED_MODES`."""
