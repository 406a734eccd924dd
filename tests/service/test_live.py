"""The live signal path (groundstation.dsp.live): causal filter vs batch, grid, body frame, flights."""

from __future__ import annotations

import json
import math

import numpy as np
import pytest

from firmware_interface.samples import Attitude, ExtendedSysState, Heartbeat, LocalPositionNed, ServoOutputRaw
from groundstation.dsp.live import (
    CausalSmoother,
    FlightEnded,
    FlightStarted,
    FlightTracker,
    GridAligner,
    LiveConfig,
    LivePipeline,
    ned_to_body,
)
from groundstation.dsp.smoothing import smooth5
from groundstation.sinks.zenoh_sink import dumps_numeric


@pytest.mark.parametrize("passes", [1, 2, 3])
@pytest.mark.parametrize("n", [5, 6, 17, 200])
def test_causal_equals_batch_including_ends(passes, n):
    rng = np.random.default_rng(n + passes)
    y = rng.normal(size=(n, 3)).cumsum(axis=0)
    sm = CausalSmoother(3, passes)
    rows = [sm.push(r) for r in y]
    rows.append(sm.flush())
    out = np.vstack(rows)
    np.testing.assert_allclose(out, smooth5(y, passes), rtol=1e-12, atol=1e-12)


def test_causal_latency_is_two_samples_per_pass():
    rng = np.random.default_rng(1)
    y = rng.normal(size=(50, 2))
    sm = CausalSmoother(2, 1)
    batch = smooth5(y, 1)
    emitted = 0
    for i, r in enumerate(y):
        got = sm.push(r)
        emitted += len(got)
        if i >= 4:
            # after sample i, every output up to i-2 is final and equals the batch value
            assert emitted == i - 1
            np.testing.assert_allclose(got[-1], batch[i - 2], atol=1e-12)
    assert sm.latency_samples == 2


def test_fewer_than_five_samples_pass_through_unchanged():
    sm = CausalSmoother(1, 1)
    for v in (1.0, 2.0, 7.0):
        assert sm.push(np.array([v])).shape == (0, 1)
    np.testing.assert_array_equal(sm.flush()[:, 0], [1.0, 2.0, 7.0])


def test_ned_to_body_known_rotations():
    v = np.array([1.0, 0.0, 0.0])
    # facing east (yaw 90 deg): north motion is to the left, i.e. -v
    np.testing.assert_allclose(ned_to_body(v, 0.0, 0.0, math.pi / 2), [0.0, -1.0, 0.0], atol=1e-12)
    # nose up 90 deg: sinking (down) is motion out of the tail, -u
    np.testing.assert_allclose(ned_to_body(np.array([0.0, 0.0, 1.0]), 0.0, math.pi / 2, 0.0),
                               [-1.0, 0.0, 0.0], atol=1e-12)
    rng = np.random.default_rng(0)
    vv = rng.normal(size=(20, 3))
    ang = rng.uniform(-1, 1, size=(3, 20))
    vb = ned_to_body(vv, *ang)
    np.testing.assert_allclose(np.linalg.norm(vb, axis=1), np.linalg.norm(vv, axis=1), rtol=1e-12)


def test_grid_releases_a_row_when_the_last_holding_stream_arrives():
    al = GridAligner(50.0, {"a": (1, True), "b": (1, True), "c": (1, False)}, stale_s=0.1)
    for k in range(6):    # warm-up: 0.1 s of FC time with all streams
        al.add("a", k * 0.02, (k,), 10.0 + k)
        al.add("b", k * 0.02 + 0.005, (k,), 10.0 + k)
        al.add("c", k * 0.02, (5.0,), 10.0 + k)
    t, v, h, _ = al.pop()
    np.testing.assert_allclose(t, np.arange(6) * 0.02)
    assert math.isnan(v[0, 1])      # tick 0.0 is before b's first sample
    al.add("a", 0.12, (6.0,), 20.0)
    t, v, h, _ = al.pop()
    assert len(t) == 0              # b has nothing at/after 0.12 yet: the row waits
    al.add("b", 0.125, (6.0,), 21.0)
    t, v, h, _ = al.pop()
    np.testing.assert_allclose(t, [0.12])
    np.testing.assert_allclose(v[0], [6.0, 5.0 + 0.75, 5.0])   # b interpolated between 0.105 and 0.125
    assert h[0] == 21.0             # the packet that completed the row


def test_grid_stale_stream_stops_holding_and_gap_restarts():
    al = GridAligner(50.0, {"a": (1, True), "b": (1, True)}, stale_s=0.1, max_gap_s=1.0)
    for k in range(10):
        al.add("a", k * 0.02, (k,))
        al.add("b", k * 0.02, (k,))
    t, v, _, _ = al.pop()
    assert len(t) == 10
    for k in range(10, 30):   # b goes silent
        al.add("a", k * 0.02, (k,))
    t, v, _, _ = al.pop()
    assert t[-1] == pytest.approx(29 * 0.02)
    assert np.isnan(v[-1, 1]) and v[-1, 0] == 29
    al.add("a", 10.0, (1.0,))   # 9.4 s outage
    t, v, _, restarted = al.pop()
    assert restarted and len(t) == 1 and t[0] == pytest.approx(10.0)


def test_flight_tracker_transitions_and_in_air():
    ft = FlightTracker(in_air_alt_m=0.3)
    assert ft.on_heartbeat(False, 1.0) is None
    ft.on_altitude(100.0)
    assert isinstance(ft.on_heartbeat(True, 2.0), FlightStarted)
    assert not ft.in_air
    ft.on_altitude(101.0)
    assert ft.in_air and ft.height_m == pytest.approx(1.0)
    ft.landed_state = 1
    assert not ft.in_air          # landed_state wins over height
    end = ft.on_heartbeat(False, 12.0)
    assert isinstance(end, FlightEnded) and end.flight == 1 and end.duration_s == pytest.approx(10.0)
    assert isinstance(ft.on_heartbeat(True, 20.0), FlightStarted) and ft.flight == 2


