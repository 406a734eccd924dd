"""The incremental estimate (rows fed as they arrive, the live excitation monitor's) equals the batch
estimate of ``validate --freq`` on the same data, to rounding."""

from __future__ import annotations

import dataclasses

import numpy as np
import pytest

from groundstation.freq.spectra import FreqConfig, IncrementalResponses, estimate_responses
from groundstation.sysid.model import OUTPUTS
from tests.freq.conftest import flight


def _two_segments_with_gaps():
    """A 150-s simulated flight cut into two in-air segments, with a 3-s dropout of q and a 2-s one of
    every input (NaN), so windows with different finite channels are summed apart."""
    prep = flight(150.0, seed=3)
    s = prep.segments[0]
    u, y = s.inputs.copy(), s.outputs_raw.copy()
    y[2000:2150, OUTPUTS.index("q")] = np.nan
    u[5000:5100, :] = np.nan
    cut = 3700
    segs = [dataclasses.replace(s, t_s=s.t_s[a:b], inputs=u[a:b], outputs=s.outputs[a:b], outputs_raw=y[a:b],
                                alt_m=s.alt_m[a:b]) for a, b in ((0, cut), (cut + 40, u.shape[0]))]
    return dataclasses.replace(prep, segments=segs)


@pytest.mark.parametrize("cfg", [FreqConfig(), FreqConfig(window_s=(4.0, 8.0, 16.0), overlap=0.5, detrend="constant")])
def test_incremental_equals_batch(cfg):
    prep = _two_segments_with_gaps()
    batch = estimate_responses(prep, cfg)
    inc = IncrementalResponses(prep.dt_s, cfg)
    rng = np.random.default_rng(0)
    for seg in prep.segments:
        k = 0
        while k < seg.inputs.shape[0]:     # chunks of 1..120 rows, as the link delivers them
            n = int(rng.integers(1, 121))
            inc.add(seg.inputs[k:k + n], seg.outputs_raw[k:k + n])
            k += n
        inc.end_segment()
    live = inc.responses()
    np.testing.assert_array_equal(live.f_hz, batch.f_hz)
    assert live.windows_s == batch.windows_s and live.conditioned_on == batch.conditioned_on
    assert live.notes == batch.notes
    compared = 0
    for a, b in zip(batch.pairs, live.pairs, strict=True):
        assert (a.input, a.output, a.reason) == (b.input, b.output, b.reason)
        np.testing.assert_array_equal(a.coherent, b.coherent)
        for x, z in ((a.response, b.response), (a.coherence, b.coherence), (a.random_error, b.random_error)):
            np.testing.assert_array_equal(np.isfinite(x), np.isfinite(z))
            np.testing.assert_allclose(z[np.isfinite(z)], x[np.isfinite(x)], rtol=1e-9, atol=1e-12)
        compared += a.has_response
    assert compared >= 8      # the on-axis pairs and more have responses: the comparison is not empty


def test_subset_of_pairs_is_the_same_numbers():
    """The live monitor asks only for the on-axis pairs: the same numbers, fewer solves."""
    prep = flight(120.0, seed=4)
    inc = IncrementalResponses(prep.dt_s)
    s = prep.segments[0]
    inc.add(s.inputs, s.outputs_raw)
    full = inc.responses()
    part = inc.responses(pairs=(("lat", "q"), ("ped", "r")))
    assert [(p.input, p.output) for p in part.pairs] == [("lat", "q"), ("ped", "r")]
    for p in part.pairs:
        np.testing.assert_allclose(p.coherence, full.pair(p.input, p.output).coherence, rtol=1e-12, equal_nan=True)


def test_cost_of_an_update_does_not_grow_with_the_flight():
    """What is kept is a fixed set of sums per window length (plus one count per segment), however many
    rows went in."""
    prep = flight(150.0, seed=5)
    s = prep.segments[0]
    inc = IncrementalResponses(prep.dt_s)
    sizes = []
    for k in range(0, s.inputs.shape[0], 500):
        inc.add(s.inputs[k:k + 500], s.outputs_raw[k:k + 500])
        sizes.append(sum(x.nbytes for ws in inc.windows for _, x in ws._sums.values())
                     + sum(ws._tail.nbytes for ws in inc.windows))
    assert max(sizes[4:]) <= sizes[4]      # after the longest window first completes, memory stays flat
