"""Kinematics of the ROOM continuum bronchoscope: closed form vs the Cosserat ODE, Jacobian, IK."""
from __future__ import annotations

import math
from fractions import Fraction

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st
from scipy.integrate import solve_ivp

from room_pipeline.errors import ConfigError
from room_pipeline.robot import kinematics as K
from room_pipeline.robot.inverse_kinematics import IKResult, ik
from room_pipeline.robot.kinematics import DEFAULT_GEOMETRY as G
from room_pipeline.robot.kinematics import ScopeGeometry, clamp_q, fk, jacobian, kappa

EPS = np.finfo(float).eps
SPECIAL_Q1 = [0.0, 1e-12, -1e-12, 1e-6, -1e-6, G.q1_max, -G.q1_max]
PROP = settings(deadline=None, max_examples=100)

q1_in = st.floats(-G.q1_max, G.q1_max, allow_nan=False)
angle = st.floats(-20.0, 20.0, allow_nan=False)
insertion = st.floats(-0.3, 0.3, allow_nan=False)
q_in = st.tuples(q1_in, angle, insertion).map(np.array)


def q1_of_theta(theta: float, geometry: ScopeGeometry = G) -> float:
    """q1 giving bending angle theta over the whole segment."""
    return -2.0 * geometry.gamma * theta


# ----------------------------------------------------------------------------- reference ODE


def integrate(q, s_eval, geometry: ScopeGeometry = G):
    """dr/ds = R e3, dR/ds = R hat([kappa, 0, 0]) as 12 states, DOP853 rtol 1e-12 atol 1e-14."""
    k = float(kappa(q[0], geometry))

    def rhs(s, y):
        R = y[3:].reshape(3, 3)
        dR = np.zeros((3, 3))
        dR[:, 1] = k * R[:, 2]          # R hat(u) with u = k e1: columns (0, k R e3, -k R e2)
        dR[:, 2] = -k * R[:, 1]
        return np.concatenate([R[:, 2], dR.ravel()])

    c, s = math.cos(q[1]), math.sin(q[1])
    y0 = np.concatenate([[0.0, 0.0, q[2]], [c, -s, 0.0, s, c, 0.0, 0.0, 0.0, 1.0]])
    sol = solve_ivp(rhs, (0.0, geometry.l), y0, method="DOP853", rtol=1e-12, atol=1e-14,
                    t_eval=np.asarray(s_eval, dtype=float))
    assert sol.success
    return sol.y[:3].T, sol.y[3:].T.reshape(-1, 3, 3)


@pytest.mark.parametrize("q1", SPECIAL_Q1 + list(np.linspace(-G.q1_max, G.q1_max, 17)))
def test_fk_matches_cosserat_ode(q1):
    s_eval = np.linspace(0.0, G.l, 6)
    for q2 in (0.0, 0.7, -2.5):
        q = np.array([q1, q2, 0.013])
        r_ode, R_ode = integrate(q, s_eval)
        T = fk(q, s_eval)
        assert np.abs(T[:, :3, 3] - r_ode).max() <= 1e-9
        assert np.abs(T[:, :3, :3] - R_ode).max() <= 1e-10
        np.testing.assert_array_equal(fk(q)[None], fk(q, [G.l]))   # default s is the tip


def test_fk_is_a_rigid_transform():
    q = np.array([[q1, q2, 0.02] for q1 in SPECIAL_Q1 for q2 in (-1.0, 0.3, 4.0)])
    T = fk(q)
    R = T[:, :3, :3]
    np.testing.assert_allclose(R @ np.swapaxes(R, 1, 2), np.broadcast_to(np.eye(3), R.shape), atol=4 * EPS)
    np.testing.assert_allclose(np.linalg.det(R), 1.0, atol=4 * EPS)
    np.testing.assert_array_equal(T[:, 3], np.broadcast_to([0.0, 0.0, 0.0, 1.0], (len(q), 4)))


