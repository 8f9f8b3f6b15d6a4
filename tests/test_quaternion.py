"""Property tests of ``app.quaternion`` against scipy's Rotation as the independent reference.

scipy's quaternions are scalar LAST ``[x, y, z, w]``; ours are scalar first ``[w, x, y, z]``,
sensor->world (``v_world = Q(q) v_sensor``).
"""

from __future__ import annotations

import math

import numpy as np
import pytest
from hypothesis import example, given, settings, strategies as st
from scipy.spatial.transform import Rotation

from app import quaternion as qm

# no deadline: the first call of a numba function compiles it (or loads it from the cache)
prop = settings(deadline=None, max_examples=100)

unit = st.floats(-1.0, 1.0, allow_nan=False, allow_infinity=False)
quats = st.lists(unit, min_size=4, max_size=4).map(np.array).filter(
    lambda v: np.linalg.norm(v) > 0.1)
vec3 = st.lists(st.floats(-5.0, 5.0, allow_nan=False), min_size=3, max_size=3).map(np.array)
steps = st.floats(1e-4, 0.5)


def rot(q) -> Rotation:
    """scipy Rotation of our scalar-first quaternion."""
    q = np.asarray(q, dtype=float)
    return Rotation.from_quat([q[1], q[2], q[3], q[0]])


def ours(r: Rotation) -> np.ndarray:
    x, y, z, w = r.as_quat()
    return np.array([w, x, y, z])


def same_rotation(p, q, tol=1e-9) -> bool:
    return min(np.abs(p - q).max(), np.abs(p + q).max()) < tol


# ---------------------------------------------------------------- Q and its inverse

@prop
@given(quats)
def test_Q_equals_scipy_matrix(q):
    q = q / np.linalg.norm(q)
    np.testing.assert_allclose(qm.Q(q), rot(q).as_matrix(), atol=1e-12)


@prop
@given(quats)
def test_Q_maps_sensor_to_world(q):
    q = q / np.linalg.norm(q)
    v = np.array([0.3, -1.2, 2.0])
    np.testing.assert_allclose(qm.Q(q) @ v, rot(q).apply(v), atol=1e-12)


@prop
@given(quats)
def test_quat_from_matrix_inverts_Q(q):
    n = qm.normalize(q)
    back = qm.quat_from_matrix(qm.Q(n))
    assert back[0] >= 0.0
    assert same_rotation(back, n, 1e-9)
    # and on scipy's matrix, an independent source
    assert same_rotation(qm.quat_from_matrix(rot(n).as_matrix()), n, 1e-9)


@pytest.mark.parametrize("axis", range(3))
def test_quat_from_matrix_half_turns(axis):
    """The trace <= 0 pivots: rotations by pi about each axis."""
    v = np.zeros(3)
    v[axis] = math.pi
    r = Rotation.from_rotvec(v)
    q = qm.quat_from_matrix(r.as_matrix())
    assert same_rotation(q, ours(r), 1e-12)


# ---------------------------------------------------------------- normalize

@prop
@given(quats)
def test_normalize_unit_and_w_nonnegative(q):
    n = qm.normalize(q)
    assert n[0] >= 0.0
    assert abs(np.linalg.norm(n) - 1.0) < 1e-12
    np.testing.assert_allclose(qm.Q(n), rot(q).as_matrix(), atol=1e-12)  # same rotation
    assert np.allclose(n, q / np.linalg.norm(q)) or np.allclose(n, -q / np.linalg.norm(q))


def test_normalize_zero_and_nan_give_identity():
    np.testing.assert_array_equal(qm.normalize(np.zeros(4)), [1.0, 0.0, 0.0, 0.0])
    np.testing.assert_array_equal(qm.normalize(np.full(4, np.nan)), [1.0, 0.0, 0.0, 0.0])


# ---------------------------------------------------------------- products and angles

@prop
@given(quats, quats)
def test_quat_mul_matches_composition(p, q):
    p, q = p / np.linalg.norm(p), q / np.linalg.norm(q)
    pq = qm.quat_mul(p, q)
    np.testing.assert_allclose(qm.Q(pq), qm.Q(p) @ qm.Q(q), atol=1e-12)
    assert same_rotation(pq, ours(rot(p) * rot(q)), 1e-12)


@prop
@given(quats)
def test_conj_is_inverse(q):
    q = q / np.linalg.norm(q)
    np.testing.assert_allclose(qm.quat_mul(q, qm.quat_conj(q)), [1, 0, 0, 0], atol=1e-12)


