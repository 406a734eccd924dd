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
