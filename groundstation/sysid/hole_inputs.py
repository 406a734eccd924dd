"""The inputs inside the holes of a lossy link, estimated from the outputs around them.

Data preparation bridges a hole of the input stream with a straight line. The line is wrong by what the
input did inside the hole, the model integrates that error, and the parameters are pulled to explain it
(errors in the variables). But the outputs after a hole carry what the input did: for the linear hover
model they are linear in the input samples. So, given a model, each hole's input is re-estimated by
least squares from the measured outputs around it (the errors-in-variables treatment of Klein & Morelli's
*Aircraft System Identification*, with the missing inputs as nuisance parameters):

* the correction to the line is a sum of ``K`` half-sine shapes ``sin(k pi s)``, ``s`` from 0 to 1
  over the hole (zero at the measured samples on either side: the bridge stays continuous);
  ``K = ceil(2 h f_b)`` for a hole of ``h`` s, the number of shapes a band of ``f_b`` Hz fits in the
  hole. ``f_b`` is ``band_factor`` times the rotor's corner frequency ``(1/tau_s) / 2 pi`` of the
  model: input content far above it barely reaches the outputs, so the outputs neither determine it
  nor does the fit need it;
* per hole and subsystem (lat and lon drive the horizontal states, col and ped the vertical ones)
  the coefficients are solved together with the state at the start of a stretch from
  ``horizon_s`` before the hole to ``horizon_s`` after it and one constant offset per input over
  that stretch (the model's trim may be off there; the offset is not applied to the inputs), over the output
  samples measured there (weighted by each channel's noise: the model file's ``noise_sigma``);
* a prior keeps what the outputs do not determine near the line: each coefficient has zero mean and
  the variance of a straight line's error over holes of that length, measured on the segment's own
  stretches without holes (:func:`line_error_var`);
* holes are visited in time order, each with the others' inputs as estimated so far, ``sweeps`` times;
* only the inputs of ``subsystems`` are estimated (0 horizontal: lat, lon; 1 vertical: col, ped), the
  others keep the line.

Standard errors: the inputs in the holes were estimated from the same outputs as the parameters, so
the parameters' uncertainty includes theirs. :class:`WindowHoles` gives the refinement's standard
errors the Jacobian of the residuals with the hole-input coefficients projected out (their own
responses, through each window's initial-state least squares, with the same prior): the parameters
get only the information the outputs hold beyond what the estimated inputs explain.

The input samples in holes stay marked as bridged (``inputs_bridged``) and the output samples there
stay uncounted: only the values the windows are driven with change. Pure numpy; which model to use and
when to refit is :mod:`groundstation.sysid.identify`'s.
"""

from __future__ import annotations

from dataclasses import dataclass, replace
from typing import Any

import numpy as np

from groundstation.sysid.model import PARAM_INDEX, build_matrices, discretize
from groundstation.sysid.settings import IdentifyConfig
from groundstation.sysid.simulate import WindowSimulator, kinematic_forcing

__all__ = ["WindowHoles", "basis_count", "estimate_hole_inputs", "hole_runs", "window_holes"]

# (states, inputs, (state, output column) measured, (state, forcing column)) per subsystem, as the simulator's
_SUBS = ((8, (0, 1), ((0, 0), (1, 1), (5, 3), (4, 4), (2, 6), (3, 7)), ((0, 0), (1, 1))),
         (3, (2, 3), ((0, 2), (1, 5)), ((0, 2),)))
OUTPUTS = ("u", "v", "w", "p", "q", "r", "theta", "phi")


def hole_runs(bridged: np.ndarray) -> list[tuple[int, int]]:
    """Contiguous runs ``[a, b)`` of True in ``bridged (n,)``."""
    b = np.concatenate([[False], np.asarray(bridged, dtype=bool), [False]])
    d = np.diff(b.astype(int))
    return list(zip(np.flatnonzero(d == 1).tolist(), np.flatnonzero(d == -1).tolist(), strict=True))


def basis_count(n_hole: int, dt_s: float, band_hz: float) -> int:
    """Half-sine shapes over a hole of ``n_hole`` samples: ``ceil(2 h band_hz)``, at least 1, at most ``n_hole``."""
    h = (n_hole + 1) * dt_s
    return int(min(n_hole, max(1, np.ceil(2.0 * h * band_hz - 1e-9))))


