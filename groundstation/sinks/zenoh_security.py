"""Start-up checks for the secured zenoh network (TLS, mutual TLS, user/password, access control).

The security itself is configuration (``groundstation/configs/zenoh/*.json5``, rendered by
``scripts/make-field-certs``); zenoh enforces it. This module turns the ways a field setup goes
wrong into one clear line naming the file or endpoint, before or after ``zenoh.open``:

* :func:`check_zenoh_config` reads a json5 config with zenoh's own parser and checks what can be
  checked locally: certificate and key files present and readable, PEM that parses, certificates
  inside their validity window, leaf certificates signed by the configured CA, private keys that
  match their certificates and are not group/world-readable, user and password given together, the
  router's credentials dictionary well formed, access control enabled on a TLS router. It raises
  :class:`ZenohSecurityError` for the first problem and returns a :class:`SecuritySummary`.
* :func:`probe_endpoint` tries the transport under zenoh: TCP connect, then a TLS handshake with the
  configured CA and client certificate. It tells an unreachable router from a refused certificate.
* :func:`explain_open_failure` turns a failed ``zenoh.open`` into one line: the probe's finding, or,
  when TLS is fine, "the router refused the session" (wrong user/password or unknown user: the
  router cannot tell a client more without leaking which users exist).
* :class:`BackgroundConnector` opens a session in a thread and keeps retrying (with back-off) until
  it succeeds or is closed, reporting the first failure line once, so local recording never waits.

Leaves publishing to :mod:`groundstation.sinks.zenoh_sink` and the wiring to the service.
"""

from __future__ import annotations

import datetime as dt
import json
import os
import socket
import ssl
import stat
import threading
from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import zenoh
from cryptography import x509
from cryptography.exceptions import InvalidSignature
from cryptography.hazmat.primitives import serialization

from groundstation.errors import GroundstationError


class ZenohSecurityError(GroundstationError, ValueError):
    """The secured zenoh setup is wrong (one line naming the file, key or endpoint)."""


@dataclass(frozen=True)
class SecuritySummary:
    """What a checked zenoh config does (no secrets in it)."""

    path: str
    mode: str
    endpoints: tuple[str, ...]        # connect endpoints (client/peer) or listen endpoints (router)
    tls: bool                         # all endpoints are tls/
    mutual_tls: bool
    user: str | None                  # usrpwd user of a client; None for a router
    acl_enabled: bool
    not_after: dt.datetime | None     # earliest expiry of the certificates in the config (UTC)
    warnings: tuple[str, ...] = ()


def _one_line(text: object, limit: int = 200) -> str:
    s = " ".join(str(text).split())
    return s if len(s) <= limit else s[: limit - 1] + "…"


def _get(cfg: zenoh.Config, key: str) -> Any:
    return json.loads(cfg.get_json(key))


def load_zenoh_config(path: str | os.PathLike[str]) -> zenoh.Config:
    """Parse ``path`` with zenoh's own json5 parser; :class:`ZenohSecurityError` naming it if bad."""
    p = Path(path)
    if not p.is_file():
        raise ZenohSecurityError(f"{p}: zenoh config file not found")
    try:
        return zenoh.Config.from_file(str(p))
    except zenoh.ZError as exc:
        raise ZenohSecurityError(f"{p}: bad zenoh config: {_config_error(exc)}") from None


def _config_error(exc: BaseException) -> str:
    """zenoh's parse error in one line, without the config dump (it would print the password)."""
    text = _one_line(exc, 10_000)
    if "Invalid configuration" in text or "it is invalid" in text:
        return ("zenoh rejects a value in it (e.g. transport/auth/usrpwd user without password, "
                "or a TLS option without its file)")
    return _one_line(text.split("{", 1)[0] if text.count("{") > 3 else text, 160)


def _endpoints(cfg: zenoh.Config, section: str, mode: str) -> list[str]:
    eps = _get(cfg, f"{section}/endpoints")
    if isinstance(eps, dict):   # per-mode form {router: [...], peer: [...], client: [...]}
        eps = eps.get(mode, [])
    return [str(e) for e in (eps or [])]


def _private_file(path: Path, what: str, where: str) -> None:
    st = path.stat()
    if st.st_mode & (stat.S_IRWXG | stat.S_IRWXO):
        raise ZenohSecurityError(
            f"{where}: {what} {path} is accessible by group/others (mode {stat.S_IMODE(st.st_mode):o}); "
            f"run chmod 600 {path}"
        )


