"""The operator console at ``/ui``: overview of every loop, a page per loop with live
trends and actions, the tuner's health (see docs/console.md).

``router`` is an :class:`fastapi.APIRouter` the admin API includes; it reads the app's
``state.tuner`` and ``state.settings`` and the tuner's ring of recent samples
(``tuner.recent``, :mod:`service.daemon.recent`) when it has one. Its assets (pages,
scripts, the vendored uPlot with its licence) are package files: no CDN, no build step.
"""

from service.daemon.console.routes import router

__all__ = ["router"]
