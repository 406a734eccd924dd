"""The sans-IO log downloader against the simulated FC's own protocol logic, in memory, time passed in.

Bytes go both ways through the real pieces: the downloader's requests through
:class:`MavlinkSession` (the read-only allowlist) into :class:`hil_replay.fc.FcProtocol`, whose
LOG_ENTRY/LOG_DATA packets (with its seeded loss and bit flips) come back through the session's
framer, in one-byte chunks where a test says so. No event loop, no sleeps.
"""

from __future__ import annotations

import random
from dataclasses import dataclass

import pytest
from pymavlink.dialects.v20 import ardupilotmega as mavlink2

from firmware_interface.logdownload import (
    DownloadComplete,
    DownloadConfig,
    DownloadFailed,
    LogDownloader,
    LogEntry,
    LogListed,
    LogLister,
    LogRequestFailed,
)
from firmware_interface.samples import RawPacket
from firmware_interface.session import MavlinkSession, SessionConfig
from hil_replay.fc import FcConfig, FcProtocol

TICK_S = 0.02


@dataclass
class Tick:
    t_boot_s: float
    armed: bool = False
    flight_index: int | None = None
    available: tuple[str, ...] = ()

    def build(self, name, mav):
        raise KeyError(name)


class Harness:
    """Downloader/lister <-> session <-> FcProtocol, one 20 ms tick at a time."""

    def __init__(self, fc: FcProtocol, machine, *, byte_at_a_time: bool = False, armed: bool = False) -> None:
        self.fc = fc
        self.m = machine
        self.session = MavlinkSession(SessionConfig(request_streams=False, link_timeout_s=1e9))
        self.decoder = mavlink2.MAVLink(None, 255, 190)
        self.t = 100.0
        self.k = 0
        self.byte_at_a_time = byte_at_a_time
        self.armed = armed
        self.sent: list = []        # every message the ground station sent
        self.events: list = []
        self.fc_silent = False      # the FC's bytes are lost (unplugged, or it stopped answering)
        self.gs_silent = False      # the ground station's bytes are lost
        self.bad_crc = 0

    def step(self) -> None:
        self.k += 1
        self.t += TICK_S
        out = b"".join(self.fc.on_frame(Tick(self.k * TICK_S, self.armed)))
        if not self.fc_silent:
            chunks = [out[i:i + 1] for i in range(len(out))] if self.byte_at_a_time else [out]
            for c in chunks:
                self.session.receive_data(c, self.t)
        bad, self.bad_crc = self.session.stats.bad_crc - self.bad_crc, self.session.stats.bad_crc
        if bad and isinstance(self.m, LogDownloader):
            self.m.link_noise(bad, self.t)  # as the drivers do: the framer's failed CRCs
        for ev in self.session.events():
            if isinstance(ev, RawPacket) and ev.msg_type in ("LOG_ENTRY", "LOG_DATA"):
                self.m.receive_message(self.decoder.decode(bytearray(ev.data)), self.t)
        self.m.fc_armed(self.armed, self.t)
        self.m.handle_timer(self.t)
        for msg in self.m.messages_to_send():
            self.sent.append(msg)
            self.session.send_message(msg)
        data = self.session.data_to_send(self.t)
        if data and not self.gs_silent:
            self.fc.receive_data(data)
        self.events += self.m.events()

    def run(self, until, max_s: float = 120.0) -> None:
        for _ in range(int(max_s / TICK_S)):
            if until(self):
                return
            self.step()
        raise AssertionError(f"not done after {max_s} s of FC time; events {self.events[-3:]}")

    def done(self) -> bool:
        return any(isinstance(e, (DownloadComplete, DownloadFailed, LogListed, LogRequestFailed))
                   for e in self.events)

    def kinds(self) -> list[str]:
        return [m.get_type() for m in self.sent]


def _fc(data: bytes, **kw) -> FcProtocol:
    fc = FcProtocol(FcConfig(packet_loss=kw.pop("packet_loss", 0.0), seed=kw.pop("seed", 1),
                             log_bytes_per_s=kw.pop("log_bytes_per_s", 50_000.0), **kw))
    fc.add_log(data)
    return fc


