"""Command-line entry point: ``groundstation COMMAND ...``.

Each subcommand lives in ``groundstation/commands/<name>.py`` exposing ``HELP`` (one line),
``add_arguments(parser)`` and ``run(args) -> int``; benchmarks live in ``groundstation/bench/<name>.py``
with the same shape and are reached through ``groundstation bench NAME``. Modules are imported lazily
so a broken optional piece never stops the others. Errors derived from :class:`groundstation.errors.GroundstationError`
(and ValueError/OSError at the edge) print one line and exit non-zero.
"""

from __future__ import annotations

import argparse
import importlib
import sys

from groundstation.errors import GroundstationError

# command name -> module under groundstation.commands
COMMANDS: dict[str, str] = {
    "run": "run",
    "demo": "demo",
    "record": "record",
    "log-info": "log_info",
    "logs": "logs",
    "replay": "replay",
    "simulate": "simulate",
    "identify": "identify",
    "validate": "validate",
    "diagnose": "diagnose",
    "report": "report",
    "campaign": "campaign",
    "bench": "bench",
}


def _load(module: str):
    return importlib.import_module(f"groundstation.commands.{module}")


def build_parser() -> argparse.ArgumentParser:
    parser = argparse.ArgumentParser(prog="groundstation", description=__doc__.splitlines()[0])
    sub = parser.add_subparsers(dest="command", required=True, metavar="COMMAND")
    for name, module in COMMANDS.items():
        try:
            mod = _load(module)
        except ModuleNotFoundError as exc:
            if exc.name != f"groundstation.commands.{module}":
                raise
            continue
        p = sub.add_parser(name, help=getattr(mod, "HELP", ""), description=getattr(mod, "HELP", ""))
        mod.add_arguments(p)
        p.set_defaults(_module=mod)
    return parser


def main(argv: list[str] | None = None) -> int:
    parser = build_parser()
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
