"""The live ground-station service: asyncio wiring of link, session, recorder, live DSP and sinks.

One :class:`Service` per run, one ``asyncio.TaskGroup``:

* ``link``      -- the link driver :class:`firmware_interface.link.LinkRunner` (the same one
  ``groundstation record`` runs): reads the link, feeds the
  :class:`firmware_interface.session.MavlinkSession`, sends what it wants to send (heartbeats, stream
  requests), reopens a lost link with backoff (a USB cable pulled and plugged back). Each batch of
  events goes to the :class:`firmware_interface.recorder.Recorder` first (recording never depends on
  anything after it), then to :class:`groundstation.dsp.live.LivePipeline`; windows to zenoh, rows to
  Rerun (both through their own threads: the loop never blocks on a sink). The in-air rows of the
  current flight also feed :class:`groundstation.dsp.excitation.ExcitationMonitor` (its transforms and
  verdicts run half a hop after a window went out), whose verdict (is each axis excited enough yet?)
  goes to zenoh, Rerun and the status about once per FC second while armed. Reading waits while a batch is processed: back-pressure onto the link, nothing dropped;
* ``timer``     -- recorder flushes, the status record at ``status_rate_hz``;
* ``stopper``   -- waits for Ctrl-C/SIGTERM, ``exit_after_flights`` or :meth:`Service.request_stop`.

On disarm (a flight ends) the flight's .tlog is handed to :func:`groundstation.worker.run_job` in a
``ProcessPoolExecutor(max_workers=1)`` with the spawn context, one job at a time (later flights wait
in the service's queue, so a worker that dies loses only the job it was running); its result (model,
gap report) is published on zenoh and logged to Rerun when it comes back. A serial port that is not
there yet is waited for before all this starts ("waiting for /dev/ttyUSB0"; Ctrl-C ends the wait).
Shutdown closes the recorder first, then kills the worker, then closes the sinks and the link: well
within 2 s.

The numbers are computed elsewhere (``dsp``, ``sysid``, ``gap``); this module only wires.
"""

from __future__ import annotations

import asyncio
import concurrent.futures
import concurrent.futures.process
import dataclasses
import functools
import math
import multiprocessing
import os
import signal
import time
from collections import deque
from collections.abc import Awaitable, Callable
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np
from threadpoolctl import threadpool_limits

from firmware_interface.errors import LinkError
from firmware_interface.link import LinkRunner
from firmware_interface.recorder import Recorder
from firmware_interface.samples import (
    FcRebooted,
    Heartbeat,
    Imu,
    LinkLost,
    LinkRestored,
    RawPacket,
)
from firmware_interface.session import MavlinkSession
from firmware_interface.signing import SigningConfig, session_hooks
from firmware_interface.transports import open_link
from groundstation.config import ServiceConfig
from groundstation.dsp.excitation import ExcitationMonitor, ExcitationReport
from groundstation.dsp.live import FlightEnded, FlightStarted, LivePipeline, RateMeter, Window
from groundstation.onboard import OnboardLogs, analyse_onboard, link_kind
from groundstation.pipeline import with_aircraft_file
from groundstation.sinks.background import BackgroundCalls
from groundstation.sinks.zenoh_sink import ZenohSink, ZenohSinkError
from groundstation.worker import IdentifyJob, JobResult, run_job


class _Stop(Exception):
    """Raised inside the TaskGroup to end the run cleanly."""


class _Stopped(Exception):
    """Stopped before the link ever opened (Ctrl-C while waiting for the port)."""


@dataclass
class IdentState:
    state: str = "idle"            # idle | running | done | failed | off
    flight: int | None = None
    queued: int = 0
    done: int = 0
    failed: int = 0
    last_error: str | None = None
    last_seconds: float | None = None
    last_data: str | None = None    # what the last published result came from: telemetry or onboard_log


@dataclass
class RunReport:
    """What the run did (returned by :meth:`Service.run`, printed by the commands)."""

    record_dir: str
    session_tlog: str | None = None
    flight_tlogs: list[str] = field(default_factory=list)
    results: list[JobResult] = field(default_factory=list)
    rrd: str | None = None
    campaign_db: str | None = None      # the per-flight table, once a flight is in it
    zenoh_endpoint: str = ""
    packets: int = 0
    packets_lost: int = 0
    bad_crc: int = 0
    windows_published: int = 0
    windows_dropped: int = 0
    flights: int = 0
    warnings: list[str] = field(default_factory=list)
    stopped_by: str = ""


