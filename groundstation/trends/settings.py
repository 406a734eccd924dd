"""Settings of the change test across flights (``[trends]``), apart from the statistics so the
configuration loads them without importing scipy.stats."""

from __future__ import annotations

from dataclasses import dataclass


@dataclass(frozen=True)
class TrendConfig:
    """Change-test settings (``[trends]``)."""

    alpha: float = 0.05  # family-wise false-alarm probability over every series and flight tested
    baseline: int = 1  # flights averaged into the reference value
