"""The service's side of a campaign: each identified flight goes into the aircraft's table and the
trend summary over all its flights comes back for publishing (``heli/{vehicle}/trends``).

:func:`record_flight` runs in the service's worker process (after identification and diagnosis,
never on the event loop): one row (:func:`groundstation.campaign.job.model_row`) into the SQLite
table next to the recordings, then the change test over the aircraft's flights.
"""

from __future__ import annotations

from pathlib import Path
from typing import Any

from groundstation.campaign.job import Settings, file_sha256, log_date_utc, model_row
from groundstation.campaign.store import CampaignStore, series
from groundstation.trends.change import assess_all, campaign_summary


def record_flight(db_path: str | Path, aircraft: str, log_path: str, flight: int, model: Any, report: dict | None,
                  prepared: Any, config: Any, seconds: float | None = None) -> dict:
    """Store the flight's row; return the ``heli-trends/1`` summary over the aircraft's flights."""
    date, src = log_date_utc(log_path)
    key = Settings(config=config, diagnose=report is not None).key()
    row = {"aircraft": aircraft, "log": str(log_path), "log_name": Path(log_path).name, "sha256": file_sha256(log_path),
           "settings_key": key, "flight_index": flight, "date_utc": date, "date_source": src,
           **model_row(model, report, prepared), "seconds": seconds, "error": None}
    store = CampaignStore(db_path)
    try:
        store.put([row])
        rows = store.rows(aircraft, key)
    finally:
        store.close()
    labels = [f"{r['log_name']}#{int(r['flight_index'])}" for r in rows]
    return campaign_summary(aircraft, labels, assess_all(series(rows), getattr(config, "trends", None)))
