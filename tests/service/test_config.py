"""One configuration model: TOML loading into the domain dataclasses, unknown keys and wrong types
rejected with one line naming the file and the key, one value per setting."""

from __future__ import annotations

import dataclasses

import pytest

from groundstation.config import ConfigError, ServiceConfig, from_dict, load_config, load_toml
from groundstation.dsp.live import LiveConfig
from groundstation.dsp.prepare import PrepConfig
from groundstation.gap.diagnose import DiagnoseConfig
from groundstation.sysid.identify import IdentifyConfig


def test_defaults_and_shipped_default_file_agree(tmp_path):
    from importlib.resources import files

    shipped = files("groundstation") / "configs" / "default.toml"
    cfg = load_config(str(shipped))
    assert cfg == ServiceConfig()


def test_sections_are_the_domain_configurations():
    cfg = ServiceConfig()
    assert isinstance(cfg.prepare, PrepConfig) and isinstance(cfg.live, LiveConfig)
    assert isinstance(cfg.identify, IdentifyConfig) and isinstance(cfg.diagnose, DiagnoseConfig)
    # one value each: the live path's in-air height and the search restarts are the same everywhere
    assert cfg.live.in_air_alt_m == cfg.prepare.in_air_alt_m == PrepConfig().in_air_alt_m == 0.5
    assert cfg.identify.search_restarts == cfg.diagnose.identify_restarts == 2


def test_values_are_read(tmp_path):
    p = tmp_path / "gs.toml"
    p.write_text('[service]\nvehicle = "trex"\n[live]\nwindow_s = 2\nhop_s = 0.25\n'
                 '[prepare]\ninput_channels = [2, 1, 3, 4]\ninput_trim_pwm = [1500, 1510, 1560, 1480]\n'
                 'pwm_per_unit = 400\nsmooth_passes = 2\n'
                 '[identify]\nwindow_s = 2.5\nsearch_restarts = 3\n[bounds]\nM_a = [0.0, 150.0]\n'
                 '[diagnose]\nwindow_s = 4\n[identification]\nscope = "all"\n')
    cfg = load_config(p)
    assert cfg.service.vehicle == "trex"
    assert cfg.live.window_s == 2.0 and isinstance(cfg.live.window_s, float)
    assert cfg.prepare.input_trim_pwm == (1500.0, 1510.0, 1560.0, 1480.0)
    assert cfg.prepare.smooth_passes == 2 and cfg.prepare.pwm_per_unit == 400.0
    # the live path takes its channel map, trim and scale from [prepare]
    assert cfg.live.servo_numbers == (2, 1, 3, 4) and cfg.live.trim_pwm == (1500.0, 1510.0, 1560.0, 1480.0)
    assert cfg.live.pwm_per_unit == 400.0
    assert cfg.identify.window_s == 2.5 and cfg.identify.search_restarts == cfg.diagnose.identify_restarts == 3
    assert cfg.bounds == {"M_a": (0.0, 150.0)}
    assert cfg.diagnose.window_s == 4.0
    assert cfg.identification.scope == "all"


def test_empty_trim_is_automatic(tmp_path):
    p = tmp_path / "gs.toml"
    p.write_text("[prepare]\ninput_trim_pwm = []\n")
    cfg = load_config(p)
    assert cfg.prepare.input_trim_pwm is None and cfg.live.trim_pwm == (1500.0,) * 4