def test_tip_frame_conventions():
    """Tip z = tangent d r / d s (view direction); x = bending axis; kappa > 0 turns z to -y."""
    q = np.array([-0.004, 0.4, 0.01])                            # q1 < 0: kappa > 0
    k = float(kappa(q[0]))
    s, h = 0.03, 1e-6
    T = fk(q, s)
    tangent = (fk(q, s + h)[:3, 3] - fk(q, s - h)[:3, 3]) / (2 * h)
    np.testing.assert_allclose(tangent, T[:3, 2], atol=1e-9)
    dz_ds = (fk(q, s + h)[:3, 2] - fk(q, s - h)[:3, 2]) / (2 * h)
    np.testing.assert_allclose(dz_ds, -k * T[:3, 1], atol=1e-7)
    np.testing.assert_allclose(fk(q, 0.0)[:3, 0], fk(q, G.l)[:3, 0], atol=1e-15)   # bending axis
    base = fk(q, 0.0)
    np.testing.assert_allclose(base[:3, 3], [0.0, 0.0, q[2]], atol=0)
    np.testing.assert_allclose(base[:3, 2], [0.0, 0.0, 1.0], atol=0)
    # q2 = 0, kappa > 0: bends in the base y-z plane towards -y
    p = fk([-0.004, 0.0, 0.0])[:3, 3]
    assert p[0] == 0.0 and p[1] < 0.0


# ----------------------------------------------------------------------------- series / switches


def _sin_cos_exact(x: float, terms: int = 40) -> tuple[Fraction, Fraction]:
    x = Fraction(x)
    sin, cos, ts, tc = Fraction(0), Fraction(0), x, Fraction(1)
    for n in range(terms):
        sin, cos = sin + ts, cos + tc
        ts = -ts * x * x / ((2 * n + 2) * (2 * n + 3))
        tc = -tc * x * x / ((2 * n + 1) * (2 * n + 2))
    return sin, cos


@pytest.mark.parametrize("x", [1e-300, 1e-8, 1e-3, 0.0999, 0.1, 0.1001, 0.5, 1.0, 1.9999, 2.0, 2.0001, 2.29, 3.0])
def test_series_helpers_against_exact_arithmetic(x):
    sin, cos = _sin_cos_exact(x)
    X = Fraction(x)
    refs = {K._sinc: sin / X, K._cosc: (1 - cos) / X**2, K._dsinc: (sin - X * cos) / X**2}
    for fn, ref in refs.items():
        for sign in (1, -1):
            value = float(fn(np.float64(sign * x)))
            expected = float(ref) * (sign if fn is K._dsinc else 1)
            assert abs(value - expected) <= 4 * EPS * abs(expected), (fn.__name__, x)


def test_branches_agree_at_the_switch_points():
    def direct_sinc(x):
        return math.sin(x) / x

    def direct_dsinc(x):
        return (math.sin(x) - x * math.cos(x)) / (x * x)

    for fn, direct, x_s in ((K._sinc, direct_sinc, K._SINC_SWITCH), (K._dsinc, direct_dsinc, K._D_SWITCH)):
        below = np.nextafter(x_s, 0.0)
        series = float(fn(np.float64(below)))
        assert abs(series - direct(below)) <= 2 * EPS * abs(series)
        assert abs(float(fn(np.float64(x_s))) - series) <= 2 * EPS * abs(series)
    assert float(K._sinc(np.float64(0.0))) == 1.0 and float(K._cosc(np.float64(0.0))) == 0.5
    assert float(K._dsinc(np.float64(0.0))) == 0.0


def test_straight_limit_is_continuous():
    straight = fk([0.0, 0.9, 0.02])
    np.testing.assert_array_equal(straight[:3, 3], [0.0, 0.0, 0.02 + G.l])
    np.testing.assert_array_equal(straight[:3, 2], [0.0, 0.0, 1.0])
    for k in (1e-12, -1e-12):
        q1 = -2.0 * G.gamma * G.l * k
        T = fk([q1, 0.9, 0.02])
        assert np.all(np.isfinite(T))
        assert np.abs(T[:3, 3] - straight[:3, 3]).max() <= 2e-15          # offset is l^2 k / 2 ~ 1e-15
        assert np.abs(T[:3, :3] - straight[:3, :3]).max() <= 1e-13        # angle l k = 5e-14
        lateral = math.hypot(T[0, 3], T[1, 3])
        assert lateral == pytest.approx(G.l**2 * abs(k) / 2, rel=1e-12)


# ----------------------------------------------------------------------------- Jacobian


def _central_fd(q, s=None):
    steps = np.array([1e-7, 1e-6, 1e-6])
    J = np.empty((6, 3))
    for j in range(3):
        dq = np.zeros(3)
        dq[j] = steps[j]
        Tp, Tm = fk(q + dq, s), fk(q - dq, s)
        fp = np.concatenate([Tp[:3, 3], Tp[:3, 2]])
        fm = np.concatenate([Tm[:3, 3], Tm[:3, 2]])
        J[:, j] = (fp - fm) / (2 * steps[j])
    return J


