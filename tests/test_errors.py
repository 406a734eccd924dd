"""Errors as types: each numerical package raises its own error (a GroundstationError and a
ValueError), and the command line turns bad input into one line naming the file, key and value."""

from __future__ import annotations

import json

import numpy as np
import pytest

from groundstation.cli import main
from groundstation.errors import DspError, FreqError, GapError, GroundstationError, SysidError
from tests.realdata import real_log


@pytest.mark.parametrize("err", [DspError, SysidError, GapError, FreqError])
def test_package_errors_are_project_errors_and_value_errors(err):
    assert issubclass(err, GroundstationError) and issubclass(err, ValueError)


def test_each_package_raises_its_own_error():
    from groundstation.dsp.smoothing import smooth5
    from groundstation.freq.spectra import FreqConfig
    from groundstation.gap.evaluate import Evaluator
    from groundstation.sysid.cost import make_windows
    from groundstation.sysid.model import HoverModel

    with pytest.raises(DspError, match="passes must be >= 0, got -1"):
        smooth5(np.zeros((10, 2)), passes=-1)
    with pytest.raises(SysidError, match=r"identify\.window_s = 0\.04: fewer than 5 samples"):
        make_windows([], 0.02, 0.04, key="identify.window_s")
    with pytest.raises(SysidError, match=r"model field parameters\.X_u = 'abc': not a number"):
        HoverModel.from_json({"schema": "heli-hover-model/1", "parameters": {"X_u": "abc"}})
    with pytest.raises(GapError, match="too little in-air data"):
        Evaluator([], 0.02, np.zeros(31), np.ones(8, bool), window_s=3.0, folds=3)
    with pytest.raises(FreqError, match=r"freq\.overlap must be in \[0, 1\), got 1\.5"):
        FreqConfig(overlap=1.5)
    # existing callers that catch ValueError keep working
    with pytest.raises(ValueError):
        make_windows([], 0.02, 0.04)


def _one_line_error(capsys, argv: list[str]) -> str:
    rc = main(argv)
    err = capsys.readouterr().err.strip()
    assert rc == 2
    assert len(err.splitlines()) == 1, err
    assert "Traceback" not in err
    return err


@pytest.fixture(scope="module")
def model_file(tmp_path_factory):
    from benchkit.synthetic import EXAMPLE_TRUTH
    from groundstation.sysid.model import HoverModel

    path = tmp_path_factory.mktemp("errors") / "model.json"
    path.write_text(json.dumps(HoverModel(params=dict(EXAMPLE_TRUTH)).to_json()))
    return path


@pytest.mark.parametrize("command", ["identify", "validate", "diagnose"])
def test_a_log_with_no_flight_is_one_line_naming_the_log(command, model_file, tmp_path, capsys):
    log = real_log("px4/trex550_groundrun.px4log")
    argv = {"identify": ["identify", str(log), "--out", str(tmp_path / "m.json"), "--no-plot", "--quiet"],
            "validate": ["validate", str(model_file), str(log)],
            "diagnose": ["diagnose", str(log), "--model", str(model_file), "--out", str(tmp_path / "r.json"),
                         "--quiet"]}[command]
    err = _one_line_error(capsys, argv)
    assert err.startswith(f"groundstation {command}: error: ")
    assert str(log) in err and "never left the ground" in err
    assert not (tmp_path / "m.json").exists() and not (tmp_path / "r.json").exists()


@pytest.mark.parametrize("command", ["identify", "validate"])
def test_an_aircraft_file_with_an_unknown_key_is_one_line_naming_file_key_value(command, model_file, tmp_path,
                                                                                capsys):
    aircraft = tmp_path / "heli.toml"
    aircraft.write_text('name = "heli"\nrotor_colour = "red"\n[inputs]\nsource = "SERVO_OUTPUT_RAW"\n')
    log = real_log("trex550/flight1.tlog")
    argv = {"identify": ["identify", str(log), "--out", str(tmp_path / "m.json"), "--no-plot", "--quiet"],
            "validate": ["validate", str(model_file), str(log)]}[command]
    err = _one_line_error(capsys, argv + ["--aircraft", str(aircraft)])
    assert str(aircraft) in err and "rotor_colour" in err and "red" not in err.split("allowed")[-1]
    assert "unknown key" in err


def test_a_window_longer_than_any_flight_names_log_key_and_value(model_file, tmp_path, capsys):
    log = real_log("trex550/flight1.tlog")
    err = _one_line_error(capsys, ["diagnose", str(log), "--model", str(model_file), "--out",
                                   str(tmp_path / "r.json"), "--quiet", "--window-s", "5000"])
    assert str(log) in err and "diagnose.window_s = 5000" in err
    config = tmp_path / "long.toml"
    config.write_text("[identify]\nwindow_s = 4000.0\n")
    err = _one_line_error(capsys, ["identify", str(log), "--out", str(tmp_path / "m.json"), "--no-plot",
                                   "--quiet", "--config", str(config)])
    assert str(log) in err and "identify.window_s = 4000" in err and "longest" in err


def test_a_model_file_that_is_not_json_text_names_the_file(tmp_path, capsys):
    bad = tmp_path / "model.json"  # a flight log given where the model belongs
    bad.write_bytes(real_log("px4/trex550_groundrun.px4log").read_bytes())
    err = _one_line_error(capsys, ["validate", str(bad), str(real_log("trex550/flight1.tlog"))])
    assert str(bad) in err and "not a model file" in err
