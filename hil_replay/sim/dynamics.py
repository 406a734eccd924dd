"""Nonlinear helicopter dynamics (paper eqs. 1-5) whose hover Jacobian is exactly eq. 8.

State vector (15 floats, a plain list for speed; see :data:`STATE_NAMES`)::

    0 u  1 v  2 w      body velocity (m/s, ground-relative: what the GPS/EKF measures)
    3 p  4 q  5 r      body rates (rad/s)
    6 phi 7 theta 8 psi  Euler angles (rad, ZYX)
    9 a_s 10 b_s       rotor flapping (rad), 11 r_fb  yaw-gyro feedback state
    12 n 13 e 14 d     NED position (m) relative to the take-off point

Model, per unit mass (inputs ``d = (lat, lon, col, ped)`` normalised, trim removed; ``*_a`` are
air-relative velocities ``v - wind``; ``T`` is the rotor thrust per unit mass, ``g`` at trim)::

    T     = (g - Z_w w_a - Z_r r - Z_col d_col - Z_ped d_ped) * k_ge(height)
    u_dot = r v - q w - g sin(theta)          - T sin(a_s)          + X_u u_a + X_lat d_lat - c|u_a|u_a
    v_dot = p w - r u + g sin(phi) cos(theta) + T sin(b_s)          + Y_v v_a + Y_lon d_lon - c|v_a|v_a
    w_dot = q u - p v + g cos(phi) cos(theta) - T cos(a_s) cos(b_s)                         - c|w_a|w_a
    p_dot = L_u u_a + L_v v_a + L_p p + L_a a_s + L_b b_s + L_lat d_lat + L_lon d_lon + (Iyy-Izz)/Ixx q r
    q_dot = M_u u_a + M_v v_a + M_q q + M_a a_s + M_b b_s + M_lat d_lat + M_lon d_lon + (Izz-Ixx)/Iyy p r
    r_dot = N_w w_a + N_r r + N_fb r_fb + N_col d_col + N_ped d_ped                + (Ixx-Iyy)/Izz p q
    a_s_dot = -q + k1 p - a_s / tau_s + A_lat d_lat            (eq. 4, paper naming)
    b_s_dot = -k1 q - p - b_s / tau_s + B_lon d_lon
    r_fb_dot = k_r r - k_fb r_fb                                (eq. 5), N_fb = -N_ped, k_fb = -2 N_r
    Euler kinematics (eq. 3) and NED position from the full rotation matrix (eq. 2).

At hover (all zero, no wind, drag and ground effect off) the Jacobian with respect to
``[u v theta phi q p a_s b_s]``/``[lat lon]`` and ``[w r r_fb]``/``[col ped]`` is the paper's eq. 8.
Ground effect (Cheeseman-Bennett, tapered to zero between 0.75 and 1.25 rotor diameters of rotor
height) and quadratic drag are the unmodelled physics switched on by ``effects``.

Leaves to others: inputs (pilot, input effects), ground contact (session), sensors (telemetry).
"""

from __future__ import annotations

import math
from collections.abc import Callable, Mapping, Sequence

from hil_replay.sim.aircraft import Aircraft

G_M_S2 = 9.81
STATE_NAMES: tuple[str, ...] = ("u", "v", "w", "p", "q", "r", "phi", "theta", "psi", "a_s", "b_s", "r_fb",
                                "n", "e", "d")
N_STATES = len(STATE_NAMES)
IDX = {n: i for i, n in enumerate(STATE_NAMES)}

Deriv = Callable[..., list[float]]


def ground_effect_excess(height_m: float, rotor_radius_m: float, hub_height_m: float) -> float:
    """Cheeseman-Bennett thrust excess ``T/T_inf - 1`` at skid height ``height_m``, tapered out.

    ``T/T_inf = 1 / (1 - (R / 4 z)^2)`` with ``z`` the rotor height; multiplied by a cosine taper
    that is 1 below 0.75 rotor diameters and 0 above 1.25 diameters (no effect out of ground effect).
    """
    r = rotor_radius_m
    dia = 2.0 * r
    z = max(height_m, 0.0) + hub_height_m
    z = max(z, 0.5 * r)  # the formula is singular at z = R/4; a skid height of ~0 never goes below R/2
    if z >= 1.25 * dia:
        return 0.0
    excess = 1.0 / (1.0 - (r / (4.0 * z)) ** 2) - 1.0
    if z > 0.75 * dia:
        excess *= 0.5 * (1.0 + math.cos(math.pi * (z - 0.75 * dia) / (0.5 * dia)))
    return excess


