"""The tuner's flood limit, one rule for the tuner (:mod:`service.engine.table`) and for
the gateways that pace themselves under it (:mod:`service.gateways.backlog`)."""

MAX_SAMPLE_RATE_HZ = 1000.0
"""The tuner's flood limit (default): a bucket of :func:`burst` samples per loop, refilled
at this many per second of its wall clock, whatever their ``t``; a sample that finds the
bucket empty is rejected as ``flood`` (docs/protocol.md, Accounting)."""


def burst(rate_hz: float) -> float:
    """The bucket's size at ``rate_hz`` samples a second: one second's worth, at least one
    sample (a limit below 1/s still takes a sample at a time)."""
    return max(float(rate_hz), 1.0)
