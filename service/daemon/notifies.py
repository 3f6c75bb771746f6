"""A cluster member's wait between two ticks: it reloads the loops other members changed
(``NOTIFY pitune_loops``) as their notifications come; a part of
:class:`~service.daemon.cluster.Cluster` (a mixin), which holds the state it uses."""

from __future__ import annotations

import logging
import time

import psycopg

log = logging.getLogger("pitune.cluster")
WAKE_POLL_S = 0.1
"""The longest a tick waits, once a member's token has gone, before it comes (the
wait for notifications is cut in slices this long to look)."""


class Notifies:
    def _wait_notifies(self, until: float) -> None:
        """Until the next tick (or a member's token going, :meth:`token_changed`): reload
        the loops other members changed."""
        while not self._stop.is_set():
            left = until - time.monotonic()
            if left <= 0 or self._wake.is_set():
                self._wake.clear()
                return
            changed: set[str] = set()
            try:
                wait = min(left, WAKE_POLL_S)
                for note in self._conn.notifies(timeout=wait, stop_after=1):
                    changed.update(note.payload.split(","))
                # take the rest queued meanwhile without waiting
                for note in self._conn.notifies(timeout=0.0):
                    changed.update(note.payload.split(","))
            except psycopg.Error:
                self._stop.wait(max(0.0, until - time.monotonic()))
                return
            changed |= self._reload_todo  # a reload that failed: again until it works
            if changed:
                try:
                    self.tuner.reload_loops(sorted(changed))
                    self._reload_todo = set()
                    self.outage.worked("reload")
                except psycopg.Error as exc:  # the store unreachable: logged once
                    self._reload_todo = changed
                    self.outage.failed("reload", exc)
                except Exception:
                    self._reload_todo = changed
                    log.exception("reloading %d changed loops failed; retried", len(changed))
