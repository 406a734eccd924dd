"""A virtual serial port: a Linux pseudo-terminal exposed at a stable symlink path.

The flight-controller side (replay player, simulated FC) holds the pty *master*; the ground
station opens the *slave* through the symlink with pyserial (``serial:///tmp/.../ttyFC``), the
same code path as a USB serial adapter. :meth:`VirtualSerialPort.unplug` closes the pty and removes
the symlink (the device vanishes, as when a USB cable is pulled: a reader gets an error);
:meth:`VirtualSerialPort.replug` creates a new pty and points the same symlink at it (as a USB
re-enumeration).

IO on the master is non-blocking. Writes never drop bytes silently: :meth:`write_nowait` returns how
many bytes the kernel accepted, :meth:`write` blocks (select) and :meth:`awrite` awaits (event-loop
writer callback) until everything is written. Reads return the bytes the ground station wrote.

A Linux pty reports POLLHUP on the master while no process has the slave open; this module uses
that to tell whether a reader is attached (:meth:`reader_attached`). pyserial flushes the input
queue when it opens a port, so bytes written before a reader is attached (or while it is still
opening) are lost, exactly as on a real serial line. The master runs in packet mode (TIOCPKT),
where the kernel reports the reader's input flush as a control byte; :meth:`wait_for_reader`
waits for that flush (or ``flush_wait_s`` for readers that never flush), so callers that must
deliver every byte know when writing is safe.

Not thread-safe: use one port from one thread (or one event loop) at a time. Leaves MAVLink,
timing and fault injection to :mod:`hil_replay.player` and :mod:`hil_replay.fc`.
"""

from __future__ import annotations

import asyncio
import errno
import fcntl
import os
import select
import shutil
import struct
import tempfile
import termios
import time
import tty
import weakref
from pathlib import Path

__all__ = ["PortUnplugged", "VirtualSerialPort"]


def _wake(fut: asyncio.Future[None]) -> None:
    if not fut.done():
        fut.set_result(None)


_TIOCPKT = getattr(termios, "TIOCPKT", 0x5420)
_TIOCPKT_DATA = 0
_TIOCPKT_FLUSHREAD = 1


class PortUnplugged(OSError):
    """IO was attempted on a virtual port while it is unplugged (or closed)."""


