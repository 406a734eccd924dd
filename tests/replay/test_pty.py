"""VirtualSerialPort through real pseudo-terminals and real pyserial."""

from __future__ import annotations

import asyncio
import os
import time

import pytest
import serial

from hil_replay.pty import PortUnplugged, VirtualSerialPort


def _read_exactly(ser: serial.Serial, n: int, timeout_s: float = 5.0) -> bytes:
    out = bytearray()
    deadline = time.monotonic() + timeout_s
    while len(out) < n and time.monotonic() < deadline:
        out += ser.read(n - len(out))
    return bytes(out)


def test_both_directions_with_pyserial(tmp_path):
    with VirtualSerialPort(tmp_path / "ttyFC") as port:
        assert os.path.islink(port.path)
        assert os.path.realpath(port.path) == port.device
        assert not port.reader_attached()
        ser = serial.Serial(port.path, 921600, timeout=0.2)
        try:
            assert port.wait_for_reader(2.0)
            payload = bytes(range(256)) * 4  # every byte value: raw mode, no translation
            port.write(payload, timeout_s=5.0)
            assert _read_exactly(ser, len(payload)) == payload
            ser.write(b"\x00\r\n\x03\xfd from gcs")
            ser.flush()
            got = b""
            deadline = time.monotonic() + 2
            while len(got) < 14 and time.monotonic() < deadline:
                got += port.read_nowait()
                time.sleep(0.005)
            assert got == b"\x00\r\n\x03\xfd from gcs"
        finally:
            ser.close()


def test_back_pressure_never_drops_bytes(tmp_path):
    """More than the pty buffer holds: the writer waits for the reader instead of dropping."""
    with VirtualSerialPort(tmp_path / "tty") as port:
        ser = serial.Serial(port.path, 115200, timeout=0.05)
        try:
            assert port.wait_for_reader(2.0)
            payload = os.urandom(200_000)
            with pytest.raises(TimeoutError):
                port.write(payload, timeout_s=0.2)  # nobody reads -> times out, does not drop
            received = _read_exactly(ser, 1_000_000, timeout_s=0.5)
            assert 0 < len(received) < len(payload)
            assert payload.startswith(received)
        finally:
            ser.close()


def test_async_writer_with_back_pressure(tmp_path):
    payload = os.urandom(100_000)

    async def main(port: VirtualSerialPort, ser: serial.Serial) -> bytes:
        loop = asyncio.get_running_loop()
        reader = loop.run_in_executor(None, _read_exactly, ser, len(payload), 10.0)
        await port.awrite(payload)
        return await reader

    with VirtualSerialPort(tmp_path / "tty") as port:
        ser = serial.Serial(port.path, 115200, timeout=0.05)
        try:
            assert port.wait_for_reader(2.0)
            assert asyncio.run(main(port, ser)) == payload
        finally:
            ser.close()


def test_unplug_vanishes_and_replug_returns_at_same_path(tmp_path):
    port = VirtualSerialPort(tmp_path / "ttyFC")
    try:
        path = port.path
        ser = serial.Serial(path, 57600, timeout=0.2)
        assert port.wait_for_reader(2.0)
        port.write(b"before")
        assert _read_exactly(ser, 6) == b"before"

        port.unplug()
        assert not os.path.lexists(path)
        assert not port.plugged
        with pytest.raises(serial.SerialException):
            ser.read(10)
        ser.close()
        with pytest.raises(serial.SerialException):
            serial.Serial(path, 57600)
        with pytest.raises(PortUnplugged):
            port.write_nowait(b"x")

        port.replug()
        assert os.path.islink(path) and os.path.realpath(path) == port.device
        ser2 = serial.Serial(path, 57600, timeout=0.2)
        try:
            assert port.wait_for_reader(2.0)
            port.write(b"after")
            assert _read_exactly(ser2, 5) == b"after"
        finally:
            ser2.close()
    finally:
        port.close()
    assert not os.path.lexists(path)


def test_default_path_is_private_and_removed(tmp_path):
    port = VirtualSerialPort()
    d = os.path.dirname(port.path)
    assert os.path.basename(d).startswith("gs-replay-")
    port.close()
    assert not os.path.exists(d)


def test_refuses_to_replace_a_regular_file(tmp_path):
    f = tmp_path / "notalink"
    f.write_text("keep me")
    with pytest.raises(FileExistsError, match="notalink"):
        VirtualSerialPort(f)
    assert f.read_text() == "keep me"


def test_ready_only_after_the_readers_open_flush(tmp_path):
    """pyserial flushes its input on open: the port reports ready only after that flush, so
    bytes written from then on all arrive; a reader that never flushes is ready after flush_wait_s."""
    with VirtualSerialPort(tmp_path / "tty", flush_wait_s=0.3) as port:
        assert not port.reader_ready()
        for _ in range(3):
            ser = serial.Serial(port.path, 115200, timeout=0.2)
            try:
                assert port.wait_for_reader(2.0) and port.reader_ready()
                port.write(b"first bytes after open")
                assert _read_exactly(ser, 22) == b"first bytes after open"
            finally:
                ser.close()
            assert not port.reader_attached() and not port.reader_ready()
        fd = os.open(port.path, os.O_RDWR | os.O_NOCTTY)   # a raw reader: no flush on open
        try:
            t0 = time.monotonic()
            assert port.wait_for_reader(2.0)
            assert time.monotonic() - t0 >= 0.25
            assert not port.reader_ready()
        finally:
            os.close(fd)
