"""RerunSink writes a real .rrd that reads back with the expected entities, values, blueprint and chunking."""

from __future__ import annotations

import numpy as np
import pytest
from rerun.chunk import RrdReader

from benchkit.rerun_inspect import chunk_check, read_layout
from groundstation.gap.pictures import EffectPicture, GapPictures
from groundstation.sinks.rerun_layout import OUTPUTS, UNITS
from groundstation.sinks.rerun_sink import INPUTS, RerunSink, RerunSinkError, _check_reachable
from groundstation.sinks.zenoh_sink import free_tcp_port

DT = 0.02


def _scalars(chunks, path):
    vals = []
    for c in chunks:
        if c.entity_path == path and not c.is_static:
            rb = c.to_record_batch()
            col = next(n for n in rb.schema.names if n.startswith("Scalars"))
            vals.append(np.concatenate([np.asarray(v, dtype=float) for v in rb.column(col).to_pylist()]))
    return np.concatenate(vals) if vals else np.zeros(0)


def _result(flight, t, y):
    """A worker result as the service hands it over: fit, gap report and the diagnosis pictures."""
    f_hz = np.linspace(0.0, 25.0, 101)
    psd = np.ones((101, 8))
    psd[48, :] = 30.0                                    # a line at 12 Hz
    pic = GapPictures(t_s=t, residual=0.1 * y, channels=("u", "q"), flagged_s=((t[10], t[60]),), f_hz=f_hz,
                      psd=psd, floor=np.ones((101, 8)), lines_hz=(12.0,),
                      effects=(EffectPicture("input_delay lon", True, t[::50], np.full((len(t[::50]), 8), 30.0),
                                             np.full((len(t[::50]), 8), 20.0), ("q",)),))
    gap = {"verdict": "input_delay", "method": {"alpha": 0.01},
           "gap": {"channels": {"u": {"match": 80.0}, "q": {"match": 70.0}}, "windows_s": [[t[10], t[60]]],
                   "significant": True, "gap_to_noise_ratio": {"u": 1.1, "q": 3.2}},
           "effects": [{"effect": "input_delay", "input": "lon", "estimate": {"delay_s": 0.11}, "score": 41.0,
                        "p_value": 1e-4, "shrink_pct": 58.0, "shrink_interval": [40.0, 70.0],
                        "evidence": "residual/input cross-correlation peak at +110 ms"}]}
    return {"flight": flight, "validation": {"channels": {c: {"match": 90.0 + k} for k, c in enumerate(OUTPUTS)}},
            "held_out": {"channels": {c: {"match": 80.0 + k} for k, c in enumerate(OUTPUTS)}},
            "gap": gap, "seconds": 12.0}, pic


def test_session_reads_back_with_units_flight_tabs_and_gap_pictures(tmp_path):
    path = tmp_path / "run.rrd"
    sink = RerunSink("heli", "save", str(path), raw=True, flush_rows=512)
    t = np.arange(3000) * DT                           # 60 s: flight 1 from 10 s to 50 s
    inputs = 0.2 * np.column_stack([np.sin(t + k) for k in range(4)])
    outputs = np.column_stack([np.cos(t + k) for k in range(8)])
    sink.log_flight_state("on ground", 0.0)
    for i in range(0, len(t), 25):                     # the service's per-window batches
        s = slice(i, i + 25)
        sink.log_rows(t[s], 1.7e9 + t[s], inputs[s], outputs[s], "raw")
        sink.log_rows(t[s], 1.7e9 + t[s], None, outputs[s], "smoothed")
        if i == 500:
            sink.log_flight_state("armed", t[i])
        if i == 2500:
            sink.log_flight_state("on ground", t[i])
            sink.flight_ended(1, 10.0, 50.0)
    m = (t >= 12.0) & (t <= 48.0)
    res, pic = _result(1, t[m], outputs[m])
    sink.log_result(res, {"t_fc_s": t[m], "model": 0.9 * outputs[m], "measured": outputs[m]}, pic)
    sink.close()

    chunks = RrdReader(path).stream().to_chunks()
    np.testing.assert_allclose(_scalars(chunks, "/heli/inputs/lat"), 100.0 * inputs[:, 0])      # % of travel
    np.testing.assert_allclose(_scalars(chunks, "/heli/outputs/q/smoothed"), outputs[:, 4])
    np.testing.assert_allclose(_scalars(chunks, "/heli/outputs/q/residual"), 0.1 * outputs[m, 4], atol=1e-12)
    lay = read_layout(path)
    for e in ("/heli/flight/state", "/heli/gap/flagged", "/heli/gap/residual/q/flagged", "/heli/flights/1/verdict",
              "/heli/flights/1/spectrum/q/psd", "/heli/flights/1/spectrum/q/lines", "/heli/flights/1/fit",
              "/heli/flights/1/effects/input_delay_lon/q/after", "/__properties/aircraft", "/__properties/flights"):
        assert e in lay.entities, e
    # the recording opens on flight 1, every plot of it on the flight's span
    tab = lay.opening_tab()
    assert lay.name(tab).startswith("flight 1")
    views = lay.views_under(tab)
    plots = [v for v in views if v.kind in ("TimeSeries", "StateTimeline")]
    assert plots and all(v.fc_range_s is not None and v.fc_range_s[0] <= 10.0 and v.fc_range_s[1] >= 50.0
                         and v.fc_range_s[1] - v.fc_range_s[0] < 45.0 for v in plots)
    for v in views:
        if v.kind in ("TimeSeries", "BarChart"):
            assert "[" in v.name and "]" in v.name, v.name          # a unit in every plot's title
    q = next(v for v in views if v.origin == "/heli/outputs/q")
    assert f"[{UNITS['q']}]" in q.name and "fit 94%" in q.name and "held-out 84%" in q.name
    assert any(v.origin == "/heli/gap/residual/q" for v in views)
    assert any(v.origin.endswith("/spectrum/q") and v.kind == "BarChart" for v in views)