def _basis(n_hole: int, k: int) -> np.ndarray:
    """(n_hole, k) half-sine shapes, zero at the measured samples on either side of the hole."""
    s = np.arange(1, n_hole + 1) / (n_hole + 1)
    return np.sin(np.pi * np.outer(s, np.arange(1, k + 1)))


def _system(theta: np.ndarray, sub: int, dt_s: float, forced: bool) -> tuple[np.ndarray, np.ndarray]:
    """Discrete (Ad, Bd) of a subsystem; Bd has unit forcing columns after the inputs when ``forced``."""
    Ah, Bh, Av, Bv = build_matrices(theta)
    A, B = (Ah, Bh) if sub == 0 else (Av, Bv)
    if forced:
        E = np.zeros((A.shape[0], len(_SUBS[sub][3])))
        for c, (st, _) in enumerate(_SUBS[sub][3]):
            E[st, c] = 1.0
        B = np.concatenate([B, E], axis=1)
    return discretize(A, B, dt_s)


def _responses(Ad: np.ndarray, Bd: np.ndarray, U: np.ndarray, s_idx: np.ndarray) -> np.ndarray:
    """Measured-state responses (L, nch, c) of ``c`` columns: the first ``n`` from unit initial states
    with no input, the rest from rest driven by ``U (L, m, c - n)``."""
    n = Ad.shape[0]
    L, _, cu = U.shape
    X = np.zeros((n, n + cu))
    X[:, :n] = np.eye(n)
    out = np.empty((L, s_idx.size, n + cu))
    for k in range(L):
        out[k] = X[s_idx]
        X = Ad @ X
        X[:, n:] += Bd @ U[k]
    return out


def _solve_hole(seg_u: np.ndarray, y: np.ndarray, meas: np.ndarray, forcing: np.ndarray | None, a: int, b: int,
                sys: tuple[np.ndarray, np.ndarray], sub: int, w_ch: np.ndarray, k: int, prior_var: np.ndarray,
                pad: int) -> np.ndarray | None:
    """Correction (b - a, inputs of ``sub``) to the inputs of the hole ``[a, b)`` (see the module
    docstring); None (the line stays) when no output is measured after the hole or the model's
    responses over the stretch are not finite."""
    n_states, inputs, meas_map, forced = _SUBS[sub]
    Ad, Bd = sys
    s0, e = max(0, a - pad), min(seg_u.shape[0], b + pad)
    s_idx = np.array([s for s, _ in meas_map])
    o_idx = np.array([o for _, o in meas_map])
    m = meas[s0:e][:, o_idx] & (w_ch > 0)[None, :]
    if not m[b - s0:].any():
        return None
    drive = seg_u[s0:e][:, list(inputs)]
    if forcing is not None:
        drive = np.concatenate([drive, forcing[s0:e][:, [c for _, c in forced]]], axis=1)
    mi = len(inputs)
    shapes = _basis(b - a, k)
    L = e - s0
    U = np.zeros((L, drive.shape[1], 1 + mi * k + mi))
    U[:, :, 0] = drive
    for i in range(mi):
        U[a - s0:b - s0, i, 1 + i * k:1 + (i + 1) * k] = shapes
        U[:, i, 1 + mi * k + i] = 1.0                        # the stretch's own input offset (a nuisance)
    R = _responses(Ad, Bd, U, s_idx)                        # (L, nch, n + 1 + mi k + mi)
    sw = np.sqrt(w_ch)[None, :] * m                          # (L, nch) row weights, zero where not measured
    A = (R * sw[..., None]).reshape(L * o_idx.size, -1)
    r = ((np.nan_to_num(y[s0:e][:, o_idx]) - R[:, :, n_states]) * sw).reshape(-1)
    A = np.delete(A, n_states, axis=1)                       # the drive's own response is on the right
    G = A.T @ A
    d = np.diag(G)[:n_states]
    G[np.arange(n_states), np.arange(n_states)] += 1e-6 * max(float(d.max()), 1e-300)
    prior = np.concatenate([np.repeat(1.0 / np.maximum(prior_var, 1e-12), k), np.zeros(mi)])
    G[n_states:, n_states:] += np.diag(prior)
    d = np.diag(G)
    G[np.arange(d.size), np.arange(d.size)] += 1e-9 * max(float(d.max()), 1e-300)
    rhs = A.T @ r
    if not (np.isfinite(G).all() and np.isfinite(rhs).all()):
        return None                                          # a model that runs away over the stretch: keep the line
    try:
        c = np.linalg.solve(G, rhs)[n_states:n_states + mi * k].reshape(mi, k)
    except np.linalg.LinAlgError:
        return None
    return shapes @ c.T


