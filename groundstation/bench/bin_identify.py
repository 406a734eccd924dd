"""``groundstation bench bin-identify``: identification from the autopilot's onboard log vs from telemetry.

One simulated flight (``--seed``, with a rotor-vibration effect unless ``--no-vibration``) written
twice from the same simulator run: as the 50 Hz telemetry ``.tlog`` a ground station records, and as
the onboard dataflash ``.bin`` the simulated FC logs at 200 Hz. Both are identified with
``groundstation identify`` (same defaults); the table gives the 8 key parameters against the truth
(target: both within 10 %), and the vibration line the onboard log's IMU shows (the same statistic
``diagnose`` reports) against the true rotor frequency.
"""

from __future__ import annotations

import argparse
import json
import shutil
import tempfile
from pathlib import Path

HELP = "identify from the simulated FC's 200 Hz onboard .bin and from its .tlog: 8 key parameters, vibration line"

KEY = ("M_a", "L_b", "inv_tau_s", "A_lat", "B_lon", "Z_col", "N_ped", "N_r")


def add_arguments(p: argparse.ArgumentParser) -> None:
    p.add_argument("--seed", type=int, default=3)
    p.add_argument("--no-vibration", action="store_true", help="no rotor-vibration effect")
    p.add_argument("--keep", type=Path, default=None, help="keep the logs and models in this directory")


def run(args: argparse.Namespace) -> int:
    import contextlib
    import io

    import numpy as np
    from rich.console import Console
    from rich.table import Table

    from firmware_interface.readers import load_log
    from groundstation.cli import main as cli_main
    from groundstation.commands.diagnose import native_vibration
    from hil_replay.dataflash import write_bin
    from hil_replay.sim import write_tlog

    con = Console()
    effects = () if args.no_vibration else ("rotor_vibration",)
    tmp = Path(tempfile.mkdtemp(prefix="bench-bin-identify-"))
    try:
        tlog, binp = tmp / "flight.tlog", tmp / "flight.bin"
        truth = write_tlog(tlog, seed=args.seed, effects=effects)
        write_bin(binp, seed=args.seed, effects=effects)
        models = {}
        for name, path in (("telemetry .tlog (50 Hz)", tlog), ("onboard .bin (200 Hz)", binp)):
            out = tmp / f"{path.stem}{path.suffix.replace('.', '_')}.json"
            with contextlib.redirect_stdout(io.StringIO()):
                code = cli_main(["identify", str(path), "--out", str(out), "--no-plot", "--quiet"])
            if code != 0:
                raise RuntimeError(f"identify failed on {path}")
            models[name] = json.loads(out.read_text())["parameters"]
        native = native_vibration([load_log(binp)], 50.0)
        if args.keep:
            shutil.copytree(tmp, args.keep, dirs_exist_ok=True)
    finally:
        shutil.rmtree(tmp, ignore_errors=True)
    tp = truth["parameters"]
    t = Table(title=f"8 key parameters, seed {args.seed} ({'with' if effects else 'no'} rotor vibration)")
    t.add_column("parameter")
    t.add_column("truth", justify="right")
    for name in models:
        t.add_column(name, justify="right")
        t.add_column("err %", justify="right")
    errs: dict[str, dict[str, float]] = {n: {} for n in models}
    for k in KEY:
        row = [k, f"{tp[k]:.4g}"]
        for name, par in models.items():
            e = abs(par[k] - tp[k]) / abs(tp[k]) * 100
            errs[name][k] = e
            row += [f"{par[k]:.4g}", f"{e:.1f}"]
        t.add_row(*row)
    con.print(t)
    for name, e in errs.items():
        con.print(f"{name}: {sum(v <= 10 for v in e.values())}/8 within 10 % (worst {max(e, key=lambda k: e[k])} "
                  f"{max(e.values()):.1f} %)")
    true_hz = next((e["params"].get("frequency_hz") for e in truth["effects"] if e["effect"] == "rotor_vibration"),
                   None)
    top = native["lines"][0]["frequency_hz"] if native and native["lines"] else None
    con.print(f"vibration line in the .bin's IMU: {top if top is not None else 'none'} Hz; "
              f"true rotor frequency: {true_hz if true_hz is not None else 'no vibration simulated'} Hz")
    print(json.dumps({"key_error_pct": {n: {k: round(v, 2) for k, v in e.items()} for n, e in errs.items()},
                      "within_10pct": {n: int(np.sum([v <= 10 for v in e.values()])) for n, e in errs.items()},
                      "vibration_line_hz": top, "true_rotor_hz": true_hz}))
    return 0
