"""The package's error base: every error the ``groundstation`` package raises on bad input derives
from :class:`GroundstationError` (sub-packages add their own subclasses beside their code, e.g.
``ConfigError``, ``ZenohSinkError``); the command line prints such an error as one line and exits 2.

The link package has its own bases in :mod:`firmware_interface.errors`.
"""

from __future__ import annotations


class GroundstationError(Exception):
    """Base of the errors the command line reports as one line (bad input, not a bug)."""


class DspError(GroundstationError, ValueError):
    """Bad input to signal processing and flight-data preparation (:mod:`groundstation.dsp`):
    a log without the messages or the flight needed, a setting out of range."""


class SysidError(GroundstationError, ValueError):
    """Bad input to the time-domain identification (:mod:`groundstation.sysid`): too little
    in-air data, an unknown algorithm or parameter name, a malformed model document."""


class GapError(GroundstationError, ValueError):
    """Bad input to the sim-to-real gap diagnosis (:mod:`groundstation.gap`)."""


class FreqError(GroundstationError, ValueError):
    """Bad input to the frequency-domain analysis (:mod:`groundstation.freq`), naming the field
    and value."""