def line_error_var(u: np.ndarray, bridged: np.ndarray, n_hole: int, default: Any = "ones") -> Any:
    """(inputs,) mean square error of a straight line over ``n_hole`` samples, measured on the stretches of
    ``u (n, inputs)`` without a bridged sample (every start, the line between the samples on either side);
    ones (or ``default``, when given) when the segment has no such stretch."""
    n = u.shape[0]
    span = n_hole + 1
    none = np.ones(u.shape[1]) if isinstance(default, str) else default
    if n <= span:
        return none
    br = np.concatenate([[0], np.cumsum(np.asarray(bridged, dtype=int))])
    starts = np.flatnonzero(br[span + 1:] - br[:n - span] == 0)          # u[i .. i + span] all measured
    if starts.size == 0:
        return none
    s = np.arange(1, span) / span
    mid = u[starts[:, None] + np.arange(1, span)[None, :]]               # (S, n_hole, inputs)
    line = u[starts][:, None] * (1 - s)[None, :, None] + u[starts + span][:, None] * s[None, :, None]
    return np.mean((mid - line) ** 2, axis=(0, 1))


def line_shape_var(u: np.ndarray, bridged: np.ndarray, n_hole: int) -> np.ndarray | None:
    """(n_hole, inputs) mean square of a straight line's error over ``n_hole`` samples in each half-sine
    shape ``sin(k pi s)`` (k = 1 .. n_hole: a complete basis of the hole's samples), measured as
    :func:`line_error_var` on the stretches of ``u (n, inputs)`` without a bridged sample; None when
    there is no such stretch. Their sum over the shapes is ``2 n_hole / (n_hole + 1)`` times the
    line's mean square error."""
    n = u.shape[0]
    span = n_hole + 1
    if n <= span:
        return None
    br = np.concatenate([[0], np.cumsum(np.asarray(bridged, dtype=int))])
    starts = np.flatnonzero(br[span + 1:] - br[:n - span] == 0)
    if starts.size == 0:
        return None
    s = np.arange(1, span) / span
    mid = u[starts[:, None] + np.arange(1, span)[None, :]]
    line = u[starts][:, None] * (1 - s)[None, :, None] + u[starts + span][:, None] * s[None, :, None]
    c = np.einsum("snj,nk->skj", mid - line, _basis(n_hole, n_hole)) * (2.0 / span)   # the shapes are orthogonal
    return np.mean(c ** 2, axis=0)


def _shape_var(cache: dict, u: np.ndarray, bridged: np.ndarray, a: int, b: int, local_n: int) -> np.ndarray:
    """(b - a, inputs) :func:`line_shape_var` of the hole ``[a, b)``, over ``local_n`` samples either side
    of it (the segment's when that stretch has none without a bridged sample; zeros when neither has)."""
    key = ("shapes", b - a, a if local_n else 0)
    if key not in cache:
        v = None
        if local_n:
            lo, hi = max(0, a - local_n), min(bridged.size, b + local_n)
            v = line_shape_var(u[lo:hi], bridged[lo:hi], b - a)
        if v is None:
            v = line_shape_var(u, bridged, b - a)
        cache[key] = np.zeros((b - a, u.shape[1])) if v is None else v
    return cache[key]


def _prior_var(cache: dict, u: np.ndarray, bridged: np.ndarray, a: int, b: int, local_n: int) -> np.ndarray:
    """(inputs,) prior variance of the coefficients of the hole ``[a, b)``: :func:`line_error_var` over
    the segment (``local_n`` 0), else over ``local_n`` samples either side of the hole (the segment's
    when that stretch has none without a bridged sample); cached in ``cache``."""
    key = (b - a, a if local_n else 0)
    if key not in cache:
        v = None
        if local_n:
            lo, hi = max(0, a - local_n), min(bridged.size, b + local_n)
            v = line_error_var(u[lo:hi], bridged[lo:hi], b - a, default=None)
        cache[key] = line_error_var(u, bridged, b - a) if v is None else v
    return cache[key]


