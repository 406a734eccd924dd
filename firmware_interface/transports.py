"""Byte transports to the flight controller, opened from URLs (asyncio).

=============================================  =============================================
``serial:///dev/ttyUSB0:921600``               pyserial, non-blocking fd read with ``loop.add_reader``
``pty:///tmp/gs-replay-xxx/ttyFC``             same as serial (a virtual port from :mod:`hil_replay.pty`)
``udpin://0.0.0.0:14550``                      listen; replies go to the last sender
``udpout://127.0.0.1:14550``                   send to a fixed address, read its replies
``tcp://127.0.0.1:5760``                       asyncio stream client
=============================================  =============================================

Every link satisfies the :class:`Link` protocol: ``await read() -> bytes`` (at least one byte),
``await write(bytes)``, ``await close()``. When the underlying device goes away (USB unplug: EIO,
empty read, the path vanished; TCP: EOF or reset) ``read``/``write`` raise :class:`LinkDown`; the
driver (:class:`firmware_interface.link.LinkRunner`) then opens the URL again with backoff. UDP has
no connection: loss shows only as silence, which the session's link timeout reports.

A URL that cannot be opened raises :class:`~firmware_interface.errors.TransportError` with the URL
in the message; a serial port that does not exist (yet) raises its subclass :class:`PortMissing`
(the driver waits for it), a path that exists but is not a serial device is a plain TransportError.
Third-party exceptions (``serial.SerialException``, socket errors) are mapped to these at this edge.

:class:`ScriptedLink` is an in-memory link (as httpcore ships its ``MockStream``): scripted chunks
and link losses, for tests of the logic above the transport without ptys or sleeps.
Leaves MAVLink to :mod:`firmware_interface.session`.
"""

from __future__ import annotations

import asyncio
import os
import socket
import stat
from collections.abc import Iterable
from dataclasses import dataclass
from typing import Protocol, runtime_checkable
from urllib.parse import urlparse

import serial

from firmware_interface.errors import TransportError

__all__ = ["Link", "LinkDown", "LinkUrl", "PortMissing", "ScriptedLink", "SerialLink", "TcpLink", "UdpLink",
           "open_link", "parse_url"]

DEFAULT_BAUD = 115200


class LinkDown(TransportError):
    """The device or connection went away; open the URL again."""


class PortMissing(TransportError):
    """The serial port's path does not exist (yet): the flight controller is not plugged in."""

    def __init__(self, message: str, path: str) -> None:
        super().__init__(message)
        self.path = path


@dataclass(frozen=True)
class LinkUrl:
    scheme: str  # serial, udpin, udpout, tcp
    path: str = ""  # serial device
    baud: int = DEFAULT_BAUD
    host: str = ""
    port: int = 0
    text: str = ""


def parse_url(url: str) -> LinkUrl:
    """Parse a link URL (see the module docstring); raises TransportError naming the URL."""
    u = urlparse(url)
    scheme = u.scheme.lower()
    if scheme in ("serial", "pty"):
        spec = (u.netloc + u.path) if u.netloc else u.path
        baud = DEFAULT_BAUD
        head, sep, tail = spec.rpartition(":")
        if sep and tail.isdigit():
            spec, baud = head, int(tail)
        elif sep and tail:
            raise TransportError(f"{url}: baud rate {tail!r} is not a number")
        if not spec:
            raise TransportError(f"{url}: no device path (expected serial:///dev/ttyUSB0:921600)")
        return LinkUrl("serial", path=spec, baud=baud, text=url)
    if scheme in ("udpin", "udpout", "udp", "tcp"):
        if scheme == "udp":
            scheme = "udpin"
        try:
            host, port = u.hostname, u.port
        except ValueError:
            raise TransportError(f"{url}: bad port number") from None
        if not host or port is None or (port == 0 and scheme != "udpin"):
            raise TransportError(f"{url}: expected {scheme}://HOST:PORT")
        return LinkUrl(scheme, host=host, port=port, text=url)
    raise TransportError(f"{url}: unknown link scheme {u.scheme!r} (serial://, udpin://, udpout://, tcp://)")


@runtime_checkable
class Link(Protocol):
    """What the driver needs of a transport (see the module docstring)."""

    url: str

    async def read(self) -> bytes:
        """At least one byte; raises :class:`LinkDown` when the device or connection is gone."""
        ...

    async def write(self, data: bytes) -> None:
        """All of ``data``; raises :class:`LinkDown` when the device or connection is gone."""
        ...

    async def close(self) -> None:
        """Release the device (idempotent)."""
        ...


