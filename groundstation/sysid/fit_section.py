"""The model file's ``fit`` section as typed, frozen objects: :class:`ModelFit` and its :class:`HeldOut`.

``ModelFit.from_json(model.fit)`` reads the section a model file (docs/model-file.md) carries: how the
model was found (algorithm, cost, fitness, evaluations, seconds, windows), the channels it was fitted
on, the held-out verdict (:class:`HeldOut`, ``usable``, ``unusable_subsystems``, ``closed_loop``),
the prior's part (:class:`PriorReport`), the held-out choice of the configuration (:class:`Selection`)
and of the stabilised aircraft's structure (:class:`StructureChoice`), each candidate a
:class:`CandidateScore`; the search history, the service's cross-flight check and the frequency
scores stay plain JSON values; keys the version does not know go to ``extra``. ``to_json()`` gives the
section back key for key and in the same order, so a file read and written again is unchanged.
Every field is optional (None or empty): a model from the frequency-domain fit, the reference fit
or an older file has fewer of them. A field is in the document when it was read from one or set by
:meth:`JsonSection.make` / :meth:`JsonSection.set` (so ``"seconds": null`` stays in the file), in the
order it was set. ``HoverModel.fit`` is a ModelFit: producers build it with ``ModelFit.make(...)`` and
update it with ``fit.set(...)`` (a :func:`dataclasses.replace` that also records a new key's place);
an unknown name raises TypeError, so a misspelt key never reaches a file. Pure.
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
        return _field_types(cls)

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

    @classmethod
    def make(cls: type[T], **fields: Any) -> T:
        """A section with these fields, in this order (JSON lists and objects read as :meth:`from_json`
        reads them); an unknown name raises TypeError."""
        return cls()._with(fields)

    def set(self: T, **fields: Any) -> T:
        """A copy with these fields changed; a field not yet in the document goes after the others, as a
        new key of a dict would. An unknown name raises TypeError."""
        return self._with(fields)

    def without(self: T, *names: str) -> T:
        """A copy without these keys (fields back to their defaults, extra keys dropped)."""
        known = self._fields()
        defaults = {f.name: _default(f) for f in dataclasses.fields(self) if f.name in known}
        gone = set(names)
        return dataclasses.replace(self, **{n: defaults[n] for n in gone if n in known},
                                   extra={k: v for k, v in self.extra.items() if k not in gone},
                                   keys=tuple(k for k in self.keys if k not in gone))

    def has(self, name: str) -> bool:
        """Whether the document has key ``name`` (a field can be in it with its default value)."""
        return name in self.keys or name in self.extra or (
            name in self._fields() and getattr(self, name) != _default(
                next(f for f in dataclasses.fields(self) if f.name == name)))

    def _with(self: T, fields: Mapping[str, Any]) -> T:
        known = self._fields()
        unknown = sorted(set(fields) - set(known))
        if unknown:
            raise TypeError(f"{type(self).__name__} has no field {', '.join(unknown)}")
        kw = {k: _read(known[k], v) for k, v in fields.items()}
        keys = self.keys if self.keys or not self._set_fields() else tuple(self.to_json())
        return dataclasses.replace(self, **kw, keys=keys + tuple(k for k in fields if k not in keys))

    def _set_fields(self) -> bool:
        """Whether any field differs from its default (a section built by the plain constructor)."""
        return any(getattr(self, f.name) != _default(f) for f in dataclasses.fields(self) if f.name != "keys")

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


_FIELD_TYPES: dict[type, dict[str, Any]] = {}


def _field_types(cls: type) -> dict[str, Any]:
    """The JSON fields of a section type with their types (resolved once per type)."""
    if cls not in _FIELD_TYPES:
        hints = typing.get_type_hints(cls)
        _FIELD_TYPES[cls] = {f.name: hints[f.name] for f in dataclasses.fields(cls)
                             if f.name not in ("extra", "keys") and f.metadata.get("json", True)}
    return _FIELD_TYPES[cls]


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
            item = typing.get_args(t)[0] if typing.get_args(t) else None
            if isinstance(item, type) and issubclass(item, JsonSection):
                return tuple(item.from_json(x) if isinstance(x, Mapping) else copy.deepcopy(x) for x in v)
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
        return [_write(x) for x in v]
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
class PriorReport(JsonSection):
    """The prior model's part in the fit (``fit.prior``, output error with a priori weighting): which free
    parameters the flight determines and which stay near their prior. Empty (``{}`` in the file) when
    the fit had no prior."""

    #: where the prior came from (the aircraft file's path, or "given")
    source: str | None = None
    #: free parameters the flight determines (the prior's share of their information at most one half)
    determined: tuple[str, ...] = ()
    #: free parameters kept near the prior (its share above one half)
    prior_dominated: tuple[str, ...] = ()
    #: parameters on a search bound: neither determined nor near the prior, and not an estimate
    on_bound: tuple[str, ...] = ()
    #: parameters the data cannot move at all: the prior's value and std
    fixed_at_prior: tuple[str, ...] = ()
    #: the prior's share of each free parameter's information (0..1)
    prior_share: Mapping[str, float] = field(default_factory=dict)
    nominal: Mapping[str, float] = field(default_factory=dict)
    std: Mapping[str, float] = field(default_factory=dict)


@dataclass(frozen=True)
class CandidateScore(JsonSection):
    """One candidate of a held-out comparison (a row of ``fit.selection.candidates`` or
    ``fit.structure_choice.candidates``): its per-fold scores and, beside the first row (the base),
    its paired gain over the base and whether that gain counts."""

    name: str | None = None
    #: the configuration keys it changes (the selection's candidates)
    overrides: Mapping[str, Any] = field(default_factory=dict)
    #: per fold: the mean over channels of the held-out match (%), each channel floored
    fold_score: tuple[float, ...] = ()
    mean_match: float | None = None
    channel_mean: Mapping[str, float] = field(default_factory=dict)
    #: fold -> channels whose prediction ran away
    runaway: Mapping[str, Any] = field(default_factory=dict)
    #: mean paired gain over the base (points per fold) and its standard error
    gain: float | None = None
    gain_se: float | None = None
    #: folds it gains on
    gain_folds: int | None = None
    significant: bool | None = None
    #: why it cannot win (a runaway prediction), when that decides
    reason: str | None = None
    #: the selection round it ran in (1 = the first)
    round: int | None = None
    #: the winner refitted with its full search, scored again
    final: CandidateScore | None = None


@dataclass(frozen=True)
class Selection(JsonSection):
    """The held-out choice of the fitting configuration (``fit.selection``): every candidate's scores,
    the one chosen and the rule; ``skipped`` says why no comparison ran (then the rest is empty)."""

    #: folds
    k: int | None = None
    chosen: str | None = None
    candidates: tuple[CandidateScore, ...] = ()
    #: the configuration keys the chosen candidate changes
    overrides: Mapping[str, Any] = field(default_factory=dict)
    rule: str | None = None
    skipped: str | None = None


@dataclass(frozen=True)
class StructureChoice(JsonSection):
    """The stabilised aircraft's structure comparison (``fit.structure_choice``): ``chosen`` is "hover"
    or "command_response", ``reason`` says why; ``candidates`` the two structures' held-out scores when
    they were compared."""

    chosen: str | None = None
    reason: str | None = None
    candidates: tuple[CandidateScore, ...] = ()


@dataclass(frozen=True)
class ModelFit(JsonSection):
    """The model file's ``fit`` section (docs/model-file.md); see the module docstring."""

    algorithm: str | None = None
    seed: int | None = None
    #: 1 / (1 + cost)
    fitness: float | None = None
    #: the refined windowed output-error cost (eq. 11)
    cost: float | None = None
    #: the search's cost before refinement (the frequency-domain fit: per subsystem)
    search_cost: float | Mapping[str, float] | None = None
    search_window_s: float | None = None
    search_cost_by_subsystem: Mapping[str, float] = field(default_factory=dict)
    search_restarts: int | None = None
    search_algorithm_by_subsystem: Mapping[str, str] = field(default_factory=dict)
    refined: bool | None = None
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
    #: why each group of parameters is fixed (one sentence each)
    fixed_reasons: tuple[str, ...] = ()
    #: output noise standard deviation per channel
    noise_sigma: Mapping[str, float] = field(default_factory=dict)
    #: search cost per iteration, per subsystem
    history: Mapping[str, Any] = field(default_factory=dict)
    #: cost evaluations at each history entry, per subsystem
    history_nfev: Mapping[str, Any] = field(default_factory=dict)
    notes: tuple[str, ...] = ()
    trim_estimated: bool | None = None
    kinematic_forcing: tuple[Any, ...] = ()
    input_trim_correction_pwm: Mapping[str, float] = field(default_factory=dict)
    #: parameter on a search bound -> why
    pinned_reasons: Mapping[str, Any] = field(default_factory=dict)
    #: unstable modes with their time constants (one sentence each)
    unstable_modes: tuple[str, ...] = ()
    #: the prior model's part in the fit (which parameters it decided, its nominal and std)
    prior: PriorReport | None = None
    #: the held-out choice of the fitting configuration
    selection: Selection | None = None
    heldout: HeldOut | None = None
    #: False when a subsystem's held-out prediction runs away; None when not checked
    usable: bool | None = None
    unusable_subsystems: tuple[str, ...] = ()
    #: what the closed loop means for this model (one sentence each)
    closed_loop: tuple[str, ...] = ()
    #: channels whose prediction runs away (``identify --domain``)
    runaway_channels: tuple[str, ...] = ()
    #: the stabilised aircraft's structure comparison: which structure predicts, and why
    structure_choice: StructureChoice | None = None
    #: the command-response fit, one line per axis
    command_response: tuple[str, ...] = ()
    #: the hover structure's held-out check when the command-response structure was chosen
    heldout_hover: HeldOut | None = None
    #: the previous flights' model predicting this one (the service)
    cross_flight: Mapping[str, Any] = field(default_factory=dict)
    #: frequency-domain scores (``identify --domain``)
    scores: Mapping[str, Any] = field(default_factory=dict)
    #: "frequency" for the frequency-domain fit
    domain: str | None = None
    J_by_subsystem: Mapping[str, float] = field(default_factory=dict)
    cost_by_subsystem: Mapping[str, float] = field(default_factory=dict)
    weighting: str | None = None
    windows_s: tuple[Any, ...] = ()
    frequency_hz: tuple[float, ...] = ()
    sample_interval_s: float | None = None
    #: starts of the least-squares reference fit
    starts: int | None = None