@pytest.mark.parametrize("text, needle", [
    ("[live]\nwindow_len = 3\n", "unknown key live.window_len"),
    ("[lvie]\nwindow_s = 3\n", "unknown table [lvie]"),
    ("[live]\nwindow_s = 'long'\n", "live.window_s"),
    ("[live]\nhop_s = 10\n", "live.hop_s"),
    ("[live]\nservo_numbers = [1, 2, 3, 4]\n", "prepare.input_channels"),
    ("[live]\nin_air_alt_m = 0.3\n", "prepare.in_air_alt_m"),
    ("[diagnose]\nidentify_restarts = 3\n", "identify.search_restarts"),
    ("[rerun]\nmode = 'tv'\n", "rerun.mode"),
    ("[service]\nvehicle = 'a/b'\n", "service.vehicle"),
    ("[identify]\nsearch_restarts = 0\n", "identify.search_restarts"),
    ("[identify]\nsearch_restarts = 1.5\n", "identify.search_restarts"),
    ("[prepare]\nsmoth_passes = 2\n", "unknown key prepare.smoth_passes"),
    ("[prepare]\nrate_hz = -1\n", "rate_hz"),
    ("[prepare]\ninput_channels = [1, 2, 3]\n", "prepare.input_channels"),
    ("[prepare]\ninput_channels = [1, 2, 3, 17]\n", "prepare.input_channels"),
    ("[prepare]\ninput_trim_pwm = [1500, 'x', 1500, 1500]\n", "prepare.input_trim_pwm"),
    ("[bounds]\nM_x = [0, 1]\n", "bounds.M_x"),
    ("[bounds]\nM_a = [5, 1]\n", "bounds.M_a"),
    ("[bounds]\nM_a = 5\n", "bounds.M_a"),
    ("[diagnose]\nalpha = true\n", "diagnose.alpha"),
    ("prepare = 3\n", "prepare"),
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


@dataclasses.dataclass(frozen=True)
class Prior:
    nominal: dict[str, float] = dataclasses.field(default_factory=dict)


@dataclasses.dataclass(frozen=True)
class Aircraft:
    name: str = ""
    prepare: PrepConfig = dataclasses.field(default_factory=PrepConfig)
    prior: Prior = dataclasses.field(default_factory=Prior)
    mass_kg: float | None = None


def test_the_loader_is_generic_a_new_section_is_one_field(tmp_path):
    """Another file (an aircraft file, say) or a new section: a dataclass tree, nothing else to write."""

    p = tmp_path / "trex.toml"
    p.write_text('name = "trex"\nmass_kg = 4\n[prepare]\ninput_source = "RC_CHANNELS"\n[prior.nominal]\nX_u = -0.1\n')
    a = load_toml(p, Aircraft)
    assert a.name == "trex" and a.mass_kg == 4.0 and a.prepare.input_source == "RC_CHANNELS"
    assert a.prior.nominal == {"X_u": -0.1}
    with pytest.raises(ConfigError, match=r"aircraft.toml: unknown key prior\.sigma"):
        from_dict(Aircraft, {"prior": {"sigma": 1.0}}, "aircraft.toml")
    with pytest.raises(ConfigError, match=r"x.toml: prepare.input_source"):
        from_dict(Aircraft, {"prepare": {"input_source": "SBUS"}}, "x.toml")


@pytest.mark.parametrize("command", ["run", "identify", "validate", "diagnose"])
def test_every_command_takes_config_and_prints_one_line(tmp_path, capsys, command):
    from groundstation.cli import main

    p = tmp_path / "bad.toml"
    p.write_text("[zenoh]\nmode = 'peer'\n")
    log = tmp_path / "x.tlog"
    log.write_bytes(b"")
    args = {"run": [], "identify": [str(log), "--out", str(tmp_path / "m.json")],
            "validate": [str(tmp_path / "m.json"), str(log)],
            "diagnose": [str(log), "--out", str(tmp_path / "g.json")]}[command]
    if command == "validate":
        (tmp_path / "m.json").write_text("{}")
    assert main([command, *args, "--config", str(p)]) == 2
    err = capsys.readouterr().err.strip()
    assert "unknown key zenoh.mode" in err and str(p) in err and len(err.splitlines()) == 1


def test_every_key_is_in_the_default_file_and_in_the_documentation():
    """The dataclasses are the truth: default.toml sets (or, for a value TOML cannot write, names in a
    comment) every key, and docs/configuration.md carries the generated table of every key."""
    import re
    import tomllib
    from pathlib import Path

    from groundstation.config import reference, reference_markdown

    root = Path(__file__).resolve().parents[2]
    text = (root / "groundstation/configs/default.toml").read_text()
    doc = tomllib.loads(text)
    missing = [f"[{t}] {k}" for t, k, default, _ in reference()
               if k not in doc.get(t, {}) and not (not default and re.search(rf"^#\s*{k}\s*=", text, re.M))]
    assert not missing, f"keys missing from groundstation/configs/default.toml: {missing}"
    md = (root / "docs/configuration.md").read_text()
    start = md.index("<!-- every-key table")
    table = md[md.index("\n", start) + 1: md.index("<!-- end of the every-key table -->")]
    assert table == reference_markdown(), "docs/configuration.md: regenerate the every-key table (python -m groundstation.config)"
    assert {"trends", "freq_identify"} <= {t for t, *_ in reference()}


def test_a_renamed_key_says_what_replaced_it(tmp_path):
    from groundstation.config import ConfigError, config_from_dict

    with pytest.raises(ConfigError, match=r"old.toml: identification.restarts was renamed: it is now \[identify\] search_restarts"):
        config_from_dict({"identification": {"restarts": 3}}, "old.toml")
    with pytest.raises(ConfigError, match=r"\[inputs\] is no longer read: inputs.trim_pwm is now \[prepare\] input_trim_pwm"):
        config_from_dict({"inputs": {"trim_pwm": [1500, 1500, 1500, 1500]}}, "old.toml")
    cfg = config_from_dict({"trends": {"alpha": 0.01}, "freq_identify": {"weighting": "coherence"}})
    assert cfg.trends.alpha == 0.01 and cfg.freq_identify.weighting == "coherence"


def test_every_analysis_command_takes_an_aircraft_file():
    import argparse

    from groundstation.cli import build_parser

    sub = next(a for a in build_parser()._actions if isinstance(a, argparse._SubParsersAction))
    analysis = [c for c in ("identify", "validate", "diagnose", "campaign", "run", "report") if c in sub.choices]
    assert {"identify", "validate", "diagnose", "campaign", "run"} <= set(analysis)
    missing = [c for c in analysis if "--aircraft" not in sub.choices[c]._option_string_actions]
    assert not missing, f"commands without --aircraft: {missing}"
