"""TOML tables [prepare], [identify], [bounds] for the identify/validate commands."""

from __future__ import annotations

import tomllib

import pytest

from groundstation.sysid.config import parse_sysid_config


def test_tables_map_onto_the_dataclasses():
    doc = tomllib.loads("""
[prepare]
smooth_passes = 2
input_channels = [2, 1, 3, 4]
[identify]
window_s = 2.5
[bounds]
M_a = [0.0, 150.0]
""")
    prep, ident, bounds = parse_sysid_config(doc, "cfg.toml")
    assert prep.smooth_passes == 2 and prep.input_channels == (2, 1, 3, 4)
    assert ident.window_s == 2.5
    assert bounds == {"M_a": (0.0, 150.0)}


@pytest.mark.parametrize("text, needle", [
    ("[prepare]\nsmoth_passes = 2\n", "smoth_passes"),
    ("[identfy]\n", "identfy"),
    ("[bounds]\nM_x = [0, 1]\n", "M_x"),
    ("[bounds]\nM_a = [5, 1]\n", "M_a"),
    ("[prepare]\nrate_hz = -1\n", "rate_hz"),
])
def test_bad_config_names_file_and_key(text, needle):
    with pytest.raises(ValueError) as e:
        parse_sysid_config(tomllib.loads(text), "cfg.toml")
    assert "cfg.toml" in str(e.value) and needle in str(e.value)
