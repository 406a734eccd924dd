"""Helpers of the commands that run the frequency-domain analysis (``validate --freq``,
``identify --domain frequency|both``): preparing logs at their native rate, the J table, the
Bode and Rerun outputs. Not a command itself."""

from __future__ import annotations

import argparse
import json
from dataclasses import replace
from pathlib import Path
from typing import Any


def add_freq_arguments(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("--freq-config", type=Path, default=None,
                        help="TOML whose [freq] table (window_s, overlap, coherence_min, f_max_hz, ...) replaces "
                             "the one of --config")
    parser.add_argument("--grid-rate", action="store_true",
                        help="analyse on the 50 Hz grid even where the log is sampled faster")


def load_freq_config(path: Path | None, cfg: Any = None) -> Any:
    """The ``[freq]`` settings: of ``path`` if given, else of the configuration ``cfg`` (``--config``)."""
    from groundstation.config import ServiceConfig, load_config

    if path is not None:
        return load_config(path).freq
    return (cfg if cfg is not None else ServiceConfig()).freq


def prepare_native(logs: list[Any], prep_cfg: Any, *, grid_only: bool = False) -> Any:
    """Prepared data at the log's native rate where that is faster than the grid (else the grid)."""
    from groundstation.dsp.prepare import prepare
    from groundstation.freq.spectra import native_rate_hz

    prepared = prepare(logs, prep_cfg)
    rate = None if grid_only else native_rate_hz(prepared, prep_cfg.rate_hz)
    if rate is None:
        return prepared
    return prepare(logs, replace(prep_cfg, rate_hz=rate))


def j_table(v: Any, title: str):
    from rich.table import Table

    t = Table(title=title)
    for c in ("input", "output", "J", "", "coherent pts", "band Hz", "delay ms", "outside 95 % bound"):
        t.add_column(c, justify="right")
    for p in v.pairs:
        dev = ", ".join(f"{b.f_lo_hz:.2g}-{b.f_hi_hz:.2g} Hz ({b.magnitude_db:+.1f} dB, {b.phase_deg:+.0f} deg)"
                        for b in p.deviations[:3])
        t.add_row(p.input, p.output, f"{p.J:.1f}", "pass" if p.passed else "[red]FAIL[/]", str(p.coherent_points),
                  f"{p.f_lo_hz:.2g}-{p.f_hi_hz:.2g}", "-" if p.delay_s is None else f"{p.delay_s * 1000:+.0f}", dev)
    ja = v.J_avg
    t.add_row("all", "", "-" if ja is None else f"{ja:.1f}", "good" if v.good else "[red]not good[/]", "", "", "", "")
    return t


def print_verification(v: Any, title: str, con: Any = None) -> None:
    from rich.console import Console

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

    from groundstation.sinks.bode import log_bode

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
    return json.dumps(doc, indent=1, allow_nan=False)
