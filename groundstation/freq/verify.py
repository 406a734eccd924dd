"""Frequency-domain verification of one hover model against flight data.

``verify(theta, responses, delays_s=None) -> FreqVerification``: the model's responses on the
data's frequencies (zero-order-hold discrete at the data's sample interval, plus the input delays),
then per input-output pair with a response: Tischler's J over its coherent points with pass/fail
(``J <= 200``), the equivalent delay of the data relative to the model from the phase slope, the
frequency bands where model and data differ beyond the 95 % random-error bound; per input the
delay fitted jointly over its pairs; for attitude pairs the ADS-33 bandwidth and phase delay of the
data (coherent points) and of the model; ``J_avg`` over the pairs and ``J_avg <= 100``.

Pairs the data show coherently but the model has no path for (a lateral input moving yaw, say) are
listed as ``unmodelled``, not scored: J of a zero response is infinite and says nothing more.
:meth:`FreqVerification.to_json` is the ``heli-freq-verification/1`` document (``J_avg`` and
``pairs``: ``{input, output, J, coherent_points, delay_s}`` plus the rest). Pure numpy.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any

import numpy as np

from groundstation.freq.cost import J_AVG_GOOD, J_PAIR_ACCEPTABLE, tischler_cost
from groundstation.freq.metrics import (
    Bandwidth,
    DelayEstimate,
    DeviationBand,
    attitude_bandwidth,
    deviation_bands,
    phase_slope_delay,
)
from groundstation.freq.model_response import has_path, model_response
from groundstation.freq.spectra import ResponseSet
from groundstation.sysid.model import INPUTS, OUTPUTS

ATTITUDE_OUTPUTS = ("theta", "phi")


@dataclass(frozen=True)
class PairScore:
    input: str
    output: str
    J: float
    coherent_points: int
    f_lo_hz: float
    f_hi_hz: float
    delay_s: float | None
    delay_std_s: float | None
    deviations: tuple[DeviationBand, ...] = ()

    @property
    def passed(self) -> bool:
        return bool(np.isfinite(self.J) and self.J <= J_PAIR_ACCEPTABLE)


@dataclass(frozen=True, eq=False)
class FreqVerification:
    responses: ResponseSet
    model: np.ndarray  # (n_freq, 8, 4) model responses on the data's frequencies
    pairs: tuple[PairScore, ...]
    no_response: tuple[tuple[str, str, str], ...]  # (input, output, reason)
    unmodelled: tuple[tuple[str, str, int], ...]  # (input, output, coherent points)
    input_delays: dict[str, DelayEstimate]
    bandwidth: dict[tuple[str, str], tuple[Bandwidth, Bandwidth]]  # (data, model)

    @property
    def J_avg(self) -> float | None:
        return float(np.mean([p.J for p in self.pairs])) if self.pairs else None

    @property
    def good(self) -> bool:
        return self.J_avg is not None and bool(np.isfinite(self.J_avg)) and self.J_avg <= J_AVG_GOOD

    def to_json(self) -> dict[str, Any]:
        rs = self.responses
        return {
            "schema": "heli-freq-verification/1",
            "J_avg": _num(self.J_avg),
            "J_avg_good": self.good,
            "guidelines": {"J_avg_good": J_AVG_GOOD, "J_pair_acceptable": J_PAIR_ACCEPTABLE},
            "pairs": [{"input": p.input, "output": p.output, "J": _num(p.J), "coherent_points": p.coherent_points,
                       "delay_s": _num(p.delay_s), "delay_std_s": _num(p.delay_std_s), "pass": p.passed,
                       "band_hz": [p.f_lo_hz, p.f_hi_hz],
                       "deviations": [_band(b) for b in p.deviations]} for p in self.pairs],
            "no_response": [{"input": i, "output": o, "reason": r} for i, o, r in self.no_response],
            "unmodelled": [{"input": i, "output": o, "coherent_points": n} for i, o, n in self.unmodelled],
            "input_delays": {k: {"delay_s": d.delay_s, "std_s": d.std_s, "points": d.points}
                             for k, d in self.input_delays.items()},
            "bandwidth": [{"input": i, "output": o, "data": _bw(d), "model": _bw(m)}
                          for (i, o), (d, m) in self.bandwidth.items()],
            "frequency_hz": [float(rs.f_hz[0]), float(rs.f_hz[-1])],
            "n_freq": int(rs.f_hz.size),
            "sample_interval_s": rs.dt_s,
            "windows_s": list(rs.windows_s),
            "coherence_min": rs.config.coherence_min,
            "conditioned_on": list(rs.conditioned_on),
            "notes": list(rs.notes),
        }


def _num(x: float | None) -> float | None:
    return None if x is None or not np.isfinite(x) else float(x)


def _band(b: DeviationBand) -> dict[str, float]:
    return {"f_lo_hz": b.f_lo_hz, "f_hi_hz": b.f_hi_hz, "points": b.points, "magnitude_db": b.magnitude_db,
            "phase_deg": b.phase_deg, "max_ratio": b.max_ratio}


def _bw(b: Bandwidth) -> dict[str, Any]:
    return {"bandwidth_hz": b.bandwidth_hz, "phase_bandwidth_hz": b.phase_bandwidth_hz,
            "gain_bandwidth_hz": b.gain_bandwidth_hz, "f180_hz": b.f180_hz, "phase_delay_s": b.phase_delay_s,
            "note": b.note}


def verify(theta: np.ndarray, responses: ResponseSet, delays_s: np.ndarray | None = None) -> FreqVerification:
    """Score the model ``theta (31,)`` (with input ``delays_s (4,)``) on ``responses``."""
    rs = responses
    G = model_response(np.asarray(theta, float), rs.f_hz, dt_s=rs.dt_s, delays_s=delays_s)
    pairs, no_resp, unmod = [], [], []
    joint: dict[str, list[tuple[np.ndarray, ...]]] = {}
    bw: dict[tuple[str, str], tuple[Bandwidth, Bandwidth]] = {}
    for p in rs.pairs:
        if not p.has_response:
            no_resp.append((p.input, p.output, p.reason))
            continue
        if not has_path(p.input, p.output):
            unmod.append((p.input, p.output, p.coherent_points))
            continue
        g = G[:, OUTPUTS.index(p.output), INPUTS.index(p.input)]
        m = p.coherent
        J = float(tischler_cost(g, p.response, p.coherence, m))
        d = phase_slope_delay(rs.f_hz, p.response, g, p.random_error, m)
        f_c = rs.f_hz[m]
        pairs.append(PairScore(p.input, p.output, J, p.coherent_points, float(f_c.min()), float(f_c.max()),
                               None if d is None else d.delay_s, None if d is None else d.std_s,
                               tuple(deviation_bands(rs.f_hz, p.response, g, p.random_error, m))))
        joint.setdefault(p.input, []).append((rs.f_hz[m], p.response[m], g[m], p.random_error[m]))
        if p.output in ATTITUDE_OUTPUTS:
            fine = np.geomspace(rs.f_hz[0], rs.f_hz[-1], 400)
            gm = model_response(np.asarray(theta, float), fine, dt_s=rs.dt_s, delays_s=delays_s)
            bw[(p.input, p.output)] = (attitude_bandwidth(rs.f_hz, p.response, m),
                                       attitude_bandwidth(fine, gm[:, OUTPUTS.index(p.output), INPUTS.index(p.input)]))
    delays = {}
    for inp, parts in joint.items():
        f, data, ref, eps = (np.concatenate([q[k] for q in parts]) for k in range(4))
        d = phase_slope_delay(f, data, ref, eps, np.ones(f.size, bool))
        if d is not None:
            delays[inp] = d
    return FreqVerification(rs, G, tuple(pairs), tuple(no_resp), tuple(unmod), delays, bw)


def freq_pairs(v: Any) -> list[dict[str, Any]]:
    """The pairs of a :class:`FreqVerification` as :meth:`groundstation.sinks.rerun_sink.RerunSink.log_frequency_response`
    takes them (data, model and coherence per scored input-output pair); ``[]`` for anything else."""
    if v is None or not hasattr(v, "responses") or not hasattr(v, "pairs"):
        return []
    scored = {(s.input, s.output) for s in v.pairs}
    return [{"input": p.input, "output": p.output, "f_hz": p.f_hz, "data": p.response, "coherence": p.coherence,
             "model": v.model[:, OUTPUTS.index(p.output), INPUTS.index(p.input)]}
            for p in v.responses.with_response if (p.input, p.output) in scored]
