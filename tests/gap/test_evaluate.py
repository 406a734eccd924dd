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


def test_a_refinement_run_again_in_a_family_ends_where_running_it_ends_without_forming_anything(
        flight_factory, paper_theta):
    """Two stages that refine the same data from the same parameters (an input effect's re-fit, then
    its encompassing test) run it once: the second gets the end point, cost and base state of the
    first, bit for bit those of an evaluator outside the family that runs it; and a base state is
    formed only when used (data set again after construction: the state in between is never formed)."""
    prep = flight_factory(T_s=30.0, seed=3)
    segs, avail = segments_from_prepared(prep)
    memo = JacobianMemo(size=8)
    first = _evaluator(segs, avail, paper_theta * 1.03, memo)
    cost = first.refine(2)
    end_state = first.Jn   # formed on first use
    formed = len(memo._states)
    second = _evaluator(segs, avail, paper_theta * 1.03, memo)
    alone = _evaluator(segs, avail, paper_theta * 1.03)
    assert second.refine(2) == cost == alone.refine(2)
    assert not np.array_equal(alone.theta0, paper_theta * 1.03)   # it moved
    np.testing.assert_array_equal(second.theta0, alone.theta0)
    assert second.Jn is end_state and len(memo._states) == formed   # nothing formed again
    for name in ("r0", "col", "Jn", "JtJ"):
        np.testing.assert_array_equal(getattr(second, name), getattr(alone, name))
    third = _evaluator(segs, avail, paper_theta * 1.03, memo)
    third.refine(1)   # another refinement: run
    assert not np.array_equal(third.theta0, second.theta0)

    lazy_memo = JacobianMemo(size=8)
    changed = _evaluator(segs, avail, paper_theta, lazy_memo)
    changed.Y = changed.Y + 0.01
    changed.set_theta(changed.theta0)
    assert len(lazy_memo._states) == 0
    assert np.isfinite(changed.r0).all() and len(lazy_memo._states) == 1
