"""``groundstation bench rerun``: how efficient and how readable a saved Rerun recording is.

With ``--rrd PATH`` (e.g. ``demo_out/demo.rrd``) it inspects that recording; without, it writes a
synthetic session of ``--minutes`` at 50 Hz through :class:`groundstation.sinks.rerun_sink.RerunSink`
in the service's batch size (one call per live window hop) with a flight every three minutes, and
inspects that. Prints Rerun's own chunk check (``rerun rrd stats``: effective chunks over the
theoretical lower bound; target <= 10x), the time to read the file back, whether every plot title
carries a unit, and the tab and FC-time span the recording opens on. Only measures.
"""

from __future__ import annotations

import argparse
import re
import tempfile
import time
from pathlib import Path

import numpy as np

from benchkit.rerun_inspect import chunk_check, read_layout
from groundstation.sinks.rerun_sink import RerunSink

HELP = "rerun: chunk count vs Rerun's lower bound, read-back time, units in view titles, opening view"


def add_arguments(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("--rrd", type=Path, default=None, help="inspect this .rrd instead of a synthetic session")
    parser.add_argument("--minutes", type=float, default=6.0, help="length of the synthetic session")
    parser.add_argument("--hop-s", type=float, default=0.5, help="rows per sink call = hop x 50 Hz")


def _synthetic(path: Path, minutes: float, hop_s: float) -> float:
    """Write the synthetic session; returns the sink's CPU seconds per minute of flight data."""
    t = np.arange(int(minutes * 60 * 50)) * 0.02
    y = np.column_stack([np.sin(0.3 * t + k) for k in range(8)])
    sink = RerunSink("heli", "save", str(path))
    step = max(1, int(hop_s * 50))
    flight_s = 180.0
    c0 = time.process_time()
    for i in range(0, len(t), step):
        s = slice(i, i + step)
        sink.log_rows(t[s], 1.7e9 + t[s], 0.1 * y[s, :4], y[s], "raw")
        sink.log_rows(t[s], 1.7e9 + t[s], None, y[s], "smoothed")
        k = int(t[i] // flight_s)
        if t[i] % flight_s < hop_s:
            sink.log_flight_state("armed" if k % 2 == 0 else "on ground", t[i])
        if (t[i] + hop_s) % flight_s < hop_s:
            sink.flight_ended(k + 1, k * flight_s + 5.0, t[i])
    sink.close()
    return (time.process_time() - c0) / max(minutes, 1e-9)


def run(args: argparse.Namespace) -> int:
    with tempfile.TemporaryDirectory(prefix="bench-rerun-") as d:
        path = args.rrd
        if path is None:
            path = Path(d) / "session.rrd"
            cpu = _synthetic(path, args.minutes, args.hop_s)
            print(f"synthetic session: {args.minutes:g} min at 50 Hz, sink CPU {cpu * 1000 / 60:.2f} ms per s of data")
        check = chunk_check(path)
        t0 = time.perf_counter()
        lay = read_layout(path)
        read_s = time.perf_counter() - t0
        views = [v for c in lay.children(lay.root) for v in lay.views_under(c)]
        plots = [v for v in views if v.kind in ("TimeSeries", "BarChart")]
        no_unit = [v.name for v in plots if not re.search(r"\[[^\]]+\]", v.name)]
        opening = lay.opening_tab()
        spans = sorted({v.fc_range_s for v in lay.views_under(opening) if v.kind == "TimeSeries" and v.fc_range_s})
        print(f"{path.name}: {check.effective} chunks, lower bound {check.lower_bound} = {check.factor:.1f}x "
              f"(target <= 10); read back in {read_s:.2f} s ({sum(lay.rows.values())} rows)")
        print(f"plot titles with a unit: {len(plots) - len(no_unit)}/{len(plots)}"
              + (f" (missing: {', '.join(no_unit[:5])})" if no_unit else ""))
        span = ", ".join(f"{a:.1f}-{b:.1f} s" for a, b in spans) or "whole timeline"
        print(f"opens on: {lay.name(opening)!r}, plots over FC time {span}")
    return 0
