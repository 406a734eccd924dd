"""What a flight log holds (the figures of ``groundstation log-info`` and of the flight report): flights,
in-air time, message rates, gaps, link loss. Reads nothing itself: it summarises a read log."""

from __future__ import annotations

import math
from typing import Any

import numpy as np

from groundstation.dsp.prepare import PrepConfig, _land_detector, airborne_evidence, bridge_why, derive_bridge

MAX_GAPS_LISTED = 200


def _num(x: float) -> float | None:
    return None if not math.isfinite(x) else round(float(x), 6)


def summarise(log: Any) -> dict[str, Any]:
    """The log-info dict of a :class:`firmware_interface.samples.LogData`."""
    spans = [(float(s.t_fc_s[0]), float(s.t_fc_s[-1])) for s in log.series.values()
             if len(s) and np.isfinite(s.t_fc_s[0]) and np.isfinite(s.t_fc_s[-1])]
    log_span = (max(b for _, b in spans) - min(a for a, _ in spans)) if spans else math.nan
    messages: dict[str, dict[str, Any]] = {}
    for name, count in sorted(log.message_counts.items()):
        s = log.series.get(name)
        rate = math.nan
        if s is not None and len(s) >= 2:
            span = float(s.t_fc_s[-1] - s.t_fc_s[0])
            rate = (len(s) - 1) / span if span > 0 else math.nan
        elif log_span and log_span > 0:
            rate = count / log_span
        messages[name] = {"count": int(count), "rate_hz": _num(rate)}
    gaps: list[dict[str, Any]] = []
    for name, s in log.series.items():
        if len(s) < 3:
            continue
        t = s.t_fc_s[np.isfinite(s.t_fc_s)]
        dt = np.diff(t)
        pos = dt[dt > 0]
        if not pos.size:
            continue
        period = float(np.median(pos))
        for k in np.flatnonzero(dt > 3 * period):
            gaps.append({"message": name, "start_s": _num(t[k]), "duration_s": _num(dt[k])})
    gaps.sort(key=lambda g: (g["start_s"] if g["start_s"] is not None else 0.0, g["message"]))
    st = log.stats
    return {
        "source": log.source,
        "flights": [_flight(log, f) for f in log.flights],
        "messages": messages,
        "gaps": gaps[:MAX_GAPS_LISTED],
        "gaps_total": len(gaps),
        "corrupt_bytes": int(st.corrupt_bytes),
        "truncated_tail_bytes": int(st.truncated_tail_bytes),
        "fc_reboots": int(st.fc_reboots),
        "packet_loss": {"lost": int(st.packets_lost), "by_source": dict(st.loss_by_source)},
        "link": link_summary(log),
        "dropouts": [{"start_s": _num(a), "duration_s": _num(d)} for a, d in getattr(log, "dropouts_s", [])],
        "notes": list(getattr(log, "notes", [])),
        "chirps": [{"index": c.index, "axis": c.axis_name, "sid_axis": c.axis, "magnitude": _num(c.magnitude),
                    "f_start_hz": _num(c.f_start_hz), "f_stop_hz": _num(c.f_stop_hz),
                    "start_s": _num(c.start_fc_s), "duration_s": _num(c.duration_s)}
                   for c in getattr(log, "chirps", [])],
    }


#: the telemetry streams an analysis needs: their common outages are the link's
_STREAMS = ("ATTITUDE", "SERVO_OUTPUT_RAW", "LOCAL_POSITION_NED", "GLOBAL_POSITION_INT", "RC_CHANNELS")


def link_summary(log: Any, bridge_limit_s: float | None = None) -> dict[str, Any]:
    """The link as a radio delivers it: packets lost (MAVLink sequence numbers), outages (the holes of
    the telemetry streams - intervals over 1.5 of a stream's period - merged where they overlap: a fade
    takes every type at once), their length, packets lost per outage (the burst length), and how many
    are longer than data preparation's input bridge (``[prepare] max_input_bridge_s``, else derived from the
    log's inputs and the default rotor, :func:`groundstation.dsp.prepare.derive_bridge`; shorter ones are
    bridged and their samples left out of every cost)."""
    bridge = derive_bridge([log], PrepConfig(max_input_bridge_s=bridge_limit_s))
    limit = float(bridge["limit_s"])
    st = log.stats
    total = int(st.packets) + int(st.packets_lost)
    loss = 100.0 * st.packets_lost / total if total and st.packets_lost else (0.0 if total else math.nan)
    streams = [log.series[n] for n in _STREAMS if n in log.series and len(log.series[n]) > 3]
    out: dict[str, Any] = {"loss_pct": _num(loss), "outages": 0, "outages_per_min": None, "median_outage_s": None,
                           "longest_outage_s": None, "lost_per_outage": None, "bridge_limit_s": limit,
                           "outages_split": 0, "bridge_rule": bridge["rule"], "bridge_why": bridge_why(bridge)}
    iv: list[tuple[float, float]] = []
    t_lo, t_hi = math.inf, -math.inf
    for s in streams:
        t = s.t_fc_s[np.isfinite(s.t_fc_s)]
        d = np.diff(t)
        if not (d > 0).any():
            continue
        period = float(np.median(d[d > 0]))
        t_lo, t_hi = min(t_lo, float(t[0])), max(t_hi, float(t[-1]))
        k = np.flatnonzero(d > 1.5 * period)
        iv += list(zip(t[k].tolist(), t[k + 1].tolist(), strict=True))
    iv.sort()
    merged: list[list[float]] = []
    for a, b in iv:
        if merged and a <= merged[-1][1]:
            merged[-1][1] = max(merged[-1][1], b)
        else:
            merged.append([a, b])
    hole = np.array([b - a for a, b in merged])
    span_min = (t_hi - t_lo) / 60.0 if t_hi > t_lo else 0.0
    out.update(outages=int(hole.size), outages_per_min=_num(hole.size / span_min) if span_min > 0 else None,
               median_outage_s=_num(float(np.median(hole))) if hole.size else None,
               longest_outage_s=_num(float(hole.max())) if hole.size else None,
               lost_per_outage=_num(st.packets_lost / hole.size) if hole.size else None,
               outages_split=int((hole > limit).sum()))
    return out


def _flight(log: Any, f: Any) -> dict[str, Any]:
    """One row of ``flights``. Where height alone says "in the air" and the IMU and body rates say the
    aircraft never left the ground, ``in_air_s`` is 0, the height's figure is kept as
    ``in_air_by_height_s`` and ``on_ground_evidence`` says why."""
    evidence = _ground_evidence(log, f)
    row = {"index": f.index, "start_s": _num(f.start_fc_s), "end_s": _num(f.end_fc_s),
           "duration_s": _num(f.duration_s), "in_air_s": _num(f.in_air_s), "on_ground_evidence": evidence}
    if evidence is not None:
        row["in_air_by_height_s"] = row["in_air_s"]
        row["in_air_s"] = 0.0
    return row


def _ground_evidence(log: Any, flight: Any) -> str | None:
    """Where only height says "in the air": why the aircraft did not fly (no rotor vibration, no body
    motion), else None."""
    air = list(getattr(flight, "in_air_intervals_fc_s", ()) or ())
    if not air or _land_detector(log, flight):
        return None
    flying, why = airborne_evidence(log, float(air[0][0]), float(air[-1][1]), PrepConfig())
    return None if flying else f"in the air by height only, but on the ground: {why}"