def make_derivative(ac: Aircraft, *, drag_c_per_m: float = 0.0, ground_effect_gain: float = 0.0) -> Deriv:
    """Return ``f(x, d_lat, d_lon, d_col, d_ped, wn, we, wd) -> x_dot`` (lists of 15 floats).

    ``wn, we, wd`` is the air-mass velocity (NED, m/s). Plain-float code: this runs ~10^6 times.
    """
    P = {k: float(v) for k, v in ac.parameters.items()}
    g = G_M_S2
    X_u, Y_v = P["X_u"], P["Y_v"]
    M_u, M_v, M_q, M_a, M_b = P["M_u"], P["M_v"], P["M_q"], P["M_a"], P["M_b"]
    L_u, L_v, L_p, L_a, L_b = P["L_u"], P["L_v"], P["L_p"], P["L_a"], P["L_b"]
    k1, it = P["k1"], P["inv_tau_s"]
    X_lat, Y_lon, M_lat, M_lon, L_lat, L_lon = P["X_lat"], P["Y_lon"], P["M_lat"], P["M_lon"], P["L_lat"], P["L_lon"]
    A_lat, B_lon = P["A_lat"], P["B_lon"]
    Z_w, Z_r, N_w, N_r, k_r = P["Z_w"], P["Z_r"], P["N_w"], P["N_r"], P["k_r"]
    Z_col, Z_ped, N_col, N_ped = P["Z_col"], P["Z_ped"], P["N_col"], P["N_ped"]
    N_fb = -N_ped
    k_fb = -2.0 * N_r
    Ixx, Iyy, Izz = (float(v) for v in ac.inertia_kg_m2)
    cpx = (Iyy - Izz) / Ixx
    cqy = (Izz - Ixx) / Iyy
    crz = (Ixx - Iyy) / Izz
    c_drag = float(drag_c_per_m)
    ge_gain = float(ground_effect_gain)
    radius, hub = ac.rotor_radius_m, ac.hub_height_m
    sin, cos = math.sin, math.cos

    def f(x: Sequence[float], dl: float, dn: float, dc: float, dp: float,
          wn: float = 0.0, we: float = 0.0, wd: float = 0.0) -> list[float]:
        u, v, w, p, q, r, ph, th, ps, a_s, b_s, rfb = x[0], x[1], x[2], x[3], x[4], x[5], x[6], x[7], x[8], \
            x[9], x[10], x[11]
        sph, cph, sth, cth, sps, cps = sin(ph), cos(ph), sin(th), cos(th), sin(ps), cos(ps)
        r11 = cth * cps
        r12 = sph * sth * cps - cph * sps
        r13 = cph * sth * cps + sph * sps
        r21 = cth * sps
        r22 = sph * sth * sps + cph * cps
        r23 = cph * sth * sps - sph * cps
        r32 = sph * cth
        r33 = cph * cth
        if wn or we or wd:
            ua = u - (r11 * wn + r21 * we - sth * wd)
            va = v - (r12 * wn + r22 * we + r32 * wd)
            wa = w - (r13 * wn + r23 * we + r33 * wd)
        else:
            ua, va, wa = u, v, w
        T = g - Z_w * wa - Z_r * r - Z_col * dc - Z_ped * dp
        if ge_gain:
            T *= 1.0 + ge_gain * ground_effect_excess(-x[14], radius, hub)
        fx = -T * sin(a_s) + X_u * ua + X_lat * dl
        fy = T * sin(b_s) + Y_v * va + Y_lon * dn
        fz = -T * cos(a_s) * cos(b_s)
        if c_drag:
            fx -= c_drag * abs(ua) * ua
            fy -= c_drag * abs(va) * va
            fz -= c_drag * abs(wa) * wa
        qs_rc = q * sph + r * cph
        return [
            r * v - q * w - g * sth + fx,
            p * w - r * u + g * r32 + fy,
            q * u - p * v + g * r33 + fz,
            L_u * ua + L_v * va + L_p * p + L_a * a_s + L_b * b_s + L_lat * dl + L_lon * dn + cpx * q * r,
            M_u * ua + M_v * va + M_q * q + M_a * a_s + M_b * b_s + M_lat * dl + M_lon * dn + cqy * p * r,
            N_w * wa + N_r * r + N_fb * rfb + N_col * dc + N_ped * dp + crz * p * q,
            p + qs_rc * sth / cth,
            q * cph - r * sph,
            qs_rc / cth,
            -q + k1 * p - it * a_s + A_lat * dl,
            -k1 * q - p - it * b_s + B_lon * dn,
            k_r * r - k_fb * rfb,
            r11 * u + r12 * v + r13 * w,
            r21 * u + r22 * v + r23 * w,
            -sth * u + r32 * v + r33 * w,
        ]

    return f


