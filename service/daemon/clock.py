"""The tuner's clock: real time, or time running ``speed`` times faster (accelerated runs).

Every reading of the wall clock that the tuner keeps or acts on goes through
:class:`Clock`: the audit rows' ``wall_time``, the retention horizon (but a cluster's,
on the database's clock: :mod:`service.daemon.upkeep`) and the interval between
retention passes, the engine's flood limit and status (those two on
:meth:`Clock.steady`, which a step of the wall clock does not move:
:mod:`service.engine.steady`). An accelerated clock
(``clock_speed`` > 1, :mod:`service.bench.retention`) therefore makes a day of the
tuner's bookkeeping pass in ``86400 / speed`` real seconds without any other change of
behaviour; the plant clock is the gateways' own (the ``t`` of the samples), so the load
generator plays it at the same speed. Timeouts of I/O (lanes, store retries, snapshot
period) stay on real time: they are about the machine, not about the history.
"""

from __future__ import annotations

import time


class Clock:
    """``wall()`` (seconds since the epoch) and ``monotonic()``, ``speed`` times real time,
    both starting from the real clocks at construction."""

    def __init__(self, speed: float = 1.0) -> None:
        if not speed > 0.0:
            raise ValueError(f"clock speed must be positive, not {speed}")
        self.speed = speed
        self._wall0 = time.time()
        self._mono0 = time.monotonic()

    def monotonic(self) -> float:
        if self.speed == 1.0:
            return time.monotonic()
        return self._mono0 + self.speed * (time.monotonic() - self._mono0)

    def wall(self) -> float:
        return time.time() if self.speed == 1.0 else self.steady()

    def steady(self) -> float:
        """Seconds since the epoch as :meth:`wall` read at construction, advanced by
        :meth:`monotonic`: a clock that a step of the wall clock (NTP, ``date``) does not
        move, for elapsed-time rules (the engine's staleness and flood limit:
        :mod:`service.engine.steady`)."""
        return self._wall0 + self.speed * (time.monotonic() - self._mono0)

    def until(self, when: float) -> float:
        """Real seconds until :meth:`monotonic` reaches ``when``."""
        return (when - self.monotonic()) / self.speed
