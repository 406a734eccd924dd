"""Run sink calls on a background thread behind a bounded queue (the event loop never waits).

``submit(fn, *args)`` enqueues without blocking; when ``maxsize`` calls are already waiting the call
is dropped and counted in :attr:`BackgroundCalls.dropped`. Errors in a call are kept (first one in
:attr:`error`, one line) and later calls still run. Used for Rerun logging by the service.
"""

from __future__ import annotations

import queue
import threading
from collections.abc import Callable
from typing import Any


class BackgroundCalls:
    def __init__(self, name: str, maxsize: int = 64) -> None:
        self._q: queue.Queue[tuple[Callable[..., Any], tuple[Any, ...]] | None] = queue.Queue(maxsize)
        self.dropped = 0
        self.done = 0
        self.error: str | None = None
        self._thread = threading.Thread(target=self._run, name=name, daemon=True)
        self._thread.start()

    def submit(self, fn: Callable[..., Any], *args: Any) -> bool:
        try:
            self._q.put_nowait((fn, args))
            return True
        except queue.Full:
            self.dropped += 1
            return False

    def _run(self) -> None:
        while True:
            item = self._q.get()
            if item is None:
                return
            fn, args = item
            try:
                fn(*args)
                self.done += 1
            except Exception as exc:  # a sink failing must not stop the others; reported in status
                if self.error is None:
                    self.error = f"{getattr(fn, '__qualname__', fn)}: {type(exc).__name__}: {exc}".splitlines()[0]

    def close(self, timeout_s: float = 1.0) -> bool:
        """Finish what is queued (up to ``timeout_s``) and stop; True if the thread ended."""
        try:
            self._q.put(None, timeout=timeout_s)
        except queue.Full:
            return False
        self._thread.join(timeout_s)
        return not self._thread.is_alive()
