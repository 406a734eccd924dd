"""``groundstation bench heldout LOG... [--aircraft FILE] [--folds 5] [--train-first-s 60]``.

Held-out prediction on a real flight, the figure that says whether a model predicts the aircraft:

* ``--folds k`` contiguous blocks of the in-air time (train on k-1 blocks, predict the left-out
  one), and a "train on the first ``--train-first-s`` seconds, predict the rest" split;
* for each split, (a) the project's identification (``identify`` with the aircraft file's prior)
  and (b) the plain output-error reference (multi-start least squares of the same structure, no
  prior, :mod:`benchkit.reference`): the floor to beat;
* the project minus the reference per split, with a bootstrap interval over the held-out windows and
  the difference without the one window that counts most (:mod:`benchkit.paired`);
* ``--input-shift-s`` advances the logged inputs of every split (a time skew between the logged
  channels, :mod:`groundstation.dsp.timeskew`); ``auto`` measures it per split on the training part
  (:func:`benchkit.reference.shift_profile`), and the held-out part gets the same shift;
* with ``--linear``, (c) an unconstrained linear predictor from the logged inputs and the window's
  start state (:mod:`benchkit.linear`): how much of each channel any linear model could predict;
* "_no_offsets" rows: the project's model (when it estimates input offsets per window) and the linear
  predictor scored again with nothing estimated from a held-out window's own outputs but its
  unmeasured initial states, the figure that needs no caveat;
* scored by eq. 19 on ``--window-s`` windows started from the measured states (unmeasured states
  by least squares over the window, inputs against the model's trim: :mod:`groundstation.sysid.heldout`),
  per channel and the mean over the channels measured in the held-out part, with any unstable
  mode of either model.

Prints a table per split and the overall figures (mean over folds); ``--json`` writes them too.
"""

from __future__ import annotations

import argparse
import dataclasses
import json
import time
from pathlib import Path
from typing import Any

import numpy as np
from rich.console import Console
from rich.table import Table

from benchkit.linear import linear_heldout
from benchkit.paired import paired_difference
from benchkit.reference import fit_reference, shift_profile
from benchkit.residuals import BAND_HZ, residual_table
from groundstation.config import ServiceConfig
from groundstation.dsp.split import contiguous_kfold, train_first
from groundstation.dsp.timeskew import shift_inputs
from groundstation.pipeline import load_aircraft, prepare_logs
from groundstation.sysid.fit_section import Selection
from groundstation.sysid.heldout import predict, predicted_windows, runaway_channels, unstable_modes
from groundstation.sysid.identify import IdentifyConfig, identify

#: the predictors a split may score: the project's identification, the plain reference, the linear ceiling;
#: "_no_offsets": the same predictor with nothing estimated from a held-out window's own outputs but its
#: unmeasured initial states (no input offsets per window; the linear ceiling without its offset and trend)
KINDS = ("project", "project_no_offsets", "reference", "linear", "linear_no_offsets")

HELP = "held-out prediction on real flights: project identification vs a plain least-squares reference, k-fold"


