"""Helpers of the commands that run the frequency-domain analysis (``validate --freq``,
``identify --domain frequency|both``): preparing logs at their native rate, the J table, the
Bode and Rerun outputs. Not a command itself."""

from __future__ import annotations

import argparse
import time
from dataclasses import replace
from pathlib import Path
from typing import Any

from rich.console import Console
from rich.table import Table

from groundstation.commands.model_summary import print_model, write_json
from groundstation.config import ServiceConfig, load_config
from groundstation.dsp.prepare import prepare
from groundstation.freq.identify import identify_frequency
from groundstation.freq.model_response import delays_from_augmentations
from groundstation.freq.spectra import estimate_responses
from groundstation.freq.verify import verify
from groundstation.jsonio import dumps
from groundstation.pipeline import identify_prepared, prepare_native
from groundstation.sinks.bode import log_bode
from groundstation.sysid.heldout import SUBSYSTEM_CHANNELS, predict, runaway_channels, unstable_modes
from groundstation.sysid.model import PARAM_NAMES
from groundstation.sysid.validate import validate


def add_freq_arguments(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("--freq-config", type=Path, default=None,
                        help="TOML whose [freq] table (window_s, overlap, coherence_min, f_max_hz, ...) replaces "
                             "the one of --config")
    parser.add_argument("--grid-rate", action="store_true",
                        help="analyse on the 50 Hz grid even where the log is sampled faster")


def load_freq_config(path: Path | None, cfg: Any = None) -> Any:
    """The ``[freq]`` settings: of ``path`` if given, else of the configuration ``cfg`` (``--config``)."""
    if path is not None:
        return load_config(path).freq
    return (cfg if cfg is not None else ServiceConfig()).freq


def j_table(v: Any, title: str):
    t = Table(title=title)
    for c in ("input", "output", "J", "", "coherent pts", "band Hz", "delay ms", "model outside the 95 % bound"):
        t.add_column(c, justify="right")
    for p in v.pairs:
        worst = max(p.deviations, key=lambda b: b.max_ratio, default=None)
        dev = "" if worst is None else (f"{len(p.deviations)} band(s); worst {worst.f_lo_hz:.2g}-{worst.f_hi_hz:.2g} Hz "
                                        f"{worst.magnitude_db:+.1f} dB {worst.phase_deg:+.0f} deg")
        t.add_row(p.input, p.output, f"{p.J:.1f}", "pass" if p.passed else "[red]FAIL[/]", str(p.coherent_points),
                  f"{p.f_lo_hz:.2g}-{p.f_hi_hz:.2g}", "-" if p.delay_s is None else f"{p.delay_s * 1000:+.0f}", dev)
    ja = v.J_avg
    t.add_row("all", "", "-" if ja is None else f"{ja:.1f}", "good" if v.good else "[red]not good[/]", "", "", "", "")
    return t


def print_verification(v: Any, title: str, con: Any = None) -> None:
    con = con or Console()
    con.print(j_table(v, title))
    for inp, d in v.input_delays.items():
        con.print(f"equivalent delay of {inp} relative to the model (phase slope): {d.delay_s * 1000:+.0f} ms "
                  f"(+/- {d.std_s * 1000:.0f} ms, {d.points} points)")
    for (i, o), (d, m) in v.bandwidth.items():
        con.print(f"ADS-33 {i}->{o}: bandwidth data {_hz(d.bandwidth_hz)} model {_hz(m.bandwidth_hz)}, "
                  f"phase delay data {_ms(d.phase_delay_s)} model {_ms(m.phase_delay_s)}"
                  + (f" ({d.note})" if d.note else ""))
    for i, o, n in v.unmodelled:
        con.print(f"{i}->{o}: the flight shows a coherent response ({n} points) the model has no path for")
    for i, o, r in v.no_response:
        con.print(f"no response {i}->{o}: {r}")
    for n in v.responses.notes:
        con.print(f"note: {n}")


def _hz(x: float | None) -> str:
    return "-" if x is None else f"{x:.2f} Hz"


def _ms(x: float | None) -> str:
    return "-" if x is None else f"{x * 1000:.0f} ms"


def write_rerun(v: Any, mode: list[str], app: str) -> Path | None:
    """``--rerun save PATH.rrd``: the Bode data to one explicit RecordingStream saved to PATH."""
    import rerun as rr

    if not mode or mode[0] == "off":
        return None
    if mode[0] != "save" or len(mode) != 2:
        raise ValueError(f"--rerun {' '.join(mode)}: expected 'save FILE.rrd' or 'off'")
    path = Path(mode[1])
    path.parent.mkdir(parents=True, exist_ok=True)
    rec = rr.RecordingStream(app)
    rec.save(str(path))
    log_bode(rec, v)
    rec.flush()
    return path


def verification_json(v: Any, **extra: Any) -> str:
    doc = v.to_json()
    doc.update(extra)

    return dumps(doc, indent=1)


def identify_domain(args: argparse.Namespace, logs: list[Any], cfg: Any) -> int:
    """``identify --domain frequency|both``.

    ``frequency``: the frequency-domain fit (global search, then refinement) is written to ``--out``.
    ``both``: the time-domain fit to ``--out``; the frequency cost then refines it (the time fit as the
    warm start, no search) and that model goes to ``<out>_freq.json``; each model is scored both ways
    (time: mean match degree on the training windows; frequency: J_avg) and a table prints the four figures.
    """

    con = Console(stderr=True, quiet=args.quiet)
    prepared = prepare(logs, cfg.prepare)
    fast = prepare_native(logs, cfg.prepare, grid_only=args.grid_rate)
    rs = estimate_responses(fast, load_freq_config(args.freq_config, cfg))
    ic = cfg.identification
    bounds = dict(cfg.bounds)
    over: dict[str, Any] = {"refine": ic.refine}   # [freq_identify] of the configuration, the options over it
    if getattr(args, "fit_delays", False):
        over["fit_delays"] = True
    if getattr(args, "freq_weighting", None) is not None:
        over["weighting"] = args.freq_weighting
    if args.maxiter:
        over["maxiter"] = args.maxiter
    fcfg = replace(cfg.freq_identify, **over)
    models = {}
    start = None
    if args.domain == "both":
        t0 = time.perf_counter()
        with con.status("time-domain identification"):
            tm = identify_prepared(prepared, cfg)
        tm.fit = tm.fit.set(seconds=round(time.perf_counter() - t0, 3))
        models["time"] = tm
        start = tm.theta
    t0 = time.perf_counter()
    with con.status("frequency-domain identification" if start is None else "frequency-domain refinement of the time fit"):
        fm = identify_frequency(rs, prepared, algorithm=ic.algorithm, seed=ic.seed, bounds=bounds or None,
                                config=fcfg, start=start, search_options=cfg.identify.search_options(ic.algorithm))
    fm.fit = fm.fit.set(seconds=round(time.perf_counter() - t0, 3))
    if start is not None:
        fm.fit = fm.fit.set(algorithm="frequency refinement of the time-domain fit")
    models["frequency"] = fm
    return _score_and_write(args, models, rs, prepared, cfg.identify)


def _score_and_write(args: argparse.Namespace, models: dict[str, Any], rs: Any, prepared: Any, icfg: Any) -> int:
    """Score each model both ways, write them and print the table (``identify --domain``)."""

    scores = {}
    for name, m in models.items():
        v = verify(m.theta, rs, delays_from_augmentations(m.augmentations))
        t = validate(m, prepared)
        scores[name] = {"J_avg": v.J_avg, "J_avg_good": v.good, "mean_match": t.mean_match,
                        "J": {f"{p.input}->{p.output}": p.J for p in v.pairs}}
        m.fit = m.fit.set(scores={"frequency": {k: scores[name][k] for k in ("J_avg", "J_avg_good", "J")},
                                  "time": {"mean_match": t.mean_match}})
        mark_unsupported(m, prepared, icfg.runaway_factor, icfg.heldout_window_s)
        m.source["logs"] = [str(p) for p in args.logs]
    outs = {"frequency": args.out} if args.domain == "frequency" else {
        "time": args.out, "frequency": args.out.with_name(args.out.stem + "_freq.json")}
    for name, path in outs.items():
        write_json(path, models[name].to_json())
    if not args.quiet:
        out = Console()
        for name, m in models.items():
            out.print(f"[bold]{name}-domain fit[/] -> {outs[name]}")
            if name == "frequency":
                _print_freq_fit(m, out)
            else:
                print_model(m, out)

        tab = Table(title="each fit scored both ways (J_avg: Tischler, <= 100 good; match: eq. 19 mean, %)")
        for c in ("fit", "J_avg", "mean match %", "written to"):
            tab.add_column(c, justify="right")
        for name, sc in scores.items():
            ja = sc["J_avg"]
            tab.add_row(name, "-" if ja is None else f"{ja:.1f}", f"{sc['mean_match']:.1f}", str(outs[name]))
        out.print(tab)
        for p in rs.without_response:
            out.print(f"no response {p.input}->{p.output}: {p.reason}")
        for name, m in models.items():
            for u in m.fit.unstable_modes:
                out.print(f"[yellow]unstable[/] ({name}-domain fit): {u}")
            for sub in m.fit.unusable_subsystems:
                own = [c for c in m.fit.runaway_channels if c in SUBSYSTEM_CHANNELS[sub]]
                out.print(f"[red]unusable[/] ({name}-domain fit): the {sub} subsystem's prediction of this flight "
                          f"runs away ({', '.join(own)}): not a model of the aircraft")
    return 0


def mark_unsupported(model: Any, prepared: Any, runaway_factor: float = 3.0, window_s: float = 5.0) -> None:
    """Record in ``model.fit`` what the flight does not support: ``unstable_modes`` (with their time
    constants), ``runaway_channels`` (eq. 19 prediction of the flight it was fitted to, ``window_s``
    windows from the measured states, error above ``runaway_factor`` times the signal; ``[identify]
    runaway_factor`` and ``heldout_window_s``), ``unusable_subsystems`` and
    ``usable``. A frequency fit never sees the time histories whole, so this is its first check in time."""
    ran = runaway_channels(predict(model, prepared, window_s=window_s), runaway_factor)
    unusable = [s for s, cs in SUBSYSTEM_CHANNELS.items() if any(c in ran for c in cs)]
    model.fit = model.fit.set(unstable_modes=[u.describe() for u in unstable_modes(model.theta)],
                              runaway_channels=ran, unusable_subsystems=unusable, usable=not unusable)


def _print_freq_fit(model: Any, con: Any) -> None:
    fit = model.fit
    cost = "J" if (fit.weighting or "coherence") == "coherence" else "the random-error-weighted cost"
    con.print(f"{fit.algorithm} on {cost}: J by subsystem "
              + ", ".join(f"{k} {v:.1f}" for k, v in fit.J_by_subsystem.items())
              + f"; {fit.evaluations} evaluations, {fit.seconds} s; "
              f"{fit.frequency_hz[0]:.2f}-{fit.frequency_hz[1]:.2f} Hz, windows {list(fit.windows_s)} s")
    p = Table(title="parameters (frequency-domain fit)")
    for c in ("name", "value", "std error", "note"):
        p.add_column(c, justify="right")
    for n in PARAM_NAMES:
        s = model.parameter_std.get(n)
        note = "fixed" if n in fit.fixed else ("PINNED at bound" if n in model.pinned else "")
        p.add_row(n, f"{model.params[n]:.4g}", "-" if s is None else f"{s:.3g}", note)
    con.print(p)
    for a in model.augmentations:
        con.print(f"input delay {a['input']}: {a['delay_s'] * 1000:.0f} ms")
    for r in fit.fixed_reasons:
        con.print(f"note: {r}")
