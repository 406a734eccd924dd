"""zenoh publisher for the live service (eclipse-zenoh 1.x), per the key space of docs/zenoh.md.

Keys (JSON payloads, encoding ``application/json``):

* ``heli/{vehicle}/status``                 about 1 Hz (congestion control DROP)
* ``heli/{vehicle}/telemetry/window``       smoothed windows, a few Hz (DROP)
* ``heli/{vehicle}/excitation``             the live excitation verdict per axis, about 1 Hz while armed (DROP)
* ``heli/{vehicle}/flight/{n}/model``       once per identified flight (BLOCK, reliable)
* ``heli/{vehicle}/flight/{n}/gap``         once per diagnosed flight (BLOCK, reliable)
* ``heli/{vehicle}/flight/{n}/freq``        the model's frequency-domain check (Tischler J per
  input-output pair), once per identified flight (BLOCK, reliable)
* ``heli/{vehicle}/trends``                 trend summary over the vehicle's flights, after each one (BLOCK, reliable)
* ``heli/{vehicle}/flight/{n}/report``      the flight's HTML page: its path and a one-line summary (BLOCK, reliable)
* queryables ``heli/{vehicle}/model/latest`` and ``heli/{vehicle}/gap/latest`` (late subscribers)
* liveliness token ``heli/{vehicle}/alive``

zenoh's Python API is synchronous, so nothing here runs on the event loop: the ``publish_*`` methods
only enqueue (never block; a window is dropped and counted when ``window_queue`` windows are already
waiting), and one publisher thread serialises to JSON and calls ``put``. Queryable callbacks run on
zenoh threads and read the latest documents; if a loop is given, each served query is reported back
to it with ``loop.call_soon_threadsafe``.

Session config: a json5 file (client mode to a ``zenohd`` router on the team network, or anything
zenoh accepts) or the default: a peer listening on ``tcp/127.0.0.1:<port>`` with multicast scouting
off. A config that zenoh rejects raises :class:`ZenohSinkError` (one line naming the file); a router
that cannot be reached yet is retried in the publisher thread while the service goes on.
Leaves what to publish and when to :mod:`groundstation.service`.
"""

from __future__ import annotations

import asyncio
import json
import math
import queue
import socket
import threading
import time
from collections import deque
from collections.abc import Callable
from pathlib import Path
from typing import Any

import numpy as np
import zenoh

from groundstation.errors import GroundstationError
from groundstation.sinks.zenoh_security import ZenohSecurityError, check_zenoh_config, explain_open_failure


class ZenohSinkError(GroundstationError):
    """The zenoh session could not be configured (one line)."""


def free_tcp_port() -> int:
    """A currently free TCP port on 127.0.0.1."""
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return int(s.getsockname()[1])


def loopback_peer_config(listen_port: int = 0, connect_ports: tuple[int, ...] = ()) -> str:
    """json5 text of a loopback peer with scouting off (listening on ``listen_port``, 0 = free port)."""
    port = listen_port or free_tcp_port()
    cfg: dict[str, Any] = {
        "mode": "peer",
        "listen": {"endpoints": [f"tcp/127.0.0.1:{port}"]},
        "scouting": {"multicast": {"enabled": False}, "gossip": {"enabled": False}},
    }
    if connect_ports:
        cfg["connect"] = {"endpoints": [f"tcp/127.0.0.1:{p}" for p in connect_ports]}
    return json.dumps(cfg)


def _json_default(o: Any) -> Any:
    if isinstance(o, np.ndarray):
        return o.tolist()
    if isinstance(o, np.generic):
        return o.item()
    return str(o)


def dumps_numeric(doc: Any) -> str:
    """Fast strict JSON for documents whose only strings are fixed keys (windows): NaN/inf -> null."""
    return (json.dumps(doc, default=_json_default)
            .replace("-Infinity", "null").replace("Infinity", "null").replace("NaN", "null"))


def _security_check(path: str) -> tuple[str | None, bool]:
    """(one-line problem or None, whether it is a client config) from :mod:`zenoh_security`."""
    try:
        return None, check_zenoh_config(path).mode == "client"
    except ZenohSecurityError as exc:
        return str(exc), False


def _explain_failure(path: str) -> str | None:
    """Why a client could not open its session (unreachable, certificate, password), one line."""
    try:
        return f"{path}: zenoh not connected yet: {explain_open_failure(path)}"
    except (ZenohSecurityError, OSError):
        return None


def dumps(doc: Any) -> str:
    """JSON with NaN/inf as null (strict JSON for non-Python subscribers)."""
    def clean(x: Any) -> Any:
        if isinstance(x, float):
            return x if math.isfinite(x) else None
        if isinstance(x, dict):
            return {k: clean(v) for k, v in x.items()}
        if isinstance(x, list | tuple):
            return [clean(v) for v in x]
        return x

    return json.dumps(clean(doc), default=_json_default, allow_nan=False)


