"""The gateway side of the protocol (service.gateways.base, deploy/examples/dcs_gateway.py)
against a real tuner on loopback: QoS of samples, the seq rule per (loop, instance_id),
batched gains, the state query on (re)connect and the tuners' liveliness."""

from __future__ import annotations

import importlib.util
import json
import queue
import sys
import time

import orjson
import pytest
import zenoh

from service.daemon.tuner import Tuner
from service.engine.config import LoopConfig
from service.gateways.base import Gateway, Source, Update
from service.procs import ROOT, Proc
from service.wire.protocol import (
    GainsBatch,
    GainsMessage,
    Keys,
    Mode,
    Sample,
    SampleColumns,
    encode,
)
from tests.sockets import LOOPBACK, listening
from tests.tuner_support import loop_body, open_peer, subscribers, tuner_settings, wait_until

pytestmark = pytest.mark.timeout(90)
EXAMPLE = ROOT / "deploy" / "examples" / "dcs_gateway.py"
KEYS = Keys()


def gains(loop_id: str, seq: int, kp: float, *, instance: str = "test-tuner", mode=Mode.auto):
    return GainsMessage(loop_id=loop_id, seq=seq, t=0.0, dkp=0.0, dki=0.0, kp=kp, ki=0.02,
                        mode=mode, instance_id=instance)  # fmt: skip


class Plant:
    """A gateway peer of the tuner with its own session; collects its updates."""

    def __init__(self, tuner: Tuner, loop_ids, gateway_id: str | None = None) -> None:
        self.session = open_peer(tuner.settings.zenoh_listen, admin=True)
        self.gateway = Gateway(self.session, loop_ids, KEYS, gateway_id=gateway_id)
        self.updates: list[Update] = []

    def poll(self) -> list[Update]:
        self.updates += self.gateway.gains()
        return self.updates

    def until(self, predicate, what: str) -> list[Update]:
        wait_until(lambda: predicate(self.poll()), timeout=10.0, what=what)
        return self.updates

    def close(self) -> None:
        self.gateway.close()
        self.session.close()


def _zid(session: zenoh.Session) -> str:
    return str(session.info.zid())


@pytest.fixture
def tuner(tmp_path):
    tuner = Tuner(tuner_settings(tmp_path)).start()
    try:
        yield tuner
    finally:
        tuner.stop()


@pytest.fixture
def other(tuner):
    """A second peer of the tuner: injects messages as a tuner would, watches samples."""
    session = open_peer(tuner.settings.zenoh_listen, admin=True)
    try:
        yield session
    finally:
        session.close()


