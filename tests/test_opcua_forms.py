"""Gain forms of DCS PID blocks <-> pitune's parallel form, and the map file's validation."""

from __future__ import annotations

import math

import pytest
from hypothesis import given
from hypothesis import strategies as st

from service.gateways.opcua.forms import FormError, GainForm, ITerm, PTerm
from service.gateways.opcua.sitemap import MapError, parse_map

positive = st.floats(min_value=1e-6, max_value=1e6, allow_nan=False, allow_infinity=False)
spans = st.sampled_from([1.0, 0.5, 80.0, 120.0, 1000.0])
forms = st.builds(GainForm, p=st.sampled_from(list(PTerm)), i=st.sampled_from(list(ITerm)),
                  pv_span=spans, op_span=spans)  # fmt: skip


def close(a, b) -> bool:
    return all(math.isclose(x, y, rel_tol=1e-9) for x, y in zip(a, b, strict=True))


@given(forms, positive, positive)
def test_every_form_round_trips_from_parallel(form, kp, ki):
    assert close(form.to_parallel(*form.from_parallel(kp, ki)), (kp, ki))


@given(forms, positive, positive)
def test_every_form_round_trips_from_the_block(form, p, i):
    assert close(form.from_parallel(*form.to_parallel(p, i)), (p, i))


@pytest.mark.parametrize(
    ("form", "block", "parallel"),
    [
        # gain 2, reset 1 min/repeat: ki = 2 / 60 s
        (GainForm(p="gain", i="reset_min"), (2.0, 1.0), (2.0, 2.0 / 60.0)),
        (GainForm(p="gain", i="reset_s"), (2.0, 30.0), (2.0, 2.0 / 30.0)),
        # 3 repeats/min: Ti = 20 s
        (GainForm(p="gain", i="repeats_per_min"), (2.0, 3.0), (2.0, 2.0 / 20.0)),
        (GainForm(p="gain", i="repeats_per_s"), (2.0, 0.5), (2.0, 1.0)),
        # independent integral gain
        (GainForm(p="gain", i="ki_per_s"), (2.0, 0.1), (2.0, 0.1)),
        (GainForm(p="gain", i="ki_per_min"), (2.0, 6.0), (2.0, 0.1)),
        # proportional band 50 % = gain 2
        (GainForm(p="band", i="reset_min"), (50.0, 2.0), (2.0, 2.0 / 120.0)),
        # dimensionless gain on spans: PV 0-200 cm, OUT 0-100 %: kp = 1 * 100 / 200
        (GainForm(p="gain", i="reset_s", pv_span=200.0, op_span=100.0), (1.0, 10.0), (0.5, 0.05)),
        (GainForm(p="band", i="ki_per_s", pv_span=200.0, op_span=100.0), (200.0, 1.0), (0.25, 0.5)),
    ],
)
def test_known_values(form, block, parallel):
    assert close(form.to_parallel(*block), parallel)
    assert close(form.from_parallel(*parallel), block)


@pytest.mark.parametrize("bad", [0.0, -1.0, math.inf, math.nan])
def test_values_without_a_parallel_equivalent_are_refused(bad):
    form = GainForm()
    with pytest.raises(FormError):
        form.to_parallel(bad, 1.0)
    with pytest.raises(FormError):
        form.from_parallel(1.0, bad)


LOOP = {
    "id": "LIC-101", "sp": "ns=2;s=LIC-101.SP", "pv": "ns=2;s=LIC-101.PV",
    "p": "ns=2;s=LIC-101.GAIN", "i": "ns=2;s=LIC-101.RESET",
    "limits": {"p": [0.1, 5.0], "i": [0.1, 30.0]},
}  # fmt: skip
SECURE = {"url": "opc.tcp://dcs:4840", "certificate": "c.der", "private_key": "k.pem",
          "server_certificate": "s.der"}  # fmt: skip


def test_security_none_needs_an_explicit_allow():
    with pytest.raises(MapError, match="allow_insecure"):
        parse_map({"server": {"url": "opc.tcp://dcs:4840", "security": "None"}, "loops": [LOOP]})
    site = parse_map(
        {
            "server": {"url": "opc.tcp://dcs:4840", "security": "None", "allow_insecure": True},
            "loops": [LOOP],
        }  # fmt: skip
    )
    assert site.server.security.value == "None"


