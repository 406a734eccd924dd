"""``groundstation bench NAME [args...]``: dispatch to ``groundstation/bench/<NAME>.py``.

Each bench module exposes ``HELP``, ``add_arguments(parser)`` and ``run(args) -> int`` like a
command; this module only finds it, parses the remaining arguments with it and runs it.
"""

from __future__ import annotations

import argparse
import importlib
import pkgutil

import groundstation.bench as bench_pkg


def available() -> list[str]:
    return sorted(m.name for m in pkgutil.iter_modules(bench_pkg.__path__))


def add_arguments(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("name", help=f"benchmark name, one of: {', '.join(available()) or '(none yet)'}")
    parser.add_argument("bench_args", nargs=argparse.REMAINDER, help="options of that benchmark")


def run(args: argparse.Namespace) -> int:
    name = args.name.replace("-", "_")
    if name not in available():
        raise ValueError(f"unknown benchmark {args.name!r}; available: {available()}")
    mod = importlib.import_module(f"groundstation.bench.{name}")
    p = argparse.ArgumentParser(prog=f"groundstation bench {args.name}", description=getattr(mod, "HELP", ""))
    mod.add_arguments(p)
    return int(mod.run(p.parse_args(args.bench_args)) or 0)
