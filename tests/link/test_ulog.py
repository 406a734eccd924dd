"""PX4 ULog import on the real pyulog sample log, and on variants of it written back by pyulog itself
(an armed flight with a land detector, a topic removed): nothing here writes ULog bytes by hand."""

from __future__ import annotations

import json
import struct

import numpy as np
import pytest
from pyulog import ULog

from firmware_interface.errors import LogError
from firmware_interface.readers import load_log
from groundstation.cli import main as cli_main
from tests.realdata import real_log


@pytest.fixture(scope="module")
def sample():
    return real_log("px4/pyulog_sample.ulg")


def test_log_info_agrees_with_pyulog_counts_and_finds_the_flight(sample, capsys):
    assert cli_main(["log-info", str(sample), "--json"]) == 0
    info = json.loads(capsys.readouterr().out)
    ref = ULog(str(sample))
    want = {d.name if d.multi_id == 0 else f"{d.name}/{d.multi_id}": len(d.data["timestamp"]) for d in ref.data_list}
    got = {k: v["count"] for k, v in info["messages"].items()}
    assert got == want
    # a bench log (never armed): one flight over the whole log, and a note says so
    assert len(info["flights"]) == 1
    f = info["flights"][0]
    span_s = (ref.last_timestamp - ref.start_timestamp) * 1e-6
    assert f["duration_s"] == pytest.approx(span_s, abs=0.5)
    assert any("never shows the vehicle armed" in n and str(sample) in n for n in info["notes"])


def test_series_map_onto_mavlink_names_in_si_units(sample):
    log = load_log(sample)
    ref = ULog(str(sample))
    va = ref.get_dataset("vehicle_attitude").data
    att = log.series["ATTITUDE"]
    assert len(att) == len(va["timestamp"])
    assert att.t_fc_s[0] == pytest.approx(va["timestamp"][0] * 1e-6)
    # roll from the quaternion: rotating body z by (roll, pitch) gives the quaternion's own z axis
    w, x, y, z = (va[f"q[{k}]"] for k in range(4))
    zb_y = 2 * (y * z + w * x)
    zb_z = 1 - 2 * (x * x + y * y)
    assert np.tan(att["roll_rad"]) == pytest.approx(zb_y / zb_z, rel=1e-5, abs=1e-6)
    assert att["p_rad_s"] == pytest.approx(va["rollspeed"])  # this PX4 version kept the rates there
    assert len(log.series["SERVO_OUTPUT_RAW"]) == len(ref.get_dataset("actuator_outputs").data["timestamp"])
    lp = ref.get_dataset("vehicle_local_position").data
    assert log.series["LOCAL_POSITION_NED"]["vz_m_s"] == pytest.approx(lp["vz"])
    sc = ref.get_dataset("sensor_combined").data
    assert log.series["IMU"]["gz_rad_s"] == pytest.approx(sc["gyro_rad[2]"])


def _variant(sample, tmp_path, name, edit):
    ulog = ULog(str(sample))
    edit(ulog)
    out = tmp_path / name
    ulog.write_ulog(str(out))
    return out


def test_armed_interval_of_vehicle_status_is_the_flight(sample, tmp_path):
    def edit(ulog):
        vs = ulog.get_dataset("vehicle_status").data
        t = vs["timestamp"] * 1e-6
        vs["arming_state"][:] = np.where((t > 120.0) & (t < 170.0), 2, 1)

    path = _variant(sample, tmp_path, "armed.ulg", edit)
    log = load_log(path)
    assert len(log.flights) == 1 and not any("never shows the vehicle armed" in n for n in log.notes)
    f = log.flights[0]
    assert f.start_fc_s == pytest.approx(120.0, abs=0.3) and f.end_fc_s == pytest.approx(170.0, abs=0.3)


def test_ulog_without_vehicle_attitude_is_one_line_naming_file_and_topic(sample, tmp_path, capsys):
    def edit(ulog):
        ulog._data_list = [d for d in ulog.data_list if d.name != "vehicle_attitude"]

    path = _variant(sample, tmp_path, "noatt.ulg", edit)
    with pytest.raises(LogError, match="noatt.ulg.*vehicle_attitude"):
        load_log(path)
    assert cli_main(["log-info", str(path)]) != 0
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and "noatt.ulg" in err[0] and "vehicle_attitude" in err[0]


def test_ulog_without_servo_outputs_names_the_topic(sample, tmp_path):
    def edit(ulog):
        ulog._data_list = [d for d in ulog.data_list if d.name != "actuator_outputs"]

    path = _variant(sample, tmp_path, "noout.ulg", edit)
    log = load_log(path)
    assert not log.has("SERVO_OUTPUT_RAW")
    assert any("noout.ulg" in n and "actuator_outputs" in n for n in log.notes)


def _one_line_or_ok(code, err, log):
    if code != 0:
        assert len(err.strip().splitlines()) == 1 and str(log) in err, err


