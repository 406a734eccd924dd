"""Missing data are data: holes of a lossy, bursty link are bridged (inputs) and marked (outputs), and
every cost counts only what was measured."""

from __future__ import annotations

import numpy as np
import pytest

from groundstation.dsp.prepare import PrepConfig, prepare


@pytest.fixture(scope="module")
def lossy(tmp_path_factory):
    from firmware_interface.readers import load_log
    from hil_replay.sim import write_tlog

    d = tmp_path_factory.mktemp("lossy")
    rates = {"ATTITUDE": 25, "SERVO_OUTPUT_RAW": 25, "LOCAL_POSITION_NED": 25}
    truth = write_tlog(d / "f.tlog", seed=5, flight_duration_s=60.0, rates_hz=rates, packet_loss=0.10, loss_burst=8.0)
    write_tlog(d / "c.tlog", seed=5, flight_duration_s=60.0, rates_hz=rates, packet_loss=0.0)
    return load_log(d / "f.tlog"), load_log(d / "c.tlog"), truth["parameters"]


def test_holes_are_bridged_and_marked(lossy):
    log, clean, _ = lossy
    p = prepare([log])
    lq = p.link_quality
    assert 6.0 < lq["loss_pct"] < 15.0 and lq["in_air_holes"] > 10
    assert 0 < lq["unmeasured_pct"] < 25.0 and lq["longest_gap_s"] > 0.1
    assert any(f"{lq['loss_pct']:.1f} % of packets lost" in n for n in p.notes)
    seg = max(p.segments, key=lambda s: s.n)
    m = seg.measured_mask()
    assert seg.measured is not None and not m.all() and m.mean() > 0.7
    assert np.isfinite(seg.inputs).all() and np.isfinite(seg.outputs[:, seg.available]).all()
    # without bridging the same log falls apart into short pieces (or nothing at all)
    try:
        strict = prepare([log], PrepConfig(max_input_bridge_s=0.0)).duration_s
    except ValueError:
        strict = 0.0
    assert strict < 0.6 * p.duration_s
    # a clean flight has no holes, nothing marked, nothing bridged
    c = prepare([clean])
    assert all(s.measured is None for s in c.segments) and c.link_quality["bridged_s"] == 0.0
    assert p.duration_s > 0.8 * c.duration_s


def test_output_error_counts_measured_samples_only(lossy):
    from benchkit.synthetic import EXAMPLE_TRUTH
    from groundstation.sysid.cost import make_windows
    from groundstation.sysid.model import theta_from_dict
    from groundstation.sysid.simulate import WindowSimulator

    p = prepare([lossy[0]])
    win = make_windows(p.segments, p.dt_s, 3.0)
    assert win.measured is not None and (~win.measured).any()
    theta = theta_from_dict(EXAMPLE_TRUTH)[None].repeat(3, axis=0) * np.array([[1.0], [1.05], [0.95]])
    sim = WindowSimulator(win.inputs, win.outputs, win.dt_s, win.available, measured=win.measured)
    e = sim.errors(theta)
    assert np.all(e[:, ~sim.smask] == 0.0)
    np.testing.assert_allclose(sim.sse(theta), (e ** 2).sum(axis=(1, 2)), rtol=1e-8, atol=1e-10)
    # projected B entries (the search) count the same samples
    from groundstation.sysid.cost import WindowedCost

    free = np.ones(theta.shape[1], bool)
    c = WindowedCost(win, free, theta[0], varpro=True)
    assert np.isfinite(c(theta[:, c.free])).all()


def test_gap_residuals_ignore_holes(lossy):
    from benchkit.synthetic import EXAMPLE_TRUTH
    from groundstation.gap.diagnose import segments_from_prepared
    from groundstation.gap.evaluate import Evaluator
    from groundstation.sysid.model import theta_from_dict

    p = prepare([lossy[0]])
    segs, avail = segments_from_prepared(p)
    ev = Evaluator(segs, p.dt_s, theta_from_dict(EXAMPLE_TRUTH), avail, window_s=3.0, folds=3)
    assert ev.M is not None and ev.W >= 6
    r = ev.residual(ev.simulate(theta_from_dict(EXAMPLE_TRUTH)[None]))[0]
    assert np.all(r[~ev.M] == 0.0)
    assert (~ev.M).any() and ev.score_mask.shape == ev.Y.shape


