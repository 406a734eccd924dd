"""Byte transports to the flight controller, opened from URLs (asyncio).

=============================================  =============================================
``serial:///dev/ttyUSB0:921600``               pyserial, non-blocking fd read with ``loop.add_reader``
``pty:///tmp/gs-replay-xxx/ttyFC``             same as serial (a virtual port from :mod:`hil_replay.pty`)
``udpin://0.0.0.0:14550``                      listen; replies go to the last sender
``udpout://127.0.0.1:14550``                   send to a fixed address, read its replies
``tcp://127.0.0.1:5760``                       asyncio stream client
=============================================  =============================================

Every link has ``await read() -> bytes`` (at least one byte), ``await write(bytes)``,
``await close()`` and ``await reconnect()``. When the underlying device goes away (USB unplug: EIO,
empty read, the path vanished; TCP: EOF or reset) ``read``/``write`` raise :class:`LinkDown`;
``reconnect`` then retries with exponential backoff (``backoff_s`` doubling up to ``backoff_max_s``)
until the same path/address opens again. UDP has no connection: loss shows only as silence, which the
session's link timeout reports.

A URL that cannot be opened at all raises :class:`~firmware_interface.errors.TransportError` with the
URL in the message. Third-party exceptions (``serial.SerialException``, socket errors) are mapped to
these two at this edge. Leaves MAVLink to :mod:`firmware_interface.session`.
"""

from __future__ import annotations

import asyncio
import os
import socket
from dataclasses import dataclass
from urllib.parse import urlparse

from firmware_interface.errors import TransportError

__all__ = ["Link", "LinkDown", "LinkUrl", "SerialLink", "TcpLink", "UdpLink", "open_link", "parse_url"]

DEFAULT_BAUD = 115200


class LinkDown(TransportError):
    """The device or connection went away; call ``reconnect()``."""


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


class Link:
    """Base of the transports (see the module docstring)."""

    url: str
    backoff_s: float = 0.1
    backoff_max_s: float = 2.0

    async def read(self) -> bytes:  # pragma: no cover - interface
        raise NotImplementedError

    async def write(self, data: bytes) -> None:  # pragma: no cover - interface
        raise NotImplementedError

    async def close(self) -> None:  # pragma: no cover - interface
        raise NotImplementedError

    async def _open(self) -> None:  # pragma: no cover - interface
        raise NotImplementedError

    async def reconnect(self) -> None:
        """Reopen after :class:`LinkDown`, retrying with exponential backoff until it works."""
        await self.close()
        delay = self.backoff_s
        while True:
            try:
                await self._open()
                return
            except OSError:
                await asyncio.sleep(delay)
                delay = min(2 * delay, self.backoff_max_s)


class SerialLink(Link):
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
        import serial

        if not os.path.exists(self.path):
            raise TransportError(f"{self.url}: no such port {self.path}")
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


class UdpLink(Link):
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


class TcpLink(Link):
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
    link: Link
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

