"""``groundstation bench replay``: replay throughput through a pty into the recorder.

Makes a 50 Hz full-telemetry flight (``hil_replay.sim.write_tlog`` when present,
else a synthetic one encoded with pymavlink: ATTITUDE, SERVO_OUTPUT_RAW, RAW_IMU,
LOCAL_POSITION_NED, GLOBAL_POSITION_INT at 50 Hz, GPS_RAW_INT 5 Hz, SYS_STATUS and
EXTENDED_SYS_STATE 2 Hz, HEARTBEAT 1 Hz), replays it with :class:`hil_replay.player.TlogPlayer`
at maximum speed on a :class:`hil_replay.pty.VirtualSerialPort` into a recorder, and prints the
real-time factor (log seconds per wall second, target >= 20) and the packets lost (target 0),
median of ``--runs`` runs. ``--fc`` measures the simulated flight controller instead (simulator +
MAVLink protocol at maximum speed into the recorder, FC seconds per wall second).

The recorder is ``groundstation record --link serial://PORT --out DIR`` in a subprocess (the
record command, the real path) when it exists; otherwise an in-process pyserial reader
that frames packets with pymavlink and writes them with :class:`firmware_interface.tlog.TlogWriter`
(``--recorder direct`` forces it). Packets lost = source packets missing from the recorded .tlog.
The real-time factor is log seconds over wall seconds from the first byte written until the
recorder has read the last one (the pty drained); the pty buffer is ~18 KB, so the writer is
throttled by the recorder's reading and processing throughout.
"""

from __future__ import annotations

import argparse
import importlib.util
import os
import signal
import statistics
import subprocess
import sys
import tempfile
import threading
import time
from collections import Counter
from pathlib import Path

import serial
from pymavlink.dialects.v20 import ardupilotmega as mavlink

from benchkit.telemetry import sine_flight_tlog
from firmware_interface.tlog import TlogWriter
from hil_replay.fc import FcConfig, SimulatedFCThread
from hil_replay.player import TlogPlayer, read_tlog_packets
from hil_replay.pty import VirtualSerialPort
from hil_replay.sim import write_tlog

HELP = "replay a 50 Hz full-telemetry flight through a pty into the recorder at max speed"