@pytest.mark.parametrize("theta", [0.0, 1e-12, -1e-9, 0.05, -0.2, 0.2 + 1e-9, 0.7, -1.5, 2.0, -2.0 + 1e-9, 2.2857])
def test_jacobian_matches_central_differences(theta):
    for q2, s in ((0.3, None), (-2.0, 0.031)):
        q = np.array([q1_of_theta(theta), q2, -0.04])
        J = jacobian(q, s)
        np.testing.assert_allclose(J, _central_fd(q, s), rtol=1e-6, atol=1e-8)


def test_jacobian_continuous_across_switches():
    # the helpers switch at |theta| = 0.2 (sinc(theta/2)), 0.1 (sinc(theta)) and 2.0 (dsinc)
    for theta in (0.2, 0.1, 2.0):
        a = jacobian([q1_of_theta(theta * (1 - 1e-12)), 0.4, 0.0])
        b = jacobian([q1_of_theta(theta * (1 + 1e-12)), 0.4, 0.0])
        np.testing.assert_allclose(a, b, rtol=1e-10, atol=1e-13)


def test_batched_fk_and_jacobian_match_single_calls():
    rng = np.random.default_rng(3)
    q = np.column_stack([rng.uniform(-G.q1_max, G.q1_max, 20), rng.uniform(-4, 4, 20), rng.uniform(-0.1, 0.1, 20)])
    q[:3, 0] = [0.0, 1e-12, -G.q1_max]
    T, J = fk(q), jacobian(q)
    assert T.shape == (20, 4, 4) and J.shape == (20, 6, 3)
    for i in range(20):
        np.testing.assert_array_equal(T[i], fk(q[i]))
        np.testing.assert_array_equal(J[i], jacobian(q[i]))
    s = np.linspace(0, G.l, 7)
    assert fk(q[0], s).shape == (7, 4, 4)
    assert fk(q.reshape(4, 5, 3)).shape == (4, 5, 4, 4)


# ----------------------------------------------------------------------------- parameters, limits


def test_geometry_curvature_bound():
    assert G.kappa_max == pytest.approx(0.008 / (2 * 1.75e-3 * 0.05))
    assert round(G.kappa_max, 2) == 45.71
    assert float(kappa(G.q1_max)) == pytest.approx(-G.kappa_max)
    assert float(kappa(-G.q1_max)) == pytest.approx(G.kappa_max)
    assert G.theta_max == pytest.approx(G.kappa_max * G.l)
    th = K.THETA_TURN
    assert math.tan(th / 2) == pytest.approx(th, rel=1e-14)               # turn of (1 - cos t)/t
    assert G.theta_max < th


def test_geometry_from_dict():
    assert ScopeGeometry.from_dict(None) == ScopeGeometry()
    g = ScopeGeometry.from_dict({"l": 0.04, "gamma": 2e-3, "q1_max": 0.006})
    assert (g.l, g.gamma, g.q1_max) == (0.04, 2e-3, 0.006)
    with pytest.raises(ConfigError, match="lenght") as err:
        ScopeGeometry.from_dict({"l": 0.05, "lenght": 0.05})
    assert "\n" not in str(err.value)
    for bad in ({"l": -0.05}, {"gamma": 0}, {"q1_max": float("nan")}, {"l": "5cm"}, {"l": True}):
        with pytest.raises(ConfigError):
            ScopeGeometry.from_dict(bad)


def test_joint_limits_clamp_and_fk_extrapolates():
    np.testing.assert_array_equal(clamp_q([0.02, 7.0, -1.0]), [G.q1_max, 7.0, -1.0])
    np.testing.assert_array_equal(clamp_q([[-1.0, 0, 0], [0.001, 0, 0]])[:, 0], [-G.q1_max, 0.001])
    T = fk([0.012, 0.0, 0.0])                                          # beyond the limit: evaluated
    assert np.all(np.isfinite(T)) and T[2, 2] == pytest.approx(math.cos(0.012 / (2 * G.gamma)))
    with pytest.raises(ValueError):
        fk([0.0, 0.0, 0.0], s=G.l * 1.01)
    with pytest.raises(ValueError):
        fk([0.0, 0.0], s=None)
    with pytest.raises(ValueError):
        ik([0.0, 0.0, 0.1], [0.0, 0.0, 0.0])
    with pytest.raises(ValueError):
        ik([0.0, np.nan, 0.1])


