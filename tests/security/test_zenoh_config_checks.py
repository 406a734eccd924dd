"""Start-up checks of the secured zenoh configs: one clear line naming the file for each problem."""

from __future__ import annotations

import datetime as dt
import os
import shutil
import subprocess
import sys
import threading

import pytest
import zenoh

from groundstation.sinks.zenoh_security import (
    BackgroundConnector,
    ZenohSecurityError,
    check_zenoh_config,
    probe_endpoint,
)
from groundstation.sinks.zenoh_sink import free_tcp_port

from .conftest import SCRIPT, make_field, open_router, retarget, wait_for


@pytest.fixture
def kit(tmp_path, field):
    """A private copy of the field directory (tests mutate it) with configs pointing at the copy."""
    d = tmp_path / "kit"
    shutil.copytree(field, d)
    for f in d.glob("*.json5"):
        f.write_text(f.read_text().replace(str(field), str(d)))
    return d


def test_rendered_configs_pass_and_describe_themselves(kit):
    r = check_zenoh_config(kit / "router.json5")
    gs = check_zenoh_config(kit / "groundstation.json5")
    assert (r.mode, r.tls, r.mutual_tls, r.acl_enabled, r.warnings) == ("router", True, True, True, ())
    assert (gs.mode, gs.user, gs.tls, gs.endpoints) == ("client", "groundstation", True, ("tls/localhost:7447",))
    assert gs.not_after is not None and gs.not_after > dt.datetime.now(dt.UTC) + dt.timedelta(days=300)
    assert "password" not in repr(gs) and _password(kit, "groundstation") not in repr(gs)


def _password(kit, user):
    return dict(line.split(":", 1) for line in (kit / "credentials.txt").read_text().splitlines())[user]


def _one_line_error(path, match):
    with pytest.raises(ZenohSecurityError) as e:
        check_zenoh_config(path)
    msg = str(e.value)
    assert "\n" not in msg and str(path) in msg and match in msg, msg
    return msg


def test_expired_certificate(tmp_path):
    old = make_field(tmp_path / "old", "--valid-days", "1", "--backdate-days", "3")
    msg = _one_line_error(old / "groundstation.json5", "expired on")
    assert "make-field-certs" in msg


def test_certificate_checked_against_the_clock_passed_in(kit):
    future = dt.datetime.now(dt.UTC) + dt.timedelta(days=400)
    with pytest.raises(ZenohSecurityError, match="expired"):
        check_zenoh_config(kit / "viewer.json5", now=future)
    past = dt.datetime.now(dt.UTC) - dt.timedelta(days=30)
    with pytest.raises(ZenohSecurityError, match="clock"):
        check_zenoh_config(kit / "viewer.json5", now=past)


def test_missing_certificate_file(kit):
    (kit / "viewer.pem").unlink()
    _one_line_error(kit / "viewer.json5", f"{kit / 'viewer.pem'} not found")


def test_missing_config_file(kit):
    _one_line_error(kit / "nobody.json5", "not found")


def test_key_readable_by_others_is_refused(kit):
    os.chmod(kit / "router.key", 0o644)
    _one_line_error(kit / "router.json5", "chmod 600")


def test_config_with_password_readable_by_others_is_refused(kit):
    os.chmod(kit / "viewer.json5", 0o644)
    _one_line_error(kit / "viewer.json5", "chmod 600")


def test_key_not_matching_certificate(kit):
    shutil.copy(kit / "alice.key", kit / "viewer.key")
    _one_line_error(kit / "viewer.json5", "does not match")


def test_certificate_from_another_ca(kit, rogue_field):
    shutil.copy(rogue_field / "viewer.pem", kit / "viewer.pem")
    shutil.copy(rogue_field / "viewer.key", kit / "viewer.key")
    _one_line_error(kit / "viewer.json5", "not signed by the CA")


def test_malformed_credentials_dictionary(kit):
    (kit / "credentials.txt").write_text("groundstation\n")
    _one_line_error(kit / "router.json5", "line 1 is not 'user:password'")


def test_user_without_password(kit):
    p = kit / "viewer.json5"
    pw = _password(kit, "viewer")
    p.write_text(p.read_text().replace(f'password: "{pw}"', "password: null"))
    msg = _one_line_error(p, "user without password")
    # password without user: zenoh's own error message dumps the whole config, password included
    p.write_text(p.read_text().replace("password: null", f'password: "{pw}"').replace('user: "viewer", ', ""))
    msg += _one_line_error(p, "user without password")
    assert pw not in msg


def test_plain_endpoint_next_to_tls_is_refused(kit):
    p = kit / "router.json5"
    p.write_text(p.read_text().replace('endpoints: ["tls/0.0.0.0:7447"]',
                                       'endpoints: ["tls/0.0.0.0:7447", "tcp/0.0.0.0:7448"]'))
    _one_line_error(p, "plain endpoint")


