"""``groundstation report``: the page a person opens, checked as one would look at it.

A 150-s simulated flight (with a 80-ms delay on the longitudinal input) goes through the command once
(module fixture); the tests read the page it wrote: every section, at least 8 figures, every axis with
a unit, no network reference, under 5 MB; then headless Chromium opens it (installed by the set-up when
missing, or the test is skipped with the reason) and must report no console error. Bad input still
gets a page: a log with no in-air data and a file that is not a log.
"""

from __future__ import annotations

import json
import re
import subprocess
import sys
from html.parser import HTMLParser
from pathlib import Path
from types import SimpleNamespace

import pytest

from groundstation.report.data import SECTIONS, FlightReportData
from groundstation.report.render import one_line_summary
from tests.report.browser import Browser, ensure_chromium

SECTION_IDS = [s for s, _ in SECTIONS]
UNIT = re.compile(r"\([^()]*\)\s*$")


def _cli(*args: str) -> subprocess.CompletedProcess:
    return subprocess.run([sys.executable, "-m", "groundstation.cli", *args], capture_output=True, text=True,
                          timeout=900)


class Page(HTMLParser):
    """What the tests look at in a page: sections, figures with their axis labels, external references."""

    def __init__(self, html: str) -> None:
        super().__init__()
        self.sections: list[str] = []
        self.figures: list[dict] = []
        self.external: list[str] = []
        self.scripts = 0
        self.unmade: list[str] = []
        self._in_unmade = False
        self._section = ""
        self.feed(html)

    def handle_starttag(self, tag: str, attrs: list) -> None:
        a = dict(attrs)
        if tag == "section":
            self._section = a.get("id", "")
            self.sections.append(self._section)
        if tag == "figure" and "report-figure" in (a.get("class") or ""):
            self.figures.append({"id": a["id"], "kind": a["data-kind"], "axes": json.loads(a["data-axes"]),
                                 "section": self._section})
        if tag == "script":
            self.scripts += 1
        for k in ("src", "href", "xlink:href"):
            v = a.get(k) or ""
            if v and not v.startswith(("#", "data:")):
                self.external.append(v)
        if a.get("data-unmade"):
            self._in_unmade = True
            self.unmade.append(self._section)

    def handle_endtag(self, tag: str) -> None:
        if tag == "p":
            self._in_unmade = False


@pytest.fixture(scope="module")
def sim_page(tmp_path_factory) -> tuple[Path, str]:
    d = tmp_path_factory.mktemp("report")
    log = d / "flight.tlog"
    r = _cli("simulate", "--out", str(log), "--duration-s", "150", "--seed", "5",
             "--effect", "input_delay:input=lon,delay_s=0.08")
    assert r.returncode == 0, r.stderr
    out = d / "flight.html"
    cfg = d / "fast.toml"   # one search per subsystem instead of two: the page is the same kind of page
    cfg.write_text("[identify]\nsearch_restarts = 1\n")
    r = _cli("report", str(log), "--out", str(out), "--jobs", "1", "--json-out", str(d / "json"), "--config", str(cfg))
    assert r.returncode == 0, r.stderr
    return out, r.stderr


def test_page_has_every_section_figures_with_units_and_no_external_file(sim_page):
    path, stderr = sim_page
    html = path.read_text()
    page = Page(html)
    assert page.sections == SECTION_IDS
    assert len(page.figures) >= 8, [f["id"] for f in page.figures]
    for f in page.figures:
        assert f["axes"], f"{f['id']}: no axes recorded"
        for x, y in f["axes"]:
            assert UNIT.search(x) and UNIT.search(y), f"{f['id']}: axis without a unit: {x!r} / {y!r}"
    # every analysed section has its figures: the flight, the model, frequency domain, the gap
    for sec in ("flight", "model", "frequency", "gap"):
        assert any(f["section"] == sec for f in page.figures), sec
    assert {"fit", "heldout", "tischler-j", "residual"} <= {f["id"].removeprefix("fig-") for f in page.figures}
    assert page.external == [] and page.scripts == 0, page.external
    assert not re.search(r"https?://", re.sub(r'xmlns(:\w+)?="[^"]*"', "", html)), "network reference in the page"
    assert path.stat().st_size < 5_000_000
    # on this flight everything could be made; the across-flights section says none are known
    assert set(page.unmade) <= {"across"}, page.unmade
    assert "verdict" in html and "input_delay" in html
    assert "wrote" in stderr and "verdict" in stderr
    assert (path.parent / "json" / "model.json").exists() and (path.parent / "json" / "gap.json").exists()


