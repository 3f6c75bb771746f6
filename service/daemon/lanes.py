"""Publishing lanes: committed gains messages waiting for one destination, each
destination with its own thread doing the blocking put, in order.

Publishing never holds the tuner's worker: committed gains go to a :class:`Lane` per
destination (one for the per-loop keys, one per gateway); past LANE_BOUND waiting
messages a lane keeps only the newest of each loop (gains are absolute and gateways
drop older seqs), so it stays bounded, and a stuck gateway delays only its own lane.
"""

from __future__ import annotations

import logging
import threading
import time
from collections.abc import Callable

log = logging.getLogger("pitune.tuner")
LANE_BOUND = 100_000
"""Messages a lane holds before it keeps only the newest of each loop."""
LANE_DRAIN_S = 5.0
"""Longest :meth:`Tuner.stop` waits for the lanes to publish what they hold."""


class Lane:
    """Committed gains messages waiting for one destination, and the thread publishing
    them: the per-loop keys (``gateway`` None) or one gateway's GainsBatch key.

    Messages go out in the order submitted. While the destination blocks, messages
    pile up; past ``bound`` of them, only the newest of each loop is kept (gains are
    absolute, and gateways drop a seq below one they took), so a lane holds at most
    ``max(bound, loops)`` messages however long its destination blocks.
    """

    def __init__(
        self,
        gateway: str | None,
        send: Callable[[str | None, list[dict]], None],
        bound: int = LANE_BOUND,
    ):
        self.gateway = gateway
        self._send = send
        self.bound = bound
        self._pending: list[dict] = []
        self._cond = threading.Condition()
        self._busy = False
        self._closing = False
        self.superseded = 0
        """Messages replaced by a newer one of the same loop before they went out."""
        self.thread = threading.Thread(
            target=self._run, name=f"pitune-publish-{gateway or 'loops'}", daemon=True
        )
        self.thread.start()

    def submit(self, messages: list[dict]) -> None:
        with self._cond:
            self._pending.extend(messages)
            if len(self._pending) > self.bound:
                newest = {m["loop_id"]: i for i, m in enumerate(self._pending)}
                kept = [self._pending[i] for i in sorted(newest.values())]
                self.superseded += len(self._pending) - len(kept)
                self._pending = kept
            self._cond.notify_all()

    def discard(self, loop_ids: set[str]) -> int:
        """Take the waiting messages of ``loop_ids`` out (their loops left this member's
        engine); how many."""
        with self._cond:
            kept = [m for m in self._pending if m["loop_id"] not in loop_ids]
            gone = len(self._pending) - len(kept)
            self._pending = kept
        return gone

    def _run(self) -> None:
        while True:
            with self._cond:
                while not self._pending and not self._closing:
                    self._cond.wait()
                if not self._pending:
                    return
                batch, self._pending = self._pending, []
                self._busy = True
            try:
                self._send(self.gateway, batch)
            except Exception:
                log.exception("publishing %d gains messages failed", len(batch))
            finally:
                with self._cond:
                    self._busy = False
                    self._cond.notify_all()

    @property
    def idle(self) -> bool:
        return not self._pending and not self._busy

    def drain(self, timeout: float) -> bool:
        """Wait until everything submitted went out; False on timeout."""
        deadline = time.monotonic() + timeout
        with self._cond:
            while self._pending or self._busy:
                left = deadline - time.monotonic()
                if left <= 0.0:
                    return False
                self._cond.wait(left)
            return True

    def close(self, timeout: float) -> None:
        with self._cond:
            self._closing = True
            self._cond.notify_all()
        self.thread.join(timeout)
