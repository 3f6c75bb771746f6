"""Samples off the wire into columns: the one decoder of the tuner's input.

Every sample message, single (``{prefix}/loops/{id}/sample``) or batched
(``{prefix}/samples``), ends here as rows of :class:`Columns` (float64 and bool arrays,
one row per accepted sample, in arrival order) plus one :class:`Rejection` per sample
that is not a valid :class:`~service.wire.protocol.Sample`. Every received sample ends
in exactly one of the two.

The acceptance rules are the pydantic models' (:mod:`service.wire.protocol`). A
vectorised check accepts the plain case (every field of the expected JSON type, finite,
within :data:`MAX_MAGNITUDE`) without building a model per sample; any item it does not
accept is validated by the model itself, alone, so one odd item neither sends its
neighbours to the slow path nor is judged by a second set of rules. A test fuzzes the
decoder against the models.
"""

from __future__ import annotations

import dataclasses
import json
from dataclasses import dataclass
from operator import itemgetter

import numpy as np
import orjson
from pydantic import ValidationError

from service.wire.protocol import (
    _ID_RE,
    MAX_BATCH,
    MAX_MAGNITUDE,
    SCHEMA_VERSION,
    BatchedSample,
    RejectReason,
)

FLOAT_FIELDS = ("t", "e", "sp", "pv", "kp", "ki", "op")
_RANGE_ERRORS = {"less_than_equal", "greater_than_equal", "less_than", "greater_than"}
_FLOAT = {float}
_OPT_FLOAT = {float, type(None)}
_BOOL = {bool}
_INT = {int}


@dataclass(frozen=True)
class Rejection:
    """A sample that was not accepted, and why."""

    index: int
    """Position of the sample among those received together (the first, for ``count``)."""
    loop_id: str | None
    reason: RejectReason
    detail: str
    count: int = 1
    """Samples it stands for: a message rejected whole is one rejection of all of them
    (one object, counted at once: a 32 MiB message of 16 million items would otherwise
    cost as many objects and seconds of the worker's time)."""


@dataclass
class Columns:
    """Accepted samples as columns, one row each (engineering units, plant seconds).

    ``t``, ``e`` (the error: ``e``, or ``sp - pv``), ``sp``, ``kp``, ``ki``: float64, NaN
    where the sample did not carry the field (``sp`` only matters to the excitation
    gate); ``auto``, ``saturated``: bool; ``index``: each row's position among the
    samples received together.
    """

    loop_ids: list[str]
    t: np.ndarray
    e: np.ndarray
    sp: np.ndarray
    kp: np.ndarray
    ki: np.ndarray
    auto: np.ndarray
    saturated: np.ndarray
    index: np.ndarray
    op: np.ndarray | None = None
    """Controller output, NaN where the sample did not carry it (identification only)."""
    applied_seq: np.ndarray | None = None
    """int64: seq of the last gains message the DCS applied, -1 where the sample did not
    carry it (None: no row carried it, as for columns built without a decoder)."""

    def __len__(self) -> int:
        return len(self.loop_ids)

    def take(self, rows: np.ndarray) -> Columns:
        """The rows selected by an index or mask array, in that order."""
        ids = self.loop_ids
        picked = np.flatnonzero(rows) if rows.dtype == bool else rows
        return Columns(
            [ids[i] for i in picked.tolist()],
            *(None if getattr(self, f) is None else getattr(self, f)[picked] for f in _ARRAYS),
        )

    @classmethod
    def empty(cls) -> Columns:
        return _columns(_fields([]), [])


_ARRAYS = ("t", "e", "sp", "kp", "ki", "auto", "saturated", "index", "op", "applied_seq")
_SEQ_MAX = 2**63 - 1
"""An ``applied_seq`` beyond int64 (valid JSON, never a real seq) is kept as this."""


@dataclass
class Decoded:
    """What a group of received samples decoded to."""

    rows: Columns
    rejected: list[Rejection]
    received: int
    """Samples received (accepted + rejected)."""
    slots: np.ndarray | None = None
    """int64: each row's slot in the engine's table (-1: not registered), when the caller
    already looked them up under the engine's lock (the tuner's gateway check), so the
    engine does not again (a lookup per sample in a dict of every loop)."""


