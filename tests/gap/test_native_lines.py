"""Vibration lines in high-rate body rates (an autopilot's onboard log): found at their true frequency,
not folded onto the 50 Hz grid; none in noise alone; the diagnosis report gets the unfolded frequency."""

from __future__ import annotations

import numpy as np

from groundstation.analysis import unfold_rotor_line
from groundstation.gap.fingerprints import native_rate_lines


def _gyro(f_hz: float | None, amp: float, n: int = 200 * 120, seed: int = 0) -> np.ndarray:
    rng = np.random.default_rng(seed)
    t = np.arange(n) / 200.0
    g = 0.003 * rng.standard_normal((n, 3)) + 0.05 * np.sin(2 * np.pi * 0.5 * t)[:, None]  # flown motion
    if f_hz is not None:
        g += amp * np.array([1.0, 0.8, 0.5]) * np.sin(2 * np.pi * f_hz * t)[:, None]
    return g


def test_line_at_its_true_frequency_above_the_grid_nyquist():
    lines = native_rate_lines(_gyro(37.3, 0.002), 1 / 200.0)
    assert lines and abs(lines[0].frequency_hz - 37.3) < 0.05
    assert "p" in lines[0].channels


def test_no_line_in_noise_alone():
    for seed in range(5):
        assert native_rate_lines(_gyro(None, 0.0, seed=seed), 1 / 200.0) == []


def test_report_effect_gets_the_unfolded_frequency():
    report = {"effects": [{"effect": "rotor_vibration", "estimate": {"frequency_hz": 12.7}, "evidence": "line"}]}
    native = {"source": "IMU at 200 Hz in x.bin", "lines": [{"frequency_hz": 37.3, "channels": ["p"]}],
              "rotor_speed_hz": 37.3}
    unfold_rotor_line(report, native, 50.0)
    est = report["effects"][0]["estimate"]
    assert est["frequency_hz"] == 37.3 and est["frequency_hz_on_grid"] == 12.7
    assert report["vibration_native"] is native


def test_native_line_settings_come_from_the_diagnosis_configuration():
    """``[diagnose] native_line_min_hz`` (and its window and level) reach the native-rate line search."""
    from types import SimpleNamespace

    from groundstation.analysis import native_vibration
    from groundstation.gap.config import DiagnoseConfig

    g = _gyro(12.5, 0.002)
    t = np.arange(len(g)) / 200.0

    class _Series(dict):
        t_fc_s = t

        def __len__(self) -> int:
            return len(t)

    imu = _Series(gx_rad_s=g[:, 0], gy_rad_s=g[:, 1], gz_rad_s=g[:, 2])
    log = SimpleNamespace(series={"IMU": imu}, flights=[SimpleNamespace(start_fc_s=0.0, end_fc_s=t[-1])],
                          source="x.bin")
    found = native_vibration([log], 50.0)
    assert found is not None and abs(found["lines"][0]["frequency_hz"] - 12.5) < 0.5   # within a bin
    assert native_vibration([log], 50.0, DiagnoseConfig(native_line_min_hz=15.0))["lines"] == []