def test_frequency_responses_from_gapped_windows(lossy):
    from groundstation.freq.spectra import estimate_responses

    lossy_set = estimate_responses(prepare([lossy[0]]))
    clean_set = estimate_responses(prepare([lossy[1]]))
    ok_l = sum(int(pr.coherent.sum()) for pr in lossy_set.pairs)
    ok_c = sum(int(pr.coherent.sum()) for pr in clean_set.pairs)
    assert ok_l > 0.35 * ok_c  # windows with short holes are kept, not dropped


def test_frequency_response_errors_count_windows_with_holes_by_their_measured_share(lossy):
    """The bridged samples carry no independent information: the random-error bounds of the frequency
    responses grow with the share of each window the link lost, the responses themselves stay."""
    import dataclasses

    from groundstation.freq.spectra import estimate_responses

    p = prepare([lossy[0]])
    assert any(s.measured is not None for s in p.segments)
    as_whole = dataclasses.replace(p, segments=[dataclasses.replace(s, measured=None) for s in p.segments])
    by_share, whole = estimate_responses(p), estimate_responses(as_whole)
    grew = []
    for a, b in zip(by_share.with_response, whole.with_response, strict=True):
        assert (a.input, a.output) == (b.input, b.output)
        ok = np.isfinite(a.random_error) & np.isfinite(b.random_error)
        assert ok.any()
        np.testing.assert_allclose(np.abs(a.response[ok]), np.abs(b.response[ok]), rtol=0.05)
        ratio = a.random_error[ok] / b.random_error[ok]
        assert np.all(ratio >= 1.0 - 1e-9)
        grew.append(float(np.median(ratio)))
    # the flight lost about a tenth of its samples: errors grow by about sqrt(1 / 0.9), not by a factor
    assert 1.01 < float(np.median(grew)) < 1.3, grew


def _bridged_copy(segs, rng, share=0.1):
    """The segments with random holes: inputs a straight line over each, outputs there unmeasured."""
    from dataclasses import replace

    from groundstation.gap.bridging import line_error

    out = []
    for s in segs:
        n = s.t_s.shape[0]
        br = np.zeros(n, bool)
        for a in rng.choice(np.arange(2, n - 16), max(1, int(share * n / 8)), replace=False):
            br[a:a + int(rng.integers(3, 13))] = True
        br[0] = br[-1] = False
        u = s.inputs.copy()
        d = np.diff(np.r_[0, br.astype(int), 0])
        for a, b in zip(np.flatnonzero(d == 1), np.flatnonzero(d == -1), strict=True):
            u[a:b] -= line_error(s.inputs[a - 1:b + 1])
        out.append(replace(s, inputs=u, bridged=br, measured=np.repeat(~br[:, None], 8, axis=1)))
    return out


def test_bridge_error_floor_matches_what_straight_lines_cost(lossy):
    """The floor the bridged inputs add (measured from the flight's own inputs) is the mean-square
    held-out error straight lines over holes really cause, over many placements of the holes."""
    from benchkit.synthetic import EXAMPLE_TRUTH
    from groundstation.gap.bridging import bridge_error_nrmse
    from groundstation.gap.diagnose import segments_from_prepared
    from groundstation.gap.evaluate import Evaluator
    from groundstation.sysid.model import theta_from_dict

    th = theta_from_dict(EXAMPLE_TRUTH)
    clean, avail = segments_from_prepared(prepare([lossy[1]]))
    ev0 = Evaluator(clean, 0.02, th, avail, window_s=3.0, folds=3)
    assert not bridge_error_nrmse(ev0, clean, th, np.random.default_rng(0)).any()   # no bridge, no floor
    rng = np.random.default_rng(3)
    true2, floor2 = [], []
    for _ in range(6):
        segs = _bridged_copy(clean, rng)
        ev = Evaluator(segs, 0.02, th, avail, window_s=3.0, folds=3)
        r = ev.residual(ev.simulate(th[None], U=ev0.U)[0]) - ev.residual(ev.simulate(th[None])[0])
        true2.append((ev.heldout_residual(r)[:, ev.start:] ** 2).sum(axis=(0, 1)) / ev.energy.sum(0))
        floor2.append(bridge_error_nrmse(ev, segs, th, rng, draws=8) ** 2)
    true_rms, floor_rms = np.sqrt(np.mean(true2, axis=0)), np.sqrt(np.mean(floor2, axis=0))
    assert (floor_rms > 0).all()
    ratio = np.sqrt(np.sum(floor_rms ** 2) / np.sum(true_rms ** 2))
    assert 0.6 < ratio < 1.6, (ratio, true_rms, floor_rms)


