"""Between flights the worker scores the new model on the previous flight and the previous flight's
model on the new one (published inside the model payload as ``fit.cross_flight``)."""

from __future__ import annotations

import json

import numpy as np

from benchkit.synthetic import EXAMPLE_TRUTH
from groundstation.dsp.prepare import prepare
from groundstation.sysid.model import HoverModel
from groundstation.worker import IdentifyJob, _cross_flight
from tests.realdata import real_log


def test_cross_flight_scores_both_ways(tmp_path):
    from firmware_interface.readers import load_log

    tlog = str(real_log("trex550/flight1.tlog"))
    prepared = prepare([load_log(tlog)])
    prev_model = HoverModel(params=dict(EXAMPLE_TRUTH, N_r=2.0))  # a yaw that diverges: scores badly
    (tmp_path / "model-flight01.json").write_text(json.dumps(prev_model.to_json()))
    new_model = HoverModel(params=dict(EXAMPLE_TRUTH))
    job = IdentifyJob(flight=2, tlogs=(tlog,), out_dir=str(tmp_path), previous_flight=1, previous_tlogs=(tlog,))
    out = _cross_flight(job, new_model, prepared)
    assert out["previous_flight"] == 1 and "error" not in out
    new_on_prev = out["new_model_on_previous_flight"]
    prev_on_new = out["previous_model_on_new_flight"]
    assert set(new_on_prev["match"]) == set(prev_on_new["match"]) >= {"p", "q", "r", "theta", "phi"}
    assert np.isfinite(new_on_prev["mean_match"]) and np.isfinite(prev_on_new["mean_match"])
    assert prev_on_new["match"]["r"] < new_on_prev["match"]["r"]  # the diverging yaw is seen
    assert _cross_flight(IdentifyJob(flight=1, tlogs=(tlog,), out_dir=str(tmp_path)), new_model, prepared) == {}


def test_the_service_logs_the_cross_flight_check():
    from groundstation.service import cross_flight_line

    line = cross_flight_line(3, {"previous_flight": 2, "new_model_on_previous_flight": {"mean_match": 31.24, "match": {}},
                                 "previous_model_on_new_flight": {"mean_match": -12.0, "match": {}}})
    assert line == ("flight 3: same aircraft as flight 2? held-out match: this model on flight 2 31.2 %; "
                    "flight 2's model on this flight -12.0 %")
    assert "bad log" in cross_flight_line(3, {"previous_flight": 2, "error": "ValueError: bad log"})
    assert cross_flight_line(1, {}) == ""
