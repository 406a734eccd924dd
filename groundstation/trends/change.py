"""Change test for one quantity over a campaign's flights (an identified parameter or an effect estimate).

``assess(name, values, std)`` takes the per-flight values in flight order, ``(n,)``, with their
standard errors ``(n,)`` (NaN where unknown, e.g. effect estimates, which have none) and returns a
:class:`Trend`.

Uncertainty of one flight's value: ``sigma_i^2 = std_i^2 + tau^2``. ``tau`` is the flight-to-flight
scatter that the reported standard errors do not cover (different weather, excitation, a search in
another basin), measured from the series itself: the spread of the successive differences
about their median, divided by sqrt(2), the largest one left out when it is an outlier. Taking the differences about
their median keeps a steady trend out of the scatter; leaving out an outlying one keeps one jump out. Nothing is fitted
to a simulator: the scale is the data's own.

The test at flight ``k`` (sequential: only flights ``1..k`` are used, as it would have run on the
day) compares the value with the baseline (the mean of the first ``baseline`` flights):
``z_k = (v_k - ref) / sqrt(sigma_k^2 + sigma_ref^2)``. The quantity has *moved* at the first flight
where ``|z|`` exceeds the critical value on two consecutive flights, or on one flight together with a
significant weighted linear trend the same way over the flights before it, ``1..k-1`` (a steadily
growing deadband is caught at the flight where it leaves the band; a one-off outlier, even on the
latest flight, is not called a change: it cannot confirm itself). The critical value is
Bonferroni-corrected over the series tested (``n_tests``), a Student t with the degrees of freedom
of the scatter estimate; the repeated looks at one series are covered by asking for two
consecutive flights (or a significant trend) beyond it. A campaign of many unchanged parameters
then raises no false alarm at family-wise level about ``alpha``.
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np
from scipy.stats import norm
from scipy.stats import t as student_t

from groundstation.trends.settings import TrendConfig

#: fewest finite flights from which tau (the between-flight scatter) is measured; no flight is tested
#: before that: standard errors from one flight alone miss how much flights differ (another basin of
#: the search, other excitation), and a change called on them would be a false alarm
MIN_FLIGHTS_FOR_SCATTER = 4


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


def critical_z(alpha: float, n_tests: int, dof: int | None = None) -> float:
    """Two-sided Bonferroni critical value for ``n_tests`` tests at family-wise level ``alpha``;
    Student t with ``dof`` degrees of freedom when the scale was estimated from that few differences."""
    if not 0 < alpha < 1:
        raise ValueError(f"alpha: {alpha} must be in (0, 1)")
    p = alpha / (2 * max(int(n_tests), 1))
    return float(norm.isf(p) if dof is None else student_t.isf(p, max(int(dof), 1)))


def between_flight_scatter(values: np.ndarray, std: np.ndarray) -> tuple[float, int]:
    """(tau, degrees of freedom): flight-to-flight scatter beyond the reported standard errors.

    From the successive differences about their median (a steady drift cancels), the largest one
    dropped when there are five or more and it lies beyond 4 robust sigmas (one jump, e.g. a
    repair, does not inflate it): the variance
    of a difference is twice a flight's. ``(nan, 0)`` with fewer than ``MIN_FLIGHTS_FOR_SCATTER`` values.
    """
    v = values[np.isfinite(values)]
    if v.size < MIN_FLIGHTS_FOR_SCATTER:
        return float("nan"), 0
    d = np.diff(v)
    d = d - np.median(d)
    if d.size >= 5:  # one outlying difference (a jump) is left out; dropping any other would bias tau low
        mad = 1.4826 * float(np.median(np.abs(d)))
        if np.abs(d).max() > 4.0 * mad:
            d = np.delete(d, np.argmax(np.abs(d)))
    total2 = float(np.mean(d ** 2)) / 2.0
    s = std[np.isfinite(values) & np.isfinite(std)]
    reported2 = float(np.median(s ** 2)) if s.size else 0.0
    return float(np.sqrt(max(total2 - reported2, 0.0))), int(d.size - 1)


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


def _sigma(values: np.ndarray, std: np.ndarray, upto: int) -> tuple[np.ndarray, float, int]:
    """Per-flight sigma over flights ``0..upto``, tau and its degrees of freedom, from those flights only."""
    v, s = values[: upto + 1], std[: upto + 1]
    tau, dof = between_flight_scatter(v, s)
    s0 = np.where(np.isfinite(s), s, 0.0)
    t2 = tau ** 2 if np.isfinite(tau) else 0.0
    return np.sqrt(s0 ** 2 + t2), tau, dof


def assess(name: str, values, std=None, *, n_tests: int = 1, config: TrendConfig | None = None) -> Trend:
    """The sequential change test of one series (see module docstring)."""
    cfg = config or TrendConfig()
    v = np.asarray(values, dtype=float)
    s = np.full(v.shape, np.nan) if std is None else np.asarray(std, dtype=float)
    if v.ndim != 1 or s.shape != v.shape:
        raise ValueError(f"{name}: values and std must be 1-D of the same length, got {v.shape} and {s.shape}")
    n = v.size
    z = np.full(n, np.nan)
    fin = np.flatnonzero(np.isfinite(v))
    base_idx = fin[: cfg.baseline]
    sig_all, tau, dof_all = _sigma(v, s, n - 1)
    z_crit = critical_z(cfg.alpha, n_tests, dof_all if np.isfinite(tau) else None)
    if fin.size < 2 or fin.size <= cfg.baseline:
        return Trend(name, v, s, sig_all, z, z_crit, tau, float("nan"), 0.0, tested=False,
                     reason=f"{fin.size} flight(s) with a value")
    changed_at, kind, direction, above_prev = None, "", 0, False
    for k in fin[cfg.baseline:]:
        sig, tau_k, dof = _sigma(v, s, k)
        crit = critical_z(cfg.alpha, n_tests, dof)
        if not np.isfinite(tau_k):
            continue  # the flight-to-flight scatter is not measurable yet: reported errors alone are too optimistic
        ref = float(v[base_idx].mean())
        sig_ref = float(np.sqrt((sig[base_idx] ** 2).sum()) / base_idx.size)
        den = float(np.hypot(sig[k], sig_ref))
        if not den > 0:
            continue
        z[k] = (v[k] - ref) / den
        above = abs(z[k]) > crit
        if above and changed_at is None:
            idx = fin[fin <= k]
            before = fin[fin < k]  # the trend that confirms flight k is the one before it: an outlier
            _, bz = _slope(v[before], sig[before])  # at the end of a series does not confirm itself
            if above_prev or (abs(bz) > crit and np.sign(bz) == np.sign(z[k])):
                changed_at, direction = int(k), int(np.sign(z[k]))
                kind = "trend" if _steady(v[idx]) else "step"
        above_prev = above
    idx = fin
    b, bz = _slope(v[idx], sig_all[idx])
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
    """:func:`assess` for every series, the critical value corrected for the number of series."""
    n_tests = sum(bool(np.isfinite(np.asarray(v, dtype=float)).any()) for v, _ in series.values())
    return {k: assess(k, v, s, n_tests=max(n_tests, 1), config=config) for k, (v, s) in series.items()}


def campaign_summary(aircraft: str, labels: list[str], trends: dict[str, Trend]) -> dict:
    """The ``heli-trends/1`` document of a campaign (``trends.json``; the service publishes it on
    ``heli/{vehicle}/trends``): flight labels, the series that changed, and every series' summary."""
    return {"schema": "heli-trends/1", "aircraft": aircraft, "flights": labels,
            "changed": [t.summary() for t in trends.values() if t.changed],
            "series": {k: t.summary() for k, t in trends.items()}}
