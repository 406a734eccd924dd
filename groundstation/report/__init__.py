"""One self-contained HTML page per flight and per campaign.

``collect(logs, ...)`` (:mod:`groundstation.report.collect`) runs what the page needs and is missing
- data quality, identification, held-out check, frequency check, diagnosis - and returns a
:class:`~groundstation.report.data.FlightReportData`; :func:`render_report` turns that into the page
(Jinja2 template, matplotlib figures embedded as SVG or PNG); :func:`render_campaign` makes the
campaign's page from its table. :func:`write_html` writes a page atomically. The analysis is the
other packages'; this one only gathers and draws.
"""

from __future__ import annotations

from pathlib import Path

from groundstation.report.data import SECTIONS, FlightReportData, Timeline
from groundstation.report.render import one_line_summary, render_campaign, render_report

__all__ = ["SECTIONS", "FlightReportData", "Timeline", "one_line_summary", "render_campaign", "render_report",
           "write_html"]


def write_html(path: str | Path, html: str) -> Path:
    """Write ``html`` to ``path`` (atomically: a reader never sees half a page)."""
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    tmp = path.with_name(path.name + ".tmp")
    tmp.write_text(html, encoding="utf-8")
    tmp.replace(path)
    return path
