"""The plain output-error reference fit: the floor an identification must beat on held-out data.

``fit_reference(prepared, starts=4, seed=0, window_s=5.0)`` fits the same eq.-8 structure (every
parameter the data can move, see :func:`groundstation.sysid.identify.free_mask`) by nothing more
than multi-start least squares (:func:`groundstation.sysid.optimizers.minimize_lsq`) on the
windowed output error: windows of ``window_s`` started from the measured states, unmeasured
initial states by least squares, residuals normalised per channel as in the paper's eq. 11. No
search, no prior, no trims, no stability check: a baseline, not a product.
"""

from __future__ import annotations

from typing import Any

import numpy as np
from threadpoolctl import threadpool_limits

from groundstation.sysid.cost import WindowedCost, make_windows
from groundstation.sysid.fit_section import ModelFit
from groundstation.sysid.identify import free_mask
from groundstation.sysid.model import N_PARAMS, HoverModel, bounds_array, theta_to_dict
from groundstation.sysid.optimizers import minimize_lsq
from groundstation.sysid.refine import _fd_step


def fit_reference(prepared: Any, *, starts: int = 4, seed: int = 0, window_s: float = 5.0,
                  max_nfev: int = 60) -> HoverModel:
    """Plain multi-start least-squares output-error fit (see the module docstring)."""
    free, _ = free_mask(prepared)
    b = bounds_array()[free]
    span = b[:, 1] - b[:, 0]
    with threadpool_limits(1):
        cost = WindowedCost(make_windows(prepared.segments, prepared.dt_s, window_s), free, np.zeros(N_PARAMS))

        def residuals(x: np.ndarray) -> np.ndarray:
            return cost.residuals(x[None])[0].ravel()

        def jac(x: np.ndarray) -> np.ndarray:
            h = _fd_step(x, span)
            h = np.where(x + h > b[:, 1], -h, h)
            R = cost.residuals(np.vstack([x[None], x[None] + np.diag(h)])).reshape(x.size + 1, -1)
            return ((R[1:] - R[0]) / h[:, None]).T

        zero = np.clip(np.zeros(int(free.sum())), b[:, 0], b[:, 1])
        res = minimize_lsq(cost, b, rng=seed, maxiter=max_nfev, residuals=residuals, jac=jac, x0=[zero], starts=starts)
        theta = cost.full(res.x[None])[0]
    return HoverModel(params=theta_to_dict(theta), sample_rate_hz=1.0 / prepared.dt_s,
                      input_trim_pwm=dict(prepared.input_trim_pwm), pwm_per_unit=float(prepared.pwm_per_unit),
                      output_trim=dict(prepared.output_trim),
                      fit=ModelFit.make(algorithm="reference-lsq", cost=float(res.fun), starts=int(starts),
                                        window_s=float(window_s), estimate_all_initial=False))