def joined(parts: list[Decoded]) -> Decoded:
    """Groups of samples decoded apart, as one group received in that order (positions
    renumbered among all of them): the tuner's worker hands a backlog of batch messages
    to the engine in one pass, whose cost is mostly per pass, not per sample."""
    if len(parts) == 1:
        return parts[0]
    offsets = np.cumsum([0] + [p.received for p in parts[:-1]]).tolist()
    cols = [p.rows for p in parts]
    n = sum(len(c) for c in cols)
    ids = [i for c in cols for i in c.loop_ids]
    arrays = {
        f: np.concatenate([getattr(c, f) for c in cols]) if n else getattr(cols[0], f)
        for f in ("t", "e", "sp", "kp", "ki", "auto", "saturated")
    }
    index = np.concatenate([c.index + o for c, o in zip(cols, offsets, strict=True)])
    op = np.concatenate([_or(c.op, len(c), np.nan, np.float64) for c in cols])
    seq = np.concatenate([_or(c.applied_seq, len(c), -1, np.int64) for c in cols])
    rejected = [
        dataclasses.replace(r, index=r.index + o)
        for p, o in zip(parts, offsets, strict=True)
        for r in p.rejected
    ]
    rows = Columns(ids, **arrays, index=index.astype(np.int64), op=op, applied_seq=seq)
    slots = None
    if all(p.slots is not None for p in parts):
        slots = np.concatenate([p.slots for p in parts])
    return Decoded(rows, rejected, sum(p.received for p in parts), slots)


def _or(values: np.ndarray | None, n: int, fill, dtype) -> np.ndarray:
    return np.full(n, fill, dtype) if values is None else values


def classify(exc: ValidationError) -> RejectReason:
    """The rejection reason of a sample that failed validation (its first error)."""
    err = exc.errors()[0]
    kind, loc = err["type"], err["loc"]
    if kind == "json_invalid":
        return RejectReason.malformed_json
    if loc == ("v",) and kind in _RANGE_ERRORS:
        return RejectReason.unsupported_version
    if kind == "finite_number":
        return RejectReason.non_finite
    if kind in _RANGE_ERRORS:
        return RejectReason.out_of_range
    return RejectReason.schema


def decode_objects(items: list, *, strict_json: bool = True) -> Decoded:
    """Decode parsed JSON values, each meant to be a :class:`BatchedSample`.

    ``strict_json`` False says the values were parsed by a parser that admits NaN and
    Infinity: every item then goes through the model, which rejects them.
    """
    n = len(items)
    if strict_json and items and set(map(type, items)) == {dict}:
        fields = _fields(items)  # the usual case: every sample plain, one pass per field
        if _plain_whole(fields, _seqs_ok(items)):
            return Decoded(_columns(fields, range(n)), [], n)
    plain = _plain_rows_each(items) if strict_json else np.zeros(n, bool)
    good = np.flatnonzero(plain).tolist()
    kept: list[dict] = [items[i] for i in good]
    kept_index: list[int] = good
    rejected: list[Rejection] = []
    for i in np.flatnonzero(~plain).tolist():
        item = items[i]
        try:
            sample = BatchedSample.model_validate(item)
        except ValidationError as exc:
            loop_id = item.get("loop_id") if isinstance(item, dict) else None
            loop_id = loop_id if isinstance(loop_id, str) else None
            rejected.append(Rejection(i, loop_id, classify(exc), exc.errors()[0]["msg"]))
            continue
        kept.append(sample.model_dump())
        kept_index.append(i)
    order = np.argsort(np.asarray(kept_index, np.int64), kind="stable")
    kept = [kept[j] for j in order.tolist()]
    kept_index = [kept_index[j] for j in order.tolist()]
    return Decoded(_columns(_fields(kept), kept_index), rejected, n)


def decode_values(items: list) -> Decoded:
    """Decode Python values as if they had come over the wire as JSON: numpy floats are
    floats, NaN and Infinity are rejected (what the daemon would make of them)."""
    try:
        text = json.dumps(items)
    except (TypeError, ValueError):  # not JSON-able (an array, an object): the model says why
        return decode_objects(items, strict_json=False)
    return decode_objects(
        json.loads(text), strict_json="NaN" not in text and "Infinity" not in text
    )


