"""prepare(): segments, trims, velocities, availability and bad input."""

from __future__ import annotations

import dataclasses

import numpy as np
import pytest

from firmware_interface.flights import find_flights
from firmware_interface.samples import Series
from groundstation.dsp.prepare import PrepConfig, prepare, prepared_from_arrays
from groundstation.dsp.split import by_flight, kfold

from .conftest import make_log


def test_prepare_grid_trims_and_body_velocity():
    # the synthetic log's constant velocity does not follow its attitude: the kinematic check is off here
    p = prepare([make_log(60.0, yaw_rad=np.pi / 2, vel_ned=(1.0, 0.0, 0.0))],
                PrepConfig(smooth_passes=0, velocity_check=False))
    assert p.dt_s == pytest.approx(0.02)
    assert len(p.segments) == 1
    s = p.segments[0]
    assert np.allclose(np.diff(s.t_s), 0.02)
    # in the air 3..57 s (landed_state), 1 s trimmed at both ends
    assert s.t_s[0] == pytest.approx(4.0) and s.t_s[-1] == pytest.approx(56.0, abs=0.02)
    assert s.available.all()
    # flying north with the nose east -> v = -1 m/s in body axes, trimmed by the in-air median
    assert p.output_trim["v"] == pytest.approx(-1.0, abs=0.05)
    assert p.output_trim["p"] == 0.0 and p.output_trim["q"] == 0.0
    assert p.input_trim_pwm["col"] == pytest.approx(1560.0, abs=3.0)
    assert np.abs(np.nanmedian(s.inputs, axis=0)).max() < 0.01
    assert s.inputs.shape == (s.n, 4) and s.outputs.shape == (s.n, 8)
    assert np.isfinite(s.alt_m).all() and s.alt_m.max() == pytest.approx(5.0, abs=0.1)


def test_ground_contact_before_the_land_detector_is_trimmed_by_height():
    """Touchdown at 52 s, the land detector says landed only at 57 s: the segment ends at the last
    sample off the ground minus the edge trim; take-off (already on time) is unchanged; with the
    trim turned off the segment runs to the land detector."""
    def z_of_t(t):
        climb = np.clip((t - 2.0) * 2.0, 0.0, 5.0)
        descent = np.clip((52.0 - t) * 2.5, 0.0, 5.0)
        return -np.minimum(climb, descent) + 0.01 * np.sin(7 * t)  # 1 cm of sensor wobble

    log = make_log(60.0, z_of_t=z_of_t)
    s = prepare([log]).segments[0]
    assert s.t_s[0] == pytest.approx(4.0, abs=0.02)
    off_ground = 52.0 - 0.1 / 2.5  # last moment 0.1 m up
    assert s.t_s[-1] == pytest.approx(off_ground - 1.0, abs=0.12)
    s0 = prepare([log], PrepConfig(ground_clearance_m=0.0)).segments[0]
    assert s0.t_s[-1] == pytest.approx(56.0, abs=0.02)


def test_ground_levels_that_disagree_leave_the_land_detector_alone():
    # still at 5 m when disarmed (a log cut in the air): no common ground, nothing trimmed
    s = prepare([make_log(60.0)]).segments[0]
    assert s.t_s[-1] == pytest.approx(56.0, abs=0.02)


def test_long_servo_gap_splits_segment_short_gap_does_not():
    p = prepare([make_log(80.0, drop_servo=(30.0, 32.0))])
    assert len(p.segments) == 2
    assert p.segments[0].t_s[-1] < 30.0 < 32.0 < p.segments[1].t_s[0]
    p2 = prepare([make_log(80.0, drop_servo=(30.0, 30.05))])
    assert len(p2.segments) == 1


def test_constant_velocity_while_the_attitude_moves_is_left_out():
    p = prepare([make_log(60.0)])
    assert not p.available[:3].any()
    assert sum(" left out: " in n for n in p.notes) == 3


def test_velocity_missing_part_becomes_its_own_segment():
    p = prepare([make_log(80.0, vel_nan_after_s=50.0)], PrepConfig(velocity_check=False))
    avail = [tuple(s.available[:3]) for s in p.segments]
    assert avail == [(True, True, True), (False, False, False)]
    assert np.isnan(p.segments[1].outputs[:, :3]).all()
    assert np.isfinite(p.segments[1].outputs[:, 3:]).all()
    assert any("missing in part" in n for n in p.notes)