def test_outputs_after_a_bridged_hole_are_not_counted_while_the_rotor_settles(lossy):
    from groundstation.dsp.prepare import _settling

    br = np.zeros(30, bool)
    br[5:8] = True
    cfg = PrepConfig(rotor_inv_tau_s=25.0, settle_after_bridge_tau=3.0)   # 3 x 0.04 s = 6 samples at 50 Hz
    assert np.flatnonzero(_settling(br, cfg)).tolist() == list(range(8, 14))
    assert not _settling(br, PrepConfig(settle_after_bridge_tau=0.0)).any()
    p = prepare([lossy[0]])
    p0 = prepare([lossy[0]], PrepConfig(settle_after_bridge_tau=0.0))
    assert p.link_quality["unmeasured_pct"] > p0.link_quality["unmeasured_pct"]
    seg = max(p.segments, key=lambda s: s.n)
    assert seg.inputs_bridged is not None
    after = _settling(seg.inputs_bridged, PrepConfig())
    assert after.any() and not seg.measured_mask()[after].any()


def test_inputs_shifted_for_a_time_skew_keep_where_they_were_bridged(lossy):
    p = prepare([lossy[0]], PrepConfig(input_shift_s=0.06))
    for s in p.segments:
        assert s.inputs_bridged is None or s.inputs_bridged.shape == s.t_s.shape
    assert any(s.inputs_bridged is not None and s.inputs_bridged.any() for s in p.segments)


def test_identification_windows_restart_after_each_bridged_hole(lossy):
    """No window simulates through a bridged hole into the samples it counts (except a start too close
    to the segment's end, which takes the segment's last window); every measured sample is counted
    once; a flight without holes gets make_windows' windows."""
    from groundstation.sysid.cost import make_windows
    from groundstation.sysid.holes import restart_windows

    log, clean, _ = lossy
    c = prepare([clean])
    a, b = restart_windows(c.segments, c.dt_s, 3.0), make_windows(c.segments, c.dt_s, 3.0)
    assert b.measured is None and a.measured is None
    np.testing.assert_array_equal(a.inputs, b.inputs)
    np.testing.assert_array_equal(a.t0_s, b.t0_s)
    p = prepare([log])
    win = restart_windows(p.segments, p.dt_s, 3.0)
    through = make_windows(p.segments, p.dt_s, 3.0)
    counted = {i: np.zeros(s.n, int) for i, s in enumerate(p.segments)}
    for w in range(win.count):
        s = p.segments[win.segment[w]]
        a0 = int(round((win.t0_s[w] - s.t_s[0]) / p.dt_s))
        rows = np.flatnonzero(win.measured[w].any(axis=1))
        assert rows.size
        counted[win.segment[w]][a0 + rows] += 1
        br = s.inputs_bridged[a0:a0 + rows[-1] + 1] if s.inputs_bridged is not None else np.zeros(1, bool)
        # from its start, or (a start too close to the segment's end) from the first sample it counts
        first = rows[0] if a0 == s.n - win.length else 0
        assert not br[first:].any(), f"window {w} counts samples after a bridged hole"
    for i, s in enumerate(p.segments):
        assert counted[i].max() <= 1
        assert counted[i].sum() >= 0.97 * s.measured_mask().all(axis=1).sum() - 5
    assert win.count > through.count


