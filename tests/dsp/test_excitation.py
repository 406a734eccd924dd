"""The live excitation monitor (groundstation.dsp.excitation) driven through the live path from
simulated flights: each swept axis says enough within 10 s of the end of its sweep; a flight flown
with a few per cent of the card's excitation never does; a SYSID chirp is judged over its own band;
rows that only bridge holes of a lossy link count in the random error by their share."""

from __future__ import annotations

import math

import numpy as np
import pytest

from firmware_interface.samples import Heartbeat
from firmware_interface.session import MavlinkSession, SessionConfig
from firmware_interface.tlogread import scan_tlog
from groundstation.dsp.excitation import (
    AXES,
    ExcitationConfig,
    ExcitationMonitor,
    coverage,
    flight_mode_name,
)
from groundstation.dsp.live import FlightEnded, FlightStarted, LivePipeline
from hil_replay.sim import write_tlog
from hil_replay.sim.session import DEFAULT_TLOG_RATES_HZ

#: the streams the service asks the flight controller for (RAW_IMU at 50 Hz: the vertical acceleration)
RATES = {**DEFAULT_TLOG_RATES_HZ, "RAW_IMU": 50.0}


def drive(path, config: ExcitationConfig | None = None, batch: int = 24, freq=None, spectra: list | None = None,
          masks: list | None = None):
    """Replay a .tlog through the session, the live pipeline and the monitor as the service does
    (batches of packets); every verdict the monitor gives, in order (with ``freq``: each flight's
    ``[freq]`` spectra appended to ``spectra``; with ``masks``: the in-air rows' measured masks)."""
    session = MavlinkSession(SessionConfig(request_streams=False, send_heartbeat=False, emit_raw_packets=False,
                                           link_timeout_s=math.inf))
    live = LivePipeline()
    mon = ExcitationMonitor(config, 1.0 / live.config.grid_rate_hz, freq=freq)
    reports = []
    pending = []

    def step(events):
        out = live.feed(events)
        for fe in out.flight_events:
            if isinstance(fe, FlightStarted):
                mon.flight_started(fe.flight, fe.t_fc_s)
        mon.events(events)
        ft = live.flights
        if masks is not None and ft.in_air and ft.armed:
            masks.append(out.outputs_measured)
        rep = mon.rows(out.t_fc_s, out.inputs, out.outputs_raw, armed=ft.armed, in_air=ft.in_air,
                       measured=out.outputs_measured)
        if rep is not None:
            reports.append(rep)
        for fe in out.flight_events:
            if isinstance(fe, FlightEnded):
                last = mon.flight_ended()
                if last is not None:
                    reports.append(last)
                if spectra is not None:
                    spectra.append(mon.take_freq_spectra(fe.flight))

    with open(path, "rb") as f:
        data = f.read()
    for t_host, pkt in scan_tlog(data):
        session.receive_packet(pkt, t_host)
        pending.extend(session.events())
        if len(pending) >= batch:
            step(pending)
            pending = []
    step(pending)
    return reports


@pytest.fixture(scope="module")
def card_flight(tmp_path_factory):
    path = tmp_path_factory.mktemp("exc") / "card.tlog"
    truth = write_tlog(path, seed=0, flights=1, rates_hz=RATES)
    return path, truth


@pytest.fixture(scope="module")
def quiet_flight(tmp_path_factory):
    path = tmp_path_factory.mktemp("exc") / "quiet.tlog"
    truth = write_tlog(path, seed=0, flights=1, excitation_scale=0.03, rates_hz=RATES)
    return path, truth


def _sweeps(truth):
    fl = truth["flights"][0]
    return {s["axis"]: (s["start_fc_s"], s["end_fc_s"]) for s in fl["segments"] if s["name"].startswith("sweep_")}