class VirtualSerialPort:
    """A pseudo-terminal whose slave device is reachable at a stable symlink path.

    Parameters
    ----------
    link_path : where the symlink to the slave device is created. ``None`` makes a private
        temporary directory ``/tmp/gs-replay-XXXX/ttyFC`` (removed by :meth:`close`). An existing
        symlink at that path (a stale port) is replaced; any other existing file is an error.
    flush_wait_s : after a reader attaches, :meth:`wait_for_reader` waits at most this long for
        the reader's open-time input flush (pyserial does one) before declaring it ready.
    """

    def __init__(self, link_path: str | os.PathLike[str] | None = None, *,
                 flush_wait_s: float = 0.5) -> None:
        self._own_dir: Path | None = None
        if link_path is None:
            self._own_dir = Path(tempfile.mkdtemp(prefix="gs-replay-"))
            # removed at close(), or when the object is collected / the interpreter exits
            self._cleanup = weakref.finalize(self, shutil.rmtree, str(self._own_dir), True)
            path = self._own_dir / "ttyFC"
        else:
            path = Path(link_path)
            if path.exists() and not path.is_symlink():
                raise FileExistsError(f"{path}: exists and is not a symlink; refusing to replace it")
            path.parent.mkdir(parents=True, exist_ok=True)
        self._path = path
        self._flush_wait_s = flush_wait_s
        self._master: int | None = None
        self._inbox = bytearray()        # data the GCS wrote, read while looking for control bytes
        self._flush_seen = False         # the current reader's open-time flush has happened
        self._device = ""
        self._poll: select.poll | None = None
        self._closed = False
        self.unplug_count = 0
        self._plug()

    # ---------------------------------------------------------------- state

    @property
    def path(self) -> str:
        """The stable symlink path (what the ground station opens)."""
        return str(self._path)

    link_path = path

    @property
    def device(self) -> str:
        """The current slave device (``/dev/pts/N``); changes on every replug."""
        return self._device

    @property
    def plugged(self) -> bool:
        return self._master is not None

    def fileno(self) -> int:
        """The master file descriptor (for event-loop readers/writers)."""
        if self._master is None:
            raise PortUnplugged(errno.ENODEV, f"{self._path}: virtual port is unplugged")
        return self._master

    def _plug(self) -> None:
        master, slave = os.openpty()
        try:
            tty.setraw(slave)  # no echo, no line discipline: bytes through unchanged
            attrs = termios.tcgetattr(slave)
            attrs[3] &= ~termios.ECHO
            termios.tcsetattr(slave, termios.TCSANOW, attrs)
            device = os.ttyname(slave)
        finally:
            # The slave is not held open here: POLLHUP on the master then tells us whether a
            # reader is attached, and the termios settings persist while the master is open.
            os.close(slave)
        try:
            os.set_blocking(master, False)
            # packet mode: every read starts with a status byte, 0 = data, else TIOCPKT_* flags
            fcntl.ioctl(master, _TIOCPKT, struct.pack("i", 1))
            tmp = self._path.with_name(f".{self._path.name}.{os.getpid()}.tmp")
            if tmp.is_symlink() or tmp.exists():
                tmp.unlink()
            os.symlink(device, tmp)
            os.replace(tmp, self._path)  # atomic: the path never points at a dead device
        except BaseException:
            os.close(master)
            raise
        self._inbox.clear()
        self._flush_seen = False
        self._master = master
        self._device = device
        self._poll = select.poll()
        self._poll.register(master, select.POLLOUT | select.POLLHUP)

    def unplug(self) -> None:
        """Close the pty and remove the symlink: the port vanishes; an attached reader errors out."""
        if self._master is None:
            return
        try:
            if self._path.is_symlink():
                self._path.unlink()
        finally:
            os.close(self._master)
            self._master = None
            self._poll = None
            self.unplug_count += 1

    def replug(self) -> None:
        """Create a fresh pty and point the same symlink path at it."""
        if self._closed:
            raise PortUnplugged(errno.ENODEV, f"{self._path}: virtual port is closed")
        if self._master is None:
            self._plug()

    def close(self) -> None:
        """Unplug for good and remove the private temporary directory, if any."""
        self.unplug()
        self._closed = True
        if self._own_dir is not None:
            shutil.rmtree(self._own_dir, ignore_errors=True)
            self._own_dir = None

    def __enter__(self) -> VirtualSerialPort:
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()

    def __repr__(self) -> str:
        state = self._device if self.plugged else "unplugged"
        return f"VirtualSerialPort({self.path!s} -> {state})"

    # ---------------------------------------------------------------- reader presence

    def reader_attached(self) -> bool:
        """Whether some process has the slave side open right now."""
        if self._poll is None:
            return False
        for _fd, ev in self._poll.poll(0):
            if ev & select.POLLHUP:
                self._flush_seen = False   # the next reader will flush again when it opens
                return False
        return True

    def reader_ready(self) -> bool:
        """A reader is attached and its open-time input flush has happened."""
        if not self.reader_attached():
            return False
        self._pump()
        return self._flush_seen

    def wait_for_reader(self, timeout_s: float | None = None, *, poll_s: float = 0.002) -> bool:
        """Block until a reader has the port open and is ready (see ``flush_wait_s``).

        Returns False on timeout (or if the reader went away again).
        """
        deadline = None if timeout_s is None else time.monotonic() + timeout_s
        attached_at: float | None = None
        while True:
            now = time.monotonic()
            if self.reader_attached():
                if self.reader_ready():
                    return True
                attached_at = now if attached_at is None else attached_at
                if now - attached_at >= self._flush_wait_s:
                    return True   # a reader that does not flush on open
            else:
                attached_at = None
            if deadline is not None and now >= deadline:
                return False
            time.sleep(poll_s)

    async def await_reader(self, timeout_s: float | None = None, *, poll_s: float = 0.002) -> bool:
        """:meth:`wait_for_reader` for coroutines."""
        loop = asyncio.get_running_loop()
        deadline = None if timeout_s is None else loop.time() + timeout_s
        attached_at: float | None = None
        while True:
            now = loop.time()
            if self.reader_attached():
                if self.reader_ready():
                    return True
                attached_at = now if attached_at is None else attached_at
                if now - attached_at >= self._flush_wait_s:
                    return True
            else:
                attached_at = None
            if deadline is not None and now >= deadline:
                return False
            await asyncio.sleep(poll_s)

    def unread_bytes(self) -> int:
        """Bytes written to the port that the reader has not read yet (0 if unplugged)."""
        if self._master is None:
            return 0
        # A second, short-lived slave descriptor: opening it does not flush, closing it does not
        # hang up while the reader keeps its own descriptor open.
        fd = os.open(self._device, os.O_RDWR | os.O_NOCTTY | os.O_NONBLOCK)
        try:
            return int(struct.unpack("i", fcntl.ioctl(fd, termios.FIONREAD, b"\0\0\0\0"))[0])
        finally:
            os.close(fd)

    def drain(self, timeout_s: float = 2.0, *, quiet_s: float = 0.25, poll_s: float = 0.005) -> bool:
        """Wait until the reader has read everything written (True) or ``timeout_s`` passes.

        The reader's queue (what FIONREAD counts) holds at most 4 KB; the rest of what was written
        waits in the pty's buffer, which the kernel moves into that queue from a work queue after
        each read. The queue can therefore read empty while bytes are still on their way, for as
        long as that work is delayed on a busy machine: it must stay empty for ``quiet_s`` before
        the bytes count as read.
        """
        deadline = time.monotonic() + timeout_s
        empty_since: float | None = None
        while True:
            if not self.reader_attached():
                return False
            now = time.monotonic()
            if self.unread_bytes() == 0:
                empty_since = now if empty_since is None else empty_since
                if now - empty_since >= quiet_s:
                    return True
            else:
                empty_since = None
            if now >= deadline:
                return False
            time.sleep(poll_s)

    # ---------------------------------------------------------------- writing

    def write_nowait(self, data: bytes | memoryview) -> int:
        """Write as much as the pty accepts now; returns the number of bytes written (maybe 0)."""
        fd = self.fileno()
        try:
            return os.write(fd, data)
        except BlockingIOError:
            return 0
        except OSError as exc:
            if exc.errno == errno.EIO:
                return 0
            raise

    def write(self, data: bytes, timeout_s: float | None = None) -> None:
        """Write all of ``data``, blocking while the pty buffer is full.

        Raises TimeoutError (with the number of bytes written so far in the message) if
        ``timeout_s`` passes first, PortUnplugged if the port is unplugged.
        """
        view = memoryview(data)
        deadline = None if timeout_s is None else time.monotonic() + timeout_s
        while view:
            n = self.write_nowait(view)
            view = view[n:]
            if not view:
                break
            wait = None if deadline is None else deadline - time.monotonic()
            if wait is not None and wait <= 0:
                raise TimeoutError(f"{self._path}: reader not draining; "
                                   f"{len(data) - len(view)} of {len(data)} bytes written")
            select.select([], [self.fileno()], [], 0.05 if wait is None else min(wait, 0.05))

    async def awrite(self, data: bytes, stop: asyncio.Event | None = None) -> int:
        """Write all of ``data``, awaiting writability (back-pressure) while the pty buffer is full.

        Returns the number of bytes written: all of them unless ``stop`` was set meanwhile.
        """
        loop = asyncio.get_running_loop()
        view = memoryview(data)
        while view and not (stop is not None and stop.is_set()):
            n = self.write_nowait(view)
            view = view[n:]
            if not view:
                break
            fd = self.fileno()
            fut: asyncio.Future[None] = loop.create_future()
            loop.add_writer(fd, _wake, fut)
            try:
                # the timeout re-checks the port (unplugged meanwhile -> fileno() raises)
                await asyncio.wait_for(fut, 0.05)
            except TimeoutError:
                pass
            finally:
                loop.remove_writer(fd)
        return len(data) - len(view)

    # ---------------------------------------------------------------- reading

    def _pump(self, max_bytes: int = 65536) -> None:
        """Drain the master: data into the inbox, control bytes into the flush flag."""
        fd = self.fileno()
        while True:
            try:
                chunk = os.read(fd, max_bytes + 1)
            except BlockingIOError:
                return
            except OSError as exc:
                if exc.errno == errno.EIO:  # no slave open
                    return
                raise
            if not chunk:
                return
            if chunk[0] == _TIOCPKT_DATA:
                self._inbox += chunk[1:]
                if len(self._inbox) >= max_bytes:
                    return
            elif chunk[0] & _TIOCPKT_FLUSHREAD:
                self._flush_seen = True

    def read_nowait(self, max_bytes: int = 65536) -> bytes:
        """Bytes the ground station has written, or b"" if none (or no reader attached)."""
        self._pump(max_bytes)
        out = bytes(self._inbox[:max_bytes])
        del self._inbox[:max_bytes]
        return out

    async def aread(self, max_bytes: int = 65536, *, poll_s: float = 0.02) -> bytes:
        """Bytes from the ground station; waits up to ``poll_s`` and returns b"" if none came."""
        data = self.read_nowait(max_bytes)
        if data:
            return data
        await asyncio.sleep(poll_s)
        return self.read_nowait(max_bytes) if self.plugged else b""
