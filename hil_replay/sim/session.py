"""A simulated flight-test session: flights with disarmed pauses, as 50 Hz telemetry frames, and .tlog.

:class:`SimulatedSession` plans everything from the seed at construction (per-seed trims, cards,
schedule; :meth:`SimulatedSession.truth` is known before flying) and :meth:`SimulatedSession.frames`
flies it, yielding one :class:`~hil_replay.sim.telemetry.TelemetryFrame` per 50 Hz tick of the FC
clock (repeatable: every call replays the same session). The loop per tick: card -> pilot ->
integer PWM (what SERVO_OUTPUT_RAW reports; the truth's input is exactly ``(pwm - trim) /
pwm_per_unit``) -> measurement of the state at this tick -> frame -> four RK4 sub-steps of 5 ms
(200 Hz) with the input effects applied per sub-step, gusts held per tick, ground contact.

Always on: sensor noise (gyro, attitude, velocity, position, GPS, accelerometer), +-1 ms FC-time
jitter; :func:`write_tlog` adds packet loss (~0.2 %, MAVLink seq shows the gap) and host-time
jitter. Effects (``effects.py``) switch on the unmodelled physics and sensor errors.

Leaves to others: the MAVLink protocol on a port (``hil_replay.fc``), reading logs back.
"""

from __future__ import annotations

import json
import math
import os
from collections import deque
from collections.abc import Iterator, Mapping, Sequence
from dataclasses import asdict, dataclass
from pathlib import Path
from typing import Any

import numpy as np
from pymavlink.dialects.v20 import ardupilotmega as mavlink

from firmware_interface.tlog import TlogWriter
from hil_replay.sim.aircraft import INPUTS, PARAM_NAMES, Aircraft, resolve_aircraft
from hil_replay.sim.card import Card, make_card
from hil_replay.sim.dynamics import G_M_S2, ground_effect_excess, make_specific_force, make_stepper
from hil_replay.sim.effects import (
    CHAIN_EFFECTS,
    Effect,
    GustModel,
    HeldBackChain,
    InputChain,
    TurbulenceModel,
    aliased_hz,
    resolve_effects,
    rotor_sag,
)
from hil_replay.sim.pilot import Pilot, PilotConfig, design_gains
from hil_replay.sim.rateloop import RateLoop, RateLoopState, closed_loop_truth
from hil_replay.sim.telemetry import FIELD_ORIGIN, MESSAGE_NAMES, Measurement, TelemetryFrame, heartbeat

FRAME_RATE_HZ = 50.0
SUBSTEPS = 4
#: Unix time of FC boot in written .tlog files (fixed so that the same seed gives the same bytes).
TLOG_EPOCH_S = 1_767_225_600.0
#: Message rates of :func:`write_tlog` (Hz; decimated from the 50 Hz frames).
DEFAULT_TLOG_RATES_HZ: dict[str, float] = {
    "HEARTBEAT": 1.0, "SERVO_OUTPUT_RAW": 50.0, "ATTITUDE": 50.0, "LOCAL_POSITION_NED": 50.0,
    "GLOBAL_POSITION_INT": 10.0, "RAW_IMU": 10.0, "GPS_RAW_INT": 5.0, "EXTENDED_SYS_STATE": 5.0, "SYS_STATUS": 1.0,
}


@dataclass(frozen=True)
class NoiseConfig:
    """Always-on sensor noise (1 sigma) of the simulated autopilot's estimates."""

    gyro_rad_s: float = 0.006
    attitude_rad: float = 0.0015
    yaw_rad: float = 0.003
    vel_m_s: float = 0.03
    vel_down_m_s: float = 0.04
    pos_m: float = 0.03
    alt_m: float = 0.05
    accel_m_s2: float = 0.25
    gps_pos_m: float = 0.3
    gps_vel_m_s: float = 0.08


_N_NOISE = 22  # normals drawn per tick (fixed so the stream never depends on what is built)


