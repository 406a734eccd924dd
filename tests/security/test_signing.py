"""MAVLink 2 signing helpers, cross-checked against pymavlink's own signing implementation."""

from __future__ import annotations

import logging
import os
import pickle

import pytest
from hypothesis import given, settings
from hypothesis import strategies as st
from pymavlink.dialects.v20 import ardupilotmega as mavlink2

from firmware_interface.signing import (
    EPOCH_UNIX_S,
    SignatureCheck,
    SignatureVerifier,
    SigningConfig,
    SigningError,
    SigningKey,
    is_signed,
    make_signer,
    sign_frame,
    timestamp_from_unix,
    verify,
)

KEY = SigningKey(bytes(range(32)))
OTHER = SigningKey(bytes(range(1, 33)))
NOW = 1_790_000_000.0   # a Unix time in 2026


def _mav(src=1, key: SigningKey | None = None, sign=False) -> mavlink2.MAVLink:
    mav = mavlink2.MAVLink(None, src, 1)
    if key is not None:
        mav.signing.secret_key = key.secret()
        mav.signing.sign_outgoing = sign
        mav.signing.timestamp = timestamp_from_unix(NOW)
    return mav


def _heartbeat(mav=None) -> bytes:
    mav = mav or _mav()
    return mav.heartbeat_encode(mavlink2.MAV_TYPE_GCS, mavlink2.MAV_AUTOPILOT_INVALID, 0, 0, 4).pack(mav)


def _attitude(mav=None, roll=0.1) -> bytes:
    mav = mav or _mav()
    return mav.attitude_encode(1234, roll, 0.2, 0.3, 0.01, 0.02, 0.03).pack(mav)


def test_our_signature_is_accepted_by_pymavlink():
    signed = make_signer(KEY, now_unix_s=NOW).sign(_heartbeat())
    assert is_signed(signed) and verify(signed, KEY)
    rx = _mav(src=200, key=KEY)
    msgs = rx.parse_buffer(signed)
    assert [m.get_type() for m in msgs] == ["HEARTBEAT"] and msgs[0].get_signed()
    assert rx.signing.goodsig_count == 1


def test_pymavlink_signature_is_accepted_by_us():
    frame = _attitude(_mav(key=KEY, sign=True))
    assert is_signed(frame)
    assert verify(frame, KEY) and not verify(frame, OTHER)
    assert SignatureVerifier(KEY).check(frame) is SignatureCheck.OK


def test_unsigned_bad_and_replayed_frames_are_classified_and_counted():
    v = SignatureVerifier(KEY, accept_unsigned=("RADIO_STATUS",))
    signer = make_signer(KEY, now_unix_s=NOW)
    good = signer.sign(_attitude())
    forged = make_signer(OTHER, now_unix_s=NOW).sign(_attitude(roll=1.5))
    tampered = bytearray(good)
    tampered[-1] ^= 0x01
    mav = _mav()
    radio = mav.radio_status_encode(200, 190, 0, 50, 40, 0, 0).pack(mav)
    assert v.check(_attitude()) is SignatureCheck.UNSIGNED
    assert v.check(radio) is SignatureCheck.ACCEPTED_UNSIGNED
    assert v.check(forged) is SignatureCheck.BAD_SIGNATURE
    assert v.check(bytes(tampered)) is SignatureCheck.BAD_SIGNATURE
    assert v.check(good) is SignatureCheck.OK
    assert v.check(good) is SignatureCheck.REPLAYED            # same frame again
    assert v.check(signer.sign(_attitude())) is SignatureCheck.OK
    assert v.counts == {"ok": 2, "unsigned": 1, "accepted_unsigned": 1, "bad_signature": 2, "replayed": 1}
    assert [c.ok for c in SignatureCheck] == [True, False, True, False, False]


def test_a_stale_new_stream_is_a_replay():
    v = SignatureVerifier(KEY)
    assert v.check(make_signer(KEY, now_unix_s=NOW).sign(_heartbeat(_mav(src=1)))) is SignatureCheck.OK
    # a recorded frame of another stream, two minutes older than what we have seen
    old = make_signer(KEY, now_unix_s=NOW - 120).sign(_heartbeat(_mav(src=2)))
    assert v.check(old) is SignatureCheck.REPLAYED
    recent = make_signer(KEY, now_unix_s=NOW - 30).sign(_heartbeat(_mav(src=3)))
    assert v.check(recent) is SignatureCheck.OK