class ScriptedLink:
    """An in-memory :class:`Link`: ``read`` returns the scripted chunks in order (an exception in the
    script, e.g. ``LinkDown``, is raised from ``read`` instead), then waits for :meth:`feed`.
    ``written`` collects what was sent; ``closed`` tells whether :meth:`close` was called."""

    def __init__(self, script: Iterable[bytes | BaseException] = (), url: str = "script://") -> None:
        self.url = url
        self._script: list[bytes | BaseException] = list(script)
        self._wake = asyncio.Event()
        self.written = bytearray()
        self.closed = False

    def feed(self, *items: bytes | BaseException) -> None:
        """Append chunks (or an exception to raise) to the script; wakes a waiting ``read``."""
        self._script.extend(items)
        self._wake.set()

    @property
    def pending(self) -> int:
        """Script items not read yet."""
        return len(self._script)

    async def read(self) -> bytes:
        while not self._script:
            if self.closed:
                raise LinkDown(f"{self.url}: closed")
            self._wake.clear()
            await self._wake.wait()
        item = self._script.pop(0)
        if isinstance(item, BaseException):
            raise item
        return item

    async def write(self, data: bytes) -> None:
        if self.closed:
            raise LinkDown(f"{self.url}: closed")
        self.written += data

    async def close(self) -> None:
        self.closed = True
        self._wake.set()


class SerialLink:
    """A serial port through pyserial, read without blocking the event loop (``add_reader``)."""

    def __init__(self, path: str, baud: int = DEFAULT_BAUD, url: str = "") -> None:
        self.path = path
        self.baud = baud
        self.url = url or f"serial://{path}:{baud}"
        self._ser = None
        self._fd = -1
        self._buf = bytearray()
        self._err: str | None = None
        self._wake = asyncio.Event()
        self.bytes_read = 0

    async def _open(self) -> None:
        try:
            mode = os.stat(self.path).st_mode
        except FileNotFoundError:
            raise PortMissing(f"{self.url}: no such port {self.path}", self.path) from None
        except OSError as exc:
            raise TransportError(f"{self.url}: cannot open {self.path} ({exc.strerror or exc})") from None
        if not stat.S_ISCHR(mode):
            raise TransportError(f"{self.url}: {self.path} is not a serial device")
        try:
            ser = serial.Serial(self.path, self.baud, timeout=0, write_timeout=0, exclusive=True)
        except serial.SerialException as exc:
            raise TransportError(f"{self.url}: cannot open ({exc})") from None
        except ValueError as exc:
            raise TransportError(f"{self.url}: {exc}") from None
        self._ser = ser
        self._fd = ser.fileno()
        os.set_blocking(self._fd, False)
        self._err = None
        self._buf.clear()
        asyncio.get_running_loop().add_reader(self._fd, self._on_readable)

    def _on_readable(self) -> None:
        try:
            data = os.read(self._fd, 65536)
        except BlockingIOError:
            return
        except OSError as exc:
            self._fail(f"read error: {os.strerror(exc.errno) if exc.errno else exc}")
            return
        if not data:
            self._fail("device returned no data (disconnected)")
            return
        self._buf += data
        self.bytes_read += len(data)
        self._wake.set()

    def _fail(self, reason: str) -> None:
        self._err = reason
        if self._fd >= 0:
            try:
                asyncio.get_running_loop().remove_reader(self._fd)
            except RuntimeError:
                pass
        self._wake.set()

    async def read(self) -> bytes:
        while not self._buf:
            if self._err is not None or self._ser is None:
                raise LinkDown(f"{self.url}: {self._err or 'port closed'}")
            try:
                # asyncio.timeout, not wait_for: on 3.11 wait_for can swallow a cancellation
                # that races its own timeout, and the reader task would not stop.
                async with asyncio.timeout(0.5):
                    await self._wake.wait()
            except TimeoutError:
                if not os.path.exists(self.path):
                    self._fail(f"port {self.path} vanished")
            self._wake.clear()
        data = bytes(self._buf)
        self._buf.clear()
        return data

    async def write(self, data: bytes) -> None:
        view = memoryview(data)
        while view:
            if self._ser is None or self._err is not None:
                raise LinkDown(f"{self.url}: {self._err or 'port closed'}")
            try:
                n = os.write(self._fd, view)
            except BlockingIOError:
                await asyncio.sleep(0.001)
                continue
            except OSError as exc:
                self._fail(f"write error: {os.strerror(exc.errno) if exc.errno else exc}")
                raise LinkDown(f"{self.url}: {self._err}") from None
            view = view[n:]

    async def close(self) -> None:
        if self._ser is not None:
            if self._fd >= 0:
                try:
                    asyncio.get_running_loop().remove_reader(self._fd)
                except (RuntimeError, ValueError):
                    pass
            try:
                self._ser.close()
            except OSError:
                pass
            self._ser = None
            self._fd = -1