class SimulatedSession:
    """Several flights with disarmed pauses; see the module docstring.

    Parameters
    ----------
    seed : everything random (trims, card, pilot, noise, gusts) derives from it
    flights : number of flights (armed intervals)
    effects : :class:`~hil_replay.sim.effects.Effect` objects or ``"name:key=value"`` strings
    aircraft : ``None`` (TREX-600 default), an aircraft name, a TOML path or an ``Aircraft``
    pause_s : disarmed time between flights (heartbeats continue, FC clock keeps running)
    flight_duration_s : armed time per flight (default: the card's ~150-200 s)
    pre_arm_s, post_s : disarmed time before the first flight and after the last
    linear_kinematics : nonlinear kinematics off: the rigid body linearised about hover (see
        :func:`hil_replay.sim.dynamics.make_stepper`); default False (the full nonlinear equations)
    rate_loop : a stabiliser between the sticks and the swashplate (:mod:`hil_replay.sim.rateloop`):
        the log then holds the sticks (rate demands), the rotor gets the loop's output; None = none
    """

    def __init__(self, seed: int = 0, flights: int = 1, effects: Sequence[Effect | str] = (),
                 aircraft: Aircraft | str | os.PathLike[str] | None = None, pause_s: float = 10.0, *,
                 flight_duration_s: float | None = None, pre_arm_s: float = 3.0, post_s: float = 2.0,
                 noise: NoiseConfig | None = None, pilot: PilotConfig | None = None,
                 excitation_scale: float = 1.0, sweeps: bool = True, linear_kinematics: bool = False,
                 rate_loop: RateLoop | None = None) -> None:
        if int(flights) < 1:
            raise ValueError(f"flights: {flights} must be >= 1")
        if not pause_s >= 0 or not pre_arm_s >= 0 or not post_s >= 0:
            raise ValueError("pause_s, pre_arm_s and post_s must be >= 0")
        if not 0.0 < excitation_scale <= 4.0:
            raise ValueError(f"excitation_scale: {excitation_scale} not in (0, 4]")
        self.pilot_config = pilot or PilotConfig()
        self.excitation_scale = float(excitation_scale)
        self.sweeps = bool(sweeps)
        self.linear_kinematics = bool(linear_kinematics)
        self.rate_loop = rate_loop
        self.seed = int(seed)
        self.n_flights = int(flights)
        base = resolve_aircraft(aircraft)  # type: ignore[arg-type]
        self.effects = resolve_effects(tuple(effects), base.rotor_rpm)
        self.noise = noise or NoiseConfig()
        self.pause_s = float(pause_s)
        ss = np.random.SeedSequence(self.seed)
        self._seeds = ss.spawn(6)
        plan = np.random.default_rng(self._seeds[0])
        trims = {k: int(v + plan.integers(-15, 16)) for k, v in base.trim_pwm.items()}
        self.aircraft = base.with_trim(trims)
        design_gains(self.aircraft, self.pilot_config)  # an aircraft the pilot cannot fly fails here, before any output
        self.cards: list[Card] = []
        self.arm_times_s: list[float] = []
        t = float(pre_arm_s)
        heading = None
        for _ in range(self.n_flights):
            # later flights take off facing about where the last one landed
            card = make_card(self.aircraft, plan, duration_s=flight_duration_s, excitation_scale=self.excitation_scale,
                             sweeps=self.sweeps,
                             heading_rad=None if heading is None else heading + float(plan.uniform(-0.15, 0.15)))
            heading = card.heading_rad
            self.cards.append(card)
            self.arm_times_s.append(round(t, 6))
            t += card.duration_s + self.pause_s
        self.end_s = self.arm_times_s[-1] + self.cards[-1].duration_s + float(post_s)
        self.in_air_fc_s: list[list[float | None]] = []

    # ------------------------------------------------------------------------------------------
    @property
    def duration_s(self) -> float:
        return self.end_s

    def truth(self) -> dict[str, Any]:
        """The exact truth behind the session (the .truth.json sidecar content)."""
        ac = self.aircraft
        effects = []
        for e in self.effects:
            d = e.to_json()
            if e.name in ("rotor_vibration", "wandering_vibration"):
                f = float(e.params["rpm"]) / 60.0
                d["params"]["frequency_hz"] = f
                d["params"]["aliased_hz"] = aliased_hz(f, FRAME_RATE_HZ)  # 1/rev line in 50 Hz samples
                d["params"]["aliased_2rev_hz"] = aliased_hz(2 * f, FRAME_RATE_HZ)
            effects.append(d)
        flights = []
        for k, (t0, card) in enumerate(zip(self.arm_times_s, self.cards, strict=False)):
            flights.append({"index": k, "start_fc_s": t0, "end_fc_s": round(t0 + card.duration_s, 6),
                            "heading_rad": card.heading_rad, "segments": card.to_json(t0)})
        return {
            "schema": "heli-sim-truth/1",
            "aircraft": ac.name,
            "parameters": {n: float(ac.parameters[n]) for n in PARAM_NAMES},
            "constraints": {"N_fb": -float(ac.parameters["N_ped"]), "k_fb": -2.0 * float(ac.parameters["N_r"])},
            "input_trim_pwm": {k: int(ac.trim_pwm[k]) for k in INPUTS},
            "pwm_per_unit": float(ac.pwm_per_unit),
            "servo": {k: int(ac.servo[k]) for k in INPUTS},
            "effects": effects,
            "flights": flights,
            "seed": self.seed,
            "sample_rate_hz": FRAME_RATE_HZ,
            "integration_rate_hz": FRAME_RATE_HZ * SUBSTEPS,
            "rotor_diameter_m": ac.rotor_diameter_m,
            "rotor_rpm": ac.rotor_rpm,
            "hub_height_m": ac.hub_height_m,
            "noise": asdict(self.noise),
            "pilot": asdict(self.pilot_config),
            "excitation_scale": self.excitation_scale,
            "sweeps": self.sweeps,
            "linear_kinematics": self.linear_kinematics,
            **({} if self.rate_loop is None else {"rate_loop": asdict(self.rate_loop) | {
                "closed_loop": closed_loop_truth(ac, self.rate_loop)}}),
            "field_origin": {"lat_deg": FIELD_ORIGIN[0], "lon_deg": FIELD_ORIGIN[1], "alt_m": FIELD_ORIGIN[2]},
        }

    # ------------------------------------------------------------------------------------------
    def frames(self, fast_gyro: bool = False) -> Iterator[TelemetryFrame]:
        """Fly the session; one frame per 50 Hz tick from FC time 0 to the end.

        ``fast_gyro``: each frame also carries ``fast_before``, the gyro and attitude
        (t_s, p, q, r, roll, pitch, yaw; rad/s, rad) measured at the three 200 Hz sub-steps since the
        previous tick (with the frame's own: 200 Hz), as an autopilot's onboard log holds them."""
        ac = self.aircraft
        dt = 1.0 / FRAME_RATE_HZ
        fx = _EffectState.of(self.effects, ac, dt, np.random.default_rng(self._seeds[4]))
        step = make_stepper(ac, drag_c_per_m=fx.drag_c, ground_effect_gain=fx.ge_gain, wind=fx.wind,
                            linear_kinematics=self.linear_kinematics)
        sf = make_specific_force(ac, drag_c_per_m=fx.drag_c, ground_effect_gain=fx.ge_gain)
        pilot = Pilot(ac, np.random.default_rng(self._seeds[1]), dt_s=dt, config=self.pilot_config)
        noise_rng = np.random.default_rng(self._seeds[2])
        gust: GustModel | TurbulenceModel | None = None
        if fx.wind:
            ge = next(e for e in self.effects if e.name in ("wind_gust", "turbulence"))
            gp = ge.params
            if ge.name == "turbulence":
                gust = TurbulenceModel(np.random.default_rng(self._seeds[3]), dt, float(gp["sigma_m_s"]),
                                       float(gp["tau_slow_s"]), float(gp["tau_fast_s"]), float(gp["fast_share"]))
            else:
                gust = GustModel(np.random.default_rng(self._seeds[3]), dt, float(gp["sigma_m_s"]),
                                 float(gp["tau_s"]))
        sensors = _Sensors(self.noise, fx, sf, ac, dt)
        # the stabiliser runs at the 200 Hz integration rate (a flybarless unit runs faster than the link)
        loop = RateLoopState(self.rate_loop, ac, dt / SUBSTEPS) if self.rate_loop is not None else None
        trim = [float(ac.trim_pwm[c]) for c in INPUTS]
        ppu = float(ac.pwm_per_unit)
        Z_col = float(ac.parameters["Z_col"])
        # ground idle: collective well below hover pitch (thrust-reducing direction for this aircraft)
        col_low = min(0.9, 0.25 * max(1.0, 6.0 / max(abs(Z_col), 1e-3))) * (1.0 if Z_col > 0 else -1.0)

        avail_all = tuple(n for n in MESSAGE_NAMES if n not in ("HEARTBEAT", "GPS_RAW_INT", "SYS_STATUS"))
        avail_gps = avail_all + ("GPS_RAW_INT",)
        avail_1hz = ("HEARTBEAT",) + avail_gps + ("SYS_STATUS",)

        x = [0.0] * 15
        x[8] = self.cards[0].heading_rad
        landed = True
        air: list[list[float | None]] = []
        self.in_air_fc_s = air  # filled while flying: [[liftoff, touchdown], ...] (FC s)
        flight_k = -1
        off_n = off_e = 0.0
        n_ticks = int(round(self.end_s * FRAME_RATE_HZ)) + 1
        arm = self.arm_times_s
        ends = [a + c.duration_s for a, c in zip(arm, self.cards, strict=False)]
        # high-rate gyro (200 Hz) only when asked: its own noise stream, so the 50 Hz telemetry is unchanged
        fast_rng = np.random.default_rng(np.random.SeedSequence(self.seed, spawn_key=(6,))) if fast_gyro else None
        fast_before: tuple[tuple[float, ...], ...] = ()
        for k in range(n_ticks):
            t = k * dt
            fi = next((i for i in range(self.n_flights) if arm[i] - 1e-9 <= t < ends[i] - 1e-9), None)
            armed = fi is not None
            seg_kind = "off"
            if fi is not None:
                if fi != flight_k:  # new flight: fresh battery, the card starts where the aircraft stands
                    flight_k = fi
                    sensors.used_mah = 0.0
                    off_n, off_e = x[12], x[13]
                fx.set_progress(min(1.0, (t - arm[fi]) / max(self.cards[fi].duration_s, 1e-9)))
                cmd, throttle, seg_kind = _pilot_command(self.cards[fi], t - arm[fi], pilot, x, (off_n, off_e),
                                                         col_low)
            else:
                cmd = [0.0, 0.0, col_low, 0.0]
                throttle = 1000
            pwm = [min(2000, max(1000, int(round(tr + c * ppu)))) for tr, c in zip(trim, cmd, strict=False)]
            dcmd = [(p_ - tr) / ppu for p_, tr in zip(pwm, trim, strict=False)]
            wind = gust.wind if gust is not None else [0.0, 0.0, 0.0]
            spinning = armed and (seg_kind != "ground" or throttle > 1500)
            meas = sensors.measure(noise_rng.standard_normal(_N_NOISE).tolist(), t, x, armed, seg_kind, landed,
                                   spinning, throttle, dcmd, wind, pwm)
            if k % 50 == 0:
                avail = avail_1hz
            elif k % 10 == 0:
                avail = avail_gps
            else:
                avail = avail_all
            blade = dcmd if loop is None else loop.blade(dcmd, x)   # the sticks are logged, the rotor gets the loop's
            da0 = fx.actuate(blade)
            yield TelemetryFrame(meas, fi, avail, tuple(x), tuple(dcmd), tuple(da0), tuple(wind), fast_before)
            x, landed, fast_before = _integrate(step, fx, ac, x, landed, t, dt, da0, blade, wind, armed, seg_kind,
                                                spinning, air, fast_rng, self.noise,
                                                None if loop is None else (lambda xs, st=dcmd: loop.blade(st, xs)))
            if gust is not None:
                gust.step()


