"""Grid alignment with gaps, run handling and the NED->body rotation."""

from __future__ import annotations

import numpy as np

from groundstation.dsp.frames import body_to_ned_matrix, ned_to_body
from groundstation.dsp.grid import fill_short_holes, interpolate_onto, runs, uniform_grid


def test_uniform_grid_spacing_and_end():
    t = uniform_grid(1.0, 2.0, 50.0)
    assert t[0] == 1.0 and abs(t[-1] - 2.0) < 1e-9
    assert np.allclose(np.diff(t), 0.02)


def test_linear_interpolation_is_exact_for_a_line():
    src = np.sort(np.random.default_rng(0).uniform(0, 10, 400))
    vals = 3.0 * src - 1.0
    t = uniform_grid(src[0], src[-1], 50.0)
    out, ok = interpolate_onto(src, vals, t, max_gap_s=1.0)
    assert ok.all()
    assert np.allclose(out, 3.0 * t - 1.0)


def test_short_gap_bridged_long_gap_marked_invalid():
    src = np.concatenate([np.arange(0, 5, 0.02), np.arange(5.06, 10, 0.02), np.arange(11.0, 15, 0.02)])
    vals = np.sin(src)
    t = uniform_grid(0.0, 14.9, 50.0)
    out, ok = interpolate_onto(src, vals, t, max_gap_s=0.1)
    # the 0.08 s hole near 5 s is bridged, the 1 s hole near 10.5 s is not
    assert ok[(t > 4.9) & (t < 5.2)].all()
    assert not ok[(t > 10.0) & (t < 11.0)].any()
    assert np.isnan(out[~ok]).all()
    assert np.allclose(out[ok], np.sin(t[ok]), atol=1e-3)


def test_nan_source_samples_invalidate_only_their_neighbourhood():
    src = np.arange(0, 2, 0.1)
    vals = np.stack([src, src * 2], axis=1)
    vals[10, 1] = np.nan
    t = uniform_grid(0, 1.9, 20.0)
    out, ok = interpolate_onto(src, vals, t, max_gap_s=0.5)
    assert ok[:, 0].all()
    bad = ~ok[:, 1]
    assert bad.any() and bad.sum() <= 3
    assert np.all(np.abs(t[bad] - 1.0) < 0.11)


def test_runs_and_fill_short_holes():
    m = np.array([1, 1, 0, 1, 0, 0, 0, 1, 1], dtype=bool)
    assert runs(m) == [(0, 2), (3, 4), (7, 9)]
    filled = fill_short_holes(m, 1)
    assert filled[2] and not filled[4:7].any()


def test_level_attitude_rotation_by_yaw():
    yaw = np.array([np.pi / 2])
    v_b = ned_to_body(np.array([[1.0, 0.0, 0.0]]), np.zeros(1), np.zeros(1), yaw)
    # flying north with the nose east: the velocity is to the left (negative v)
    assert np.allclose(v_b, [[0.0, -1.0, 0.0]], atol=1e-12)


def test_pitch_rotation_and_orthonormality():
    rng = np.random.default_rng(1)
    ang = rng.uniform(-0.5, 0.5, size=(100, 3))
    R = body_to_ned_matrix(ang[:, 0], ang[:, 1], ang[:, 2])
    assert np.allclose(np.einsum("nij,nkj->nik", R, R), np.eye(3), atol=1e-12)
    v = rng.normal(size=(100, 3))
    vb = ned_to_body(v, ang[:, 0], ang[:, 1], ang[:, 2])
    assert np.allclose(np.einsum("nij,nj->ni", R, vb), v)
    # nose up 0.3 rad, moving straight down in NED: body sees +u*sin component
    vb2 = ned_to_body(np.array([[0.0, 0.0, 1.0]]), np.zeros(1), np.array([0.3]), np.zeros(1))
    assert np.allclose(vb2, [[-np.sin(0.3), 0.0, np.cos(0.3)]])
