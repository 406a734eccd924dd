"""``groundstation simulate --out x.bin``: the simulated autopilot's onboard dataflash log, read back by
pymavlink's DFReader (through log-info), with its 200 Hz records and the card's sweeps as SYSID chirps."""

from __future__ import annotations

import json

import numpy as np
import pytest
from pymavlink import DFReader

from firmware_interface.readers import load_log
from groundstation.cli import main as cli_main


@pytest.fixture(scope="module")
def sim_bin(tmp_path_factory):
    out = tmp_path_factory.mktemp("bin") / "flight.bin"
    assert cli_main(["simulate", "--out", str(out), "--duration-s", "40", "--seed", "2",
                     "--effect", "rotor_vibration"]) == 0
    return out


def test_records_at_200_hz_and_chirps_match_the_card(sim_bin, capsys):
    capsys.readouterr()
    truth = json.loads(sim_bin.with_suffix(".truth.json").read_text())
    df = DFReader.DFReader_binary(str(sim_bin), zero_time_base=False)  # pymavlink reads it on its own
    names = {df.id_to_name[k] for k, offs in enumerate(df.offsets) if len(offs) and k in df.id_to_name}
    assert {"IMU", "ATT", "RATE", "RCOU", "HELI", "XKF1", "SIDS", "SIDD", "EV"} <= names
    log = load_log(sim_bin)
    for name in ("IMU", "ATTITUDE", "SERVO_OUTPUT_RAW", "ROTOR"):
        dt = np.median(np.diff(log.series[name].t_fc_s))
        assert dt == pytest.approx(0.005, abs=1e-4), name
    sweeps = [s for f in truth["flights"] for s in f["segments"] if s["name"].startswith("sweep_")]
    assert len(log.chirps) == len(sweeps) > 0
    axes = {"lat": "mixer_roll", "lon": "mixer_pitch", "ped": "mixer_yaw", "col": "mixer_thrust"}
    for c, s in zip(log.chirps, sweeps, strict=True):
        assert c.axis_name == axes[s["axis"]]
        assert c.start_fc_s == pytest.approx(s["start_fc_s"], abs=0.01)
        assert c.duration_s == pytest.approx(s["end_fc_s"] - s["start_fc_s"], abs=0.02)
    rpm = log.series["ROTOR"]["rotor_speed_rpm"]
    assert np.max(rpm) == pytest.approx(truth["effects"][0]["params"]["rpm"])
    assert len(log.flights) == 1


def test_identify_on_the_sysid_segments_only(sim_bin, tmp_path, capsys):
    out = tmp_path / "m.json"
    code = cli_main(["identify", str(sim_bin), "--segments", "sysid", "--out", str(out), "--maxiter", "3",
                     "--no-plot", "--quiet"])
    err = capsys.readouterr().err
    if code != 0:  # two 6 s chirps may be too little for the windows: then one line says so
        assert len(err.strip().splitlines()) == 1 and str(sim_bin) in err
    else:
        doc = json.loads(out.read_text())
        log = load_log(sim_bin)
        total = sum(c.duration_s for c in log.chirps)
        assert doc["schema"] == "heli-hover-model/1"
        assert doc["source"]["window_s"][1] - doc["source"]["window_s"][0] <= total + 1.0


def test_bin_writer_and_log_serving_fc_are_independent_of_the_estimators(tmp_path):
    """Writing the onboard log and serving it must not load groundstation.sysid/gap (the simulator is the truth)."""
    import subprocess
    import sys

    code = ("import sys; from hil_replay.dataflash import write_bin; import hil_replay.fc; "
            f"write_bin({str(tmp_path / 'i.bin')!r}, seed=0, flight_duration_s=30); "
            "bad = [m for m in sys.modules if m.startswith(('groundstation.sysid', 'groundstation.gap'))]; "
            "print(bad); sys.exit(1 if bad else 0)")
    res = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, timeout=120)
    assert res.returncode == 0, res.stdout + res.stderr
