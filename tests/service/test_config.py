"""Service configuration: TOML loading, unknown keys rejected with one line naming the key."""

from __future__ import annotations

import pytest

from groundstation.config import ConfigError, ServiceConfig, load_config


def test_defaults_and_shipped_default_file_agree(tmp_path):
    from importlib.resources import files

    shipped = files("groundstation") / "configs" / "default.toml"
    cfg = load_config(str(shipped))
    assert cfg == ServiceConfig()


def test_values_are_read(tmp_path):
    p = tmp_path / "gs.toml"
    p.write_text('[service]\nvehicle = "trex"\n[live]\nwindow_s = 2\nhop_s = 0.25\n'
                 '[inputs]\ntrim_pwm = [1500, 1510, 1560, 1480]\n[identification]\nscope = "all"\n')
    cfg = load_config(p)
    assert cfg.service.vehicle == "trex"
    assert cfg.live.window_s == 2.0 and isinstance(cfg.live.window_s, float)
    assert cfg.inputs.trim_pwm == (1500.0, 1510.0, 1560.0, 1480.0)
    assert cfg.identification.scope == "all"


@pytest.mark.parametrize("text, needle", [
    ("[live]\nwindow_len = 3\n", "unknown key live.window_len"),
    ("[lvie]\nwindow_s = 3\n", "unknown table [lvie]"),
    ("[live]\nwindow_s = 'long'\n", "live.window_s"),
    ("[live]\nhop_s = 10\n", "live.hop_s"),
    ("[rerun]\nmode = 'tv'\n", "rerun.mode"),
    ("[service]\nvehicle = 'a/b'\n", "service.vehicle"),
    ("[identification]\nrestarts = 0\n", "identification.restarts"),
    ("[service\n", "not valid TOML"),
])
def test_bad_config_is_one_line_naming_file_and_key(tmp_path, text, needle):
    p = tmp_path / "bad.toml"
    p.write_text(text)
    with pytest.raises(ConfigError) as exc:
        load_config(p)
    msg = str(exc.value)
    assert needle in msg and str(p) in msg and "\n" not in msg


def test_missing_file_names_it(tmp_path):
    with pytest.raises(ConfigError, match="nope.toml"):
        load_config(tmp_path / "nope.toml")


def test_cli_prints_one_line_and_exits_2(tmp_path, capsys):
    from groundstation.cli import main

    p = tmp_path / "bad.toml"
    p.write_text("[zenoh]\nmode = 'peer'\n")
    assert main(["run", "--config", str(p)]) == 2
    err = capsys.readouterr().err.strip()
    assert "unknown key zenoh.mode" in err and len(err.splitlines()) == 1