def _pilot_command(card: Card, t_flight: float, pilot: Pilot, x: list[float], offset_ne: tuple[float, float],
                   col_low: float) -> tuple[list[float], int, str]:
    """The pilot's normalised commands, throttle PWM and segment kind at ``t_flight`` into the card."""
    mode, seg, ref, exc = card.at(t_flight)
    ref = (ref[0] + offset_ne[0], ref[1] + offset_ne[1]) + ref[2:]
    if mode == "fly":
        excited = INPUTS.index(seg.axis) if seg.axis is not None else None
        cmd = pilot.command(x, ref, excited)
        return [c + e for c, e in zip(cmd, exc, strict=False)], 1850, seg.kind
    rem = pilot.remnant()
    spool_t = t_flight - seg.start_s if seg.name == "spool_up" else seg.end_s - t_flight
    return ([0.3 * rem[0], 0.3 * rem[1], col_low, 0.3 * rem[3]],
            int(1100 + 750 * min(1.0, max(0.0, spool_t / 3.0))), seg.kind)


@dataclass
class _EffectState:
    """The injected effects as the simulation loop uses them (input chains hold state)."""

    drag_c: float
    ge_gain: float
    wind: bool
    chains: list[InputChain | None]
    post: _PostChain | None
    bias: list[float]
    gscale: list[float]
    vscale: float
    vib_amp: float
    vib_w: float
    vib_phase: list[float]
    latency_ticks: float
    vib_axis: tuple[float, float, float] = (1.0, 0.8, 0.5)
    held: HeldBackChain | None = None  # held-back input physics (effects.HELD_BACK)
    drift_bias: tuple[float, float, float] = (0.0, 0.0, 0.0)  # gyro bias at the end of the flight
    vib_wander: float = 0.0  # relative rpm wander of the rotor line
    vib_period_s: float = 40.0
    progress: float = 0.0  # 0 at arming, 1 at the end of the flight's card

    def set_progress(self, progress: float) -> None:
        self.progress = progress
        if self.held is not None:
            self.held.progress = progress

    @classmethod
    def of(cls, effects: Sequence[Effect], ac: Aircraft, dt: float, phase_rng: np.random.Generator) -> _EffectState:
        eff = {e.name: e for e in effects}

        def param(name: str, key: str, default: float) -> float:
            return float(eff[name].params[key]) if name in eff else default

        h = dt / SUBSTEPS
        chains: list[InputChain | None] = [None, None, None, None]
        for i, ch in enumerate(INPUTS):
            kw: dict[str, float] = {}
            for e in effects:
                if e.input == ch and e.name in CHAIN_EFFECTS:
                    kw.update({k: float(v) for k, v in e.params.items()})
            if kw:
                chains[i] = InputChain(h, **kw)
        bias, gscale, asym = [0.0, 0.0, 0.0], [1.0, 1.0, 1.0], [0.0, 0.0, 0.0, 0.0]
        for e in effects:
            if e.name == "gyro_bias":
                bias["pqr".index(str(e.output))] += float(e.params["bias_rad_s"])
            elif e.name == "gyro_scale":
                gscale["pqr".index(str(e.output))] = 1.0 + float(e.params["scale_error"])
            elif e.name == "input_asymmetry":
                asym[INPUTS.index(str(e.input))] = float(e.params["asymmetry"])
        sag = param("rotor_sag", "sag_per_unit", 0.0)
        vib_phase = phase_rng.uniform(0, 2 * math.pi, 6).tolist()
        held = HeldBackChain(h, list(effects), INPUTS, float(ac.parameters["Z_col"]), G_M_S2)
        drift = [0.0, 0.0, 0.0]
        for e in effects:
            if e.name == "drifting_bias":
                drift["pqr".index(str(e.output))] += float(e.params["bias_end_rad_s"])
        vib = "wandering_vibration" if "wandering_vibration" in eff else "rotor_vibration"
        return cls(drag_c=param("quadratic_drag", "c_per_m", 0.0), ge_gain=param("ground_effect", "gain", 0.0),
                   wind="wind_gust" in eff or "turbulence" in eff, chains=chains,
                   post=_PostChain(asym, sag, float(ac.parameters["Z_col"])) if sag or any(asym) else None,
                   bias=bias, gscale=gscale, vscale=1.0 + param("velocity_scale", "scale_error", 0.0),
                   vib_amp=param(vib, "amplitude_rad_s", 0.0),
                   vib_w=2 * math.pi * param(vib, "rpm", 0.0) / 60.0, vib_phase=vib_phase,
                   latency_ticks=param("velocity_latency", "latency_s", 0.0) / dt,
                   held=held if held.active else None, drift_bias=(drift[0], drift[1], drift[2]),
                   vib_wander=param("wandering_vibration", "wander", 0.0),
                   vib_period_s=param("wandering_vibration", "period_s", 40.0))

    def actuate(self, dcmd: list[float]) -> list[float]:
        """The inputs acting on the rotor at the next 200 Hz sub-step (one step of each input chain)."""
        da = [dcmd[i] if self.chains[i] is None else self.chains[i](dcmd[i]) for i in range(4)]  # type: ignore[misc]
        da = self.post(da) if self.post is not None else da
        return self.held(da) if self.held is not None else da

    def vibration(self, t: float) -> list[float]:
        """Rotor vibration on p q r at ``t`` (rad/s)."""
        wt = self.vib_w * t
        if self.vib_wander:  # rpm (1 + wander sin(2 pi t / P)): the phase is its integral
            om = 2 * math.pi / self.vib_period_s
            wt += self.vib_w * self.vib_wander * (1.0 - math.cos(om * t)) / om
        s1 = [math.sin(wt + self.vib_phase[i]) for i in range(3)]
        s2 = [math.sin(2 * wt + self.vib_phase[3 + i]) for i in range(3)]
        return [self.vib_amp * a * (x1 + 0.5 * x2) for a, x1, x2 in zip(self.vib_axis, s1, s2, strict=False)]