def _need_file(value: Any, key: str, where: str) -> Path:
    if not value:
        raise ZenohSecurityError(f"{where}: {key} is not set")
    p = Path(str(value))
    if not p.is_file():
        raise ZenohSecurityError(f"{where}: {key} file {p} not found")
    if not os.access(p, os.R_OK):
        raise ZenohSecurityError(f"{where}: {key} file {p} is not readable")
    return p


def _load_cert(path: Path, key: str, where: str) -> x509.Certificate:
    try:
        certs = x509.load_pem_x509_certificates(path.read_bytes())
    except ValueError as exc:
        raise ZenohSecurityError(f"{where}: {key} {path} is not a PEM certificate ({_one_line(exc, 80)})") from None
    return certs[0]


def _check_validity(cert: x509.Certificate, path: Path, where: str, now: dt.datetime) -> None:
    if now > cert.not_valid_after_utc:
        raise ZenohSecurityError(
            f"{where}: certificate {path} expired on {cert.not_valid_after_utc:%Y-%m-%d %H:%M} UTC; "
            f"make new ones with scripts/make-field-certs"
        )
    if now < cert.not_valid_before_utc:
        raise ZenohSecurityError(
            f"{where}: certificate {path} is not valid before {cert.not_valid_before_utc:%Y-%m-%d %H:%M} UTC "
            f"(is this computer's clock right?)"
        )


def _check_pair(cert_path: Path, key_path: Path, ca: x509.Certificate | None, ca_path: Path | None,
                where: str, now: dt.datetime, cert_key: str) -> x509.Certificate:
    cert = _load_cert(cert_path, cert_key, where)
    _check_validity(cert, cert_path, where, now)
    if ca is not None:
        try:
            cert.verify_directly_issued_by(ca)
        except (ValueError, TypeError, InvalidSignature):
            raise ZenohSecurityError(
                f"{where}: certificate {cert_path} is not signed by the CA {ca_path}"
            ) from None
    _private_file(key_path, "private key", where)
    try:
        key = serialization.load_pem_private_key(key_path.read_bytes(), password=None)
    except (ValueError, TypeError) as exc:
        raise ZenohSecurityError(
            f"{where}: private key {key_path} cannot be read ({_one_line(exc, 80)})"
        ) from None
    pub = key.public_key().public_bytes(serialization.Encoding.DER,
                                        serialization.PublicFormat.SubjectPublicKeyInfo)
    if pub != cert.public_key().public_bytes(serialization.Encoding.DER,
                                             serialization.PublicFormat.SubjectPublicKeyInfo):
        raise ZenohSecurityError(f"{where}: private key {key_path} does not match certificate {cert_path}")
    return cert


def _check_dictionary(path: Path, where: str) -> int:
    _private_file(path, "credentials file", where)
    n = 0
    for lineno, line in enumerate(path.read_text().splitlines(), start=1):
        if not line.strip():
            continue
        user, sep, pw = line.partition(":")
        if not sep or not user or not pw:
            raise ZenohSecurityError(
                f"{where}: credentials file {path} line {lineno} is not 'user:password'"
            )
        n += 1
    if n == 0:
        raise ZenohSecurityError(f"{where}: credentials file {path} holds no user")
    return n