def _channel_weights(model: Any, seg: Any) -> np.ndarray:
    """(8,) least-squares weights 1 / sigma^2 from the model's noise estimate (else the segment's spread)."""
    ns = dict(getattr(model.fit, "noise_sigma", {}) or {})
    y = seg.outputs
    w = np.zeros(8)
    for j, ch in enumerate(OUTPUTS):
        s = ns.get(ch)
        if s is None or not np.isfinite(s) or s <= 0:
            s = float(np.nanstd(y[:, j])) if np.isfinite(y[:, j]).any() else 0.0
        w[j] = 1.0 / s ** 2 if s > 0 and seg.available[j] else 0.0
    return w


def estimate_hole_inputs(prepared: Any, model: Any, *, horizon_s: float = IdentifyConfig.hole_input_horizon_s,
                         band_factor: float = IdentifyConfig.hole_input_band, sweeps: int = 2, forcing_channels: tuple[str, ...] = (),
                         subsystems: tuple[int, ...] = (0, 1), prior_s: float = IdentifyConfig.hole_input_prior_s) -> Any:
    """``prepared`` with the inputs in its bridged holes estimated with ``model`` (see the module
    docstring); segments without bridged inputs are returned as they are. ``forcing_channels``: the
    velocity channels whose measured kinematic terms drive the model (``identify.kinematic_forcing``)."""
    theta = model.theta
    dt = float(prepared.dt_s)
    band_hz = band_factor * abs(float(model.params["inv_tau_s"])) / (2.0 * np.pi)
    offset = _input_offset(model, prepared)
    systems = {sub: _system(theta, sub, dt, bool(forcing_channels)) for sub in (0, 1)}
    pad = max(1, int(round(horizon_s / dt)))
    local_n = int(round(prior_s / dt))
    trim = np.array([float(prepared.output_trim.get(c, 0.0)) for c in OUTPUTS])
    segs = []
    holes = 0
    for seg in prepared.segments:
        br = getattr(seg, "inputs_bridged", None)
        runs = hole_runs(br) if br is not None else []
        if not runs:
            segs.append(seg)
            continue
        br = np.asarray(br, dtype=bool)
        u = seg.inputs + offset[None, :]
        forcing = None
        if forcing_channels:
            forcing = kinematic_forcing(seg.outputs, trim)
            forcing[:, [j for j, c in enumerate(("u", "v", "w")) if c not in forcing_channels]] = 0.0
        holes += len(runs)
        meas = seg.measured_mask()
        w_ch = _channel_weights(model, seg)
        var: dict[tuple[int, int], np.ndarray] = {}
        for _ in range(max(1, sweeps)):
            for a, b in runs:
                k = basis_count(b - a, dt, band_hz)
                v = _prior_var(var, seg.inputs, br, a, b, local_n)
                for sub in subsystems:
                    ins = list(_SUBS[sub][1])
                    o_idx = [o for _, o in _SUBS[sub][2]]
                    dc = _solve_hole(u, seg.outputs, meas, forcing, a, b, systems[sub], sub, w_ch[o_idx], k,
                                     v[ins], pad)
                    if dc is not None:
                        u[a:b, ins] += dc
        segs.append(replace(seg, inputs=u - offset[None, :]))
    lq = dict(getattr(prepared, "link_quality", {}) or {})
    lq["inputs_in_holes"] = {"estimated_holes": holes, "band_hz": round(band_hz, 3), "horizon_s": horizon_s}
    return replace(prepared, segments=segs, link_quality=lq)


def _input_offset(model: Any, prepared: Any) -> np.ndarray:
    """(4,) offset that expresses ``prepared``'s inputs against the model's (estimated) trims."""
    ppu = float(prepared.pwm_per_unit)
    return np.array([(float(v) - float(model.input_trim_pwm.get(k, v))) / ppu
                     for k, v in prepared.input_trim_pwm.items()])


