"""``groundstation bench freq [--seeds 3] [--duration-s 150] [--source linear|sim|both] [--skip-identify] [--skip-time]``.

Frequency-domain figures on simulated flights with known truth:

1. the measured responses against the TRUE model's analytic ones: the share of coherent points
   inside their 95 % random-error bound, and the true model's J_avg (per flight, and the median);
2. the CPU time of the whole analysis (composite spectra of every excited pair with the three
   window lengths, the truth's J, delays and bandwidths), median of repeats, BLAS on one thread;
3. a 100 ms transport delay on the lon input after the log: the delay recovered from the phase
   slope of the data against the delay-free truth;
4. frequency-domain identification (CABC on J + refinement, then the output-error step): the 8 key parameters' errors against truth;
   the time-domain fit and the frequency-domain refinement started from it (``identify --domain
   both``: the time fit as warm start, the frequency cost only as refinement); and the same refinement started at the
   truth (the J minimum nearest it): when that minimum is itself off, the responses (not the search)
   put J's minimum there. The summary gives the median and minimum count over the flights. Each
   model is also scored on the next seed's flight (held-out mean match, eq. 19).

Flights: ``linear`` = the eq.-8 model under a state-feedback pilot (:mod:`benchkit.synthetic`;
the delay is a shift of the logged input), ``sim`` = the nonlinear simulator (hil_replay)
(``hil_replay.sim.write_tlog``, read back through the ordinary .tlog reader; the delay is its
``input_delay`` effect).
"""

from __future__ import annotations

import argparse
import json
import tempfile
import time
from pathlib import Path
from typing import Any

import numpy as np
from rich.console import Console
from threadpoolctl import threadpool_limits

from benchkit.synthetic import EXAMPLE_TRUTH, simulate_flight
from firmware_interface.readers import load_log
from groundstation.dsp.prepare import PrepConfig, prepared_from_arrays
from groundstation.freq.identify import FreqIdentifyConfig, identify_frequency
from groundstation.freq.metrics import Z95_COMPLEX
from groundstation.freq.model_response import model_response
from groundstation.freq.spectra import estimate_responses
from groundstation.freq.verify import verify
from groundstation.pipeline import prepare_native
from groundstation.sysid.identify import identify
from groundstation.sysid.model import INPUTS, OUTPUTS, theta_from_dict
from groundstation.sysid.validate import validate
from hil_replay.sim import write_tlog

HELP = "frequency-domain benchmark: responses vs truth, true-model J, delay from phase slope, speed, identification"

KEY = ("M_a", "L_b", "inv_tau_s", "A_lat", "B_lon", "Z_col", "N_ped", "N_r")


