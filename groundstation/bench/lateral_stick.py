"""``groundstation bench lateral-stick SEGMENTS.csv[.xz] [--aircraft FILE]``.

What a logged lateral stick is worth to held-out prediction: the flight's segments (a CSV with a
``segment`` column, as in ``tests/data/trex550/flight1_segments_filtered.csv.xz``: the stick and gyro
columns of two windows of one flight) are identified one at a time with the same structure and
settings, and each model predicts the *other* segment (:func:`groundstation.sysid.heldout.predict`:
windows started from the measured states, eq.-19 match per channel). Every pair runs twice: with the
lateral stick, and with it held at trim (what a log without it gives the identification). The rest is
the same: the trims (the median of each column over all segments), the aircraft file's prior, input
shift and identification settings (``--set KEY=VALUE`` overrides these), the seed.

Prints a table per pair (match per channel without / with the lateral stick, and the gain);
``--json`` writes them too. Collective and vertical velocity are not in such a file: w is unmeasured
and the collective held at trim in both runs.
"""

from __future__ import annotations

import argparse
import json
import lzma
from pathlib import Path
from typing import Any

import numpy as np
from rich.console import Console
from rich.table import Table

from groundstation.bench.heldout import _identify_config
from groundstation.dsp.prepare import prepared_from_arrays
from groundstation.dsp.timeskew import shift_inputs
from groundstation.pipeline import load_aircraft
from groundstation.sysid.heldout import predict
from groundstation.sysid.identify import identify

HELP = "held-out prediction of one segment from another, with and without the lateral stick"

#: input column index (lat lon col ped) -> CSV column
INPUT_COLUMNS = {0: "lat_cyclic_norm_f", 1: "lon_cyclic_norm_f", 3: "pedal_norm_f"}
#: output column index (u v w p q r theta phi) -> CSV column
OUTPUT_COLUMNS = {3: "p_radps_f", 4: "q_radps_f", 5: "r_radps_f", 6: "theta_rad_f", 7: "phi_rad_f"}


def add_arguments(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("segments", type=Path, help="CSV (or .csv.xz) with time_s, segment and the stick/gyro columns")
    parser.add_argument("--aircraft", type=Path, default=None, help="aircraft TOML (prior, input shift, identify settings)")
    parser.add_argument("--rate-hz", type=float, default=50.0, help="grid the segments are interpolated to (default 50)")
    parser.add_argument("--train", action="append", default=[], metavar="SEGMENT",
                        help="identify only on these segments (default: each in turn)")
    parser.add_argument("--seed", type=int, default=0)
    parser.add_argument("--set", action="append", default=[], metavar="KEY=VALUE",
                        help="override an identification setting (JSON value), as in bench heldout")
    parser.add_argument("--json", type=Path, default=None, help="write the figures as JSON")


def load_segments(path: Path) -> dict[str, dict[str, np.ndarray]]:
    """The CSV's numeric columns per segment name; ``#`` lines are comments."""
    opener: Any = lzma.open if path.suffix == ".xz" else open
    with opener(path, "rt") as f:
        rows = [ln.strip().split(",") for ln in f if ln.strip() and not ln.startswith("#")]
    head, body = rows[0], rows[1:]
    need = {"time_s", "segment", *INPUT_COLUMNS.values(), *OUTPUT_COLUMNS.values()}
    if not need <= set(head):
        raise ValueError(f"{path}: missing columns {sorted(need - set(head))}")
    k_seg = head.index("segment")
    out: dict[str, dict[str, np.ndarray]] = {}
    for name in dict.fromkeys(r[k_seg] for r in body):
        sel = [r for r in body if r[k_seg] == name]
        out[name] = {c: np.array([float(r[j]) for r in sel]) for j, c in enumerate(head) if c in need - {"segment"}}
    return out


def _trims(segs: dict[str, dict[str, np.ndarray]]) -> dict[str, float]:
    """Median of each stick and attitude column over all segments (rates keep their zero)."""
    cols = [*INPUT_COLUMNS.values(), "theta_rad_f", "phi_rad_f"]
    return {c: float(np.median(np.concatenate([s[c] for s in segs.values()]))) for c in cols}


def segment_prepared(seg: dict[str, np.ndarray], trims: dict[str, float], *, lateral: bool, rate_hz: float,
                     shift_s: float = 0.0, name: str = "segment") -> Any:
    """One segment on a uniform grid as prepared data (lateral stick at trim unless ``lateral``)."""
    t = seg["time_s"]
    tg = np.arange(t[0], t[-1], 1.0 / rate_hz)
    u = np.zeros((tg.size, 4))
    y = np.full((tg.size, 8), np.nan)
    for j, c in INPUT_COLUMNS.items():
        if j or lateral:
            u[:, j] = np.interp(tg, t, seg[c]) - trims[c]
    for j, c in OUTPUT_COLUMNS.items():
        y[:, j] = np.interp(tg, t, seg[c]) - trims.get(c, 0.0)
    prepared = prepared_from_arrays(u, y, 1.0 / rate_hz, smooth_passes=0, source=name)
    return shift_inputs(prepared, shift_s)


def _pair(segs: dict, trims: dict, train: str, val: str, args: argparse.Namespace, aircraft: Any, cfg: Any) -> dict:
    shift = float(aircraft.prep_config().input_shift_s) if aircraft is not None else 0.0
    row: dict[str, Any] = {"train": train, "predict": val}
    for lateral in (False, True):
        prep = {n: segment_prepared(segs[n], trims, lateral=lateral, rate_hz=args.rate_hz, shift_s=shift, name=n)
                for n in (train, val)}
        model = identify(prep[train], seed=args.seed, prior=aircraft.prior if aircraft else None, config=cfg)
        pred = predict(model, prep[val])
        row["with_lateral" if lateral else "without_lateral"] = {
            "match": dict(pred.match), "mean": float(pred.mean_match),
            "lateral_terms": {k: float(v) for k, v in model.params.items() if k.endswith("_lat")}}
    return row


def run(args: argparse.Namespace) -> int:
    aircraft = load_aircraft(args.aircraft)
    cfg = _identify_config(args.set, aircraft)
    segs = load_segments(args.segments)
    if len(segs) < 2:
        raise ValueError(f"{args.segments}: needs two segments or more, found {list(segs)}")
    trims = _trims(segs)
    trains = args.train or list(segs)
    rows = [_pair(segs, trims, a, b, args, aircraft, cfg) for a in trains for b in segs if b != a]
    con = Console()
    for r in rows:
        _print_pair(con, r)
    if args.json:
        args.json.write_text(json.dumps({"segments": str(args.segments), "pairs": rows}, indent=1))
    return 0


def _print_pair(con: Any, row: dict[str, Any]) -> None:
    t = Table(title=f"identified on {row['train']}, predicting {row['predict']} (eq.-19 match %)")
    t.add_column("channel")
    for h in ("without lateral stick", "with lateral stick", "gain"):
        t.add_column(h, justify="right")
    a, b = row["without_lateral"], row["with_lateral"]
    for c in a["match"]:
        t.add_row(c, f"{a['match'][c]:.1f}", f"{b['match'][c]:.1f}", f"{b['match'][c] - a['match'][c]:+.1f}")
    t.add_row("mean", f"{a['mean']:.1f}", f"{b['mean']:.1f}", f"{b['mean'] - a['mean']:+.1f}")
    con.print(t)