def _blob(n: int, seed: int = 0) -> bytes:
    return random.Random(seed).randbytes(n)


def _entry(data: bytes) -> LogEntry:
    return LogEntry(1, len(data), 0, 1)


def _start(h: Harness) -> None:
    h.m.fc_armed(h.armed, h.t)
    h.m.start(h.t)
    for msg in h.m.messages_to_send():
        h.sent.append(msg)
        h.session.send_message(msg)
    h.fc.receive_data(h.session.data_to_send(h.t))


def test_list_then_download_byte_at_a_time_is_byte_identical():
    data = _blob(20_000)
    fc = _fc(data)
    fc.add_log(_blob(333, 1))
    lister = LogLister((1, 1))
    h = Harness(fc, lister, byte_at_a_time=True)
    _start(h)
    h.run(Harness.done)
    (listed,) = h.events
    assert [(e.log_id, e.size_bytes) for e in listed.entries] == [(1, 20_000), (2, 333)]
    dl = LogDownloader(listed.entries[0], (1, 1))
    h2 = Harness(fc, dl, byte_at_a_time=True)
    _start(h2)
    h2.run(Harness.done)
    assert isinstance(h2.events[-1], DownloadComplete) and h2.events[-1].data == data
    assert h2.kinds().count("LOG_REQUEST_END") == 1 and h2.kinds()[-1] == "LOG_REQUEST_END"
    assert set(h2.kinds()) <= {"LOG_REQUEST_DATA", "LOG_REQUEST_END"}


def test_corrupted_and_lost_packets_are_refetched_within_the_request_bounds():
    data = _blob(60_000, 2)
    cfg = DownloadConfig(max_in_flight=4, max_requests_per_s=50.0)
    fc = _fc(data, corrupt_rate=0.01, packet_loss=0.02, seed=3)
    dl = LogDownloader(_entry(data), (1, 1), cfg)
    h = Harness(fc, dl)
    issued: list[tuple[float, int, int]] = []
    orig = dl._request

    def spy(ofs, count, now):
        issued.append((now, ofs, count))
        orig(ofs, count, now)

    dl._request = spy
    _start(h)
    h.run(Harness.done)
    done = h.events[-1]
    assert isinstance(done, DownloadComplete) and done.data == data
    assert fc.stats.packets_corrupted > 50 and dl.requests > 5  # the faults really happened
    # never more gap requests per second than allowed (a burst of max_in_flight at most)
    times = sorted(t for t, _, count in issued)
    for i, t0 in enumerate(times):
        n_in_1s = sum(1 for t in times[i:] if t < t0 + 1.0)
        assert n_in_1s <= cfg.max_in_flight + cfg.max_requests_per_s
    assert h.kinds().count("LOG_REQUEST_END") == 1


def test_an_armed_fc_refuses_and_the_reason_is_one_line():
    data = _blob(5_000)
    fc = _fc(data)
    dl = LogDownloader(_entry(data), (1, 1))
    h = Harness(fc, dl, armed=True)
    fc.on_frame(Tick(0.0, True))  # the FC knows it is armed
    _start(h)
    h.run(Harness.done)
    (failed,) = [e for e in h.events if isinstance(e, DownloadFailed)]
    assert "armed" in failed.reason and "\n" not in failed.reason
    assert h.kinds() == ["LOG_REQUEST_END"]  # nothing asked of an armed FC but the end


def test_armed_lister_says_so():
    fc = _fc(_blob(100))
    h = Harness(fc, LogLister((1, 1)), armed=True)
    fc.on_frame(Tick(0.0, True))
    _start(h)
    h.run(Harness.done)
    assert isinstance(h.events[-1], LogRequestFailed) and "armed" in h.events[-1].reason
    assert fc.stats.log_data_sent == 0 and fc.stats.log_requests >= 1


