"""Per-gateway Zenoh users of the shipped ACL (deploy/zenoh/router.json5, the example
user ``gateway-gw-1``), live through the router, the tuner daemon as the tuner user.

The shared ``gateway`` user may put samples on every loop's key, ``pitune/samples`` and
any gateway's samples key: any holder of its password feeds fabricated samples to a loop
of another gateway, and the tuner publishes gains for them to that gateway's DCS (the
tuner checks the gateway only on gateway keys: ``wrong_gateway``). A per-gateway user
puts samples on its own gateway's key only and gets its own gains and state only.
"""

from __future__ import annotations

import json
import logging
import queue
import re
from collections.abc import Iterator

import pytest
import zenoh

from service.daemon.tuner import Tuner
from service.engine.config import LoopConfig
from service.gateways.base import Gateway
from service.wire.protocol import GainsBatch, Keys, Sample, StateBatch
from service.wire.session import session_config
from tests.test_deploy_acl_live import ZENOH, client, python_router
from tests.tuner_support import loop_body, tuner_settings, wait_until

KEYS = Keys()
USER, PASSWORD = "gateway-gw-1", "gateway-gw-1-secret"
OWN, OTHER = "A1", "B1"
"""Loops of gateway gw-1 (the per-gateway user's) and of gateway gw-2."""
SOLO = "SOLO"
"""A loop registered without a gateway: its samples and gains go on its own keys."""
PERIOD = 165.0
"""The loops' RL period: two samples that far apart make a step."""


@pytest.fixture
def bus(tmp_path) -> Iterator[tuple[str, Tuner]]:
    """The router (with the example per-gateway user's password added to the example
    credentials) and the tuner daemon as its tuner user, loops A1 (gw-1), B1 (gw-2) and
    SOLO registered."""
    credentials = tmp_path / "credentials.txt"
    example = (ZENOH / "credentials.txt").read_text()
    credentials.write_text(f"{example.rstrip()}\n{USER}:{PASSWORD}\n")
    with python_router(tmp_path, credentials=credentials) as endpoint:
        settings = tuner_settings(tmp_path, zenoh_config=ZENOH / "tuner.json5",
                                  zenoh_mode="client", zenoh_connect=[endpoint],
                                  zenoh_listen=[])  # fmt: skip
        tuner = Tuner(settings).start()
        try:
            period = {"sample_period_s": PERIOD}
            tuner.register_many([
                LoopConfig(**loop_body(OWN, gateway="gw-1", **period)),
                LoopConfig(**loop_body(OTHER, gateway="gw-2", **period)),
                LoopConfig(**loop_body(SOLO, **period)),
            ])  # fmt: skip
            yield endpoint, tuner
        finally:
            tuner.stop()


def per_gateway_client(endpoint: str) -> zenoh.Session:
    """gateway.json5 as the per-gateway user: what its site would deploy."""
    config = session_config(config_file=ZENOH / "gateway.json5", connect=[endpoint])
    config.insert_json5("transport/auth/usrpwd/user", json.dumps(USER))
    config.insert_json5("transport/auth/usrpwd/password", json.dumps(PASSWORD))
    return zenoh.open(config)


def batch(loop_id: str, t: float) -> bytes:
    return json.dumps({"samples": [{"loop_id": loop_id, "t": t, "e": 0.5}]}).encode()


def on(q: queue.SimpleQueue, tag: str):
    return lambda s: q.put((tag, s.payload.to_bytes()))


def samples_of(tuner: Tuner, loop_id: str) -> int:
    return tuner.view(loop_id).counters.samples


def test_a_per_gateway_user_cannot_feed_another_gateways_loop(bus):
    """gw-1's user puts B1's samples (B1 is gw-2's) on every key it might try: B1's own
    key, pitune/samples, gw-2's samples key (the ACL drops them) and its own samples key
    (the tuner refuses them, wrong_gateway, counted globally and not on B1). None is
    taken; its own loop's are. The shared gateway user's put on B1's key is taken: it
    reaches every loop."""
    endpoint, tuner = bus
    rogue, shared = per_gateway_client(endpoint), client("gateway", endpoint)
    t = iter(range(1, 10_000))
    try:
        own_key = KEYS.gateway_samples("gw-1")
        wait_until(lambda: rogue.put(own_key, batch(OWN, next(t))) or samples_of(tuner, OWN),
                   timeout=10.0, what="gw-1's first sample through the router")  # fmt: skip
        sample = Sample(t=float(next(t)), e=0.5).model_dump_json().encode()
        rogue.put(KEYS.sample(OTHER), sample)
        rogue.put(KEYS.batch, batch(OTHER, next(t)))
        rogue.put(KEYS.gateway_samples("gw-2"), batch(OTHER, next(t)))
        rogue.put(own_key, batch(OTHER, next(t)))  # reaches the tuner: refused
        # a control after them, on the same link: once the tuner took it, the router had
        # handled (dropped or forwarded) every put before it
        control = next(t)
        rogue.put(own_key, batch(OWN, control))
        wait_until(lambda: tuner.view(OWN).last_sample_t == control, what="the control")
        assert samples_of(tuner, OTHER) == 0
        # counted globally only: another gateway's puts never touch B1's own record
        assert tuner.view(OTHER).counters.rejected == 0 and tuner.view(OTHER).refused is None
        assert tuner.view(OTHER).refused_counts == {}
        assert tuner.metrics.value("pitune_samples_rejected_total", reason="wrong_gateway") == 1
        received = tuner.metrics.value("pitune_samples_received_total")
        assert received == samples_of(tuner, OWN) + 1, "only gw-1's own and the refused one"
        # the shared user's put on B1's key goes through (B1 takes samples)
        wait_until(lambda: shared.put(KEYS.sample(OTHER), sample) or samples_of(tuner, OTHER),
                   timeout=10.0, what="the shared user's sample of B1")  # fmt: skip
    finally:
        shared.close()
        rogue.close()