def _holed(seg, rng, share=0.1):
    """``seg`` (a prepared segment) with random holes: the inputs a straight line over each (3-12 samples),
    the outputs there not measured."""
    from dataclasses import replace

    br = np.zeros(seg.n, bool)
    for a in rng.choice(np.arange(2, seg.n - 16), max(1, int(share * seg.n / 8)), replace=False):
        br[a:a + int(rng.integers(3, 13))] = True
    br[0] = br[-1] = False
    u = seg.inputs.copy()
    d = np.diff(np.r_[0, br.astype(int), 0])
    for a, b in zip(np.flatnonzero(d == 1), np.flatnonzero(d == -1), strict=True):
        s = np.arange(1, b - a + 1) / (b - a + 1)
        u[a:b] = u[a - 1] * (1 - s)[:, None] + u[b] * s[:, None]
    return replace(seg, inputs=u, measured=np.repeat(~br[:, None], 8, axis=1), inputs_bridged=br)


def test_inputs_in_holes_estimated_from_the_outputs_come_closer_than_the_line(lossy):
    """Given the true model, the inputs estimated in holes from the outputs around them are nearer the
    inputs the holes hid than the straight line (lat and lon: the horizontal outputs see them best);
    nothing outside the holes moves, and what is bridged stays marked."""
    from dataclasses import replace

    from groundstation.sysid.hole_inputs import estimate_hole_inputs, hole_runs
    from groundstation.sysid.model import HoverModel

    _, clean, truth = lossy
    c = prepare([clean])
    rng = np.random.default_rng(3)
    p = replace(c, segments=[_holed(s, rng) for s in c.segments])
    model = HoverModel(params=dict(truth), input_trim_pwm=dict(p.input_trim_pwm), pwm_per_unit=p.pwm_per_unit)
    f = estimate_hole_inputs(p, model)
    line_err, est_err, holes = [], [], 0
    for s0, s, fs in zip(c.segments, p.segments, f.segments, strict=True):
        br = s.inputs_bridged
        holes += len(hole_runs(br))
        np.testing.assert_array_equal(fs.inputs[~br], s.inputs[~br])
        assert fs.inputs_bridged is br and fs.measured is s.measured
        line_err.append((s.inputs - s0.inputs)[br])
        est_err.append((fs.inputs - s0.inputs)[br])
    le, ee = np.concatenate(line_err), np.concatenate(est_err)
    rms_line, rms_est = np.sqrt((le ** 2).mean(axis=0)), np.sqrt((ee ** 2).mean(axis=0))
    assert holes > 20
    # with identify's default band (1x the rotor's corner frequency) lat 0.51 and lon 0.90 of the
    # line's error on this flight (a 3x band: 0.37 and 0.91)
    assert rms_est[0] < 0.6 * rms_line[0] and rms_est[1] < rms_line[1], (rms_est, rms_line)
    assert f.link_quality["inputs_in_holes"]["estimated_holes"] == holes
    # a flight without bridged inputs comes back as it is
    assert all(a is b for a, b in zip(estimate_hole_inputs(c, model).segments, c.segments, strict=True))


def test_standard_errors_widen_by_what_the_estimated_hole_inputs_take(lossy):
    """With the inputs in holes estimated from the same outputs, the standard errors come from the
    Jacobian with the hole-input coefficients projected out: never narrower, wider where the holes are."""
    from dataclasses import replace

    from groundstation.sysid.cost import WindowedCost, make_windows
    from groundstation.sysid.hole_inputs import window_holes
    from groundstation.sysid.model import HOR_PARAMS, PARAM_INDEX, bounds_array, theta_from_dict
    from groundstation.sysid.refine import jac_final

    _, clean, truth = lossy
    c = prepare([clean])
    p = replace(c, segments=[_holed(s, np.random.default_rng(3)) for s in c.segments])
    win = make_windows(p.segments, p.dt_s, 3.0)
    holes = window_holes(p.segments, win, subsystems=(0,))
    assert holes is not None and np.unique(holes.window).size > 5
    assert window_holes(c.segments, make_windows(c.segments, c.dt_s, 3.0)) is None
    free = np.zeros(31, bool)
    free[[PARAM_INDEX[n] for n in HOR_PARAMS]] = True
    theta = theta_from_dict(truth)
    cost = WindowedCost(win, free, theta, estimate_all_initial=True, subsystems=(0,))
    b = bounds_array()[free]
    x, sigma = theta[free], np.full(8, 0.01)
    J = jac_final(cost, x, sigma, b[:, 1] - b[:, 0], b[:, 1])
    Jm = holes.marginal_jacobian(cost, x, sigma, J)
    ratio = np.sqrt(np.diag(np.linalg.pinv(Jm.T @ Jm)) / np.diag(np.linalg.pinv(J.T @ J)))
    assert np.all(ratio > 0.999) and ratio.max() > 1.02, ratio
    # the vertical subsystem's inputs were not estimated: its Jacobian stays as it is
    assert holes.marginal_jacobian(WindowedCost(win, free, theta, subsystems=(1,)), x, sigma, J) is J