def test_samples_go_out_with_block_and_gains_are_taken_once_in_seq_order(tuner, other):
    tuner.register(LoopConfig(**loop_body("LIC-101")))
    seen = queue.SimpleQueue()
    sub = other.declare_subscriber(KEYS.all_samples, lambda s: seen.put(s.congestion_control))
    plant = Plant(tuner, ["LIC-101"])
    try:
        # the state query the token triggers answered (seq 0) before any sample: else the
        # tuner, which queues queries and samples from separate Zenoh threads, could answer
        # it after the step, and the step's gains come as a state reply
        plant.until(
            lambda _: plant.gateway.tuner_up and "LIC-101" in plant.gateway.inbox.supervision,
            "the tuner's liveliness token and its state reply",
        )
        # the other peer hears the plant's samples, the plant the other peer's gains: each
        # knows the other's subscriber (their direct link comes by gossip, after the tuner's)
        wait_until(
            lambda: (
                subscribers(plant.session, KEYS.sample("LIC-101"))
                >= {_zid(tuner.bus.session), _zid(other)}
            ),
            timeout=10.0,
            what="the subscribers of the plant's samples",
        )
        wait_until(
            lambda: _zid(plant.session) in subscribers(other, KEYS.gains("LIC-101")),
            timeout=10.0,
            what="the plant's subscriber of gains",
        )
        for i in range(170):  # one RL step (165 samples), through the gateway's publisher
            plant.gateway.publish("LIC-101", Sample(t=float(i), e=1.0))
        (step,) = plant.until(lambda u: u, "the agent's gains")
        assert (step.source, step.seq, step.instance_id) == (Source.gains, 1, "test-tuner")
        assert seen.get(timeout=5) == zenoh.CongestionControl.BLOCK

        sent = [
            gains("LIC-101", 1, 9.0),  # duplicate of the tuner's seq 1: dropped
            gains("LIC-101", 1, 0.6, instance="other"),  # another instance: its own count
            gains("LIC-101", 3, 0.7),
            gains("LIC-101", 2, 9.0),  # late: dropped
            gains("LIC-101", 4, 0.8, mode=Mode.advisory),  # shown, not applied
            gains("LIC-101", 4, 9.0),  # same seq as the advisory one: dropped
            gains("OTHER", 5, 9.0),  # not this gateway's loop: ignored
            gains("LIC-101", 5, 0.9),
        ]
        for msg in sent:
            other.put(KEYS.gains(msg.loop_id), encode(msg))
        updates = plant.until(lambda u: u[-1].seq == 5, "the last message")[1:]
        assert [(u.instance_id, u.seq, u.kp, u.mode) for u in updates] == [
            ("other", 1, 0.6, Mode.auto),
            ("test-tuner", 3, 0.7, Mode.auto),
            ("test-tuner", 4, 0.8, Mode.advisory),
            ("test-tuner", 5, 0.9, Mode.auto),
        ]
        assert (plant.gateway.inbox.stale, plant.gateway.inbox.invalid) == (3, 0)
        other.put(KEYS.gains("LIC-101"), b'{"seq": "no"}')
        wait_until(lambda: plant.poll() is not None and plant.gateway.inbox.invalid == 1)
    finally:
        sub.undeclare()
        plant.close()


def test_batched_gains_of_a_gateway_follow_the_same_rule(tuner, other):
    fronted = ["B0", "B1", "B2"]
    tuner.register_many(
        [LoopConfig(**loop_body(i, sample_period_s=165.0, gateway="gw-1")) for i in fronted]
    )
    tuner.register(LoopConfig(**loop_body("SOLO", sample_period_s=165.0)))
    batches = queue.SimpleQueue()
    sub = other.declare_subscriber(KEYS.gateway_gains("gw-1"), lambda s: batches.put(s))
    plant = Plant(tuner, fronted, gateway_id="gw-1")
    deaf = Plant(tuner, fronted)  # no gateway id: the batches are not for it
    try:
        for p in (plant, deaf):
            p.until(lambda _, p=p: p.gateway.tuner_up, "the tuner's liveliness token")
        # the state reply first: on a loaded machine it could come after the step below
        # and bring seq 1 itself (source state_batch)
        plant.until(lambda _: set(fronted) <= set(plant.gateway.inbox.supervision), "state")
        for t in (0.0, 165.0):
            batch = {"samples": [{"loop_id": i, "t": t, "e": 0.5} for i in [*fronted, "SOLO"]]}
            other.put(KEYS.batch, json.dumps(batch).encode())
        updates = plant.until(lambda u: len(u) == 3, "a batch of 3")
        assert sorted(u.loop_id for u in updates) == fronted
        assert {(u.source, u.seq) for u in updates} == {(Source.batch, 1)}
        sample = batches.get(timeout=5)  # what the tuner sent, and how
        assert sample.congestion_control == zenoh.CongestionControl.BLOCK
        assert sample.priority == zenoh.Priority.DATA_HIGH

        # the same batch again (a duplicate), then one whose B1 item is newer
        payload = GainsBatch.model_validate_json(sample.payload.to_bytes())
        other.put(KEYS.gateway_gains("gw-1"), encode(payload))
        newer = [g.model_copy(update={"seq": 2, "kp": 0.8}) for g in payload.gains[1:2]]
        other.put(KEYS.gateway_gains("gw-1"), encode(GainsBatch(gains=[*payload.gains, *newer])))
        updates = plant.until(lambda u: len(u) == 4, "the newer item")
        assert (updates[3].loop_id, updates[3].seq, updates[3].kp) == ("B1", 2, 0.8)
        assert plant.gateway.inbox.stale == 6
        # the control: news for B2 on the same key, after the two batches above; nothing
        # else came in between
        (b2,) = (g for g in payload.gains if g.loop_id == "B2")
        control = GainsBatch(gains=[b2.model_copy(update={"seq": 2, "kp": 0.4})])
        other.put(KEYS.gateway_gains("gw-1"), encode(control))
        updates = plant.until(lambda u: len(u) >= 5, "the control item")
        assert [(u.loop_id, u.seq, u.kp) for u in updates[4:]] == [("B2", 2, 0.4)]
        assert plant.gateway.inbox.stale == 6
        # the batches are not for the gateway without the id; it may still learn the
        # gains from a state reply, if its query on the tuner's token came after the step
        assert all(u.source is Source.state for u in deaf.poll())
    finally:
        sub.undeclare()
        deaf.close()
        plant.close()


