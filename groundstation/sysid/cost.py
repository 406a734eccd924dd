"""Windows cut from prepared segments and the vectorised identification cost over free parameters.

``make_windows`` cuts non-overlapping windows of ``window_s`` from every segment (tails shorter than
a window are dropped). :class:`WindowedCost` maps a batch of free-parameter vectors ``(C, D)`` onto
full 31-parameter vectors (fixed parameters keep their value), simulates all windows
(:class:`~groundstation.sysid.simulate.WindowSimulator`) and returns the paper's eq. 11 cost (C,),
counting evaluations; candidates are simulated in batches of bounded memory, so the cost of a
colony grows with the windows and nothing else. ``residuals`` gives the per-channel normalised residual vector used by the
local refinement. Which parameters are free is decided in :mod:`groundstation.sysid.identify`.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any

import numpy as np

from groundstation.errors import SysidError
from groundstation.sysid.model import N_PARAMS, PARAM_INDEX
from groundstation.sysid.simulate import WindowSimulator, objective_from_sse

#: B-matrix parameters: name -> (subsystem, state, input within the subsystem). N_ped is not here:
#: it is also in A (N_fb = -N_ped), so the output is not linear in it.
LINEAR_B: dict[str, tuple[int, int, int]] = {
    "X_lat": (0, 0, 0), "Y_lon": (0, 1, 1), "M_lat": (0, 4, 0), "M_lon": (0, 4, 1),
    "L_lat": (0, 5, 0), "L_lon": (0, 5, 1), "A_lat": (0, 6, 0), "B_lon": (0, 7, 1),
    "Z_col": (1, 0, 0), "Z_ped": (1, 0, 1), "N_col": (1, 1, 0),
}

#: simulator work memory per batch of candidates (see :attr:`WindowedCost.chunk`)
CANDIDATE_CHUNK_BYTES = 64e6


@dataclass(frozen=True, eq=False)
class Windows:
    """inputs (W, L, 4), outputs (W, L, 8), available (W, 8), segment (W,) index, t0_s (W,) start time;
    measured (W, L, 8) bool, False in holes of the link (None: every sample measured)."""

    inputs: np.ndarray
    outputs: np.ndarray
    available: np.ndarray
    segment: np.ndarray
    t0_s: np.ndarray
    dt_s: float
    measured: np.ndarray | None = None

    @property
    def count(self) -> int:
        return int(self.inputs.shape[0])

    @property
    def length(self) -> int:
        return int(self.inputs.shape[1])


def make_windows(segments: list, dt_s: float, window_s: float, *, raw: bool = False,
                 key: str = "window_s", step_s: float = 0.0) -> Windows:
    """Windows of ``round(window_s / dt_s)`` samples from each segment, one every ``step_s`` seconds
    (0 = every ``window_s``: non-overlapping; shorter steps give overlapping windows, more starting
    points of the same data).

    Raises SysidError (a ValueError) when no segment holds one window; its message names the
    setting ``key`` the window length came from (e.g. ``identify.window_s``) and its value.
    """
    L = int(round(window_s / dt_s))
    if L < 5:
        raise SysidError(f"{key} = {window_s:g}: fewer than 5 samples at dt_s={dt_s:g}")
    S = L if step_s <= 0 else max(1, int(round(step_s / dt_s)))
    ins, outs, av, seg, t0, meas = [], [], [], [], [], []
    holes = any(getattr(s, "measured", None) is not None for s in segments)
    for i, s in enumerate(segments):
        y = s.outputs_raw if raw else s.outputs
        m = s.measured_mask() if holes and hasattr(s, "measured_mask") else None
        for a in range(0, s.n - L + 1, S):
            sl = slice(a, a + L)
            ins.append(s.inputs[sl])
            outs.append(y[sl])
            if holes:
                meas.append(np.ones((L, 8), dtype=bool) if m is None else m[sl])
            av.append(np.asarray(s.available, dtype=bool))
            seg.append(i)
            t0.append(float(s.t_s[a]))
    if not ins:
        longest = max((s.duration_s for s in segments), default=0.0)
        raise SysidError(f"{key} = {window_s:g}: no in-air segment is that long (longest {longest:.1f} s)")
    return Windows(np.stack(ins), np.stack(outs), np.stack(av), np.array(seg), np.array(t0), float(dt_s),
                   np.stack(meas) if holes else None)


def subset_windows(win: Windows, idx: np.ndarray) -> Windows:
    """The windows ``idx`` of ``win``."""
    return Windows(win.inputs[idx], win.outputs[idx], win.available[idx], win.segment[idx], win.t0_s[idx], win.dt_s,
                   None if win.measured is None else win.measured[idx])


class WindowedCost:
    """Vectorised cost over free parameters.

    Parameters
    ----------
    windows : the data windows
    free : (31,) bool, parameters searched
    theta_fixed : (31,) values of the parameters that are not free
    estimate_all_initial, subsystems : see WindowSimulator
    estimate_trim : solve one constant offset per input (the trim) with the initial states (see
        :class:`~groundstation.sysid.simulate.WindowSimulator`; not with ``varpro``)
    forcing : (W, L, 3) known accelerations on u, v, w (see WindowSimulator; not with ``varpro``)
    window_offsets : one constant offset per input in each window (see WindowSimulator; not with
        ``varpro`` or ``estimate_trim``)
    varpro : the free B-matrix parameters (:data:`LINEAR_B`) are not searched but solved by least
        squares inside every evaluation (variable projection); ``x`` then holds only the other free
        parameters and :meth:`complete` returns full vectors with the solved B entries
    """

    def __init__(self, windows: Windows, free: np.ndarray, theta_fixed: np.ndarray, *,
                 estimate_all_initial: bool = False, subsystems: tuple[int, ...] = (0, 1),
                 varpro: bool = False, estimate_trim: bool = False, forcing: np.ndarray | None = None,
                 window_offsets: bool = False) -> None:
        self.windows = windows
        free = np.asarray(free, dtype=bool)
        self.theta_fixed = np.asarray(theta_fixed, dtype=float).copy()
        if free.shape != (N_PARAMS,) or self.theta_fixed.shape != (N_PARAMS,):
            raise SysidError("free and theta_fixed must have 31 entries")
        self.linear_idx: dict[int, list[int]] = {}
        linear: dict[int, tuple[tuple[int, int], ...]] = {}
        self.searched = free.copy()
        if varpro:
            for name, (sub, st, inp) in LINEAR_B.items():
                i = PARAM_INDEX[name]
                if free[i] and sub in subsystems:
                    self.linear_idx.setdefault(sub, []).append(i)
                    linear[sub] = linear.get(sub, ()) + ((st, inp),)
                    self.searched[i] = False
                    self.theta_fixed[i] = 0.0
        self.free = self.searched
        self.sim = WindowSimulator(windows.inputs, windows.outputs, windows.dt_s, windows.available,
                                   estimate_all_initial=estimate_all_initial, subsystems=subsystems, linear=linear,
                                   estimate_trim=estimate_trim, forcing=forcing, measured=windows.measured,
                                   window_offsets=window_offsets)
        self.nfev = 0
        self.used: np.ndarray = np.asarray(self.sim.mask.any(axis=0), dtype=bool)  # (8,) channels in the cost

    def __getstate__(self) -> dict[str, Any]:
        """Pickled for worker processes without the reusable Jacobian array (see refine)."""
        state = dict(self.__dict__)
        state.pop("_jac_buffer", None)
        return state

    @property
    def dim(self) -> int:
        return int(self.free.sum())

    def full(self, x: np.ndarray) -> np.ndarray:
        """Free vectors (C, D) -> full parameter vectors (C, 31)."""
        xx = np.atleast_2d(np.asarray(x, dtype=float))
        th = np.broadcast_to(self.theta_fixed, (xx.shape[0], N_PARAMS)).copy()
        th[:, self.free] = xx
        return th

    @property
    def chunk(self) -> int:
        """Candidates simulated per batch: about :data:`CANDIDATE_CHUNK_BYTES` of the simulator's lifted
        work arrays (~600 bytes per candidate per window sample), so memory stays bounded however
        many windows the data hold and a batch still amortises the per-call overhead."""
        return max(1, int(CANDIDATE_CHUNK_BYTES // (600 * self.sim.W * self.sim.L)))

    def complete(self, x: np.ndarray) -> np.ndarray:
        """Full parameter vectors (C, 31) including the least-squares B entries (varpro)."""
        th = self.full(x)
        if self.linear_idx:
            for c0 in range(0, th.shape[0], self.chunk):
                beta = self.sim.solve_linear(th[c0:c0 + self.chunk])
                for sub, idx in self.linear_idx.items():
                    th[c0:c0 + self.chunk, idx] = beta[sub]
        return th

    def __call__(self, x: np.ndarray) -> np.ndarray:
        th = self.full(x)
        self.nfev += th.shape[0]
        if th.shape[0] <= self.chunk:
            return objective_from_sse(self.sim, th)
        return np.concatenate([objective_from_sse(self.sim, th[c0:c0 + self.chunk])
                               for c0 in range(0, th.shape[0], self.chunk)])

    def simulate(self, x: np.ndarray) -> np.ndarray:
        return self.sim.simulate(self.full(x))

    def residuals(self, x: np.ndarray, sigma: np.ndarray | None = None) -> np.ndarray:
        """Residuals ``(yhat - y) / sigma_ch`` of C candidates, shape (C, W, L, n_used).

        ``sigma`` (8,) per-channel noise scale; default the channel scales of eq. 11.
        """
        th = self.full(x)
        self.nfev += th.shape[0]
        e = self.sim.errors(th)
        s = self.sim.scales if sigma is None else np.asarray(sigma, dtype=float)
        return (e / s[None, None, None, :])[..., self.used]

    def residuals_native(self, x: np.ndarray, sigma: np.ndarray) -> np.ndarray:
        """The residuals of :meth:`residuals` as flat vectors (C, N) in the simulator's own row order
        (:meth:`~groundstation.sysid.simulate.WindowSimulator.residuals_native`; zeros where a channel
        is unused): for the normal equations of the refinement, which do not depend on the order."""
        th = self.full(x)
        self.nfev += th.shape[0]
        return self.sim.residuals_native(th, sigma)

    def native_errors_and_sse(self, x: np.ndarray) -> tuple[dict[int, np.ndarray], np.ndarray]:
        """The simulator's :meth:`~groundstation.sysid.simulate.WindowSimulator.native_errors_and_sse` of
        C candidates: what :meth:`residuals_native` weights, and the per-channel sums of squared errors."""
        th = self.full(x)
        self.nfev += th.shape[0]
        return self.sim.native_errors_and_sse(th)