def test_in_air_from_altitude_without_landed_state():
    p = prepare([make_log(60.0, landed_state=False)])
    # altitude above 0.5 m from 2.25 s on (climb of 2 m/s from 2 s)
    assert 3.0 < p.segments[0].t_s[0] < 4.0


def test_a_landed_state_stream_that_starts_late_leaves_the_armed_time_before_it_to_height():
    """The landed-state stream's request was answered only at 40 s (lost on a radio link, retried):
    before its first message the aircraft is judged by height, and the flight is one in-air interval
    from the climb through 0.3 m (2.15 s, within a position sample) to the landed state's "on ground" at 58 s."""
    log = make_log(60.0)
    ess = log.series["EXTENDED_SYS_STATE"]
    late = ess.t_fc_s >= 40.0
    log.series["EXTENDED_SYS_STATE"] = Series(ess.t_fc_s[late], ess.t_host_s[late],
                                              {k: v[late] for k, v in ess.columns.items()})
    (fl,) = find_flights(log.series)
    assert len(fl.in_air_intervals_fc_s) == 1
    a, b = fl.in_air_intervals_fc_s[0]
    assert a == pytest.approx(2.15, abs=0.1) and b == pytest.approx(58.0)
    p = prepare([dataclasses.replace(log, flights=[fl])])
    assert p.segments[0].t_s[0] < 4.0 and p.segments[-1].t_s[-1] > 55.0
    # the same log with the stream from the start keeps the landed state's own take-off (3 s)
    (fl0,) = find_flights(make_log(60.0).series)
    assert fl0.in_air_intervals_fc_s == ((3.0, 58.0),)


@pytest.mark.parametrize(
    "kwargs, needle",
    [({"with_servo": False}, "SERVO_OUTPUT_RAW"), ({"with_att": False}, "ATTITUDE"),
     ({"duration_s": 9.0}, "never in the air")],
)
def test_bad_input_one_line(kwargs, needle):
    with pytest.raises(ValueError) as e:
        prepare([make_log(**kwargs)])
    msg = str(e.value)
    assert needle in msg and "synthetic.tlog" in msg and "\n" not in msg


def test_smoothing_passes_reduce_noise_but_raw_is_kept():
    rng = np.random.default_rng(0)
    y = rng.normal(0, 1, (500, 8))
    u = np.zeros((500, 4))
    p0 = prepared_from_arrays(u, y, 0.02, smooth_passes=0)
    p2 = prepared_from_arrays(u, y, 0.02, smooth_passes=2)
    assert np.allclose(p2.segments[0].outputs_raw, y)
    assert p2.segments[0].outputs.std() < 0.8 * p0.segments[0].outputs.std()


def test_kfold_never_splits_by_sample_and_covers_everything():
    p = prepare([make_log(100.0)])
    folds = kfold(p, k=4, block_s=10.0)
    n_total = sum(s.n for s in p.segments)
    val_times = []
    for train, val in folds:
        assert sum(s.n for s in train.segments) + sum(s.n for s in val.segments) == n_total
        for s in train.segments + val.segments:
            assert s.n >= 10.0 / p.dt_s - 1 or s.t_s[-1] == p.segments[0].t_s[-1]  # whole blocks
            assert np.allclose(np.diff(s.t_s), p.dt_s)  # contiguous
        val_times.append(np.concatenate([s.t_s for s in val.segments]))
    allv = np.sort(np.concatenate(val_times))
    assert allv.size == n_total and np.unique(allv).size == n_total  # every sample validated exactly once


def test_by_flight_needs_two_flights():
    p = prepare([make_log(40.0)])
    with pytest.raises(ValueError, match="two flights"):
        by_flight(p)


def test_native_sample_intervals_are_kept_per_channel():
    """The diagnosis calibrates its noise floors for channels sent slower than the grid."""
    p = prepare([make_log(60.0, servo_rate_hz=25.0, att_rate_hz=50.0, pos_rate_hz=10.0)])
    ni = p.native_interval_s
    assert ni["lat"] == pytest.approx(0.04) and ni["ped"] == pytest.approx(0.04)
    assert ni["u"] == pytest.approx(0.1) and ni["w"] == pytest.approx(0.1)
    assert ni["p"] == pytest.approx(0.02) and ni["phi"] == pytest.approx(0.02)
    assert p.native_stride(("lat", "u", "p")) == pytest.approx([2.0, 5.0, 1.0])
