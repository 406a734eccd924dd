"""The model file's ``fit`` section as typed, frozen objects: :class:`ModelFit` and its :class:`HeldOut`.

``ModelFit.from_json(model.fit)`` reads the section a model file (docs/model-file.md) carries: how the
model was found (algorithm, cost, fitness, evaluations, seconds, windows), the channels it was fitted
on, the held-out verdict (:class:`HeldOut`, ``usable``, ``unusable_subsystems``, ``closed_loop``),
and, as plain JSON values in ``extra``, the sections only some fits have (the configuration
selection, the prior, the search history, the frequency scores, ...). ``to_json()`` gives the
section back key for key and in the same order, so a file read and written again is unchanged.
Every field is optional (None or empty): a model from the frequency-domain fit, the reference fit
or an older file has fewer of them. Pure; the producers (:mod:`groundstation.sysid.identify`,
:mod:`groundstation.analysis`) still build the section as a dict on the model.
"""

from __future__ import annotations

import copy
import dataclasses
import types
import typing
from collections.abc import Mapping
from dataclasses import dataclass, field
from typing import Any, TypeVar

T = TypeVar("T", bound="JsonSection")


@dataclass(frozen=True)
class JsonSection:
    """A JSON object with typed fields for the keys it knows and ``extra`` for the others; the
    document's key order is kept (``keys``), so ``from_json(d).to_json() == d`` key for key and in
    order. Fields typed ``tuple[...]`` hold JSON lists; a field whose type has ``from_json`` holds that
    type."""

    #: keys this type has no field for, with their JSON values as read
    extra: Mapping[str, Any] = field(default_factory=dict, repr=False)
    #: the document's key order
    keys: tuple[str, ...] = field(default=(), repr=False, compare=False)

    @classmethod
    def _fields(cls) -> dict[str, Any]:
        hints = typing.get_type_hints(cls)
        return {f.name: hints[f.name] for f in dataclasses.fields(cls)
                if f.name not in ("extra", "keys") and f.metadata.get("json", True)}

    @classmethod
    def from_json(cls: type[T], doc: Mapping[str, Any]) -> T:
        if not isinstance(doc, Mapping):
            raise ValueError(f"{cls.__name__}: expected a JSON object, got {type(doc).__name__}")
        known = cls._fields()
        kw: dict[str, Any] = {}
        for k, v in doc.items():
            if k in known:
                kw[k] = _read(known[k], v)
        extra = {k: copy.deepcopy(v) for k, v in doc.items() if k not in known}
        return cls(**kw, extra=extra, keys=tuple(doc))

    def to_json(self) -> dict[str, Any]:
        known = self._fields()
        defaults = {f.name: f for f in dataclasses.fields(self)}
        order = list(self.keys)
        # fields set without a document (built in code): after the document's keys, in field order
        for name in known:
            if name not in order and getattr(self, name) != _default(defaults[name]):
                order.append(name)
        order += [k for k in self.extra if k not in order]
        out: dict[str, Any] = {}
        for k in order:
            if k in known:
                out[k] = _write(getattr(self, k))
            elif k in self.extra:
                out[k] = copy.deepcopy(self.extra[k])
        return out


def _default(f: dataclasses.Field) -> Any:
    if f.default is not dataclasses.MISSING:
        return f.default
    if f.default_factory is not dataclasses.MISSING:
        return f.default_factory()
    return dataclasses.MISSING


def _read(tp: Any, v: Any) -> Any:
    """A JSON value into a field of type ``tp`` (lists into tuples, objects into sections)."""
    if v is None:
        return None
    union = typing.get_origin(tp) in (typing.Union, types.UnionType)
    for t in typing.get_args(tp) if union else (tp,):
        if isinstance(t, type) and issubclass(t, JsonSection) and isinstance(v, Mapping):
            return t.from_json(v)
        if typing.get_origin(t) is tuple and isinstance(v, list):
            return tuple(copy.deepcopy(v))
        if typing.get_origin(t) is Mapping and isinstance(v, Mapping):
            item = typing.get_args(t)[1]
            if isinstance(item, type) and issubclass(item, JsonSection):
                return {k: item.from_json(x) for k, x in v.items()}
    return copy.deepcopy(v)


def _write(v: Any) -> Any:
    if isinstance(v, JsonSection):
        return v.to_json()
    if isinstance(v, Mapping):
        return {k: _write(x) for k, x in v.items()}
    if isinstance(v, tuple):
        return [copy.deepcopy(x) for x in v]
    return copy.deepcopy(v)


@dataclass(frozen=True)
class HeldOut(JsonSection):
    """The held-out check (``fit.heldout``): the model refitted on k-1 contiguous blocks of the in-air
    time predicts the k-th. ``skipped`` says why it did not run (then the rest is empty)."""

    k: int | None = None
    window_s: float | None = None
    #: mean held-out match degree (%) over the predicted channels and folds
    mean_match: float | None = None
    #: mean match (%) per channel over the folds
    channel_mean: Mapping[str, float] = field(default_factory=dict)
    #: match (%) per channel, one mapping per fold
    folds: tuple[Mapping[str, float], ...] = ()
    predicted: tuple[str, ...] = ()
    not_predicted: tuple[str, ...] = ()
    #: channel -> folds in which its prediction ran away
    runaway: Mapping[str, Any] = field(default_factory=dict)
    unusable_subsystems: tuple[str, ...] = ()
    skipped: str | None = None


@dataclass(frozen=True)
class ModelFit(JsonSection):
    """The model file's ``fit`` section (docs/model-file.md); see the module docstring."""

    algorithm: str | None = None
    seed: int | None = None
    #: 1 / (1 + cost)
    fitness: float | None = None
    #: the refined windowed output-error cost (eq. 11)
    cost: float | None = None
    #: match degree (%) per output channel on the training windows
    match_degree: Mapping[str, float] = field(default_factory=dict)
    evaluations: int | None = None
    iterations: int | None = None
    #: wall time of the identification (s); None where not measured
    seconds: float | None = None
    window_s: float | None = None
    window_step_s: float | None = None
    windows: int | None = None
    estimate_all_initial: bool | None = None
    #: output channels the fit used
    channels: tuple[str, ...] = ()
    #: parameters held fixed (the flight does not move them)
    fixed: tuple[str, ...] = ()
    notes: tuple[str, ...] = ()
    heldout: HeldOut | None = None
    #: False when a subsystem's held-out prediction runs away; None when not checked
    usable: bool | None = None
    unusable_subsystems: tuple[str, ...] = ()
    #: what the closed loop means for this model (one sentence each)
    closed_loop: tuple[str, ...] = ()
