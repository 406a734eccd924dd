"""TlogPlayer: timing, fault injection and its report, through a real pty read with pyserial."""

from __future__ import annotations

import numpy as np
import pytest
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

from hil_replay.player import TlogPlayer, read_tlog_packets
from hil_replay.pty import VirtualSerialPort
from tests.replay.conftest import RawReconnectingReader, make_tlog


def _play(tlog, tmp_path, **kw):
    with VirtualSerialPort(tmp_path / "ttyFC") as port:
        reader = RawReconnectingReader(port.path)
        try:
            player = TlogPlayer(tlog, port, reader_timeout_s=10, **kw)
            report = player.run()
        finally:
            reader.close()
    return player, report, reader


def test_reads_back_what_was_written(tmp_path):
    packets = make_tlog(tmp_path / "a.tlog", duration_s=1.0)
    got = read_tlog_packets(tmp_path / "a.tlog")
    assert [p.data for p in got] == packets
    assert all(b.t_us >= a.t_us for a, b in zip(got, got[1:], strict=False))


def test_speed_10x_keeps_order_and_spacing(tmp_path):
    packets = make_tlog(tmp_path / "a.tlog", duration_s=2.0)
    player, report, reader = _play(tmp_path / "a.tlog", tmp_path, speed=10.0)
    assert reader.data == b"".join(packets)                  # every byte, in order
    assert report.intact == list(range(len(packets))) and report.finished and report.undrained == 0
    # a 2 s log at 10x cannot finish in less than ~0.2 s, and arrives spread over that time
    assert report.wall_s >= 0.9 * player.replay_s[-1] / 10
    t = np.array([tc for tc, _ in reader.chunks])
    assert t[-1] - t[0] >= 0.8 * player.replay_s[-1] / 10
    assert report.log_s == pytest.approx(player.replay_s[-1])


def test_corruption_rate_and_report(tmp_path):
    packets = make_tlog(tmp_path / "a.tlog", duration_s=20.0)
    _, report, reader = _play(tmp_path / "a.tlog", tmp_path, speed=0, corrupt_rate=0.01, seed=7)
    total = sum(len(p) for p in packets)
    assert report.bytes_sent == total == len(reader.data)
    # rate: binomial count of corrupted bytes within 4 sigma of 1 %
    sigma = np.sqrt(total * 0.01 * 0.99)
    assert abs(report.corrupt_bytes - 0.01 * total) < 4 * sigma
    # report: intact packets are byte-exact, corrupted ones differ in exactly the flipped bits
    received = np.frombuffer(reader.data, np.uint8)
    source = np.frombuffer(b"".join(packets), np.uint8)
    assert int(np.unpackbits(received ^ source).sum()) == report.corrupt_bytes
    offsets = np.cumsum([0] + [len(p) for p in packets])
    for i in report.intact:
        assert reader.data[offsets[i]:offsets[i + 1]] == packets[i]
    for i in report.corrupted:
        assert reader.data[offsets[i]:offsets[i + 1]] != packets[i]
    assert sorted(report.intact + report.corrupted) == list(range(len(packets)))


def test_same_seed_same_faults_different_seed_different(tmp_path):
    make_tlog(tmp_path / "a.tlog", duration_s=5.0)
    r1 = _play(tmp_path / "a.tlog", tmp_path, speed=0, corrupt_rate=0.005, drop_rate=0.05, seed=1)[1]
    r2 = _play(tmp_path / "a.tlog", tmp_path, speed=0, corrupt_rate=0.005, drop_rate=0.05, seed=1)[1]
    r3 = _play(tmp_path / "a.tlog", tmp_path, speed=0, corrupt_rate=0.005, drop_rate=0.05, seed=2)[1]
    assert (r1.corrupted, r1.dropped) == (r2.corrupted, r2.dropped)
    assert (r1.corrupted, r1.dropped) != (r3.corrupted, r3.dropped)