def test_a_gateway_fronting_loops_registered_without_it_sends_theirs_on_their_keys(tuner):
    """Loops registered with the gateway's id go in its SampleColumns, the others on
    their own keys (on the gateway's key the tuner rejects them as wrong_gateway); and an
    advisory loop's state reply is no update to apply (docs/protocol.md, State)."""
    tuner.register(LoopConfig(**loop_body("A", gateway="gw-1")))
    tuner.register(LoopConfig(**loop_body("B")))
    tuner.register(LoopConfig(**loop_body("C", mode="advisory")))
    tuner.reset("C")  # seq 1: its state reply has a seq to order by
    plant = Plant(tuner, ["A", "B", "C"], gateway_id="gw-1")
    try:
        plant.until(lambda _: {"A", "B", "C"} <= set(plant.gateway.inbox.supervision), "state")
        wait_until(lambda: plant.gateway._batches.matching_status.matching, 10.0, "the tuner")
        for t in range(5):
            plant.gateway.publish_scan({i: Sample(t=float(t), e=0.1) for i in ("A", "B", "C")})
        wait_until(
            lambda: all(tuner.view(i).counters.samples == 5 for i in ("A", "B", "C")),
            10.0, "every sample taken",
        )  # fmt: skip
        assert tuner.metrics.value("pitune_samples_rejected_total", reason="wrong_gateway") == 0
        assert not [u for u in plant.poll() if u.loop_id == "C"]  # the advisory reply
    finally:
        plant.close()


def test_missed_gains_come_from_the_state_query_on_connect_and_reconnect(tmp_path):
    settings = tuner_settings(tmp_path)
    tuner = Tuner(settings).start()
    plant = None
    try:
        tuner.register(LoopConfig(**loop_body("LIC-101", kp=0.7, ki=0.02)))
        tuner.register(LoopConfig(**loop_body("QUIET", kp=0.7, ki=0.02)))
        tuner.reset("LIC-101")  # seq 1 published while no gateway listens
        plant = Plant(tuner, ["LIC-101", "QUIET"])
        (missed,) = plant.until(lambda u: u, "the state reply")
        assert (missed.source, missed.loop_id, missed.seq, missed.kp, missed.ki) == (
            Source.state,
            "LIC-101",
            1,
            0.7,
            0.02,
        )  # fmt: skip  (QUIET has no gains yet: seq 0)
        assert plant.gateway.tuner_up

        tuner.stop()
        plant.until(lambda _: not plant.gateway.tuner_up, "the token's deletion")
        again = tuner_settings(tmp_path, instance_id="tuner-2", zenoh_listen=settings.zenoh_listen)
        tuner = Tuner(again).start()
        tuner.reset("QUIET")  # seq 1 of QUIET, maybe before the gateway is back
        supervision = plant.gateway.inbox.supervision
        updates = plant.until(
            lambda u: (
                {(x.loop_id, x.instance_id) for x in u[1:]} >= {("QUIET", "tuner-2")}
                and supervision["LIC-101"].instance_id == "tuner-2"  # its state reply came
            ),
            "the new tuner's state",
        )
        assert plant.gateway.tuner_up
        # LIC-101's reply is its seq 1 under the epoch it went out under: no news (taken
        # again, it would write the stored gains over any change made in the DCS meanwhile)
        assert supervision["LIC-101"].epoch == missed.epoch
        (quiet,) = updates[1:]  # once (a reset heard and its state reply are one update)
        assert (quiet.loop_id, quiet.seq, quiet.kp, quiet.instance_id) == (
            "QUIET", 1, 0.7, "tuner-2"
        )  # fmt: skip
    finally:
        if plant is not None:
            plant.close()
        tuner.stop()