def test_each_swept_axis_says_enough_within_10_s_of_the_end_of_its_sweep(card_flight):
    path, truth = card_flight
    reports = drive(path)
    sweeps = _sweeps(truth)
    assert set(sweeps) == set(AXES)
    t0 = truth["flights"][0]["start_fc_s"]
    for axis, (start, end) in sweeps.items():
        first = next((r for r in reports if r.axes[axis].enough), None)
        assert first is not None, f"{axis} never enough: {reports[-1].axes[axis].missing}"
        # it says so at most 10 s (flight time) after its sweep ended, and not before the sweep began
        assert start < first.t_fc_s <= end + 10.0, (axis, start, end, first.t_fc_s)
        assert first.enough_at_s[axis] == pytest.approx(first.t_fc_s - t0, abs=0.05)
        v = first.axes[axis]
        assert v.band_hz == (0.3, 5.0) and v.band_from == "config" and v.missing == ""
        assert v.covered_hz[0][0] <= 0.3 + 1e-9 and v.covered_hz[-1][1] >= 4.8
        assert v.coherence_min is not None and v.coherence_min >= 0.5
    # before its sweep an axis is not enough yet, and the verdict names the band that is missing
    lat_start = sweeps["lat"][0]
    before = [r for r in reports if r.t_fc_s < lat_start - 1.0]
    assert before and not any(r.axes["lat"].enough for r in before)
    assert "missing" in before[-1].axes["lat"].missing
    # about one verdict per FC second while armed
    ts = np.array([r.t_fc_s for r in reports[:-1]])
    assert np.median(np.diff(ts)) == pytest.approx(1.0, abs=0.1)
    doc = reports[-1].to_json()
    assert doc["flight"] == 1 and set(doc["axes"]) == set(AXES)
    assert doc["axes"]["col"]["outputs"] == ["w", "az"] and doc["axes"]["lat"]["outputs"] == ["q", "theta"]


def test_a_flight_with_a_few_per_cent_of_the_excitation_is_never_enough(quiet_flight):
    path, _ = quiet_flight
    reports = drive(path)
    assert len(reports) > 100
    for r in reports:
        assert not any(v.enough for v in r.axes.values()), r.line()
    last = reports[-1]
    for v in last.axes.values():     # the pilot's corrections are coherent at low frequency, not above
        assert v.missing.startswith("coherent 0.3-") and "missing" in v.missing and v.covered_hz[-1][1] < 4.0


def test_coverage_joins_isolated_dips_and_names_the_missing_band():
    f = np.geomspace(0.3, 8.0, 60)
    g = np.where(f < 3.0, 0.9, 0.2)
    g[10] = 0.4                               # one point below the threshold: joined
    covered, missing = coverage(f, g, (0.3, 5.0), 0.6, 2)
    assert len(covered) == 1 and covered[0][0] == pytest.approx(0.3) and 2.8 < covered[0][1] < 3.0
    assert len(missing) == 1 and missing[0][1] == 5.0
    g[10:14] = 0.4                            # four points: a hole
    covered, missing = coverage(f, g, (0.3, 5.0), 0.6, 2)
    assert len(covered) == 2 and len(missing) == 2
    covered, missing = coverage(f, np.full(60, np.nan), (0.3, 5.0), 0.6, 2)
    assert covered == () and missing == ((0.3, 5.0),)
    covered, missing = coverage(f, np.full(60, 0.9), (0.2, 5.0), 0.6, 2)
    assert missing == ((0.2, 0.3),)           # below the estimate's lowest frequency: never covered


def test_flight_modes_are_named():
    assert flight_mode_name(3, 25) == "SYSTEMID" and flight_mode_name(3, 0) == "STABILIZE"
    assert flight_mode_name(12, (2 << 16)) == "ALTCTL" and flight_mode_name(12, (4 << 16) | (4 << 24)) == "AUTO_MISSION"
    assert flight_mode_name(8, 5) == "mode 5"


def _hb(mode: int, t: float) -> Heartbeat:
    return Heartbeat(t, t, 1, 1, mav_type=4, autopilot=3, base_mode=128, custom_mode=mode, system_status=4, armed=True)


def test_a_sysid_chirp_is_recognised_and_its_own_band_judged():
    """ArduPilot SYSID mode flies a chirp on one axis: the monitor finds the axis and the chirp's band
    from the input and judges that axis over the chirp's band (within the band asked for)."""
    dt = 0.02
    mon = ExcitationMonitor(ExcitationConfig(), dt)
    mon.flight_started(1, 0.0)
    rng = np.random.default_rng(0)
    t = np.arange(0, 60.0, dt)
    # lon: a log chirp 0.5 -> 3 Hz from 20 s to 40 s; the other inputs: small noise
    k = np.log(3.0 / 0.5) / 20.0
    tc = np.clip(t - 20.0, 0, 20.0)
    chirp = np.where((t >= 20) & (t <= 40), 0.1 * np.sin(2 * np.pi * 0.5 * (np.exp(k * tc) - 1) / k), 0.0)
    u = 0.002 * rng.standard_normal((t.size, 4))
    u[:, 1] += chirp
    y = 0.01 * rng.standard_normal((t.size, 8))
    y[:, 3] += 2.0 * np.convolve(u[:, 1], np.ones(3) / 3, mode="same")     # p follows lon
    y[:, 7] += np.cumsum(y[:, 3]) * dt
    mode = 0
    for a in range(0, t.size, 25):
        s = slice(a, a + 25)
        want = 25 if 20.0 <= t[a] < 40.0 else 0
        if want != mode:
            mode = want
            mon.events([_hb(mode, float(t[a]))])
        mon.rows(t[s], u[s], y[s], armed=True, in_air=True)
    rep = mon.report()
    assert rep.mode == "STABILIZE" and len(rep.chirps) == 1
    c = rep.chirps[0]
    assert c.axis == "lon" and c.f_start_hz == pytest.approx(0.5, rel=0.15) and c.f_stop_hz == pytest.approx(3.0, rel=0.15)
    lon = rep.axes["lon"]
    assert lon.band_from == "chirp" and lon.band_hz == (c.f_start_hz, c.f_stop_hz)
    assert lon.enough, lon.missing
    assert rep.axes["lat"].band_from == "config" and not rep.axes["lat"].enough
    assert rep.to_json()["chirps"][0]["axis"] == "lon"