def test_line_error_per_shape_adds_up_to_the_lines_error():
    """The line's error measured per half-sine shape holds all of it (the shapes are a complete,
    orthogonal basis of the hole's samples); a straight input has none; a bridged stretch is not used."""
    from groundstation.sysid.hole_inputs import line_error_var, line_shape_var

    t = np.arange(400) * 0.02
    u = np.stack([np.sin(2.0 * t), np.cos(5.0 * t) + 0.1 * np.sin(23.0 * t), 0.3 * t], axis=1)
    br = np.zeros(400, bool)
    n = 9
    v = line_shape_var(u, br, n)
    assert v.shape == (n, 3)
    np.testing.assert_allclose(v.sum(axis=0), 2 * n / (n + 1) * line_error_var(u, br, n), rtol=1e-10)
    assert v[:, 2].max() < 1e-20 and v[0, 0] > 10 * v[1:, 0].max()   # a smooth input's error is the first shape
    br[10:390] = True
    assert line_shape_var(u, br, n) is None


def test_standard_errors_cover_what_the_straight_lines_in_holes_move_the_parameters(lossy):
    """Inputs left straight lines over holes move the estimate by what the lines miss. The line error,
    measured per shape on the received inputs around each hole and passed through the model and the fit,
    predicts that move: over several hole patterns its z is about one. The noise alone would put it at
    several standard errors on this 25-Hz flight."""
    from dataclasses import replace

    from groundstation.sysid.cost import WindowedCost, make_windows
    from groundstation.sysid.hole_inputs import window_holes
    from groundstation.sysid.model import HOR_PARAMS, PARAM_INDEX, bounds_array, theta_from_dict
    from groundstation.sysid.refine import jac_final

    _, clean, truth = lossy
    c = prepare([clean])
    free = np.zeros(31, bool)
    free[[PARAM_INDEX[n] for n in HOR_PARAMS]] = True
    theta = theta_from_dict(truth)
    x, b = theta[free], bounds_array()[free]
    z, z_noise = [], []
    for seed in range(6):
        p = replace(c, segments=[_holed(s, np.random.default_rng(seed)) for s in c.segments])
        # the same holes with the true inputs in them: what the lines change
        q = replace(p, segments=[replace(s, inputs=s0.inputs) for s, s0 in zip(p.segments, c.segments, strict=True)])
        win = make_windows(p.segments, p.dt_s, 3.0)
        lines = window_holes(p.segments, win, subsystems=(0,), shapes=True)
        assert lines is not None and lines.shape_var is not None
        cost, cost_q = (WindowedCost(w, free, theta, estimate_all_initial=True, subsystems=(0,))
                        for w in (win, make_windows(q.segments, q.dt_s, 3.0)))
        sse, n = cost_q.sim.sse(theta[None])[0], cost_q.sim.smask.sum(axis=(0, 1))
        sigma = np.where(n > 0, np.sqrt(sse / np.maximum(n, 1)), 1.0)    # the measurement noise
        J = jac_final(cost, x, sigma, b[:, 1] - b[:, 0], b[:, 1])
        Hinv = np.linalg.pinv(J.T @ J)
        C = lines.line_covariance(cost, x, sigma, J, Hinv)
        assert np.all(np.linalg.eigvalsh(C) > -1e-12 * np.abs(C).max())
        moved = -Hinv @ (J.T @ (cost.residuals(x[None], sigma) - cost_q.residuals(x[None], sigma)).reshape(-1))
        z.append(moved / np.sqrt(np.diag(C)))
        z_noise.append(moved / np.sqrt(np.diag(Hinv)))
    rms, rms_noise = np.sqrt(np.mean(np.square(z))), np.sqrt(np.mean(np.square(z_noise)))
    assert 0.7 < rms < 1.4 and rms_noise > 3.0, (rms, rms_noise)   # 1.04 and 7.4 here
    # no hole, nothing to add; a vertical cost has no line of a horizontal input to answer for
    assert window_holes(c.segments, make_windows(c.segments, c.dt_s, 3.0), shapes=True) is None
    assert lines.line_covariance(WindowedCost(win, free, theta, subsystems=(1,)), x, sigma, J, Hinv) is None


