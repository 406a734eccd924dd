"""End-to-end: identify/validate commands on a simulated .tlog, bad input, and the real TREX 550 log."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest

from groundstation.cli import main
from tests.realdata import real_log


@pytest.fixture(scope="module")
def sim_tlog(tmp_path_factory):
    from hil_replay.sim import write_tlog

    d = tmp_path_factory.mktemp("sim")
    p = d / "flight.tlog"
    write_tlog(p, seed=3, flights=1, effects=(), aircraft=None, flight_duration_s=60.0)
    return p


def test_identify_then_validate_cli(sim_tlog, tmp_path, capsys):
    out = tmp_path / "model.json"
    assert main(["identify", str(sim_tlog), "--out", str(out), "--maxiter", "8", "--quiet"]) == 0
    doc = json.loads(out.read_text())
    assert doc["schema"] == "heli-hover-model/1"
    assert len(doc["parameters"]) == 31 and doc["fit"]["algorithm"] == "cabc"
    assert doc["fit"]["seconds"] > 0 and doc["source"]["logs"] == [str(sim_tlog)]
    assert out.with_suffix(".png").stat().st_size > 10_000
    assert (tmp_path / "model_convergence.png").stat().st_size > 5_000
    capsys.readouterr()
    rrd = tmp_path / "val.rrd"
    assert main(["validate", str(out), str(sim_tlog), "--json", "--rrd", str(rrd)]) == 0
    res = json.loads(capsys.readouterr().out)
    from rerun.chunk import RrdReader

    rows: dict[str, int] = {}
    for c in RrdReader(rrd).stream().to_chunks():
        if not c.is_static:
            rows[c.entity_path] = rows.get(c.entity_path, 0) + c.num_rows
            assert "fc_time" in c.timeline_names
    n = rows["/sysid/outputs/q/measured"]
    assert n > 1000 and rows["/sysid/outputs/q/model"] == n
    assert set(res["channels"]) == {"u", "v", "w", "p", "q", "r", "theta", "phi"}
    for m in res["channels"].values():
        assert np.isfinite(m["match"]) and 0 <= m["tic"] <= 1


def _tlog_without_servo(path: Path) -> None:
    from pymavlink.dialects.v20 import ardupilotmega as mavlink

    from firmware_interface.tlog import TlogWriter

    mav = mavlink.MAVLink(None, srcSystem=1, srcComponent=1)
    w = TlogWriter(path)
    for k in range(600):
        t = k * 0.02
        if k % 50 == 0:
            hb = mavlink.MAVLink_heartbeat_message(4, 3, mavlink.MAV_MODE_FLAG_SAFETY_ARMED, 0, 4, 3)
            w.write(hb.pack(mav), 1000.0 + t)
        att = mavlink.MAVLink_attitude_message(int(t * 1000), 0.0, 0.0, 0.0, 0.0, 0.0, 0.0)
        w.write(att.pack(mav), 1000.0 + t)
    w.close()


def test_bad_input_names_the_missing_message(tmp_path, capsys):
    bad = tmp_path / "noservo.tlog"
    _tlog_without_servo(bad)
    rc = main(["identify", str(bad), "--out", str(tmp_path / "m.json"), "--quiet"])
    err = capsys.readouterr().err.strip()
    assert rc == 2
    assert "SERVO_OUTPUT_RAW" in err and "noservo.tlog" in err and len(err.splitlines()) == 1
    assert not (tmp_path / "m.json").exists()
    rc = main(["validate", str(tmp_path / "missing.json"), str(bad)])
    assert rc == 2 and "missing.json" in capsys.readouterr().err


def test_real_trex550_log_identifies_what_it_supports():
    from firmware_interface.readers import load_log
    from groundstation.dsp.prepare import prepare
    from groundstation.sysid.identify import IdentifyConfig, identify
    from groundstation.sysid.validate import validate

    prep = prepare([load_log(real_log("trex550/flight1.tlog"))])
    assert not prep.input_active[0]  # lateral cyclic was not logged
    assert any("lat never moves" in n for n in prep.notes)
    # velocities are NaN after ~215 s: a segment without u v w exists
    assert any(not s.available[0] for s in prep.segments)
    m = identify(prep, seed=0, maxiter=6, config=IdentifyConfig(refine_max_nfev=8, refine_passes=1))
    for name in ("X_lat", "M_lat", "L_lat", "A_lat"):
        assert name in m.fit.fixed and m.params[name] == 0.0 and m.parameter_std[name] is None
    v = validate(m, prep)
    assert {"p", "q", "r", "theta", "phi"} <= set(v.channels)
    assert all(np.isfinite(c.match) for c in v.channels.values())


def test_identify_real_log_with_aircraft_file_reports_heldout_prior_and_closed_loop(tmp_path, capsys):
    """The real TREX 550 log with its aircraft file (kept short: few iterations, 3 folds): the model file
    carries the held-out check per channel, the channels predicted or not, which parameters the prior
    holds, bounds, unstable modes and the closed-loop evidence."""
    import json
    from pathlib import Path

    src = Path(__file__).resolve().parents[2] / "groundstation" / "configs" / "aircraft" / "trex550.toml"
    ac = tmp_path / "trex550.toml"
    ac.write_text(src.read_text().replace("[prior]", "refine_max_nfev = 8\nrefine_passes = 1\nsearch_restarts = 1\n\n[prior]"))
    out = tmp_path / "m.json"
    rc = main(["identify", str(real_log("trex550/flight1.tlog")), "--out", str(out), "--aircraft", str(ac),
               "--maxiter", "4", "--folds", "3", "--no-plot"])
    assert rc == 0
    fit = json.loads(out.read_text())["fit"]
    ho = fit["heldout"]
    assert ho["k"] == 3 and set(ho["channel_mean"]) >= {"p", "q", "r", "theta", "phi"}
    assert set(ho["predicted"]) | set(ho["not_predicted"]) == set(ho["channel_mean"])
    assert fit["usable"] == (not ho["unusable_subsystems"])
    assert fit["prior"]["source"].startswith("wide defaults")
    assert set(fit["prior"]["determined"]) | set(fit["prior"]["prior_dominated"]) | set(fit["prior"]["on_bound"]) | set(fit["fixed"]) >= {"inv_tau_s", "N_r"}
    assert isinstance(fit["closed_loop"], list) and isinstance(fit["unstable_modes"], list)
    # the pitch rate still rises before the stick on the pilot's sharp steps: the inputs are logged late
    assert any("before lon" in c and "60 ms already applied" in c for c in fit["closed_loop"])
    printed = capsys.readouterr().err
    assert "held-out match over 3 contiguous folds" in printed and "the model predicts" in printed
    # the configuration was compared with the aircraft file's candidate over 5 folds, and the printed
    # 3-fold check is of the configuration it chose
    sel = fit["selection"]
    assert sel["k"] == 5 and {r["name"] for r in sel["candidates"]} == {"as configured", "predictive"}
    assert "configuration chosen by held-out prediction over 5 folds" in printed and sel["chosen"] in printed
