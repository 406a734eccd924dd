"""A spectral line above the Nyquist frequency of the stream a channel was sent at is not vibration."""

import numpy as np

from groundstation.gap.fingerprints import Line, resolvable_lines


def test_lines_above_a_slow_streams_nyquist_are_interpolation_images():
    lines = [Line(24.4, ["p", "r", "theta"], 9.0, -12.0, {"p": 1e-4, "r": 2e-4, "theta": 3e-5}),
             Line(3.9, ["p", "q"], 40.0, -80.0, {"p": 5e-3, "q": 4e-3})]
    stride = np.ones(8)
    stride[[3, 4, 5, 6, 7]] = 5.0  # rates and attitude sent at 10 Hz onto the 50 Hz grid: Nyquist 5 Hz
    kept = resolvable_lines(lines, stride, 0.02)
    assert [ln.frequency_hz for ln in kept] == [3.9]
    assert kept[0].channels == ["p", "q"] and set(kept[0].amplitude) == {"p", "q"}
    # the same line on 50 Hz streams is kept; without stream information nothing is dropped
    assert len(resolvable_lines(lines, np.ones(8), 0.02)) == 2
    assert resolvable_lines(lines, None, 0.02) == lines
    # a channel sent fast keeps the line, a slow one loses it
    stride[3] = 1.0
    mixed = resolvable_lines(lines[:1], stride, 0.02)
    assert mixed and mixed[0].channels == ["p"]
