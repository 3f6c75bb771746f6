"""A gateway's batch slots are remembered while the same ids come in the same order and
no loop was added or removed (service/daemon/slotmemo.py)."""

from __future__ import annotations

import numpy as np
import pytest

from service.daemon.slotmemo import SlotMemo
from service.engine.config import LoopConfig
from service.engine.engine import TuningEngine
from tests.tuner_support import loop_body


def test_slots_are_reused_only_for_the_same_ids_of_the_same_table():
    engine = TuningEngine()
    for i in range(4):
        engine.register(LoopConfig(**loop_body(f"S{i}")))
    table = engine.table
    memo = SlotMemo(table)
    ids = ["S0", "S1", "S2"]
    first = memo.slots(list(ids))
    assert first.tolist() == [table.slot_of[i] for i in ids]
    assert memo.slots(list(ids)) is first  # a new list of the same ids: remembered
    with pytest.raises(ValueError):
        first[0] = 7  # shared with the next batch: read-only
    other = memo.slots(["S0", "S3", "S2"])  # same length and ends, another loop inside
    assert other.tolist() == [table.slot_of["S0"], table.slot_of["S3"], table.slot_of["S2"]]
    engine.remove("S1")
    engine.register(LoopConfig(**loop_body("S9")))  # may take S1's slot
    again = memo.slots(list(ids))
    assert again is not first and again.tolist()[1] == -1  # S1 is gone
    assert memo.slots([]).tolist() == [] and memo.slots(["nope"]).tolist() == [-1]
    assert np.array_equal(memo.slots(["S9"]), [table.slot_of["S9"]])
