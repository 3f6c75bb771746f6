"""A busy worker waits a few ms for more batch messages (service/daemon/pacing.py) and the
inbox's ``more`` (service/daemon/bus.py) that does the waiting."""

from __future__ import annotations

import time

from service.daemon import pacing
from service.daemon.bus import Inbox, Kind
from service.daemon.pacing import WINDOW_S, Pacer


def test_the_pacer_lingers_only_after_a_busy_window(monkeypatch):
    now = [100.0]
    monkeypatch.setattr(pacing.time, "perf_counter", lambda: now[0])
    pacer = Pacer()
    now[0] += WINDOW_S
    pacer.worked(0.3 * WINDOW_S)  # 30 % busy
    assert not pacer.lingering and abs(pacer.busy_share - 0.3) < 1e-9
    now[0] += WINDOW_S
    pacer.worked(0.7 * WINDOW_S)
    assert pacer.lingering
    now[0] += 0.5 * WINDOW_S  # within a window: no new verdict
    pacer.worked(0.0)
    assert pacer.lingering
    now[0] += 0.5 * WINDOW_S
    pacer.worked(0.1 * WINDOW_S)  # 10 % of the last window
    assert not pacer.lingering


def _inbox(*items):
    inbox = Inbox(100, 1 << 20)
    for item in items:
        inbox.put_nowait(item)
    return inbox


def test_more_takes_what_is_queued_and_waits_only_for_batches():
    batch = (Kind.batch, "pitune/gateways/g/samples", b"x" * 100)
    inbox = _inbox(batch, batch)
    items = [inbox.get()]
    began = time.monotonic()
    inbox.more(items, 10, linger_s=30.0, linger_bytes=200)  # enough bytes: no wait
    assert len(items) == 2 and time.monotonic() - began < 5.0
    query = (Kind.query, "pitune/loops/L1/state", b"")
    inbox = _inbox(query)
    items = [batch]
    began = time.monotonic()
    inbox.more(items, 10, linger_s=30.0, linger_bytes=10_000)  # a query: answer it now
    assert items == [batch, query] and time.monotonic() - began < 5.0
    inbox = _inbox(batch, batch, batch)
    items = [inbox.get()]
    inbox.more(items, 2, linger_s=30.0, linger_bytes=10_000)  # at most `most` items
    assert len(items) == 2 and inbox.qsize() == 1


def test_more_lingers_for_batches_then_returns_what_came():
    batch = (Kind.batch, "pitune/gateways/g/samples", b"x" * 100)
    inbox = _inbox(batch)
    items = [inbox.get()]
    began = time.monotonic()
    inbox.more(items, 10, linger_s=0.05, linger_bytes=10_000)
    waited = time.monotonic() - began
    assert items == [batch] and 0.04 <= waited < 5.0