class ZenohSink:
    """Publish status, windows, models and gap reports of one vehicle.

    Parameters
    ----------
    vehicle : key chunk ``{vehicle}``
    config_path : json5 zenoh config file; ``None`` = loopback peer on ``listen_port``
    listen_port : default peer's TCP port (0 = pick a free one; see :attr:`endpoint`)
    window_queue : windows allowed to wait for the publisher thread before new ones are dropped
    loop, on_query : if both given, ``on_query(key)`` runs on ``loop`` for every query served
    """

    def __init__(self, vehicle: str, *, config_path: str | None = None, listen_port: int = 0,
                 window_queue: int = 8, loop: asyncio.AbstractEventLoop | None = None,
                 on_query: Callable[[str], None] | None = None, retry_s: float = 2.0) -> None:
        self.vehicle = vehicle
        self.prefix = f"heli/{vehicle}"
        self.endpoint = ""
        if config_path:
            p = Path(config_path)
            try:
                text = p.read_text()
            except OSError as exc:
                raise ZenohSinkError(f"{p}: cannot read zenoh config: {exc.strerror or exc}") from None
            where = str(p)
        else:
            port = listen_port or free_tcp_port()
            text = loopback_peer_config(port)
            self.endpoint = f"tcp/127.0.0.1:{port}"
            where = "default zenoh config"
        try:
            self._config_text = text
            zenoh.Config.from_json5(text)
        except zenoh.ZError as exc:
            msg = " ".join(str(exc).split())
            raise ZenohSinkError(f"{where}: bad zenoh config: {msg}") from None
        self._where = where
        self._window_queue = window_queue
        self._loop = loop
        self._on_query = on_query
        self._retry_s = retry_s
        self._q: queue.Queue[tuple[str, Any, Any]] = queue.Queue()
        self._windows_waiting = 0
        self._lock = threading.Lock()
        self.latest: dict[str, dict | None] = {"model": None, "gap": None, "trends": None}
        self.sent: dict[str, int] = {"status": 0, "window": 0, "excitation": 0, "model": 0, "gap": 0, "freq": 0, "trends": 0,
                                     "report": 0}
        self.windows_dropped = 0
        self.queries_served = 0
        #: (seq, t_host_last_s, t_published_s) of recent windows, for latency measurement
        self.window_latency: deque[tuple[int, float, float]] = deque(maxlen=100000)
        self.error: str | None = None
        # secured configs (groundstation.sinks.zenoh_security): expired/missing certificates, keys
        # readable by others, ... become the one-line error now; a failed open is explained later
        self._client_file = False
        if config_path:
            self.error, self._client_file = _security_check(where)
        self.connected = threading.Event()
        self._session: Any = None
        self._entities: list[Any] = []
        self._closing = threading.Event()
        self._open()   # first attempt inline so a config error surfaces now
        self._thread = threading.Thread(target=self._run, name="zenoh-publisher", daemon=True)
        self._thread.start()

    # ------------------------------------------------------------------ session

    def _open(self) -> bool:
        try:
            session = zenoh.open(zenoh.Config.from_json5(self._config_text))
        except zenoh.ZError as exc:
            if self.error is None:
                self.error = (_explain_failure(self._where) if self._client_file else None) or \
                    f"{self._where}: zenoh not connected yet ({' '.join(str(exc).split())[:120]})"
            return False
        p = self.prefix
        json_enc = zenoh.Encoding.APPLICATION_JSON
        self._pub = {
            "status": session.declare_publisher(f"{p}/status", encoding=json_enc,
                                                congestion_control=zenoh.CongestionControl.DROP),
            "window": session.declare_publisher(f"{p}/telemetry/window", encoding=json_enc,
                                                congestion_control=zenoh.CongestionControl.DROP),
            "excitation": session.declare_publisher(f"{p}/excitation", encoding=json_enc,
                                                    congestion_control=zenoh.CongestionControl.DROP),
        }
        self._entities = [
            session.declare_queryable(f"{p}/model/latest", self._make_handler("model")),
            session.declare_queryable(f"{p}/gap/latest", self._make_handler("gap")),
            session.liveliness().declare_token(f"{p}/alive"),
        ]
        self._session = session
        self.connected.set()
        return True

    def _make_handler(self, kind: str) -> Callable[[Any], None]:
        key = f"{self.prefix}/{kind}/latest"

        def handler(query: Any) -> None:   # runs on a zenoh thread
            doc = self.latest[kind]
            if doc is None:
                query.reply_err(dumps({"error": f"no {kind} yet"}), encoding=zenoh.Encoding.APPLICATION_JSON)
            else:
                query.reply(key, dumps(doc), encoding=zenoh.Encoding.APPLICATION_JSON)
            with self._lock:
                self.queries_served += 1
            if self._loop is not None and self._on_query is not None:
                try:
                    self._loop.call_soon_threadsafe(self._on_query, key)
                except RuntimeError:   # loop already closed during shutdown
                    pass

        return handler

    # ------------------------------------------------------------------ enqueue (any thread)

    def publish_status(self, doc: dict) -> None:
        self._q.put_nowait(("status", None, doc))

    def publish_excitation(self, doc: dict | Callable[[], dict]) -> None:
        """The live excitation verdict (``heli/{vehicle}/excitation``; a dict, or a callable making it on
        the publisher thread); dropped, like the status, under congestion."""
        self._q.put_nowait(("excitation", None, doc))

    def publish_window(self, doc: dict | Callable[[], dict], *, seq: int = -1,
                       t_host_last_s: float = math.nan) -> bool:
        """Enqueue a window (a dict of numbers, or a callable making it, run on the publisher thread);
        False (and counted) if ``window_queue`` windows are already waiting."""
        with self._lock:
            if self._windows_waiting >= self._window_queue:
                self.windows_dropped += 1
                return False
            self._windows_waiting += 1
        self._q.put_nowait(("window", (seq, t_host_last_s), doc))
        return True

    def publish_model(self, flight: int, doc: dict) -> None:
        self.latest["model"] = doc
        self._q.put_nowait(("model", flight, doc))

    def publish_gap(self, flight: int, doc: dict) -> None:
        self.latest["gap"] = doc
        self._q.put_nowait(("gap", flight, doc))

    def publish_freq(self, flight: int, doc: dict) -> None:
        """The ``heli-freq-verification/1`` J table of the flight's model (reliable, like the model)."""
        self._q.put_nowait(("freq", flight, doc))

    def publish_report(self, flight: int, doc: dict) -> None:
        """Where the flight's HTML page is and its one-line summary (``{"vehicle", "flight", "path", "summary"}``)
        on ``heli/{vehicle}/flight/{n}/report`` (reliable)."""
        self._q.put_nowait(("report", flight, doc))

    def publish_trends(self, doc: dict) -> None:
        """The latest trend summary over the vehicle's flights on ``heli/{vehicle}/trends`` (reliable)."""
        self.latest["trends"] = doc
        self._q.put_nowait(("trends", None, doc))

    # ------------------------------------------------------------------ publisher thread

    def _run(self) -> None:
        next_try = time.monotonic() + self._retry_s
        backlog: list[tuple[str, Any, Any]] = []    # reliable items waiting for a session
        while True:
            try:
                item = self._q.get(timeout=0.2)
            except queue.Empty:
                item = None
            if item is not None and item[0] == "stop":
                self._q.task_done()
                break
            if item is not None and item[0] == "window":
                with self._lock:
                    self._windows_waiting -= 1
            if self._session is None:
                if item is not None:
                    if item[0] in ("model", "gap", "freq", "trends", "report"):
                        backlog.append(item)
                    self._q.task_done()
                if time.monotonic() >= next_try and not self._closing.is_set():
                    next_try = time.monotonic() + self._retry_s
                    if self._open():
                        for b in backlog:
                            self._send(*b)
                        backlog.clear()
                continue
            if item is not None:
                self._send(*item)
                self._q.task_done()

    def _send(self, kind: str, extra: Any, doc: Any) -> None:
        try:
            if kind == "window":
                payload = dumps_numeric(doc() if callable(doc) else doc)
            else:
                payload = dumps(doc() if callable(doc) else doc)
            if kind in ("status", "window", "excitation"):
                self._pub[kind].put(payload)
                if kind == "window":
                    seq, t_host = extra
                    self.window_latency.append((seq, t_host, time.time()))
            else:
                key = f"{self.prefix}/trends" if kind == "trends" else f"{self.prefix}/flight/{extra}/{kind}"
                self._session.put(key, payload,
                                  encoding=zenoh.Encoding.APPLICATION_JSON,
                                  congestion_control=zenoh.CongestionControl.BLOCK)
            self.sent[kind] += 1
        except zenoh.ZError as exc:
            self.error = f"zenoh put {kind}: {' '.join(str(exc).split())[:120]}"

    def flush(self, timeout_s: float = 2.0) -> bool:
        """Wait until everything enqueued so far has been handed to zenoh (True) or timeout."""
        end = time.monotonic() + timeout_s
        while time.monotonic() < end:
            if self._q.unfinished_tasks == 0:
                return True
            time.sleep(0.01)
        return False

    def close(self, timeout_s: float = 1.5) -> None:
        """Stop the thread (after what is queued) and close the session; idempotent."""
        if self._closing.is_set():
            return
        self._closing.set()
        self._q.put_nowait(("stop", None, None))
        self._thread.join(timeout_s)
        for ent in self._entities:
            try:
                ent.undeclare()
            except zenoh.ZError:
                pass
        if self._session is not None:
            try:
                self._session.close()
            except zenoh.ZError:
                pass
