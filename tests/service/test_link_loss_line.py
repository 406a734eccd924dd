"""A flight whose telemetry lost much says so at disarm, in one line that points to the onboard log."""

from __future__ import annotations

from types import SimpleNamespace

from groundstation.service import Service
from tests.service.conftest import service_config


def _service(tmp_path, **onboard):
    lines: list[str] = []
    svc = Service(service_config(tmp_path, identification={"enabled": False}, onboard_logs=onboard), log=lines.append)
    svc.session = SimpleNamespace(stats=SimpleNamespace(packets=1000, packets_lost=10))
    svc._link_at_arm = svc._link_counts()
    return svc, lines


def test_lossy_flight_points_to_the_onboard_log(tmp_path):
    svc, lines = _service(tmp_path)
    svc.session.stats.packets, svc.session.stats.packets_lost = 10000, 1010   # 9000 got, 1000 lost: 10 %
    svc._suggest_onboard_log(3)
    assert len(lines) == 1 and "flight 3: telemetry lost 10.0 %" in lines[0]
    assert "logs get" in lines[0] and "download = true" in lines[0]


def test_quiet_below_the_level_and_download_said_when_on(tmp_path):
    svc, lines = _service(tmp_path)
    svc.session.stats.packets, svc.session.stats.packets_lost = 10000, 50
    svc._suggest_onboard_log(1)
    assert lines == []
    svc2, lines2 = _service(tmp_path / "b", download=True, suggest_above_loss_pct=1.0)
    svc2.session.stats.packets, svc2.session.stats.packets_lost = 10000, 210
    svc2._suggest_onboard_log(2)
    assert len(lines2) == 1 and "being downloaded" in lines2[0]


def test_onboard_log_analysed_instead_over_usb_only_unless_asked(tmp_path):
    # over the autopilot's USB port the lossy flight's onboard log is fetched to be analysed instead
    svc, lines = _service(tmp_path / "usb")
    svc.link_url, svc.onboard, svc._executor = "serial:///dev/ttyACM0:115200", object(), object()
    svc.session.stats.packets, svc.session.stats.packets_lost = 10000, 1010
    assert svc._suggest_onboard_log(4) is True
    assert "downloading it to analyse it instead of the telemetry (usb link" in lines[0]
    # over a radio only when asked: said in the line
    svc, lines = _service(tmp_path / "radio", download=True)
    svc.link_url, svc.onboard, svc._executor = "serial:///dev/ttyUSB0:57600", object(), object()
    svc.session.stats.packets, svc.session.stats.packets_lost = 10000, 1010
    assert svc._suggest_onboard_log(5) is False
    assert "being downloaded" in lines[0] and 'analyse = "always"' in lines[0] and "radio link" in lines[0]
    svc, lines = _service(tmp_path / "asked", analyse="always")
    svc.link_url, svc.onboard, svc._executor = "serial:///dev/ttyUSB0:57600", object(), object()
    svc.session.stats.packets, svc.session.stats.packets_lost = 10000, 1010
    assert svc._suggest_onboard_log(6) is True and "radio link" in lines[0]
