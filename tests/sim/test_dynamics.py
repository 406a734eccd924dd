"""The nonlinear model: hover Jacobian = eq. 8 (independently coded here), trim, effects in the physics."""

from __future__ import annotations

import numpy as np
import pytest

from hil_replay.sim.aircraft import PARAM_NAMES, Aircraft, resolve_aircraft
from hil_replay.sim.dynamics import IDX, ground_effect_excess, make_derivative

G = 9.81
HOR = ("u", "v", "theta", "phi", "q", "p", "a_s", "b_s")
VER = ("w", "r", "r_fb")


def paper_eq8(P: dict[str, float]) -> tuple[np.ndarray, ...]:
    """Eq. 8 as printed in the paper (docs/model-file.md; written here again on purpose)."""
    A_hor = np.array([
        [P["X_u"], 0, -G, 0, 0, 0, -G, 0],
        [0, P["Y_v"], 0, G, 0, 0, 0, G],
        [0, 0, 0, 0, 1, 0, 0, 0],
        [0, 0, 0, 0, 0, 1, 0, 0],
        [P["M_u"], P["M_v"], 0, 0, P["M_q"], 0, P["M_a"], P["M_b"]],
        [P["L_u"], P["L_v"], 0, 0, 0, P["L_p"], P["L_a"], P["L_b"]],
        [0, 0, 0, 0, -1, P["k1"], -P["inv_tau_s"], 0],
        [0, 0, 0, 0, -P["k1"], -1, 0, -P["inv_tau_s"]],
    ])
    B_hor = np.array([[P["X_lat"], 0], [0, P["Y_lon"]], [0, 0], [0, 0], [P["M_lat"], P["M_lon"]],
                      [P["L_lat"], P["L_lon"]], [P["A_lat"], 0], [0, P["B_lon"]]])
    N_fb, k_fb = -P["N_ped"], -2 * P["N_r"]
    A_ver = np.array([[P["Z_w"], P["Z_r"], 0], [P["N_w"], P["N_r"], N_fb], [0, P["k_r"], -k_fb]])
    B_ver = np.array([[P["Z_col"], P["Z_ped"]], [P["N_col"], P["N_ped"]], [0, 0]])
    return A_hor, B_hor, A_ver, B_ver


def numerical_jacobian(ac: Aircraft, eps: float = 1e-6) -> tuple[np.ndarray, np.ndarray]:
    """Central differences of the full nonlinear derivative at hover: (15x15, 15x4)."""
    f = make_derivative(ac)
    x0 = np.zeros(15)
    d0 = np.zeros(4)
    A = np.zeros((15, 15))
    B = np.zeros((15, 4))
    for j in range(15):
        xp, xm = x0.copy(), x0.copy()
        xp[j] += eps
        xm[j] -= eps
        A[:, j] = (np.array(f(list(xp), *d0)) - np.array(f(list(xm), *d0))) / (2 * eps)
    for j in range(4):
        dp, dm = d0.copy(), d0.copy()
        dp[j] += eps
        dm[j] -= eps
        B[:, j] = (np.array(f(list(x0), *dp)) - np.array(f(list(x0), *dm))) / (2 * eps)
    return A, B


def _perturbed(seed: int) -> Aircraft:
    base = resolve_aircraft(None)
    rng = np.random.default_rng(seed)
    params = {n: float(v) * float(rng.uniform(0.5, 1.5)) for n, v in base.parameters.items()}
    return Aircraft(name="perturbed", parameters=params)