def decode_singles(messages: list[tuple[str | None, bytes]]) -> Decoded:
    """Decode single-sample messages: (loop id from the key, or None if the key is not a
    loop's sample key; JSON payload)."""
    items: list = []
    index: list[int] = []
    rejected: list[Rejection] = []
    lax = False
    for i, (loop_id, payload) in enumerate(messages):
        if loop_id is None:
            rejected.append(Rejection(i, None, RejectReason.bad_key, "not a loop's sample key"))
            continue
        try:
            item = orjson.loads(payload)
        except orjson.JSONDecodeError as exc:
            item = _lax_loads(payload)
            if item is None:
                rejected.append(Rejection(i, loop_id, RejectReason.malformed_json, str(exc)))
                continue
            lax = True
        if type(item) is not dict:
            rejected.append(Rejection(i, loop_id, RejectReason.schema, "not a JSON object"))
            continue
        item["loop_id"] = loop_id  # the key names the loop
        items.append(item)
        index.append(i)
    decoded = decode_objects(items, strict_json=not lax)
    return _renumber(decoded, index, rejected, len(messages))


def decode_batch(payload: bytes) -> Decoded:
    """Decode a :class:`~service.wire.protocol.SampleBatch` message.

    A payload that is not a batch at all counts as one rejected sample; a batch over
    :data:`MAX_BATCH` samples or of an unsupported version is rejected whole, each of its
    samples counted. NaN or Infinity in one sample (what Python's ``json`` writes by
    default) rejects that sample only.
    """
    lax = False
    try:
        message = orjson.loads(payload)
    except orjson.JSONDecodeError as exc:
        message = _lax_loads(payload)
        if message is None:
            return _whole(1, RejectReason.malformed_json, f"batch: {exc}")
        lax = True
    if isinstance(message, dict) and "columns" in message and "samples" in message:
        # which form holds the samples is ambiguous: taking one would count the other's
        # samples nowhere ("every sample received ends in exactly one counter")
        n = _held(message["columns"]) + _held(message["samples"])
        return _whole(n, RejectReason.schema, "both 'columns' and 'samples'")
    if isinstance(message, dict) and "columns" in message:
        return decode_columns(message, strict_json=not lax)
    items = message.get("samples") if isinstance(message, dict) else None
    if not isinstance(items, list):
        return _whole(1, RejectReason.schema, "batch without a 'samples' list")
    n = len(items)
    version = message.get("v", SCHEMA_VERSION)
    if not _speaks(version):
        return _whole(n, RejectReason.unsupported_version, f"batch v={version!r:.40}")
    if n > MAX_BATCH:
        return _whole(n, RejectReason.schema, f"batch of {n} samples (at most {MAX_BATCH})")
    return decode_objects(items, strict_json=not lax)


def decode_columns(message: dict, *, strict_json: bool = True) -> Decoded:
    """Decode a :class:`~service.wire.protocol.SampleColumns` message (parsed): the same
    samples as the :class:`~service.wire.protocol.SampleBatch` whose sample ``i`` has
    field ``k`` = ``columns[k][i]``, judged by the same rules.

    Plain columns are taken whole, one pass per column (no object per sample: ~5x
    cheaper than a batch's rows, the tuner's largest cost per sample at 150,000 loops
    a member); anything else is decoded as those rows, each judged by the model. Columns
    of unequal lengths, or not an object of lists, reject the message whole (each
    sample counted, the longest column's length; 1 if none)."""
    cols = message["columns"]
    if not isinstance(cols, dict) or not all(type(c) is list for c in cols.values()):
        return _whole(1, RejectReason.schema, "columns: not an object of lists")
    lengths = set(map(len, cols.values()))
    n = max(lengths, default=0)
    if len(lengths) > 1:
        return _whole(n, RejectReason.schema, f"columns of unequal lengths {sorted(lengths)}")
    version = message.get("v", SCHEMA_VERSION)
    if not _speaks(version):
        return _whole(n, RejectReason.unsupported_version, f"columns v={version!r:.40}")
    if n > MAX_BATCH:
        return _whole(n, RejectReason.schema, f"columns of {n} samples (at most {MAX_BATCH})")
    if strict_json and n and "loop_id" in cols:
        f = {k: cols.get(k) or [default] * n for k, default in _DEFAULTS.items()}
        f["present"] = set(cols)
        # a null applied_seq is one not carried, as the model reads it (a gateway's
        # columns have one where the DCS applied no update yet)
        seqs = cols.get("applied_seq", ())
        if _plain_whole(f, all(_seq_ok(a) for a in seqs if a is not None)):
            return Decoded(_columns(f, range(n)), [], n)
    names = list(cols)
    rows = [dict(zip(names, values, strict=True)) for values in zip(*cols.values(), strict=True)]
    return decode_objects(rows, strict_json=strict_json)


