"""Result JSON never holds NaN; the simulator's bursty link loses what it is asked to, in runs."""

from __future__ import annotations

import json
import math

import numpy as np
import pytest

from groundstation.jsonio import dumps, finite, write_atomic


def test_finite_turns_nan_and_inf_into_null(tmp_path):
    doc = {"a": float("nan"), "b": [1.0, float("inf"), np.float64("-inf")], "c": np.array([1.5, np.nan]),
           "d": {"e": np.int64(3), "f": np.bool_(True)}, "g": (2, "x")}
    out = finite(doc)
    assert out == {"a": None, "b": [1.0, None, None], "c": [1.5, None], "d": {"e": 3, "f": True}, "g": [2, "x"]}
    assert json.loads(dumps(doc))["c"] == [1.5, None]
    write_atomic(tmp_path / "sub" / "r.json", {"x": math.nan})
    assert json.loads((tmp_path / "sub" / "r.json").read_text()) == {"x": None}
    assert not list((tmp_path / "sub").glob("*.tmp"))


@pytest.mark.parametrize("burst", [1.0, 8.0])
def test_simulated_link_loss_rate_and_bursts(tmp_path, burst):
    from firmware_interface.readers import load_log
    from hil_replay.sim import write_tlog

    path = tmp_path / "f.tlog"
    truth = write_tlog(path, seed=2, flight_duration_s=30.0, packet_loss=0.1, loss_burst=burst)
    lost, total = truth["packets_lost"], truth["packets_lost"] + truth["packets_written"]
    assert 0.06 < lost / total < 0.14
    log = load_log(path)
    att = log.series["ATTITUDE"].t_fc_s
    gaps = np.diff(att)[np.diff(att) > 0.03]  # 50 Hz stream: a gap is at least one lost packet
    if burst > 1:  # fades take out several frames of every type: gaps of 0.06 s and more dominate
        assert np.median(gaps) >= 0.059
    else:
        assert np.median(gaps) < 0.05


def test_loss_burst_below_one_is_refused(tmp_path):
    from hil_replay.sim import write_tlog

    with pytest.raises(ValueError, match="loss_burst"):
        write_tlog(tmp_path / "f.tlog", flight_duration_s=30.0, loss_burst=0.5)


def test_log_info_reports_the_links_outages(tmp_path):
    from firmware_interface.readers import load_log
    from groundstation.commands.log_info import summarise
    from hil_replay.sim import write_tlog

    path = tmp_path / "f.tlog"
    write_tlog(path, seed=4, flight_duration_s=30.0, packet_loss=0.1, loss_burst=8.0,
               rates_hz={"ATTITUDE": 25, "SERVO_OUTPUT_RAW": 25, "LOCAL_POSITION_NED": 25})
    lk = summarise(load_log(path))["link"]
    assert 6.0 < lk["loss_pct"] < 15.0 and lk["outages"] > 10
    assert lk["lost_per_outage"] > 3.0 and lk["longest_outage_s"] >= lk["median_outage_s"] > 0.05
    assert 0 <= lk["outages_split"] <= lk["outages"] and 0.1 < lk["bridge_limit_s"] <= 1.0
    assert lk["bridge_rule"] == "derived" and "rotor" in lk["bridge_why"]