@pytest.mark.parametrize("ac", [resolve_aircraft(None), _perturbed(1), _perturbed(2)], ids=["trex600", "p1", "p2"])
def test_hover_jacobian_is_paper_eq8(ac: Aircraft) -> None:
    A, B = numerical_jacobian(ac)
    Ah, Bh, Av, Bv = paper_eq8(dict(ac.parameters))
    hi = [IDX[s] for s in HOR]
    vi = [IDX[s] for s in VER]
    blocks = {
        "A_hor": (A[np.ix_(hi, hi)], Ah), "B_hor": (B[np.ix_(hi, [0, 1])], Bh),
        "A_ver": (A[np.ix_(vi, vi)], Av), "B_ver": (B[np.ix_(vi, [2, 3])], Bv),
        # the two subsystems do not couple at hover
        "A_hv": (A[np.ix_(hi, vi)], np.zeros((8, 3))), "A_vh": (A[np.ix_(vi, hi)], np.zeros((3, 8))),
        "B_h_colped": (B[np.ix_(hi, [2, 3])], np.zeros((8, 2))), "B_v_latlon": (B[np.ix_(vi, [0, 1])], np.zeros((3, 2))),
    }
    scale = max(np.abs(Ah).max(), np.abs(Av).max())
    for name, (num, ref) in blocks.items():
        err = np.abs(num - ref)
        # relative error per entry (absolute against the matrix scale for zero entries)
        tol = 1e-3 * np.maximum(np.abs(ref), 1e-3 * scale)
        assert (err <= tol).all(), f"{name}: max error {err.max():.3g}\n{num}\n!=\n{ref}"


def test_hover_trim_is_an_equilibrium() -> None:
    f = make_derivative(resolve_aircraft(None))
    assert np.allclose(f([0.0] * 15, 0, 0, 0, 0), 0.0, atol=1e-12)
    # heading and position do not matter
    x = [0.0] * 15
    x[IDX["psi"]], x[IDX["n"]], x[IDX["e"]], x[IDX["d"]] = 2.0, 5.0, -3.0, -7.0
    assert np.allclose(f(x, 0, 0, 0, 0), 0.0, atol=1e-12)


def test_quadratic_drag_grows_with_speed_squared() -> None:
    ac = resolve_aircraft(None)
    f0 = make_derivative(ac)
    fd = make_derivative(ac, drag_c_per_m=0.05)
    extra = []
    for speed in (1.0, 2.0, 4.0):
        for axis in (0, 1, 2):
            x = [0.0] * 15
            x[axis] = speed
            diff = np.array(fd(x, 0, 0, 0, 0)) - np.array(f0(x, 0, 0, 0, 0))
            extra.append(diff[axis])
            others = np.delete(diff, axis)
            assert np.allclose(others, 0.0, atol=1e-12)
    extra_arr = np.array(extra).reshape(3, 3)
    assert np.allclose(extra_arr, -0.05 * np.array([1.0, 4.0, 16.0])[:, None], rtol=1e-9)


def test_forces_act_on_airspeed_not_ground_speed() -> None:
    """Hovering in a 3 m/s wind from ahead is aerodynamically flying at 3 m/s in still air."""
    ac = resolve_aircraft(None)
    f = make_derivative(ac)
    psi = 0.7
    still = [0.0] * 15
    still[IDX["psi"]] = psi
    moving = list(still)
    moving[IDX["u"]] = 3.0
    # air mass moving backwards along the heading at 3 m/s
    wn, we = -3.0 * np.cos(psi), -3.0 * np.sin(psi)
    a = np.array(f(still, 0, 0, 0, 0, wn, we, 0.0))
    b = np.array(f(moving, 0, 0, 0, 0))
    dyn = [IDX[s] for s in ("u", "v", "w", "p", "q", "r", "a_s", "b_s", "r_fb")]
    assert np.allclose(a[dyn], b[dyn], atol=1e-12)
    assert abs(b[IDX["q"]]) > 1.0  # M_u u: the airspeed really acts
    pos = [IDX["n"], IDX["e"]]
    assert np.allclose(a[pos], 0.0) and np.hypot(*b[pos]) == pytest.approx(3.0)  # ground speed differs


def test_ground_effect_only_below_about_one_rotor_diameter() -> None:
    ac = resolve_aircraft(None)
    R, hub, D = ac.rotor_radius_m, ac.hub_height_m, ac.rotor_diameter_m
    heights = np.linspace(0.0, 3 * D, 200)
    exc = np.array([ground_effect_excess(h, R, hub) for h in heights])
    rotor_z = heights + hub
    assert (exc[rotor_z < 0.75 * D] > 0.01).all()
    assert (exc[rotor_z >= 1.25 * D] == 0.0).all()
    assert (np.diff(exc) <= 1e-12).all()  # fades monotonically with height
    # Cheeseman-Bennett value at a rotor height of half a diameter
    z = 0.5 * D
    assert ground_effect_excess(z - hub, R, hub) == pytest.approx(1 / (1 - (R / (4 * z)) ** 2) - 1, rel=1e-9)
    # and in the dynamics: extra upward acceleration near the ground only
    f0 = make_derivative(ac)
    fg = make_derivative(ac, ground_effect_gain=1.0)
    for h, near in ((0.3, True), (5.0, False)):
        x = [0.0] * 15
        x[IDX["d"]] = -h
        dw = fg(x, 0, 0, 0, 0)[IDX["w"]] - f0(x, 0, 0, 0, 0)[IDX["w"]]
        assert (dw < -0.1) if near else (dw == 0.0)