# -- helpers ----------------------------------------------------------------------------
def _speaks(version) -> bool:
    """Whether a batch message's ``v`` is a schema version this tuner reads."""
    return type(version) is int and 1 <= version <= SCHEMA_VERSION


def _held(part) -> int:
    """Samples a batch's ``samples`` or ``columns`` counts as: a list's length, the
    longest column's (as :func:`decode_columns`), else 1."""
    if isinstance(part, dict) and all(type(c) is list for c in part.values()):
        return max(map(len, part.values()), default=0)
    return len(part) if type(part) is list else 1


def _lax_loads(payload: bytes):
    """JSON with NaN/Infinity admitted (Python's json), or None if it is not JSON."""
    try:
        return json.loads(payload)
    except (ValueError, UnicodeDecodeError, RecursionError):
        return None


def refused(decoded: Decoded, reason: RejectReason, detail: str) -> Decoded:
    """Every sample of ``decoded`` rejected with ``reason``: a message refused whole."""
    return _whole(decoded.received, reason, detail)


def _whole(n: int, reason: RejectReason, detail: str) -> Decoded:
    return Decoded(Columns.empty(), [Rejection(0, None, reason, detail, count=n)] if n else [], n)


def _renumber(decoded: Decoded, index: list[int], rejected: list[Rejection], n: int) -> Decoded:
    """Map positions among the decoded objects back to positions among the messages."""
    pos = np.asarray(index, np.int64)
    decoded.rows.index = pos[decoded.rows.index] if len(pos) else decoded.rows.index
    rejected += [dataclasses.replace(r, index=index[r.index]) for r in decoded.rejected]
    rejected.sort(key=lambda r: r.index)
    return Decoded(decoded.rows, rejected, n)


_FLAGS = {"auto": True, "saturated": False, "v": SCHEMA_VERSION, "applied_seq": None}
"""The optional non-float fields of a sample and their values when absent."""


_DEFAULTS = {"loop_id": None, **dict.fromkeys(FLOAT_FIELDS), **_FLAGS}
"""Every field a column is made of, and its value where a sample does not carry it."""


def _fields(items: list[dict]) -> dict:
    """Each field of the samples as a sequence (absent: None, or its :data:`_FLAGS`
    default), and ``"present"``: the fields any sample has. A field no sample has costs
    no pass over the samples (a gateway's batch usually carries ``loop_id``, ``t`` and
    ``e``); when every sample has the same fields (a gateway's batch), the present ones
    are read in one pass in C (``itemgetter``), 3x faster than a pass per field."""
    present = set().union(*items)
    n = len(items)
    keys = [k for k in _DEFAULTS if k in present]
    out: dict = {k: [default] * n for k, default in _DEFAULTS.items() if k not in present}
    if len(keys) > 1 and sum(map(len, items)) == n * len(present):  # each has them all
        out.update(zip(keys, zip(*map(itemgetter(*keys), items), strict=True), strict=True))
    else:
        out.update((k, [d.get(k, _DEFAULTS[k]) for d in items]) for k in keys)
    out["loop_id"] = list(out["loop_id"])
    out["present"] = present
    return out


_VALID_IDS: set[str] = set()
"""Loop ids already found valid: they come back every sample period, and a set lookup
costs a tenth of the pattern's match."""
_VALID_IDS_MAX = 1_000_000
"""Most ids remembered (~0.1 GB); past it the set starts again."""


def _ids_valid(ids: list[str]) -> bool:
    """Every id (a str) matches the loop id pattern."""
    if _VALID_IDS.issuperset(ids):
        return True
    if not all(map(_ID_RE.fullmatch, ids)):
        return False
    if len(_VALID_IDS) > _VALID_IDS_MAX:
        _VALID_IDS.clear()
    _VALID_IDS.update(ids)
    return True


def _seqs_ok(items: list[dict]) -> bool:
    """Every ``applied_seq`` the items carry is plain (:func:`_plain_whole`)."""
    return all(_seq_ok(d["applied_seq"]) for d in items if "applied_seq" in d)