class Service:
    """The live service.

    Parameters
    ----------
    config : the whole service configuration
    log : one-line messages for the operator (default ``print``)
    sim_options : extra keyword arguments for the built-in simulator's ``SimulatedSession``
    fc_config : :class:`hil_replay.fc.FcConfig` for the built-in simulator (faults in tests)
    frame_source : replaces the built-in simulator's helicopter (anything with ``frames()``)
    link_opener : ``async () -> Link`` instead of opening ``link.url`` (tests: a
        :class:`firmware_interface.transports.ScriptedLink`)
    job_fn : the picklable function the worker process runs per job (default
        :func:`groundstation.worker.run_job`; tests give one that blocks until killed)
    """

    def __init__(self, config: ServiceConfig, *, log: Callable[[str], None] = print,
                 sim_options: dict[str, Any] | None = None, fc_config: Any = None,
                 frame_source: Any = None, job_fn: Callable[[IdentifyJob], Any] = run_job,
                 link_opener: Callable[[], Awaitable[Any]] | None = None) -> None:
        self.frame_source = frame_source
        self.link_opener = link_opener
        self.runner: Any = None              # firmware_interface.link.LinkRunner
        self.job_fn = job_fn

        config = with_aircraft_file(config)[0]   # one configuration: the live path uses the aircraft's channel map too
        self.config = config
        self.log = log
        self.sim_options = sim_options
        self.fc_config = fc_config
        self.vehicle = config.service.vehicle
        self.record_dir = Path(config.service.record_dir)
        self.report = RunReport(record_dir=str(self.record_dir))
        self.ident = IdentState(state="idle" if config.identification.enabled else "off")
        self.ready = asyncio.Event()
        self.sim: Any = None                 # hil_replay.fc.SimulatedFCThread when built in
        self.link_url = config.link.url
        self.link: Any = None
        self.link_up = False
        self.session: Any = None
        self.signing: Any = None             # firmware_interface.signing.SignatureVerifier when signed
        self.recorder: Any = None
        self.zenoh: Any = None
        self.rerun: Any = None
        self._rerun_calls: BackgroundCalls | None = None
        self.live = LivePipeline(config.live)     # its channel map and trim are [prepare]'s
        self.rates = RateMeter(2.0)
        self._stop = asyncio.Event()
        self._stop_reason = ""
        self._executor: concurrent.futures.ProcessPoolExecutor | None = None
        self._pending: set[asyncio.Future[Any]] = set()        # submitted jobs without a result yet
        self._queue: deque[tuple[IdentifyJob, asyncio.Future[Any]]] = deque()   # waiting for the worker
        self._running: asyncio.Future[Any] | None = None        # the executor's future of the running job
        self._flight_tlogs: dict[int, str] = {}
        self._jobs: dict[int, IdentifyJob] = {}     # each flight's job, for its onboard log's analysis
        self._rows_buf: list[tuple[np.ndarray, ...]] = []
        self._sm_buf: list[tuple[np.ndarray, np.ndarray, np.ndarray]] = []
        self._rerun_state = ""
        self.flights_completed = 0
        self.link_drops = 0
        #: link quality of the last flight identified (loss, holes, windows kept with holes), for the status
        self.last_flight_link: dict[str, Any] | None = None
        self._link_at_arm: tuple[int, int] = (0, 0)   # (packets, lost) when the current flight armed
        self.live_errors = 0
        self.packets = 0
        self.window_seq_published = 0
        self.on_window: Callable[[Window], None] | None = None     # test/bench hook (loop thread)
        ex = config.excitation
        # the monitor also accumulates the flight with [freq]'s settings for the after-flight frequency check
        self.excitation = (ExcitationMonitor(ex, 1.0 / config.live.grid_rate_hz,
                                             freq=config.freq if config.identification.enabled else None)
                           if ex.enabled else None)
        self._excite_window_row = 0          # live row count at the last window / the monitor's last step
        self._excite_step_row = 0
        self.excitation_last: ExcitationReport | None = None
        self.on_excitation: Callable[[ExcitationReport], None] | None = None   # test hook (loop thread)
        self.onboard: Any = None             # groundstation.onboard.OnboardLogs when [onboard_logs] download
        self._onboard_busy = False

    # ------------------------------------------------------------------ control

    def request_stop(self, reason: str = "requested") -> None:
        if not self._stop.is_set():
            self._stop_reason = reason
            self._stop.set()
        if self.runner is not None:
            self.runner.stop()

    # ------------------------------------------------------------------ setup

    def _open_recorder(self) -> None:
        try:
            self.record_dir.mkdir(parents=True, exist_ok=True)
            probe = self.record_dir / ".write-test"
            probe.write_bytes(b"")
            probe.unlink()
        except OSError as exc:
            raise OSError(f"{self.record_dir}: record directory not writable ({exc.strerror or exc})") from None
        self.recorder = Recorder(self.record_dir)
        self.report.session_tlog = str(getattr(self.recorder, "session_path", "") or "") or None

    def _open_sinks(self, loop: asyncio.AbstractEventLoop) -> None:
        zc = self.config.zenoh
        if zc.enabled:
            try:
                self.zenoh = ZenohSink(self.vehicle, config_path=zc.config_file or None,
                                       listen_port=zc.listen_port, window_queue=zc.window_queue, loop=loop)
                self.report.zenoh_endpoint = self.zenoh.endpoint
                if self.zenoh.error:    # a security problem or no router yet: one line, retried in background
                    self._warn(self.zenoh.error + " (recording goes on)")
            except ZenohSinkError as exc:
                self._warn(f"{exc}; running without zenoh (recording goes on)")
        rc = self.config.rerun
        if rc.mode != "off":
            # here, not at the top: the sink imports rerun (about 0.6 s of CPU), which a service without
            # a Rerun viewer or file never needs
            from groundstation.sinks.rerun_sink import RerunSink, RerunSinkError

            try:
                self.rerun = RerunSink(self.vehicle, rc.mode, rc.target, raw=rc.raw)
                self._rerun_calls = BackgroundCalls("rerun-logger", maxsize=256)
                if rc.mode == "save":
                    self.report.rrd = rc.target
            except RerunSinkError as exc:
                self._warn(f"{exc}; running without Rerun (recording goes on)")

    def _start_builtin_sim(self) -> str:
        # here, not at the top: the simulator (with scipy.linalg, about 0.5 s) runs only without a link
        from hil_replay.fc import FcConfig, SimulatedFCThread

        sc = self.config.sim
        fc_config = self.fc_config
        if fc_config is None and self.config.onboard_logs.download:
            fc_config = FcConfig(seed=sc.seed, record_dataflash=True)   # an onboard log to download
        self.sim = SimulatedFCThread(speed=sc.speed, seed=sc.seed, flights=sc.flights, effects=sc.effects,
                                     config=fc_config, sim_options=self.sim_options,
                                     session=self.frame_source)
        self.sim.start()
        return f"serial://{self.sim.port_path}:{self.config.link.baud}"

    def _make_runner(self) -> Any:
        opener = self.link_opener or functools.partial(open_link, self.link_url)
        return LinkRunner(opener, self.session, self._on_events, tick_s=0.05, backoff_s=0.1, backoff_max_s=1.0,
                          log=self.log, on_link_up=self._on_link_up, on_link_down=self._on_link_down)

    def _warn(self, msg: str) -> None:
        self.report.warnings.append(msg)
        self.log(f"warning: {msg}")

    # ------------------------------------------------------------------ run

    async def run(self) -> RunReport:
        """Run until stopped; returns the report. Raises OSError/ValueError for bad input (one line)."""
        loop = asyncio.get_running_loop()
        installed = self._install_signals(loop)      # first: Ctrl-C during start-up is a clean stop too
        try:
            self._open_recorder()
            if self.config.prepare.input_source != "SERVO_OUTPUT_RAW":
                self._warn(f"prepare.input_source = {self.config.prepare.input_source}: identification uses it; "
                           "the live inputs are read from SERVO_OUTPUT_RAW")
            try:
                lk = self.config.link
                self.signing, signer = session_hooks(
                    SigningConfig(lk.signing_key_file, lk.signing_link_id, lk.signing_accept_unsigned), time.time())
                self.session = MavlinkSession(verifier=self.signing, signer=signer)
                ob = self.config.onboard_logs
                if ob.download or ob.analyse != "off":
                    self.onboard = OnboardLogs(ob, Path(ob.dir) if ob.dir else self.record_dir / "onboard",
                                               self.session, self.log, on_log=self._analyse_onboard_log)
                self._open_sinks(loop)
                if self.config.identification.enabled:
                    self._executor = self._new_executor()
                if not self.link_url and self.link_opener is None:
                    self.link_url = self._start_builtin_sim()
                    self.log(f"built-in simulated flight controller on {self.sim.port_path} "
                             f"(speed {self.config.sim.speed:g}x, {self.config.sim.flights} flight(s))")
                self.runner = self._make_runner()
                # a port not plugged in yet is waited for ("waiting for PATH"); Ctrl-C ends the wait
                if await self.runner.connect() is None:
                    raise _Stopped
                try:
                    async with asyncio.TaskGroup() as tg:
                        tg.create_task(self._run_link(), name="link")
                        tg.create_task(self._timer(), name="timer")
                        tg.create_task(self._stopper(), name="stopper")
                except* _Stop:
                    pass
            except _Stopped:
                pass
            finally:
                await self._shutdown()
        finally:
            for sig in installed:
                loop.remove_signal_handler(sig)
        self.report.stopped_by = self._stop_reason
        return self.report

    def _new_executor(self) -> concurrent.futures.ProcessPoolExecutor:
        return concurrent.futures.ProcessPoolExecutor(
            max_workers=1, mp_context=multiprocessing.get_context("spawn"), initializer=_worker_init,
            initargs=(self.config.service.worker_nice,))

    def _install_signals(self, loop: asyncio.AbstractEventLoop) -> list[int]:
        installed: list[int] = []
        for sig in (signal.SIGINT, signal.SIGTERM):
            try:
                loop.add_signal_handler(sig, self.request_stop, signal.Signals(sig).name)
                installed.append(sig)
            except (NotImplementedError, RuntimeError, ValueError):   # not the main thread
                pass
        return installed

    async def _stopper(self) -> None:
        await self._stop.wait()
        raise _Stop

    # ------------------------------------------------------------------ link

    def _on_link_up(self, link: Any) -> None:
        self.link, self.link_up = link, True
        self.link_url = getattr(link, "url", self.link_url)
        if not self.ready.is_set():
            self.log(f"link {self.link_url} open; recording to {self.record_dir}")
            self.ready.set()
        else:
            self.log(f"link {self.link_url} reopened")

    def _on_link_down(self, reason: str) -> None:
        self.link = None
        self.link_drops += 1
        self.link_up = False
        self.log(f"link lost ({reason[:200]}); reconnecting")

    async def _run_link(self) -> None:
        assert self.runner is not None
        await self.runner.run()
        if not self._stop.is_set():             # the runner only returns when stopped
            self.request_stop("link driver ended")

    async def _timer(self) -> None:
        period = 0.05
        status_every = 1.0 / self.config.service.status_rate_hz
        next_status = time.monotonic()
        while not self._stop.is_set():
            if self.onboard is not None:
                self.onboard.tick(time.time())   # its requests leave with the link driver's next tick
                if self._onboard_busy and not self.onboard.busy:
                    self._check_exit()   # the download (and its file) finished since the last tick
                self._onboard_busy = self.onboard.busy
            tick = getattr(self.recorder, "tick", None)
            if tick is not None:
                tick()
            if time.monotonic() >= next_status:
                next_status += status_every
                if next_status < time.monotonic():
                    next_status = time.monotonic() + status_every
                self._publish_status()
            await asyncio.sleep(period)

    # ------------------------------------------------------------------ processing

    def _on_events(self, events: list[Any]) -> None:
        """A batch of session events from the link driver (on the loop)."""
        self.recorder.handle(events)          # recording first, before anything that could fail
        now = time.time()
        if self.onboard is not None:
            self.onboard.on_events(events, now)
        try:
            self._live(events, now)
        except Exception as exc:  # a live-path bug must never stop the recording: count, warn once
            self.live_errors += 1
            if self.live_errors == 1:
                self._warn(f"live path: {type(exc).__name__}: {exc} (recording goes on)".splitlines()[0])

    def _live(self, events: list[Any], now: float) -> None:
        mon_events = []            # what the excitation monitor reads besides the rows
        for ev in events:
            if isinstance(ev, RawPacket):
                self.packets += 1
                self.rates.add(ev.msg_type, now)
            elif isinstance(ev, Imu | Heartbeat):
                mon_events.append(ev)
            elif isinstance(ev, LinkLost):
                self.link_up = False
                self._rerun_event(f"link lost: {ev.reason}", "WARN")
            elif isinstance(ev, LinkRestored):
                self.link_up = True
                self._rerun_event("link restored", "INFO")
            elif isinstance(ev, FcRebooted):
                self._rerun_event("flight controller rebooted", "WARN")
        out = self.live.feed(events)
        self._rerun_flight_state()
        if len(out.t_fc_s):
            self._rows_buf.append((out.t_fc_s, out.t_host_s, out.inputs, out.outputs_raw))
        if len(out.t_smoothed_s):
            self._sm_buf.append((out.t_smoothed_s, out.t_host_smoothed_s, out.outputs_smoothed))
        for w in out.windows:
            self._on_window(w)
        if self.excitation is not None:
            self._excite(mon_events, out)
        for fe in out.flight_events:
            self._on_flight_event(fe)

    def _excite(self, events: list[Any], out: Any) -> None:
        """Feed the excitation monitor. Rows are only gathered here; the transforms and the verdict run
        half a hop after a window went out, so that a window never waits for them."""
        mon = self.excitation
        assert mon is not None
        for fe in out.flight_events:
            if isinstance(fe, FlightStarted):
                mon.flight_started(fe.flight, fe.t_fc_s)
        if events:
            mon.events(events)
        if mon.flight is None:
            return
        ft = self.live.flights
        if len(out.t_fc_s):
            mon.rows(out.t_fc_s, out.inputs, out.outputs_raw, armed=ft.armed, in_air=ft.in_air, work=False,
                     measured=out.outputs_measured)
        rows, hop = self.live.rows, self.live.windows.hop
        if out.windows:
            self._excite_window_row = rows
        # half a hop after the last window; in a fast replay (a window in every batch) every two hops
        if (rows - self._excite_window_row >= max(1, hop // 2) and rows - self._excite_step_row >= hop) \
                or rows - self._excite_step_row >= 2 * hop:
            self._excite_step_row = rows
            rep = mon.step()
            if rep is not None:
                self._publish_excitation(rep, False)
        for fe in out.flight_events:
            if isinstance(fe, FlightEnded):
                last = mon.flight_ended()
                if last is not None:
                    self._publish_excitation(last, True)

    def _publish_excitation(self, rep: ExcitationReport, final: bool) -> None:
        if self.zenoh is not None:
            self.zenoh.publish_excitation(functools.partial(_excitation_doc, self.vehicle, rep, final))
        if self.rerun is not None and self._rerun_calls is not None:
            self._rerun_calls.submit(self.rerun.log_excitation, rep)
        self._on_excitation(rep, final)

    def _on_excitation(self, rep: ExcitationReport, final: bool) -> None:
        """A verdict, on the loop: the status, a line per axis that has just become enough and one with
        the whole verdict at the end of the flight."""
        before = self.excitation_last.enough_at_s if self.excitation_last is not None and \
            self.excitation_last.flight == rep.flight else {}
        self.excitation_last = rep
        for axis, t in rep.enough_at_s.items():
            if axis not in before:
                self.log(f"flight {rep.flight}: {rep.axes[axis].line()} at {t:.0f} s")
        if final:
            self.log(rep.line())
        if self.on_excitation is not None:
            self.on_excitation(rep)

    def _on_window(self, w: Window) -> None:
        if self.zenoh is not None:
            # the JSON is built on the publisher thread, not here on the loop
            doc = functools.partial(w.to_json, self.vehicle)
            if self.zenoh.publish_window(doc, seq=w.seq, t_host_last_s=w.t_host_last_s):
                self.window_seq_published += 1
        self._flush_rows_to_rerun()
        if self.on_window is not None:
            self.on_window(w)

    def _close_rerun(self) -> None:
        """Close the Rerun sink on its own logger thread, after every call already queued: closing it
        from here while that thread still logs a result raced it (under load a saved .rrd lost its
        blueprint). A file is given time to be finished; a live viewer at most 0.5 s."""
        if self.rerun is None:
            return
        calls, sink = self._rerun_calls, self.rerun
        if calls is None:
            calls = BackgroundCalls("rerun-close", maxsize=1)
        budget_s = 10.0 if sink.mode == "save" else 0.5
        errors: list[str] = []

        def close() -> None:
            try:
                sink.close()
            except Exception as exc:  # a viewer gone at exit must not stop the shutdown
                errors.append(f"closing Rerun: {type(exc).__name__}: {exc}")

        queued = calls.submit(close)
        if not calls.close(budget_s):
            self._warn(f"closing Rerun: the logger did not finish within {budget_s:g} s")
        elif not queued:              # the queue was full: the thread has ended now, close from here
            close()
        for e in errors:
            self._warn(e)

    def _flush_rows_to_rerun(self) -> None:
        if self.rerun is not None and self._rerun_calls is not None:
            if self._rows_buf:
                cols = [np.concatenate([r[i] for r in self._rows_buf]) for i in range(4)]
                self._rerun_calls.submit(self.rerun.log_rows, cols[0], cols[1], cols[2], cols[3], "raw")
            if self._sm_buf:
                ts, th, ys = (np.concatenate([r[i] for r in self._sm_buf]) for i in range(3))
                self._rerun_calls.submit(self.rerun.log_rows, ts, th, None, ys, "smoothed")
        self._rows_buf.clear()
        self._sm_buf.clear()

    def _rerun_flight_state(self) -> None:
        if self.rerun is None or self._rerun_calls is None:
            return
        ft = self.live.flights
        state = "in air" if ft.in_air else "armed" if ft.armed else "on ground"
        if state != self._rerun_state:
            self._rerun_state = state
            newest = self.live.aligner.newest_t_fc_s
            if math.isfinite(newest):
                self._rerun_calls.submit(self.rerun.log_flight_state, state, float(newest))

    def _rerun_event(self, text: str, level: str) -> None:
        if self.rerun is not None and self._rerun_calls is not None:
            newest = self.live.aligner.newest_t_fc_s
            t = float(newest) if math.isfinite(newest) else 0.0
            self._rerun_calls.submit(self.rerun.log_event, text, t, level)

    # ------------------------------------------------------------------ flights

    def _on_flight_event(self, fe: FlightStarted | FlightEnded) -> None:
        if isinstance(fe, FlightStarted):
            self._link_at_arm = self._link_counts()
            self.log(f"flight {fe.flight}: armed at FC {fe.t_fc_s:.1f} s")
            self._rerun_event(f"flight {fe.flight} armed", "INFO")
            return
        self.flights_completed += 1
        self.report.flights = self.flights_completed
        path = self._last_flight_tlog()
        if path:
            self._flight_tlogs[fe.flight] = path
            self.report.flight_tlogs.append(path)
        held = f"after {fe.duration_s:.1f} s" if math.isfinite(fe.duration_s) else "(no FC time seen while armed)"
        self.log(f"flight {fe.flight}: disarmed {held}; recorded {path or '(no file)'}")
        analyse = self._suggest_onboard_log(fe.flight)
        if self.onboard is not None and (analyse or self.config.onboard_logs.download):
            self.onboard.flight_ended(time.time(), fe.flight, analyse)
        self._rerun_event(f"flight {fe.flight} disarmed {held}", "INFO")
        if self.rerun is not None and self._rerun_calls is not None:
            self._flush_rows_to_rerun()
            self._rerun_calls.submit(self.rerun.flight_ended, fe.flight, fe.t_fc_s - fe.duration_s, fe.t_fc_s)
        if self._executor is not None and path:
            ic = self.config.identification
            tlogs = (tuple(self._flight_tlogs[k] for k in sorted(self._flight_tlogs)) if ic.scope == "all"
                     else (path,))
            prev = [k for k in sorted(self._flight_tlogs) if k < fe.flight]
            live = self.excitation.take_freq_spectra(fe.flight) if self.excitation is not None else None
            job = IdentifyJob(flight=fe.flight, tlogs=tlogs, out_dir=str(Path(path).parent), config=self.config,
                              previous_flight=prev[-1] if prev else -1,
                              previous_tlogs=(self._flight_tlogs[prev[-1]],) if prev else (),
                              live_spectra=live if len(tlogs) == 1 else None)
            self._jobs[fe.flight] = dataclasses.replace(job, live_spectra=None)
            self.submit_identification(job)
        self._check_exit()

    def submit_identification(self, job: IdentifyJob) -> asyncio.Future[JobResult]:
        """Queue ``job`` for the worker process (call on the loop); the result is published when done.

        The worker runs one job at a time; the returned future resolves to the job's
        :class:`JobResult` (a worker that died is a result with ``error``, never an exception)."""
        if self._executor is None:
            raise RuntimeError("identification is disabled in this service")
        fut: asyncio.Future[JobResult] = asyncio.get_running_loop().create_future()
        self._pending.add(fut)
        self._queue.append((job, fut))
        self.ident.queued += 1
        self.ident.state = "running"
        fut.add_done_callback(self._on_result)
        self._dispatch()
        return fut

    def _dispatch(self) -> None:
        """Hand the next queued job to the worker when it is free."""
        if self._running is not None or not self._queue or self._executor is None:
            return
        job, fut = self._queue.popleft()
        try:
            cfut = self._executor.submit(self.job_fn, job)
        except concurrent.futures.process.BrokenProcessPool:
            # the worker died (killed, out of memory): start a new one for this and later flights
            self._warn("identification worker died; starting a new one")
            self._executor.shutdown(wait=False, cancel_futures=True)
            self._executor = self._new_executor()
            cfut = self._executor.submit(self.job_fn, job)
        self.ident.flight = job.flight
        self._running = asyncio.wrap_future(cfut)
        self._running.add_done_callback(functools.partial(self._job_done, job, fut))

    def _job_done(self, job: IdentifyJob, fut: asyncio.Future[JobResult], inner: asyncio.Future[Any]) -> None:
        self._running = None
        if not fut.done():
            if inner.cancelled():
                fut.cancel()
            elif (exc := inner.exception()) is not None:     # the worker died (killed, out of memory)
                fut.set_result(JobResult(flight=job.flight, tlogs=job.tlogs,
                                         error=f"flight {job.flight}: worker: {type(exc).__name__}: {exc}".splitlines()[0]))
            else:
                fut.set_result(inner.result())
        self._dispatch()

    def _last_flight_tlog(self) -> str | None:
        rec = self.recorder
        for name in ("last_flight_path", "flight_paths"):
            v = getattr(rec, name, None)
            if callable(v):
                v = v()
            if isinstance(v, list | tuple):
                v = v[-1] if v else None
            if v:
                return str(v)
        return None

    def _on_result(self, fut: asyncio.Future[JobResult]) -> None:
        self._pending.discard(fut)
        self.ident.queued -= 1
        if fut.cancelled():
            return
        res = fut.result()
        # the report keeps the outcome; the arrays for the live plots go to Rerun only
        self.report.results.append(dataclasses.replace(res, overlay=None, gap_pictures=None))
        if res.error is not None:
            self.ident.failed += 1
            self.ident.state = "failed" if not self._pending else "running"
            self.ident.last_error = res.error
            self._warn(f"identification: {res.error}")
        else:
            self.ident.done += 1
            self.ident.state = "done" if not self._pending else "running"
            self.ident.last_seconds = res.seconds
            self._publish_result(res)
        if self.rerun is not None and self._rerun_calls is not None:
            overlay = None if res.overlay is None else {
                "t_fc_s": res.overlay.t_fc_s, "model": res.overlay.model, "measured": res.overlay.measured}
            self._rerun_calls.submit(self.rerun.log_result, res, overlay, res.gap_pictures)
        self._check_exit()

    def _publish_result(self, res: JobResult) -> None:
        """A new model (and gap report): log, live trim, zenoh, Rerun."""
        flight, model, gap = res.flight, res.model or {}, res.gap
        table = " ".join(f"{k}={v:.1f}" for k, v in res.match_degree.items())
        onboard = res.data == "onboard_log"
        self.ident.last_data = res.data
        whence = " from the onboard log, replacing the telemetry's" if onboard else ""
        self.log(f"flight {flight}: model {res.model_path} ({res.seconds:.1f} s){whence}; match % on this flight {table}")
        line = cross_flight_line(flight, (model.get("fit") or {}).get("cross_flight") or {})
        if line:
            self.log(line)
        lq = (model.get("source") or {}).get("link_quality") or {}
        if lq and not onboard:        # the status keeps the link's figures, not the onboard log's
            self.last_flight_link = {"flight": flight, **lq}
            if lq.get("in_air_holes"):
                self.log(f"flight {flight}: link lost {lq.get('loss_pct') or 0:.1f} % of packets, {lq['in_air_holes']} "
                         f"holes in the air (longest {lq.get('longest_gap_s', 0):.2f} s); "
                         f"{lq.get('windows_with_holes', 0)}/{lq.get('windows', 0)} windows kept with holes")
        trim = model.get("input_trim_pwm") or {}
        if self.config.prepare.input_trim_pwm is None and all(k in trim for k in ("lat", "lon", "col", "ped")):
            self.live.set_trim((float(trim["lat"]), float(trim["lon"]), float(trim["col"]), float(trim["ped"])))
        if self.zenoh is not None:
            self.zenoh.publish_model(flight, model)
            if gap is not None:
                self.zenoh.publish_gap(flight, gap)
            if res.freq is not None:
                self.zenoh.publish_freq(flight, res.freq)
            if res.trends is not None:
                self.zenoh.publish_trends(res.trends)
            if res.report_path is not None:
                self.zenoh.publish_report(flight, {"vehicle": self.vehicle, "flight": flight, "path": res.report_path,
                                                   "summary": res.report_summary})
        if res.trends is not None:
            self.report.campaign_db = str(Path(res.model_path or "").parent / self.config.service.campaign_db)
        if res.freq is not None:
            ja = res.freq.get("J_avg")
            self.log(f"flight {flight}: frequency check {res.freq_path} J_avg "
                     f"{'-' if ja is None else f'{ja:.1f}'} over {len(res.freq.get('pairs', []))} pairs")
        if res.freq_error:
            self._warn(res.freq_error)
        if res.trends_error:
            self._warn(res.trends_error)
        if gap is not None:
            self.log(f"flight {flight}: gap report {res.gap_path} verdict {gap.get('verdict')}")
        if res.report_path is not None:
            self.log(f"flight {flight}: report {res.report_path}: {res.report_summary}")
        if res.report_error:
            self._warn(res.report_error)
        if res.gap_error:
            self._warn(res.gap_error)

    def _link_counts(self) -> tuple[int, int]:
        """(packets received, packets lost) on the link so far."""
        stats = getattr(self.session, "stats", None)
        return int(getattr(stats, "packets", 0) or 0), int(getattr(stats, "packets_lost", 0) or 0)

    def _suggest_onboard_log(self, flight: int) -> bool:
        """One line when the flight's telemetry lost more than ``[onboard_logs] suggest_above_loss_pct``;
        True when its onboard log is to be downloaded and analysed instead (``[onboard_logs] analyse``
        over this kind of link, :func:`groundstation.onboard.link_kind`)."""
        (p0, l0), (p1, l1) = self._link_at_arm, self._link_counts()
        got, lost = p1 - p0, l1 - l0
        ob = self.config.onboard_logs
        if got + lost <= 0 or 100.0 * lost / (got + lost) <= ob.suggest_above_loss_pct:
            return False

        pct = 100.0 * lost / (got + lost)
        kind, why = link_kind(self.link_url, self.config.link.kind)
        analyse = analyse_onboard(ob, kind) and self.onboard is not None and self._executor is not None
        if analyse:
            how = (f"downloading it to analyse it instead of the telemetry ({kind} link: {why}); "
                   "the telemetry's results stand until then")
        elif ob.download:
            how = "it is being downloaded after this disarm" + (
                f" (not analysed automatically over a {kind} link: {why}; [onboard_logs] analyse = \"always\" "
                "to do it)" if ob.analyse == "usb" and kind == "radio" else "")
        else:
            how = (f"fetch it with `groundstation logs get N --link {self.link_url or 'URL'}` or set [onboard_logs] "
                   "download = true" + (f" (or analyse = \"always\" to have it analysed over this {kind} link)"
                                        if ob.analyse == "usb" and kind == "radio" else ""))
        self.log(f"flight {flight}: telemetry lost {pct:.1f} % of packets (above [onboard_logs] suggest_above_loss_pct "
                 f"{ob.suggest_above_loss_pct:g}); the FC's onboard log holds the full-rate data: {how}")
        return analyse

    def _analyse_onboard_log(self, flight: int, path: str) -> None:
        """The onboard log of a lossy flight is written: analyse it as the flight's telemetry was (its
        results are published after the telemetry's, marked as coming from the onboard log)."""
        job = self._jobs.get(flight)
        if job is None or self._executor is None:
            return
        tel = self._flight_tlogs.get(flight)
        tlogs = tuple(path if t == tel else t for t in job.tlogs)
        self.log(f"flight {flight}: analysing the onboard log {path} instead of the telemetry")
        self.submit_identification(dataclasses.replace(job, tlogs=tlogs, live_spectra=None, data="onboard_log"))

    def _check_exit(self) -> None:
        k = self.config.service.exit_after_flights
        if k and self.flights_completed >= k and not self._pending and not (self.onboard and self.onboard.busy):
            self.request_stop(f"{k} flight(s) done")

    # ------------------------------------------------------------------ status

    def status(self) -> dict[str, Any]:
        now = time.time()
        stats = getattr(self.session, "stats", None)
        lost = int(getattr(stats, "packets_lost", 0) or 0)
        pk = int(getattr(stats, "packets", 0) or self.packets)
        ft = self.live.flights
        z = self.zenoh
        return {
            "vehicle": self.vehicle, "t_host_s": now,
            "link": {"up": self.link_up, "url": self.link_url, "drops": self.link_drops,
                     "packets": pk, "packets_lost": lost,
                     "loss_pct": round(100.0 * lost / max(1, pk + lost), 3),
                     "bad_crc": int(getattr(stats, "bad_crc", 0) or 0),
                     "corrupt_bytes": int(getattr(stats, "corrupt_bytes", 0) or 0),
                     "last_flight": self.last_flight_link},
            "rates_hz": self.rates.rates(now),
            "armed": ft.armed, "in_air": ft.in_air, "flight": ft.flight if ft.armed else None,
            "input_trim_pwm": dict(zip(("lat", "lon", "col", "ped"), self.live.trim_pwm, strict=True)),
            "flights_completed": self.flights_completed,
            "height_m": ft.height_m if math.isfinite(ft.height_m) else None,
            "recording": {"dir": str(self.record_dir), "session": self.report.session_tlog,
                          "flights": list(self.report.flight_tlogs)},
            "identification": {"state": self.ident.state, "flight": self.ident.flight,
                               "queued": self.ident.queued, "done": self.ident.done, "failed": self.ident.failed,
                               "last_error": self.ident.last_error, "last_seconds": self.ident.last_seconds,
                               "last_data": self.ident.last_data},
            "excitation": self._excitation_status(),
            "windows": {"published": self.window_seq_published,
                        "dropped": z.windows_dropped if z is not None else 0,
                        "latency_ms": self._latency_ms()},
            "signing": ({**self.signing.status(), "dropped": int(getattr(stats, "unsigned_dropped", 0) or 0)}
                        if self.signing is not None else {"enabled": False}),
        }

    def _excitation_status(self) -> dict[str, Any] | None:
        """The latest verdict in brief: its status line and whether each axis is enough."""
        rep = self.excitation_last
        if rep is None:
            return None
        return {"flight": rep.flight, "t_s": round(rep.t_s, 1), "line": rep.line(),
                "enough": {a: v.enough for a, v in rep.axes.items()}}

    def _latency_ms(self, last: int = 200) -> dict[str, float | None]:
        """Packet arrival -> window handed to zenoh, over the last ``last`` windows (ms)."""
        z = self.zenoh
        if z is None or not z.window_latency:
            return {"median": None, "p99": None}
        recent = list(z.window_latency)[-last:]
        lat = np.array([pub - arr for _, arr, pub in recent if math.isfinite(arr)]) * 1000.0
        if len(lat) == 0:
            return {"median": None, "p99": None}
        return {"median": round(float(np.median(lat)), 2), "p99": round(float(np.percentile(lat, 99)), 2)}

    def _publish_status(self) -> None:
        if self.zenoh is not None:
            self.zenoh.publish_status(self.status())

    # ------------------------------------------------------------------ shutdown

    async def _shutdown(self) -> None:
        # 1. recording first: whatever happens next, the files are closed and valid
        if self.recorder is not None:
            try:
                self.recorder.close()
            except OSError as exc:
                self._warn(f"closing recorder: {exc}")
            self.report.session_tlog = self.report.session_tlog or str(
                getattr(self.recorder, "session_path", "") or "") or None
        # 2. the worker: cancel queued jobs, kill a running identification
        while self._queue:
            self._queue.popleft()[1].cancel()
        if self._executor is not None:
            executor, self._executor = self._executor, None
            procs = list(getattr(executor, "_processes", {}).values())
            executor.shutdown(wait=False, cancel_futures=True)
            for p in procs:
                if p.is_alive():
                    p.terminate()
            for p in procs:
                p.join(0.5)
                if p.is_alive():
                    p.kill()
        # 3. sinks (bounded waits)
        self._flush_rows_to_rerun()
        self._close_rerun()
        if self.zenoh is not None:
            self._publish_status()
            self.zenoh.close(0.5)
            self.report.windows_dropped = self.zenoh.windows_dropped
        self.report.windows_published = self.window_seq_published
        stats = getattr(self.session, "stats", None)
        self.report.packets = int(getattr(stats, "packets", 0) or self.packets)
        self.report.packets_lost = int(getattr(stats, "packets_lost", 0) or 0)
        self.report.bad_crc = int(getattr(stats, "bad_crc", 0) or 0)
        # 4. link and built-in simulator
        link = self.runner.link if self.runner is not None else None
        if link is not None:
            await self._send_what_is_queued(link)
            try:
                await asyncio.wait_for(link.close(), 0.5)
            except (OSError, TimeoutError):
                pass
            self.link = None
        if self.sim is not None:
            try:
                await asyncio.to_thread(self.sim.stop, 1.0)
            except (OSError, TimeoutError, RuntimeError) as exc:
                self._warn(f"stopping the simulator: {exc}")

    async def _send_what_is_queued(self, link: Any) -> None:
        """Messages the session still holds (a LOG_REQUEST_END queued as a download finished) are
        written before the port closes, so the FC is not left with a log transfer open."""
        if self.session is None or self.runner is None:
            return
        try:
            out = self.session.data_to_send(self.runner.clock())
            if out:
                await asyncio.wait_for(link.write(out), 0.5)
        except (LinkError, OSError, TimeoutError) as exc:
            self._warn(f"{getattr(link, 'url', 'link')}: last messages not sent ({exc})")


def _excitation_doc(vehicle: str, rep: ExcitationReport, final: bool) -> dict[str, Any]:
    """The ``heli/{vehicle}/excitation`` payload (built on the zenoh publisher thread)."""
    return {"vehicle": vehicle, **rep.to_json(), "final": final}


def _worker_init(nice: int = 19) -> None:
    """Worker process: low CPU priority (``[service] worker_nice``, the lowest by default) and one
    BLAS/OpenMP thread, so the live path keeps a core to itself while identification and diagnosis run."""
    try:
        os.nice(nice)
    except OSError:
        pass
    threadpool_limits(1)            # process-wide (not a context manager here)


def cross_flight_line(flight: int | None, cross: dict[str, Any]) -> str:
    """One log line of the worker's cross-flight check (``fit.cross_flight``): is the aircraft the same
    as on the previous flight? "" without a previous flight."""
    prev = cross.get("previous_flight")
    if prev is None:
        return ""
    if cross.get("error"):
        return f"flight {flight}: not compared with flight {prev}: {cross['error']}"
    parts = []
    for key, what in (("new_model_on_previous_flight", f"this model on flight {prev}"),
                      ("previous_model_on_new_flight", f"flight {prev}'s model on this flight")):
        if key in cross:
            parts.append(f"{what} {float(cross[key]['mean_match']):.1f} %")
    return f"flight {flight}: same aircraft as flight {prev}? held-out match: {'; '.join(parts) or 'not scored'}"
