"""Between flights the worker scores the new model on the previous flight and the previous flight's
model on the new one (published inside the model payload as ``fit.cross_flight``)."""

from __future__ import annotations

import json

import numpy as np

from groundstation.dsp.prepare import prepare
from groundstation.sysid.model import HoverModel
from groundstation.sysid.synthetic import EXAMPLE_TRUTH
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
