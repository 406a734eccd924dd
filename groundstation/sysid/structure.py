"""Low-order equivalent systems of a stabilised helicopter: stick commands to rates or attitudes.

When a flybarless unit or an autopilot's rate loop flies the helicopter and the log holds the pilot's
sticks, the inputs are commands to a closed-loop aircraft, not blade angles, and the eq.-8 hover
model (rotor flapping driven by cyclic) is the wrong structure: the controller makes the aircraft
follow the stick. What one identifies from such data is the stabilised aircraft as the pilot sees it,
a low-order equivalent system (LOES) per axis, as flying-qualities work does (MIL-F-8785C and Hoh's
equivalent systems; Tischler & Remple 2012, the chapter on identifying systems in closed loop:
identify command-to-response, the "end-to-end" dynamics, and report bandwidth and delay).

Structure (``kind``), per axis (roll lat->p/phi, pitch lon->q/theta, yaw ped->r, heave col->w):

* ``rate_command``: first order with an equivalent time delay, ``T xdot = -x + sum_j K_j d_j(t - tau)
  + b`` for x = p, q, r, w over every moving input ``d_j``; the fit keeps the inputs the data support
  (estimate beyond ``COUPLING_T`` standard errors) and names the one contributing most (gain times the
  input's spread) the on-axis input, the others are the off-axis couplings (the simulator's paper
  naming has lat driving pitch, a real aircraft's longitudinal stick does: the data say which);
  ``b`` is the rate held for a centred stick, each window's own (the controller's integrator: an
  unmeasured state estimated over the window as the hover model's flapping states are);
* ``attitude_command``: roll and pitch second order, ``phi'' = wn^2 (sum_j K_j d_j(t - tau) + b
  - phi) - 2 zeta wn phi'``; yaw and heave as above;
* attitude kinematics ``phi' = p``, ``theta' = q`` (hover, small angles) and the hover translational
  dynamics ``u' = X_u u - g theta + X_0``, ``v' = Y_v v + g phi + Y_0``.

Identification is output error on windows started from the measured states (the same windows as
the held-out prediction, :mod:`groundstation.sysid.heldout`), each axis on its own (its rate,
attitude and velocity channels, each weighted by the inverse of its signal norm: the residual sum is
then the sum of squared eq.-19 mismatch ratios), the delay by a grid of fixed delays and a free
refinement (:func:`groundstation.sysid.optimizers.minimize_grid_lsq`; the grid runs below zero: a
negative equivalent delay is a command logged late against the response, a time skew between the
logged channels, and is reported as that, not as a dynamic), standard errors from the
Jacobian (Cramér-Rao bound under white residuals: a lower bound on real data).

Reported per axis: gain, time constant (or natural frequency and damping), equivalent delay, the
-3 dB bandwidth of command to rate (for a rate-command axis ``1/T``), the attitude bandwidth of
ADS-33 (frequency of -135 deg phase of command to attitude) and the couplings kept.

Array conventions as :mod:`groundstation.sysid.heldout`: windows ``(W, L, 4)`` inputs and
``(W, L, 8)`` outputs in :data:`groundstation.sysid.model.OUTPUTS` order. Pure numpy/scipy; no IO.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import Any

import numpy as np

from groundstation.errors import SysidError
from groundstation.sysid.model import G_M_S2, INPUTS, OUTPUTS
from groundstation.sysid.optimizers import minimize_grid_lsq
from groundstation.sysid.prediction import Prediction
from groundstation.sysid.settings import IdentifyConfig

#: what the aircraft file's ``[inputs] kind`` may say
KINDS: tuple[str, ...] = ("blade", "rate_command", "attitude_command", "unknown")
#: the command structures fitted here
COMMAND_KINDS: tuple[str, ...] = ("rate_command", "attitude_command")
SCHEMA = "heli-command-response/1"
#: axis -> (rate channel, attitude channel or None, nominal on-axis input, velocity channel or None); the
#: reported on-axis input is the data's (see the module docstring)
AXES: dict[str, tuple[str, str | None, str, str | None]] = {
    "roll": ("p", "phi", "lat", "v"), "pitch": ("q", "theta", "lon", "u"),
    "yaw": ("r", None, "ped", None), "heave": ("w", None, "col", None),
}
#: a coupling is kept when its estimate exceeds this many standard errors
COUPLING_T = 3.0
#: equivalent delays searched, s; a negative one means the logged command lags the response it drives:
#: a time skew between the logged channels (data consistency), reported as such, not a dynamic
MAX_DELAY_S = 0.3
MIN_DELAY_S = -0.25
DELAY_GRID_S = 0.04
BOUNDS: dict[str, tuple[float, float]] = {
    "K": (-30.0, 30.0), "T": (0.02, 5.0), "tau": (MIN_DELAY_S, MAX_DELAY_S), "b": (-3.0, 3.0), "C": (-30.0, 30.0),
    "wn": (0.3, 40.0), "zeta": (0.05, 3.0), "X": (-3.0, 0.5), "X0": (-3.0, 3.0),
}


@dataclass(frozen=True)
class _Axis:
    """One axis's structure: parameter names, states, scored channels and the inputs it uses."""

    name: str
    order: int                       # 1 = first-order rate response, 2 = second-order attitude response
    inputs: tuple[str, ...]          # the inputs that drive it (on-axis and off-axis alike)
    with_velocity: bool

    @property
    def param_names(self) -> tuple[str, ...]:
        dyn = ("T",) if self.order == 1 else ("wn", "zeta")
        vel = ("X", "X0") if self.with_velocity else ()
        return (*dyn, "tau", "b", *(f"K_{c}" for c in self.inputs), *vel)

    @property
    def states(self) -> tuple[str, ...]:
        rate, att, _, vel = AXES[self.name]
        return tuple(s for s in (rate, att, vel) if s is not None)

    def bounds(self) -> np.ndarray:
        return np.array([BOUNDS["K" if n.startswith("K_") else n] for n in self.param_names], dtype=float)

    def matrices(self, x: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Continuous (A (n, n), B (n, m + 1)) over ``states`` driven by ``inputs`` and a constant 1."""
        p = dict(zip(self.param_names, x, strict=True))
        n, m = len(self.states), len(self.inputs)
        A = np.zeros((n, n))
        B = np.zeros((n, m + 1))
        gains = np.array([*(p[f"K_{c}"] for c in self.inputs), p["b"]])
        if self.order == 1:
            A[0, 0] = -1.0 / p["T"]
            B[0] = gains / p["T"]
        else:   # x = rate, attitude: rate' = wn^2 (command - attitude) - 2 zeta wn rate
            wn, z = p["wn"], p["zeta"]
            A[0, 0], A[0, 1] = -2 * z * wn, -wn ** 2
            B[0] = gains * wn ** 2
        if n >= 2 and AXES[self.name][1] is not None:
            A[1, 0] = 1.0     # attitude' = rate
        if self.with_velocity:
            sign = -1.0 if self.name == "pitch" else 1.0   # u' = X_u u - g theta; v' = Y_v v + g phi
            A[2, 1], A[2, 2] = sign * G_M_S2, p["X"]
            B[2, m] = p["X0"]
        return A, B


def delay_grid() -> np.ndarray:
    """The fixed delays the fit starts from (s): every ``DELAY_GRID_S`` from ``MIN_DELAY_S`` to ``MAX_DELAY_S``, 0 included."""
    return np.concatenate([-np.arange(DELAY_GRID_S, -MIN_DELAY_S + 1e-9, DELAY_GRID_S)[::-1],
                           np.arange(0.0, MAX_DELAY_S + 1e-9, DELAY_GRID_S)])


def _discretize(A: np.ndarray, B: np.ndarray, dt_s: float) -> tuple[np.ndarray, np.ndarray]:
    from scipy.linalg import expm  # here: identify of a blade-input aircraft loads no scipy

    n, m = B.shape
    M = np.zeros((n + m, n + m))
    M[:n, :n], M[:n, n:] = A, B
    E = expm(M * dt_s)
    return E[:n, :n], E[:n, n:]


@dataclass(frozen=True, eq=False)
class CommandWindows:
    """Windows with input history for delays: inputs (W, P + L + F, 4) (P samples before each window, the
    segment's first sample repeated where the segment starts later, and F after it for a negative
    delay, the last sample repeated past the segment's end), outputs (W, L, 8), mask (W, 8) (channel
    measured over the whole window)."""

    inputs: np.ndarray
    outputs: np.ndarray
    mask: np.ndarray
    pre: int
    dt_s: float
    post: int = 0

    @property
    def count(self) -> int:
        return int(self.outputs.shape[0])

    @property
    def length(self) -> int:
        return int(self.outputs.shape[1])

    def delayed(self, tau_s: float, cols: list[int]) -> np.ndarray:
        """(W, L, len(cols)) inputs ``cols`` delayed by ``tau_s`` (linear interpolation between samples)."""
        s = min(max(tau_s / self.dt_s, 1.0 - self.post if self.post else 0.0), self.pre - 1.0)
        k = int(np.floor(s))
        f = s - k
        L, P = self.length, self.pre
        a = self.inputs[:, P - k:P - k + L][..., cols]
        if f <= 0:
            return a
        b = self.inputs[:, P - k - 1:P - k - 1 + L][..., cols]
        return (1 - f) * a + f * b


def command_windows(segments: list, dt_s: float, window_s: float, step_s: float = 0.0,
                    offset: np.ndarray | None = None) -> CommandWindows:
    """Windows of ``window_s`` every ``step_s`` (0 = non-overlapping) with ``MAX_DELAY_S`` of input
    history and ``-MIN_DELAY_S`` of input after the window; ``offset`` (4,) is added to the inputs (the
    model's trim against the data's)."""
    L = int(round(window_s / dt_s))
    S = L if step_s <= 0 else max(1, int(round(step_s / dt_s)))
    P = int(np.ceil(MAX_DELAY_S / dt_s)) + 2
    F = int(np.ceil(max(-MIN_DELAY_S, 0.0) / dt_s)) + 2
    ins, outs, masks = [], [], []
    off = np.zeros(4) if offset is None else np.asarray(offset, dtype=float)
    for s in segments:
        u = np.asarray(s.inputs, dtype=float) + off[None, :]
        u = np.concatenate([np.repeat(u[:1], P, axis=0), u, np.repeat(u[-1:], F, axis=0)])
        y = np.asarray(s.outputs, dtype=float)
        for a in range(0, s.n - L + 1, S):
            yw = y[a:a + L]
            ins.append(u[a:a + P + L + F])
            outs.append(yw)
            masks.append(np.asarray(s.available, dtype=bool) & np.isfinite(yw).all(axis=0))
    if not ins:
        longest = max((s.duration_s for s in segments), default=0.0)
        raise SysidError(f"window_s = {window_s:g}: no in-air segment is that long (longest {longest:.1f} s)")
    return CommandWindows(np.stack(ins), np.stack(outs), np.stack(masks), P, float(dt_s), F)


#: parameters the response is linear in (solved by least squares inside the cost: variable projection)
def _is_linear(name: str) -> bool:
    return name in ("b", "X0") or name.startswith("K_")


class _AxisCost:
    """Output error of one axis with the linear parameters (gains, couplings, offsets) projected out.

    For given nonlinear parameters (time constant or natural frequency and damping, delay, velocity
    damping) the response is the free response from the measured initial states plus a sum of unit
    responses, one per linear parameter, weighted by it: the weighted least-squares gains are solved
    in every evaluation (Golub & Pereyra's variable projection), so the search is over 2-4 numbers.
    Channel weights: 1 / signal norm (the residual sum is the sum of squared eq.-19 mismatch ratios)."""

    def __init__(self, axis: _Axis, win: CommandWindows, window_offsets: bool = True) -> None:
        self.axis, self.win, self.window_offsets = axis, win, window_offsets
        self.names = axis.param_names
        self.lin = np.array([_is_linear(n) for n in self.names])
        self.idx = [OUTPUTS.index(s) for s in axis.states]
        m = win.mask[:, self.idx]
        y = np.nan_to_num(win.outputs[..., self.idx])
        norms = np.array([np.sqrt((y[m[:, j], :, j] ** 2).sum()) for j in range(len(self.idx))])
        scale = np.where(norms > 0, 1.0 / np.maximum(norms, 1e-12), 0.0)
        self.w = np.broadcast_to(m[:, None, :] * scale[None, None, :], y.shape).reshape(-1)
        self.y = y.reshape(-1)
        self.rows = self.w > 0
        self.cols = [INPUTS.index(c) for c in axis.inputs]

    def columns(self, x: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """(free response (N,), unit responses (N, n_linear)) flattened like ``self.y``."""
        ax, win = self.axis, self.win
        p = dict(zip(self.names, x, strict=True))
        A, _ = ax.matrices(np.where(self.lin, 0.0, x))
        n = len(ax.states)
        lin_names = [nm for nm in self.names if _is_linear(nm)]
        Bu = np.zeros((n, len(lin_names)))
        for j, nm in enumerate(lin_names):
            if nm == "X0":
                Bu[2, j] = 1.0
            else:
                Bu[0, j] = 1.0 / p["T"] if ax.order == 1 else p["wn"] ** 2
        Ad, Bd = _discretize(A, Bu, win.dt_s)
        u = win.delayed(float(p["tau"]), self.cols)                      # (W, L, m)
        W, L = win.count, win.length
        drv = np.empty((W, L, len(lin_names)))
        for j, nm in enumerate(lin_names):
            if nm.startswith("K_"):
                drv[..., j] = u[..., ax.inputs.index(nm[2:])]
            else:   # b, X0: constant
                drv[..., j] = 1.0
        J = len(lin_names)
        drive = drv[..., None] * Bd.T[None, None, :, :]                   # (W, L, J, n)
        X = np.zeros((W, J + 1, n))
        X[:, 0] = np.nan_to_num(win.outputs[:, 0, self.idx])
        out = np.empty((W, L, J + 1, n))
        AdT = Ad.T
        for k in range(L):
            out[:, k] = X
            X = X @ AdT
            X[:, 1:] += drive[:, k]
        free = out[:, :, 0].reshape(-1)
        units = out[:, :, 1:].transpose(0, 1, 3, 2).reshape(-1, J)
        return free, units

    def _project(self, x: np.ndarray, g_given: np.ndarray | None) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """(gains (J,) with ``b`` as the mean of the windows', offsets (W,), weighted residual (W * L * n,)).

        ``b`` is each window's own: the controller's integrator (its trim), an unmeasured state
        estimated over the window like the hover model's flapping states; the other gains are solved
        (``g_given`` None) or taken as given. Without ``window_offsets`` ``b`` is one gain like the others."""
        free, units = self.columns(x)
        W = self.win.count
        w = self.w.reshape(W, -1)
        R0 = (self.y - free).reshape(W, -1) * w
        M = units.reshape(W, -1, units.shape[1]) * w[..., None]
        jb = [n for n in self.names if _is_linear(n)].index("b")
        if not self.window_offsets:
            if g_given is None:
                g, *_ = np.linalg.lstsq(M.reshape(-1, M.shape[2]), R0.reshape(-1), rcond=None)
            else:
                g = np.asarray(g_given, dtype=float)
            return g, np.full(W, g[jb]), M.reshape(-1, M.shape[2]) @ g - R0.reshape(-1)
        sb = M[..., jb]
        ss = np.einsum("wk,wk->w", sb, sb)
        inv = np.where(ss > 1e-12, 1.0 / np.maximum(ss, 1e-300), 0.0)
        others = [j for j in range(M.shape[2]) if j != jb]
        Mo = M[..., others]
        R0p = R0 - sb * (np.einsum("wk,wk->w", sb, R0) * inv)[:, None]
        Mop = Mo - sb[..., None] * (np.einsum("wk,wkj->wj", sb, Mo) * inv[:, None])[:, None, :]
        if g_given is None:
            go, *_ = np.linalg.lstsq(Mop.reshape(-1, len(others)), R0p.reshape(-1), rcond=None)
        else:
            go = np.asarray(g_given, dtype=float)[others]
        d = np.einsum("wk,wk->w", sb, R0 - Mo @ go) * inv
        g = np.zeros(M.shape[2])
        g[others] = go
        g[jb] = float(np.mean(d[ss > 1e-12])) if (ss > 1e-12).any() else 0.0
        return g, d, (Mop.reshape(-1, len(others)) @ go - R0p.reshape(-1))

    def solve(self, x: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """(x with the linear parameters solved, weighted residual (N,))."""
        g, _, e = self._project(x, None)
        xx = np.asarray(x, dtype=float).copy()
        xx[self.lin] = g
        return xx, e

    def residual_full(self, x: np.ndarray) -> np.ndarray:
        """Weighted residual at ``x`` as given (the windows' offsets still estimated): for the Jacobian."""
        return self._project(x, np.asarray(x, dtype=float)[self.lin])[2]

    def predict(self, x: np.ndarray, window_offsets: bool = True) -> np.ndarray:
        """(W, L, n) response at ``x``, each window's offset estimated over it (``window_offsets``
        False: the fitted ``b`` in every window, nothing but the initial states from a window's outputs)."""
        free, units = self.columns(x)
        g = np.asarray(x, dtype=float)[self.lin]
        W = self.win.count
        if not (window_offsets and self.window_offsets):
            return (free + units @ g).reshape(W, self.win.length, len(self.axis.states))
        _, d, _ = self._project(x, g)
        jb = [n for n in self.names if _is_linear(n)].index("b")
        gg = g.copy()
        gg[jb] = 0.0
        pred = (free + units @ gg).reshape(W, -1) + d[:, None] * units[:, jb].reshape(W, -1)
        return pred.reshape(W, self.win.length, len(self.axis.states))


def _start(axis: _Axis) -> np.ndarray:
    v = {"T": 0.3, "tau": 0.05, "b": 0.0, "wn": 4.0, "zeta": 0.7, "X": -0.2, "X0": 0.0}
    return np.array([0.0 if n.startswith("K_") else v[n] for n in axis.param_names])


@dataclass
class AxisFit:
    """One axis's fitted LOES: parameter values and standard errors, the inputs that drive it (the
    on-axis one: the largest contribution, gain times the input's spread), the inputs dropped."""

    axis: str
    order: int
    params: dict[str, float]
    std: dict[str, float | None]
    inputs: tuple[str, ...]
    on_input: str
    dropped: tuple[str, ...] = ()

    @property
    def gain(self) -> float:
        return self.params[f"K_{self.on_input}"] if self.on_input else 0.0

    def summary(self) -> dict[str, Any]:
        p = self.params
        out: dict[str, Any] = {"input": self.on_input, "gain": self.gain, "delay_s": p["tau"]}
        if self.order == 1:
            out["time_constant_s"] = p["T"]
            out["bandwidth_rad_s"] = 1.0 / p["T"]   # -3 dB of command to rate
        else:
            out["natural_frequency_rad_s"] = p["wn"]
            out["damping"] = p["zeta"]
            out["bandwidth_rad_s"] = rate_bandwidth(self)
        att = attitude_bandwidth(self) if AXES[self.axis][1] is not None and self.on_input else None
        if att is not None:
            out["attitude_bandwidth_rad_s"] = att
        out["couplings"] = {c: p[f"K_{c}"] for c in self.inputs if c != self.on_input}
        return out


def _response(fit: AxisFit, w: np.ndarray, attitude: bool) -> np.ndarray:
    """Complex on-axis command-to-rate (or attitude) frequency response at ``w`` rad/s, with the delay."""
    p = fit.params
    s = 1j * w
    if fit.order == 1:
        rate = fit.gain / (p["T"] * s + 1)
    else:
        att = fit.gain * p["wn"] ** 2 / (s ** 2 + 2 * p["zeta"] * p["wn"] * s + p["wn"] ** 2)
        rate = att * s
    h = rate / s if attitude else rate
    return h * np.exp(-s * p["tau"])


def rate_bandwidth(fit: AxisFit) -> float:
    """-3 dB frequency (rad/s) of command to rate against its low-frequency (or peak) gain."""
    w = np.logspace(-2, 2.5, 2000)
    mag = np.abs(_response(fit, w, False))
    ref = mag[0] if fit.order == 1 else mag.max()
    above = np.flatnonzero(mag >= ref / np.sqrt(2))
    return float(w[above[-1]]) if above.size else float("nan")


def attitude_bandwidth(fit: AxisFit) -> float | None:
    """ADS-33 phase bandwidth (rad/s): the frequency where command-to-attitude phase reaches -135 deg
    (the sign of the gain removed)."""
    w = np.logspace(-2, 2.5, 4000)
    h = _response(fit, w, True) * np.sign(fit.gain or 1.0)
    ph = np.unwrap(np.angle(h)) * 180 / np.pi
    ph = ph - 360.0 * np.round((ph[0] + (90.0 if fit.order == 1 else 0.0)) / 360.0)
    k = np.flatnonzero(ph <= -135.0)
    return float(w[k[0]]) if k.size else None


@dataclass
class CommandModel:
    """The stabilised aircraft's LOES: ``kind``, the fitted axes, trims; what the model file's
    ``command_response`` section holds."""

    kind: str
    axes: dict[str, AxisFit]
    input_trim_pwm: dict[str, float]
    pwm_per_unit: float
    sample_rate_hz: float
    fit: dict[str, Any] = field(default_factory=dict)

    def to_json(self) -> dict[str, Any]:
        return {"schema": SCHEMA, "kind": self.kind,
                "axes": {a: {"order": f.order, "inputs": list(f.inputs), "on_axis_input": f.on_input,
                             "states": list(_axis_of(f).states),
                             "parameters": dict(f.params), "parameter_std": dict(f.std),
                             "inputs_dropped": list(f.dropped), "summary": f.summary()}
                         for a, f in self.axes.items()},
                "input_trim_pwm": dict(self.input_trim_pwm), "pwm_per_unit": self.pwm_per_unit,
                "sample_rate_hz": self.sample_rate_hz, "fit": dict(self.fit)}

    @classmethod
    def from_json(cls, doc: dict[str, Any]) -> CommandModel:
        if not isinstance(doc, dict) or doc.get("schema") != SCHEMA:
            raise SysidError(f"command_response: not a {SCHEMA} section")
        axes = {}
        for a, d in doc.get("axes", {}).items():
            if a not in AXES:
                raise SysidError(f"command_response.axes: unknown axis {a!r} (axes: {', '.join(AXES)})")
            axes[a] = AxisFit(a, int(d["order"]), {k: float(v) for k, v in d["parameters"].items()},
                              dict(d.get("parameter_std", {})), tuple(d["inputs"]), str(d.get("on_axis_input") or ""),
                              tuple(d.get("inputs_dropped", ())))
        return cls(str(doc["kind"]), axes, {k: float(v) for k, v in doc["input_trim_pwm"].items()},
                   float(doc["pwm_per_unit"]), float(doc["sample_rate_hz"]), dict(doc.get("fit", {})))

    def describe(self) -> list[str]:
        """One line per axis: what the controller makes of the aircraft."""
        out = []
        for a, f in self.axes.items():
            s = f.summary()
            dyn = (f"time constant {s['time_constant_s']:.3f} s" if f.order == 1 else
                   f"natural frequency {s['natural_frequency_rad_s']:.2f} rad/s, damping {s['damping']:.2f}")
            att = (f", attitude bandwidth {s['attitude_bandwidth_rad_s']:.2f} rad/s"
                   if s.get("attitude_bandwidth_rad_s") else "")
            cpl = ", ".join(f"{c} {v:+.3g}" for c, v in s["couplings"].items()) or "none the data support"
            out.append(f"{a} ({f.on_input or 'no input'} -> {AXES[a][0]}): gain {s['gain']:+.3g}, {dyn}, "
                       f"delay {s['delay_s'] * 1000:.0f} ms{_skew_note(s['delay_s'])}, bandwidth {s['bandwidth_rad_s']:.2f} rad/s{att}; "
                       f"couplings: {cpl}")
        return out


def _skew_note(delay_s: float) -> str:
    """What a negative equivalent delay says: the response leads the logged command."""
    return (" (negative: the logged command lags the response it drives, a time skew between the logged "
            "channels, not a dynamic of the aircraft)" if delay_s < -0.5 * DELAY_GRID_S else "")


def _has_vel(f: AxisFit) -> bool:
    return "X" in f.params


def _axis_of(f: AxisFit) -> _Axis:
    return _Axis(f.axis, f.order, f.inputs, _has_vel(f))


def _vector(f: AxisFit) -> np.ndarray:
    return np.array([f.params[n] for n in _axis_of(f).param_names])


def fit_axis(axis: _Axis, win: CommandWindows, *, x0: np.ndarray | None = None, maxiter: int = IdentifyConfig.command_maxiter,
             rng: Any = 0, window_offsets: bool = True) -> tuple[np.ndarray, np.ndarray, float]:
    """(x, std, cost) of one axis: the nonlinear parameters over a grid of delays, then every one of
    them free (:func:`groundstation.sysid.optimizers.minimize_grid_lsq`), the linear ones solved inside;
    standard errors from the Jacobian of every parameter at the end. ``window_offsets``: ``b`` per window."""
    cost = _AxisCost(axis, win, window_offsets)
    b = axis.bounds()
    nl = ~cost.lin
    start = _start(axis) if x0 is None else np.clip(x0, b[:, 0], b[:, 1])

    def full(z: np.ndarray) -> np.ndarray:
        x = start.copy()
        x[nl] = z
        return x

    def res(z: np.ndarray) -> np.ndarray:
        return cost.solve(full(z))[1]

    names_nl = [n for n, keep in zip(axis.param_names, nl, strict=True) if keep]
    r = minimize_grid_lsq(lambda Z: np.array([float(np.sum(res(z) ** 2)) for z in Z]), b[nl], rng=rng,
                          maxiter=maxiter, residuals=res, x0=[start[nl]], grid_index=names_nl.index("tau"),
                          grid=delay_grid())
    x, e = cost.solve(full(np.asarray(r.x, dtype=float)))
    # linear parameters outside their bounds (an input that barely moves): clipped
    x = np.clip(x, b[:, 0], b[:, 1])
    std = np.full(x.size, np.nan)
    r0 = cost.residual_full(x)
    J = np.empty((r0.size, x.size))
    for i in range(x.size):
        h = 1e-6 * max(1.0, abs(x[i])) if cost.lin[i] else 1e-4 * (b[i, 1] - b[i, 0])
        xp = x.copy()
        xp[i] += h
        J[:, i] = (cost.residual_full(xp) - r0) / h
    n, d = J.shape
    s2 = float(r0 @ r0) / max(n - d, 1)
    try:
        std = np.sqrt(np.maximum(np.diag(np.linalg.pinv(J.T @ J)) * s2, 0.0))
    except np.linalg.LinAlgError:
        pass
    return x, std, float(r0 @ r0)


def simulate_axis(axis: _Axis, x: np.ndarray, win: CommandWindows, window_offsets: bool = True) -> np.ndarray:
    """(W, L, n_states) response of one axis from the measured states at each window's first sample and
    each window's controller offset estimated over it (:class:`_AxisCost`; ``window_offsets`` False:
    the fitted one)."""
    return _AxisCost(axis, win, window_offsets).predict(x, window_offsets)


def identify_command(prepared: Any, kind: str = "rate_command", *, window_s: float = IdentifyConfig.command_window_s,
                     step_s: float = IdentifyConfig.command_step_s, maxiter: int = IdentifyConfig.command_maxiter, rng: Any = 0,
                     window_offsets: bool = True) -> CommandModel:
    """The LOES of ``prepared`` (see the module docstring); SysidError when no axis can be fitted.
    ``window_offsets`` False: one ``b`` per axis for the whole flight (nothing estimated from a window's
    outputs but its initial states), and the model predicts without them (``fit["window_offsets"]``)."""
    if kind not in COMMAND_KINDS:
        raise SysidError(f"inputs.kind = {kind!r}: a command structure is one of {', '.join(COMMAND_KINDS)}")
    win = command_windows(prepared.segments, prepared.dt_s, window_s, step_s)
    active = {k: bool(a) for k, a in zip(INPUTS, prepared.input_active, strict=True)}
    measured = {c: bool(win.mask[:, OUTPUTS.index(c)].any()) for c in OUTPUTS}
    axes: dict[str, AxisFit] = {}
    notes: list[str] = []
    spread = {k: float(np.std(win.inputs[..., j])) for j, k in enumerate(INPUTS)}
    for name, (rate, _, _, vel) in AXES.items():
        if not measured[rate]:
            notes.append(f"{name}: {rate} not measured, axis not identified")
            continue
        order = 2 if kind == "attitude_command" and name in ("roll", "pitch") else 1
        ins = tuple(c for c in INPUTS if active[c])
        ax = _Axis(name, order, ins, vel is not None and measured[vel])
        x, std, _ = fit_axis(ax, win, maxiter=maxiter, rng=rng, window_offsets=window_offsets)
        # keep the inputs the data support (estimate beyond COUPLING_T standard errors); refit without the others
        def t_of(c: str, ax: _Axis = ax, x: np.ndarray = x, std: np.ndarray = std) -> float:
            i = ax.param_names.index(f"K_{c}")
            return abs(x[i]) / std[i] if np.isfinite(std[i]) and std[i] > 0 else 0.0
        weak = tuple(c for c in ins if t_of(c) <= COUPLING_T)
        if weak:
            ax2 = _Axis(name, order, tuple(c for c in ins if c not in weak), ax.with_velocity)
            x0 = np.array([x[ax.param_names.index(n)] for n in ax2.param_names])
            x, std, _ = fit_axis(ax2, win, x0=x0, maxiter=maxiter, rng=rng, window_offsets=window_offsets)
            ax = ax2
        contrib = {c: abs(x[ax.param_names.index(f"K_{c}")]) * spread[c] for c in ax.inputs}
        on = max(contrib, key=lambda c: contrib[c]) if contrib else ""
        if not on:
            notes.append(f"{name}: no input moves {rate} beyond {COUPLING_T:g} standard errors")
        axes[name] = AxisFit(name, order, dict(zip(ax.param_names, map(float, x), strict=True)),
                             {n: (float(v) if np.isfinite(v) else None) for n, v in zip(ax.param_names, std, strict=True)},
                             ax.inputs, on, weak)
    if not axes:
        raise SysidError("command-response structure: no body rate measured")
    return CommandModel(kind, axes, dict(prepared.input_trim_pwm), float(prepared.pwm_per_unit),
                        float(1.0 / prepared.dt_s), {"window_s": window_s, "window_step_s": step_s, "notes": notes,
                                                     "window_offsets": bool(window_offsets)})


def predict_command(model: CommandModel, prepared: Any, *, window_s: float = 5.0, window_offsets: bool | None = None) -> Any:
    """Held-out prediction as :func:`groundstation.sysid.heldout.predict` (eq. 19 per channel over
    ``window_s`` windows started from the measured states; inputs against the model's trim);
    ``window_offsets`` False: no controller offset estimated from a held-out window's outputs (None:
    as the model was fitted)."""
    if window_offsets is None:
        window_offsets = bool(model.fit.get("window_offsets", True))
    ppu = float(prepared.pwm_per_unit)
    off = np.array([(float(prepared.input_trim_pwm.get(k, 0.0)) - float(model.input_trim_pwm.get(k, prepared.input_trim_pwm.get(k, 0.0)))) / ppu
                    for k in INPUTS])
    win = command_windows(prepared.segments, prepared.dt_s, window_s, 0.0, offset=off)
    num: dict[str, float] = {}
    den: dict[str, float] = {}
    for f in model.axes.values():
        ax = _axis_of(f)
        yhat = simulate_axis(ax, _vector(f), win, window_offsets)
        for j, ch in enumerate(ax.states):
            k = OUTPUTS.index(ch)
            m = win.mask[:, k]
            if not m.any():
                continue
            y = win.outputs[m, :, k]
            num[ch] = float(np.linalg.norm(yhat[m, :, j] - y))
            den[ch] = float(np.linalg.norm(y))
    match, ratio = {}, {}
    for ch in OUTPUTS:   # in the output order, as the hover model's prediction
        if ch in den and den[ch] > 0:
            ratio[ch] = num[ch] / den[ch]
            match[ch] = (1.0 - ratio[ch]) * 100.0
    mean = float(np.mean(list(match.values()))) if match else float("nan")
    return Prediction(match=match, mean_match=mean, windows=win.count, window_s=float(window_s),
                      duration_s=float(win.count * win.length * win.dt_s), ratio=ratio)
