"""The service's between-flight files are what the command line gives for the same flight: one
simulated flight through the built-in FC, then ``identify`` and ``diagnose --model`` of the flight's
recording with the same configuration; the model and gap files are equal but for wall times."""

from __future__ import annotations

import asyncio
import json

import pytest

from groundstation.cli import main
from groundstation.service import Service
from tests.service.conftest import service_config

#: wall-clock fields: the only ones allowed to differ
WALL = {"seconds", "identify_s", "wall_s"}


def _without_wall(doc):
    if isinstance(doc, dict):
        return {k: _without_wall(v) for k, v in doc.items() if k not in WALL}
    if isinstance(doc, list):
        return [_without_wall(v) for v in doc]
    return doc


def _diff(a, b, path="") -> list[str]:
    if isinstance(a, dict) and isinstance(b, dict):
        out = [f"{path}.{k}: only in one" for k in sorted(set(a) ^ set(b))]
        return out + [d for k in sorted(set(a) & set(b)) for d in _diff(a[k], b[k], f"{path}.{k}")]
    if isinstance(a, list) and isinstance(b, list) and len(a) == len(b):
        return [d for i, (x, y) in enumerate(zip(a, b, strict=True)) for d in _diff(x, y, f"{path}[{i}]")]
    return [] if a == b else [f"{path}: {a!r} != {b!r}"[:200]]


@pytest.mark.timeout(1800)   # a flight, its analysis in the service, then identify and diagnose again: minutes on a busy machine
def test_service_files_equal_identify_and_diagnose_of_the_recording(tmp_path):
    # [excitation] off: with it on, the service's frequency check uses the spectra its live monitor
    # accumulated during the flight (the same windows and grid as the log's, tested in
    # test_excitation_service.py), not a second pass over the recording as diagnose makes
    sections = {"identify": {"maxiter": 6}, "identification": {"refine": False, "plots": False},
                "excitation": {"enabled": False}}
    cfg = service_config(tmp_path, service={"exit_after_flights": 1}, sim={"speed": 20.0, "flights": 1, "seed": 4},
                         **sections)
    service = Service(cfg, sim_options={"flight_duration_s": 40.0, "pause_s": 3.0}, log=lambda m: None)
    report = asyncio.run(asyncio.wait_for(service.run(), 1500))
    assert report.flights == 1 and len(report.results) == 1
    r = report.results[0]
    assert r.ok, r.error
    assert r.gap_error is None and r.freq_error is None, (r.gap_error, r.freq_error)
    (tlog,) = r.tlogs
    served_model = json.loads(open(r.model_path).read())
    served_gap = json.loads(open(r.gap_path).read())
    # the model file carries the held-out verdict, as identify's does
    assert {"usable", "closed_loop", "heldout"} <= set(served_model["fit"])
    assert served_model["fit"]["seconds"] > 0

    toml = tmp_path / "same.toml"
    toml.write_text("[identify]\nmaxiter = 6\n\n[identification]\nrefine = false\n\n[excitation]\nenabled = false\n")
    model_path, gap_path = tmp_path / "cli-model.json", tmp_path / "cli-gap.json"
    assert main(["identify", tlog, "--out", str(model_path), "--config", str(toml), "--no-plot", "--quiet",
                 "--jobs", "1"]) == 0
    assert main(["diagnose", tlog, "--model", str(model_path), "--out", str(gap_path), "--config", str(toml),
                 "--quiet", "--jobs", "1"]) == 0
    cli_model = json.loads(model_path.read_text())
    cli_gap = json.loads(gap_path.read_text())

    assert not _diff(_without_wall(served_model), _without_wall(cli_model))
    assert served_gap["source"]["logs"] == cli_gap["source"]["logs"] == [tlog]
    served_gap["source"].pop("model"), cli_gap["source"].pop("model")    # where each model file was written
    assert "frequency" in served_gap and "error" not in served_gap["frequency"]
    assert not _diff(_without_wall(served_gap), _without_wall(cli_gap))