def test_rows_are_sent_in_few_chunks(tmp_path):
    path = tmp_path / "batched.rrd"
    sink = RerunSink("heli", "save", str(path), flush_rows=4096)
    t = np.arange(18000) * DT                          # 6 minutes at 50 Hz in 720 small batches
    y = np.column_stack([np.sin(t + k) for k in range(8)])
    for i in range(0, len(t), 25):
        sink.log_rows(t[i:i + 25], 1.7e9 + t[i:i + 25], y[i:i + 25, :4], y[i:i + 25], "smoothed")
    sink.close()
    chunks = RrdReader(path).stream().to_chunks()
    per_entity = [c for c in chunks if c.entity_path == "/heli/outputs/u/smoothed" and not c.is_static]
    assert sum(c.num_rows for c in per_entity) == len(t)
    assert len(per_entity) <= int(np.ceil(len(t) / 4096))
    check = chunk_check(path)
    assert check.factor <= 10.0, check


def test_raw_outputs_only_on_request(tmp_path):
    path = tmp_path / "noraw.rrd"
    sink = RerunSink("heli", "save", str(path))
    t = np.arange(50) * DT
    sink.log_rows(t, 1.7e9 + t, np.zeros((50, 4)), np.zeros((50, 8)), "raw")
    sink.close()
    ents = {c.entity_path for c in RrdReader(path).stream().to_chunks() if not c.is_static}
    assert {f"/heli/inputs/{c}" for c in INPUTS} <= ents
    assert not any(e.endswith("/raw") for e in ents)


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


def test_frequency_verification_is_drawn_as_bode_per_scored_pair(tmp_path):
    from benchkit.synthetic import EXAMPLE_TRUTH
    from groundstation.freq.spectra import estimate_responses
    from groundstation.freq.verify import verify
    from groundstation.sysid.model import theta_from_dict
    from tests.freq.conftest import flight

    v = verify(theta_from_dict(EXAMPLE_TRUTH), estimate_responses(flight(60.0, seed=3)))
    assert v.pairs
    path = tmp_path / "bode.rrd"
    sink = RerunSink("heli", "save", str(path))
    sink.flight_ended(1, 0.0, 60.0)
    sink.log_result({"flight": 1, "freq": v})
    sink.close()
    lay = read_layout(path)
    for p in v.pairs:
        for k in ("magnitude/data", "magnitude/model", "phase/data", "phase/model", "coherence/data"):
            assert f"/heli/flights/1/bode/{p.input}_{p.output}/{k}" in lay.entities
    bode = [v for v in lay.views_under(lay.opening_tab()) if "/bode/" in v.origin]
    assert len(bode) == 3 * len(v.pairs) and all(v.kind == "BarChart" and "log10 f [Hz]" in v.name for v in bode)
    # the bars stand at log10(f / Hz): the log-spaced composite frequencies evenly spread, as on a Bode axis
    p0 = v.pairs[0]
    entity = f"/heli/flights/1/bode/{p0.input}_{p0.output}/magnitude/data"
    rb = next(c.to_record_batch() for c in RrdReader(path).stream().to_chunks() if c.entity_path == entity)
    x = np.asarray(rb.column("BarChart:abscissa").to_pylist()[-1][0]["buffer"])
    assert x == pytest.approx(np.log10(v.responses.f_hz))


