"""Moved to :mod:`service.gateways.base`; this path stays for gateways that import it."""

from service.gateways.base import *  # noqa: F403
