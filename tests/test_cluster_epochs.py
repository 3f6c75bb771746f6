"""A loop that comes into a shard from another one (its gateway patched, or its id
deleted and registered again under another gateway) keeps its messages' epoch rising:
the new shard's lease token may be older than the one its messages went out under, and
a gateway drops a message whose (epoch, seq) is not above the last it took
(docs/protocol.md, Sequence rule). Real PostgreSQL, real Zenoh on loopback."""

from __future__ import annotations

import contextlib
import queue

import pytest

from service.daemon.shards import gateway_shard
from service.daemon.tuner import Tuner
from service.engine.config import LoopConfig
from service.engine.patch import LoopPatch
from service.wire.protocol import GainsBatch
from tests.tuner_support import loop_body, open_peer, tuner_settings, wait_until

pytestmark = pytest.mark.timeout(90)


@contextlib.contextmanager
def _gateway_gains(tuner: Tuner):
    """A peer collecting (loop_id, epoch, seq) of every batched gains item, once the
    tuner's token is seen."""
    taken: queue.SimpleQueue = queue.SimpleQueue()
    session = open_peer(tuner.settings.zenoh_listen)

    def take(sample) -> None:
        for item in GainsBatch.model_validate_json(sample.payload.to_bytes()).gains:
            taken.put((item.loop_id, item.epoch, item.seq))

    sub = session.declare_subscriber(tuner.settings.keys.gateway_gains("*"), take)
    try:
        wait_until(lambda: list(session.liveliness().get(tuner.settings.keys.all_tuners)))
        yield taken
    finally:
        sub.undeclare()
        session.close()


def _published(tuner: Tuner, taken: queue.SimpleQueue, loop_id: str) -> tuple[int, int]:
    """Reset the loop (its registered gains go out) and return that message's order."""
    tuner.reset(loop_id)
    while True:
        got, epoch, seq = taken.get(timeout=20.0)
        if got == loop_id:
            return epoch, seq


@pytest.fixture
def tuner(tmp_path, pg_url):
    """One member; shard gB is leased before shard gA, so gA's token is the higher."""
    t = Tuner(tuner_settings(tmp_path, db_path=pg_url, instance_id="a")).start()
    try:
        t.register(LoopConfig(**loop_body("M", gateway="gB")))
        t.register(LoopConfig(**loop_body("L", gateway="gA")))
        held = t.cluster.held
        assert held[gateway_shard("gA")] > held[gateway_shard("gB")]
        yield t
    finally:
        t.stop()


def test_a_loop_patched_to_a_gateway_of_an_older_lease_publishes_above_its_last(tuner):
    with _gateway_gains(tuner) as taken:
        before = _published(tuner, taken, "L")
        tuner.patch("L", LoopPatch(gateway="gB"))
        wait_until(  # the tuner's own NOTIFY reload moves it to gB's shard
            lambda: tuner.cluster.shard_of.get("L") == gateway_shard("gB"), 60.0, "the move"
        )
        after = _published(tuner, taken, "L")
        assert after > before  # a gateway following the sequence rule takes it
        assert after[0] > tuner.cluster.held[gateway_shard("gB")]
        # the loop that was in gB all along keeps the shard's token
        assert tuner.cluster.token("M") == tuner.cluster.held[gateway_shard("gB")]


def test_a_deleted_id_registered_again_under_another_gateway_publishes_above_its_last(tuner):
    with _gateway_gains(tuner) as taken:
        before = _published(tuner, taken, "L")
        tuner.delete("L")
        tuner.register(LoopConfig(**loop_body("L", gateway="gB")))
        after = _published(tuner, taken, "L")
        assert after > before