class _Sensors:
    """What the autopilot measures at a tick: noise, effects, battery (its state: the energy used)."""

    def __init__(self, nz: NoiseConfig, fx: _EffectState, sf: Any, ac: Aircraft, dt: float) -> None:
        self.nz, self.fx, self.sf, self.ac, self.dt = nz, fx, sf, ac, dt
        self.hist: deque[tuple[float, ...]] = deque(maxlen=int(fx.latency_ticks) + 3)
        self.servo_idx = [int(ac.servo[c]) - 1 for c in INPUTS]
        self.used_mah = 0.0

    def measure(self, z: list[float], t: float, x: list[float], armed: bool, seg_kind: str, landed: bool,
                spinning: bool, throttle: int, dcmd: list[float], wind: list[float], pwm: list[int]) -> Measurement:
        nz, fx = self.nz, self.fx
        u, v, w, p, q, r, ph, th, ps = x[0], x[1], x[2], x[3], x[4], x[5], x[6], x[7], x[8]
        sph, cph, sth, cth, sps, cps = math.sin(ph), math.cos(ph), math.sin(th), math.cos(th), \
            math.sin(ps), math.cos(ps)
        vn = cth * cps * u + (sph * sth * cps - cph * sps) * v + (cph * sth * cps + sph * sps) * w
        ve = cth * sps * u + (sph * sth * sps + cph * cps) * v + (cph * sth * sps - sph * cps) * w
        vd = -sth * u + sph * cth * v + cph * cth * w
        self.hist.append((vn, ve, vd, x[12], x[13], x[14]))
        nv = _delayed(self.hist, fx.latency_ticks) if fx.latency_ticks > 0.0 else (vn, ve, vd, x[12], x[13], x[14])
        b, gs = fx.bias, fx.gscale
        if any(fx.drift_bias):
            b = [bb + fx.progress * db for bb, db in zip(b, fx.drift_bias, strict=True)]
        mp, mq, mr = gs[0] * p + b[0], gs[1] * q + b[1], gs[2] * r + b[2]
        mroll, mpitch = ph, th
        if fx.vib_amp and spinning:
            vib = fx.vibration(t)
            mp, mq, mr = mp + vib[0], mq + vib[1], mr + vib[2]
            mroll += 0.1 * vib[0]
            mpitch += 0.1 * vib[1]
        mp += nz.gyro_rad_s * z[0]
        mq += nz.gyro_rad_s * z[1]
        mr += nz.gyro_rad_s * z[2]
        mroll += nz.attitude_rad * z[3]
        mpitch += nz.attitude_rad * z[4]
        myaw = _wrap(ps + nz.yaw_rad * z[5])
        mvn = fx.vscale * nv[0] + nz.vel_m_s * z[6]
        mve = fx.vscale * nv[1] + nz.vel_m_s * z[7]
        mvd = fx.vscale * nv[2] + nz.vel_down_m_s * z[8]
        acc_sig = nz.accel_m_s2 if spinning else 0.02
        # the accelerometer costs a model evaluation: computed only if RAW_IMU is built
        acc = _Accel(self.sf, x, dcmd, wind, landed, (acc_sig * z[12], acc_sig * z[13], acc_sig * z[14]))
        jms = (int(z[20] > 0.8) - int(z[20] < -0.8), int(z[21] > 0.8) - int(z[21] < -0.8),
               int(z[20] * z[21] > 0.6) - int(z[20] * z[21] < -0.6))
        jus = (int(z[20] * 400.0), int(z[21] * 400.0), int((z[20] - z[21]) * 300.0))
        volt, current_a, frac = self._battery(armed, spinning, landed, dcmd)
        servo = [1500, 1500, 1500, 1500, 0, 0, 0, throttle]
        for i_s, pw in zip(self.servo_idx, pwm, strict=False):
            servo[i_s] = pw
        return Measurement(t, armed, jms, jus, mroll, mpitch, myaw, mp, mq, mr,
                           nv[3] + nz.pos_m * z[9], nv[4] + nz.pos_m * z[10], nv[5] + nz.alt_m * z[11],
                           mvn, mve, mvd, acc, x[12] + nz.gps_pos_m * z[15], x[13] + nz.gps_pos_m * z[16],
                           x[14] + 2 * nz.gps_pos_m * z[17], vn + nz.gps_vel_m_s * z[18], ve + nz.gps_vel_m_s * z[19],
                           tuple(servo), _landed_state(armed, seg_kind, landed), volt, current_a, frac)

    def _battery(self, armed: bool, spinning: bool, landed: bool, dcmd: list[float]) -> tuple[float, float, float]:
        """(voltage V, current A, fraction used): current from the collective and the rotor state."""
        ac = self.ac
        if not armed:
            current_a = 0.6
        elif not spinning:
            current_a = 2.0
        elif landed:
            current_a = 0.35 * float(ac.hover_current_a)
        else:
            current_a = float(ac.hover_current_a) * max(0.3, 1.0 + 2.0 * dcmd[2])
        self.used_mah += current_a * self.dt / 3.6
        frac = min(1.0, self.used_mah / float(ac.battery_capacity_mah))
        cells = ac.battery_cells
        return cells * (4.15 - 0.55 * frac) - 0.0025 * cells * current_a, current_a, frac


