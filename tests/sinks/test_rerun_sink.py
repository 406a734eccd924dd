"""RerunSink writes a real .rrd that reads back with the expected entities, timelines and values."""

from __future__ import annotations

import numpy as np
import pytest
from rerun.chunk import RrdReader

from groundstation.sinks.rerun_sink import INPUTS, OUTPUTS, RerunSink, RerunSinkError, _check_reachable
from groundstation.sinks.zenoh_sink import free_tcp_port


def _chunks(path):
    r = RrdReader(path)
    return r, r.stream().to_chunks()


def test_rrd_has_entities_timelines_and_blueprint(tmp_path):
    path = tmp_path / "run.rrd"
    sink = RerunSink("heli", "save", str(path))
    t = np.arange(100) * 0.02
    inputs = np.column_stack([np.sin(t + k) for k in range(4)])
    outputs = np.column_stack([np.cos(t + k) for k in range(8)])
    sink.log_rows(t, 1.7e9 + t, inputs, outputs, kind="raw")
    sink.log_rows(t[:98], 1.7e9 + t[:98], None, outputs[:98], kind="smoothed")
    sink.log_model_overlay(t, outputs * 0.9)
    sink.log_gap(1, {"u": 91.0, "q": 80.5}, "input_delay", "lon delayed 0.1 s", t_fc_s=2.0)
    sink.log_event("flight 1 ended", 2.0)
    sink.close()

    reader, chunks = _chunks(path)
    assert len(reader.blueprints()) == 1
    by_entity: dict[str, int] = {}
    for c in chunks:
        if not c.is_static:
            by_entity[c.entity_path] = by_entity.get(c.entity_path, 0) + c.num_rows
    for c in INPUTS:
        assert by_entity[f"/heli/inputs/{c}"] == 100
    for c in OUTPUTS:
        assert by_entity[f"/heli/outputs/{c}/raw"] == 100
        assert by_entity[f"/heli/outputs/{c}/smoothed"] == 98
        assert by_entity[f"/heli/outputs/{c}/model"] == 100
    assert {"/heli/gap/match/u", "/heli/gap/match/q", "/heli/gap/verdict", "/heli/status"} <= set(by_entity)
    lat = next(c for c in chunks if c.entity_path == "/heli/inputs/lat" and not c.is_static)
    assert {"fc_time", "host_time"} <= set(lat.timeline_names)
    rb = lat.to_record_batch()
    col = next(n for n in rb.schema.names if n.startswith("Scalars"))
    vals = np.concatenate([np.asarray(v, dtype=float) for v in rb.column(col).to_pylist()])
    np.testing.assert_allclose(vals, inputs[:, 0])


def test_unwritable_rrd_and_unreachable_viewer_are_one_line(tmp_path):
    blocker = tmp_path / "file"
    blocker.write_text("x")
    with pytest.raises(RerunSinkError) as exc:
        RerunSink("heli", "save", str(blocker / "sub" / "x.rrd"))
    assert "x.rrd" in str(exc.value) and "\n" not in str(exc.value)
    url = f"rerun+http://127.0.0.1:{free_tcp_port()}/proxy"
    with pytest.raises(RerunSinkError, match="not reachable"):
        _check_reachable(url)
    with pytest.raises(RerunSinkError, match="not reachable"):
        RerunSink("heli", "connect", url)
