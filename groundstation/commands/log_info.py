"""``groundstation log-info LOG [--json]``: flights, message rates, gaps, corruption and loss of a log.

Reads .tlog, dataflash .bin, PX4 .px4log or PX4 .ulg through :func:`firmware_interface.readers.load_log` and
prints one JSON object (``--json``) or the same as readable tables (rich)::

    {"source": ..., "flights": [{"index", "start_s", "end_s", "duration_s", "in_air_s", "on_ground_evidence",
                                 "in_air_by_height_s" (only where the evidence overrules height)}],
     "messages": {TYPE: {"count", "rate_hz"}},
     "gaps": [{"message", "start_s", "duration_s"}], "gaps_total": n,
     "corrupt_bytes": n, "truncated_tail_bytes": n, "fc_reboots": n,
     "packet_loss": {"lost": n, "by_source": {"sysid:compid": n}},
     "link": {"loss_pct", "outages", "outages_per_min", "median_outage_s", "longest_outage_s",
              "lost_per_outage", "bridge_limit_s", "outages_split"},
     "dropouts": [{"start_s", "duration_s"}], "notes": [str],
     "chirps": [{"index", "axis", "sid_axis", "magnitude", "f_start_hz", "f_stop_hz", "start_s", "duration_s"}]}

Times are on the FC clock (s). ``rate_hz`` is the mean rate over the message's own span (series
types) or over the log span (other types). A gap is an interval longer than 3 median sample periods
of that series (a GPS outage shows as a GPS_RAW_INT gap). A flight "in the air" by height alone whose
accelerometers and body rates show no rotor running and no motion (a ground run) has ``in_air_s`` 0
and says why in ``on_ground_evidence``. ``dropouts`` are the intervals the FC's own
logger says it lost (ULog); empty for other logs. ``link``: the link as a radio delivers it - packets
lost (MAVLink sequence numbers), outages (the holes of the telemetry streams merged where they
overlap: a fade takes every type at once), their length and packets lost per outage (the burst
length), and how many are longer than the input bridge of data preparation (``[prepare]
max_input_bridge_s``; shorter ones are bridged and their samples not counted). Leaves analysis
beyond this to ``groundstation.dsp``.
"""

from __future__ import annotations

import argparse
import math
from typing import Any

import numpy as np

HELP = "summarise a flight log (.tlog, .bin, .px4log, .ulg): flights, message rates, gaps, corruption"

MAX_GAPS_LISTED = 200


def add_arguments(p: argparse.ArgumentParser) -> None:
    p.add_argument("log", help="the log file")
    p.add_argument("--json", action="store_true", help="print one JSON object")


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
    """Loss rate, outages (bursts) and what data preparation does with them (see the module docstring)."""
    from groundstation.dsp.prepare import PrepConfig

    limit = PrepConfig().max_input_bridge_s if bridge_limit_s is None else bridge_limit_s
    st = log.stats
    total = int(st.packets) + int(st.packets_lost)
    loss = 100.0 * st.packets_lost / total if total and st.packets_lost else (0.0 if total else math.nan)
    streams = [log.series[n] for n in _STREAMS if n in log.series and len(log.series[n]) > 3]
    out: dict[str, Any] = {"loss_pct": _num(loss), "outages": 0, "outages_per_min": None, "median_outage_s": None,
                           "longest_outage_s": None, "lost_per_outage": None, "bridge_limit_s": limit,
                           "outages_split": 0}
    if not streams:
        return out
    # a stream's hole: an interval over 1.5 of its periods (a message lost); outages: the holes of
    # the streams merged where they overlap (a fade takes out every type at once)
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
    from groundstation.dsp.prepare import PrepConfig, _land_detector, airborne_evidence

    air = list(getattr(flight, "in_air_intervals_fc_s", ()) or ())
    if not air or _land_detector(log, flight):
        return None
    flying, why = airborne_evidence(log, float(air[0][0]), float(air[-1][1]), PrepConfig())
    return None if flying else f"in the air by height only, but on the ground: {why}"


def _print_tables(info: dict[str, Any]) -> None:
    from rich.console import Console
    from rich.table import Table

    con = Console()
    con.print(f"[bold]{info['source']}[/bold]")
    ft = Table(title="flights (FC clock)")
    for c in ("#", "start s", "end s", "duration s", "in air s"):
        ft.add_column(c, justify="right")
    for f in info["flights"]:
        ft.add_row(str(f["index"]), *(("-" if f[k] is None else f"{f[k]:.1f}")
                                      for k in ("start_s", "end_s", "duration_s", "in_air_s")))
    con.print(ft)
    for f in info["flights"]:
        if f.get("on_ground_evidence"):
            by_h = f.get("in_air_by_height_s")
            height = f" (height alone said {by_h:.1f} s)" if by_h is not None else ""
            con.print(f"flight {f['index']}: 0 s in the air{height}; {f['on_ground_evidence']}")
    mt = Table(title="messages")
    for c in ("type", "count", "rate Hz"):
        mt.add_column(c, justify="right" if c != "type" else "left")
    for name, m in info["messages"].items():
        mt.add_row(name, str(m["count"]), "-" if m["rate_hz"] is None else f"{m['rate_hz']:.2f}")
    con.print(mt)
    if info["gaps"]:
        gt = Table(title=f"gaps > 3 sample periods ({info['gaps_total']} total)")
        for c in ("message", "start s", "duration s"):
            gt.add_column(c)
        for g in info["gaps"][:30]:
            gt.add_row(g["message"], f"{g['start_s']:.3f}", f"{g['duration_s']:.3f}")
        con.print(gt)
    pl = info["packet_loss"]
    con.print(f"corrupt bytes {info['corrupt_bytes']}, truncated tail {info['truncated_tail_bytes']} B, "
              f"packets lost {pl['lost']} {pl['by_source'] or ''}, FC reboots {info['fc_reboots']}")
    lk = info.get("link") or {}
    if lk.get("outages"):
        con.print(f"link: {lk['loss_pct'] if lk['loss_pct'] is not None else float('nan'):.1f} % of packets lost in "
                  f"{lk['outages']} outages ({lk['outages_per_min']:.1f}/min, median {lk['median_outage_s']:.2f} s, "
                  f"longest {lk['longest_outage_s']:.2f} s, ~{lk['lost_per_outage']:.1f} packets each); "
                  f"{lk['outages'] - lk['outages_split']} bridged by data preparation (not counted in any cost), "
                  f"{lk['outages_split']} longer than the {lk['bridge_limit_s']:g} s bridge ([prepare] max_input_bridge_s)")
    if info["chirps"]:
        ct = Table(title="system-identification chirps (SYSID mode)")
        for c in ("#", "axis", "from Hz", "to Hz", "start s", "duration s", "magnitude"):
            ct.add_column(c, justify="right")
        for c in info["chirps"]:
            ct.add_row(str(c["index"]), c["axis"], f"{c['f_start_hz']:g}", f"{c['f_stop_hz']:g}",
                       f"{c['start_s']:.1f}", f"{c['duration_s']:.1f}", f"{c['magnitude']:g}")
        con.print(ct)
    for note in info["notes"]:
        con.print(note, markup=False, highlight=False, soft_wrap=True)


def run(args: argparse.Namespace) -> int:
    from firmware_interface.readers import load_log

    info = summarise(load_log(args.log, all_topics=True))
    if args.json:
        from groundstation.jsonio import dumps

        print(dumps(info))
    else:
        _print_tables(info)
    return 0