def test_the_example_gateway_applies_state_and_batched_gains(tuner, other, tmp_path):
    """deploy/examples/dcs_gateway.py as a process, with --gateway-id, on a real tuner."""
    tuner.register(LoopConfig(**loop_body("LIC-101", gateway="gw-1")))  # kp 0.5 as the DCS
    for i in range(170):  # an agent step (seq 1) while no gateway listens
        other.put(KEYS.sample("LIC-101"), json.dumps({"t": float(i), "e": 1.0}).encode())
    wait_until(lambda: tuner.view("LIC-101").counters.steps == 1, what="the agent's step")
    stepped = tuner.view("LIC-101").kp
    assert stepped != 0.5
    samples = queue.SimpleQueue()

    # a tuner listens on the gateway's samples key: each scan is one SampleColumns there
    def on_batch(s: zenoh.Sample) -> None:
        columns = SampleColumns.model_validate_json(s.payload.to_bytes()).columns
        for values in zip(*columns.values(), strict=True):
            item = {k: v for k, v in zip(columns, values, strict=True) if v is not None}
            samples.put(orjson.dumps(item))

    sub = other.declare_subscriber(KEYS.gateway_samples("gw-1"), on_batch)
    child = Proc(
        "gateway",
        [sys.executable, str(EXAMPLE), "--connect", tuner.settings.zenoh_listen[0],
         "--gateway-id", "gw-1", "--period", "0.1", "--seconds", "10"],
        log=tmp_path / "gateway.log",
    )  # fmt: skip

    kps: list[float] = []

    def reported(kp: float) -> Sample:
        """The first sample reporting ``kp`` in force (the gains of earlier ones in kps)."""
        deadline = time.monotonic() + 8
        while time.monotonic() < deadline:
            try:
                sample = Sample.model_validate_json(samples.get(timeout=0.5))
            except queue.Empty:
                continue
            kps.append(sample.kp)
            if sample.kp == kp:
                return sample
        raise AssertionError(f"no sample with kp={kp}:\n{child.tail()}")

    try:
        # The DCS's 0.5 is what the step replaced: the tuner takes it for the update not
        # applied yet, and the state query brings the gateway the step's gains.
        reported(stepped)
        # reachable from this host only (Zenoh's default peer listener is every interface)
        assert listening(child.pid) and set(listening(child.pid)) <= LOOPBACK
        batch = [gains("LIC-101", 4, 0.9)]
        other.put(KEYS.gateway_gains("gw-1"), encode(GainsBatch(gains=batch)))
        first = reported(0.9)
        for msg in (gains("LIC-101", 3, 0.3), gains("LIC-101", 5, 1.1, mode=Mode.advisory)):
            other.put(KEYS.gains("LIC-101"), encode(msg))  # late; advisory
        other.put(KEYS.gateway_gains("gw-1"), encode(GainsBatch(gains=[gains("LIC-101", 6, 1.3)])))
        last = reported(1.3)
        assert last.t > first.t
        assert 0.3 not in kps and 1.1 not in kps, kps
        assert child.wait(20) == 0, child.tail()
    finally:
        sub.undeclare()
        child.kill()
    log = child.log.read_text()
    assert "tuner up: pitune/tuners/test-tuner" in log, log


def test_the_example_is_importable_without_side_effects():
    spec = importlib.util.spec_from_file_location("dcs_gateway", EXAMPLE)
    module = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(module)
    dcs = module.Dcs({"A": (0.5, 0.01)})
    dcs.write_gains("A", 0.6, 0.02)
    assert dcs.gains("A") == {"kp": 0.6, "ki": 0.02}
