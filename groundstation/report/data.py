"""What a flight report shows, gathered in one frozen object (:class:`FlightReportData`).

The report renders whatever this holds: each part is either present or replaced by the one line
that says why it could not be made (``errors[section]``). Nothing here runs an analysis; that is
:mod:`groundstation.report.collect`'s job. Arrays follow the house conventions: times in FC
seconds ``(n,)``, channels ``(n, 8)`` in :data:`groundstation.sysid.model.OUTPUTS` order.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import Any

import numpy as np

from groundstation.sysid.validate import Validation

#: the sections of a flight page, in page order (id, heading)
SECTIONS: tuple[tuple[str, str], ...] = (
    ("flight", "The flight"),
    ("model", "The model"),
    ("frequency", "Frequency domain"),
    ("gap", "The gap"),
    ("across", "Across flights"),
)


@dataclass(frozen=True)
class Timeline:
    """One log's flight timeline: armed and in-air intervals, flight modes, SYSID chirps, height."""

    source: str
    span_s: tuple[float, float]                       # first and last FC time of the log
    armed_s: tuple[tuple[float, float], ...]
    in_air_s: tuple[tuple[float, float], ...]
    modes: tuple[tuple[float, str], ...]              # (FC time of the change, mode name)
    chirps: tuple[tuple[float, float, str], ...]      # (start, duration s, axis)
    t_height_s: np.ndarray = field(default_factory=lambda: np.zeros(0))
    height_m: np.ndarray = field(default_factory=lambda: np.zeros(0))


@dataclass(frozen=True)
class FlightReportData:
    """Everything a flight page shows; any part may be None with a one-line reason in ``errors``.

    ``log_info``: :func:`groundstation.commands.log_info.summarise` of each log; ``prepared``: a
    :class:`groundstation.dsp.prepare.PreparedData`; ``model``: a :class:`groundstation.sysid.model.HoverModel`
    (its ``fit`` carries the held-out check, the prior and the closed-loop notes); ``validation``: the
    training-window scores (a :class:`groundstation.sysid.validate.Validation` with its ``series``); ``freq``: a :class:`groundstation.freq.verify.FreqVerification`;
    ``gap``: the ``heli-gap-report/1`` document; ``pictures``: its :class:`groundstation.gap.pictures.GapPictures`;
    ``history``: campaign-table rows of this aircraft's flights (oldest first), this flight included or not.
    """

    title: str
    logs: tuple[str, ...]
    aircraft: str | None = None
    input_source: str = ""
    log_info: tuple[dict[str, Any], ...] = ()
    timelines: tuple[Timeline, ...] = ()
    prepared: Any = None
    model: Any = None
    validation: Validation | None = None
    freq: Any = None
    gap: dict[str, Any] | None = None
    pictures: Any = None
    history: tuple[dict[str, Any], ...] = ()
    history_label: str = ""
    errors: dict[str, str] = field(default_factory=dict)
    notes: tuple[str, ...] = ()
    generated_utc: str = ""

    def error(self, part: str) -> str | None:
        return self.errors.get(part)
