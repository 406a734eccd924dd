"""Held-out prediction scores, shared by the hover model's prediction (:mod:`groundstation.sysid.heldout`)
and the stabilised aircraft's (:mod:`groundstation.sysid.structure`). A plain record; no numerics."""

from __future__ import annotations

from dataclasses import dataclass, field


@dataclass(frozen=True)
class Prediction:
    """Held-out scores: ``match`` per channel (%), ``mean_match`` over them, window count and length."""

    match: dict[str, float]
    mean_match: float
    windows: int
    window_s: float
    duration_s: float
    ratio: dict[str, float] = field(default_factory=dict)  # ||yhat - y|| / ||y|| per channel