@prop
@given(quats, quats)
def test_angle_between_is_relative_rotation_magnitude(p, q):
    p, q = p / np.linalg.norm(p), q / np.linalg.norm(q)
    expected = (rot(p).inv() * rot(q)).magnitude()
    assert abs(qm.angle_between(p, q) - expected) < 1e-6
    assert abs(qm.angle_between(p, -q) - expected) < 1e-6   # sign of q does not matter


@prop
@given(vec3)
def test_rotvec_round_trip(v):
    v = v * (min(1.0, 3.0 / max(np.linalg.norm(v), 1e-12)))  # angle below pi
    q = qm.quat_from_rotvec(v)
    assert same_rotation(q, ours(Rotation.from_rotvec(v)), 1e-12)
    np.testing.assert_allclose(qm.rotvec_from_quat(q), v, atol=1e-9)


# ---------------------------------------------------------------- derivatives (2d)-(2i)

@prop
@given(quats)
def test_dQdq_matches_finite_differences(q):
    D = qm.dQdq(q)
    h = 1e-6
    for i in range(4):
        e = np.zeros(4)
        e[i] = h
        fd = (qm.Q(q + e) - qm.Q(q - e)) / (2 * h)   # Q is quadratic: central differences exact
        np.testing.assert_allclose(D[i], fd, atol=1e-7)


@prop
@given(quats, vec3)
def test_S_omega_and_S_bar_identity(q, w):
    np.testing.assert_allclose(qm.S_omega(w) @ q, qm.S_bar(q) @ w, atol=1e-12)
    # both are the body-rate product q * [0, w]
    np.testing.assert_allclose(qm.S_omega(w) @ q, qm.quat_mul(q, np.r_[0.0, w]), atol=1e-12)


# ---------------------------------------------------------------- time updates (2j), (2k)

@prop
@given(quats, vec3, steps)
def test_exact_time_update_is_body_rotation(q, w, T):
    q = q / np.linalg.norm(q)
    got = qm.time_update_exact(q, w, T)
    np.testing.assert_allclose(got, qm.quat_mul(q, qm.quat_from_rotvec(w * T)), atol=1e-12)
    expected = rot(q) * Rotation.from_rotvec(w * T)
    np.testing.assert_allclose(qm.Q(got), expected.as_matrix(), atol=1e-12)
    assert abs(np.linalg.norm(got) - 1.0) < 1e-12      # F_exact is orthogonal


@prop
@given(quats, vec3.filter(lambda w: np.linalg.norm(w) > 1e-3))
def test_approx_update_agrees_to_second_order(q, w):
    q = q / np.linalg.norm(q)
    u = w / np.linalg.norm(w)
    ratios = []
    for x in (1e-3, 1e-2, 0.1):   # x = |w| T
        d = np.linalg.norm(qm.time_update_exact(q, u, x) - qm.time_update_approx(q, u, x))
        ratios.append(d / x ** 2)
    # (cos(x/2) - 1) q dominates: |difference| ~ x²/8 (second order, not first or third)
    np.testing.assert_allclose(ratios, 0.125, rtol=0.02)


@prop
@given(quats, vec3.filter(lambda w: np.linalg.norm(w) > 1e-3))
def test_approx_update_differs_for_large_steps(q, w):
    q = q / np.linalg.norm(q)
    u = w / np.linalg.norm(w)
    exact = qm.time_update_exact(q, u, 2.0)      # |w| T = 2 rad
    approx = qm.normalize(qm.time_update_approx(q, u, 2.0))
    # even renormalised, (2k) turns by 2 atan(1) = 1.571 rad instead of 2 rad
    assert abs(qm.angle_between(exact, approx) - (2.0 - 2 * math.atan(1.0))) < 1e-9


# ---------------------------------------------------------------- q2euler (appendix A.2.2)

S = math.sqrt(0.5)


def qaxis(axis: int, angle: float) -> np.ndarray:
    q = np.zeros(4)
    q[0] = math.cos(angle / 2)
    q[axis + 1] = math.sin(angle / 2)
    return q