def check_zenoh_config(path: str | os.PathLike[str], *, now: dt.datetime | None = None) -> SecuritySummary:
    """Check a zenoh json5 config for a secured field network; one-line error for the first problem.

    A config without any TLS setting (e.g. the loopback default) passes with a warning: security is
    opt-in per config file, and this function only judges what the file asks for.
    """
    where = str(path)
    cfg = load_zenoh_config(path)
    now = now or dt.datetime.now(dt.UTC)
    mode = str(_get(cfg, "mode") or "peer")
    section = "listen" if mode == "router" else "connect"
    endpoints = _endpoints(cfg, section, mode)
    if mode != "router":
        endpoints += [e for e in _endpoints(cfg, "listen", mode) if e not in endpoints]
    tls = _get(cfg, "transport/link/tls") or {}
    protocols = _get(cfg, "transport/link/protocols")
    usr = _get(cfg, "transport/auth/usrpwd") or {}
    acl = _get(cfg, "access_control") or {}
    warnings: list[str] = []

    uses_tls = any(e.startswith("tls/") for e in endpoints)
    plain = [e for e in endpoints if not e.startswith(("tls/", "quic/"))]
    if uses_tls and plain:
        raise ZenohSecurityError(f"{where}: plain endpoint(s) {plain} next to tls ones; use tls/ only")
    if protocols is not None and plain:
        bad = [e for e in plain if e.split("/", 1)[0] not in protocols]
        if bad:
            raise ZenohSecurityError(
                f"{where}: endpoint {bad[0]} uses a protocol not in transport/link/protocols {protocols}"
            )
    if mode == "client" and not endpoints:
        raise ZenohSecurityError(f"{where}: client config has no connect/endpoints (the router's address)")
    if not uses_tls:
        warnings.append(f"{where}: no tls/ endpoint: traffic is neither encrypted nor authenticated")

    mtls = bool(tls.get("enable_mtls"))
    not_after: list[dt.datetime] = []
    ca = None
    ca_path = None
    if uses_tls:
        ca_path = _need_file(tls.get("root_ca_certificate"), "transport/link/tls/root_ca_certificate", where)
        ca = _load_cert(ca_path, "root_ca_certificate", where)
        _check_validity(ca, ca_path, where, now)
        not_after.append(ca.not_valid_after_utc)
        if mode == "router" or tls.get("listen_certificate"):
            cert_path = _need_file(tls.get("listen_certificate"), "transport/link/tls/listen_certificate", where)
            key_path = _need_file(tls.get("listen_private_key"), "transport/link/tls/listen_private_key", where)
            c = _check_pair(cert_path, key_path, ca, ca_path, where, now, "listen_certificate")
            not_after.append(c.not_valid_after_utc)
        if mode != "router" and (mtls or tls.get("connect_certificate")):
            cert_path = _need_file(tls.get("connect_certificate"), "transport/link/tls/connect_certificate", where)
            key_path = _need_file(tls.get("connect_private_key"), "transport/link/tls/connect_private_key", where)
            c = _check_pair(cert_path, key_path, ca, ca_path, where, now, "connect_certificate")
            not_after.append(c.not_valid_after_utc)
        if mode == "router" and not mtls:
            warnings.append(f"{where}: enable_mtls is off: clients need no certificate")

    user = usr.get("user")
    password = usr.get("password")
    if bool(user) != bool(password):
        raise ZenohSecurityError(f"{where}: transport/auth/usrpwd needs both user and password")
    if mode == "router":
        dict_file = usr.get("dictionary_file")
        if dict_file:
            _check_dictionary(_need_file(dict_file, "transport/auth/usrpwd/dictionary_file", where), where)
        elif uses_tls:
            warnings.append(f"{where}: no usrpwd dictionary_file: any certificate holder may connect")
        if uses_tls and not acl.get("enabled"):
            warnings.append(f"{where}: access_control is disabled: any client may publish")
        user = None
    elif user and os.name == "posix":
        # the password sits in this file: it must not be readable by others
        _private_file(Path(path), "config with a password", where)

    return SecuritySummary(
        path=where, mode=mode, endpoints=tuple(endpoints), tls=uses_tls, mutual_tls=mtls,
        user=str(user) if user else None, acl_enabled=bool(acl.get("enabled")),
        not_after=min(not_after) if not_after else None, warnings=tuple(warnings),
    )


def _host_port(endpoint: str) -> tuple[str, int]:
    addr = endpoint.split("/", 1)[1].split("#", 1)[0].split("?", 1)[0]
    host, _, port = addr.rpartition(":")
    host = host.strip("[]")
    try:
        return host, int(port)
    except ValueError:
        raise ZenohSecurityError(f"endpoint {endpoint}: no port") from None


