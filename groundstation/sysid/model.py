"""The paper's hover state-space model (eq. 8): parameter vector, matrices, discretisation, model file.

Array conventions
-----------------
* A parameter vector ``theta`` has shape ``(..., N_PARAMS)`` in the order of :data:`PARAM_NAMES`;
  leading dimensions are candidates (a whole colony at once).
* :func:`build_matrices` returns ``A_hor (..., 8, 8)``, ``B_hor (..., 8, 2)``, ``A_ver (..., 3, 3)``,
  ``B_ver (..., 3, 2)``, exactly as printed in the paper (see docs/model-file.md):
  entry ``-1/tau_s`` is ``-inv_tau_s``; constraints ``N_fb = -N_ped`` and ``k_fb = -2 N_r`` are applied
  here, so 31 parameters are free.
* States: horizontal ``u v theta phi q p a_s b_s`` driven by ``lat lon``; vertical ``w r r_fb`` driven
  by ``col ped``. Measured outputs are :data:`OUTPUTS` = ``u v w p q r theta phi``.
* :func:`discretize` is the exact zero-order-hold discretisation at ``dt_s`` (batched).

Pure numpy/scipy; the model-file JSON mapping is here as dicts, reading/writing files is the CLI's.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import Any

import numpy as np

from groundstation.errors import SysidError
from groundstation.sysid.fit_section import ModelFit

G_M_S2 = 9.81

HOR_STATES: tuple[str, ...] = ("u", "v", "theta", "phi", "q", "p", "a_s", "b_s")
HOR_INPUTS: tuple[str, ...] = ("lat", "lon")
VER_STATES: tuple[str, ...] = ("w", "r", "r_fb")
VER_INPUTS: tuple[str, ...] = ("col", "ped")
INPUTS: tuple[str, ...] = ("lat", "lon", "col", "ped")
#: Measured output channels, in the order used by every (n_samples, 8) output array.
OUTPUTS: tuple[str, ...] = ("u", "v", "w", "p", "q", "r", "theta", "phi")
#: Units of the output channels.
OUTPUT_UNITS: dict[str, str] = {
    "u": "m/s", "v": "m/s", "w": "m/s", "p": "rad/s", "q": "rad/s", "r": "rad/s", "theta": "rad", "phi": "rad",
}

HOR_PARAMS: tuple[str, ...] = (
    "X_u", "Y_v", "M_u", "M_v", "M_q", "M_a", "M_b", "L_u", "L_v", "L_p", "L_a", "L_b", "k1", "inv_tau_s",
    "X_lat", "Y_lon", "M_lat", "M_lon", "L_lat", "L_lon", "A_lat", "B_lon",
)
VER_PARAMS: tuple[str, ...] = ("Z_w", "Z_r", "N_w", "N_r", "k_r", "Z_col", "Z_ped", "N_col", "N_ped")
#: The 31 free parameters. ``inv_tau_s`` is 1/tau_s (1/s); the matrix entry is ``-inv_tau_s``.
PARAM_NAMES: tuple[str, ...] = HOR_PARAMS + VER_PARAMS
N_PARAMS = len(PARAM_NAMES)
PARAM_INDEX: dict[str, int] = {n: i for i, n in enumerate(PARAM_NAMES)}

#: Default search bounds (lower, upper). Wide enough for the paper's Table 5 and for Mettler-class
#: small helicopters (R-50: M_a ~ 83, L_b ~ 166 1/s^2, 1/tau ~ 20); signs are left free except where
#: physics fixes them (1/tau_s > 0).
DEFAULT_BOUNDS: dict[str, tuple[float, float]] = {
    "X_u": (-2.0, 1.0), "Y_v": (-2.0, 1.0),
    "M_u": (-3.0, 3.0), "M_v": (-3.0, 3.0), "M_q": (-10.0, 10.0),
    "M_a": (-250.0, 250.0), "M_b": (-250.0, 250.0),
    "L_u": (-3.0, 3.0), "L_v": (-3.0, 3.0), "L_p": (-20.0, 10.0),
    "L_a": (-300.0, 300.0), "L_b": (-300.0, 300.0),
    "k1": (-2.0, 2.0), "inv_tau_s": (1.0, 40.0),
    "X_lat": (-20.0, 20.0), "Y_lon": (-20.0, 20.0),
    "M_lat": (-50.0, 50.0), "M_lon": (-50.0, 50.0), "L_lat": (-50.0, 50.0), "L_lon": (-50.0, 50.0),
    "A_lat": (-20.0, 20.0), "B_lon": (-20.0, 20.0),
    "Z_w": (-10.0, 2.0), "Z_r": (-10.0, 10.0), "N_w": (-10.0, 10.0), "N_r": (-10.0, 5.0),
    "k_r": (-20.0, 20.0),
    "Z_col": (-80.0, 80.0), "Z_ped": (-30.0, 30.0), "N_col": (-50.0, 50.0), "N_ped": (-50.0, 50.0),
}


def bounds_array(bounds: dict[str, tuple[float, float]] | None = None) -> np.ndarray:
    """Bounds as an array of shape (N_PARAMS, 2) in PARAM_NAMES order (missing keys: defaults)."""
    merged = dict(DEFAULT_BOUNDS)
    if bounds:
        unknown = set(bounds) - set(PARAM_NAMES)
        if unknown:
            raise SysidError(f"unknown parameter name(s) in bounds: {sorted(unknown)}; allowed: {PARAM_NAMES}")
        merged.update(bounds)
    out = np.array([merged[n] for n in PARAM_NAMES], dtype=float)
    bad = out[:, 0] >= out[:, 1]
    if bad.any():
        names = [PARAM_NAMES[i] for i in np.flatnonzero(bad)]
        raise SysidError(f"bounds with lower >= upper for {names}")
    return out


def _number(value: Any, key: str) -> float:
    """``value`` as a float, or a SysidError naming the model field ``key`` and the value."""
    try:
        return float(value)
    except (TypeError, ValueError):
        raise SysidError(f"model field {key} = {value!r}: not a number") from None


def _numbers(doc: dict[str, Any], key: str) -> dict[str, float]:
    """The table ``doc[key]`` (absent: empty) with float values; a SysidError names a bad entry."""
    table = doc.get(key, {})
    if not isinstance(table, dict):
        raise SysidError(f"model field {key} = {table!r}: not a table of numbers")
    return {k: _number(v, f"{key}.{k}") for k, v in table.items()}


def theta_from_dict(params: dict[str, float]) -> np.ndarray:
    """Parameter dict -> vector (N_PARAMS,); raises SysidError (a ValueError) naming a missing key."""
    missing = [n for n in PARAM_NAMES if n not in params]
    if missing:
        raise SysidError(f"model parameters missing: {missing}")
    return np.array([float(params[n]) for n in PARAM_NAMES])


def theta_to_dict(theta: np.ndarray) -> dict[str, float]:
    return {n: float(v) for n, v in zip(PARAM_NAMES, np.asarray(theta, dtype=float), strict=True)}


def build_matrices(theta: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """Paper eq. (8) matrices for a batch of parameter vectors.

    Parameters
    ----------
    theta : array (..., 31)

    Returns
    -------
    A_hor (..., 8, 8), B_hor (..., 8, 2), A_ver (..., 3, 3), B_ver (..., 3, 2)
    """
    th = np.asarray(theta, dtype=float)
    lead = th.shape[:-1]
    P = {n: th[..., i] for i, n in enumerate(PARAM_NAMES)}
    g = G_M_S2
    Ah = np.zeros(lead + (8, 8))
    Bh = np.zeros(lead + (8, 2))
    # rows: 0 u, 1 v, 2 theta, 3 phi, 4 q, 5 p, 6 a_s, 7 b_s
    Ah[..., 0, 0] = P["X_u"]
    Ah[..., 0, 2] = -g
    Ah[..., 0, 6] = -g
    Ah[..., 1, 1] = P["Y_v"]
    Ah[..., 1, 3] = g
    Ah[..., 1, 7] = g
    Ah[..., 2, 4] = 1.0
    Ah[..., 3, 5] = 1.0
    Ah[..., 4, 0] = P["M_u"]
    Ah[..., 4, 1] = P["M_v"]
    Ah[..., 4, 4] = P["M_q"]
    Ah[..., 4, 6] = P["M_a"]
    Ah[..., 4, 7] = P["M_b"]
    Ah[..., 5, 0] = P["L_u"]
    Ah[..., 5, 1] = P["L_v"]
    Ah[..., 5, 5] = P["L_p"]
    Ah[..., 5, 6] = P["L_a"]
    Ah[..., 5, 7] = P["L_b"]
    Ah[..., 6, 4] = -1.0
    Ah[..., 6, 5] = P["k1"]
    Ah[..., 6, 6] = -P["inv_tau_s"]
    Ah[..., 7, 4] = -P["k1"]
    Ah[..., 7, 5] = -1.0
    Ah[..., 7, 7] = -P["inv_tau_s"]
    Bh[..., 0, 0] = P["X_lat"]
    Bh[..., 1, 1] = P["Y_lon"]
    Bh[..., 4, 0] = P["M_lat"]
    Bh[..., 4, 1] = P["M_lon"]
    Bh[..., 5, 0] = P["L_lat"]
    Bh[..., 5, 1] = P["L_lon"]
    Bh[..., 6, 0] = P["A_lat"]
    Bh[..., 7, 1] = P["B_lon"]

    Av = np.zeros(lead + (3, 3))
    Bv = np.zeros(lead + (3, 2))
    N_fb = -P["N_ped"]
    k_fb = -2.0 * P["N_r"]
    Av[..., 0, 0] = P["Z_w"]
    Av[..., 0, 1] = P["Z_r"]
    Av[..., 1, 0] = P["N_w"]
    Av[..., 1, 1] = P["N_r"]
    Av[..., 1, 2] = N_fb
    Av[..., 2, 1] = P["k_r"]
    Av[..., 2, 2] = -k_fb
    Bv[..., 0, 0] = P["Z_col"]
    Bv[..., 0, 1] = P["Z_ped"]
    Bv[..., 1, 0] = P["N_col"]
    Bv[..., 1, 1] = P["N_ped"]
    return Ah, Bh, Av, Bv


#: Padé (13, 13) coefficients and the norm bound theta_13 of Higham (2005), as scipy's expm uses.
_PADE13 = (64764752532480000.0, 32382376266240000.0, 7771770303897600.0, 1187353796428800.0,
           129060195264000.0, 10559470521600.0, 670442572800.0, 33522128640.0, 1323241920.0, 40840800.0,
           960960.0, 16380.0, 182.0, 1.0)
_THETA13 = 5.371920351148152


def expm_batched(M: np.ndarray) -> np.ndarray:
    """Matrix exponential of a batch ``(..., k, k)``: Padé 13 with scaling and squaring (Higham 2005).

    Each matrix gets its own scaling ``2^-s`` (``||M/2^s||_1 <= theta_13``) and ``s`` squarings, all
    matrices in a few batched products: ~8x faster than ``scipy.linalg.expm`` on a colony of small
    matrices (scipy picks the Padé degree per matrix in a Python loop); agrees with it to ~1e-15
    relative for the norms met here (tests). Non-finite input gives non-finite output.
    """
    M = np.asarray(M, dtype=float)
    k = M.shape[-1]
    lead = M.shape[:-2]
    A = M.reshape((-1, k, k))
    with np.errstate(all="ignore"):
        nrm = np.abs(A).sum(axis=-2).max(axis=-1)  # 1-norm
        s = np.where(nrm > _THETA13, np.ceil(np.log2(np.where(nrm > _THETA13, nrm, 1.0) / _THETA13)), 0.0)
        s = np.clip(np.nan_to_num(s, nan=0.0, posinf=0.0), 0.0, 1100.0).astype(int)  # non-finite: NaN below
        A = A * np.exp2(-s.astype(float))[:, None, None]
        b = _PADE13
        eye = np.eye(k)
        A2 = A @ A
        A4 = A2 @ A2
        A6 = A4 @ A2
        U = A @ (A6 @ (b[13] * A6 + b[11] * A4 + b[9] * A2) + b[7] * A6 + b[5] * A4 + b[3] * A2 + b[1] * eye)
        V = A6 @ (b[12] * A6 + b[10] * A4 + b[8] * A2) + b[6] * A6 + b[4] * A4 + b[2] * A2 + b[0] * eye
        P, Q = V + U, V - U
        ok = np.isfinite(P).all(axis=(-2, -1)) & np.isfinite(Q).all(axis=(-2, -1))
        R = np.full_like(A, np.nan)
        if ok.any():
            try:
                R[ok] = np.linalg.solve(Q[ok], P[ok])
            except np.linalg.LinAlgError:  # a singular denominator: fall back matrix by matrix
                for i in np.flatnonzero(ok):
                    try:
                        R[i] = np.linalg.solve(Q[i], P[i])
                    except np.linalg.LinAlgError:
                        pass
        for q in range(int(s.max(initial=0))):
            sel = s > q
            if sel.all():
                R = R @ R
            else:
                R[sel] = R[sel] @ R[sel]
    return R.reshape(lead + (k, k))


def _fit(doc: Any) -> ModelFit:
    try:
        return ModelFit.from_json(doc)
    except ValueError as exc:
        raise SysidError(f"model document: 'fit': {exc}") from exc


def discretize(A: np.ndarray, B: np.ndarray, dt_s: float) -> tuple[np.ndarray, np.ndarray]:
    """Exact zero-order-hold discretisation, batched over leading dimensions.

    A (..., n, n), B (..., n, m) -> Ad (..., n, n), Bd (..., n, m) with
    expm([[A, B], [0, 0]] dt) = [[Ad, Bd], [0, I]] (:func:`expm_batched`).
    """
    n = A.shape[-1]
    m = B.shape[-1]
    lead = np.broadcast_shapes(A.shape[:-2], B.shape[:-2])
    M = np.zeros(lead + (n + m, n + m))
    M[..., :n, :n] = A * dt_s
    M[..., :n, n:] = B * dt_s
    E = expm_batched(M)
    return E[..., :n, :n], E[..., :n, n:]


@dataclass
class HoverModel:
    """An identified (or true) hover model with its trims: what the model file holds."""

    params: dict[str, float]
    sample_rate_hz: float = 50.0
    input_trim_pwm: dict[str, float] = field(default_factory=lambda: {k: 1500.0 for k in INPUTS})
    pwm_per_unit: float = 500.0
    output_trim: dict[str, float] = field(default_factory=lambda: {k: 0.0 for k in OUTPUTS})
    parameter_std: dict[str, float | None] = field(default_factory=dict)
    augmentations: list[dict[str, Any]] = field(default_factory=list)
    #: how the model was found and the held-out verdict (the file's ``fit`` section), typed
    fit: ModelFit = field(default_factory=ModelFit)
    source: dict[str, Any] = field(default_factory=dict)
    pinned: list[str] = field(default_factory=list)  # parameters at a search bound
    #: the stabilised aircraft's command-response structure (``heli-command-response/1`` section,
    #: :mod:`groundstation.sysid.structure`), when fitted
    command: dict[str, Any] | None = None
    #: which structure predicts: "hover" (eq. 8) or "command_response"
    structure: str = "hover"
    #: every prediction estimates one constant offset per input in each window, with the window's
    #: unmeasured initial states (``identify.window_input_offsets``: a stabiliser's integrator trim)
    window_input_offsets: bool = False

    @property
    def theta(self) -> np.ndarray:
        return theta_from_dict(self.params)

    def matrices(self) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
        return build_matrices(self.theta)

    def to_json(self) -> dict[str, Any]:
        """The ``heli-hover-model/1`` document (docs/model-file.md)."""
        Ah, Bh, Av, Bv = self.matrices()
        return {
            "schema": "heli-hover-model/1",
            "horizontal": {"states": list(HOR_STATES), "inputs": list(HOR_INPUTS),
                           "A": Ah.tolist(), "B": Bh.tolist()},
            "vertical": {"states": list(VER_STATES), "inputs": list(VER_INPUTS),
                         "A": Av.tolist(), "B": Bv.tolist()},
            "parameters": {n: float(self.params[n]) for n in PARAM_NAMES},
            "parameter_std": {n: (None if self.parameter_std.get(n) is None else float(self.parameter_std[n]))  # type: ignore[arg-type]
                              for n in PARAM_NAMES},
            "pinned_at_bound": list(self.pinned),
            "input_trim_pwm": {k: float(v) for k, v in self.input_trim_pwm.items()},
            "pwm_per_unit": float(self.pwm_per_unit),
            "output_trim": {k: float(v) for k, v in self.output_trim.items()},
            "sample_rate_hz": float(self.sample_rate_hz),
            "augmentations": list(self.augmentations),
            "fit": self.fit.to_json(),
            "source": dict(self.source),
            **({} if self.command is None else {"structure": self.structure, "command_response": dict(self.command)}),
            **({"window_input_offsets": True} if self.window_input_offsets else {}),
        }

    @classmethod
    def from_json(cls, doc: dict[str, Any]) -> HoverModel:
        """Inverse of :meth:`to_json`; raises SysidError (a ValueError) naming the bad field."""
        if not isinstance(doc, dict) or doc.get("schema") != "heli-hover-model/1":
            schema = doc.get("schema") if isinstance(doc, dict) else type(doc).__name__
            raise SysidError(f"not a heli-hover-model/1 document (schema={schema!r})")
        if "parameters" not in doc:
            raise SysidError("model document has no 'parameters'")
        params = _numbers(doc, "parameters")
        theta_from_dict(params)  # validates presence
        return cls(
            params=params,
            sample_rate_hz=_number(doc.get("sample_rate_hz", 50.0), "sample_rate_hz"),
            input_trim_pwm=_numbers(doc, "input_trim_pwm") or {k: 1500.0 for k in INPUTS},
            pwm_per_unit=_number(doc.get("pwm_per_unit", 500.0), "pwm_per_unit"),
            output_trim=_numbers(doc, "output_trim") or {k: 0.0 for k in OUTPUTS},
            parameter_std=dict(doc.get("parameter_std", {})),
            augmentations=list(doc.get("augmentations", [])),
            fit=_fit(doc.get("fit", {})),
            source=dict(doc.get("source", {})),
            pinned=list(doc.get("pinned_at_bound", [])),
            command=dict(doc["command_response"]) if isinstance(doc.get("command_response"), dict) else None,
            structure=str(doc.get("structure", "hover")),
            window_input_offsets=bool(doc.get("window_input_offsets", False)),
        )
