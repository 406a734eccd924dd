"""Large onboard logs for the log benchmarks: dataflash (.bin) and ULog (.ulg).

* :func:`write_dataflash`: a dataflash log of a given size with the records an ArduPilot helicopter
  logs at 400 Hz (IMU, ATT, RATE, RCOU, HELI) and 10 Hz (XKF1), built with numpy (fast: for reading
  speed, no flight physics);
* :func:`write_ulog`: the pyulog sample log's topics repeated end to end, timestamps moved on,
  written by pyulog itself;
* :func:`simulated_dataflash`: the simulated FC's own dataflash writer on simulated flights (what
  the FC serves for download).
"""

from __future__ import annotations

import lzma
from pathlib import Path

import numpy as np
from pyulog import ULog

from hil_replay.dataflash import _FORMATS, _PACK, DataflashWriter, _fmt_record, chirp_plan, rotor_rpm
from hil_replay.sim import SimulatedSession


def write_dataflash(path: Path, size_bytes: int, seed: int = 0) -> int:
    """A dataflash log of about ``size_bytes`` (400 Hz IMU/ATT/RATE/RCOU/HELI, 10 Hz XKF1)."""
    ids = {name: typ for typ, name, _, _ in _FORMATS}
    names = ("IMU", "ATT", "RATE", "RCOU", "HELI")
    parts = []
    for nm in names:
        parts.append((f"h_{nm}", "S3"))
        parts.append((f"b_{nm}", f"S{_PACK[nm].size}"))
    tick = np.dtype(parts)
    per_tick = tick.itemsize
    xkf = _PACK["XKF1"]
    n = int(size_bytes / (per_tick + (3 + xkf.size) / 40))
    rng = np.random.default_rng(seed)
    t_us = (1_000_000 + np.arange(n) * 2500).astype(np.uint64)
    ts = t_us * 1e-6
    w = 2 * np.pi * 25.0
    gyro = 0.05 * np.sin(np.outer(ts, [0.7, 1.1, 0.4])) + 0.01 * np.sin(w * ts)[:, None] \
        + 0.002 * rng.standard_normal((n, 3))
    arr = np.zeros(n, dtype=tick)

    def body(dtype_fields: list[tuple[str, str]], cols: list[np.ndarray]) -> np.ndarray:
        d = np.dtype(dtype_fields)
        a = np.zeros(n, dtype=d)
        for (name, _), c in zip(dtype_fields, cols, strict=True):
            a[name] = c
        return a.view(f"S{d.itemsize}")

    f = "<f4"
    for nm in names:
        arr[f"h_{nm}"] = b"\xa3\x95" + bytes([ids[nm]])
    arr["b_IMU"] = body([("t", "<u8"), ("i", "u1")] + [(f"g{k}", f) for k in range(6)],
                        [t_us, np.zeros(n), gyro[:, 0], gyro[:, 1], gyro[:, 2], np.zeros(n), np.zeros(n),
                         np.full(n, -9.8)])
    deg = np.degrees(np.cumsum(gyro, axis=0) * 0.0025)
    arr["b_ATT"] = body([("t", "<u8")] + [(f"a{k}", f) for k in range(6)],
                        [t_us, np.zeros(n), deg[:, 0], np.zeros(n), deg[:, 1], np.zeros(n), deg[:, 2] % 360])
    rate = np.degrees(gyro)
    arr["b_RATE"] = body([("t", "<u8")] + [(f"r{k}", f) for k in range(9)],
                         [t_us, np.zeros(n), rate[:, 0], np.zeros(n), np.zeros(n), rate[:, 1], np.zeros(n),
                          np.zeros(n), rate[:, 2], np.zeros(n)])
    pwm = (1500 + 200 * np.sin(np.outer(ts, [0.5, 0.8, 0.3, 1.2]))).astype(np.uint16)
    arr["b_RCOU"] = body([("t", "<u8")] + [(f"c{k}", "<u2") for k in range(8)],
                         [t_us, *pwm.T, np.zeros(n), np.zeros(n), np.zeros(n), np.full(n, 1850)])
    arr["b_HELI"] = body([("t", "<u8")] + [(f"h{k}", f) for k in range(4)],
                         [t_us, np.full(n, 1500.0), 1500 + rng.standard_normal(n), np.ones(n), np.ones(n)])
    head = b"".join(_fmt_record(*fm) for fm in _FORMATS)
    blocks = arr.view(np.uint8).reshape(n, per_tick)
    with path.open("wb") as fh:
        fh.write(head)
        step = 40  # one XKF1 per 40 ticks (10 Hz)
        for k0 in range(0, n, 40_000):
            k1 = min(n, k0 + 40_000)
            out = bytearray()
            for a in range(k0, k1, step):
                b = min(k1, a + step)
                out += blocks[a:b].tobytes()
                out += b"\xa3\x95" + bytes([ids["XKF1"]]) + xkf.pack(int(t_us[a]), 0, 0.1, 0.2, 0.0, 1.0, 2.0, -3.0)
            fh.write(out)
    return path.stat().st_size


def write_ulog(path: Path, size_bytes: int) -> int:
    """The pyulog sample's topics repeated (timestamps moved on) until about ``size_bytes``."""
    src = Path(__file__).resolve().parents[1] / "tests" / "data" / "px4" / "pyulog_sample.ulg.xz"
    if not src.is_file():
        raise FileNotFoundError(f"{src}: the sample ULog is missing from the checkout")
    sample = path.with_name("sample.ulg")
    sample.write_bytes(lzma.decompress(src.read_bytes()))
    ulog = ULog(str(sample))
    k = max(1, int(round(size_bytes / sample.stat().st_size)))
    span = int(ulog.last_timestamp - ulog.start_timestamp) + 1000
    for d in ulog.data_list:
        for key, v in list(d.data.items()):
            if key == "timestamp":
                d.data[key] = np.concatenate([v + np.uint64(span * i) for i in range(k)])
            else:
                d.data[key] = np.tile(v, k)
    ulog._last_timestamp = ulog.last_timestamp + span * (k - 1)
    ulog.write_ulog(str(path))
    sample.unlink()
    return path.stat().st_size


def simulated_dataflash(size_bytes: int, seed: int) -> bytes:
    """A dataflash log of about ``size_bytes`` from the simulated FC's own writer (200 Hz records of
    simulated flights), as the FC would serve it for download."""
    sess = SimulatedSession(seed=seed, flights=max(1, int(size_bytes // 6_000_000) + 1))
    w = DataflashWriter(rotor_rpm(sess), chirp_plan(sess))
    for frame in sess.frames(fast_gyro=True):
        w.add(frame)
        if len(w) >= size_bytes:
            break
    return w.getvalue()
