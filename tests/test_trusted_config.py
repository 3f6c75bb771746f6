"""Stored configs loaded by :func:`service.engine.trusted.stored_config`: the same object
validation makes, for every kind of config the API accepts; a row that breaks any rule
(shape, type, bound, pattern, enum, the models' validators) is left to full validation
and its clear error."""

from __future__ import annotations

import orjson
import pytest
from pydantic import ValidationError

from service.bench.config import BenchConfig
from service.bench.fleet import Fleet
from service.engine.config import LoopConfig, Registration
from service.engine.trusted import stored_config, trusted
from tests.tuner_support import loop_body

NO_SCALING = {"scaling": None, "guard": {"kp_min": 0.01, "kp_max": 5.0}}
VARIANTS = [
    {},
    {"gateway": "gw-north", "mode": "advisory", "action": "direct", "forgetting": 0.9},
    {"mode": "frozen", "sample_period_s": 5.0, "guard": {"identify": True, "model_band": None}},
    {"mode": "shadow", "scaling": {"k_hat": 2.0, "tau_hat": 40.0, "e_scale": 0.5}},
    {"scaling": {"u_scale": 0.3, "time_unit_s": 12.0, "pv_scale": 3.0}},
    NO_SCALING,
    {"scaling": None},
    {"kp": 2.5e4, "ki": 1.25e10, "sample_period_s": 1e-6,
     "scaling": {"k_hat": 1e-6, "tau_hat": 1e-6, "pv_scale": 1.0}},
]  # fmt: skip


def _stored(body: dict) -> str:
    """What the store writes for a registration."""
    return Registration.model_validate(body).model_dump_json()


@pytest.mark.parametrize("overrides", VARIANTS)
def test_a_stored_config_loads_as_validation_makes_it(overrides):
    raw = _stored(loop_body("LIC-1", **overrides))
    expected = LoopConfig.model_validate_json(raw)
    got = trusted(orjson.loads(raw))
    assert got is not None  # (not left to validation)
    assert got == expected and got.model_dump_json() == raw
    assert got.resolved_scaling == expected.resolved_scaling
    assert got.mode is expected.mode and got.model_fields_set == expected.model_fields_set


def test_the_bench_s_configs_load_as_validation_makes_them():
    fleet = Fleet(BenchConfig(loops=300, rate=1.0, gateways=4))
    for body in fleet.registrations:
        raw = _stored(body)
        assert stored_config(raw) == LoopConfig.model_validate_json(raw)


BROKEN = [
    ("an extra field", lambda c: c.update(colour="red")),
    ("an extra field in the scaling", lambda c: c["scaling"].update(k=1.0)),
    ("a string for a float", lambda c: c.update(kp="0.5")),
    ("a bool for a float", lambda c: c.update(ki=True)),
    ("a bound past its maximum (an older version's)", lambda c: c["guard"].update(ki_max=1.25e13)),
    ("a gain at zero", lambda c: c.update(kp=0.0)),
    ("a forgetting factor above 1", lambda c: c.update(forgetting=1.5)),
    ("an id off its pattern", lambda c: c.update(id="bad id")),
    ("an unknown mode", lambda c: c.update(mode="manual")),
    ("an unknown action", lambda c: c.update(action="sideways")),
    ("bounds the wrong way round", lambda c: c["guard"].update(kp_min=10.0, kp_max=1.0)),
    ("gains outside their bounds", lambda c: c.update(kp=100.0)),
    ("pv_scale and e_scale both", lambda c: c["scaling"].update(e_scale=1.0)),
    ("a scaling without k_hat or u_scale", lambda c: c["scaling"].update(k_hat=None)),
    ("a negative k_hat", lambda c: c["scaling"].update(k_hat=-1.0)),
    ("not an object", lambda c: c.clear()),
]


@pytest.mark.parametrize("what, edit", BROKEN, ids=[b[0] for b in BROKEN])
def test_a_row_breaking_a_rule_gets_validation_s_error(what, edit):
    values = orjson.loads(_stored(loop_body("LIC-1")))
    edit(values)
    raw = orjson.dumps(values)
    assert trusted(orjson.loads(raw)) is None
    with pytest.raises(ValidationError):
        stored_config(raw)


def test_an_integer_in_a_float_field_is_a_float_as_validation_makes_it():
    values = orjson.loads(_stored(loop_body("LIC-1")))
    values["sample_period_s"], values["guard"]["stale_periods"] = 2, 5
    raw = orjson.dumps(values)
    got = trusted(orjson.loads(raw))
    assert got == LoopConfig.model_validate_json(raw)
    assert type(got.sample_period_s) is float and type(got.guard.stale_periods) is float


def test_a_row_of_another_shape_is_validated_fully():
    """A field the row lacks (written before it was added) takes its default, as always."""
    values = orjson.loads(_stored(loop_body("LIC-1")))
    values.pop("forgetting")
    values["guard"].pop("verify")
    raw = orjson.dumps(values)
    assert trusted(orjson.loads(raw)) is None
    assert stored_config(raw) == LoopConfig.model_validate_json(raw)
