"""The campaign table: one SQLite table per aircraft (``flights_<aircraft>``), optionally Parquet.

Columns: identity (``aircraft, log, log_name, sha256, settings_key, flight_index, date_utc``),
conditions (``in_air_s, mean_speed_m_s, input_rms_*, conditions``), the model (``p_<name>`` and
``se_<name>`` for every parameter, ``fixed``, ``pinned``, ``model`` JSON), fits (``train_match_pct``,
``heldout_match_pct`` k-fold held-out, ``cross_match_pct`` on ``cross_log``), the diagnosis
(``verdict``, ``gap_significant``, ``effects`` JSON, ``effect_values`` JSON of every scored estimate)
and ``seconds``, ``error``. A log is done when it has an error-free row with the same content hash
and settings key; rows with an error are retried on the next run.

Series for the trend test come from :func:`series`; flights are ordered by date, then log name.
"""

from __future__ import annotations

import json
import re
import sqlite3
from pathlib import Path
from typing import Any

import numpy as np

from groundstation.sysid.model import PARAM_NAMES

_TEXT = {"aircraft", "log", "log_name", "sha256", "settings_key", "date_utc", "date_source", "fixed", "pinned",
         "cross_log", "verdict", "effects", "effect_values", "conditions", "model", "error"}
COLUMNS: tuple[str, ...] = (
    "aircraft", "log", "log_name", "sha256", "settings_key", "flight_index", "date_utc", "date_source",
    "in_air_s", "mean_speed_m_s", "input_rms_lat", "input_rms_lon", "input_rms_col", "input_rms_ped", "conditions",
    "cost", "windows", "train_match_pct", "heldout_match_pct", "cross_log", "cross_match_pct",
    "verdict", "gap_significant", "effects", "effect_values",
    *[f"{k}_{n}" for n in PARAM_NAMES for k in ("p", "se")],
    "fixed", "pinned", "model", "seconds", "error",
)


def table_name(aircraft: str) -> str:
    """``flights_<aircraft>`` with anything but letters, digits and _ replaced."""
    return "flights_" + (re.sub(r"[^A-Za-z0-9_]", "_", aircraft) or "aircraft")