def test_hole_inputs_are_estimated_only_on_streams_at_the_grid_rate(lossy):
    """25 Hz input streams on the 50 Hz grid keep their straight lines (there the estimate did not
    help); allowing a stride of 2 grid steps estimates them; a flight without holes never does."""
    from groundstation.sysid.identify import estimates_hole_inputs
    from groundstation.sysid.settings import IdentifyConfig

    log, clean, _ = lossy
    p = prepare([log])
    assert p.native_stride(("lat", "lon")).min() > 1.5
    assert not estimates_hole_inputs(p, IdentifyConfig())
    assert estimates_hole_inputs(p, IdentifyConfig(hole_input_max_stride=2.5))
    assert not estimates_hole_inputs(p, IdentifyConfig(hole_input_max_stride=2.5, hole_input_passes=0))
    assert not estimates_hole_inputs(prepare([clean]), IdentifyConfig(hole_input_max_stride=2.5))


def test_a_model_that_runs_away_keeps_the_lines(lossy):
    """A model whose responses overflow over the estimation stretch leaves the straight lines as they are."""
    from dataclasses import replace

    from groundstation.sysid.hole_inputs import estimate_hole_inputs
    from groundstation.sysid.model import HoverModel

    _, clean, truth = lossy
    c = prepare([clean])
    p = replace(c, segments=[_holed(s, np.random.default_rng(3)) for s in c.segments])
    wild = HoverModel(params={**truth, "M_q": 400.0, "L_p": 400.0}, input_trim_pwm=dict(p.input_trim_pwm),
                      pwm_per_unit=p.pwm_per_unit)
    with np.errstate(all="ignore"):
        f = estimate_hole_inputs(p, wild, subsystems=(0,))
    for s, fs in zip(p.segments, f.segments, strict=True):
        np.testing.assert_array_equal(fs.inputs, s.inputs)


def test_identify_refits_on_the_estimated_hole_inputs(lossy):
    """One pass of the refit: the model is refined on the estimated inputs, says so in its link report,
    and keeps finite standard errors for the parameters the flight determines."""
    from dataclasses import replace

    from groundstation.sysid.identify import refit_hole_inputs
    from groundstation.sysid.model import HoverModel
    from groundstation.sysid.settings import IdentifyConfig

    _, clean, truth = lossy
    c = prepare([clean])
    p = replace(c, segments=[_holed(s, np.random.default_rng(3)) for s in c.segments])
    m0 = HoverModel(params=dict(truth), input_trim_pwm=dict(p.input_trim_pwm), pwm_per_unit=p.pwm_per_unit)
    # this flight streams at 25 Hz: allow it, so that the refit's standard errors project the holes out too
    filled, m = refit_hole_inputs(p, m0, IdentifyConfig(hole_input_passes=1, hole_input_max_stride=2.5))
    assert filled.link_quality["inputs_in_holes"]["estimated_holes"] > 20
    assert m.source["link_quality"]["inputs_in_holes"] == filled.link_quality["inputs_in_holes"]
    assert not np.array_equal(filled.segments[0].inputs[:, :2], p.segments[0].inputs[:, :2])
    np.testing.assert_array_equal(filled.segments[0].inputs[:, 2:], p.segments[0].inputs[:, 2:])  # col, ped: lines
    for k in ("M_a", "L_b", "A_lat", "B_lon"):
        assert m.parameter_std[k] is not None and np.isfinite(m.parameter_std[k])
        assert abs(m.params[k] - truth[k]) < 0.3 * abs(truth[k])