def make_specific_force(ac: Aircraft, *, drag_c_per_m: float = 0.0,
                        ground_effect_gain: float = 0.0) -> Callable[..., tuple[float, float, float]]:
    """Return ``sf(x, d_lat, d_lon, d_col, d_ped, wn, we, wd) -> (fx, fy, fz)``: the non-gravitational
    acceleration in body axes (m/s^2) an accelerometer measures (``fz ~ -g`` in hover)."""
    f = make_derivative(ac, drag_c_per_m=drag_c_per_m, ground_effect_gain=ground_effect_gain)
    g = G_M_S2

    def sf(x: Sequence[float], dl: float, dn: float, dc: float, dp: float,
           wn: float = 0.0, we: float = 0.0, wd: float = 0.0) -> tuple[float, float, float]:
        xd = f(x, dl, dn, dc, dp, wn, we, wd)
        u, v, w, p, q, r, ph, th = x[0], x[1], x[2], x[3], x[4], x[5], x[6], x[7]
        # body acceleration = x_dot + omega x v; specific force = that - gravity (body)
        ax = xd[0] - r * v + q * w
        ay = xd[1] - p * w + r * u
        az = xd[2] - q * u + p * v
        return (ax + g * math.sin(th), ay - g * math.sin(ph) * math.cos(th), az - g * math.cos(ph) * math.cos(th))

    return sf


def rk4_step(f: Deriv, x: list[float], dt: float, dl: float, dn: float, dc: float, dp: float,
             wn: float = 0.0, we: float = 0.0, wd: float = 0.0) -> list[float]:
    """One classical Runge-Kutta step of ``dt`` seconds with the inputs and wind held."""
    h2 = 0.5 * dt
    k1 = f(x, dl, dn, dc, dp, wn, we, wd)
    k2 = f([a + h2 * b for a, b in zip(x, k1, strict=False)], dl, dn, dc, dp, wn, we, wd)
    k3 = f([a + h2 * b for a, b in zip(x, k2, strict=False)], dl, dn, dc, dp, wn, we, wd)
    k4 = f([a + dt * b for a, b in zip(x, k3, strict=False)], dl, dn, dc, dp, wn, we, wd)
    h6 = dt / 6.0
    return [a + h6 * (b1 + 2.0 * (b2 + b3) + b4) for a, b1, b2, b3, b4 in zip(x, k1, k2, k3, k4, strict=False)]


def eq8_matrices(params: Mapping[str, float]) -> tuple[list[list[float]], list[list[float]],
                                                       list[list[float]], list[list[float]]]:
    """The paper's eq.-8 matrices as nested lists (the pilot designs its loops on them).

    Returns ``A_hor (8x8), B_hor (8x2), A_ver (3x3), B_ver (3x2)``; states ``u v theta phi q p a_s b_s``
    and ``w r r_fb``.
    """
    P = {k: float(v) for k, v in params.items()}
    g = G_M_S2
    it = P["inv_tau_s"]
    Ah: list[list[float]] = [
        [P["X_u"], 0, -g, 0, 0, 0, -g, 0],
        [0, P["Y_v"], 0, g, 0, 0, 0, g],
        [0, 0, 0, 0, 1, 0, 0, 0],
        [0, 0, 0, 0, 0, 1, 0, 0],
        [P["M_u"], P["M_v"], 0, 0, P["M_q"], 0, P["M_a"], P["M_b"]],
        [P["L_u"], P["L_v"], 0, 0, 0, P["L_p"], P["L_a"], P["L_b"]],
        [0, 0, 0, 0, -1, P["k1"], -it, 0],
        [0, 0, 0, 0, -P["k1"], -1, 0, -it],
    ]
    Bh: list[list[float]] = [[P["X_lat"], 0], [0, P["Y_lon"]], [0, 0], [0, 0], [P["M_lat"], P["M_lon"]], [P["L_lat"], P["L_lon"]],
          [P["A_lat"], 0], [0, P["B_lon"]]]
    Av: list[list[float]] = [[P["Z_w"], P["Z_r"], 0], [P["N_w"], P["N_r"], -P["N_ped"]], [0, P["k_r"], 2.0 * P["N_r"]]]
    Bv: list[list[float]] = [[P["Z_col"], P["Z_ped"]], [P["N_col"], P["N_ped"]], [0, 0]]
    return ([[float(a) for a in row] for row in Ah], [[float(a) for a in row] for row in Bh],
            [[float(a) for a in row] for row in Av], [[float(a) for a in row] for row in Bv])