def add_arguments(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("logs", nargs="+", type=Path, help="flight logs (.tlog / .bin / .px4log)")
    parser.add_argument("--aircraft", type=Path, default=None, help="aircraft TOML (channel map, outputs, prior)")
    parser.add_argument("--folds", type=int, default=5, help="contiguous blocks of the in-air time (0 = none)")
    parser.add_argument("--train-first-s", type=float, default=60.0, help="also train on the first S s (0 = no)")
    parser.add_argument("--window-s", type=float, default=5.0, help="prediction window, s")
    parser.add_argument("--reference-starts", type=int, default=4, help="starts of the least-squares reference")
    parser.add_argument("--no-reference", action="store_true", help="score only the project's identification")
    parser.add_argument("--seed", type=int, default=0)
    parser.add_argument("--json", type=Path, default=None, help="write the figures here")
    parser.add_argument("--linear", action="store_true",
                        help="also score an unconstrained linear predictor from the logged inputs (a ceiling, "
                             ":mod:`benchkit.linear`)")
    parser.add_argument("--input-shift-s", default="0", metavar="S|S1,S2,..|auto",
                        help="advance the logged inputs by S s in every split (both models), or by one value per split "
                             "in the order printed; auto: per split, the shift under which the plain reference fit "
                             "predicts held-out blocks of the training part best (on a closed-loop flight a profile "
                             "to look at, not a value to trust)")
    parser.add_argument("--set", action="append", default=[], metavar="KEY=VALUE",
                        help="override an IdentifyConfig field of the project's identification (repeatable)")
    parser.add_argument("--residuals", action="store_true",
                        help="also say where each hover model misses: per channel the noise floor and the "
                             "residual's share in drift / in-band / high frequencies (:mod:`benchkit.residuals`)")


def _identify_config(pairs: list[str], aircraft: Any) -> Any:
    kw: dict[str, Any] = {}
    fields = {f.name: f for f in dataclasses.fields(IdentifyConfig)}
    for p in pairs:
        k, _, v = p.partition("=")
        if k not in fields:
            raise ValueError(f"--set {p}: unknown IdentifyConfig field {k!r}")
        kw[k] = json.loads(v) if v not in ("", "none") else None
    base = aircraft.identify_config() if aircraft is not None else IdentifyConfig()
    return dataclasses.replace(base, **kw)


def _splits(prepared: Any, args: argparse.Namespace) -> list[tuple[str, Any, Any]]:
    out = []
    if args.train_first_s > 0:
        tr, va = train_first(prepared, args.train_first_s)
        out.append((f"first {args.train_first_s:g} s", tr, va))
    if args.folds >= 2:
        out += [(f"fold {f + 1}/{args.folds}", tr, va) for f, (tr, va) in enumerate(contiguous_kfold(prepared, args.folds))]
    return out


def _shifted(train: Any, val: Any, args: argparse.Namespace, row: dict[str, Any], i: int) -> tuple[Any, Any]:
    """Split ``i`` with its inputs advanced by ``--input-shift-s`` (measured on ``train`` with ``auto``)."""
    if args.input_shift_s == "auto":
        prof = shift_profile(train, seed=args.seed, window_s=args.window_s)
        row["input_shift_profile"] = prof
        shift = prof["shift_s"]
    else:
        given = [float(v) for v in args.input_shift_s.split(",")]
        shift = given[i] if len(given) > 1 else given[0]
    row["input_shift_s"] = shift
    return shift_inputs(train, shift), shift_inputs(val, shift)


def _score(model: Any, val: Any, window_s: float, residuals: bool = False, **kw: Any) -> dict[str, Any]:
    p = predict(model, val, window_s=window_s, **kw)
    out = {"match": p.match, "mean": p.mean_match, "runaway": runaway_channels(p),
           "unstable": [m.describe() for m in unstable_modes(model.theta)]}
    if residuals and getattr(model, "structure", "hover") != "command_response":
        out["residuals"] = residual_table(predicted_windows(model, val, window_s=window_s, **kw))
    return out


def _selection(model: Any) -> dict[str, Any]:
    """The configuration the identification chose by held-out prediction on its training part."""
    sel, ho = model.fit.selection or Selection(), model.fit.heldout
    return {"chosen": sel.chosen, "scores": {r.name: r.mean_match for r in sel.candidates},
            "not_predicted": [] if ho is None else list(ho.not_predicted),
            "inv_tau_s": float(model.params["inv_tau_s"]), "pinned": sorted(model.pinned)}


def run(args: argparse.Namespace) -> int:
    con = Console()
    aircraft = load_aircraft(args.aircraft)
    id_cfg = _identify_config(args.set, aircraft)
    prepared = prepare_logs(args.logs, ServiceConfig(), aircraft=aircraft)
    results: list[dict[str, Any]] = []
    for i, (name, train, val) in enumerate(_splits(prepared, args)):
        row: dict[str, Any] = {"split": name, "train_s": train.duration_s, "val_s": val.duration_s}
        train, val = _shifted(train, val, args, row, i)
        t0 = time.perf_counter()
        model = identify(train, seed=args.seed, prior=aircraft.prior if aircraft else None, config=id_cfg)
        row["project"] = _score(model, val, args.window_s, args.residuals) | {"seconds": time.perf_counter() - t0,
                                                              "selection": _selection(model)}
        if model.window_input_offsets or getattr(model, "structure", "hover") == "command_response":
            row["project_no_offsets"] = _score(model, val, args.window_s, window_offsets=False) | {"seconds": 0.0}
        if not args.no_reference:
            t0 = time.perf_counter()
            ref = fit_reference(train, starts=args.reference_starts, seed=args.seed, window_s=args.window_s)
            row["reference"] = _score(ref, val, args.window_s, args.residuals) | {"seconds": time.perf_counter() - t0}
            if getattr(model, "structure", "hover") != "command_response":
                row["versus_reference"] = paired_difference(predicted_windows(model, val, window_s=args.window_s),
                                                            predicted_windows(ref, val, window_s=args.window_s))
        if args.linear:
            t0 = time.perf_counter()
            row["linear"] = linear_heldout(train, val, window_s=args.window_s) | {"seconds": time.perf_counter() - t0}
            t0 = time.perf_counter()
            row["linear_no_offsets"] = linear_heldout(train, val, window_s=args.window_s, window_unknowns=False) | {
                "seconds": time.perf_counter() - t0}
        results.append(row)
        _print_split(con, row)
    summary = _summary(results)
    _print_summary(con, summary)
    if args.json is not None:
        args.json.write_text(json.dumps({"splits": results, "summary": summary}, indent=1, default=float))
    return 0


def _print_split(con: Any, row: dict[str, Any]) -> None:
    kinds = [k for k in KINDS if k in row]
    chans = list(row["project"]["match"])
    shift = f", inputs advanced {row['input_shift_s'] * 1000:.0f} ms" if row.get("input_shift_s") else ""
    t = Table(title=f"{row['split']}: train {row['train_s']:.0f} s, predict {row['val_s']:.0f} s{shift} (match %, eq. 19)")
    t.add_column("model")
    for c in chans + ["mean", "s"]:
        t.add_column(c, justify="right")
    for k in kinds:
        r = row[k]
        t.add_row(k, *[f"{r['match'].get(c, float('nan')):.1f}" for c in chans], f"{r['mean']:.1f}", f"{r['seconds']:.0f}")
    con.print(t)
    sel = row["project"].get("selection") or {}
    if len(sel.get("scores") or {}) > 1:
        scores = ", ".join(f"{n} {v:.1f} %" for n, v in sel["scores"].items())
        con.print(f"  project: configuration chosen by held-out prediction on the training part: {sel['chosen']} "
                  f"(inner folds: {scores})")
    if "inv_tau_s" in sel:
        con.print(f"  project: 1/tau_s {sel['inv_tau_s']:.2f} /s; on a search bound: {', '.join(sel['pinned']) or 'none'}")
    if sel.get("not_predicted"):
        con.print(f"  project: its held-out check on the training part says it does not predict "
                  f"{', '.join(sel['not_predicted'])} (scored here all the same)")
    if "versus_reference" in row:
        _print_versus(con, row["versus_reference"])
    for k in kinds:
        if "residuals" in row[k]:
            _print_residuals(con, f"{row['split']}, {k}", row[k]["residuals"])
    for k in kinds:
        for u in row[k]["unstable"]:
            con.print(f"  {k}: {u}")
        if row[k]["runaway"]:
            con.print(f"  {k}: prediction runs away on {', '.join(row[k]['runaway'])}")


def _print_versus(con: Any, v: dict[str, Any]) -> None:
    con.print(f"  project - reference: {v['difference']:+.1f} points ({v['level']:.0%} bootstrap interval over the "
              f"{v['windows']} held-out windows {v['lo']:+.1f} to {v['hi']:+.1f}; without window {v['window']} "
              f"{v['without_window']:+.1f})")


def _versus_summary(folds: list[dict[str, Any]]) -> dict[str, Any]:
    """How many folds the project predicts worse than the reference, and how many beyond the windows' spread."""
    vs = [r["versus_reference"] for r in folds if "versus_reference" in r]
    return {"folds": len(vs), "below": sum(v["difference"] < 0 for v in vs), "below_beyond_spread": sum(v["hi"] < 0 for v in vs)}


def _summary(results: list[dict[str, Any]]) -> dict[str, Any]:
    out: dict[str, Any] = {}
    folds = [r for r in results if r["split"].startswith("fold")]
    for k in KINDS:
        if not results or k not in results[0]:
            continue
        s: dict[str, Any] = {}
        if folds:
            s["folds_mean"] = float(np.mean([r[k]["mean"] for r in folds]))
            chans = sorted({c for r in folds for c in r[k]["match"]})
            s["folds_channel_mean"] = {c: float(np.mean([r[k]["match"][c] for r in folds if c in r[k]["match"]]))
                                       for c in chans}
            s["folds_min_channel"] = float(min(min(r[k]["match"].values()) for r in folds))
            s["folds_min_channel_name"] = min(((v, c) for r in folds for c, v in r[k]["match"].items()))[1]
            claimed = [v for r in folds for c, v in r[k]["match"].items()
                       if c not in r[k].get("selection", {}).get("not_predicted", [])]
            if k == "project" and claimed:
                s["folds_min_claimed_channel"] = float(min(claimed))
            s["chosen"] = sorted({str(r[k].get("selection", {}).get("chosen")) for r in results
                                  if r[k].get("selection", {}).get("chosen")})
            if all("residuals" in r[k] for r in folds):
                s["folds_residuals"] = _residual_mean([r[k]["residuals"] for r in folds])
        first = [r for r in results if r["split"].startswith("first")]
        if first:
            s["train_first_mean"] = first[0][k]["mean"]
        s["unstable_splits"] = sum(bool(r[k]["unstable"]) for r in results)
        out[k] = s
    if any("versus_reference" in r for r in folds):
        out["versus_reference"] = _versus_summary(folds)
    return out


#: the columns of a residual table (:mod:`benchkit.residuals`) and their headers
RESIDUAL_COLUMNS = {"match": "match", "noise_floor": "noise floor", "drift": "drift %", "in_band": "in band %",
                    "high": "high %", "noise": "noise %", "match_no_drift": "match w/o drift",
                    "match_active": "match active", "match_calm": "match calm"}


def _residual_mean(tables: list[dict[str, dict[str, float]]]) -> dict[str, dict[str, float]]:
    """Per channel and figure, the mean over the folds that hold the channel."""
    chans = [c for c in tables[0]] + [c for t in tables[1:] for c in t if c not in tables[0]]
    return {c: {f: float(np.nanmean([t[c][f] for t in tables if c in t])) for f in RESIDUAL_COLUMNS} for c in chans}


def _print_residuals(con: Any, title: str, table: dict[str, dict[str, float]]) -> None:
    t = Table(title=f"{title}: where the prediction misses (residual energy shares; drift = a constant and a ramp "
                    f"per window; in band = up to {BAND_HZ:g} Hz)")
    t.add_column("channel")
    for h in RESIDUAL_COLUMNS.values():
        t.add_column(h, justify="right")
    for c, r in table.items():
        t.add_row(c, *[f"{r[f]:.1f}" for f in RESIDUAL_COLUMNS])
    con.print(t)


def _print_summary(con: Any, summary: dict[str, Any]) -> None:
    summary = dict(summary)
    vs = summary.pop("versus_reference", None)
    for k, s in summary.items():
        if "folds_residuals" in s:
            _print_residuals(con, f"{k}, mean over the folds", s["folds_residuals"])
    for k, s in summary.items():
        parts = []
        if "folds_mean" in s:
            chan = ", ".join(f"{c} {v:.1f}" for c, v in s["folds_channel_mean"].items())
            parts.append(f"k-fold held-out mean match {s['folds_mean']:.1f} % (per channel: {chan}; "
                         f"lowest channel in any fold {s['folds_min_channel']:.1f} % ({s['folds_min_channel_name']}))")
        if "folds_min_claimed_channel" in s:
            parts.append(f"lowest channel the model says it predicts (its own held-out check on the training part) "
                         f"{s['folds_min_claimed_channel']:.1f} %")
        if s.get("chosen"):
            parts.append(f"configuration chosen: {', '.join(s['chosen'])}")
        if "train_first_mean" in s:
            parts.append(f"train-first split {s['train_first_mean']:.1f} %")
        parts.append(f"splits with an unstable mode: {s['unstable_splits']}")
        con.print(f"[bold]{k}[/]: " + "; ".join(parts))
    if vs:
        con.print(f"project below the reference on {vs['below']} of {vs['folds']} folds, beyond the bootstrap "
                  f"interval over the fold's windows on {vs['below_beyond_spread']}")
    if any(k.endswith("_no_offsets") for k in summary):
        con.print("(_no_offsets: the same predictor with nothing estimated from a held-out window's own outputs "
                  "but its unmeasured initial states: no input offsets per window, no offset or trend of the linear one)")
