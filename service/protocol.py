"""Moved to :mod:`service.wire.protocol`; this path stays for gateways that import it."""

from service.wire.protocol import *  # noqa: F403
