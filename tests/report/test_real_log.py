"""The page of the real TREX 550 flight says what the data do not support, as plainly as the terminal:
the lateral stick never moves, the velocities are not usable, most parameters cannot be identified, and
the held-out prediction is poor. (The log: tests/data/trex550, see its README.)"""

from __future__ import annotations

import re
import subprocess
import sys
from pathlib import Path

import pytest

from tests.realdata import real_log
from tests.report.test_report import SECTION_IDS, UNIT, Page

AIRCRAFT = Path(__file__).resolve().parents[2] / "groundstation" / "configs" / "aircraft" / "trex550.toml"


@pytest.mark.slow
def test_trex550_page_says_what_the_flight_does_not_support(tmp_path):
    out = tmp_path / "trex.html"
    r = subprocess.run([sys.executable, "-m", "groundstation.cli", "report", str(real_log("trex550/flight1.tlog")),
                        "--aircraft", str(AIRCRAFT), "--out", str(out), "--jobs", "1"],
                       capture_output=True, text=True, timeout=1500)
    assert r.returncode == 0, r.stderr
    html = out.read_text()
    page = Page(html)
    assert page.sections == SECTION_IDS and len(page.figures) >= 8
    assert all(UNIT.search(x) and UNIT.search(y) for f in page.figures for x, y in f["axes"])
    box = re.search(r'<div class="unsupported" id="unsupported">(.*?)</div>', html, re.S)
    assert box, "no 'what this flight does not support' box"
    text = re.sub(r"<[^>]+>", " ", box.group(1))
    assert "Input never moved: lat" in text
    assert re.search(r"Outputs not measured or left out: u, v, w", text)
    assert "cannot be identified from this flight" in text
    assert re.search(r"predicts only \d+ % of held-out data", text)
    # the summary line the terminal prints is the page's first line too
    assert "held-out match" in r.stderr and "in air" in r.stderr
