"""The evaluator's base state shared within a family of evaluators: the same numbers, formed once."""

import pickle

import numpy as np

from groundstation.gap.diagnose import segments_from_prepared
from groundstation.gap.evaluate import Evaluator, JacobianMemo, SegmentArrays


def _evaluator(segs, avail, theta, memo=None):
    return Evaluator(segs, 0.02, theta, avail, window_s=3.0, folds=3, memo=memo)


def test_evaluators_of_one_family_form_a_base_state_once_with_the_same_numbers(flight_factory, paper_theta):
    """An evaluator built for the data and parameters a family member reached (a re-fit's end point)
    takes that member's arrays; they equal a fresh evaluator's bit for bit; other data, other
    outputs set after construction or a copy in another process do not share them."""
    prep = flight_factory(T_s=30.0, seed=3)
    segs, avail = segments_from_prepared(prep)
    memo = JacobianMemo()
    ev = _evaluator(segs, avail, paper_theta * 1.03, memo)
    ev.refine(2)
    again = _evaluator(segs, avail, ev.theta0, memo)
    fresh = _evaluator(segs, avail, ev.theta0)
    assert again.Jn is ev.Jn and again.r0 is ev.r0 and fresh.Jn is not ev.Jn
    for name in ("r0", "col", "Jn", "JtJ"):
        np.testing.assert_array_equal(getattr(again, name), getattr(fresh, name))
    np.testing.assert_array_equal(again.heldout(again.r0)[0], fresh.heldout(fresh.r0)[0])

    s = segs[0]
    u = s.inputs.copy()
    u[:, 1] *= 1.1
    other = _evaluator([SegmentArrays(s.t_s, u, s.outputs, s.outputs_raw, s.alt_m)], avail, ev.theta0, memo)
    assert other.Jn is not ev.Jn and not np.array_equal(other.r0, ev.r0)
    moved = _evaluator(segs, avail, ev.theta0, memo)
    moved.Y = moved.Y + 0.01
    moved.set_theta(moved.theta0)
    assert moved.r0 is not ev.r0 and not np.array_equal(moved.r0, ev.r0)

    assert len(memo._states) == memo.size  # bounded
    assert len(pickle.loads(pickle.dumps(memo))._states) == 0
    memo.clear()
    assert _evaluator(segs, avail, ev.theta0, memo).Jn is not ev.Jn
