"""The table's lock handed from a busy worker to another thread between two messages
(service/daemon/handoff.py): a failover's chunks of adopted loops must not wait for the
end of the worker's batch."""

from __future__ import annotations

import threading
import time

from service.daemon.handoff import Handoff

MESSAGES = 200
MESSAGE_S = 0.002
"""A batch of 200 messages of 2 ms each: 0.4 s holding the lock."""


def test_a_waiting_thread_gets_the_lock_at_the_workers_next_message():
    lock = threading.RLock()
    handoff = Handoff(lock)
    handled = 0
    started = threading.Event()

    def worker():
        nonlocal handled
        with lock:
            started.set()
            for _ in range(MESSAGES):
                handoff.let_in()
                time.sleep(MESSAGE_S)  # handling one message
                handled += 1

    thread = threading.Thread(target=worker)
    thread.start()
    try:
        assert started.wait(5.0)
        turns = []
        for _ in range(3):  # three chunks, each at a message boundary
            with handoff.hold():
                turns.append(handled)
    finally:
        thread.join(10.0)
    assert handled == MESSAGES  # the worker went on after each turn
    assert turns[-1] < MESSAGES / 2, turns  # not at the end of the batch


def test_without_waiters_the_worker_keeps_the_lock():
    lock = threading.RLock()
    handoff = Handoff(lock)
    with lock:
        handoff.let_in()  # nobody waits: returns at once, the lock still held
        assert lock._is_owned()