def _plain_whole(f: dict, seqs_ok: bool) -> bool:
    """True if the vectorised rules accept every item exactly as the model would
    (``f``: :func:`_fields` of the items, or a columns message's columns; ``seqs_ok``:
    every ``applied_seq`` carried is plain), decided with one pass per field present.

    Plain: a JSON object with a valid string ``loop_id``, ``t`` a float, ``e``/``sp``/
    ``pv``/``kp``/``ki`` floats or absent (not null), ``e`` or both ``sp`` and ``pv``,
    booleans ``auto``/``saturated``, integer ``v`` of this version and an integer
    ``applied_seq`` >= 0 (within int64) when present, every number within
    :data:`MAX_MAGNITUDE` and gains positive. Anything else (ints, strings,
    nulls, ...) is for the model to judge.
    """
    present = f["present"]
    ids = f["loop_id"]
    if set(map(type, ids)) != {str} or not _ids_valid(ids):
        return False
    v = f["v"]
    if (
        set(map(type, f["t"])) != _FLOAT
        or not all(set(map(type, f[k])) <= _OPT_FLOAT for k in FLOAT_FIELDS[1:] if k in present)
        or ("auto" in present and set(map(type, f["auto"])) != _BOOL)
        or ("saturated" in present and set(map(type, f["saturated"])) != _BOOL)
        or ("v" in present and (set(map(type, v)) != _INT or set(v) != {SCHEMA_VERSION}))
        or not seqs_ok
    ):
        return False
    return bool(_numbers_ok(_floats(f)).all())


def _floats(f: dict) -> dict[str, np.ndarray]:
    """The float fields of :func:`_fields` as float64 arrays (absent: NaN)."""
    n = len(f["loop_id"])
    return {
        k: np.array(f[k], dtype=np.float64).reshape(n) if k in f["present"] else np.full(n, np.nan)
        for k in FLOAT_FIELDS
    }


def _seq_ok(v) -> bool:
    return type(v) is int and 0 <= v <= _SEQ_MAX  # not bool, not null: the model's to judge


def _plain_rows_each(items: list) -> np.ndarray:
    """:func:`_plain_whole` item by item (only when the group as a whole is not plain)."""
    return np.fromiter(
        (type(d) is dict and _plain_whole(_fields([d]), _seqs_ok([d])) for d in items),
        bool,
        len(items),
    )


def _numbers_ok(cols: dict[str, np.ndarray]) -> np.ndarray:
    with np.errstate(invalid="ignore"):
        ok = np.ones(cols["t"].shape, bool)
        for k in ("t", "e", "sp", "pv", "op"):  # NaN (absent) compares False: passes
            ok &= ~(np.abs(cols[k]) > MAX_MAGNITUDE)
        for k in ("kp", "ki"):
            ok &= ~((cols[k] <= 0.0) | (cols[k] > MAX_MAGNITUDE))
        ok &= ~np.isnan(cols["e"]) | (~np.isnan(cols["sp"]) & ~np.isnan(cols["pv"]))
    return ok


def _flags(f: dict, key: str) -> np.ndarray:
    """A boolean field as an array (absent from every sample: its default, no pass)."""
    n = len(f["loop_id"])
    if key not in f["present"]:
        return np.full(n, _FLAGS[key], bool)
    return np.fromiter(f[key], bool, n)


def _columns(f: dict, index) -> Columns:
    """Plain samples' :func:`_fields` as columns."""
    n = len(f["loop_id"])
    cols = _floats(f)
    e = cols["e"]
    error = np.where(np.isnan(e), cols["sp"] - cols["pv"], e)
    if "applied_seq" in f["present"]:
        seqs = (-1 if a is None else min(a, _SEQ_MAX) for a in f["applied_seq"])
        applied = np.fromiter(seqs, np.int64, n)
    else:
        applied = np.full(n, -1, np.int64)
    return Columns(
        f["loop_id"],
        cols["t"],
        error,
        cols["sp"],
        cols["kp"],
        cols["ki"],
        _flags(f, "auto"),
        _flags(f, "saturated"),
        np.arange(n) if isinstance(index, range) else np.asarray(index, np.int64).reshape(n),
        cols["op"],
        applied,
    )
