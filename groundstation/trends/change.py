"""Change test for one quantity over a campaign's flights (an identified parameter or an effect estimate).

``assess(name, values, std)`` takes the per-flight values in flight order, ``(n,)``, with their
standard errors ``(n,)`` (NaN where unknown, e.g. effect estimates, which have none) and returns a
:class:`Trend`.

Uncertainty of one flight's value: ``sigma_i^2 = std_i^2 + tau^2``. ``tau`` is the flight-to-flight
scatter that the reported standard errors do not cover (different weather, excitation, a search in
another basin), measured from the series itself: the robust spread (MAD) of the successive
differences about their median, divided by sqrt(2). Taking the differences about their median
keeps a steady trend out of the scatter; the MAD keeps a single jump out of it. Nothing is fitted
to a simulator: the scale is the data's own.

The test at flight ``k`` (sequential: only flights ``1..k`` are used, as it would have run on the
day) compares the value with the baseline (the mean of the first ``baseline`` flights):
``z_k = (v_k - ref) / sqrt(sigma_k^2 + sigma_ref^2)``. The quantity has *moved* at the first flight
where ``|z|`` exceeds the critical value on two consecutive flights, or on one flight together with a
significant weighted linear trend over ``1..k`` (a steadily growing deadband is caught at the flight
where it leaves the band; a one-off outlier is not called a change). The critical value is
Bonferroni-corrected over all the series and flights tested (``n_tests``), so a campaign of many
unchanged parameters raises no false alarm at family-wise level ``alpha``.
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np
from scipy.stats import norm

#: fewest finite flights from which tau (the between-flight scatter) is measured; no flight is tested
#: before that: standard errors from one flight alone miss how much flights differ (another basin of
#: the search, other excitation), and a change called on them would be a false alarm
MIN_FLIGHTS_FOR_SCATTER = 4


@dataclass(frozen=True)
class TrendConfig:
    """Change-test settings (``[trends]``)."""

    alpha: float = 0.05  # family-wise false-alarm probability over every series and flight tested
    baseline: int = 1  # flights averaged into the reference value


@dataclass(frozen=True)
class Trend:
    """One quantity over the campaign and its change verdict.

    ``values``, ``std`` (reported standard errors) and ``sigma`` (total per-flight uncertainty) are
    ``(n,)`` in flight order; ``z`` ``(n,)`` the sequential departure from the baseline in sigmas.
    ``changed_at`` is the index of the flight where the change was first called (None: no change);
    ``kind`` ``"trend"`` (steady drift) or ``"step"``; ``direction`` +1 / -1; ``tested`` False when the
    series has too few finite values to judge (``reason`` says why).
    """

    name: str
    values: np.ndarray
    std: np.ndarray
    sigma: np.ndarray
    z: np.ndarray
    z_crit: float
    tau: float
    slope_per_flight: float
    slope_z: float
    changed_at: int | None = None
    kind: str = ""
    direction: int = 0
    tested: bool = True
    reason: str = ""
    extra: dict = field(default_factory=dict)

    @property
    def changed(self) -> bool:
        return self.changed_at is not None

    def summary(self) -> dict:
        """JSON-able summary (what the service publishes and the table stores)."""
        last = int(np.flatnonzero(np.isfinite(self.values))[-1]) if np.isfinite(self.values).any() else None
        return {"name": self.name, "changed": self.changed, "changed_at": self.changed_at, "kind": self.kind,
                "direction": self.direction, "tested": self.tested, "reason": self.reason,
                "first": _f(self.values[np.isfinite(self.values)][0]) if last is not None else None,
                "latest": _f(self.values[last]) if last is not None else None,
                "latest_sigma": _f(self.sigma[last]) if last is not None else None,
                "latest_z": _f(self.z[last]) if last is not None else None,
                "z_crit": _f(self.z_crit), "tau": _f(self.tau), "slope_per_flight": _f(self.slope_per_flight),
                "slope_z": _f(self.slope_z)}


def _f(x: float) -> float | None:
    return float(x) if np.isfinite(x) else None


def critical_z(alpha: float, n_tests: int) -> float:
    """Two-sided Bonferroni critical value for ``n_tests`` tests at family-wise level ``alpha``."""
    if not 0 < alpha < 1:
        raise ValueError(f"alpha: {alpha} must be in (0, 1)")
    return float(norm.isf(alpha / (2 * max(int(n_tests), 1))))


def between_flight_scatter(values: np.ndarray, std: np.ndarray) -> float:
    """tau: robust flight-to-flight scatter beyond the reported standard errors (NaN if too few flights)."""
    v = values[np.isfinite(values)]
    if v.size < MIN_FLIGHTS_FOR_SCATTER:
        return float("nan")
    d = np.diff(v)
    mad = 1.4826 * np.median(np.abs(d - np.median(d)))
    total2 = (mad / np.sqrt(2.0)) ** 2
    s = std[np.isfinite(values) & np.isfinite(std)]
    reported2 = float(np.median(s ** 2)) if s.size else 0.0
    return float(np.sqrt(max(total2 - reported2, 0.0)))


def _slope(v: np.ndarray, sig: np.ndarray) -> tuple[float, float]:
    """Weighted least-squares slope per flight and its z (flight index as abscissa; NaN-free input)."""
    if v.size < 3:
        return float("nan"), 0.0
    x = np.arange(v.size, dtype=float)
    if not (sig > 0).all():
        return float("nan"), 0.0
    w = 1.0 / sig ** 2
    xm = (w * x).sum() / w.sum()
    sxx = (w * (x - xm) ** 2).sum()
    b = (w * (x - xm) * v).sum() / sxx
    return float(b), float(b * np.sqrt(sxx))


def _sigma(values: np.ndarray, std: np.ndarray, upto: int) -> tuple[np.ndarray, float]:
    """Per-flight sigma over flights ``0..upto`` and tau, from those flights only."""
    v, s = values[: upto + 1], std[: upto + 1]
    tau = between_flight_scatter(v, s)
    s0 = np.where(np.isfinite(s), s, 0.0)
    t2 = tau ** 2 if np.isfinite(tau) else 0.0
    return np.sqrt(s0 ** 2 + t2), tau


def assess(name: str, values, std=None, *, n_tests: int = 1, config: TrendConfig | None = None) -> Trend:
    """The sequential change test of one series (see module docstring)."""
    cfg = config or TrendConfig()
    v = np.asarray(values, dtype=float)
    s = np.full(v.shape, np.nan) if std is None else np.asarray(std, dtype=float)
    if v.ndim != 1 or s.shape != v.shape:
        raise ValueError(f"{name}: values and std must be 1-D of the same length, got {v.shape} and {s.shape}")
    z_crit = critical_z(cfg.alpha, n_tests)
    n = v.size
    z = np.full(n, np.nan)
    fin = np.flatnonzero(np.isfinite(v))
    base_idx = fin[: cfg.baseline]
    sig_all, tau = _sigma(v, s, n - 1)
    if fin.size < 2 or fin.size <= cfg.baseline:
        return Trend(name, v, s, sig_all, z, z_crit, tau, float("nan"), 0.0, tested=False,
                     reason=f"{fin.size} flight(s) with a value")
    changed_at, kind, direction, above_prev = None, "", 0, False
    for k in fin[cfg.baseline:]:
        sig, tau_k = _sigma(v, s, k)
        if not np.isfinite(tau_k):
            continue  # the flight-to-flight scatter is not measurable yet: reported errors alone are too optimistic
        ref = float(v[base_idx].mean())
        sig_ref = float(np.sqrt((sig[base_idx] ** 2).sum()) / base_idx.size)
        den = float(np.hypot(sig[k], sig_ref))
        if not den > 0:
            continue
        z[k] = (v[k] - ref) / den
        above = abs(z[k]) > z_crit
        if above and changed_at is None:
            idx = fin[fin <= k]
            _, bz = _slope(v[idx], np.maximum(sig[idx], 1e-300))
            if above_prev or abs(bz) > z_crit:
                changed_at, direction = int(k), int(np.sign(z[k]))
                kind = "trend" if _steady(v[idx]) else "step"
        above_prev = above
    idx = fin
    b, bz = _slope(v[idx], np.maximum(sig_all[idx], 1e-300))
    tested = bool(np.isfinite(z).any())
    return Trend(name, v, s, sig_all, z, z_crit, tau, b, bz, changed_at, kind, direction, tested,
                 "" if tested else "no uncertainty: no standard errors and too few flights to measure the scatter")


def _steady(v: np.ndarray) -> bool:
    """Most successive changes share the sign of the overall change (a drift, not one jump)."""
    d = np.diff(v)
    total = v[-1] - v[0]
    if d.size < 2 or total == 0:
        return False
    return bool(np.mean(np.sign(d) == np.sign(total)) >= 0.6 and np.max(np.abs(d)) < 0.6 * abs(total))


def assess_all(series: dict[str, tuple[np.ndarray, np.ndarray | None]],
               config: TrendConfig | None = None) -> dict[str, Trend]:
    """:func:`assess` for every series, the critical value corrected for all of them and all flights."""
    n_tests = sum(int(np.isfinite(np.asarray(v, dtype=float)).sum()) for v, _ in series.values())
    return {k: assess(k, v, s, n_tests=max(n_tests, 1), config=config) for k, (v, s) in series.items()}