def test_attacker_who_fixes_the_crc_still_fails_the_signature():
    good = make_signer(KEY, now_unix_s=NOW).sign(_attitude())
    # change the payload and recompute a valid CRC (what a man in the middle would do)
    unsigned = bytearray(good[:-13])
    unsigned[2] &= ~0x01
    unsigned[12] ^= 0x40
    n = 10 + unsigned[1]
    crc = mavlink2.x25crc(bytes(unsigned[1:n]))
    crc.accumulate(bytes([mavlink2.MAVLink_attitude_message.crc_extra]))
    body = bytes(unsigned[:n]) + crc.crc.to_bytes(2, "little")
    resigned_wrong_key = sign_frame(body, OTHER, timestamp_from_unix(NOW) + 10)
    with_old_signature = sign_frame(body, KEY, timestamp_from_unix(NOW))[:-6] + good[-6:]
    assert not verify(resigned_wrong_key, KEY)
    assert not verify(with_old_signature, KEY)


@settings(max_examples=60, deadline=None)
@given(roll=st.floats(-3.0, 3.0), ts_offset_s=st.floats(0, 1e6), link_id=st.integers(0, 255),
       flip=st.integers(0, 10_000))
def test_sign_verify_round_trip_and_any_flipped_bit_fails(roll, ts_offset_s, link_id, flip):
    frame = _attitude(roll=roll)
    signed = make_signer(KEY, link_id=link_id, now_unix_s=NOW + ts_offset_s).sign(frame)
    assert verify(signed, KEY)
    assert signed[-13] == link_id
    bit = flip % (8 * len(signed))
    bad = bytearray(signed)
    bad[bit // 8] ^= 1 << (bit % 8)
    assert not verify(bytes(bad), KEY)


def test_sign_stream_signs_every_frame_of_an_encoder_chunk_with_increasing_timestamps():
    chunk = _heartbeat() + _attitude() + _heartbeat()
    signer = make_signer(KEY, now_unix_s=NOW)
    out = signer.sign_stream(chunk, NOW)
    msgs = _mav(src=200, key=KEY).parse_buffer(out)
    assert [m.get_type() for m in msgs] == ["HEARTBEAT", "ATTITUDE", "HEARTBEAT"]
    assert all(m.get_signed() for m in msgs)
    with pytest.raises(SigningError):
        signer.sign_stream(chunk[:-3])
    with pytest.raises(SigningError, match="MAVLink 2"):
        sign_frame(_mav().heartbeat_encode(6, 8, 0, 0, 4).pack(_mav(), force_mavlink1=True), KEY, 1)


def test_session_output_signed_is_accepted_by_a_signing_flight_controller():
    from firmware_interface.session import MavlinkSession, SessionConfig

    session = MavlinkSession(SessionConfig())
    fc = _mav(src=1, key=KEY, sign=True)
    session.receive_data(fc.heartbeat_encode(mavlink2.MAV_TYPE_HELICOPTER,
                                             mavlink2.MAV_AUTOPILOT_ARDUPILOTMEGA, 0, 0, 4).pack(fc), NOW)
    out = session.data_to_send(NOW + 0.1)
    assert out, "the session sends a heartbeat and stream requests once it has seen the FC"
    signed = make_signer(KEY, now_unix_s=NOW).sign_stream(out, NOW + 0.1)
    fc_rx = _mav(src=1, key=KEY)
    names = [m.get_type() for m in fc_rx.parse_buffer(signed)]
    assert "HEARTBEAT" in names and fc_rx.signing.goodsig_count == len(names)
    # the same bytes unsigned are rejected by an FC that requires signing
    fc_strict = _mav(src=1, key=KEY)
    fc_strict.signing.allow_unsigned_callback = lambda mav, msg_id: False
    with pytest.raises(mavlink2.MAVError):
        fc_strict.parse_buffer(out)


# ---------------------------------------------------------------- key handling


def _write_key(path, data: bytes, mode: int):
    fd = os.open(path, os.O_WRONLY | os.O_CREAT | os.O_TRUNC, mode)
    with os.fdopen(fd, "wb") as f:
        f.write(data)
    os.chmod(path, mode)
    return path


@pytest.mark.parametrize("mode", [0o644, 0o640, 0o604, 0o660, 0o601])
def test_key_file_accessible_by_others_is_refused(tmp_path, mode):
    p = _write_key(tmp_path / "fc.key", bytes(range(32)).hex().encode(), mode)
    with pytest.raises(SigningError) as e:
        SigningKey.from_file(p)
    msg = str(e.value)
    assert str(p) in msg and "chmod 600" in msg and bytes(range(32)).hex() not in msg


def test_key_file_forms(tmp_path):
    raw = _write_key(tmp_path / "raw.key", bytes(range(32)), 0o600)
    hexf = _write_key(tmp_path / "hex.key", (bytes(range(32)).hex() + "\n").encode(), 0o600)
    phrase = _write_key(tmp_path / "phrase.key", b"correct horse battery staple\n", 0o400)
    assert SigningKey.from_file(raw) == KEY == SigningKey.from_file(hexf)
    assert SigningKey.from_file(phrase) == SigningKey.from_passphrase("correct horse battery staple")
    with pytest.raises(SigningError, match="not found"):
        SigningKey.from_file(tmp_path / "missing.key")
    empty = _write_key(tmp_path / "empty.key", b"\n", 0o600)
    with pytest.raises(SigningError, match="empty"):
        SigningKey.from_file(empty)
    cfg = SigningConfig(key_file=str(hexf), accept_unsigned=("RADIO_STATUS",))
    assert cfg.enabled and cfg.load_key() == KEY and not SigningConfig().enabled
    with pytest.raises(SigningError, match="NOT_A_MESSAGE"):
        SigningConfig(key_file=str(hexf), accept_unsigned=("NOT_A_MESSAGE",))


def test_key_never_appears_in_repr_logs_errors_or_pickles(tmp_path, caplog):
    secret = bytes(range(32))
    p = _write_key(tmp_path / "fc.key", b"hunter2 is my passphrase", 0o600)
    phrase_key = SigningKey.from_passphrase("hunter2 is my passphrase")
    caplog.set_level(logging.DEBUG)
    key = SigningKey.from_file(p)
    signer = make_signer(KEY, now_unix_s=NOW)
    verifier = SignatureVerifier(KEY)
    verifier.check(signer.sign(_heartbeat()))
    logging.getLogger("test").info("signing with %r %s %r %r", key, KEY, signer, verifier)
    text = caplog.text + repr(key) + str(KEY) + repr(signer) + repr(verifier) + repr(SigningConfig(str(p)))
    for needle in (secret.hex(), secret.hex().upper(), repr(secret), "hunter2", phrase_key.secret().hex()):
        assert needle not in text
    assert KEY.fingerprint in text and len(KEY.fingerprint) == 12
    with pytest.raises(TypeError):
        pickle.dumps(KEY)
    with pytest.raises(SigningError) as e:
        SigningKey(secret[:31])
    assert secret[:31].hex() not in str(e.value)


def test_timestamp_epoch():
    assert timestamp_from_unix(EPOCH_UNIX_S) == 0
    assert timestamp_from_unix(EPOCH_UNIX_S + 1.5) == 150_000


def test_session_with_hooks_from_a_key_file_drops_and_counts_what_fails(tmp_path):
    from firmware_interface.samples import Heartbeat, RawPacket
    from firmware_interface.session import MavlinkSession, SessionConfig
    from firmware_interface.signing import session_hooks

    key_file = _write_key(tmp_path / "fc.key", bytes(range(32)).hex().encode(), 0o600)
    assert session_hooks(SigningConfig(), NOW) == (None, None)
    verifier, signer = session_hooks(SigningConfig(key_file=str(key_file)), NOW)
    session = MavlinkSession(SessionConfig(), verifier=verifier, signer=signer)
    fc = _mav(src=1, key=KEY, sign=True)
    hb = fc.heartbeat_encode(mavlink2.MAV_TYPE_HELICOPTER, mavlink2.MAV_AUTOPILOT_ARDUPILOTMEGA, 0, 0, 4)
    good = hb.pack(fc)
    forged = make_signer(OTHER, now_unix_s=NOW).sign(_attitude(_mav(src=1)))
    session.receive_data(good + _attitude(_mav(src=1)) + forged + good, NOW)
    events = session.events()
    raw = [(e.msg_type, e.signature_ok) for e in events if isinstance(e, RawPacket)]
    assert raw == [("HEARTBEAT", True), ("ATTITUDE", False), ("ATTITUDE", False), ("HEARTBEAT", False)]
    assert [type(e) for e in events if not isinstance(e, RawPacket)] == [Heartbeat]   # only the good one
    assert session.stats.unsigned_dropped == 3
    status = verifier.status()
    assert status == {"enabled": True, "key_fingerprint": KEY.fingerprint, "ok": 1, "unsigned": 1,
                      "accepted_unsigned": 0, "bad_signature": 1, "replayed": 1}
    out = session.data_to_send(NOW + 0.5)
    fc_rx = _mav(src=1, key=KEY)
    fc_rx.signing.allow_unsigned_callback = lambda mav, msg_id: False
    assert fc_rx.parse_buffer(out) and fc_rx.signing.goodsig_count >= 1
    os.chmod(key_file, 0o640)
    with pytest.raises(SigningError, match="chmod 600"):
        session_hooks(SigningConfig(key_file=str(key_file)), NOW)