def test_q2_periodicity_and_equivalent_branch():
    for q1 in SPECIAL_Q1:
        q = np.array([q1, 0.8, 0.01])
        np.testing.assert_allclose(fk(q + [0, 2 * math.pi, 0]), fk(q), atol=1e-15)
        T, Tb = fk(q), fk([-q1, 0.8 + math.pi, 0.01])                  # same position and direction,
        np.testing.assert_allclose(Tb[:3, 3], T[:3, 3], atol=1e-17)     # roll differs by pi
        np.testing.assert_allclose(Tb[:3, 2], T[:3, 2], atol=1e-15)
        np.testing.assert_allclose(Tb[:3, :2], -T[:3, :2], atol=1e-15)


def test_q3_is_a_pure_translation():
    for q1 in SPECIAL_Q1:
        T0, T1 = fk([q1, -1.1, 0.0]), fk([q1, -1.1, 0.25])
        np.testing.assert_array_equal(T1[:3, :3], T0[:3, :3])
        np.testing.assert_allclose(T1[:3, 3] - T0[:3, 3], [0.0, 0.0, 0.25], atol=1e-16)


# ----------------------------------------------------------------------------- IK


def _cost(q, p, t, w=G.l):
    T = fk(q)
    return float(np.sum((T[:3, 3] - p) ** 2) + w**2 * np.sum((T[:3, 2] - t) ** 2))


def test_ik_on_axis_is_straight_without_nan():
    r = ik([0.0, 0.0, 0.1])
    assert r.reachable and r.q.tolist() == [0.0, 0.0, 0.1 - G.l] and r.iterations == 0
    r = ik([0.0, 0.0, 0.1], q0=[0.003, 1.3, 0.0])
    assert r.reachable and r.q[0] == 0.0 and r.q[1] == 1.3
    r = ik([0.0, 0.0, 0.1], [0.0, 0.0, 2.0], q0=[0.0, -0.5, 0.0])
    assert r.reachable and r.q.tolist() == [0.0, -0.5, 0.1 - G.l]
    assert r.position_error_m == 0.0 and r.direction_error_rad == 0.0
    for p in ([1e-300, 0.0, 0.0], [0.0, -1e-18, 0.05]):
        r = ik(p)
        assert np.all(np.isfinite(r.q)) and r.reachable


def test_ik_unreachable_position_is_the_radial_projection():
    rho_max = float(fk([G.q1_max, 0.0, 0.0])[1, 3])                  # lateral reach at full bend
    r = ik([0.03, 0.04, 0.2])
    assert not r.reachable and abs(r.q[0]) == G.q1_max
    assert r.position_error_m == pytest.approx(0.05 - rho_max, rel=1e-12)
    p = fk(r.q)[:3, 3]
    np.testing.assert_allclose(p, [0.03 * rho_max / 0.05, 0.04 * rho_max / 0.05, 0.2], atol=1e-15)


def test_ik_branch_follows_q0():
    p = fk([0.005, 0.3, 0.02])[:3, 3]
    a = ik(p)
    b = ik(p, q0=[0.0, 0.3 + math.pi - 0.1, 0.0])
    c = ik(p, q0=[0.0, 0.3 + 6 * math.pi, 0.0])
    assert a.q[1] == pytest.approx(0.3) and a.q[0] == pytest.approx(0.005)
    assert b.q[1] == pytest.approx(0.3 + math.pi) and b.q[0] == pytest.approx(-0.005)
    assert c.q[1] == pytest.approx(0.3 + 6 * math.pi)
    for r in (a, b, c):
        assert r.reachable and r.position_error_m <= 1e-15


def test_ik_unreachable_pose_is_a_local_optimum():
    p, t = np.array([0.02, -0.01, 0.03]), np.array([1.0, 1.0, 0.2]) / math.sqrt(2.04)
    r = ik(p, t)
    assert isinstance(r, IKResult) and not r.reachable and r.iterations >= 0
    assert abs(r.q[0]) <= G.q1_max
    best = _cost(r.q, p, t)
    rng = np.random.default_rng(0)
    for _ in range(200):
        qq = clamp_q(r.q + rng.normal(size=3) * [2e-5, 2e-3, 2e-4])
        assert _cost(qq, p, t) >= best * (1 - 1e-9)
    T = fk(r.q)
    assert r.position_error_m == pytest.approx(np.linalg.norm(T[:3, 3] - p))
    assert r.direction_error_rad == pytest.approx(math.acos(float(T[:3, 2] @ t)))


