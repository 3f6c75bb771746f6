"""Loops added to the table a chunk at a time (``LoopTable.add_many``: a failover's insert,
a bulk registration, a restart) end in exactly the state of adding them one by one
(``tests/registration_reference.py``), field by field, for varied loops: hinted and
hint-free, identified (a scaling in force), flagged and paused (mismatch, out of the
envelope, manual), every mode, both actions, with and without gateway, snapshots of
older versions (keys and counters missing, a hidden state of another size)."""

from __future__ import annotations

import math

import numpy as np
import orjson
import pytest

from service.agent import untrained_agent
from service.engine import LoopConfig, TuningEngine, monitor, oscillation, verify
from service.engine.saved import Saved
from service.engine.table import _BOOL, _F64, _I64, _REC, LoopTable
from tests.registration_reference import add_one
from tests.test_identify import drive, hint_free

N = 300
MODES = ("auto", "advisory", "frozen", "shadow")


def _config(i: int) -> LoopConfig:
    guard: dict = {}
    if i % 5 == 1:
        guard["identify"] = True
    if i % 6 == 2:
        guard["excitation_periods"] = 0.0
    if i % 7 == 3:
        guard["verify"] = False
    if i % 11 == 4:
        guard |= {"kp_min": 0.01, "kp_max": 50.0}
    scaling = (
        None
        if i % 4 == 3
        else {"k_hat": 0.5 + i % 9, "tau_hat": 5.0 + 3 * i, "pv_scale": 1.0 + i % 3}
        if i % 8
        else {"e_scale": 0.5, "u_scale": 0.25, "time_unit_s": 12.0}
    )
    return LoopConfig(
        id=f"X{i:03d}", kp=0.2 + 0.01 * i, ki=0.01 + 0.001 * i, sample_period_s=1.0,
        scaling=scaling, mode=MODES[i % 4], action="direct" if i % 3 == 1 else "reverse",
        gateway=None if i % 2 else f"gw-{i % 3}", guard=guard, forgetting=0.9 + 0.0001 * i,
    )  # fmt: skip


@pytest.fixture(scope="module")
def snapshots() -> list[tuple[bytes, dict]]:
    """Real runtime snapshots to vary: an identified hint-free loop, a hinted one."""
    engine = TuningEngine(untrained_agent(0))
    engine.register(hint_free(), wall=0.0)
    drive(engine, moves=6)
    assert engine.view("L", wall=0.0).counters.identified == 1
    engine.register(_config(0).model_copy(update={"id": "H", "gateway": None}), wall=0.0)
    drive(engine, "H", moves=2)
    return [(hidden, orjson.loads(runtime)) for _, hidden, runtime in engine.snapshot()]


def _snapshot(i: int, snapshots) -> tuple[bytes, str] | None:
    """Loop ``i``'s snapshot: none, or a real one varied."""
    if i % 9 == 0:
        return None
    hidden, rt = snapshots[i % 2]
    rt = orjson.loads(orjson.dumps(rt))
    rt["last_t"] = 100.0 + i
    rt["counters"] = [c + i for c in rt["counters"]]
    if i % 10 == 1:
        rt["ident"]["mismatch"] = True
    if i % 10 == 3:
        rt["ident"]["out_env"] = True
    if i % 13 == 2:
        rt["manual"] = True
    if i % 17 == 5:  # older versions: keys missing, fewer counters
        for key in ("sp_ref", "obs_gain", "sp_anchor", "move_t", "excited_until"):
            rt.pop(key, None)
        rt["counters"] = rt["counters"][:5]
    if i % 19 == 6:
        rt.pop("verify")
    if i % 23 == 7:
        rt.pop("ident")
    if i % 6 == 4:
        rt["figures"] = {"last": [200.0 + i, 1.5, None, 3.0, 4.0, 0.1],
                         "hist": [[200.0 + i, 1.5, 2.0, 3.0, 4.0, 0.1]] * (i % 12)}  # fmt: skip
    if i % 7 == 2:  # refusals by reason (a newer tuner's reason dropped)
        rt["refused"] = {"flood": i, "out_of_order": 1, "a_newer_reason": 5}
    if i % 29 == 8:
        hidden = hidden[:8]  # another agent's size: not restored
    return hidden, orjson.dumps(rt).decode()


def _loops(snapshots) -> list[tuple]:
    return [
        (_config(i), 0.3 + 0.001 * i if i % 9 else None, 0.02 if i % 9 else None, i,
         _snapshot(i, snapshots))
        for i in range(N)
    ]  # fmt: skip


def _saved(snap) -> Saved | None:
    return None if snap is None else Saved.parse(*snap)