def test_a_flight_start_does_not_import_scipy_signal():
    """The service starts a flight's estimate on its event loop: importing scipy.signal there (about a
    second of CPU) stalled the live windows. The Hann taper is computed with numpy, equal to scipy's."""
    import subprocess
    import sys

    code = ("import sys\nfrom groundstation.dsp.excitation import ExcitationMonitor\n"
            "m = ExcitationMonitor()\nm.flight_started(1, 0.0)\nprint('scipy.signal' in sys.modules)")
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, check=True).stdout
    assert out.strip() == "False"
    from scipy.signal import get_window

    from groundstation.freq.spectra import taper_window

    for n in (7, 125, 500):
        np.testing.assert_allclose(taper_window("hann", n), get_window("hann", n), rtol=0, atol=1e-15)


def test_the_flights_freq_spectra_accumulated_live_serve_the_after_flight_check(card_flight):
    """With ``[freq]``'s settings the monitor also accumulates the flight (the worker's frequency check
    then makes no second pass): on the recorded log they give what ``validate --freq`` gives, up to
    the live rows not being ``prepare``'s exactly (edge trims)."""
    from firmware_interface.readers import load_log
    from groundstation.commands.freq_support import prepare_native
    from groundstation.config import ServiceConfig
    from groundstation.freq.spectra import FreqConfig, estimate_responses

    path, _ = card_flight
    spectra: list = []
    drive(path, freq=FreqConfig(), spectra=spectra)
    assert len(spectra) == 1 and spectra[0] is not None
    live = spectra[0].responses()
    batch = estimate_responses(prepare_native([load_log(str(path))], ServiceConfig().prepare), FreqConfig())
    np.testing.assert_allclose(live.f_hz, batch.f_hz)
    assert live.windows_s == batch.windows_s
    assert {(p.input, p.output) for p in live.with_response} == {(p.input, p.output) for p in batch.with_response}
    for inp, out in (("lat", "q"), ("lon", "p"), ("col", "w"), ("ped", "r")):
        a, b = live.pair(inp, out), batch.pair(inp, out)
        assert abs(a.coherent_points - b.coherent_points) <= 2
        m = a.coherent & b.coherent
        assert np.median(np.abs(np.abs(a.response[m]) / np.abs(b.response[m]) - 1)) < 0.01
        assert np.median(np.abs(a.coherence[m] - b.coherence[m])) < 0.01


def test_live_spectra_count_only_what_a_lossy_link_delivered(tmp_path):
    """A replay of a flight whose link lost 20 % of its packets in bursts: the rows bridging the holes
    are marked by the live grid and the live spectra count each window by its measured share (as the
    after-flight estimate does), so the averages behind the random error shrink by the share lost
    (a loss-free replay keeps every average: the monitor then takes the plain path, as the test above
    checks against the after-flight estimate)."""
    from groundstation.freq.spectra import FreqConfig

    rates = {**RATES, "ATTITUDE": 25.0, "SERVO_OUTPUT_RAW": 25.0, "LOCAL_POSITION_NED": 25.0}
    path = tmp_path / "lossy.tlog"
    write_tlog(path, seed=3, flights=1, flight_duration_s=40.0, rates_hz=rates, packet_loss=0.2, loss_burst=8.0)
    spectra: list = []
    masks: list = []
    drive(path, freq=FreqConfig(), spectra=spectra, masks=masks)
    ws = max(spectra[0].windows, key=lambda w: w.win_s)
    per_seg = [sum(c.values()) for c in ws.counts]
    keys = tuple(k for c in ws.counts for k in c)
    share_q = (ws.measured_averages(keys, per_seg) / ws.averages(per_seg))[4 + 4]    # output q
    lost_q = 1.0 - np.vstack(masks)[:, 4].mean()                                    # rows of q not measured
    assert 0.05 < lost_q < 0.3
    assert share_q == pytest.approx(1.0 - lost_q, abs=0.03)