def test_fit_table_shows_the_cross_flight_check():
    from groundstation.sinks.rerun_text import fit_table, fit_text

    res = {"flight": 2, "validation": {"channels": {"q": {"match": 95.0}}},
           "cross_flight": {"model_flight": 1, "channels": {"q": {"match": 71.5}}}}
    table = fit_table(2, res)
    assert "flight 1's model %" in table and "71.5" in table and "95.0" in table
    assert fit_text(res)["q"] == "fit 95% · held-out 72%"


def test_cross_flight_from_the_models_fit_as_the_worker_writes_it():
    from groundstation.sinks.rerun_text import fit_table, fit_text

    res = {"flight": 3, "validation": {"channels": {"p": {"match": 93.0}}},
           "model": {"fit": {"cross_flight": {"previous_flight": 2,
                                              "previous_model_on_new_flight": {"mean_match": 80.0,
                                                                               "match": {"p": 80.4}}}}}}
    assert "flight 2's model %" in fit_table(3, res) and "80.4" in fit_table(3, res)
    assert fit_text(res)["p"] == "fit 93% · held-out 80%"


def test_flight_armed_before_the_fc_clock_still_gets_a_view_and_the_file_its_blueprint(tmp_path):
    """A flight whose arming came before any FC time (start NaN) once made close() fail converting
    NaN and the saved file had no blueprint at all."""
    path = tmp_path / "nan_start.rrd"
    sink = RerunSink("heli", "save", str(path))
    t = 10.0 + np.arange(500) * DT
    sink.log_rows(t, 1.7e9 + t, np.zeros((500, 4)), np.zeros((500, 8)), "smoothed")
    sink.flight_ended(1, float("nan"), float(t[-1]))
    sink.close()
    lay = read_layout(path)
    ranges = [v.fc_range_s for v in lay.views.values() if v.fc_range_s is not None]
    assert ranges, "no view opens on the flight"
    assert all(np.isfinite(r).all() for r in ranges)
    assert min(r[0] for r in ranges) <= t[0] + 1e-6 and max(r[1] for r in ranges) >= t[-1] - 1e-6


def test_excitation_panel_reads_back(tmp_path):
    """The live excitation monitor's verdicts: coherence vs log10 f per axis on fc_time (building up), the
    share of each band covered, the status line, and an ``excitation`` tab in the saved blueprint."""
    from groundstation.dsp.excitation import ExcitationConfig, ExcitationMonitor

    path = tmp_path / "exc.rrd"
    sink = RerunSink("heli", "save", str(path))
    mon = ExcitationMonitor(ExcitationConfig(), DT)
    mon.flight_started(1, 0.0)
    rng = np.random.default_rng(0)
    t = np.arange(0, 80.0, DT)
    u = 0.05 * rng.standard_normal((t.size, 4))
    y = 0.01 * rng.standard_normal((t.size, 8))
    y[:, 4] += 3.0 * u[:, 0]                           # q follows lat: lat becomes enough, the others never
    reports = []
    for a in range(0, t.size, 50):
        rep = mon.rows(t[a:a + 50], u[a:a + 50], y[a:a + 50], armed=True, in_air=True)
        if rep is not None:
            reports.append(rep)
            sink.log_excitation(rep)
    sink.close()
    assert reports[-1].axes["lat"].enough and not reports[-1].axes["lon"].enough
    chunks = RrdReader(path).stream().to_chunks()
    covered = _scalars(chunks, "/heli/excitation/covered/lat")
    assert len(covered) == len(reports) and covered[-1] == 100.0 and covered[0] < 100.0
    assert _scalars(chunks, "/heli/excitation/covered/lon")[-1] < 100.0
    lay = read_layout(path)
    for a in INPUTS:
        assert f"/heli/excitation/{a}/coherence" in lay.entities
    assert "/heli/excitation/summary" in lay.entities
    tabs = [lay.name(c) for c in lay.children(lay.root)]
    exc = next(c for c in lay.children(lay.root) if lay.name(c) == "excitation")
    kinds = {v.origin: v.kind for v in lay.views_under(exc)}
    assert kinds["/heli/excitation/lat/coherence"] == "BarChart" and kinds["/heli/excitation/covered"] == "TimeSeries"
    assert tabs[-1] == "excitation"