def test_ik_unreachable_pose_is_the_global_optimum():
    """Against brute force over (theta, q2) with q3 matching z: no grid point does better."""
    rng = np.random.default_rng(11)
    th, q2 = np.meshgrid(np.linspace(-G.theta_max, G.theta_max, 201), np.linspace(-np.pi, np.pi, 201))
    grid = np.stack([q1_of_theta(1.0) * th.ravel(), q2.ravel(), np.zeros(th.size)], axis=-1)
    for _ in range(12):
        p = rng.uniform(-0.08, 0.08, 3)
        t = rng.normal(size=3)
        t /= np.linalg.norm(t)
        r = ik(p, t)
        assert not r.reachable and abs(r.q[0]) <= G.q1_max
        grid[:, 2] = p[2] - fk(grid * [1, 1, 0])[:, 2, 3]
        T = fk(grid)
        costs = np.sum((T[:, :3, 3] - p) ** 2, axis=-1) + G.l**2 * np.sum((T[:, :3, 2] - t) ** 2, axis=-1)
        assert _cost(r.q, p, t) <= costs.min() + 1e-18
    with pytest.raises(ValueError):
        ik([0.0, 0.0, 0.1], [1.0, 0.0, 0.0], direction_weight_m=-1.0)


def test_ik_custom_geometry_bending_past_pi():
    g = ScopeGeometry(q1_max=0.02)                                     # theta_max = 5.7 rad > pi
    for q1 in np.linspace(-0.02, 0.02, 9):
        T = fk([q1, 0.3, 0.01], geometry=g)
        r = ik(T[:3, 3], T[:3, 2], geometry=g)
        assert r.reachable and abs(r.q[0]) <= g.q1_max
        assert ik(T[:3, 3], geometry=g).reachable


@PROP
@given(q=q_in, s_frac=st.floats(0.0, 1.0))
def test_prop_position_ik_round_trip(q, s_frac):
    s = s_frac * G.l
    p = fk(q, s)[:3, 3]
    r = ik(p, s=s)
    assert r.reachable and abs(r.q[0]) <= G.q1_max
    assert np.linalg.norm(fk(r.q, s)[:3, 3] - p) <= 1e-9
    assert r.position_error_m <= 1e-9


@PROP
@given(q=q_in, q0=q_in)
def test_prop_pose_ik_round_trip(q, q0):
    T = fk(q)
    r = ik(T[:3, 3], T[:3, 2], q0=q0)
    assert r.reachable and abs(r.q[0]) <= G.q1_max
    T2 = fk(r.q)
    assert np.linalg.norm(T2[:3, 3] - T[:3, 3]) <= 1e-9
    assert math.atan2(np.linalg.norm(np.cross(T2[:3, 2], T[:3, 2])), T2[:3, 2] @ T[:3, 2]) <= 1e-9
    assert abs(r.q[1] - q0[1]) <= math.pi + 1e-12                         # branch/wrap near q0


@PROP
@given(p=st.tuples(*[st.floats(-0.08, 0.08)] * 3).map(np.array),
       t=st.one_of(st.none(), st.tuples(*[st.floats(-1, 1)] * 3).map(np.array).filter(lambda v: v @ v > 1e-6)))
def test_prop_ik_within_limits_for_any_target(p, t):
    r = ik(p, t)
    assert r.q.shape == (3,) and np.all(np.isfinite(r.q)) and abs(r.q[0]) <= G.q1_max
    assert np.isfinite(r.position_error_m) and np.isfinite(r.direction_error_rad)
    if t is None:
        rho_max = float(fk([G.q1_max, 0.0, 0.0])[1, 3])
        rho = math.hypot(p[0], p[1])
        assert r.position_error_m == pytest.approx(max(rho - rho_max, 0.0), abs=1e-15)
        assert r.reachable == (rho <= rho_max)


@PROP
@given(q1=st.floats(-10 * G.q1_max, 10 * G.q1_max), q2=st.floats(-1e4, 1e4), q3=st.floats(-10, 10),
       s_frac=st.floats(0.0, 1.0))
def test_prop_fk_and_jacobian_finite(q1, q2, q3, s_frac):
    q = np.array([q1, q2, q3])
    assert np.all(np.isfinite(fk(q, s_frac * G.l)))
    assert np.all(np.isfinite(jacobian(q, s_frac * G.l)))