def add_arguments(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("--duration", type=float, default=300.0, help="flight length in s (synthetic log)")
    parser.add_argument("--runs", type=int, default=3, help="number of runs (median reported)")
    parser.add_argument("--speed", type=float, default=0.0, help="replay speed (0 = as fast as read)")
    parser.add_argument("--recorder", choices=("auto", "record", "direct"), default="auto",
                        help="record = groundstation record subprocess; direct = in-process reader")
    parser.add_argument("--tlog", type=Path, default=None, help="replay this .tlog instead")
    parser.add_argument("--source", choices=("auto", "sim", "synthetic"), default="auto",
                        help="where the flight comes from when --tlog is not given")
    parser.add_argument("--fc", action="store_true",
                        help="instead: the simulated FC (hil_replay.fc + hil_replay.sim) at max speed "
                             "into groundstation record; prints its real-time factor")


def _make_flight(tmp: Path, args: argparse.Namespace) -> tuple[Path, str]:
    if args.tlog is not None:
        return args.tlog, str(args.tlog)
    path = tmp / "flight.tlog"
    if args.source in ("auto", "sim"):
        rates = {"SERVO_OUTPUT_RAW": 50.0, "ATTITUDE": 50.0, "LOCAL_POSITION_NED": 50.0,
                 "GLOBAL_POSITION_INT": 50.0, "RAW_IMU": 50.0, "GPS_RAW_INT": 5.0,
                 "EXTENDED_SYS_STATE": 2.0, "SYS_STATUS": 2.0}
        write_tlog(path, seed=0, flights=1, effects=(), aircraft=None, rates_hz=rates)
        return path, "hil_replay.sim.write_tlog(seed=0, flights=1), 50 Hz full telemetry"
    sine_flight_tlog(path, args.duration)
    return path, f"synthetic {args.duration:.0f} s, 50 Hz full telemetry"


class _DirectRecorder:
    """In-process fallback: pyserial reader -> pymavlink framing -> TlogWriter."""

    def __init__(self, port_path: str, out: Path) -> None:
        self.out = out
        self._ser = serial.Serial(port_path, 921600, timeout=0.05)
        self._parser = mavlink.MAVLink(None)
        self._parser.robust_parsing = True
        self._writer = TlogWriter(out)
        self._stop = threading.Event()
        self._thread = threading.Thread(target=self._run, daemon=True)
        self._thread.start()

    def _run(self) -> None:
        while not self._stop.is_set():
            data = self._ser.read(65536)
            if data:
                now = time.time()
                for m in self._parser.parse_buffer(data) or []:
                    if m.get_type() != "BAD_DATA":
                        self._writer.write(bytes(m.get_msgbuf()), now)

    def finish(self) -> None:
        self._stop.set()
        self._thread.join(5)
        self._ser.close()
        self._writer.close()


class _RecordSubprocess:
    """``groundstation record --link serial://PORT --out DIR`` stopped with SIGINT."""

    def __init__(self, port_path: str, out_dir: Path) -> None:
        self.out_dir = out_dir
        self.proc = subprocess.Popen(
            [sys.executable, "-m", "groundstation.cli", "record", "--link", f"serial://{port_path}:921600",
             "--out", str(out_dir)], stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)

    def finish(self) -> str:
        time.sleep(0.3)  # let it write what it read
        self.proc.send_signal(signal.SIGINT)
        try:
            out, err = self.proc.communicate(timeout=20)
        except subprocess.TimeoutExpired:
            self.proc.kill()
            out, err = self.proc.communicate()
        return out + err

    def recorded(self) -> Path:
        logs = sorted(self.out_dir.rglob("*.tlog"), key=lambda p: p.stat().st_size)
        if not logs:
            raise OSError(f"{self.out_dir}: groundstation record wrote no .tlog")
        return logs[-1]  # the session file holds everything


def _one_run(flight: Path, tmp: Path, recorder: str, speed: float) -> tuple[float, int, int, float]:
    packets = read_tlog_packets(flight)
    out_dir = Path(tempfile.mkdtemp(dir=tmp, prefix="rec-"))
    with VirtualSerialPort(out_dir / "ttyFC") as port:
        rec: _RecordSubprocess | _DirectRecorder
        if recorder == "record":
            rec = _RecordSubprocess(port.path, out_dir / "out")
        else:
            rec = _DirectRecorder(port.path, out_dir / "direct.tlog")
        player = TlogPlayer(packets, port, speed=speed, reader_timeout_s=30.0)
        report = player.run()
        if isinstance(rec, _RecordSubprocess):
            rec.finish()
            recorded_path = rec.recorded()
        else:
            rec.finish()
            recorded_path = rec.out
    got = Counter(p.data for p in read_tlog_packets(recorded_path))
    want = Counter(p.data for p in packets)
    lost = sum((want - got).values())
    return report.real_time_factor, lost, len(packets), report.log_s


def _fc_run(flight_s: float) -> tuple[float, int, int]:
    """Simulated FC (one flight of ``flight_s``) at max speed into ``groundstation record``."""
    with tempfile.TemporaryDirectory(prefix="gs-bench-fc-") as d:
        fc = SimulatedFCThread(speed=0, seed=0, flights=1, config=FcConfig(packet_loss=0.0),
                               sim_options={"flight_duration_s": flight_s, "pause_s": 1.0})
        rec = _RecordSubprocess(fc.port_path, Path(d) / "out")
        try:
            if not fc.port.wait_for_reader(30.0):
                raise OSError(f"{fc.port_path}: groundstation record did not open the port")
            t0 = time.monotonic()
            fc.start()
            end_s = float(fc.fc.session.end_s)  # type: ignore[attr-defined]  # a SimulatedSession
            while fc.stats.last_t_boot_s < end_s - 0.05 and fc.is_alive():
                time.sleep(0.01)
            wall = time.monotonic() - t0
            fc_s = fc.stats.last_t_boot_s
        finally:
            fc.stop()
            rec.finish()
        sent = sum(fc.stats.sent_by_type.values())
        recorded = len(read_tlog_packets(rec.recorded()))
    return fc_s / wall, sent, recorded


def run(args: argparse.Namespace) -> int:
    if args.fc:
        rtfs = []
        for i in range(args.runs):
            f, sent, recorded = _fc_run(60.0)
            rtfs.append(f)
            print(f"run {i + 1}: simulated FC real-time factor {f:.1f}x; {sent} packets sent, "
                  f"{recorded} recorded", flush=True)
        print(f"median simulated-FC real-time factor: {statistics.median(rtfs):.1f}x "
              f"(one 60 s flight, all streams the ground station asks for, {os.cpu_count()} cpus)")
        return 0
    recorder = args.recorder
    if recorder == "auto":
        recorder = "record" if importlib.util.find_spec("groundstation.commands.record") else "direct"
    with tempfile.TemporaryDirectory(prefix="gs-bench-replay-") as d:
        tmp = Path(d)
        flight, desc = _make_flight(tmp, args)
        rtf, lost = [], []
        n = 0
        log_s = 0.0
        for i in range(args.runs):
            f, l_, n, log_s = _one_run(flight, tmp, recorder, args.speed)
            rtf.append(f)
            lost.append(l_)
            print(f"run {i + 1}: real-time factor {f:.1f}x, packets lost {l_}/{n}", flush=True)
    print(f"flight: {desc}; {n} packets, {log_s:.1f} s of log; recorder: {recorder}; "
          f"{os.cpu_count()} cpus")
    print(f"median real-time factor: {statistics.median(rtf):.1f}x (target >= 20x)")
    print(f"median packets lost: {statistics.median(lost):.0f} (target 0)")
    return 0