def add_arguments(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("--seeds", type=int, default=3, help="flights per source")
    parser.add_argument("--duration-s", type=float, default=150.0)
    parser.add_argument("--source", choices=("linear", "sim", "both"), default="both")
    parser.add_argument("--repeats", type=int, default=5, help="timing repeats")
    parser.add_argument("--skip-identify", action="store_true")
    parser.add_argument("--algorithm", default="cabc")
    parser.add_argument("--weighting", choices=("coherence", "random_error", "output_error"), default=None,
                        help="frequency-domain fit cost (default: the fit's default)")
    parser.add_argument("--skip-time", action="store_true",
                        help="skip the time-domain fit and the frequency refinement warm-started from it")


def _linear(seed: int, duration_s: float, delay_s: float = 0.0) -> tuple[Any, dict[str, float]]:
    dt = 0.02
    d = int(round(delay_s / dt))
    n = int(round(duration_s / dt))
    u, _, ym = simulate_flight(theta_from_dict(EXAMPLE_TRUTH), duration_s + (d + 1) * dt, dt, seed=seed)
    logged = u.copy()
    if d:
        logged[: u.shape[0] - d, 1] = u[d:, 1]  # the aircraft receives lon d samples after the log
    return prepared_from_arrays(logged[:n], ym[:n], dt, source=f"linear seed {seed}"), dict(EXAMPLE_TRUTH)


def _sim(seed: int, duration_s: float, tmp: Path, delay_s: float = 0.0) -> tuple[Any, dict[str, float]]:
    path = tmp / f"sim{seed}_{int(delay_s * 1000)}.tlog"
    effects = (f"input_delay:input=lon,delay_s={delay_s}",) if delay_s else ()
    truth = write_tlog(path, seed=seed, flights=1, effects=effects, aircraft=None, flight_duration_s=duration_s)
    if truth is None:
        truth = json.loads(path.with_suffix(".truth.json").read_text())
    return prepare_native([load_log(path)], PrepConfig()), dict(truth["parameters"])


def _agreement(rs: Any, theta: np.ndarray) -> tuple[float, int]:
    G = model_response(theta, rs.f_hz, dt_s=rs.dt_s)
    inside = total = 0
    for p in rs.with_response:
        g = G[:, OUTPUTS.index(p.output), INPUTS.index(p.input)]
        if not np.any(g != 0):
            continue
        z = np.abs(g - p.response) / (p.random_error * np.abs(p.response))
        inside += int((z[p.coherent] <= Z95_COMPLEX).sum())
        total += p.coherent_points
    return inside / max(total, 1), total


def _timing(prepared: Any, theta: np.ndarray, repeats: int) -> float:
    cpu = []
    with threadpool_limits(1):
        for _ in range(repeats):
            c0 = time.process_time()
            verify(theta, estimate_responses(prepared))
            cpu.append(time.process_time() - c0)
    return float(np.median(cpu))


def _key_errors(params: dict[str, float], truth: dict[str, float]) -> tuple[int, str]:
    err = {k: 100 * (params[k] - truth[k]) / abs(truth[k]) for k in KEY}
    w = max(err, key=lambda k: abs(err[k]))
    return sum(abs(e) <= 10 for e in err.values()), f"{w} {err[w]:+.1f} %"


def _identification(con: Any, args: argparse.Namespace, rs: Any, prep: Any, truth: dict[str, float], seed: int,
                    counts: dict[str, list[int]], heldout: Any = None) -> None:
    """Key-parameter counts of the frequency fit, the time fit, the refinement warm-started from the
    time fit and the refinement from the truth, appended to ``counts`` and printed; with ``heldout``
    (another flight of the same aircraft) each model's mean match on it (eq. 19) too."""
    fc = FreqIdentifyConfig(**({"weighting": args.weighting} if args.weighting else {}))
    fits: list[tuple[str, Any]] = [("frequency-domain identification",
                                    lambda: identify_frequency(rs, prep, algorithm=args.algorithm, seed=seed, config=fc))]
    if not args.skip_time:
        tm: dict[str, Any] = {}
        fits += [("time-domain identification", lambda: tm.setdefault("m", identify(prep, algorithm=args.algorithm,
                                                                                        seed=seed))),
                 ("frequency refinement from the time fit",
                  lambda: identify_frequency(rs, prep, start=tm["m"].theta, config=fc))]
    fits.append(("cost minimum nearest the truth (refined from it)",
                 lambda: identify_frequency(rs, prep, start=theta_from_dict(truth), config=fc)))
    for label, fit in fits:
        m = fit()
        n, worst = _key_errors(m.params, truth)
        counts.setdefault(label, []).append(n)
        ho = "" if heldout is None else f", held-out match on the next flight {validate(m, heldout).mean_match:.1f} %"
        con.print(f"    {label}: {n}/8 key parameters within 10 % (worst {worst}), J_avg {verify(m.theta, rs).J_avg:.1f}{ho}")


def run(args: argparse.Namespace) -> int:
    con = Console()
    sources = ("linear", "sim") if args.source == "both" else (args.source,)
    with tempfile.TemporaryDirectory() as td:
        tmp = Path(td)
        for src in sources:
            con.print(f"[bold]{src} flights[/], {args.duration_s:g} s, seeds 1..{args.seeds}")
            inside, J_true, delays = [], [], []
            counts: dict[str, list[int]] = {}
            for seed in range(1, args.seeds + 1):
                prep, truth = _linear(seed, args.duration_s) if src == "linear" else _sim(seed, args.duration_s, tmp)
                th = theta_from_dict(truth)
                rs = estimate_responses(prep)
                frac, n = _agreement(rs, th)
                v = verify(th, rs)
                inside.append(frac)
                J_true.append(v.J_avg if v.J_avg is not None else np.nan)
                line = (f"  seed {seed}: {1 / rs.dt_s:.0f} Hz, {len(v.pairs)} pairs, {n} coherent points, "
                        f"{100 * frac:.1f} % inside the 95 % bound, true-model J_avg {J_true[-1]:.1f}")
                if seed == 1:
                    line += f", analysis {_timing(prep, th, args.repeats):.2f} s CPU (median of {args.repeats})"
                con.print(line)
                dprep, _ = (_linear(seed, args.duration_s, 0.1) if src == "linear"
                            else _sim(seed, args.duration_s, tmp, 0.1))
                dv = verify(th, estimate_responses(dprep))
                d = dv.input_delays.get("lon")
                delays.append(np.nan if d is None else d.delay_s)
                con.print(f"    100 ms lon delay: {1000 * delays[-1]:.1f} ms from the phase slope")
                if not args.skip_identify:
                    nxt = _linear(seed + 1, args.duration_s) if src == "linear" else _sim(seed + 1, args.duration_s, tmp)
                    _identification(con, args, rs, prep, truth, seed, counts, nxt[0])
            con.print(f"  median: {100 * np.median(inside):.1f} % inside the bound (min {100 * np.min(inside):.1f} %), "
                      f"true-model J_avg {np.nanmedian(J_true):.1f} (max {np.nanmax(J_true):.1f}), "
                      f"delay error {1000 * np.nanmedian(np.abs(np.array(delays) - 0.1)):.1f} ms "
                      f"(max {1000 * np.nanmax(np.abs(np.array(delays) - 0.1)):.1f} ms)")
            for label, ks in counts.items():
                con.print(f"  key parameters within 10 %, {label}: {', '.join(f'{k}/8' for k in ks)} "
                          f"(median {np.median(ks):g}/8, min {min(ks)}/8)")
    return 0