# Worked out by hand from the appendix code: it reorders q to [a, b, c, d] = [q0, q2, q1, q3],
# xzpwy = b d + a c, yaw = atan2(2(bc - ad), 1 - 2(c² + d²)), roll = atan2(2(cd - ab), 1 - 2(b² + c²)),
# pitch = -asin(2 xzpwy); at xzpwy = +0.5 yaw = 2 atan2(b, a), at -0.5 yaw = -2 atan2(b, a), roll 0.
# A rotation by +t about z: a = cos(t/2), d = sin(t/2) -> yaw = atan2(-sin t, cos t) = -t;
# about x: c = sin(t/2) -> pitch = -asin(sin t) = -t; about y: b = sin(t/2) -> roll = -t.
@pytest.mark.parametrize("q, expected", [
    ([1.0, 0.0, 0.0, 0.0], [0.0, 0.0, 0.0]),
    (qaxis(2, 0.5), [-0.5, 0.0, 0.0]),
    (qaxis(2, -2.0), [2.0, 0.0, 0.0]),
    (qaxis(2, math.pi / 2), [-math.pi / 2, 0.0, 0.0]),
    (qaxis(0, 0.7), [0.0, -0.7, 0.0]),
    (qaxis(0, -1.2), [0.0, 1.2, 0.0]),
    (qaxis(1, 0.4), [0.0, 0.0, -0.4]),
    (qaxis(1, 2.5), [0.0, 0.0, -2.5]),
    # poles: x by +90°: a = c = sqrt(1/2): xzpwy = 0.5 -> north pole, yaw = 2 atan2(0, a) = 0
    ([S, S, 0.0, 0.0], [0.0, -math.pi / 2, 0.0]),
    # x by -90°: xzpwy = -0.5 -> south pole
    ([S, -S, 0.0, 0.0], [0.0, math.pi / 2, 0.0]),
    # z by 0.6 after x by +90°: q = sqrt(1/2) [cos .3, cos .3, sin .3, sin .3]:
    # a = c = S cos .3, b = d = S sin .3, xzpwy = 0.5 -> yaw = 2 atan2(sin .3, cos .3) = +0.6
    (S * np.array([math.cos(0.3), math.cos(0.3), math.sin(0.3), math.sin(0.3)]),
     [0.6, -math.pi / 2, 0.0]),
    # z by 0.6 after x by -90°: q = sqrt(1/2) [cos .3, -cos .3, -sin .3, sin .3]:
    # a = S cos .3, b = -S sin .3, c = -S cos .3: xzpwy = -0.5 -> yaw = -2 atan2(b, a) = +0.6
    (S * np.array([math.cos(0.3), -math.cos(0.3), -math.sin(0.3), math.sin(0.3)]),
     [0.6, math.pi / 2, 0.0]),
])
def test_q2euler_matches_manual_appendix(q, expected):
    np.testing.assert_allclose(qm.q2euler(np.array(q)), expected, atol=1e-7)


def test_q2euler_wraps_and_handles_sign_of_q():
    q = qaxis(2, 3.0)
    np.testing.assert_allclose(qm.q2euler(q), [-3.0, 0.0, 0.0], atol=1e-12)
    np.testing.assert_allclose(qm.q2euler(-q), qm.q2euler(q), atol=1e-12)
    e = qm.q2euler_many(np.stack([q, [1.0, 0, 0, 0]]))
    assert e.shape == (2, 3)
    assert np.all(e >= -math.pi) and np.all(e < math.pi)


# ---------------------------------------------------------------- error_angles (BROAD's metric)

@prop
@given(quats, st.floats(-3.0, 3.0))
def test_error_pure_heading(q, a):
    """An error that is a rotation about the world's vertical is all heading."""
    ref = q / np.linalg.norm(q)
    est = qm.quat_mul(qaxis(2, a), ref)       # world-frame rotation applied after ref
    tot, head, inc = (x[0] for x in qm.error_angles(est, ref))
    assert abs(tot - abs(a)) < 1e-6
    assert abs(head - abs(a)) < 1e-6
    assert inc < 1e-6


@prop
@given(quats, st.floats(-3.0, 3.0), st.integers(0, 1))
def test_error_pure_inclination(q, a, axis):
    """An error about a horizontal world axis is all inclination."""
    ref = q / np.linalg.norm(q)
    est = qm.quat_mul(qaxis(axis, a), ref)
    tot, head, inc = (x[0] for x in qm.error_angles(est, ref))
    assert abs(tot - abs(a)) < 1e-6
    assert abs(inc - abs(a)) < 1e-6
    assert head < 1e-6


@prop
@given(quats, quats)
@example(np.array([0.0, 0.0, 0.0, 1.0]), np.array([1e-9, 0.0, 0.0, 1.0]))
def test_error_split_is_consistent(p, q):
    p, q = p / np.linalg.norm(p), q / np.linalg.norm(q)
    tot, head, inc = (x[0] for x in qm.error_angles(p, q))
    assert abs(tot - (rot(p) * rot(q).inv()).magnitude()) < 1e-6
    # swing-twist: cos(total/2) = cos(heading/2) cos(inclination/2)
    assert abs(math.cos(tot / 2) - math.cos(head / 2) * math.cos(inc / 2)) < 1e-9
    # (the total comes from arccos, which near 1 resolves only ~1e-8 rad: a 2e-9 heading
    # beside a total of 0 is that rounding, found by hypothesis in a fresh-clone run)
    assert head <= tot + 1e-7 and inc <= tot + 1e-7
    # invariant under the sign of either quaternion
    np.testing.assert_allclose([x[0] for x in qm.error_angles(-p, q)], [tot, head, inc], atol=1e-9)