def test_a_user_with_security_none_needs_an_explicit_allow_of_a_readable_password():
    insecure = {"url": "opc.tcp://dcs:4840", "security": "None", "allow_insecure": True}
    with pytest.raises(MapError) as refused:
        parse_map({"server": {**insecure, "user": "pitune"}, "loops": [LOOP]})
    assert str(refused.value) == (
        "map: invalid map: server: Value error, security \"None\" with user 'pitune' sends "
        "its password in clear text: use security Basic256Sha256, or set "
        "allow_plaintext_password = true in [server] to accept that"
    )
    opted = {**insecure, "user": "pitune", "allow_plaintext_password": True}
    assert parse_map({"server": opted, "loops": [LOOP]}).server.user == "pitune"
    secure = parse_map({"server": {**SECURE, "user": "pitune"}, "loops": [LOOP]})
    assert not secure.server.allow_plaintext_password  # encrypted: nothing to allow


def test_secure_by_default_and_certificates_required():
    with pytest.raises(MapError, match="certificate"):
        parse_map({"server": {"url": "opc.tcp://dcs:4840"}, "loops": [LOOP]})
    site = parse_map({"server": SECURE, "loops": [LOOP]}, base=__import__("pathlib").Path("/m"))
    assert (site.server.security.value, site.server.mode.value) == (
        "Basic256Sha256",
        "SignAndEncrypt",
    )
    assert str(site.server.certificate) == "/m/c.der"  # relative to the map's folder
    unpinned = {k: v for k, v in SECURE.items() if k != "server_certificate"}
    with pytest.raises(MapError, match="needs server_certificate"):
        parse_map({"server": unpinned, "loops": [LOOP]})
    trusting = {**unpinned, "trust_endpoint_certificate": True}
    assert parse_map({"server": trusting, "loops": [LOOP]}).server.server_certificate is None


def test_defaults_apply_to_every_loop_and_limits_are_checked():
    site = parse_map(
        {
            "server": SECURE,
            "defaults": {"min_write_interval_s": 30, "auto_values": ["AUTO"]},
            "loops": [LOOP, {**LOOP, "id": "FIC-2", "min_write_interval_s": 5}],
        }  # fmt: skip
    )
    assert [lp.min_write_interval_s for lp in site.loops] == [30, 5]
    assert site.loops[1].auto_values == ["AUTO"]
    with pytest.raises(MapError, match="limits"):
        parse_map({"server": SECURE, "loops": [{**LOOP, "limits": {"p": [5, 1], "i": [1, 2]}}]})
    with pytest.raises(MapError, match="duplicate"):
        parse_map({"server": SECURE, "loops": [LOOP, LOOP]})


def test_a_block_gain_pitune_cannot_read_is_never_overwritten():
    """A negative gain (a DCS that encodes the controller action as the gain's sign) has
    no parallel form: an update is refused for it, never written over it with pitune's
    positive gain, which would flip the block's action."""
    from service.gateways.base import Source, Update
    from service.gateways.opcua.loops import LoopRuntime, Pending, decide
    from service.wire.protocol import Mode

    site = parse_map({"server": SECURE, "loops": [{**LOOP, "tuning_enable": True}]})
    update = Update("LIC-101", kp=0.6, ki=0.01, mode=Mode.auto, seq=1, instance_id="t",
                    source=Source.gains)  # fmt: skip
    for p, decision in ((-0.5, "invalid_block_gains"), (0.5, None)):
        lr = LoopRuntime(0, site.loops[0], values={"p": p, "i": 2.0})
        lr.pending = Pending(update, 0.0, lr.block_gains())
        if decision is not None:
            assert decide(lr, link_up=True, now=100.0) == decision
    # a readable block: the same update is written
    assert decide(lr, link_up=True, now=100.0) == pytest.approx(
        site.loops[0].form.from_parallel(0.6, 0.01)
    )
