"""The offline chain every entry point shares: logs -> prepared data -> identified model.

``groundstation identify``, ``validate``, ``diagnose`` and the service's worker process all call
these two functions with the same :class:`groundstation.config.ServiceConfig`, so a flight is
prepared (``[prepare]``: channel map, trims, ``pwm_per_unit``, in-air height) and identified
(``[identify]``, ``[bounds]``, ``[identification]`` algorithm/seed/refine) the same way whichever
of them runs it. Reading files is here; the numbers are :mod:`groundstation.dsp` and
:mod:`groundstation.sysid`'s.
"""

from __future__ import annotations

import dataclasses
import json
import os
from collections.abc import Callable, Iterator, Sequence
from contextlib import contextmanager
from pathlib import Path
from typing import Any

from firmware_interface.readers import load_log, restrict_to_chirps
from groundstation.aircraft import load_aircraft as _load
from groundstation.config import ServiceConfig
from groundstation.dsp.prepare import prepare
from groundstation.errors import DspError, FreqError, GapError, SysidError
from groundstation.freq.spectra import native_rate_hz
from groundstation.parallel import Map, serial_map
from groundstation.sysid.identify import identify
from groundstation.sysid.model import HoverModel


@contextmanager
def about_logs(paths: Sequence[str | os.PathLike[str]]) -> Iterator[None]:
    """Name the logs in an error of the numerical packages that does not already name one.

    The pure packages know settings and samples, not files: ``identify.window_s = 30: no in-air
    segment is that long`` becomes ``flight1.tlog: identify.window_s = 30: ...``, one line that
    names the file, the key and the value. The error keeps its type (a ValueError too).
    """
    try:
        yield
    except (DspError, SysidError, GapError, FreqError) as exc:
        msg = str(exc)
        if any(Path(p).name in msg for p in paths):
            raise
        names = [str(p) for p in paths]
        where = ", ".join(names) if len(names) <= 3 else f"{', '.join(names[:2])} and {len(names) - 2} more logs"
        raise type(exc)(f"{where}: {msg}") from exc


def load_logs(paths: Sequence[str | os.PathLike[str]], segments: str = "flights",
              pmap: Map = serial_map) -> list[Any]:
    """Read the logs (.tlog/.bin/.px4log/.ulg); ``segments="sysid"`` keeps only the system-identification
    chirps of ArduPilot SYSID-mode logs. A missing file raises OSError naming it. ``pmap`` reads them
    (one log per worker process with :func:`groundstation.parallel.worker_map`)."""
    for p in paths:
        if not Path(p).exists():
            raise OSError(f"{p}: no such log file")
    logs = pmap(load_log, [str(p) for p in paths])
    if segments == "sysid":
        logs = [restrict_to_chirps(log) for log in logs]
    return logs


def load_aircraft(path: str | os.PathLike[str] | None) -> Any:
    """The aircraft file (:class:`groundstation.aircraft.Aircraft`), or None without one."""
    if path is None or str(path) == "":
        return None

    return _load(Path(path))


def with_aircraft(cfg: ServiceConfig, aircraft: Any) -> ServiceConfig:
    """``cfg`` with the aircraft file's input source, channel map, units, trims and outputs in ``[prepare]``
    and its ``[identify]`` overrides."""
    if aircraft is None:
        return cfg
    return dataclasses.replace(cfg, prepare=aircraft.prep_config(cfg.prepare),
                               identify=aircraft.identify_config(cfg.identify))


def with_aircraft_file(cfg: ServiceConfig) -> tuple[ServiceConfig, Any]:
    """(``cfg`` with the aircraft file ``[identification] aircraft`` applied, the aircraft or None): the
    service's flights are prepared and identified as ``groundstation identify --aircraft`` would."""
    aircraft = load_aircraft(cfg.identification.aircraft or None)
    return with_aircraft(cfg, aircraft), aircraft


def load_model(path: str | os.PathLike[str]) -> Any:
    """A model file (``heli-hover-model/1``, docs/model-file.md) as a :class:`groundstation.sysid.model.HoverModel`;
    a missing or malformed file raises an error naming it."""

    path = Path(path)
    if not path.exists():
        raise OSError(f"{path}: no such model file")
    try:
        doc = json.loads(path.read_bytes())
    except UnicodeDecodeError:
        raise SysidError(f"{path}: not a model file (binary, not JSON text)") from None
    except json.JSONDecodeError as exc:
        raise SysidError(f"{path}: not valid JSON ({exc.msg} at line {exc.lineno})") from None
    try:
        return HoverModel.from_json(doc)
    except ValueError as exc:
        raise SysidError(f"{path}: {exc}") from None


def prepare_native(logs: list[Any], prep_cfg: Any, *, grid_only: bool = False) -> Any:
    """Prepared data at the log's native rate where that is faster than the grid (else the grid): what
    the frequency-domain analysis runs on."""
    prepared = prepare(logs, prep_cfg)
    rate = None if grid_only else native_rate_hz(prepared, prep_cfg.rate_hz)
    if rate is None:
        return prepared
    return prepare(logs, dataclasses.replace(prep_cfg, rate_hz=rate))


def prepare_logs(paths: Sequence[str | os.PathLike[str]], cfg: ServiceConfig, segments: str = "flights",
                 aircraft: Any = None, pmap: Map = serial_map) -> Any:
    """Read the logs and prepare them with ``cfg.prepare`` (a :class:`groundstation.dsp.prepare.PreparedData`),
    the aircraft file's channel map and outputs applied when one is given."""
    return prepare(load_logs(paths, segments, pmap), with_aircraft(cfg, aircraft).prepare)


def identify_prepared(prepared: Any, cfg: ServiceConfig, *, callback: Callable[[dict], Any] | None = None,
                      aircraft: Any = None, pmap: Map = serial_map) -> Any:
    """The hover model of ``prepared`` (a :class:`groundstation.sysid.model.HoverModel`) identified with
    ``cfg.identify``, ``cfg.bounds`` and ``cfg.identification``'s algorithm, seed and refine, and the
    aircraft file's prior model (output error with a priori weighting) when one is given."""
    ic = cfg.identification
    return identify(prepared, algorithm=ic.algorithm, seed=ic.seed, refine=ic.refine, callback=callback,
                    bounds=dict(cfg.bounds) or None, config=cfg.identify,
                    prior=aircraft.prior if aircraft is not None else None, pmap=pmap)
