"""Command-line entry point: ``groundstation COMMAND ...``.

Each subcommand lives in ``groundstation/commands/<name>.py`` exposing ``add_arguments(parser)`` and
``run(args) -> int``; its one-line help is in :data:`COMMANDS` below. Benchmarks live in
``groundstation/bench/<name>.py`` with the same shape (and a ``HELP`` line) and are reached through
``groundstation bench NAME``.

A command's module (and everything it imports) is loaded only when that command runs or its own
``--help`` is asked for: the one deliberately lazy import of the command line, so ``groundstation
--help`` lists every command without loading any, and ``groundstation identify`` does not load the
live service, the simulator or the report. Errors derived from
:class:`groundstation.errors.GroundstationError` (and ValueError/OSError at the edge) print one line
and exit non-zero.
"""

from __future__ import annotations

import argparse
import importlib
import sys
from collections.abc import Iterable, Sequence
from types import ModuleType

from groundstation.errors import GroundstationError

#: command name -> (module under groundstation.commands, one-line help)
COMMANDS: dict[str, tuple[str, str]] = {
    "run": ("run", "run the live ground-station service (no --link: built-in simulated helicopter)"),
    "demo": ("demo", "two simulated flights end to end: record, stream, identify, diagnose, zenoh, Rerun "
                     "(demo_out/)"),
    "record": ("record", "record the flight-controller link to .tlog files (session + one per flight) until "
                         "Ctrl-C"),
    "log-info": ("log_info", "summarise a flight log (.tlog, .bin, .px4log, .ulg): flights, message rates, gaps, "
                             "corruption"),
    "logs": ("logs", "list or download the flight controller's onboard logs (dataflash .bin) over the link"),
    "replay": ("replay", "serve a .tlog on a virtual serial port (original timing or N× faster, fault injection)"),
    "simulate": ("simulate", "write a simulated helicopter flight (.tlog + .truth.json), or serve a simulated FC "
                             "on a pty"),
    "identify": ("identify", "identify the hover model (paper eq. 8) from flight logs with CABC and write the "
                             "model JSON"),
    "validate": ("validate", "score a hover model file on flight logs (match degree, NRMSE fit, Theil U, "
                             "correlation per channel)"),
    "diagnose": ("diagnose", "diagnose where and why the hover model departs from flight data (gap report JSON)"),
    "report": ("report", "write one self-contained HTML flight report (flight, model, frequency domain, gap, "
                         "across flights)"),
    "campaign": ("campaign", "identify and diagnose every flight of a set of logs into one table per aircraft, "
                             "with trends"),
    "bench": ("bench", "run a benchmark: groundstation bench NAME [options] (NAME: a module of "
                       "groundstation/bench)"),
}


def _load(module: str) -> ModuleType:
    return importlib.import_module(f"groundstation.commands.{module}")


def build_parser(load: Iterable[str] | None = None) -> argparse.ArgumentParser:
    """The command-line parser; only the commands named in ``load`` (every command when ``None``) get
    their options, which imports their modules."""
    wanted = set(COMMANDS if load is None else load)
    parser = argparse.ArgumentParser(prog="groundstation", description=__doc__.splitlines()[0])
    sub = parser.add_subparsers(dest="command", required=True, metavar="COMMAND")
    for name, (module, help_line) in COMMANDS.items():
        p = sub.add_parser(name, help=help_line, description=help_line)
        if name in wanted:
            mod = _load(module)
            mod.add_arguments(p)
            p.set_defaults(_module=mod)
    return parser


def _command(argv: Sequence[str]) -> str | None:
    """The command named on the command line (its first word that is not an option), if any."""
    return next((a for a in argv if not a.startswith("-")), None)


def main(argv: list[str] | None = None) -> int:
    argv = sys.argv[1:] if argv is None else argv
    parser = build_parser([c for c in (_command(argv),) if c in COMMANDS])
    args = parser.parse_args(argv)
    try:
        return int(args._module.run(args) or 0)
    except KeyboardInterrupt:
        return 130
    except (GroundstationError, ValueError, OSError) as exc:
        print(f"groundstation {args.command}: error: {exc}", file=sys.stderr)
        return 2


if __name__ == "__main__":
    # Run through the package module, not this __main__ copy, so that the
    # exception classes caught in main() are the ones the commands raise.
    from groundstation.cli import main as _package_main

    sys.exit(_package_main())
