"""``groundstation log-info LOG [--json]``: flights, message rates, gaps, corruption and loss of a log.

Reads .tlog, dataflash .bin, PX4 .px4log or PX4 .ulg through :func:`firmware_interface.readers.load_log` and
prints one JSON object (``--json``) or the same as readable tables (rich)::

    {"source": ..., "flights": [{"index", "start_s", "end_s", "duration_s", "in_air_s", "on_ground_evidence",
                                 "in_air_by_height_s" (only where the evidence overrules height)}],
     "messages": {TYPE: {"count", "rate_hz"}},
     "gaps": [{"message", "start_s", "duration_s"}], "gaps_total": n,
     "corrupt_bytes": n, "truncated_tail_bytes": n, "fc_reboots": n,
     "packet_loss": {"lost": n, "by_source": {"sysid:compid": n}},
     "link": {"loss_pct", "outages", "outages_per_min", "median_outage_s", "longest_outage_s", "lost_per_outage",
              "bridge_limit_s", "outages_split"},
     "dropouts": [{"start_s", "duration_s"}], "notes": [str],
     "chirps": [{"index", "axis", "sid_axis", "magnitude", "f_start_hz", "f_stop_hz", "start_s", "duration_s"}]}

Times are on the FC clock (s). ``rate_hz`` is the mean rate over the message's own span (series
types) or over the log span (other types). A gap is an interval longer than 3 median sample periods
of that series (a GPS outage shows as a GPS_RAW_INT gap). A flight "in the air" by height alone whose
accelerometers and body rates show no rotor running and no motion (a ground run) has ``in_air_s`` 0
and says why in ``on_ground_evidence``. ``dropouts`` are the intervals the FC's own
logger says it lost (ULog); empty for other logs. ``link``: loss rate, the link's outages and their
burst length, and how many data preparation bridges (:func:`groundstation.loginfo.link_summary`). Leaves analysis beyond this to ``groundstation.dsp``.
"""

from __future__ import annotations

import argparse
from typing import Any

from rich.console import Console
from rich.table import Table

from firmware_interface.readers import load_log
from groundstation.jsonio import dumps
from groundstation.loginfo import (  # noqa: F401 - importable from here as before
    MAX_GAPS_LISTED,
    _flight,
    _ground_evidence,
    _num,
    summarise,
)


def add_arguments(p: argparse.ArgumentParser) -> None:
    p.add_argument("log", help="the log file")
    p.add_argument("--json", action="store_true", help="print one JSON object")


def _print_tables(info: dict[str, Any]) -> None:
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
        loss = lk["loss_pct"] if lk["loss_pct"] is not None else float("nan")
        con.print(f"link: {loss:.1f} % of packets lost in {lk['outages']} outages ({lk['outages_per_min']:.1f}/min, "
                  f"median {lk['median_outage_s']:.2f} s, longest {lk['longest_outage_s']:.2f} s, "
                  f"~{lk['lost_per_outage']:.1f} packets each); {lk['outages'] - lk['outages_split']} bridged by data "
                  f"preparation (not counted in any cost), {lk['outages_split']} longer than the "
                  f"{lk['bridge_limit_s']:g} s bridge ({lk.get('bridge_why', '[prepare] max_input_bridge_s')})")
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
    info = summarise(load_log(args.log, all_topics=True))
    if args.json:
        print(dumps(info))
    else:
        _print_tables(info)
    return 0