_NAMES12 = ("u", "v", "w", "p", "q", "r", "ph", "th", "ps", "as_", "bs", "rfb", "pn", "pe", "pd")


def _deriv_source(P: dict[str, float], *, wind: bool, drag: float, ge: bool, Ic: tuple[float, float, float],
                  linear: bool = False) -> str:
    """Source lines of the derivative (same equations as :func:`make_derivative`) with ``{i}``
    marking the stage's state suffix and ``{o}`` the derivative suffix; ``linear``: the rigid body
    linearised about hover (see :func:`make_stepper`)."""
    c = {k: repr(float(v)) for k, v in P.items()}
    c["N_fb"] = repr(-float(P["N_ped"]))
    c["k_fb"] = repr(-2.0 * float(P["N_r"]))
    g = repr(G_M_S2)
    L = [
        "sph = sin(ph{i}); cph = cos(ph{i}); sth = sin(th{i}); cth = cos(th{i}); sps = sin(ps{i}); cps = cos(ps{i})",
        "r11 = cth * cps; r12 = sph * sth * cps - cph * sps; r13 = cph * sth * cps + sph * sps",
        "r21 = cth * sps; r22 = sph * sth * sps + cph * cps; r23 = cph * sth * sps - sph * cps",
        "r32 = sph * cth; r33 = cph * cth",
    ]
    if wind:
        L += ["ua = u{i} - (r11 * wn + r21 * we - sth * wd)",
              "va = v{i} - (r12 * wn + r22 * we + r32 * wd)",
              "wa = w{i} - (r13 * wn + r23 * we + r33 * wd)"]
    else:
        L += ["ua = u{i}; va = v{i}; wa = w{i}"]
    L += [f"T = {g} - {c['Z_w']} * wa - {c['Z_r']} * r{{i}} - {c['Z_col']} * dc - {c['Z_ped']} * dp"]
    if ge:
        L += ["T *= 1.0 + ge_gain * ge_fn(-pd{i}, radius, hub)"]
    if linear:  # rotor tilt to first order about the trim thrust g
        L += [f"fx = -{g} * as_{{i}} + {c['X_u']} * ua + {c['X_lat']} * dl",
              f"fy = {g} * bs{{i}} + {c['Y_v']} * va + {c['Y_lon']} * dn",
              "fz = -T"]
    else:
        L += [f"fx = -T * sin(as_{{i}}) + {c['X_u']} * ua + {c['X_lat']} * dl",
              f"fy = T * sin(bs{{i}}) + {c['Y_v']} * va + {c['Y_lon']} * dn",
              "fz = -T * cos(as_{i}) * cos(bs{i})"]
    if drag:
        d = repr(float(drag))
        L += [f"fx -= {d} * abs(ua) * ua", f"fy -= {d} * abs(va) * va", f"fz -= {d} * abs(wa) * wa"]
    cpx, cqy, crz = (repr(v) for v in ((0.0, 0.0, 0.0) if linear else Ic))
    if linear:  # small angles, no velocity-rate products, Euler rates = body rates
        L += [
            f"ku{{o}} = -{g} * th{{i}} + fx",
            f"kv{{o}} = {g} * ph{{i}} + fy",
            f"kw{{o}} = {g} + fz",
        ]
    else:
        L += [
            f"ku{{o}} = r{{i}} * v{{i}} - q{{i}} * w{{i}} - {g} * sth + fx",
            f"kv{{o}} = p{{i}} * w{{i}} - r{{i}} * u{{i}} + {g} * r32 + fy",
            f"kw{{o}} = q{{i}} * u{{i}} - p{{i}} * v{{i}} + {g} * r33 + fz",
        ]
    L += [
        "qsrc = q{i} * sph + r{i} * cph",
        f"kp{{o}} = {c['L_u']} * ua + {c['L_v']} * va + {c['L_p']} * p{{i}} + {c['L_a']} * as_{{i}} + {c['L_b']} * bs{{i}}"
        f" + {c['L_lat']} * dl + {c['L_lon']} * dn + {cpx} * q{{i}} * r{{i}}",
        f"kq{{o}} = {c['M_u']} * ua + {c['M_v']} * va + {c['M_q']} * q{{i}} + {c['M_a']} * as_{{i}} + {c['M_b']} * bs{{i}}"
        f" + {c['M_lat']} * dl + {c['M_lon']} * dn + {cqy} * p{{i}} * r{{i}}",
        f"kr{{o}} = {c['N_w']} * wa + {c['N_r']} * r{{i}} + {c['N_fb']} * rfb{{i}} + {c['N_col']} * dc"
        f" + {c['N_ped']} * dp + {crz} * p{{i}} * q{{i}}",
    ]
    if linear:
        L += ["kph{o} = p{i}", "kth{o} = q{i}", "kps{o} = r{i}"]
    else:
        L += ["kph{o} = p{i} + qsrc * sth / cth", "kth{o} = q{i} * cph - r{i} * sph", "kps{o} = qsrc / cth"]
    L += [
        f"kas_{{o}} = -q{{i}} + {c['k1']} * p{{i}} - {c['inv_tau_s']} * as_{{i}} + {c['A_lat']} * dl",
        f"kbs{{o}} = -{c['k1']} * q{{i}} - p{{i}} - {c['inv_tau_s']} * bs{{i}} + {c['B_lon']} * dn",
        f"krfb{{o}} = {c['k_r']} * r{{i}} - {c['k_fb']} * rfb{{i}}",
        "kpn{o} = r11 * u{i} + r12 * v{i} + r13 * w{i}",
        "kpe{o} = r21 * u{i} + r22 * v{i} + r23 * w{i}",
        "kpd{o} = -sth * u{i} + r32 * v{i} + r33 * w{i}",
    ]
    return "\n".join(L)


