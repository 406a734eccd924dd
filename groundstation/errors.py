"""The package's error base: every error the ``groundstation`` package raises on bad input derives
from :class:`GroundstationError` (sub-packages add their own subclasses beside their code, e.g.
``ConfigError``, ``ZenohSinkError``); the command line prints such an error as one line and exits 2.

The link package has its own bases in :mod:`firmware_interface.errors`.
"""

from __future__ import annotations


class GroundstationError(Exception):
    """Base of the errors the command line reports as one line (bad input, not a bug)."""