# ------------------------------------------------------------------ many at once, alignment

def test_vectorised_helpers_equal_the_scalar_ones():
    rng = np.random.default_rng(7)
    p = np.array([qm.normalize(x) for x in rng.standard_normal((20, 4))])
    q = np.array([qm.normalize(x) for x in rng.standard_normal((20, 4))])
    v = rng.standard_normal((20, 3))
    np.testing.assert_allclose(qm.quat_mul_many(p, q), [qm.quat_mul(a, b) for a, b in zip(p, q)],
                               atol=1e-14)
    np.testing.assert_allclose(qm.quat_from_rotvec_many(v), [qm.quat_from_rotvec(x) for x in v],
                               atol=1e-14)
    np.testing.assert_allclose(qm.quat_from_rotvec_many(np.zeros((2, 3))), [[1, 0, 0, 0]] * 2)
    np.testing.assert_allclose(qm.rotate_inv_many(q, v), [qm.Q(a).T @ x for a, x in zip(q, v)],
                               atol=1e-12)
    np.testing.assert_allclose(qm.rotate_inv_many(q, v[0]), [qm.Q(a).T @ v[0] for a in q],
                               atol=1e-12)
    np.testing.assert_allclose(qm.rotate_many(q, v), [qm.Q(a) @ x for a, x in zip(q, v)], atol=1e-12)
    np.testing.assert_allclose(qm.rotate_many(q, v[0]), [qm.Q(a) @ v[0] for a in q], atol=1e-12)
    np.testing.assert_allclose(qm.quat_conj_many(q), [qm.quat_conj(a) for a in q], atol=0)
    signed = np.vstack([q, -q, [[1.0, 0.0, 0.0, 0.0]]])       # w < 0 too, and no rotation
    np.testing.assert_allclose(qm.rotvec_from_quat_many(signed),
                               [qm.rotvec_from_quat(a) for a in signed], atol=1e-12)


@given(quats)
@settings(max_examples=50, deadline=None)
def test_alignment_recovers_the_orientation_from_gravity_and_field(q):
    q = qm.normalize(q)
    g, m = np.array([0.0, 0.0, 9.81]), np.array([0.0, 20.0, -45.0])
    q_al = qm.q_from_acc_mag(qm.Q(q).T @ g, qm.Q(q).T @ m, True)
    assert qm.angle_between(q_al, q) < 1e-6
    np.testing.assert_allclose(qm.field_reference(qm.Q(q) @ (qm.Q(q).T @ m)), m, atol=1e-9)


def test_alignment_without_field_points_the_phones_top_north():
    # tilted 30 deg about x: the top still points north, only upwards
    q = qm.quat_from_rotvec(np.array([np.radians(30), 0.0, 0.0]))
    q_al = qm.q_from_acc_mag(qm.Q(q).T @ np.array([0.0, 0.0, 9.81]), np.zeros(3), False)
    assert qm.angle_between(q_al, q) < 1e-9


def test_Q_many_is_Q_row_by_row():
    from app.quaternion import Q, Q_many, quat_from_rotvec_many
    rng = np.random.default_rng(3)
    qs = quat_from_rotvec_many(rng.normal(size=(50, 3)))
    np.testing.assert_allclose(Q_many(qs), np.array([Q(q) for q in qs]), atol=1e-15)


def test_integrate_many_is_the_exact_time_update_step_by_step():
    """A gyroscope's turns, integrated from q0: each attitude is the last one turned by its step
    in the body frame (time_update_exact's rotation), unit, w >= 0."""
    rng = np.random.default_rng(11)
    q0 = qm.normalize(rng.standard_normal(4))
    w, T = rng.standard_normal((50, 3)), 0.01
    got = qm.integrate_many(q0, w * T)
    want, q = [], q0
    for x in w:
        q = qm.normalize(qm.time_update_exact(q, x, T))
        want.append(q)
    np.testing.assert_allclose(got, want, atol=1e-12)
    assert np.all(got[:, 0] >= 0.0)
    np.testing.assert_allclose(np.linalg.norm(got, axis=1), 1.0, atol=1e-12)