@pytest.fixture(scope="module")
def browser():
    exe, why = ensure_chromium()
    if exe is None:
        pytest.skip(f"headless Chromium not available: {why}")
    with Browser(exe) as b:
        yield b


def test_page_renders_in_chromium_without_console_error(sim_page, browser, tmp_path):
    path, _ = sim_page
    problems = browser.open(path)
    assert problems == []
    ids = browser.evaluate("Array.from(document.querySelectorAll('section.report-section')).map(s => s.id)")
    assert ids == SECTION_IDS
    heads = browser.evaluate("Array.from(document.querySelectorAll('section h2')).map(h => h.innerText)")
    assert [h.split(". ", 1)[1] for h in heads] == [t for _, t in SECTIONS]
    # every figure is drawn with a real size inside the page width
    sizes = browser.evaluate("Array.from(document.querySelectorAll('figure.report-figure > :first-child'))"
                             ".map(e => { const r = e.getBoundingClientRect(); return [r.width, r.height]; })")
    assert len(sizes) >= 8 and all(w > 200 and h > 100 for w, h in sizes), sizes
    assert browser.evaluate("document.documentElement.scrollWidth <= window.innerWidth")
    assert browser.evaluate("Array.from(document.images).every(i => i.complete && i.naturalWidth > 0)")
    pdf = browser.pdf()
    assert pdf.startswith(b"%PDF") and len(re.findall(rb"/Type\s*/Page(?!s)", pdf)) >= 5   # printable, paged
    shot = browser.screenshot(tmp_path / "page.png")
    assert shot.read_bytes()[:8] == b"\x89PNG\r\n\x1a\n"


def test_a_log_without_flight_still_gets_a_page(tmp_path, sim_page, browser):
    """The first seconds of a log (on the ground) and a file that is not a log: data quality where there
    is any, and one clear line per section that could not be made."""
    log = sim_page[0].parent / "flight.tlog"
    short = tmp_path / "ground.tlog"
    short.write_bytes(log.read_bytes()[: log.stat().st_size // 40])
    junk = tmp_path / "junk.tlog"
    junk.write_bytes(b"this is not a flight log\n" * 50)
    for src, readable in ((short, True), (junk, False)):
        out = tmp_path / (src.stem + ".html")
        r = _cli("report", str(src), "--out", str(out), "--jobs", "1")
        assert r.returncode == 0, r.stderr
        page = Page(out.read_text())
        assert page.sections == SECTION_IDS
        assert {"model", "frequency", "gap"} <= set(page.unmade), (src, page.unmade)
        text = out.read_text()
        assert "Could not be made" in text
        if readable:
            assert "fig-timeline" in text and "fig-rates" in text   # the data-quality section is there
        assert browser.open(out) == []


def test_the_one_line_summary_gives_j_avg_as_the_page_does():
    """The published one-line summary rounds J_avg to one decimal, as the page's frequency section does
    (a J_avg of 3.43 read "J_avg 3" beside "J_avg = 3.4")."""
    freq = SimpleNamespace(J_avg=3.43)  # the one figure the line reads of a FreqVerification
    line = one_line_summary(FlightReportData(title="t", logs=(), freq=freq))
    assert "J_avg 3.4" in line