def test_drop_rate(tmp_path):
    packets = make_tlog(tmp_path / "a.tlog", duration_s=20.0)
    _, report, reader = _play(tmp_path / "a.tlog", tmp_path, speed=0, drop_rate=0.1, seed=3)
    n = len(packets)
    assert abs(len(report.dropped) - 0.1 * n) < 4 * np.sqrt(n * 0.09)
    assert reader.data == b"".join(packets[i] for i in report.intact)
    assert sorted(report.intact + report.dropped) == list(range(n))


def test_unplug_gap_and_replug_at_same_path(tmp_path):
    packets = make_tlog(tmp_path / "a.tlog", duration_s=4.0)
    player, report, reader = _play(tmp_path / "a.tlog", tmp_path, speed=4.0,
                                   unplug_at_s=1.0, unplug_for_s=1.2)
    in_gap = [i for i, t in enumerate(player.replay_s) if 1.0 <= t < 2.2]
    assert report.unplugged == in_gap and len(in_gap) > 50
    assert report.intact == [i for i in range(len(packets)) if i not in set(in_gap)]
    assert reader.connections == 2                      # the reader had to reopen the same path
    assert reader.data == b"".join(packets[i] for i in report.intact)
    assert report.unplugs_s == [(1.0, 2.2)] and report.undrained == 0


def test_bad_files(tmp_path):
    empty = tmp_path / "empty.tlog"
    empty.write_bytes(b"")
    with pytest.raises(ValueError, match="empty.tlog: empty"):
        read_tlog_packets(empty)
    text = tmp_path / "notes.tlog"
    text.write_text("this is not a telemetry log\n" * 20)
    with pytest.raises(ValueError, match="notes.tlog: no MAVLink packets"):
        read_tlog_packets(text)
    with pytest.raises(FileNotFoundError):
        read_tlog_packets(tmp_path / "missing.tlog")


def test_tolerates_garbage_and_truncation(tmp_path):
    packets = make_tlog(tmp_path / "a.tlog", duration_s=1.0)
    blob = (tmp_path / "a.tlog").read_bytes()
    rec = 8 + len(packets[0])
    damaged = blob[:rec] + b"\xfd\x09garbage\xfe" + blob[rec:-5]   # junk between records, cut end
    (tmp_path / "b.tlog").write_bytes(damaged)
    got = [p.data for p in read_tlog_packets(tmp_path / "b.tlog")]
    assert got == packets[:-1]


def test_replay_clock_clamps_backward_steps_and_long_gaps(tmp_path):
    from hil_replay.player import TlogPacket

    base = 1_700_000_000_000_000
    pk = [TlogPacket(base + dt, b"\xfd") for dt in (0, 100_000, 50_000, 3_600_000_000, 3_600_200_000)]
    with VirtualSerialPort(tmp_path / "tty") as port:
        assert TlogPlayer(pk, port).replay_s.tolist() == pytest.approx([0, 0.1, 0.1, 3600.05, 3600.25])
        assert TlogPlayer(pk, port, max_gap_s=2.0).replay_s.tolist() == pytest.approx([0, 0.1, 0.1, 2.1, 2.3])
        with pytest.raises(ValueError, match="max_gap_s"):
            TlogPlayer(pk, port, max_gap_s=0)


@settings(derandomize=True, max_examples=40, deadline=None,
          suppress_health_check=[HealthCheck.function_scoped_fixture])
@given(garbage=st.lists(st.tuples(st.integers(0, 200), st.binary(min_size=1, max_size=40)), max_size=8),
       cut=st.integers(0, 30))
