"""Stored configs loaded without pydantic's validation pipeline, checked by the same rules.

The store writes a config as ``model_dump_json()`` of a validated
:class:`~service.engine.config.LoopConfig`. Loading it back through pydantic costs
~25-45 µs a loop (the JSON walked field by field, then the models' validators in
Python), most of a cluster member's takeover of a dead member's loops (75,000 loops:
2-3 s of CPU, 6-7 s on a survivor whose worker shares the interpreter).
:func:`stored_config` parses the JSON with orjson and checks what validation checks,
from the same declarations: every object has exactly its model's fields, each value a
JSON type its field accepts, within the field's bounds (``gt``/``ge``/``lt``/``le``)
and pattern, an enum's or literal's value one of theirs; then the models' own
validators run on the result (the scaling's factors, the bounds). Anything that fails a
check (a row of an older schema, a field added or removed, a value edited out of range)
goes through full validation, which raises the clear
:class:`~pydantic.ValidationError` that :meth:`Store.load
<service.daemon.store.Store.load>` reports. The rules are read from the models when
this module is imported; a model validator or metadata kind it does not know stops the
import (:data:`VALIDATORS`), so a rule added to the models cannot be skipped here.
"""

from __future__ import annotations

import enum
import operator
import re
import types
import typing
from typing import Annotated, Literal, Union

import annotated_types as at
import orjson
from pydantic import AllowInfNan, BaseModel, Strict
from pydantic._internal._fields import PydanticMetadata
from pydantic.fields import FieldInfo

from service.engine.config import Guard, LoopConfig
from service.units import ScalingSpec

_NONE = type(None)
VALIDATORS = {
    LoopConfig: ({"_resolve_bounds"}, set()),
    Guard: (set(), set()),
    ScalingSpec: ({"_complete"}, {"_k_magnitude"}),
}
"""Each model's (model validators, field validators) this module runs: the model
validators on the built object (:func:`_validated`); ``_k_magnitude`` (k_hat not
negative) is implied by k_hat's lower bound, checked with the field's."""
_BOUNDS = {at.Gt: ("gt", operator.gt), at.Ge: ("ge", operator.ge)}
_BOUNDS |= {at.Lt: ("lt", operator.lt), at.Le: ("le", operator.le)}
_GENERAL = {"pattern", "allow_inf_nan", "strict"}
"""The settings of pydantic's general metadata this module knows."""


class _Field:
    """What a field's stored JSON value must be."""

    __slots__ = ("kinds", "choices", "bounds", "pattern")

    def __init__(self, field: FieldInfo) -> None:
        self.kinds: set[type] = set()
        self.choices: dict | None = None
        """Value -> Python value, of an enum or literal field."""
        self.bounds: list[tuple] = []
        self.pattern: re.Pattern | None = None
        self._walk(field.annotation)
        self._constrain(field.metadata)  # (an Annotated field's own constraints land here)

    def _walk(self, annotation) -> None:
        origin = typing.get_origin(annotation)
        if origin is Annotated:
            base, *metadata = typing.get_args(annotation)
            self._walk(base)
            self._constrain(metadata)
        elif origin in (Union, types.UnionType):
            for arg in typing.get_args(annotation):
                self._walk(arg)
        elif origin is Literal:
            self._choose({a: a for a in typing.get_args(annotation)})
        elif isinstance(annotation, type) and issubclass(annotation, enum.Enum):
            self._choose({m.value: m for m in annotation})
        elif annotation is float:
            self.kinds |= {float, int}
        elif annotation in (int, bool, str, _NONE):
            self.kinds.add(annotation)
        else:
            raise TypeError(f"no trusted load for a field of type {annotation!r}")

    def _choose(self, choices: dict) -> None:
        self.kinds |= {type(v) for v in choices}
        self.choices = {**(self.choices or {}), **choices}

    def _constrain(self, metadata) -> None:
        for item in metadata:
            if isinstance(item, FieldInfo):
                self._constrain(item.metadata)
            elif type(item) in _BOUNDS:
                name, op = _BOUNDS[type(item)]
                self.bounds.append((op, getattr(item, name)))
            elif isinstance(item, PydanticMetadata) and set(vars(item)) <= _GENERAL:
                if getattr(item, "pattern", None) is not None:
                    self.pattern = re.compile(item.pattern)
            elif not isinstance(item, Strict | AllowInfNan):
                # (strict, allow_inf_nan: exact types are checked; JSON has no inf or NaN)
                raise TypeError(f"no trusted load for the constraint {item!r}")

    def fits(self, values: dict, name: str) -> bool:
        """``values[name]`` is a value of this field (made a float or an enum member in
        place, as validation does)."""
        value = values[name]
        kind = type(value)
        if kind not in self.kinds:
            return False
        if value is None:
            return True
        if self.choices is not None:
            if value not in self.choices:
                return False
            values[name] = self.choices[value]
            return True
        if kind is int and float in self.kinds:
            value = values[name] = float(value)
        if self.pattern is not None and not self.pattern.match(value):
            return False
        return all(op(value, bound) for op, bound in self.bounds)


def _rules(model: type[BaseModel], nested: tuple[str, ...] = ()) -> dict[str, _Field]:
    checks = model.__pydantic_decorators__
    found = (set(checks.model_validators), set(checks.field_validators))
    if found != VALIDATORS[model] or checks.validators or checks.root_validators:
        raise TypeError(f"{model.__name__}'s validators changed: update {__name__}")
    return {n: _Field(f) for n, f in model.model_fields.items() if n not in nested}


_LOOP = _rules(LoopConfig, ("guard", "scaling"))
_GUARD = _rules(Guard)
_SPEC = _rules(ScalingSpec)
_LOOP_KEYS = _LOOP.keys() | {"guard", "scaling"}


def _fits(values, rules: dict[str, _Field], keys) -> bool:
    if type(values) is not dict or values.keys() != keys:
        return False
    return all(rule.fits(values, name) for name, rule in rules.items())


def _built(model: type[BaseModel], values: dict, private: dict | None = None):
    """An instance of ``model`` holding ``values`` as they are (what ``model_construct``
    ends with, without its per-field Python)."""
    obj = model.__new__(model)
    setattr_ = object.__setattr__
    setattr_(obj, "__dict__", values)
    setattr_(obj, "__pydantic_fields_set__", set(values))
    setattr_(obj, "__pydantic_extra__", None)
    setattr_(obj, "__pydantic_private__", private)
    return obj


def stored_config(raw: str | bytes) -> LoopConfig:
    """The config the store wrote as ``raw`` (see the module doc; ValidationError if it
    does not validate)."""
    config = trusted(orjson.loads(raw))
    return LoopConfig.model_validate_json(raw) if config is None else config


def trusted(values) -> LoopConfig | None:
    """The config of the parsed stored JSON ``values`` (consumed), checked by the rules
    above and the models' validators; None if it fails one (the caller validates it
    fully, for the error)."""
    if not _fits(values, _LOOP, _LOOP_KEYS) or not _fits(values["guard"], _GUARD, _GUARD.keys()):
        return None
    spec = values["scaling"]
    try:
        if spec is not None:
            if not _fits(spec, _SPEC, _SPEC.keys()):
                return None
            spec = values["scaling"] = _built(ScalingSpec, spec, {})
            spec._complete()
        values["guard"] = _built(Guard, values["guard"])
        return _built(LoopConfig, values)._resolve_bounds()
    except ValueError:
        return None
