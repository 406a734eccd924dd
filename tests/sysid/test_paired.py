"""The paired held-out difference of two models' predictions of the same windows, with a bootstrap
interval over the windows (benchkit.paired), on predictions whose errors are set by construction."""

import numpy as np
import pytest

from benchkit.paired import paired_difference, window_score
from groundstation.sysid.heldout import PredictedWindows


def _pred(y: np.ndarray, err: np.ndarray) -> PredictedWindows:
    """Predictions of ``y`` (W, L, 8) off by ``err`` times the signal per window (W,) in every channel."""
    return PredictedWindows(outputs=y, predicted=y * (1.0 - err[:, None, None]), mask=np.ones(y.shape, bool),
                            inputs=np.zeros(y.shape[:2] + (4,)), dt_s=0.02)


@pytest.fixture
def y():
    return np.random.default_rng(3).normal(size=(9, 50, 8))


def test_a_model_better_on_every_window_is_better_beyond_the_spread(y):
    rng = np.random.default_rng(1)
    a, b = _pred(y, 0.3 + 0.05 * rng.random(9)), _pred(y, 0.5 + 0.05 * rng.random(9))
    d = paired_difference(a, b)
    assert d["difference"] == pytest.approx(window_score(a, np.arange(9)) - window_score(b, np.arange(9)))
    assert 10.0 < d["lo"] <= d["difference"] <= d["hi"] < 30.0


def test_one_unlike_window_widens_the_interval_and_is_named(y):
    y = y.copy()
    y[8] *= 3.0     # the largest manoeuvre: its energy dominates the fold's eq.-19 match
    err_a = np.full(9, 0.4)
    err_a[8] = 0.6
    a, b = _pred(y, err_a), _pred(y, np.full(9, 0.4))
    d = paired_difference(a, b)
    assert d["difference"] < -5.0 and d["window"] == 9
    assert d["without_window"] == pytest.approx(0.0, abs=1e-9)
    assert d["lo"] < d["difference"] and d["hi"] >= 0.0    # the one window does not make a's loss certain


def test_predictions_of_different_windows_are_refused(y):
    with pytest.raises(ValueError, match="different windows"):
        paired_difference(_pred(y, np.full(9, 0.1)), _pred(y[:8], np.full(8, 0.1)))