class CampaignStore:
    """SQLite file holding one table per aircraft (stdlib ``sqlite3``; one writer: the campaign's parent)."""

    def __init__(self, path: str | Path) -> None:
        self.path = Path(path)
        self.path.parent.mkdir(parents=True, exist_ok=True)
        try:
            self.db = sqlite3.connect(self.path)
            self.db.execute("PRAGMA journal_mode=WAL")
        except sqlite3.DatabaseError as exc:
            raise OSError(f"{self.path}: not a usable SQLite file ({exc})") from None

    def close(self) -> None:
        self.db.close()

    def _ensure(self, aircraft: str) -> str:
        t = table_name(aircraft)
        cols = ", ".join(f'"{c}" {"TEXT" if c in _TEXT else "REAL"}' for c in COLUMNS)
        self.db.execute(f'CREATE TABLE IF NOT EXISTS "{t}" ({cols}, '
                        'PRIMARY KEY (sha256, settings_key, flight_index))')
        return t

    def done(self, aircraft: str, sha256: str, settings_key: str) -> bool:
        """True when the log (by content) was analysed with these settings without error."""
        t = self._ensure(aircraft)
        cur = self.db.execute(f'SELECT COUNT(*) FROM "{t}" WHERE sha256=? AND settings_key=? AND error IS NULL',
                              (sha256, settings_key))
        return bool(cur.fetchone()[0])

    def put(self, rows: list[dict[str, Any]]) -> None:
        """Insert (or replace) rows; a log's earlier rows for the same settings are replaced."""
        for r in rows:
            t = self._ensure(str(r["aircraft"]))
            self.db.execute(f'DELETE FROM "{t}" WHERE sha256=? AND settings_key=?', (r["sha256"], r["settings_key"]))
        for r in rows:
            t = table_name(str(r["aircraft"]))
            vals = [_sql(r.get(c)) for c in COLUMNS]
            self.db.execute(f'INSERT OR REPLACE INTO "{t}" VALUES ({", ".join("?" * len(COLUMNS))})', vals)
        self.db.commit()

    def aircraft(self) -> list[str]:
        cur = self.db.execute("SELECT name FROM sqlite_master WHERE type='table' AND name LIKE 'flights_%'")
        out = []
        for (name,) in cur.fetchall():
            row = self.db.execute(f'SELECT aircraft FROM "{name}" LIMIT 1').fetchone()
            if row:
                out.append(row[0])
        return sorted(out)

    def rows(self, aircraft: str, settings_key: str | None = None) -> list[dict[str, Any]]:
        """Error-free rows of one aircraft in flight order (date, log name, flight index)."""
        t = self._ensure(aircraft)
        q = f'SELECT * FROM "{t}" WHERE error IS NULL'
        args: tuple = ()
        if settings_key is not None:
            q += " AND settings_key=?"
            args = (settings_key,)
        cur = self.db.execute(q + " ORDER BY date_utc, log_name, flight_index", args)
        names = [d[0] for d in cur.description]
        return [dict(zip(names, r, strict=True)) for r in cur.fetchall()]

    def errors(self, aircraft: str) -> list[dict[str, Any]]:
        t = self._ensure(aircraft)
        cur = self.db.execute(f'SELECT log_name, error FROM "{t}" WHERE error IS NOT NULL')
        return [{"log_name": a, "error": b} for a, b in cur.fetchall()]

    def write_parquet(self, aircraft: str, path: str | Path) -> Path:
        """The aircraft's table as a Parquet file (pyarrow)."""
        import pyarrow as pa
        import pyarrow.parquet as pq

        rows = self.rows(aircraft)
        cols = {c: [r.get(c) for r in rows] for c in COLUMNS}
        schema = pa.schema([(c, pa.string() if c in _TEXT else pa.float64()) for c in COLUMNS])
        out = Path(path)
        out.parent.mkdir(parents=True, exist_ok=True)
        pq.write_table(pa.table(cols, schema=schema), out)
        return out


def _sql(v: Any) -> Any:
    if v is None:
        return None
    if isinstance(v, bool | np.bool_):
        return float(v)
    if isinstance(v, int | float | np.integer | np.floating):
        f = float(v)
        return f if np.isfinite(f) else None
    return str(v)


def series(rows: list[dict[str, Any]]) -> dict[str, tuple[np.ndarray, np.ndarray | None]]:
    """Per-quantity values over the flights: every free parameter (with its standard error), every
    effect estimate in the report's own units (no standard error; its copy in PWM units is left out); ``{name: (values (n,), std (n,) or None)}``."""
    out: dict[str, tuple[np.ndarray, np.ndarray | None]] = {}
    n = len(rows)
    for p in PARAM_NAMES:
        v = np.array([_num(r.get(f"p_{p}")) for r in rows])
        s = np.array([_num(r.get(f"se_{p}")) for r in rows])
        fixed = [p in json.loads(r.get("fixed") or "[]") for r in rows]
        v = np.where(fixed, np.nan, v)
        if np.isfinite(v).any():
            out[p] = (v, s)
    effects: dict[str, np.ndarray] = {}
    for i, r in enumerate(rows):
        for k, val in json.loads(r.get("effect_values") or "{}").items():
            if "_pwm_us" in k:  # the same estimate in PWM units: one series per quantity
                continue
            effects.setdefault(k, np.full(n, np.nan))[i] = _num(val)
    out.update({f"effect:{k}": (v, None) for k, v in sorted(effects.items())})
    return out


def _num(v: Any) -> float:
    try:
        f = float(v)
    except (TypeError, ValueError):
        return float("nan")
    return f
