"""The link to the flight controller: sans-IO MAVLink session, transports, .tlog recording and log readers.

Public API (import from the modules):

* :mod:`~firmware_interface.session` — ``MavlinkSession(SessionConfig(...), verifier=None, signer=None)``:
  ``receive_data(bytes, now)``, ``events()``, ``data_to_send(now)``, ``handle_timer(now)``,
  ``link_down(now, reason)``, ``stats`` (LinkStats), ``clock`` (host/FC offset and drift),
  ``stream_status``; ``check_outgoing(msg)`` (read-only allowlist). Pure: no IO, no clock.
* :mod:`~firmware_interface.codec` — ``Framer`` (MAVLink 1/2 framing with garbage/CRC accounting),
  ``check_frame``, ``frame_header``.
* :mod:`~firmware_interface.transports` — ``await open_link(url)`` for ``serial://PATH:BAUD``,
  ``pty://``, ``udpin://``, ``udpout://``, ``tcp://``; ``LinkDown`` and ``reconnect()``.
* :mod:`~firmware_interface.link` — ``LinkRunner(link, session, on_events).run()``: the async pump.
* :mod:`~firmware_interface.recorder` — ``Recorder(out_dir).handle(events)``: session .tlog plus
  ``flight-NN.tlog`` per armed interval, crash-safe.
* :mod:`~firmware_interface.readers` — ``load_log(path) -> LogData`` for .tlog, .bin, .px4log;
  ``build_logdata(events, ...)``, ``find_flights(series)``.
* :mod:`~firmware_interface.tlogread` — ``scan_tlog(bytes, TlogScan())``: tolerant record scanner.
* :mod:`~firmware_interface.samples` — the event dataclasses and ``LogData``;
  :mod:`~firmware_interface.errors` — ``LinkError`` (ValueError) and subclasses, ``TransportError``.
"""