@pytest.mark.slow
def test_every_command_reads_the_ulog_and_px4log(sample, tmp_path, capsys):
    """Each command runs on the ULog and the .px4log; where the log cannot support the command (a
    bench ULog, a ground run: never in the air) it says why in one line naming the file."""
    from benchkit.synthetic import EXAMPLE_TRUTH
    from groundstation.sysid.model import HoverModel

    px4log = real_log("px4/trex550_groundrun.px4log")
    model = tmp_path / "m.json"  # a model to validate and diagnose with (neither log is a flight to identify)
    model.write_text(json.dumps(HoverModel(params=dict(EXAMPLE_TRUTH)).to_json()))
    for log in (sample, px4log):
        assert cli_main(["log-info", str(log), "--json"]) == 0
        assert json.loads(capsys.readouterr().out)["flights"]
        code = cli_main(["identify", str(log), "--out", str(tmp_path / "m2.json"), "--maxiter", "2", "--no-plot",
                         "--quiet"])
        _one_line_or_ok(code, capsys.readouterr().err, log)
        code = cli_main(["validate", str(model), str(log), "--json"])
        out = capsys.readouterr()
        _one_line_or_ok(code, out.err, log)
        if code == 0:
            assert json.loads(out.out)
        code = cli_main(["diagnose", str(log), "--model", str(model), "--out", str(tmp_path / "gap.json"),
                         "--quiet"])
        _one_line_or_ok(code, capsys.readouterr().err, log)


def _add_gps_topic(ulog, outage_s):
    """A ``vehicle_gps_position`` topic (PX4 < 1.14 fields) at 5 Hz over the log, silent in
    ``outage_s``, built with pyulog's own format, subscription and data classes."""
    fmt = b"vehicle_gps_position:uint64_t timestamp;int32_t lat;int32_t lon;int32_t alt;float vel_m_s;" \
          b"uint8_t fix_type;uint8_t satellites_used;"
    ulog._message_formats["vehicle_gps_position"] = ULog.MessageFormat(fmt, None)
    msg_id = max(d.msg_id for d in ulog.data_list) + 1
    sub = ULog._MessageAddLogged(struct.pack("<BH", 0, msg_id) + b"vehicle_gps_position", None,
                                 ulog._message_formats)
    t_us = np.arange(ulog.start_timestamp, ulog.last_timestamp, 200_000, dtype=np.uint64)
    t_s = t_us * 1e-6
    t_us = t_us[(t_s < outage_s[0]) | (t_s > outage_s[1])]
    rec = np.zeros(len(t_us), dtype=sub.dtype)
    rec["timestamp"] = t_us
    rec["lat"], rec["lon"], rec["alt"] = 473977420, 85455940, 488_000
    rec["vel_m_s"], rec["fix_type"], rec["satellites_used"] = 1.5, 3, 11
    sub.buffer = bytearray(rec.tobytes())
    ulog._data_list.append(ULog.Data(sub))


def test_gps_and_logger_dropouts_in_log_info(sample, tmp_path, capsys):
    path = _variant(sample, tmp_path, "gps.ulg", lambda u: _add_gps_topic(u, (150.0, 160.0)))
    log = load_log(path)
    gps = log.series["GPS_RAW_INT"]
    assert gps["lat_deg"][0] == pytest.approx(47.397742) and gps["alt_m"][0] == pytest.approx(488.0)
    assert gps["satellites"][0] == 11 and gps["fix_type"][0] == 3
    assert cli_main(["log-info", str(path), "--json"]) == 0
    info = json.loads(capsys.readouterr().out)
    outage = [g for g in info["gaps"] if g["message"] == "GPS_RAW_INT"]
    assert len(outage) == 1 and outage[0]["start_s"] == pytest.approx(150.0, abs=0.25)
    assert outage[0]["duration_s"] == pytest.approx(10.0, abs=0.5)
    # the sample's own logger dropouts (pyulog's records), and one note that sums them
    ref = ULog(str(sample))
    want = [x for d in ref.dropouts if d.duration > 0 for x in (d.timestamp * 1e-6, d.duration * 1e-3)]
    assert want and [x for d in info["dropouts"] for x in (d["start_s"], d["duration_s"])] == pytest.approx(want)
    notes = [n for n in info["notes"] if "logger lost data" in n]
    assert len(notes) == 1 and f"{len(want) // 2} times" in notes[0] and str(path) in notes[0]


def test_ulog_missing_topic_is_one_line_in_log_info(sample, tmp_path, capsys):
    def edit(ulog):
        ulog._data_list = [d for d in ulog.data_list if d.name != "vehicle_local_position"]

    path = _variant(sample, tmp_path, "nolpos.ulg", edit)
    assert cli_main(["log-info", str(path)]) == 0
    out = capsys.readouterr().out.splitlines()
    lines = [ln for ln in out if "vehicle_local_position" in ln]
    assert len(lines) == 1 and str(path) in lines[0]


def test_default_read_decodes_only_the_mapped_topics(sample):
    from firmware_interface.ulog import ULOG_TOPICS

    fast, full = load_log(sample), load_log(sample, all_topics=True)
    assert set(fast.message_counts) <= set(ULOG_TOPICS) < set(ULOG_TOPICS) | set(full.message_counts)
    assert set(full.message_counts) - set(fast.message_counts)
    assert fast.series.keys() == full.series.keys()
    for name, s in fast.series.items():
        assert np.array_equal(s.t_fc_s, full.series[name].t_fc_s)
    assert fast.flights == full.flights
    # pyulog dates a dropout by the last record it decoded before it: the same within a few ms
    assert np.array(fast.dropouts_s) == pytest.approx(np.array(full.dropouts_s), abs=5e-3)