def _landed_state(armed: bool, seg_kind: str, landed: bool) -> int:
    """MAV_LANDED_STATE: 1 on ground, 2 in air, 3 taking off, 4 landing."""
    if not armed:
        return 1
    if seg_kind == "takeoff":
        return 3
    if seg_kind == "land":
        return 1 if landed else 4
    return 1 if landed else 2


def _integrate(step: Any, fx: _EffectState, ac: Aircraft, x: list[float], landed: bool, t: float, dt: float,
               da0: list[float], dcmd: list[float], wind: list[float], armed: bool, seg_kind: str, spinning: bool,
               air: list[list[float | None]], fast_rng: np.random.Generator | None,
               nz: NoiseConfig, loop_fn: Any = None) -> tuple[list[float], bool, tuple[tuple[float, ...], ...]]:
    """Integrate from ``t`` to ``t + dt`` in 200 Hz sub-steps: lift-off and touchdown (appended to
    ``air``), and the 200 Hz gyro between two ticks when ``fast_rng`` is given."""
    h = dt / SUBSTEPS
    g = G_M_S2
    Z_col, Z_ped = float(ac.parameters["Z_col"]), float(ac.parameters["Z_ped"])
    wn, we, wd = wind
    fast: list[tuple[float, ...]] = []
    for sub in range(SUBSTEPS):
        # a stabiliser (``loop_fn(x) -> blade``) acts at every sub-step on the state there
        da = da0 if sub == 0 else fx.actuate(dcmd if loop_fn is None else loop_fn(x))
        moves = True
        if landed:
            thrust = g - Z_col * da[2] - Z_ped * da[3]
            if fx.ge_gain:
                thrust *= 1.0 + fx.ge_gain * ground_effect_excess(0.0, ac.rotor_radius_m, ac.hub_height_m)
            if not armed or seg_kind == "ground" or thrust <= g:
                moves = False
            else:
                landed = False
                air.append([round(t + (sub + 1) * h, 4), None])
        if moves:
            x = step(x, h, da[0], da[1], da[2], da[3], wn, we, wd)
            if x[14] > 0.0:  # touchdown: skids on the ground, level, at rest
                landed = True
                air[-1][1] = round(t + (sub + 1) * h, 4)
                x = [0.0] * 6 + [0.0, 0.0, x[8], 0.0, 0.0, 0.0, x[12], x[13], 0.0]
        if fast_rng is not None and sub < SUBSTEPS - 1:  # the 200 Hz gyro between two ticks
            fast.append(_fast_sample(fast_rng, fx, nz, x, t + (sub + 1) * h, spinning))
    return x, landed, tuple(fast)


