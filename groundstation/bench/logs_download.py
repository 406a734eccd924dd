"""``groundstation bench logs-download``: onboard log download from the simulated FC through a pty.

Two runs, each a fresh simulated FC (serving disarmed, at the FC's 250 kB/s USB-like LOG_DATA
throughput) on a virtual serial port opened at 921600 baud settings, serving a dataflash log its own
writer produced from the simulator (200 Hz records):

1. clean link: the throughput (kB/s of log bytes over the download's wall time), and the time the
   last 5 % of the file took against its 5 % share (target: at most 2x; of the last pass when the
   download read every block a second time);
2. faults: ``--corrupt`` of the bytes flipped on the FC's side, ``--crc-blind`` of the LOG_DATA
   packets with an error their CRC-16 misses (a wrong block in a valid frame), and one cable pull
   half way: byte-identical or not, time, requests, and the download's own check (verified, blocks
   read again and why).

Prints a table and one JSON line. Wall times are noisy on a loaded machine: quote the median of a few
``--repeat`` runs.
"""

from __future__ import annotations

import argparse
import asyncio
import json
import statistics
import threading
import time
from typing import Any

from rich.console import Console
from rich.table import Table

from benchkit.onboard_logs import simulated_dataflash
from firmware_interface.logdownload import DownloadConfig
from firmware_interface.logtransfer import LogTransfer
from firmware_interface.transports import open_link
from hil_replay.fc import FcConfig, SimulatedFCThread

HELP = "download the simulated FC's onboard log through a pty: kB/s, last-5 % time, faults (byte-identical)"


def add_arguments(p: argparse.ArgumentParser) -> None:
    p.add_argument("--size-mb", type=float, default=3.0, help="log size for the throughput runs (MB)")
    p.add_argument("--fault-size-kb", type=float, default=400.0, help="log size for the fault run (kB)")
    p.add_argument("--corrupt", type=float, default=0.01, help="bit-flip probability per byte sent (fault run)")
    p.add_argument("--crc-blind", type=float, default=0.005,
                   help="share of LOG_DATA packets with an error their CRC misses (fault run)")
    p.add_argument("--repeat", type=int, default=3, help="throughput runs (median quoted)")
    p.add_argument("--seed", type=int, default=0)


class _Idle:
    def frames(self) -> Any:
        return iter(())


def download(data: bytes, *, corrupt: float = 0.0, unplug: bool = False, seed: int = 0,
             crc_blind: float = 0.0) -> dict[str, Any]:
    """One download through a pty; progress samples (wall s, bytes) and the outcome."""
    fc = SimulatedFCThread(session=_Idle(), config=FcConfig(packet_loss=0.0, corrupt_rate=corrupt, seed=seed,
                                                            crc_blind_rate=crc_blind))
    fc.fc.protocol.add_log(data)
    samples: list[tuple[float, int]] = []
    pulled = threading.Event()

    async def main() -> tuple[bytes, int, Any]:
        url = f"serial://{fc.port_path}:921600"
        async with LogTransfer(lambda: open_link(url), config=DownloadConfig(link_lost_give_up_s=30.0)) as tr:
            (entry,) = await tr.list_logs()

            def progress(received: int, size: int) -> None:
                samples.append((time.perf_counter(), received))
                if unplug and received > size // 2 and not pulled.is_set():
                    pulled.set()
                    fc.unplug(1.0)

            samples.append((time.perf_counter(), 0))
            got = await tr.download(entry, on_progress=progress)
            return got, entry.size_bytes, tr.check

    with fc:
        got, size, check = asyncio.run(main())
        stats = fc.stats
    t0, t1 = samples[0][0], samples[-1][0]
    # the last pass (a second one reads every block again when the link corrupted frames)
    last = max((k for k in range(1, len(samples)) if samples[k][1] < samples[k - 1][1]), default=0)
    t_pass = samples[last][0] if last else t0
    t95 = next(t for t, b in samples[last:] if b >= 0.95 * size)
    reread = dict(check.reread_blocks) if check is not None else {}
    return {"bytes": size, "seconds": t1 - t0, "kB_per_s": size / 1000 / (t1 - t0),
            "last5_ratio": (t1 - t95) / (0.05 * (t1 - t_pass)), "passes": 2 if last else 1, "identical": got == data,
            "log_data_sent": stats.log_data_sent, "requests": stats.log_requests,
            "corrupted_packets": stats.packets_corrupted, "crc_blind_packets": stats.packets_crc_blind,
            "unplugged": pulled.is_set(), "verified": bool(check and check.verified), "reread_blocks": reread}


def run(args: argparse.Namespace) -> int:
    con = Console()
    data = simulated_dataflash(int(args.size_mb * 1e6), args.seed)
    runs = [download(data, seed=args.seed + k) for k in range(max(1, args.repeat))]
    small = simulated_dataflash(int(args.fault_size_kb * 1e3), args.seed + 1)
    fault = download(small, corrupt=args.corrupt, unplug=True, seed=args.seed, crc_blind=args.crc_blind)
    t = Table(title=f"log download through a pty (921600 baud settings), {len(data) / 1e6:.2f} MB dataflash")
    for c in ("run", "kB/s", "seconds", "last 5 % / share", "identical", "LOG_DATA sent", "requests"):
        t.add_column(c, justify="right")
    for k, r in enumerate(runs):
        t.add_row(f"clean {k + 1}", f"{r['kB_per_s']:.0f}", f"{r['seconds']:.2f}", f"{r['last5_ratio']:.2f}",
                  str(r["identical"]), str(r["log_data_sent"]), str(r["requests"]))
    t.add_row(f"{args.corrupt:.0%} corrupt, {args.crc_blind:.1%} CRC-blind + unplug ({len(small) / 1e3:.0f} kB)",
              f"{fault['kB_per_s']:.0f}",
              f"{fault['seconds']:.2f}", f"{fault['last5_ratio']:.2f}", str(fault["identical"]),
              str(fault["log_data_sent"]), str(fault["requests"]))
    con.print(t)
    med = statistics.median(r["kB_per_s"] for r in runs)
    last5 = statistics.median(r["last5_ratio"] for r in runs)
    con.print(f"median {med:.0f} kB/s (target >= 100), last 5 % took {last5:.2f}x its share (target <= 2); "
              f"faults: byte-identical {fault['identical']} with {fault['corrupted_packets']} corrupted packets "
              f"and {'one unplug' if fault['unplugged'] else 'no unplug'}, {fault['crc_blind_packets']} CRC-blind; "
              f"verified {fault['verified']}, blocks read again {fault['reread_blocks']}")
    print(json.dumps({"kB_per_s_median": round(med, 1), "last5_ratio_median": round(last5, 3),
                      "clean_identical": all(r["identical"] for r in runs), "fault": fault}))
    return 0 if all(r["identical"] for r in runs) and fault["identical"] else 1