@dataclass(frozen=True, eq=False)
class WindowHoles:
    """The bridged holes of the identification windows: row ``h`` is the part of hole ``hole[h]`` in
    window ``window[h]``, from sample ``a[h]`` to ``b[h]`` (window-relative; a hole cut by the window's
    edge reaches beyond it), with ``var[h]`` (4,) the prior variance of its coefficients per input
    (:func:`line_error_var`); ``runs[i]`` is hole ``i`` as ``(segment, a, b)`` in its segment. A hole
    in two windows (cut by their edge, or where windows overlap) has one set of coefficients."""

    window: np.ndarray
    a: np.ndarray
    b: np.ndarray
    var: np.ndarray
    band_factor: float = 1.0
    subsystems: tuple[int, ...] = (0, 1)
    hole: np.ndarray | None = None
    runs: tuple[tuple[int, int, int], ...] = ()
    #: per row (b - a, 4): the straight line's error's mean square in each shape (:func:`line_shape_var`),
    #: for the holes whose inputs keep the line (:meth:`line_covariance`); None when not measured
    shape_var: tuple[np.ndarray, ...] | None = None

    def columns(self, theta: np.ndarray, inputs: tuple[int, ...], L: int, dt_s: float
                ) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
        """(window (q,), input sequences (q, L, 4), prior precision (G,), coefficient (q,)) of every
        row's part of every coefficient; coefficients are numbered ``0 .. G - 1`` in the order of
        :meth:`coefficients`."""
        band = self.band_factor * abs(float(theta[PARAM_INDEX["inv_tau_s"]])) / (2.0 * np.pi)
        keys = self.coefficients(theta, inputs, dt_s)
        index = {key: g for g, key in enumerate(keys)}
        hole = np.arange(self.window.size) if self.hole is None else self.hole
        win, seqs, coef = [], [], []
        for w, a, b, hid in zip(self.window, self.a, self.b, hole, strict=True):
            k = basis_count(int(b - a), dt_s, band)
            lo, hi = max(0, int(a)), min(L, int(b))
            part = _basis(int(b - a), k)[lo - a:hi - a]
            for i in inputs:
                for j in range(k):
                    u = np.zeros((L, 4))
                    u[lo:hi, i] = part[:, j]
                    win.append(w)
                    seqs.append(u)
                    coef.append(index[(int(hid), i, j)])
        prec = np.array([1.0 / max(float(self._var_of(h)[i]), 1e-12) for h, i, _ in keys])
        return (np.array(win, dtype=int), np.array(seqs).reshape(-1, L, 4), prec, np.array(coef, dtype=int))

    def coefficients(self, theta: np.ndarray, inputs: tuple[int, ...], dt_s: float) -> list[tuple[int, int, int]]:
        """(hole, input, shape) of every coefficient, holes in order of first appearance."""
        band = self.band_factor * abs(float(theta[PARAM_INDEX["inv_tau_s"]])) / (2.0 * np.pi)
        hole = np.arange(self.window.size) if self.hole is None else self.hole
        keys: list[tuple[int, int, int]] = []
        seen: set[int] = set()
        for a, b, hid in zip(self.a, self.b, hole, strict=True):
            if int(hid) in seen:
                continue
            seen.add(int(hid))
            keys += [(int(hid), i, j) for i in inputs for j in range(basis_count(int(b - a), dt_s, band))]
        return keys

    def _var_of(self, hid: int) -> np.ndarray:
        hole = np.arange(self.window.size) if self.hole is None else self.hole
        return self.var[int(np.flatnonzero(hole == hid)[0])]

    def _inputs(self, cost: Any) -> tuple[int, ...]:
        return tuple(i for sub in cost.sim.subsystems if sub in self.subsystems for i in _SUBS[sub][1])

    def responses(self, cost: Any, x: np.ndarray, sigma: np.ndarray
                  ) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray, list] | None:
        """(window (q,), coefficient (q,), weighted residual responses (q, L n_used), prior precision
        (G,), coefficient keys) of the hole-input coefficients in ``cost``'s windows at ``x``: each row
        the response of its window's part of one coefficient, through the window's initial-state least
        squares (exact: the outputs are linear in the inputs); None without any, or when the responses
        are not finite (a model that runs away)."""
        sim, win = cost.sim, cost.windows
        theta = cost.full(np.asarray(x, dtype=float)[None])[0]
        inputs = self._inputs(cost)
        if not inputs:
            return None
        w_idx, U, prec, coef = self.columns(theta, inputs, sim.L, sim.dt_s)
        if w_idx.size == 0:
            return None
        meas = None if win.measured is None else win.measured[w_idx]
        kw = dict(estimate_all_initial=sim.estimate_all_initial, subsystems=sim.subsystems, measured=meas,
                  scales=sim.scales, window_offsets=sim.window_offsets)
        y, av = win.outputs[w_idx], win.available[w_idx]
        e1 = WindowSimulator(U, y, sim.dt_s, av, **kw).errors(theta[None])[0]
        e0 = WindowSimulator(np.zeros_like(U), y, sim.dt_s, av, **kw).errors(theta[None])[0]
        Jc = ((e1 - e0) / np.asarray(sigma, dtype=float)[None, None, :])[..., cost.used].reshape(w_idx.size, -1)
        if not np.isfinite(Jc).all():
            return None
        return w_idx, coef, Jc, prec, self.coefficients(theta, inputs, sim.dt_s)

    @staticmethod
    def _normal(w_idx: np.ndarray, coef: np.ndarray, Jc: np.ndarray, prec: np.ndarray,
                per_window: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """``(Jc^T Jc + P (G, G), Jc^T V (G, ...))`` with ``V`` the window blocks ``per_window`` (W, L n_used, ...)."""
        G = prec.size
        N = np.diag(prec).astype(float)
        rhs = np.zeros((G,) + per_window.shape[2:])
        for w in np.unique(w_idx):
            sel = np.flatnonzero(w_idx == w)
            C = Jc[sel]
            np.add.at(N, (coef[sel][:, None], coef[sel][None, :]), C @ C.T)
            np.add.at(rhs, coef[sel], np.tensordot(C, per_window[w], axes=(1, 0)))
        return N, rhs

    def solve(self, cost: Any, x: np.ndarray, sigma: np.ndarray) -> dict[tuple[int, int], np.ndarray]:
        """The hole-input coefficients that minimise ``cost``'s weighted output error at ``x`` (channel
        scales ``sigma`` (8,)) plus the prior ``c^T P c``, the inputs of ``cost``'s windows being the
        straight lines: one linear solve. Returns ``{(hole, input): (k,) coefficients}`` (empty when
        there is nothing to solve)."""
        got = self.responses(cost, x, sigma)
        if got is None:
            return {}
        w_idx, coef, Jc, prec, keys = got
        r = cost.residuals(np.asarray(x, dtype=float)[None], sigma)[0].reshape(cost.sim.W, -1)
        N, g = self._normal(w_idx, coef, Jc, prec, r)
        try:
            c = -np.linalg.solve(N, g)
        except np.linalg.LinAlgError:
            return {}
        out: dict[tuple[int, int], list[float]] = {}
        for (h, i, _), v in zip(keys, c, strict=True):
            out.setdefault((h, i), []).append(float(v))
        return {key: np.array(v) for key, v in out.items()}

    def fill(self, segments: list, coeffs: dict[tuple[int, int], np.ndarray]) -> list:
        """``segments`` with each hole's inputs the straight line plus its shapes times ``coeffs``
        (:meth:`solve`); segments without a solved hole are returned as they are."""
        new = {}
        for (h, i), c in coeffs.items():
            si, a, b = self.runs[h]
            if si not in new:
                new[si] = np.array(segments[si].inputs, dtype=float)
            new[si][a:b, i] += _basis(b - a, c.size) @ c
        return [replace(s, inputs=new[j]) if j in new else s for j, s in enumerate(segments)]

    def line_covariance(self, cost: Any, x: np.ndarray, sigma: np.ndarray, J: np.ndarray,
                        Hinv: np.ndarray) -> np.ndarray | None:
        """(D, D) the parameters' covariance from the straight lines' errors in the holes: each hole's
        input error is its shapes times coefficients of zero mean and the variance measured on the
        received inputs around it (``shape_var``), it moves the residuals by their responses ``Jc``
        (through each window's initial-state least squares), and the fit passes that on:
        ``Hinv B^T diag(var) B Hinv`` with ``B = Jc^T J`` (``J`` (W L n_used, D) the Jacobian of
        ``cost``'s weighted residuals at ``x``, ``Hinv`` the inverse of its ``J^T J``). None without any."""
        if self.shape_var is None:
            return None
        got = self.responses(cost, x, sigma)
        if got is None:
            return None
        w_idx, coef, Jc, _, keys = got
        var = np.array([float(self.shape_var[self._row_of(h)][j, i]) for h, i, j in keys])
        Jw = np.asarray(J, dtype=float).reshape(cost.sim.W, -1, J.shape[1])
        B = np.zeros((var.size, J.shape[1]))
        for q in range(w_idx.size):
            B[coef[q]] += Jc[q] @ Jw[w_idx[q]]
        C = Hinv @ (B.T * var) @ B @ Hinv
        return 0.5 * (C + C.T)

    def _row_of(self, hid: int) -> int:
        hole = np.arange(self.window.size) if self.hole is None else self.hole
        return int(np.flatnonzero(hole == hid)[0])

    def marginal_jacobian(self, cost: Any, x: np.ndarray, sigma: np.ndarray, J: np.ndarray) -> np.ndarray:
        """``J`` (W L n_used, D), the Jacobian of ``cost``'s weighted residuals at ``x`` (channel scales
        ``sigma`` (8,)), with the hole-input coefficients projected out:
        ``J - Jc (Jc^T Jc + P)^-1 Jc^T J`` (``Jc`` their residual responses, ``P`` their prior precision)."""
        got = self.responses(cost, x, sigma)
        if got is None:
            return J
        w_idx, coef, Jc, prec, _ = got
        out = np.array(J, dtype=float).reshape(cost.sim.W, -1, J.shape[1])
        N, JcJ = self._normal(w_idx, coef, Jc, prec, out)
        D = np.linalg.solve(N, JcJ)                                      # (G, D)
        for q in range(w_idx.size):
            out[w_idx[q]] -= np.outer(Jc[q], D[coef[q]])
        return out.reshape(J.shape)


def window_holes(segments: list, win: Any, band_factor: float = IdentifyConfig.hole_input_band,
                 subsystems: tuple[int, ...] = (0, 1), local_s: float = IdentifyConfig.hole_input_prior_s,
                 shapes: bool = False) -> WindowHoles | None:
    """Where the bridged holes of ``segments`` lie in the windows ``win``
    (:class:`~groundstation.sysid.cost.Windows` cut from them); None without any. ``shapes``: also
    measure each hole's line error per shape (``WindowHoles.shape_var``, over ``local_s`` either side)."""
    L = win.length
    local_n = int(round(local_s / win.dt_s))
    rows: list[tuple[int, int, int, np.ndarray, int]] = []
    svar: list[np.ndarray] = []
    cache: dict[int, tuple[list[tuple[int, int]], dict[tuple[int, int], np.ndarray]]] = {}
    ids: dict[tuple[int, int, int], int] = {}
    for w in range(win.count):
        si = int(win.segment[w])
        seg = segments[si]
        br = getattr(seg, "inputs_bridged", None)
        if br is None:
            continue
        if si not in cache:
            cache[si] = (hole_runs(br), {})
        runs, var = cache[si]
        s = int(np.searchsorted(seg.t_s, win.t0_s[w] - 0.25 * win.dt_s))
        for a, b in runs:
            if b > s and a < s + L:
                hid = ids.setdefault((si, a, b), len(ids))
                brb = np.asarray(br, dtype=bool)
                rows.append((w, a - s, b - s, _prior_var(var, seg.inputs, brb, a, b, local_n), hid))
                if shapes:
                    svar.append(_shape_var(var, seg.inputs, brb, a, b, local_n))
    if not rows:
        return None
    w_, a_, b_, v_, h_ = zip(*rows, strict=True)
    return WindowHoles(np.array(w_), np.array(a_), np.array(b_), np.array(v_), float(band_factor), tuple(subsystems),
                       np.array(h_), tuple(ids), tuple(svar) if shapes else None)
