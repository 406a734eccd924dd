"""A flight whose telemetry lost too much is analysed again from the FC's onboard log: through a real pty,
the built-in simulated FC loses 10 % of its telemetry packets but writes its own log of the flight
without loss; after disarm the service publishes the telemetry's model, downloads the onboard log over
the same link and publishes the onboard log's model, marked as such. What carries the link (USB or a
radio) decides whether that happens by default."""

from __future__ import annotations

import asyncio
import dataclasses
import json

import pytest

from groundstation.config import ServiceConfig
from groundstation.onboard import analyse_onboard, link_kind
from groundstation.service import Service
from hil_replay.fc import FcConfig
from tests.service.conftest import service_config


@pytest.mark.parametrize(("url", "configured", "kind"), [
    ("serial:///dev/ttyACM0:115200", "auto", "usb"),          # the autopilot's own USB port (CDC-ACM)
    ("serial:///dev/cu.usbmodem14101:57600", "auto", "usb"),  # the same on macOS: the baud is not used
    ("serial:///dev/pts/7:115200", "auto", "usb"),            # a virtual port (the built-in simulated FC)
    ("serial:///dev/ttyUSB0:57600", "auto", "radio"),         # a USB-serial adapter: how SiK/RFD900 radios connect
    ("serial:///dev/ttyUSB0:921600", "auto", "radio"),
    ("serial://COM3:57600", "auto", "radio"),
    ("udpin://0.0.0.0:14550", "auto", "radio"),              # WiFi telemetry, a forwarded radio
    ("udpin://0.0.0.0:14550", "usb", "usb"),                 # said in the configuration: that wins
    ("serial:///dev/ttyACM0:115200", "radio", "radio"),
])
def test_link_kind_from_the_port_or_the_configuration(url, configured, kind):
    got, why = link_kind(url, configured)
    assert got == kind and why


def test_analyse_policy_usb_by_default_radio_only_when_asked():
    sec = ServiceConfig().onboard_logs
    assert sec.analyse == "usb"
    assert analyse_onboard(sec, "usb") and not analyse_onboard(sec, "radio")
    assert analyse_onboard(dataclasses.replace(sec, analyse="always"), "radio")
    assert not analyse_onboard(dataclasses.replace(sec, analyse="off"), "usb")


def test_lossy_flight_ends_with_the_onboard_logs_model(tmp_path):
    cfg = service_config(tmp_path, service={"exit_after_flights": 1, "campaign_db": ""},
                         sim={"speed": 20.0, "flights": 1, "seed": 6},
                         identify={"maxiter": 6},
                         identification={"refine": False, "diagnose": False, "plots": False, "heldout_folds": 0},
                         excitation={"enabled": False},
                         # download stays off: the lossy flight's log is fetched for its analysis alone.
                         # The link loses 10 % of the list requests' answers too: a lost one is asked again
                         # after 2 s, and many retries (not a long timeout) keep a starved machine from
                         # being taken for a silent FC
                         onboard_logs={"after_disarm_s": 0.5, "list_timeout_s": 2.0, "list_retries": 60,
                                       "give_up_s": 120.0})
    lines: list[str] = []
    fc = FcConfig(seed=6, packet_loss=0.10, record_dataflash=True)
    service = Service(cfg, sim_options={"flight_duration_s": 40.0, "pause_s": 2.0}, fc_config=fc, log=lines.append)
    report = asyncio.run(asyncio.wait_for(service.run(), 600))
    assert report.flights == 1, lines
    assert [r.data for r in report.results] == ["telemetry", "onboard_log"], lines   # telemetry first, then the better one
    tel, onb = report.results
    assert tel.ok and onb.ok, (tel.error, onb.error)
    assert any("telemetry lost" in ln and "downloading it to analyse it instead" in ln for ln in lines), lines
    (bin_path,) = onb.tlogs
    assert bin_path.endswith("log-1.bin") and service.onboard.downloaded == [bin_path]
    # the telemetry's files stay; the onboard log's are beside them and say where they come from
    tel_model = json.loads(open(tel.model_path).read())
    onb_model = json.loads(open(onb.model_path).read())
    assert onb.model_path.endswith("model-flight01-onboard.json") and tel.model_path.endswith("model-flight01.json")
    assert tel_model["source"].get("data") is None and tel_model["source"]["link_quality"]["loss_pct"] > 5
    assert onb_model["source"]["data"] == "onboard_log" and onb_model["source"]["replaces"] == tel.model_path
    assert onb_model["source"]["logs"] == [bin_path]
    assert not onb_model["source"]["link_quality"].get("in_air_holes")      # the onboard log lost nothing
    # what the service serves last is the onboard log's model; its status keeps the link's figures
    assert service.zenoh.latest["model"]["source"]["data"] == "onboard_log"
    status = service.status()
    assert status["identification"]["last_data"] == "onboard_log"
    assert status["link"]["last_flight"]["loss_pct"] > 5