def _fast_sample(rng: np.random.Generator, fx: _EffectState, nz: NoiseConfig, x: list[float], ts: float,
                 spinning: bool) -> tuple[float, ...]:
    """One 200 Hz gyro and attitude sample (t_s, p, q, r, roll, pitch, yaw)."""
    gz = rng.standard_normal(6).tolist()
    gy = [x[3 + i] + fx.bias[i] + nz.gyro_rad_s * gz[i] for i in range(3)]
    att = [x[6] + nz.attitude_rad * gz[3], x[7] + nz.attitude_rad * gz[4], _wrap(x[8] + nz.yaw_rad * gz[5])]
    if fx.vib_amp and spinning:
        for i in range(3):
            vb = fx.vib_amp * fx.vib_axis[i] * (math.sin(fx.vib_w * ts + fx.vib_phase[i])
                                                + 0.5 * math.sin(2 * fx.vib_w * ts + fx.vib_phase[3 + i]))
            gy[i] += vb
            if i < 2:
                att[i] += 0.1 * vb
    return (ts, gy[0], gy[1], gy[2], att[0], att[1], att[2])


class _PostChain:
    """Input nonlinearities outside the catalogue, after the input chains: per-channel asymmetric
    gain (``1 + a`` above trim, ``1 - a`` below) and rotor-speed sag with collective."""

    def __init__(self, asymmetry: list[float], sag_per_unit: float, z_col: float) -> None:
        self.asym = asymmetry
        self.sag = sag_per_unit
        self.z_col = z_col

    def __call__(self, d: list[float]) -> list[float]:
        d = [x * (1.0 + a if x > 0 else 1.0 - a) for x, a in zip(d, self.asym, strict=True)]
        return rotor_sag(d, self.sag, self.z_col, G_M_S2) if self.sag else d


