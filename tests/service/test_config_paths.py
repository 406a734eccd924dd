"""One configuration, one preparation: a non-default servo map, fixed trims and pwm_per_unit from
``--config`` give the same model through ``groundstation identify`` and through the service's worker
process (spawned, as the service runs it)."""

from __future__ import annotations

import concurrent.futures
import json
import multiprocessing
from pathlib import Path

import numpy as np
import pytest

from groundstation.cli import main
from groundstation.config import load_config
from groundstation.worker import IdentifyJob, run_job

ROOT = Path(__file__).resolve().parents[2]
TRIM = (1490.0, 1512.0, 1575.0, 1466.0)


@pytest.fixture(scope="module")
def remapped_flight(tmp_path_factory):
    """A simulated flight whose aircraft carries lat lon col ped on servos 2 1 4 3, 400 us per unit."""
    from hil_replay.sim import write_tlog

    d = tmp_path_factory.mktemp("remap")
    text = (ROOT / "hil_replay" / "aircraft" / "trex600.toml").read_text()
    text = text.replace("pwm_per_unit = 500.0", "pwm_per_unit = 400.0")
    text = text.replace("lat = 1\nlon = 2\ncol = 3\nped = 4", "lat = 2\nlon = 1\ncol = 4\nped = 3")
    assert "col = 4" in text
    (d / "remap.toml").write_text(text)
    log = d / "flight.tlog"
    write_tlog(log, seed=5, flights=1, aircraft=d / "remap.toml", flight_duration_s=45.0)
    cfg = d / "gs.toml"
    cfg.write_text("[prepare]\ninput_channels = [2, 1, 4, 3]\n"
                   f"input_trim_pwm = {list(TRIM)}\npwm_per_unit = 400.0\n"
                   "[identify]\nmaxiter = 4\nsearch_restarts = 1\nrefine_passes = 1\nrefine_max_nfev = 8\n"
                   "[identification]\nseed = 3\ndiagnose = false\nplots = false\n")
    return log, cfg


def test_service_worker_and_identify_command_give_the_same_model(remapped_flight, tmp_path):
    log, cfg_path = remapped_flight
    out = tmp_path / "cli" / "model.json"
    assert main(["identify", str(log), "--out", str(out), "--config", str(cfg_path), "--no-plot", "--quiet"]) == 0
    cli = json.loads(out.read_text())

    (tmp_path / "svc").mkdir()
    job = IdentifyJob(flight=1, tlogs=(str(log),), out_dir=str(tmp_path / "svc"), config=load_config(cfg_path))
    with concurrent.futures.ProcessPoolExecutor(1, mp_context=multiprocessing.get_context("spawn")) as ex:
        res = ex.submit(run_job, job).result(timeout=600)
    assert res.ok, res.error
    svc = res.model

    # the configuration reached identification: the scale is the model's, the trims the same
    # (the configured trim plus the offset identification estimates)
    assert cli["pwm_per_unit"] == svc["pwm_per_unit"] == 400.0
    assert svc["input_trim_pwm"] == pytest.approx(cli["input_trim_pwm"], rel=1e-9)
    assert svc["parameters"] == pytest.approx(cli["parameters"], rel=1e-9, abs=1e-12)
    for sub in ("horizontal", "vertical"):
        for m in ("A", "B"):
            np.testing.assert_allclose(svc[sub][m], cli[sub][m], rtol=1e-9, atol=1e-12)


def test_the_channel_map_matters(remapped_flight):
    """Control for the test above: the default map reads other servos (the inputs differ)."""
    from groundstation.config import ServiceConfig
    from groundstation.pipeline import prepare_logs

    log, cfg_path = remapped_flight
    mapped = prepare_logs([log], load_config(cfg_path))
    default = prepare_logs([log], ServiceConfig())
    u_mapped = np.concatenate([s.inputs for s in mapped.segments])
    u_default = np.concatenate([s.inputs for s in default.segments])
    n = min(len(u_mapped), len(u_default))
    assert not np.allclose(u_mapped[:n], u_default[:n], atol=1e-3)
    # the collective is on servo 4: it is what the mapped col channel reads (same PWM, own trim/scale)
    assert mapped.input_trim_pwm == dict(zip(("lat", "lon", "col", "ped"), TRIM, strict=True))


def test_service_worker_takes_the_aircraft_file(remapped_flight, tmp_path):
    """``[identification] aircraft`` (``run --aircraft``): the worker prepares the flight with the aircraft
    file's channel map and identifies it with its prior, as ``identify --aircraft`` does; the service's
    live path reads the same map."""
    from groundstation.config import ServiceConfig
    from groundstation.service import Service

    log, _ = remapped_flight
    ac = tmp_path / "remap.aircraft.toml"
    ac.write_text('name = "remap"\n[inputs]\nlat = 2\nlon = 1\ncol = 4\nped = 3\npwm_per_unit = 400.0\n'
                  '[identify]\nmaxiter = 4\nsearch_restarts = 1\nrefine_passes = 1\nrefine_max_nfev = 8\n'
                  'select_candidates = ""\n[prior]\nsource = "test prior"\ninv_tau_s = [9.0, 3.0]\n')
    gs = tmp_path / "gs.toml"
    gs.write_text("[identification]\nseed = 3\ndiagnose = false\nplots = false\n")
    out = tmp_path / "cli" / "model.json"
    assert main(["identify", str(log), "--out", str(out), "--config", str(gs), "--aircraft", str(ac),
                 "--no-plot", "--quiet", "--folds", "0"]) == 0
    cli = json.loads(out.read_text())

    cfg = load_config(gs).replace("identification", aircraft=str(ac))
    assert Service(cfg, log=lambda _: None).config.live.servo_numbers == (2, 1, 4, 3)
    (tmp_path / "svc").mkdir()
    res = run_job(IdentifyJob(flight=1, tlogs=(str(log),), out_dir=str(tmp_path / "svc"), config=cfg))
    assert res.ok, res.error
    svc = res.model
    assert svc["fit"]["prior"]["source"] == cli["fit"]["prior"]["source"] == "test prior"
    assert svc["pwm_per_unit"] == 400.0
    assert svc["parameters"] == pytest.approx(cli["parameters"], rel=1e-9, abs=1e-12)
    # without the file the worker reads the default servos and has no prior: another model
    plain = run_job(IdentifyJob(flight=1, tlogs=(str(log),), out_dir=str(tmp_path / "svc"), config=ServiceConfig()
                                .replace("identify", maxiter=4, search_restarts=1, select_candidates="")
                                .replace("identification", diagnose=False, plots=False)))
    assert plain.ok and not plain.model["fit"]["prior"]
    assert plain.model["parameters"] != pytest.approx(svc["parameters"], rel=1e-3)
