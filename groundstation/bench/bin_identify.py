"""``groundstation bench bin-identify``: identification from the autopilot's onboard log vs from telemetry.

Each simulated flight (``--seeds``, with a rotor-vibration effect at the head speed ``--rpm``
(cycled over the seeds; by default one below and two above the telemetry's 25 Hz Nyquist
frequency) unless ``--no-vibration``) is
written twice from the same simulator run: as the 50 Hz telemetry ``.tlog`` a ground station
records, and as the onboard dataflash ``.bin`` the simulated FC logs at 200 Hz. Both are identified
with ``groundstation identify`` (same defaults); a table per seed gives the 8 key parameters against
the truth (target: both within 10 %), and the vibration line the onboard log's IMU shows (the same
statistic ``diagnose`` reports) against the true rotor frequency. The last line sums the seeds.
"""

from __future__ import annotations

import argparse
import contextlib
import io
import json
import shutil
import tempfile
from pathlib import Path
from typing import Any

from rich.console import Console
from rich.table import Table

from firmware_interface.readers import load_log
from groundstation.analysis import native_vibration
from groundstation.cli import main as cli_main
from hil_replay.dataflash import write_bin
from hil_replay.sim import write_tlog

HELP = "identify from the simulated FC's 200 Hz onboard .bin and from its .tlog: 8 key parameters, vibration line"

KEY = ("M_a", "L_b", "inv_tau_s", "A_lat", "B_lon", "Z_col", "N_ped", "N_r")
SOURCES = ("telemetry .tlog (50 Hz)", "onboard .bin (200 Hz)")


def add_arguments(p: argparse.ArgumentParser) -> None:
    p.add_argument("--seeds", type=int, nargs="+", default=[3, 4, 5], help="one simulated flight per seed")
    p.add_argument("--seed", type=int, default=None, help="one seed only (same as --seeds N)")
    p.add_argument("--rpm", type=float, nargs="+", default=[1350.0, 1900.0, 2550.0],
                   help="head speed of the rotor-vibration effect per seed (cycled): 22.5, 31.7 and 42.5 Hz, "
                        "the last two above the 50 Hz telemetry's Nyquist frequency")
    p.add_argument("--no-vibration", action="store_true", help="no rotor-vibration effect")
    p.add_argument("--keep", type=Path, default=None, help="keep the logs and models in this directory")


def one_seed(seed: int, effects: tuple[str, ...], keep: Path | None) -> dict[str, Any]:
    """Identify one simulated flight from its .tlog and its .bin; errors in % of truth, vibration line."""

    tmp = Path(tempfile.mkdtemp(prefix="bench-bin-identify-"))
    try:
        tlog, binp = tmp / "flight.tlog", tmp / "flight.bin"
        truth = write_tlog(tlog, seed=seed, effects=effects)
        write_bin(binp, seed=seed, effects=effects)
        models = {}
        for name, path in zip(SOURCES, (tlog, binp), strict=True):
            out = tmp / f"{path.stem}{path.suffix.replace('.', '_')}.json"
            with contextlib.redirect_stdout(io.StringIO()):
                code = cli_main(["identify", str(path), "--out", str(out), "--no-plot", "--quiet"])
            if code != 0:
                raise RuntimeError(f"identify failed on {path} (seed {seed})")
            models[name] = json.loads(out.read_text())["parameters"]
        native = native_vibration([load_log(binp)], 50.0)
        if keep:
            shutil.copytree(tmp, keep / f"seed{seed}", dirs_exist_ok=True)
    finally:
        shutil.rmtree(tmp, ignore_errors=True)
    tp = truth["parameters"]
    true_hz = next((e["params"].get("frequency_hz") for e in truth["effects"] if e["effect"] == "rotor_vibration"),
                   None)
    return {"seed": seed, "truth": {k: tp[k] for k in KEY},
            "estimate": {n: {k: par[k] for k in KEY} for n, par in models.items()},
            "error_pct": {n: {k: abs(par[k] - tp[k]) / abs(tp[k]) * 100 for k in KEY} for n, par in models.items()},
            "vibration_line_hz": native["lines"][0]["frequency_hz"] if native and native["lines"] else None,
            "true_rotor_hz": true_hz}


def _table(r: dict[str, Any], effects: tuple[str, ...]) -> Any:
    t = Table(title=f"8 key parameters, seed {r['seed']} ({effects[0] if effects else 'no rotor vibration'})")
    t.add_column("parameter")
    t.add_column("truth", justify="right")
    for name in SOURCES:
        t.add_column(name, justify="right")
        t.add_column("err %", justify="right")
    for k in KEY:
        row = [k, f"{r['truth'][k]:.4g}"]
        for name in SOURCES:
            row += [f"{r['estimate'][name][k]:.4g}", f"{r['error_pct'][name][k]:.1f}"]
        t.add_row(*row)
    return t


def run(args: argparse.Namespace) -> int:
    con = Console()
    seeds = [args.seed] if args.seed is not None else list(args.seeds)
    results = []
    effects: tuple[str, ...] = ()
    for k, seed in enumerate(seeds):
        effects = () if args.no_vibration else (f"rotor_vibration:rpm={args.rpm[k % len(args.rpm)]:g}",)
        r = one_seed(seed, effects, args.keep)
        results.append(r)
        con.print(_table(r, effects))
        for name, e in r["error_pct"].items():
            worst = max(e, key=lambda k: e[k])
            con.print(f"{name}: {sum(v <= 10 for v in e.values())}/8 within 10 % (worst {worst} {e[worst]:.1f} %)")
        top, true_hz = r["vibration_line_hz"], r["true_rotor_hz"]
        con.print(f"vibration line in the .bin's IMU: {'none' if top is None else f'{top:.2f} Hz'}; true rotor "
                  f"frequency: {'no vibration simulated' if true_hz is None else f'{true_hz:.2f} Hz'}")
    summary = {name: f"{sum(sum(v <= 10 for v in r['error_pct'][name].values()) for r in results)}"
               f"/{8 * len(results)}" for name in SOURCES}
    vib_ok = sum(r["true_rotor_hz"] is not None and r["vibration_line_hz"] is not None
                 and abs(r["vibration_line_hz"] - r["true_rotor_hz"]) <= 0.5 for r in results)
    con.print(f"seeds {seeds}: within 10 % " + "; ".join(f"{n} {s}" for n, s in summary.items())
              + (f"; vibration line at the true rotor frequency (±0.5 Hz) in {vib_ok}/{len(results)}" if effects else ""))
    print(json.dumps({"seeds": [{"seed": r["seed"], "vibration_line_hz": r["vibration_line_hz"],
                                 "true_rotor_hz": r["true_rotor_hz"],
                                 "key_error_pct": {n: {k: round(v, 2) for k, v in e.items()}
                                                   for n, e in r["error_pct"].items()},
                                 "within_10pct": {n: sum(v <= 10 for v in e.values())
                                                  for n, e in r["error_pct"].items()}} for r in results],
                      "within_10pct": summary}))
    return 0
