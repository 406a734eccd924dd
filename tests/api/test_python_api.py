"""The Python API: the names ``groundstation`` exports, that importing it stays cheap, and the worked
example of docs/python-api.md run as written on the bundled real log."""

from __future__ import annotations

import json
import re
import subprocess
import sys
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[2]


def test_the_api_names_are_exported_and_the_import_is_cheap():
    code = ("import sys, groundstation as gs; heavy = [m for m in ('numpy', 'scipy', 'groundstation.sysid', "
            "'groundstation.analysis') if m in sys.modules]; print(heavy); "
            "from groundstation import load_log, analyse, identify, diagnose, HoverModel, Aircraft; "
            "print(sorted(gs.__all__))")
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, check=True).stdout.splitlines()
    assert out[0] == "[]"          # nothing heavy until a name is used
    assert {"load_log", "analyse", "identify", "diagnose", "HoverModel", "Aircraft"} <= set(eval(out[1]))
    import groundstation as gs

    with pytest.raises(AttributeError, match="no attribute 'nope'"):
        gs.nope  # noqa: B018


def test_unknown_step_and_missing_model_are_one_line_errors():
    import groundstation as gs
    from groundstation.analysis import AnalysisError

    with pytest.raises(AnalysisError, match="unknown \\['fit'\\]"):
        gs.analyse("x.tlog", steps=("fit",))
    with pytest.raises(AnalysisError, match="need a model"):
        gs.analyse(str(ROOT / "tests/data/trex550/flight1.tlog.xz"), steps=("validate",))


@pytest.mark.timeout(1800)   # a minute of CPU; much more wall on a loaded machine
def test_the_documented_example_runs(tmp_path, monkeypatch):
    text = (ROOT / "docs/python-api.md").read_text()
    blocks = re.findall(r"```python\n(.*?)```", text, re.S)
    assert blocks, "no python example in docs/python-api.md"
    monkeypatch.chdir(ROOT)
    code = "\n".join(blocks)
    code = code.replace('open("model.json"', f'open({str(tmp_path / "model.json")!r}')
    code = code.replace('open("gap.json"', f'open({str(tmp_path / "gap.json")!r}')
    ns: dict = {}
    exec(compile(code, "docs/python-api.md", "exec"), ns)
    result = ns["result"]
    # what the page says it prints
    assert result.data.outputs_measured == ("p", "q", "r", "theta", "phi")
    assert result.usable is True and 20 < result.heldout.mean_match < 45
    from groundstation.gap.diagnose import VERDICTS

    assert result.gap.verdict in VERDICTS
    assert ("diagnose", "done") in ns["steps_seen"] and ("identify", "start") in ns["steps_seen"]
    model_doc = json.loads((tmp_path / "model.json").read_text())
    assert {"usable", "closed_loop", "heldout", "seconds"} <= set(model_doc["fit"])
    gap_doc = json.loads((tmp_path / "gap.json").read_text())
    assert gap_doc["schema"].startswith("heli-gap-report/") and "frequency" in gap_doc
    # the JSON round trips
    from groundstation.analysis import DataSummary, GapReport
    from groundstation.sysid.fit_section import ModelFit
    from groundstation.sysid.validate import Validation

    assert GapReport.from_json(gap_doc).to_json() == gap_doc
    assert json.dumps(ModelFit.from_json(model_doc["fit"]).to_json()) == json.dumps(model_doc["fit"])
    assert result.fit is not None and result.fit.heldout == result.heldout and result.fit.usable is True
    assert result.validation is not None
    assert Validation.from_json(json.loads(json.dumps(result.validation.to_json()))) == result.validation
    assert DataSummary.from_json(json.loads(json.dumps(result.data.to_json()))) == result.data
    assert json.loads(json.dumps(result.to_json(), default=float))["schema"] == "heli-analysis/1"