def test_flight_armed_before_any_fc_time_starts_at_the_first_known_time():
    ft = FlightTracker()
    assert ft.on_heartbeat(True, math.nan) is None      # armed, FC time not known yet: no NaN start
    assert ft.armed and ft.flight == 1 and ft.start_pending
    started = ft.on_time(5.25)
    assert started == FlightStarted(1, 5.25) and not ft.start_pending
    assert ft.on_time(6.0) is None                      # only once
    end = ft.on_heartbeat(False, 9.25)
    assert end == FlightEnded(1, 9.25, 4.0)
    # a flight that ends before any FC time is known: time and duration NaN, never invented
    assert ft.on_heartbeat(True, math.nan) is None
    end = ft.on_heartbeat(False, math.nan)
    assert isinstance(end, FlightEnded) and end.flight == 2 and math.isnan(end.duration_s)


def test_pipeline_armed_heartbeat_before_timed_messages_gives_a_finite_start():
    lp = LivePipeline(LiveConfig(window_s=1.0, hop_s=0.2))
    first = lp.feed([Heartbeat(10.0, math.nan, 1, 1, 4, 3, 129, 0, 4, True)])
    assert first.flight_events == []                    # before: FlightStarted(1, nan)
    out = lp.feed(_events(60, t0=3.0)[2:])              # time-stamped rows from FC 3.0 s, no heartbeat
    starts = [e for e in out.flight_events if isinstance(e, FlightStarted)]
    assert starts == [FlightStarted(1, 3.0)]
    assert all(math.isfinite(e.t_fc_s) for e in out.flight_events)


def _events(n: int, t0: float = 0.0, armed: bool = True):
    evs = []
    for k in range(n):
        t = t0 + k * 0.02
        th = 10.0 + t
        if k % 50 == 0:
            evs.append(Heartbeat(th, t, 1, 1, 4, 3, 129 if armed else 1, 0, 4, armed))
            evs.append(ExtendedSysState(th, t, 1, 1, 0, 2 if armed else 1))
        evs.append(Attitude(th, t, 1, 1, 0.0, 0.0, 0.0, math.sin(t), 0.1, 0.0))
        evs.append(ServoOutputRaw(th, t, 1, 1, 0, (1500, 1600, 1400, 1500) + (0,) * 12))
        evs.append(LocalPositionNed(th, t, 1, 1, 0.0, 0.0, -2.0, 1.0, 0.5, 0.0))
    return evs


def test_pipeline_rows_windows_and_smoothing_against_batch():
    cfg = LiveConfig(window_s=1.0, hop_s=0.2)
    lp = LivePipeline(cfg)
    out = lp.feed(_events(200))
    assert [type(e) for e in out.flight_events] == [FlightStarted]
    assert len(out.t_fc_s) == 200
    np.testing.assert_allclose(out.inputs[5], [0.0, 0.2, -0.2, 0.0])
    np.testing.assert_allclose(out.outputs_raw[5, :3], [1.0, 0.5, 0.0], atol=1e-12)   # level, facing north
    # smoothed rows lag by two samples and equal the batch filter on interior samples
    assert len(out.t_smoothed_s) == 198
    batch = smooth5(out.outputs_raw, 1)
    np.testing.assert_allclose(out.outputs_smoothed[2:], batch[2:198], atol=1e-12)
    # a window every 10 rows, 50 rows long, newest two smoothed rows not final yet
    assert len(out.windows) == 20
    w = out.windows[-1]
    assert w.t_fc_s.shape == (50,) and w.t_fc_s[-1] == pytest.approx(199 * 0.02)
    assert np.isnan(w.outputs_smoothed[-2:]).all() and np.isfinite(w.outputs_smoothed[:-2]).all()
    assert w.flight == 1 and w.in_air
    js = json.loads(dumps_numeric(w.to_json("heli")))          # strict JSON: NaN -> null
    assert js["outputs"]["p"]["smoothed"][-1] is None and len(js["inputs"]["lon"]) == 50
    assert js["outputs"]["p"]["raw"][-1] == pytest.approx(w.outputs_raw[-1, 3], abs=1e-6)


def test_pipeline_fed_one_event_at_a_time_matches_batch_feed():
    evs = _events(120)
    a = LivePipeline().feed(evs)
    lp = LivePipeline()
    outs = [lp.feed([e]) for e in evs]
    np.testing.assert_allclose(np.vstack([o.outputs_raw for o in outs]), a.outputs_raw)
    np.testing.assert_allclose(np.vstack([o.outputs_smoothed for o in outs]), a.outputs_smoothed)


def test_grid_marks_rows_that_only_bridge_a_hole_of_the_link():
    """A row between two samples further apart than ordinary sampling (max(0.1 s, 2.5 intervals)) is a
    straight line, not a measurement; one lost packet of a 25 Hz stream is still ordinary sampling."""
    al = GridAligner(50.0, {"a": (1, True)}, stale_s=0.1)
    times = [k * 0.04 for k in range(40) if k not in (10, *range(20, 27))]   # one packet lost, then seven
    for t in times:
        al.add("a", t, (t,))
    t, v, _, _ = al.pop()
    m = al.measured[:, 0]
    assert m.shape == t.shape and np.isfinite(v[:, 0]).all()
    hole = (t > 19 * 0.04 + 1e-9) & (t < 27 * 0.04 - 1e-9)
    assert not m[hole].any() and m[~hole].all()