def test_fc_that_stops_answering_names_the_log_keeps_the_data_and_resumes():
    data = _blob(40_000, 4)
    fc = _fc(data)
    dl = LogDownloader(_entry(data), (1, 1), DownloadConfig(give_up_s=2.0))
    h = Harness(fc, dl)
    _start(h)
    h.run(lambda h: dl.received_blocks > 150)
    h.fc_silent = True   # the FC goes quiet (link up as far as we can tell)
    h.run(Harness.done)
    failed = h.events[-1]
    assert isinstance(failed, DownloadFailed)
    assert failed.reason.startswith("log 1:") and "stopped answering" in failed.reason
    assert failed.received_bytes >= 150 * 90 and h.kinds()[-1] == "LOG_REQUEST_END"
    for k in range(dl.n_blocks):  # every block marked received holds the FC's bytes
        if dl.have[k]:
            assert dl.data[k * 90:(k + 1) * 90] == data[k * 90:(k + 1) * 90]
    # resume: a new downloader from the kept data asks only from the first missing block on
    fc2 = _fc(data)
    dl2 = LogDownloader(_entry(data), (1, 1), data=bytes(dl.data), have=bytes(dl.have))
    h2 = Harness(fc2, dl2)
    _start(h2)
    h2.run(Harness.done)
    assert isinstance(h2.events[-1], DownloadComplete) and h2.events[-1].data == data
    first = h2.sent[0]
    assert first.get_type() == "LOG_REQUEST_DATA" and first.ofs == dl.have.find(0) * 90 > 0


def test_lost_link_pauses_and_restored_link_resumes_without_refetching():
    data = _blob(50_000, 5)
    fc = _fc(data)
    dl = LogDownloader(_entry(data), (1, 1))
    h = Harness(fc, dl)
    _start(h)
    h.run(lambda h: dl.received_blocks > 200)
    got = dl.received_blocks
    h.fc_silent = h.gs_silent = True
    dl.link_lost(h.t)
    for _ in range(100):  # 2 s unplugged: nothing is asked meanwhile
        h.step()
    assert dl.state == "paused" and dl.received_blocks == got
    n_sent = len(h.sent)
    h.fc_silent = h.gs_silent = False
    dl.link_restored(h.t)
    h.run(Harness.done)
    assert isinstance(h.events[-1], DownloadComplete) and h.events[-1].data == data
    resumed = h.sent[n_sent]
    assert resumed.get_type() == "LOG_REQUEST_DATA" and resumed.ofs >= got * 90 - 90 * 60
    assert dl.duplicate_blocks < 100


@pytest.mark.parametrize("size", [1, 89, 90, 91, 180, 9000])
def test_odd_sizes(size):
    data = _blob(size, size)
    fc = _fc(data)
    dl = LogDownloader(_entry(data), (1, 1))
    h = Harness(fc, dl)
    _start(h)
    h.run(Harness.done)
    assert isinstance(h.events[-1], DownloadComplete) and h.events[-1].data == data


def test_a_block_whose_corruption_the_crc_misses_is_not_delivered():
    """Line noise that flips four bits in the pattern of the CRC-16's own polynomial gives a frame that
    checks with a wrong block (the FC's ``crc_blind_rate``); 1 % byte noise beside it is what such an
    error comes with on a real line. The log must still arrive byte-exact."""
    data = _blob(30_000, 6)
    fc = _fc(data, corrupt_rate=0.002, crc_blind_rate=0.05, seed=7)
    dl = LogDownloader(_entry(data), (1, 1))
    h = Harness(fc, dl)
    _start(h)
    h.run(Harness.done)
    done = h.events[-1]
    assert fc.stats.packets_crc_blind > 5 and fc.stats.packets_corrupted > 5  # the faults really happened
    assert isinstance(done, DownloadComplete)
    assert done.data == data
    assert done.check.verified and dict(done.check.reread_blocks)["disagreed"] > 0, done.check
    assert done.check.corrupted_frames == h.session.stats.bad_crc > 0


def _serve_wrong_block(fc: FcProtocol, ofs: int, flip_at: int, times: int) -> list[int]:
    """The FC's first ``times`` LOG_DATA for ``ofs`` carry a wrong byte at ``flip_at`` in a valid frame
    (pymavlink packs it and computes the CRC over the wrong payload); returns a count of them."""
    encode = fc.mav.log_data_encode
    served = [0]

    def wrong(lid, o, count, data):
        if o == ofs and served[0] < times:
            served[0] += 1
            data = bytearray(data)
            data[flip_at] ^= served[0]
        return encode(lid, o, count, bytes(data))

    fc.mav.log_data_encode = wrong
    return served