def test_the_window_solve_minimises_the_refinement_cost_over_the_hole_inputs(lossy):
    """``hole_input_solve = "windows"``: the hole inputs that minimise the refinement's own cost plus the
    prior at the model, all holes at once; a hole cut by a window's edge has one set of coefficients."""
    from dataclasses import replace

    from groundstation.sysid.cost import WindowedCost, make_windows
    from groundstation.sysid.hole_inputs import window_holes
    from groundstation.sysid.model import HOR_PARAMS, PARAM_INDEX, theta_from_dict

    _, clean, truth = lossy
    c = prepare([clean])
    p = replace(c, segments=[_holed(s, np.random.default_rng(3)) for s in c.segments])
    win = make_windows(p.segments, p.dt_s, 3.0)
    holes = window_holes(p.segments, win, subsystems=(0,))
    assert holes is not None and holes.hole is not None
    shared = [h for h in np.unique(holes.hole) if (holes.hole == h).sum() > 1]
    assert shared, "no hole cut by a window edge in this flight"
    free = np.zeros(31, bool)
    free[[PARAM_INDEX[n] for n in HOR_PARAMS]] = True
    theta = theta_from_dict(truth)
    cost = WindowedCost(win, free, theta, estimate_all_initial=True, subsystems=(0,))
    x, sigma = theta[free], np.array([0.05, 0.05, 1.0, 0.01, 0.01, 1.0, 0.005, 0.005])
    coeffs = holes.solve(cost, x, sigma)
    assert {h for h, _ in coeffs} == set(np.unique(holes.hole).tolist()) and {i for _, i in coeffs} == {0, 1}
    keys = holes.coefficients(theta, (0, 1), p.dt_s)
    prec = holes.columns(theta, (0, 1), win.length, p.dt_s)[2]

    def objective(cf):
        f = replace(p, segments=holes.fill(p.segments, cf))
        wf = make_windows(f.segments, f.dt_s, 3.0)
        r = WindowedCost(wf, free, theta, estimate_all_initial=True, subsystems=(0,)).residuals(x[None], sigma)
        cv = np.concatenate([cf[(h, i)][j:j + 1] for h, i, j in keys])
        return float((r ** 2).sum() + cv @ (prec * cv))

    best = objective(coeffs)
    assert best < objective({k: 0 * v for k, v in coeffs.items()})
    rng = np.random.default_rng(1)
    for _ in range(3):   # any other coefficients cost more
        other = {k: v + 0.2 * np.abs(v).max() * rng.standard_normal(v.size) for k, v in coeffs.items()}
        assert objective(other) > best
    # the filled inputs differ from the lines only inside the holes, and only lat and lon
    f = replace(p, segments=holes.fill(p.segments, coeffs))
    for s, fs in zip(p.segments, f.segments, strict=True):
        np.testing.assert_array_equal(fs.inputs[~s.inputs_bridged], s.inputs[~s.inputs_bridged])
        np.testing.assert_array_equal(fs.inputs[:, 2:], s.inputs[:, 2:])


def test_outputs_left_out_while_the_rotor_settles_count_again_with_estimated_inputs(lossy):
    """Data preparation leaves out the outputs right after a bridged input (the line's error still moves
    the rotor) and says which; with the hole inputs estimated, identification counts them again."""
    from groundstation.sysid.identify import count_settling

    log, clean, _ = lossy
    p = prepare([log])
    seg = max(p.segments, key=lambda s: s.n)
    assert seg.settling is not None and seg.settling.any()
    assert not (seg.measured & seg.settling).any()                  # left out of the cost
    after = np.zeros(seg.n, bool)
    after[1:] = seg.inputs_bridged[:-1]
    assert seg.settling[after & ~seg.inputs_bridged].any()            # right after a bridged stretch
    c = count_settling(p)
    cs = max(c.segments, key=lambda s: s.n)
    np.testing.assert_array_equal(cs.measured, seg.measured | seg.settling)
    assert cs.settling is None and cs.inputs_bridged is seg.inputs_bridged
    assert c.link_quality["settling_samples_counted"] == sum(int(s.settling[:, s.available].sum())
                                                             for s in p.segments if s.settling is not None)
    # without a settling sample (a clean flight, or settle_after_bridge_tau = 0) nothing changes
    q = prepare([clean])
    assert all(a is b for a, b in zip(count_settling(q).segments, q.segments, strict=True))
    assert all(s.settling is None for s in prepare([log], PrepConfig(settle_after_bridge_tau=0.0)).segments)
