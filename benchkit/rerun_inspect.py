"""Read a saved .rrd back as a user would see it: the default blueprint's tabs and views, the
entity tree, and Rerun's own chunk-count check (``rerun rrd stats``).

:func:`read_layout` walks the last blueprint in the file (the one the viewer opens) with
:class:`rerun.chunk.RrdReader`: views with their kind, title, origin and visible ``fc_time`` range,
containers with their children, and the tab the recording opens on. :func:`chunk_check` runs the
``rerun`` CLI that comes with rerun-sdk and returns its lower bound and effective chunk count.
Used by the tests and by ``groundstation bench rerun``.
"""

from __future__ import annotations

import re
import shutil
import subprocess
import sys
import uuid
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

from rerun.chunk import RrdReader


@dataclass(frozen=True)
class View:
    name: str
    kind: str                                   # TimeSeries, StateTimeline, BarChart, TextDocument, ...
    origin: str
    fc_range_s: tuple[float, float] | None      # visible fc_time range, None = whole timeline


@dataclass(frozen=True)
class Layout:
    views: dict[str, View]                       # blueprint id -> view
    containers: dict[str, dict[str, Any]]        # blueprint id -> {name, kind, contents, active_tab}
    root: str
    entities: frozenset[str] = field(default_factory=frozenset)
    rows: dict[str, int] = field(default_factory=dict)

    def children(self, cid: str) -> list[str]:
        return list(self.containers.get(cid, {}).get("contents", []))

    def views_under(self, cid: str) -> list[View]:
        """Every view inside container ``cid`` (depth first)."""
        if cid in self.views:
            return [self.views[cid]]
        return [v for ch in self.children(cid) for v in self.views_under(ch)]

    def opening_tab(self) -> str:
        """Id of the tab the recording opens on (the root's active tab, or its first child)."""
        root = self.containers[self.root]
        return root.get("active_tab") or self.children(self.root)[0]

    def name(self, cid: str) -> str:
        return (self.views[cid].name if cid in self.views else self.containers[cid].get("name")) or ""


_LISTS = ("contents", "row_shares", "col_shares")


def _first(rb: Any, col: str) -> Any:
    """The last logged value of ``col`` (a list for list components, else its one element)."""
    if col not in rb.schema.names:
        return None
    vals = [v for v in rb.column(col).to_pylist() if v is not None]
    if not vals or not vals[-1]:
        return None
    return vals[-1] if col.endswith(_LISTS) else vals[-1][0]


def _newest_blueprint(reader: RrdReader) -> Any:
    """The blueprint store sent last (row ids are time-ordered), which the viewer opens."""
    def last_row_id(store: Any) -> bytes:
        ids = [c.to_record_batch().column("rerun.controls.RowId").to_pylist() for c in reader.stream(store=store).to_chunks()]
        return max((bytes(i) for chunk in ids for i in chunk), default=b"")
    return max(reader.blueprints(), key=last_row_id)


def _blueprint_rows(reader: RrdReader) -> tuple[dict[str, dict[str, Any]], str]:
    by_id: dict[str, dict[str, Any]] = {}
    root = ""
    for c in reader.stream(store=_newest_blueprint(reader)).to_chunks():
        rb = c.to_record_batch()
        parts = c.entity_path.strip("/").split("/")
        if parts[0] == "viewport":
            raw = _first(rb, "ViewportBlueprint:root_container")
            if raw is not None:
                root = f"container/{uuid.UUID(bytes=bytes(raw))}"
            continue
        if parts[0] not in ("view", "container") or len(parts) < 2:
            continue
        d = by_id.setdefault(f"{parts[0]}/{parts[1]}", {})
        for col in rb.schema.names:
            if ":" in col:
                v = _first(rb, col)
                if v is not None:
                    d[col.split(":", 1)[1] if parts[0] == "container" or len(parts) == 2 else col] = v
    return by_id, root


def read_layout(path: str | Path) -> Layout:
    """The default blueprint and the entity tree of the .rrd at ``path``."""
    reader = RrdReader(path)
    by_id, root = _blueprint_rows(reader)
    views, containers = {}, {}
    for bid, d in by_id.items():
        if bid.startswith("view/"):
            rng = d.get("VisibleTimeRanges:ranges")
            fc = None
            if isinstance(rng, dict) and rng.get("timeline") == "fc_time":
                fc = (rng["range"]["start"] / 1e9, rng["range"]["end"] / 1e9)
            views[bid] = View(name=d.get("display_name", ""), kind=d.get("class_identifier", ""),
                              origin=d.get("space_origin", ""), fc_range_s=fc)
        else:
            containers[bid] = {"name": d.get("display_name"), "kind": d.get("container_kind"),
                               "contents": list(d.get("contents") or []),
                               "active_tab": d.get("active_tab")}
    rows: dict[str, int] = {}
    for c in reader.stream().to_chunks():
        if not c.is_static:
            rows[c.entity_path] = rows.get(c.entity_path, 0) + c.num_rows
    statics = {c.entity_path for c in reader.stream().to_chunks() if c.is_static}
    return Layout(views=views, containers=containers, root=root, entities=frozenset(rows) | frozenset(statics),
                  rows=rows)


@dataclass(frozen=True)
class ChunkCheck:
    lower_bound: int
    effective: int

    @property
    def factor(self) -> float:
        return self.effective / max(self.lower_bound, 1)


def rerun_cli() -> str:
    """The ``rerun`` executable installed with rerun-sdk (beside this Python), else on PATH."""
    here = Path(sys.executable).with_name("rerun")
    found = str(here) if here.exists() else shutil.which("rerun")
    if not found:
        raise FileNotFoundError("rerun CLI not found (it comes with rerun-sdk)")
    return found


def chunk_check(path: str | Path) -> ChunkCheck:
    """``rerun rrd stats PATH``: the theoretical lower bound and the effective chunk count."""
    proc = subprocess.run([rerun_cli(), "rrd", "stats", str(path)], capture_output=True, text=True, timeout=300)
    text = proc.stdout + proc.stderr
    lo = re.search(r"theoretical lower bound:\s*([\d\s ]+)\s+chunks", text)
    eff = re.search(r"effective:\s*([\d\s ]+)\s+chunks", text)
    if proc.returncode != 0 or lo is None or eff is None:
        raise ValueError(f"{path}: rerun rrd stats gave no chunk index analysis ({text.strip().splitlines()[-1:]})")
    return ChunkCheck(int(re.sub(r"\D", "", lo.group(1))), int(re.sub(r"\D", "", eff.group(1))))