def test_a_wrong_block_that_breaks_the_dataflash_records_is_read_again_on_a_clean_link(df_log):
    ofs = 11 * 90
    assert df_log[ofs + 30:ofs + 32] == b"\xa3\x95"  # a record header: the wrong block breaks the chain
    fc = _fc(df_log)
    served = _serve_wrong_block(fc, ofs, 30, times=1)
    dl = LogDownloader(_entry(df_log), (1, 1))
    h = Harness(fc, dl)
    _start(h)
    h.run(Harness.done)
    done = h.events[-1]
    assert served == [1] and h.session.stats.bad_crc == 0
    assert isinstance(done, DownloadComplete) and done.data == df_log
    check = done.check
    assert check.verified and dict(check.reread_blocks)["structure"] >= 1 and check.corrupted_frames == 0
    assert check.structure == "dataflash records parse end to end" and "CRC-16" in check.how


def test_copies_that_disagree_are_read_again_and_the_value_seen_twice_is_kept(df_log):
    fc = _fc(df_log)
    served = _serve_wrong_block(fc, 90 * 50, 45, times=2)  # two wrong copies, each wrong differently
    dl = LogDownloader(_entry(df_log), (1, 1), DownloadConfig(confirm="always"))
    h = Harness(fc, dl)
    _start(h)
    h.run(Harness.done)
    done = h.events[-1]
    assert served == [2] and isinstance(done, DownloadComplete) and done.data == df_log
    assert done.check.verified and dict(done.check.reread_blocks) == {"confirm": dl.n_blocks, "disagreed": 1,
                                                                      "structure": 0}
    assert done.check.confirmed_blocks == dl.n_blocks and "read twice" in done.check.how


def test_a_block_whose_copies_never_agree_is_kept_and_the_log_said_unverified(df_log):
    fc = _fc(df_log)
    _serve_wrong_block(fc, 90 * 50, 45, times=10**6)
    cfg = DownloadConfig(confirm="always", max_copies=4)
    dl = LogDownloader(_entry(df_log), (1, 1), cfg)
    h = Harness(fc, dl)
    _start(h)
    h.run(Harness.done)
    done = h.events[-1]
    assert isinstance(done, DownloadComplete) and not done.check.verified
    assert done.check.unresolved_offsets == (4500,)
    assert done.data[:4500] == df_log[:4500] and done.data[4590:] == df_log[4590:]
    line = done.check.summary()
    assert line.startswith("NOT verified") and "4500" in line and "\n" not in line


def test_single_copies_from_a_noisy_link_are_kept_to_confirm_and_confirmed_on_resume():
    data = _blob(30_000, 8)
    fc = _fc(data, corrupt_rate=0.003, seed=9)
    dl = LogDownloader(_entry(data), (1, 1), DownloadConfig(give_up_s=2.0))
    h = Harness(fc, dl)
    _start(h)
    h.run(lambda h: dl.received_blocks > 150)
    h.fc_silent = True
    h.run(Harness.done)
    assert isinstance(h.events[-1], DownloadFailed) and dl.noisy
    kept, have = dl.partial()
    assert set(have) <= {0, 2, 3} and have.count(3) > 100  # nothing kept as a trusted single copy
    fc2 = _fc(data)  # a clean link now: the kept blocks still get their second copy
    dl2 = LogDownloader(_entry(data), (1, 1), data=kept, have=have)
    h2 = Harness(fc2, dl2)
    _start(h2)
    h2.run(Harness.done)
    done = h2.events[-1]
    assert isinstance(done, DownloadComplete) and done.data == data and not dl2.noisy
    assert dict(done.check.reread_blocks)["confirm"] == 0 and done.check.confirmed_blocks >= have.count(3)


def test_a_valid_frame_no_fc_sends_counts_as_corruption_the_crc_missed():
    data = _blob(9_000, 10)
    dl = LogDownloader(_entry(data), (1, 1))
    dl.start(0.0)
    mav = mavlink2.MAVLink(None, 1, 1)
    dl.receive_message(mav.log_data_encode(1, 45, 90, data[45:135]), 0.1)  # not on a block boundary
    assert dl.noisy and dl.corrupted_frames == 1 and dl.received_blocks == 0
