"""The link to the flight controller: sans-IO MAVLink session, transports, .tlog recording and log readers.

Public API (import from the modules):

* :mod:`~firmware_interface.session` — ``MavlinkSession(SessionConfig(...), verifier=None, signer=None)``:
  ``receive_data(bytes, now)``, ``events()``, ``data_to_send(now)``, ``handle_timer(now)``,
  ``link_down(now, reason)``, ``stats`` (LinkStats), ``clock`` (host/FC offset and drift),
  ``stream_status``; ``check_outgoing(msg)`` (read-only allowlist). Pure: no IO, no clock.
* :mod:`~firmware_interface.codec` — ``Framer`` (MAVLink 1/2 framing with garbage/CRC accounting),
  ``check_frame``, ``frame_header``.
* :mod:`~firmware_interface.transports` — ``await open_link(url)`` for ``serial://PATH:BAUD``,
  ``pty://``, ``udpin://``, ``udpout://``, ``tcp://``; the ``Link`` protocol; ``LinkDown``,
  ``PortMissing``; ``ScriptedLink`` (in-memory link for tests).
* :mod:`~firmware_interface.link` — ``LinkRunner(opener, session, on_events).run()``: the link driver
  (waits for a port not plugged in yet, reconnects with backoff; clock and sleep injected).
* :mod:`~firmware_interface.recorder` — ``Recorder(out_dir).handle(events)``: session .tlog plus
  ``flight-NN.tlog`` per armed interval, crash-safe.
* :mod:`~firmware_interface.readers` — ``load_log(path) -> LogData`` for .tlog, .bin, .px4log, .ulg;
  ``build_logdata(events, ...)``, ``find_flights(series)``, ``restrict_to_chirps(log)`` (SYSID chirps);
  :mod:`~firmware_interface.ulog` (pyulog) and :mod:`~firmware_interface.dfcolumns` (DFReader's index,
  decoded a record type at a time) behind it.
* :mod:`~firmware_interface.logdownload` — sans-IO onboard-log download: ``LogLister``,
  ``LogDownloader`` (block map, bounded gap re-requests, resume, second copies on a corrupting link,
  ``DownloadCheck``); pure. :mod:`~firmware_interface.logcheck` — ``record_breaks(data)``: where a
  dataflash or ULog record chain breaks.
* :mod:`~firmware_interface.logtransfer` — ``LogTransfer(opener)``: list and download over a live link;
  ``write_verified``, ``unverified_path``, ``save_partial``, ``load_partial``.
* :mod:`~firmware_interface.tlogread` — ``scan_tlog(bytes, TlogScan())``: tolerant record scanner.
* :mod:`~firmware_interface.samples` — the event dataclasses and ``LogData``;
  :mod:`~firmware_interface.errors` — ``FirmwareInterfaceError``, the base of ``LinkError`` (ValueError)
  and its subclasses and of ``TransportError`` (OSError).
"""
