"""Wire models, key expressions, rejection classification and the generated protocol doc."""

import re
from pathlib import Path

import pytest
from pydantic import ValidationError

from service.wire.decode import classify
from service.wire.doc import generated_block, render_schemas
from service.wire.protocol import (
    SCHEMA_REVISION,
    SCHEMA_VERSION,
    GainsMessage,
    Keys,
    Mode,
    RejectReason,
    Sample,
    SampleBatch,
)

pytestmark = pytest.mark.timeout(30)
DOC = Path(__file__).resolve().parents[1] / "docs" / "protocol.md"


def test_protocol_doc_schemas_are_in_sync_with_the_models():
    assert generated_block(DOC.read_text()) == render_schemas().strip("\n"), (
        "docs/protocol.md is stale: run python -m service.wire.doc docs/protocol.md"
    )


def test_protocol_doc_names_the_revision_the_code_speaks():
    """The title and the versioning table (written by hand) follow SCHEMA_REVISION: a
    gateway's author reads the revision off the title and its changes off the table."""
    text = DOC.read_text()
    title = text.splitlines()[0]
    assert title.endswith(f"(schema version {SCHEMA_VERSION}, revision {SCHEMA_REVISION})")
    rows = re.findall(rf"^\| {SCHEMA_VERSION}\.(\d+) \| (.+) \|$", text, re.M)
    assert [int(r) for r, _ in rows] == list(range(1, SCHEMA_REVISION + 1))


def test_sample_error_from_e_or_sp_pv():
    assert Sample.model_validate_json(b'{"t": 1, "sp": 55, "pv": 53.5}').error == 1.5
    assert Sample.model_validate_json(b'{"t": 1, "e": -2, "sp": 55, "pv": 53.5}').error == -2.0
    s = Sample.model_validate_json(b'{"t": 1, "e": 0, "future_field": [1, 2]}')
    assert (s.auto, s.saturated, s.kp, s.v) == (True, False, None, 1)


@pytest.mark.parametrize(
    ("payload", "reason"),
    [
        (b'{"t": 1, "e": ', RejectReason.malformed_json),
        (b"\xff\xfe", RejectReason.malformed_json),
        (b"[1, 2]", RejectReason.schema),
        (b'{"e": 1}', RejectReason.schema),
        (b'{"t": 1}', RejectReason.schema),
        (b'{"t": 1, "sp": 2}', RejectReason.schema),
        (b'{"t": "1", "e": 1}', RejectReason.schema),
        (b'{"t": 1, "e": 1, "auto": 1}', RejectReason.schema),
        (b'{"t": NaN, "e": 1}', RejectReason.non_finite),
        (b'{"t": 1, "e": Infinity}', RejectReason.non_finite),
        (b'{"t": 1, "e": 1e400}', RejectReason.non_finite),
        (b'{"t": 1, "e": 1e13}', RejectReason.out_of_range),
        (b'{"t": 1, "e": 1, "kp": 0}', RejectReason.out_of_range),
        (b'{"t": 1, "e": 1, "ki": -0.1}', RejectReason.out_of_range),
        (b'{"v": 2, "t": 1, "e": 1}', RejectReason.unsupported_version),
        (b'{"v": "1", "t": 1, "e": 1}', RejectReason.schema),
    ],
)
def test_invalid_samples_are_classified(payload, reason):
    with pytest.raises(ValidationError) as info:
        Sample.model_validate_json(payload)
    assert classify(info.value) is reason


def test_gains_message_round_trip_and_advisory_only_modes():
    msg = GainsMessage(
        loop_id="FIC-7", seq=3, t=12.5, dkp=0.1, dki=-0.01, kp=1.1, ki=0.09,
        mode=Mode.advisory, instance_id="t1",
    )  # fmt: skip
    assert GainsMessage.model_validate_json(msg.model_dump_json()) == msg
    with pytest.raises(ValidationError):
        GainsMessage.model_validate({**msg.model_dump(), "mode": "frozen"})


def test_batch_names_each_loop():
    batch = SampleBatch.model_validate_json(
        b'{"samples": [{"loop_id": "a", "t": 1, "e": 0.5}, {"loop_id": "b", "t": 1, "e": 0}]}'
    )
    assert [s.loop_id for s in batch.samples] == ["a", "b"]
    with pytest.raises(ValidationError):
        SampleBatch.model_validate_json(b'{"samples": [{"loop_id": "a/b", "t": 1, "e": 0}]}')


def test_keys_under_a_multi_chunk_prefix():
    k = Keys("plantA/pitune")
    assert k.sample("LIC-1") == "plantA/pitune/loops/LIC-1/sample"
    assert k.all_samples == "plantA/pitune/loops/*/sample"
    assert k.tuner("t1") == "plantA/pitune/tuners/t1"
    assert k.loop_id("plantA/pitune/loops/LIC-1/sample") == "LIC-1"
    assert k.loop_id("plantA/pitune/loops/a/b/sample") is None
    assert k.loop_id("other/loops/LIC-1/sample") is None
    for bad in ("", "a//b", "a/*", "/a", "a b"):
        with pytest.raises(ValueError):
            Keys(bad)