def _table(loops, how: str) -> LoopTable:
    tb = LoopTable(untrained_agent(0), max_rate_hz=10.0)
    tb.reserve(N + 8)
    # a table with holes: loops removed before the restore
    first = [LoopConfig(id=f"F{i}", kp=1.0, ki=0.1, sample_period_s=1.0) for i in range(8)]
    tb.add_many(first, wall=0.0)
    for i in (1, 4, 5):
        tb.remove(f"F{i}")
    if how == "reference":
        for config, kp, ki, seq, snap in loops:
            add_one(tb, config, kp=kp, ki=ki, seq=seq, saved=_saved(snap), wall=5.0)
    elif how == "one by one":
        for config, kp, ki, seq, snap in loops:
            tb.add(config, kp=kp, ki=ki, seq=seq, saved=_saved(snap), wall=5.0)
    else:
        for a, b in ((0, 1), (1, 8), (8, 60), (60, N)):  # chunks of several sizes
            part = loops[a:b]
            given = [kp is not None for _, kp, _, _, _ in part]
            if not all(given):  # registered gains for a whole chunk only
                for config, kp, ki, seq, snap in part:
                    tb.add_many([config], kp=None if kp is None else [kp],
                                ki=None if ki is None else [ki], seq=[seq],
                                saved=[_saved(snap)], wall=5.0)  # fmt: skip
                continue
            tb.add_many(
                [p[0] for p in part], kp=[p[1] for p in part], ki=[p[2] for p in part],
                seq=[p[3] for p in part], saved=[_saved(p[4]) for p in part], wall=5.0,
            )  # fmt: skip
    return tb


ARRAYS = [
    *_F64, *_I64, *_REC, *_BOOL, *verify.F64, *verify.F32, *monitor.F64, *monitor.F32,
    "r_mixed", "f_hist", "f_hist_n", *(name for name, _, _ in oscillation.ARRAYS), "hidden",
    "gateways", "n_refused",
]  # fmt: skip


def _same(a: LoopTable, b: LoopTable) -> None:
    for name in ARRAYS:
        x, y = getattr(a, name), getattr(b, name)
        assert x.dtype == y.dtype, name
        if x.dtype == object:
            assert x.tolist() == y.tolist(), name
        else:
            np.testing.assert_array_equal(x, y, err_msg=name, strict=True)
    assert a.ids == b.ids and a.slot_of == b.slot_of and a._free == b._free
    assert a.version == b.version
    assert a.configs._json == b.configs._json
    assert list(a.configs._json) == list(b.configs._json)
    assert [None if x is None else x.dump() for x in a.ident] == [
        None if x is None else x.dump() for x in b.ident
    ]


def test_a_chunk_of_loops_ends_in_the_state_of_adding_them_one_by_one(snapshots):
    loops = _loops(snapshots)
    reference = _table(loops, "reference")
    _same(reference, _table(loops, "one by one"))
    chunked = _table(loops, "chunks")
    _same(reference, chunked)
    # the variety is there: identified, flagged, paused, manual loops, every mode
    used = np.fromiter(chunked.slot_of.values(), np.int64)
    assert sum(chunked.ident[s].scaling is not None for s in used.tolist()) >= 10
    assert chunked.mismatch[used].any() and chunked.out_env[used].any()
    assert chunked.manual[used].any() and (chunked.f_hist_n[used] > 0).any()
    assert set(chunked.mode[used].tolist()) == {0, 1, 2, 3}
    assert np.isnan(chunked.period[used]).any() and chunked.watch[used].any()
    assert (chunked.n_refused[used].sum(axis=1) > 0).sum() >= 30


def test_a_chunk_with_a_registered_or_repeated_id_changes_nothing():
    tb = LoopTable(untrained_agent(0), max_rate_hz=10.0)
    tb.add_many([_config(i) for i in range(3)], wall=0.0)
    before = (tb.version, list(tb._free), dict(tb.slot_of), len(tb.configs))
    for chunk in ([_config(5), _config(1)], [_config(6), _config(7), _config(6)]):
        with pytest.raises(KeyError, match="already registered"):
            tb.add_many(chunk, wall=0.0)
        assert (tb.version, list(tb._free), dict(tb.slot_of), len(tb.configs)) == before
    assert "X005" not in tb.configs and not math.isnan(tb.reg_kp[0])


def test_a_chunk_larger_than_the_free_room_takes_the_slots_add_would():
    one, chunk = (LoopTable(untrained_agent(0), max_rate_hz=10.0) for _ in range(2))
    configs = [_config(i) for i in range(200)]
    for tb in (one, chunk):
        tb.add_many(configs[:70], wall=0.0)
        for i in (3, 40, 65):
            tb.remove(configs[i].id)
    for config in configs[70:]:
        one.add(config, wall=0.0)
    slots = chunk.add_many(configs[70:], wall=0.0)
    assert slots.tolist() == [one.slot_of[c.id] for c in configs[70:]]
    assert chunk.slot_of == one.slot_of
