"""Flights in a log (armed intervals, in-air time) and the last step of every reader: series sorted by
FC time and the flights found (``_finish``). Shared by :mod:`firmware_interface.readers` and
:mod:`firmware_interface.ulog`, so neither imports the other."""

from __future__ import annotations

import math

import numpy as np

from firmware_interface.samples import FlightInterval, LinkStats, LogData, Series


def _finish(source: str, series: dict[str, Series], counts: dict[str, int], stats: LinkStats) -> LogData:
    sorted_series: dict[str, Series] = {}
    for name, s in series.items():
        order = np.argsort(s.t_fc_s, kind="stable")
        if np.all(order == np.arange(len(order))):
            sorted_series[name] = s
        else:
            sorted_series[name] = Series(s.t_fc_s[order], s.t_host_s[order],
                                         {k: v[order] for k, v in s.columns.items()})
    return LogData(source, sorted_series, counts, stats, find_flights(sorted_series))


# ---------------------------------------------------------------------- flights


def _span(series: dict[str, Series]) -> tuple[float, float] | None:
    lo, hi = math.inf, -math.inf
    for s in series.values():
        if len(s):
            t = s.t_fc_s[np.isfinite(s.t_fc_s)]
            if t.size:
                lo, hi = min(lo, float(t[0])), max(hi, float(t[-1]))
    return (lo, hi) if lo <= hi else None


def _hold_intervals(t: np.ndarray, flag: np.ndarray, lo: float, hi: float) -> list[tuple[float, float]]:
    """Intervals within [lo, hi] where a sample-and-hold boolean signal is true."""
    sel = (t >= lo) & (t <= hi)
    t, flag = t[sel], flag[sel]
    out: list[tuple[float, float]] = []
    start: float | None = None
    for k in range(len(t)):
        if flag[k] and start is None:
            start = float(t[k])
        elif not flag[k] and start is not None:
            out.append((start, float(t[k])))
            start = None
    if start is not None:
        out.append((start, hi))
    return out


def _runs(flag: np.ndarray) -> list[tuple[int, int]]:
    """(first, last) index of each run of True."""
    d = np.diff(np.r_[0, flag.astype(np.int8), 0])
    return list(zip(np.flatnonzero(d == 1), np.flatnonzero(d == -1) - 1, strict=True))


def find_flights(series: dict[str, Series], *, in_air_height_m: float = 0.3) -> list[FlightInterval]:
    """Armed intervals (FC clock) with their in-air time; see the module docstring."""
    span = _span(series)
    if span is None:
        return []
    hb = series.get("HEARTBEAT")
    intervals: list[tuple[float, float]] = []
    if hb is not None and len(hb):
        armed = hb["armed"] > 0.5
        t = hb.t_fc_s
        for i0, i1 in _runs(armed):
            end = float(t[i1 + 1]) if i1 + 1 < len(t) else span[1]
            intervals.append((float(t[i0]), end))
    else:
        intervals.append(span)
    flights = []
    for k, (lo, hi) in enumerate(intervals):
        air = _in_air(series, lo, hi, in_air_height_m)
        in_air_s = math.nan if air is None else float(sum(b - a for a, b in air))
        flights.append(FlightInterval(k, lo, hi, in_air_s, tuple(air or ())))
    return flights


def _in_air(series: dict[str, Series], lo: float, hi: float, height_m: float
            ) -> list[tuple[float, float]] | None:
    """In-air intervals of the armed interval [lo, hi]: the FC's landed state where it reports one,
    the height above the take-off ground elsewhere, None when neither is logged.

    A landed-state stream can begin well after arming (its stream request lost on a radio link and
    answered on a retry): the armed time before its first message is then judged by height, and an
    interval in the air at that message joins the landed state's first one."""
    ess = series.get("EXTENDED_SYS_STATE")
    if ess is not None and len(ess):
        ls = ess["landed_state"]
        sel = (ess.t_fc_s >= lo) & (ess.t_fc_s <= hi)
        if np.any(sel & (ls > 0)):
            air = _hold_intervals(ess.t_fc_s, (ls >= 2) & (ls <= 4), lo, hi)
            t = ess.t_fc_s[sel]
            late = max(1.0, 3.0 * float(np.median(np.diff(t)))) if t.size > 1 else 1.0
            if t[0] - lo <= late:
                return air
            head = _height_air(series, lo, hi, height_m, until=float(t[0])) or []
            if head and air and head[-1][1] == air[0][0]:
                return [*head[:-1], (head[-1][0], air[0][1]), *air[1:]]
            return head + air
    return _height_air(series, lo, hi, height_m)


def _height_air(series: dict[str, Series], lo: float, hi: float, height_m: float, until: float | None = None,
                dip_s: float = 1.0) -> list[tuple[float, float]] | None:
    """Intervals of [lo, until or hi] more than ``height_m`` above the height of the first second of
    [lo, hi], from LOCAL_POSITION_NED z or GLOBAL_POSITION_INT relative altitude; None without them.

    Dips below the height shorter than ``dip_s`` (height noise at take-off and landing) do not split
    an interval, as a land detector's own hysteresis would not."""
    for name, col, sign in (("LOCAL_POSITION_NED", "z_m", -1.0), ("GLOBAL_POSITION_INT", "relative_alt_m", 1.0)):
        s = series.get(name)
        if s is None or not len(s):
            continue
        sel = (s.t_fc_s >= lo) & (s.t_fc_s <= hi) & np.isfinite(s[col])
        if not np.any(sel):
            continue
        t, h = s.t_fc_s[sel], sign * s[col][sel]
        h0 = float(np.median(h[t <= t[0] + 1.0]))
        out: list[tuple[float, float]] = []
        for a, b in _hold_intervals(t, h - h0 > height_m, lo, hi if until is None else until):
            if out and a - out[-1][1] < dip_s:
                out[-1] = (out[-1][0], b)
            else:
                out.append((a, b))
        return out
    return None