def test_splitter_recovers_every_record_around_garbage(tmp_path, garbage, cut):
    """Garbage anywhere between records (including bytes that look like MAVLink) and a cut end:
    every whole record is recovered, in order."""
    path = tmp_path / "g.tlog"
    if not path.exists():
        make_tlog(path, duration_s=1.0)
    blob = path.read_bytes()
    records = []
    i = 0
    while i < len(blob):
        n = 8 + (12 + blob[i + 9] if blob[i + 8] == 0xFD else 8 + blob[i + 9])
        records.append(blob[i:i + n])
        i += n
    inserts = {k % len(records): g for k, g in garbage}
    out = b"".join(inserts.get(k, b"") + r for k, r in enumerate(records))
    last_whole = len(records)
    if cut:
        out = out[:-cut]
        last_whole -= 1
    (tmp_path / "damaged.tlog").write_bytes(out)
    got = [p.data for p in read_tlog_packets(tmp_path / "damaged.tlog")]
    assert got == [r[8:] for r in records[:last_whole]]


def test_fake_header_near_the_end_does_not_hide_the_last_record(tmp_path):
    packets = make_tlog(tmp_path / "a.tlog", duration_s=0.2)
    blob = (tmp_path / "a.tlog").read_bytes()
    last = 8 + len(packets[-1])
    # junk whose 9th byte is a MAVLink 2 magic announcing a 255-byte payload that runs past EOF
    junk = b"\x00" * 8 + b"\xfd\xff\x00"
    (tmp_path / "b.tlog").write_bytes(blob[:-last] + junk + blob[-last:])
    assert [p.data for p in read_tlog_packets(tmp_path / "b.tlog")] == packets


def test_unknown_message_ids_only_accepted_in_step(tmp_path):
    """Out of step (after garbage) a well-formed record of an unknown message id is not trusted
    (its CRC cannot be checked) and must not swallow the real record behind it."""
    packets = make_tlog(tmp_path / "a.tlog", duration_s=0.2)
    blob = (tmp_path / "a.tlog").read_bytes()
    first = 8 + len(packets[0])
    ts = blob[:8]
    unknown = bytes([0xFD, 40, 0, 0, 7, 1, 1, 0xEF, 0xCD, 0xAB]) + bytes(40) + b"\x12\x34"
    # in step (right after a record): kept; out of step (after one junk byte): skipped
    in_step = blob[:first] + ts + unknown + blob[first:]
    (tmp_path / "b.tlog").write_bytes(in_step)
    assert [p.data for p in read_tlog_packets(tmp_path / "b.tlog")] == packets[:1] + [unknown] + packets[1:]
    out_of_step = blob[:first] + b"\x07" + ts + unknown[:20] + blob[first:]
    (tmp_path / "c.tlog").write_bytes(out_of_step)
    assert [p.data for p in read_tlog_packets(tmp_path / "c.tlog")] == packets


def test_mavlink1_and_signed_mavlink2_records(tmp_path):
    from pymavlink.dialects.v10 import ardupilotmega as mav1
    from pymavlink.dialects.v20 import ardupilotmega as mav2

    from firmware_interface.tlog import TlogWriter

    m1 = mav1.MAVLink(None, srcSystem=1, srcComponent=1)
    m2 = mav2.MAVLink(None, srcSystem=1, srcComponent=1)
    m2.signing.secret_key = bytes(range(32))
    m2.signing.sign_outgoing = True
    m2.signing.link_id = 3
    m2.signing.timestamp = 1
    pkts = [m1.attitude_encode(10, 0.1, 0.2, 0.3, 0, 0, 0).pack(m1),
            m2.attitude_encode(20, 0.1, 0.2, 0.3, 0, 0, 0).pack(m2),
            m1.heartbeat_encode(2, 3, 0, 0, 4).pack(m1)]
    assert pkts[0][0] == 0xFE and pkts[1][0] == 0xFD and pkts[1][2] & 1   # v1, signed v2
    with TlogWriter(tmp_path / "m.tlog") as w:
        for k, p in enumerate(pkts):
            w.write(p, 1.7e9 + k)
    assert [p.data for p in read_tlog_packets(tmp_path / "m.tlog")] == pkts
