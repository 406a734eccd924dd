"""Exceptions of the ``firmware_interface`` package.

One base class, :class:`FirmwareInterfaceError`. Protocol and log errors derive from
:class:`LinkError` (also a ``ValueError``), split as h11/wsproto do: :class:`LocalProtocolError` when *we* would misuse the protocol (e.g. try to send a
message outside the read-only allowlist), :class:`RemoteProtocolError` when the peer did.
:class:`LogError` is raised by the log readers for a file they cannot read; its message names the
file. :class:`TransportError` (also an ``OSError``) names the URL/port that failed to open or was lost.
The command line reports any of them as one line.
"""

from __future__ import annotations

__all__ = ["FirmwareInterfaceError", "LinkError", "LocalProtocolError", "LogError", "RemoteProtocolError",
           "TransportError"]


class FirmwareInterfaceError(Exception):
    """Base of every error raised by ``firmware_interface``."""


class LinkError(FirmwareInterfaceError, ValueError):
    """Bad data or a misuse of the protocol (a ``ValueError``)."""


class LocalProtocolError(LinkError):
    """We tried to do something the protocol (or our read-only policy) forbids."""


class RemoteProtocolError(LinkError):
    """The flight controller sent something we cannot accept."""


class LogError(LinkError):
    """A log file cannot be read; the message names the file and the reason."""


class TransportError(FirmwareInterfaceError, OSError):
    """A link URL cannot be opened or is malformed; the message names the URL."""