def test_a_per_gateway_user_gets_its_own_gains_and_state_only(bus):
    """gw-1's user receives gw-1's GainsBatch and StateBatch, never gw-2's gains or
    state nor a loop's own gains."""
    endpoint, tuner = bus
    gw1, shared = per_gateway_client(endpoint), client("gateway", endpoint)
    got: queue.SimpleQueue = queue.SimpleQueue()
    heard: queue.SimpleQueue = queue.SimpleQueue()
    entities = []
    try:
        entities = [
            gw1.declare_subscriber(KEYS.gateway_gains("gw-1"), on(got, "gw-1")),
            gw1.declare_subscriber(KEYS.gateway_gains("gw-2"), on(got, "gw-2")),
            gw1.declare_subscriber(KEYS.all_gains, on(got, "per loop")),
            shared.declare_subscriber(KEYS.gateway_gains("gw-2"), lambda s: heard.put(1)),
            shared.declare_subscriber(KEYS.gains(SOLO), lambda s: heard.put(1)),
        ]

        def both(t: float) -> bytes:
            items = [{"loop_id": i, "t": t, "e": 0.5} for i in (OTHER, SOLO)]
            return json.dumps({"samples": items}).encode()

        # B1 and SOLO step (their first samples repeated until the route is up): their
        # gains go out before gw-1's
        wait_until(lambda: shared.put(KEYS.batch, both(0.0)) or samples_of(tuner, SOLO),
                   timeout=10.0, what="the shared user's first samples")  # fmt: skip
        shared.put(KEYS.batch, both(PERIOD))
        assert heard.get(timeout=10.0) and heard.get(timeout=10.0)
        own = KEYS.gateway_samples("gw-1")
        wait_until(lambda: gw1.put(own, batch(OWN, 0.0)) or samples_of(tuner, OWN),
                   timeout=10.0, what="gw-1's first sample")  # fmt: skip
        gw1.put(own, batch(OWN, PERIOD))
        # the tuner's messages leave on one link in order: gw-2's and SOLO's before gw-1's
        tag, payload = got.get(timeout=10.0)
        assert tag == "gw-1" and got.empty()
        assert [g.loop_id for g in GainsBatch.model_validate_json(payload).gains] == [OWN]
        [reply] = gw1.get(KEYS.gateway_state("gw-1"), timeout=5.0)
        states = StateBatch.model_validate_json(reply.ok.payload.to_bytes()).states
        assert [(s.loop_id, s.seq) for s in states] == [(OWN, 1)]
        assert list(gw1.get(KEYS.gateway_state("gw-2"), timeout=1.0)) == []
        assert list(gw1.get(KEYS.state(OTHER), timeout=1.0)) == []
    finally:
        for entity in reversed(entities):
            entity.undeclare()
        shared.close()
        gw1.close()


@pytest.mark.parametrize("user", ["per-gateway", "shared"])
def test_the_reference_gateway_logs_the_samples_a_per_gateway_user_loses(bus, caplog, user):
    """service/gateways/base.py with a gateway id sends a loop's samples on the loop's
    own key while the tuner's state does not name the loop as this gateway's (SOLO: no
    gateway). A per-gateway user may not: its publisher knows no subscriber there and
    drops them on its side. The gateway says so, once, naming the loop; its own loop's
    samples go batched and reach the tuner. With the shared user SOLO's samples are
    taken and nothing is logged."""
    endpoint, tuner = bus
    caplog.set_level(logging.INFO, logger="pitune.gateway")
    session = per_gateway_client(endpoint) if user == "per-gateway" else client("gateway", endpoint)
    gateway = Gateway(session, [OWN, SOLO], KEYS, gateway_id="gw-1")
    t = iter(range(1, 10_000))

    def scan() -> bool:
        """One scan; whether a tuner is up and its state names A1 as gw-1's."""
        gateway.gains()  # takes the tuner's token and the state replies
        gateway.publish_scan({i: Sample(t=float(next(t)), e=0.5) for i in (OWN, SOLO)})
        state = gateway.inbox.supervision.get(OWN)
        return gateway.tuner_up and state is not None and state.gateway == "gw-1"

    def dropped() -> list[str]:
        return [r.getMessage() for r in caplog.records if "dropped" in r.getMessage()]

    try:
        wait_until(scan, timeout=10.0, what="a tuner up, A1 batched")
        wait_until(lambda: scan() and samples_of(tuner, OWN), timeout=10.0, what="A1's")
        if user == "shared":  # SOLO's samples reach the tuner on its own key
            wait_until(lambda: scan() and samples_of(tuner, SOLO), timeout=10.0, what="SOLO's")
            assert dropped() == []
            return
        wait_until(lambda: scan() and dropped(), timeout=10.0, what="the gateway's warning")
        for _ in range(3):
            scan()
        [warning] = dropped()  # once, not per scan
        # (A1's too when the first scans went before the tuner's state reply named it)
        assert re.match(
            r"samples of [12] loop\(s\) dropped \((A1, )?SOLO\): sent on their own keys "
            r"pitune/loops/\{id\}/sample \(no state reply names them as gateway gw-1's: "
            r"not yet, or they are registered without it\), where this gateway's Zenoh "
            r"user knows no subscriber",
            warning,
        ), warning
        assert samples_of(tuner, SOLO) == 0
    finally:
        gateway.close()
        session.close()