def test_parameter_names_match_the_model_file_convention() -> None:
    from groundstation.sysid.model import PARAM_NAMES as SYSID_NAMES  # test-only cross-check

    assert PARAM_NAMES == SYSID_NAMES


@pytest.mark.parametrize("kw, wind", [({}, False), ({"drag_c_per_m": 0.05, "ground_effect_gain": 1.2}, True)])
def test_fused_stepper_is_rk4_of_the_tested_derivative(kw: dict, wind: bool) -> None:
    """The session integrates with the generated stepper: it must be the same model as ``f``."""
    from hil_replay.sim.dynamics import make_stepper, rk4_step

    ac = resolve_aircraft(None)
    f = make_derivative(ac, **kw)
    step = make_stepper(ac, wind=wind, **kw)
    rng = np.random.default_rng(4)
    for _ in range(50):
        x = rng.uniform(-0.3, 0.3, 15)
        x[14] = -abs(x[14]) - 0.1
        d = rng.uniform(-0.1, 0.1, 4)
        w = rng.uniform(-1.5, 1.5, 3) if wind else np.zeros(3)
        a = rk4_step(f, list(x), 0.005, *d, *w)
        b = step(list(x), 0.005, *d, *w)
        assert np.allclose(a, b, rtol=0, atol=1e-13)
    # and RK4 at 200 Hz converges: halving the step changes a 1 s trajectory by < 1e-6
    x1 = x2 = [0.02] * 14 + [-5.0]
    for _ in range(200):
        x1 = step(x1, 0.005, 0.02, -0.01, 0.01, 0.0)
    for _ in range(400):
        x2 = step(x2, 0.0025, 0.02, -0.01, 0.01, 0.0)
    assert np.abs(np.array(x1) - np.array(x2)).max() < 1e-6


def test_linear_kinematics_is_the_hover_linearisation() -> None:
    """Nonlinear kinematics off: the same model to first order about hover, different at large attitude."""
    from hil_replay.sim.dynamics import make_stepper

    ac = resolve_aircraft(None)
    nonlin = make_stepper(ac)
    lin = make_stepper(ac, linear_kinematics=True)
    hover = [0.0] * 14 + [-5.0]
    assert np.allclose(lin(hover, 0.005, 0, 0, 0, 0), nonlin(hover, 0.005, 0, 0, 0, 0), atol=1e-12)
    rng = np.random.default_rng(5)
    for scale in (1e-3, 1e-2):
        x = list(rng.uniform(-scale, scale, 15))
        x[14] = -5.0
        d = rng.uniform(-scale, scale, 4)
        a = np.array(nonlin(x, 0.005, *d)) - x
        b = np.array(lin(x, 0.005, *d)) - x
        # the step differs by second-order terms only: 100x smaller state, ~10^4x smaller difference
        assert np.max(np.abs(a - b)) < 0.1 * scale ** 2
    x = [0.0] * 15
    x[6], x[14] = 0.6, -5.0  # 0.6 rad of roll: g sin(phi) against g phi
    a, b = nonlin(x, 0.005, 0, 0, 0, 0), lin(x, 0.005, 0, 0, 0, 0)
    assert abs(a[1] - b[1]) > 1e-4


def test_session_with_linear_kinematics_flies_and_says_so(tmp_path) -> None:
    from hil_replay.sim import write_tlog

    t1 = write_tlog(tmp_path / "lin.tlog", seed=3, effects=[], flight_duration_s=30.0, linear_kinematics=True)
    t0 = write_tlog(tmp_path / "non.tlog", seed=3, effects=[], flight_duration_s=30.0)
    assert t1["linear_kinematics"] is True and t0["linear_kinematics"] is False
    assert (tmp_path / "lin.tlog").read_bytes() != (tmp_path / "non.tlog").read_bytes()