class _Datagram(asyncio.DatagramProtocol):
    def __init__(self, link: UdpLink) -> None:
        self.link = link

    def datagram_received(self, data: bytes, addr) -> None:  # noqa: ANN001
        self.link._peer = addr
        self.link._buf += data
        self.link._wake.set()

    def error_received(self, exc: Exception) -> None:
        # ICMP port unreachable on udpout when nobody listens yet: not fatal for UDP
        pass


class UdpLink:
    """``udpin`` binds and answers the last sender; ``udpout`` sends to a fixed address."""

    def __init__(self, mode: str, host: str, port: int, url: str = "") -> None:
        self.mode, self.host, self.port = mode, host, port
        self.url = url or f"{mode}://{host}:{port}"
        self._transport: asyncio.DatagramTransport | None = None
        self._peer: tuple | None = None if mode == "udpin" else (host, port)
        self._buf = bytearray()
        self._wake = asyncio.Event()

    async def _open(self) -> None:
        loop = asyncio.get_running_loop()
        try:
            if self.mode == "udpin":
                tr, _ = await loop.create_datagram_endpoint(lambda: _Datagram(self),
                                                            local_addr=(self.host, self.port))
            else:
                tr, _ = await loop.create_datagram_endpoint(lambda: _Datagram(self),
                                                            remote_addr=(self.host, self.port))
        except (OSError, socket.gaierror) as exc:
            raise TransportError(f"{self.url}: cannot open ({exc})") from None
        self._transport = tr

    @property
    def local_port(self) -> int:
        assert self._transport is not None
        return self._transport.get_extra_info("sockname")[1]

    async def read(self) -> bytes:
        while not self._buf:
            if self._transport is None:
                raise LinkDown(f"{self.url}: closed")
            await self._wake.wait()
            self._wake.clear()
        data = bytes(self._buf)
        self._buf.clear()
        return data

    async def write(self, data: bytes) -> None:
        if self._transport is None:
            raise LinkDown(f"{self.url}: closed")
        if self._peer is None:
            return  # udpin: nobody has talked to us yet
        if self.mode == "udpin":
            self._transport.sendto(data, self._peer)
        else:
            self._transport.sendto(data)

    async def close(self) -> None:
        if self._transport is not None:
            self._transport.close()
            self._transport = None
            self._wake.set()


class TcpLink:
    """TCP client (e.g. SITL on port 5760)."""

    def __init__(self, host: str, port: int, url: str = "") -> None:
        self.host, self.port = host, port
        self.url = url or f"tcp://{host}:{port}"
        self._reader: asyncio.StreamReader | None = None
        self._writer: asyncio.StreamWriter | None = None

    async def _open(self) -> None:
        try:
            self._reader, self._writer = await asyncio.open_connection(self.host, self.port)
        except OSError as exc:
            raise TransportError(f"{self.url}: cannot connect ({exc.strerror or exc})") from None

    async def read(self) -> bytes:
        if self._reader is None:
            raise LinkDown(f"{self.url}: closed")
        try:
            data = await self._reader.read(65536)
        except (ConnectionError, OSError) as exc:
            raise LinkDown(f"{self.url}: {exc}") from None
        if not data:
            raise LinkDown(f"{self.url}: connection closed by peer")
        return data

    async def write(self, data: bytes) -> None:
        if self._writer is None:
            raise LinkDown(f"{self.url}: closed")
        try:
            self._writer.write(data)
            await self._writer.drain()
        except (ConnectionError, OSError) as exc:
            raise LinkDown(f"{self.url}: {exc}") from None

    async def close(self) -> None:
        if self._writer is not None:
            self._writer.close()
            try:
                await self._writer.wait_closed()
            except (ConnectionError, OSError):
                pass
            self._writer = None
            self._reader = None


async def open_link(url: str) -> Link:
    """Open a transport from its URL (raises TransportError naming the URL on failure)."""
    u = parse_url(url)
    link: SerialLink | UdpLink | TcpLink
    if u.scheme == "serial":
        link = SerialLink(u.path, u.baud, url)
    elif u.scheme in ("udpin", "udpout"):
        link = UdpLink(u.scheme, u.host, u.port, url)
    else:
        link = TcpLink(u.host, u.port, url)
    try:
        await link._open()
    except TransportError:
        raise
    except OSError as exc:
        raise TransportError(f"{url}: {os.strerror(exc.errno) if exc.errno else exc}") from None
    return link