class _Accel:
    """Deferred specific force (body axes, m/s^2) plus its noise, evaluated on demand."""

    __slots__ = ("sf", "x", "d", "wind", "landed", "noise")

    def __init__(self, sf: Any, x: list[float], d: list[float], wind: list[float], landed: bool,
                 noise: tuple[float, float, float]) -> None:
        self.sf, self.x, self.d, self.wind, self.landed, self.noise = sf, x, d, wind, landed, noise

    def __call__(self) -> tuple[float, float, float]:
        x, n = self.x, self.noise
        if self.landed:  # resting level on the skids: gravity only
            ph, th = x[6], x[7]
            f = (G_M_S2 * math.sin(th), -G_M_S2 * math.sin(ph) * math.cos(th), -G_M_S2 * math.cos(ph) * math.cos(th))
        else:
            d, w = self.d, self.wind
            f = self.sf(x, d[0], d[1], d[2], d[3], w[0], w[1], w[2])
        return (f[0] + n[0], f[1] + n[1], f[2] + n[2])


def _delayed(hist: deque[tuple[float, ...]], lag_ticks: float) -> tuple[float, ...]:
    """Linear interpolation ``lag_ticks`` ticks back in the per-tick history (newest last)."""
    n = len(hist)
    i = int(lag_ticks)
    fr = lag_ticks - i
    a = hist[max(0, n - 1 - i)]
    b = hist[max(0, n - 2 - i)]
    return tuple((1.0 - fr) * x + fr * y for x, y in zip(a, b, strict=False))


def _wrap(a: float) -> float:
    return (a + math.pi) % (2.0 * math.pi) - math.pi


# ----------------------------------------------------------------------------------------------
# .tlog writer
# ----------------------------------------------------------------------------------------------