def make_stepper(ac: Aircraft, *, drag_c_per_m: float = 0.0, ground_effect_gain: float = 0.0,
                 wind: bool = False, linear_kinematics: bool = False) -> Callable[..., list[float]]:
    """A fused RK4 step ``step(x, dt, d_lat, d_lon, d_col, d_ped, wn, we, wd) -> x_next``.

    The same equations and arithmetic as ``rk4_step(make_derivative(ac, ...), ...)``, generated as
    one straight-line function of scalars (no per-stage lists or calls): about twice as fast,
    which is what makes ten minutes of flight take seconds. ``wind=False`` drops the air-mass terms.

    ``linear_kinematics=True``: the rigid body linearised about hover, i.e. nonlinear kinematics
    off: gravity to first order in the attitude (``-g theta``, ``g phi``), no velocity-rate products
    (``r v - q w``, ...), no inertia coupling (``(Iyy - Izz)/Ixx q r``, ...), Euler rates equal to
    the body rates, rotor tilt forces to first order about the trim thrust (``-g a_s``, ``g b_s``).
    The rotor, control and stability terms, the effects (drag, ground effect, wind) and the position
    (full rotation to NED, which the sensors read) are unchanged.
    """
    Ixx, Iyy, Izz = (float(v) for v in ac.inertia_kg_m2)
    Ic = ((Iyy - Izz) / Ixx, (Izz - Ixx) / Iyy, (Ixx - Iyy) / Izz)
    P = {k: float(v) for k, v in ac.parameters.items()}
    body = _deriv_source(P, wind=wind, drag=float(drag_c_per_m), ge=bool(ground_effect_gain), Ic=Ic,
                         linear=linear_kinematics)
    n = _NAMES12
    src = ["def step(x, h, dl, dn, dc, dp, wn=0.0, we=0.0, wd=0.0):",
           "    h2 = 0.5 * h",
           "    h6 = h / 6.0",
           f"    {', '.join(s + '0' for s in n)} = x"]

    def emit(i: str, o: str) -> None:
        src.extend("    " + line for line in body.format(i=i, o=o).splitlines())

    emit("0", "1")
    src += [f"    {s}1 = {s}0 + h2 * k{s}1" for s in n]
    emit("1", "2")
    src += [f"    {s}2 = {s}0 + h2 * k{s}2" for s in n]
    emit("2", "3")
    src += [f"    {s}3 = {s}0 + h * k{s}3" for s in n]
    emit("3", "4")
    src.append("    return [" + ", ".join(f"{s}0 + h6 * (k{s}1 + 2.0 * (k{s}2 + k{s}3) + k{s}4)" for s in n) + "]")
    ns: dict[str, object] = {"sin": math.sin, "cos": math.cos, "ge_fn": ground_effect_excess,
                             "ge_gain": float(ground_effect_gain), "radius": ac.rotor_radius_m, "hub": ac.hub_height_m}
    exec(compile("\n".join(src), f"<hil_replay.sim stepper {ac.name}>", "exec"), ns)  # noqa: S102
    return ns["step"]  # type: ignore[return-value]