def test_unreachable_router_is_named(kit, tmp_path):
    port = free_tcp_port()
    path = retarget(kit / "viewer.json5", tmp_path / "v.json5", port)
    line = probe_endpoint(path)
    assert line is not None and f"tls/localhost:{port} unreachable" in line


def test_background_connector_reports_once_then_connects_when_router_appears(kit, tmp_path):
    port = free_tcp_port()
    path = retarget(kit / "viewer.json5", tmp_path / "v.json5", port, timeout_ms="500")
    problems: list[str] = []
    sessions: list[zenoh.Session] = []
    got_session = threading.Event()

    def on_session(s):
        sessions.append(s)
        got_session.set()

    conn = BackgroundConnector(path, on_session, problems.append, retry_initial_s=0.1, retry_max_s=0.3).start()
    router = None
    try:
        assert wait_for(lambda: conn.attempts >= 3, 15.0)
        assert not got_session.is_set()
        assert len(problems) == 1 and "unreachable" in problems[0]     # reported once, not per attempt
        router = open_router(kit / "router.json5", port)
        assert got_session.wait(15.0)
        assert sessions[0].info.routers_zid()
    finally:
        conn.close()
        for s in sessions:
            s.close()
        if router is not None:
            router.close()


def test_script_refuses_bad_user_names_and_existing_ca(tmp_path):
    bad = subprocess.run([sys.executable, str(SCRIPT), "--out", str(tmp_path / "x"), "--viewer", "a b"],
                         capture_output=True, text=True, timeout=60)
    assert bad.returncode == 2 and "a b" in bad.stderr and bad.stderr.count("\n") == 1
    make_field(tmp_path / "y")
    again = subprocess.run([sys.executable, str(SCRIPT), "--out", str(tmp_path / "y")],
                           capture_output=True, text=True, timeout=60)
    assert again.returncode == 2 and "--force" in again.stderr


def test_script_output_has_private_modes_and_no_passwords_on_stdout(tmp_path):
    out = tmp_path / "f"
    proc = subprocess.run([sys.executable, str(SCRIPT), "--out", str(out)], capture_output=True,
                          text=True, timeout=60)
    assert proc.returncode == 0
    for name in ("ca.key", "router.key", "groundstation.key", "viewer.key", "credentials.txt",
                 "groundstation.json5", "viewer.json5"):
        assert (out / name).stat().st_mode & 0o077 == 0, name
    for line in (out / "credentials.txt").read_text().splitlines():
        assert line.split(":", 1)[1] not in proc.stdout


def test_field_router_script_refuses_bad_files_and_serves_good_ones(kit):
    import signal

    router_script = SCRIPT.parent / "field-router"
    os.chmod(kit / "router.key", 0o644)
    bad = subprocess.run([sys.executable, str(router_script), str(kit / "router.json5")],
                         capture_output=True, text=True, timeout=60)
    assert bad.returncode == 2 and bad.stderr.count("\n") == 1 and "chmod 600" in bad.stderr
    os.chmod(kit / "router.key", 0o600)
    port = free_tcp_port()
    cfg = kit / "router.json5"
    cfg.write_text(cfg.read_text().replace("tls/0.0.0.0:7447", f"tls/127.0.0.1:{port}"))
    proc = subprocess.Popen([sys.executable, str(router_script), str(cfg)], stdout=subprocess.PIPE,
                            stderr=subprocess.PIPE, text=True)
    try:
        first = proc.stdout.readline()
        assert f"listening on tls/127.0.0.1:{port}" in first and "access control on" in first
        viewer = retarget(kit / "viewer.json5", kit / "v-local.json5", port)
        assert probe_endpoint(viewer) is None       # TLS with our client certificate works
    finally:
        proc.send_signal(signal.SIGINT)
        try:
            rc = proc.wait(30)
        except subprocess.TimeoutExpired:
            proc.kill()
            proc.wait()
            raise
        proc.stdout.close()
        proc.stderr.close()
    assert rc == 0


def test_weakened_router_configs_are_flagged(kit):
    p = kit / "router.json5"
    text = p.read_text()
    p.write_text(text.replace("enabled: true,\n    default_permission", "enabled: false,\n    default_permission")
                 .replace("enable_mtls: true", "enable_mtls: false"))
    warnings = " | ".join(check_zenoh_config(p).warnings)
    assert "access_control is disabled" in warnings and "enable_mtls is off" in warnings
    plain = kit / "plain.json5"
    plain.write_text('{mode: "router", listen: {endpoints: ["tcp/127.0.0.1:7447"]}}')
    assert any("neither encrypted nor authenticated" in w for w in check_zenoh_config(plain).warnings)