def write_tlog(path: str | os.PathLike[str], *, seed: int = 0, flights: int = 1,
               effects: Sequence[Effect | str] = (), aircraft: Aircraft | str | os.PathLike[str] | None = None,
               flight_duration_s: float | None = None, rates_hz: Mapping[str, float] | None = None,
               pause_s: float = 10.0, packet_loss: float = 0.002, pilot: PilotConfig | None = None,
               excitation_scale: float = 1.0, sweeps: bool = True, linear_kinematics: bool = False,
               loss_burst: float = 1.0, noise_scale: float = 1.0,
               rate_loop: RateLoop | None = None) -> dict[str, Any]:
    """Simulate a session and write ``path`` (.tlog) and ``path.with_suffix('.truth.json')``.

    MAVLink 2 frames from sysid 1 compid 1 with a proper sequence number; host timestamps are
    :data:`TLOG_EPOCH_S` + FC time + a few ms of link latency with jitter; ``packet_loss`` of the
    packets are dropped after encoding (the seq gap shows). ``loss_burst`` > 1 makes the loss bursty
    as a radio fade is: a two-state (Gilbert) channel whose lost runs are ``loss_burst`` packets long
    on average (geometric), every message type alike, with the same long-run loss rate
    ``packet_loss``; 1 drops packets independently. ``noise_scale`` multiplies every sensor noise of
    :class:`NoiseConfig`. Returns the truth dict (also written).
    Same arguments, same bytes.
    """

    rates = dict(DEFAULT_TLOG_RATES_HZ)
    if rates_hz:
        for name, r in rates_hz.items():
            if name not in MESSAGE_NAMES:
                raise ValueError(f"rates_hz: unknown message {name!r}; allowed: {list(MESSAGE_NAMES)}")
            if not 0 <= r <= FRAME_RATE_HZ:
                raise ValueError(f"rates_hz.{name}: {r} Hz not in [0, {FRAME_RATE_HZ:g}]")
            rates[name] = float(r)
    if not 0.0 <= packet_loss < 1.0:
        raise ValueError(f"packet_loss: {packet_loss} not in [0, 1)")
    if not loss_burst >= 1.0:
        raise ValueError(f"loss_burst: {loss_burst} must be >= 1 (mean lost run, packets)")
    # Gilbert channel: good -> bad with p_enter, bad -> good with 1/loss_burst; stationary loss = packet_loss
    p_leave = 1.0 / loss_burst
    p_enter = packet_loss * p_leave / max(1.0 - packet_loss, 1e-12)
    in_fade = False
    period = {n: max(1, int(round(FRAME_RATE_HZ / r))) for n, r in rates.items() if r > 0}
    sess = SimulatedSession(seed=seed, flights=flights, effects=effects, aircraft=aircraft, pause_s=pause_s,
                            flight_duration_s=flight_duration_s, pilot=pilot, excitation_scale=excitation_scale,
                            sweeps=sweeps, linear_kinematics=linear_kinematics, rate_loop=rate_loop,
                            noise=None if noise_scale == 1.0 else NoiseConfig(
                                **{k: v * float(noise_scale) for k, v in asdict(NoiseConfig()).items()}))
    truth = sess.truth()
    truth["tlog_rates_hz"] = {n: rates[n] for n in MESSAGE_NAMES}
    truth["packet_loss"] = packet_loss
    truth["loss_burst"] = loss_burst
    path = Path(path)
    mav = mavlink.MAVLink(None, srcSystem=1, srcComponent=1)
    link_rng = np.random.default_rng(sess._seeds[5])
    order = [n for n in MESSAGE_NAMES if n in period]
    t_last = 0.0
    written = lost = 0
    with TlogWriter(path, flush_interval_s=3600.0, clock=lambda: 0.0) as tw:
        for k, frame in enumerate(sess.frames()):
            avail = frame.available
            due = [n for n in order if k % period[n] == 0 and (n in avail or n == "HEARTBEAT" and k % 50 == 0)]
            if not due:
                continue
            rnd = link_rng.random(len(due) + 1).tolist()
            t_host = TLOG_EPOCH_S + frame.t_boot_s + 0.004 + 0.004 * rnd[-1]
            for n, rv in zip(due, rnd, strict=False):
                if n == "HEARTBEAT":
                    msg = heartbeat(mav, frame.armed)
                else:
                    msg = frame.build(n, mav)
                buf = msg.pack(mav)
                mav.seq = (mav.seq + 1) % 256
                if loss_burst > 1.0:
                    in_fade = rv >= p_leave if in_fade else rv < p_enter
                    drop = in_fade
                else:
                    drop = rv < packet_loss
                if drop:
                    lost += 1
                    continue
                t_host = max(t_host, t_last + 2e-5)
                tw.write(buf, t_host)
                t_last = t_host
                written += 1
    for fl in truth["flights"]:
        fl["in_air_fc_s"] = [iv for iv in sess.in_air_fc_s if fl["start_fc_s"] <= (iv[0] or 0) < fl["end_fc_s"]]
    truth["packets_written"] = written
    truth["packets_lost"] = lost
    truth_path = path.with_suffix(".truth.json")
    truth_path.write_text(json.dumps(truth, indent=1) + "\n")
    return truth