def probe_endpoint(path: str | os.PathLike[str], endpoint: str | None = None, *,
                   timeout_s: float = 2.0) -> str | None:
    """Try TCP and TLS to the router of client config ``path``; a one-line problem, or None if both work.

    ``None`` means the router is reachable and accepted our certificate: if the zenoh session still
    fails, the router refused the user/password (or the user is unknown to it).
    """
    cfg = load_zenoh_config(path)
    mode = str(_get(cfg, "mode") or "peer")
    eps = [endpoint] if endpoint else _endpoints(cfg, "connect", mode)
    if not eps:
        return f"{path}: no connect/endpoints to probe"
    tls = _get(cfg, "transport/link/tls") or {}
    problems = []
    for ep in eps:
        host, port = _host_port(ep)
        try:
            sock = socket.create_connection((host, port), timeout=timeout_s)
        except OSError as exc:
            problems.append(f"zenoh router {ep} unreachable ({exc.strerror or _one_line(exc, 60)})")
            continue
        if not ep.startswith("tls/"):
            sock.close()
            return None
        ctx = ssl.SSLContext(ssl.PROTOCOL_TLS_CLIENT)
        ctx.check_hostname = tls.get("verify_name_on_connect") is not False   # zenoh default: verify
        try:
            if tls.get("root_ca_certificate"):
                ctx.load_verify_locations(cafile=str(tls["root_ca_certificate"]))
            if tls.get("connect_certificate") and tls.get("connect_private_key"):
                ctx.load_cert_chain(str(tls["connect_certificate"]), str(tls["connect_private_key"]))
        except (OSError, ssl.SSLError) as exc:
            sock.close()
            return f"{path}: cannot load TLS files ({_one_line(exc, 100)})"
        try:
            with ctx.wrap_socket(sock, server_hostname=host) as tsock:
                tsock.settimeout(min(timeout_s, 0.3))
                # TLS 1.3: a rejected client certificate shows up on the first read, not the handshake
                try:
                    tsock.recv(1)
                except TimeoutError:
                    pass
            return None
        except ssl.SSLCertVerificationError as exc:
            problems.append(f"zenoh router {ep}: its certificate is not trusted by "
                            f"{tls.get('root_ca_certificate')} ({_one_line(exc.verify_message, 80)})")
        except (ssl.SSLError, OSError) as exc:
            reason = getattr(exc, "reason", None) or _one_line(exc, 80)
            problems.append(f"zenoh router {ep} refused the TLS session ({reason}): "
                            f"check {tls.get('connect_certificate') or 'the client certificate'}")
    return "; ".join(problems)


def explain_open_failure(path: str | os.PathLike[str], exc: BaseException | None = None) -> str:
    """One line for a ``zenoh.open`` that failed with client config ``path``."""
    problem = probe_endpoint(path)
    if problem:
        return problem
    cfg = load_zenoh_config(path)
    user = (_get(cfg, "transport/auth/usrpwd") or {}).get("user")
    eps = _endpoints(cfg, "connect", str(_get(cfg, "mode") or "peer"))
    who = f"user {user!r}" if user else "no user/password"
    return (f"zenoh router {', '.join(eps)} accepted the TLS certificate but refused the session "
            f"({who} from {path}): wrong password or user unknown to the router")


class BackgroundConnector:
    """Open a zenoh session from ``config_path`` in a thread, retrying until it works or is closed.

    ``on_session(session)`` runs once (on the connector thread) when a session is open;
    ``on_problem(line)`` runs for the first failure and whenever the failure reason changes.
    The caller owns the session it receives (closes it); :meth:`close` stops retrying.
    """

    def __init__(self, config_path: str | os.PathLike[str], on_session: Callable[[Any], None],
                 on_problem: Callable[[str], None], *, retry_initial_s: float = 0.5,
                 retry_max_s: float = 5.0) -> None:
        self.config_path = str(config_path)
        self._on_session = on_session
        self._on_problem = on_problem
        self._retry_initial_s = retry_initial_s
        self._retry_max_s = retry_max_s
        self._stop = threading.Event()
        self.connected = threading.Event()
        self.attempts = 0
        self.last_problem: str | None = None
        self._thread = threading.Thread(target=self._run, name="zenoh-connector", daemon=True)

    def start(self) -> BackgroundConnector:
        self._thread.start()
        return self

    def _run(self) -> None:
        delay = self._retry_initial_s
        while not self._stop.is_set():
            self.attempts += 1
            try:
                session = zenoh.open(load_zenoh_config(self.config_path))
            except zenoh.ZError as exc:
                try:
                    line = explain_open_failure(self.config_path, exc)
                except ZenohSecurityError as err:
                    line = str(err)
                if line != self.last_problem:
                    self.last_problem = line
                    self._on_problem(line)
                self._stop.wait(delay)
                delay = min(delay * 2.0, self._retry_max_s)
                continue
            except ZenohSecurityError as exc:
                if str(exc) != self.last_problem:
                    self.last_problem = str(exc)
                    self._on_problem(str(exc))
                self._stop.wait(delay)
                delay = min(delay * 2.0, self._retry_max_s)
                continue
            if self._stop.is_set():
                session.close()
                return
            self.connected.set()
            self._on_session(session)
            return

    def close(self, timeout_s: float = 5.0) -> None:
        self._stop.set()
        if self._thread.is_alive():
            self._thread.join(timeout_s)
