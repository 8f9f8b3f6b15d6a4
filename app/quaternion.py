"""Quaternion and rotation math of the lab manual, in one place.

Conventions (used everywhere in orientlab):
- quaternions are scalar first ``[w, x, y, z]`` and describe the rotation from the
  sensor frame to the world frame: ``v_world = Q(q) @ v_sensor``;
- world frame ENU (x east, y north, z up), sensor frame Android's
  (x right, y top of the screen, z out of the screen);
- after normalisation ``w >= 0`` (the manual's ``mu_normalizeQ``).

Every function is plain numpy and is also compiled with numba (``app.jitcache.compiled``), so the
estimators' hot loops can call the very same code. Formula numbers refer to the
lab manual (Section 3.1 and Appendix A.2).
"""

from __future__ import annotations

import numpy as np

from app.jitcache import compiled, ensure_fresh

ensure_fresh()   # before anything compiled runs: a cache older than its sources is dropped

_SQRT_EPS = np.sqrt(np.finfo(np.float64).eps)

IDENTITY = np.array([1.0, 0.0, 0.0, 0.0])     # no rotation
IDENTITY.setflags(write=False)


def not_estimated(q: np.ndarray) -> np.ndarray:
    """The rows of estimates ``q`` (..., 4) that are no estimate yet: an estimator reports
    :data:`IDENTITY`, exactly, until its alignment; from real sensors' data an estimate is
    never exactly that. Plots draw these rows as gaps, not as 0°."""
    return np.all(np.asarray(q) == IDENTITY, axis=-1)


@compiled
def normalize(q):
    """Unit quaternion with w >= 0 (manual A.2.1). A zero quaternion becomes identity."""
    n = np.sqrt(q[0] * q[0] + q[1] * q[1] + q[2] * q[2] + q[3] * q[3])
    out = np.empty(4)
    if n == 0.0 or not np.isfinite(n):
        out[0] = 1.0
        out[1] = 0.0
        out[2] = 0.0
        out[3] = 0.0
        return out
    s = 1.0 / n
    if q[0] < 0.0:
        s = -s
    for i in range(4):
        out[i] = q[i] * s
    return out


@compiled
def Q(q):
    """Rotation matrix of a unit quaternion, formula (2a): v_world = Q(q) v_sensor."""
    q0, q1, q2, q3 = q[0], q[1], q[2], q[3]
    R = np.empty((3, 3))
    R[0, 0] = 2.0 * (q0 * q0 + q1 * q1) - 1.0
    R[0, 1] = 2.0 * (q1 * q2 - q0 * q3)
    R[0, 2] = 2.0 * (q1 * q3 + q0 * q2)
    R[1, 0] = 2.0 * (q1 * q2 + q0 * q3)
    R[1, 1] = 2.0 * (q0 * q0 + q2 * q2) - 1.0
    R[1, 2] = 2.0 * (q2 * q3 - q0 * q1)
    R[2, 0] = 2.0 * (q1 * q3 - q0 * q2)
    R[2, 1] = 2.0 * (q2 * q3 + q0 * q1)
    R[2, 2] = 2.0 * (q0 * q0 + q3 * q3) - 1.0
    return R


@compiled
def dQdq(q):
    """Derivatives of Q(q) with respect to q0..q3, formulas (2f)-(2i); shape (4, 3, 3)."""
    q0, q1, q2, q3 = q[0], q[1], q[2], q[3]
    D = np.empty((4, 3, 3))
    D[0, 0, 0] = 2 * q0; D[0, 0, 1] = -q3;   D[0, 0, 2] = q2
    D[0, 1, 0] = q3;     D[0, 1, 1] = 2 * q0; D[0, 1, 2] = -q1
    D[0, 2, 0] = -q2;    D[0, 2, 1] = q1;     D[0, 2, 2] = 2 * q0
    D[1, 0, 0] = 2 * q1; D[1, 0, 1] = q2;     D[1, 0, 2] = q3
    D[1, 1, 0] = q2;     D[1, 1, 1] = 0.0;    D[1, 1, 2] = -q0
    D[1, 2, 0] = q3;     D[1, 2, 1] = q0;     D[1, 2, 2] = 0.0
    D[2, 0, 0] = 0.0;    D[2, 0, 1] = q1;     D[2, 0, 2] = q0
    D[2, 1, 0] = q1;     D[2, 1, 1] = 2 * q2; D[2, 1, 2] = q3
    D[2, 2, 0] = -q0;    D[2, 2, 1] = q3;     D[2, 2, 2] = 0.0
    D[3, 0, 0] = 0.0;    D[3, 0, 1] = -q0;    D[3, 0, 2] = q1
    D[3, 1, 0] = q0;     D[3, 1, 1] = 0.0;    D[3, 1, 2] = q2
    D[3, 2, 0] = q1;     D[3, 2, 1] = q2;     D[3, 2, 2] = 2 * q3
    return 2.0 * D


@compiled
def S_omega(w):
    """S(omega) of formula (2d): dq/dt = 1/2 S(omega) q, omega in the sensor frame."""
    wx, wy, wz = w[0], w[1], w[2]
    S = np.empty((4, 4))
    S[0, 0] = 0.0; S[0, 1] = -wx; S[0, 2] = -wy; S[0, 3] = -wz
    S[1, 0] = wx;  S[1, 1] = 0.0; S[1, 2] = wz;  S[1, 3] = -wy
    S[2, 0] = wy;  S[2, 1] = -wz; S[2, 2] = 0.0; S[2, 3] = wx
    S[3, 0] = wz;  S[3, 1] = wy;  S[3, 2] = -wx; S[3, 3] = 0.0
    return S


@compiled
def S_bar(q):
    """S-bar(q) of formula (2e): dq/dt = 1/2 S-bar(q) omega."""
    q0, q1, q2, q3 = q[0], q[1], q[2], q[3]
    S = np.empty((4, 3))
    S[0, 0] = -q1; S[0, 1] = -q2; S[0, 2] = -q3
    S[1, 0] = q0;  S[1, 1] = -q3; S[1, 2] = q2
    S[2, 0] = q3;  S[2, 1] = q0;  S[2, 2] = -q1
    S[3, 0] = -q2; S[3, 1] = q1;  S[3, 2] = q0
    return S


@compiled
def F_exact(w, T):
    """Transition matrix of the exact time update (2j): q_next = F q."""
    n = np.sqrt(w[0] * w[0] + w[1] * w[1] + w[2] * w[2])
    half = 0.5 * n * T
    if half < 1e-12:
        sinc = 1.0
    else:
        sinc = np.sin(half) / half
    return np.cos(half) * np.eye(4) + (0.5 * T * sinc) * S_omega(w)


@compiled
def F_approx(w, T):
    """Transition matrix of the approximate time update (2k): I + T/2 S(omega)."""
    return np.eye(4) + (0.5 * T) * S_omega(w)


@compiled
def time_update_exact(q, w, T):
    """Formula (2j) without noise: exp(1/2 S(omega) T) q (not renormalised)."""
    return F_exact(w, T) @ q


@compiled
def time_update_approx(q, w, T):
    """Formula (2k) without noise: (I + 1/2 S(omega) T) q (not renormalised)."""
    return F_approx(w, T) @ q


@compiled
def quat_mul(p, q):
    """Hamilton product p * q (scalar first)."""
    out = np.empty(4)
    out[0] = p[0] * q[0] - p[1] * q[1] - p[2] * q[2] - p[3] * q[3]
    out[1] = p[0] * q[1] + p[1] * q[0] + p[2] * q[3] - p[3] * q[2]
    out[2] = p[0] * q[2] - p[1] * q[3] + p[2] * q[0] + p[3] * q[1]
    out[3] = p[0] * q[3] + p[1] * q[2] - p[2] * q[1] + p[3] * q[0]
    return out


@compiled
def quat_conj(q):
    """Conjugate (the inverse of a unit quaternion)."""
    out = np.empty(4)
    out[0] = q[0]
    out[1] = -q[1]
    out[2] = -q[2]
    out[3] = -q[3]
    return out


@compiled
def quat_from_rotvec(v):
    """Unit quaternion of the rotation vector v (axis * angle, rad)."""
    a = np.sqrt(v[0] * v[0] + v[1] * v[1] + v[2] * v[2])
    out = np.empty(4)
    out[0] = np.cos(0.5 * a)
    if a < 1e-12:
        s = 0.5
    else:
        s = np.sin(0.5 * a) / a
    out[1] = v[0] * s
    out[2] = v[1] * s
    out[3] = v[2] * s
    return out


@compiled
def rotvec_from_quat(q):
    """Rotation vector (axis * angle, rad, angle in [0, pi]) of a unit quaternion."""
    qq = normalize(q)
    vn = np.sqrt(qq[1] * qq[1] + qq[2] * qq[2] + qq[3] * qq[3])
    out = np.zeros(3)
    if vn < 1e-15:
        return out
    angle = 2.0 * np.arctan2(vn, qq[0])
    for i in range(3):
        out[i] = qq[i + 1] / vn * angle
    return out


@compiled
def quat_from_matrix(R):
    """Unit quaternion of a rotation matrix: formula (2b), in its numerically stable
    form (the largest of the four diagonal combinations is used as the pivot). The manual's
    (2b) as printed (q1 = (R23 - R32) / 2t, ...) is the inverse of its own (2a): it gives
    the conjugate. Here the signs are those that invert (2a): ``Q(quat_from_matrix(R)) = R``."""
    tr = R[0, 0] + R[1, 1] + R[2, 2]
    q = np.empty(4)
    if tr > 0.0:
        t = np.sqrt(tr + 1.0)  # the manual's t: q0 = t/2
        q[0] = 0.5 * t
        q[1] = (R[2, 1] - R[1, 2]) / (2.0 * t)
        q[2] = (R[0, 2] - R[2, 0]) / (2.0 * t)
        q[3] = (R[1, 0] - R[0, 1]) / (2.0 * t)
    elif R[0, 0] >= R[1, 1] and R[0, 0] >= R[2, 2]:
        t = np.sqrt(1.0 + R[0, 0] - R[1, 1] - R[2, 2])
        q[1] = 0.5 * t
        q[0] = (R[2, 1] - R[1, 2]) / (2.0 * t)
        q[2] = (R[0, 1] + R[1, 0]) / (2.0 * t)
        q[3] = (R[0, 2] + R[2, 0]) / (2.0 * t)
    elif R[1, 1] >= R[2, 2]:
        t = np.sqrt(1.0 - R[0, 0] + R[1, 1] - R[2, 2])
        q[2] = 0.5 * t
        q[0] = (R[0, 2] - R[2, 0]) / (2.0 * t)
        q[1] = (R[0, 1] + R[1, 0]) / (2.0 * t)
        q[3] = (R[1, 2] + R[2, 1]) / (2.0 * t)
    else:
        t = np.sqrt(1.0 - R[0, 0] - R[1, 1] + R[2, 2])
        q[3] = 0.5 * t
        q[0] = (R[1, 0] - R[0, 1]) / (2.0 * t)
        q[1] = (R[0, 2] + R[2, 0]) / (2.0 * t)
        q[2] = (R[1, 2] + R[2, 1]) / (2.0 * t)
    return normalize(q)


@compiled
def angle_between(q0, q):
    """Formula (2c): the angle (rad) q must be turned by to obtain q0."""
    d = abs(q0[0] * q[0] + q0[1] * q[1] + q0[2] * q[2] + q0[3] * q[3])
    if d > 1.0:
        d = 1.0
    return 2.0 * np.arccos(d)


def angle_between_many(q0: np.ndarray, q: np.ndarray) -> np.ndarray:
    """Formula (2c) row by row for (N, 4) arrays (rad); NaN rows give NaN."""
    d = np.abs(np.sum(np.asarray(q0) * np.asarray(q), axis=-1))
    return 2.0 * np.arccos(np.minimum(d, 1.0))


@compiled
def wrap_angle(a):
    """a wrapped to [-π, π)."""
    return np.mod(a + np.pi, 2.0 * np.pi) - np.pi


@compiled
def q2euler(q):
    """Euler angles exactly as the manual's appendix A.2.2 ``q2euler``.

    Returns ``[yaw (about z), pitch (about x), roll (about y)]`` in rad, each wrapped
    to [-pi, pi). Note the manual's sign, on all three: ``Q(q) = Rz(-yaw) Rx(-pitch)
    Ry(-roll)``, so a right-handed turn gives a *negative* angle (yaw grows clockwise seen
    from above, like a compass; the phone's top raised is a negative pitch). At pitch ±90°
    (the phone upright) only yaw + roll is defined.
    """
    # the appendix first reorders q to [q0, q2, q1, q3]
    a, b, c, d = q[0], q[2], q[1], q[3]
    xzpwy = b * d + a * c
    e = np.zeros(3)
    if xzpwy + _SQRT_EPS > 0.5:  # north pole
        e[0] = 2.0 * np.arctan2(b, a)
    elif xzpwy - _SQRT_EPS < -0.5:  # south pole
        e[0] = -2.0 * np.arctan2(b, a)
    else:
        e[0] = np.arctan2(2.0 * (b * c - a * d), 1.0 - 2.0 * (c * c + d * d))
        e[2] = np.arctan2(2.0 * (c * d - a * b), 1.0 - 2.0 * (b * b + c * c))
    s = 2.0 * xzpwy
    if s > 1.0:
        s = 1.0
    elif s < -1.0:
        s = -1.0
    e[1] = -np.arcsin(s)
    for i in range(3):
        e[i] = wrap_angle(e[i])
    return e


@compiled
def _q2euler_rows(qs):
    out = np.empty((qs.shape[0], 3))
    for k in range(qs.shape[0]):
        out[k] = q2euler(qs[k])
    return out


def q2euler_many(qs: np.ndarray) -> np.ndarray:
    """q2euler for an (N, 4) array; returns (N, 3) (one compiled loop)."""
    qs = np.ascontiguousarray(np.atleast_2d(np.asarray(qs, dtype=float)))
    return _q2euler_rows(qs)


def quat_mul_many(p: np.ndarray, q: np.ndarray) -> np.ndarray:
    """Hamilton product of (..., 4) arrays (broadcast), scalar first: :func:`quat_mul`
    for many quaternions at once."""
    p0, p1, p2, p3 = np.moveaxis(np.asarray(p, float), -1, 0)
    q0, q1, q2, q3 = np.moveaxis(np.asarray(q, float), -1, 0)
    return np.stack([p0 * q0 - p1 * q1 - p2 * q2 - p3 * q3,
                     p0 * q1 + p1 * q0 + p2 * q3 - p3 * q2,
                     p0 * q2 - p1 * q3 + p2 * q0 + p3 * q1,
                     p0 * q3 + p1 * q2 - p2 * q1 + p3 * q0], axis=-1)


def quat_conj_many(q: np.ndarray) -> np.ndarray:
    """:func:`quat_conj` of (..., 4) arrays."""
    return np.asarray(q, float) * np.array([1.0, -1.0, -1.0, -1.0])


def Q_many(q: np.ndarray) -> np.ndarray:
    """:func:`Q` of (N, 4) unit quaternions: (N, 3, 3) rotation matrices, v_world = R v_sensor."""
    q0, q1, q2, q3 = np.asarray(q, float).T
    R = np.empty((len(q0), 3, 3))
    R[:, 0, 0] = 2.0 * (q0 * q0 + q1 * q1) - 1.0
    R[:, 0, 1] = 2.0 * (q1 * q2 - q0 * q3)
    R[:, 0, 2] = 2.0 * (q1 * q3 + q0 * q2)
    R[:, 1, 0] = 2.0 * (q1 * q2 + q0 * q3)
    R[:, 1, 1] = 2.0 * (q0 * q0 + q2 * q2) - 1.0
    R[:, 1, 2] = 2.0 * (q2 * q3 - q0 * q1)
    R[:, 2, 0] = 2.0 * (q1 * q3 - q0 * q2)
    R[:, 2, 1] = 2.0 * (q2 * q3 + q0 * q1)
    R[:, 2, 2] = 2.0 * (q0 * q0 + q3 * q3) - 1.0
    return R


def rotvec_from_quat_many(q: np.ndarray) -> np.ndarray:
    """:func:`rotvec_from_quat` of (..., 4) unit quaternions (angle in [0, pi]: q and -q
    give the same rotation vector)."""
    q = np.asarray(q, float)
    q = q * np.where(q[..., :1] < 0.0, -1.0, 1.0)
    vn = np.linalg.norm(q[..., 1:], axis=-1, keepdims=True)
    angle = 2.0 * np.arctan2(vn, q[..., :1])
    return np.where(vn < 1e-15, 0.0, q[..., 1:] / np.where(vn < 1e-15, 1.0, vn) * angle)


def quat_from_rotvec_many(v: np.ndarray) -> np.ndarray:
    """:func:`quat_from_rotvec` of (..., 3) rotation vectors."""
    v = np.asarray(v, float)
    a = np.linalg.norm(v, axis=-1)
    small = a < 1e-12
    s = np.where(small, 0.5, np.sin(0.5 * a) / np.where(small, 1.0, a))
    return np.concatenate([np.cos(0.5 * a)[..., None], v * s[..., None]], axis=-1)


def rotate_many(q: np.ndarray, v: np.ndarray) -> np.ndarray:
    """Q(q) v for (N, 4) q and (N, 3) or (3,) v (a sensor vector in the world frame):
    :func:`rotate` for many at once."""
    v = np.broadcast_to(np.asarray(v, float), (len(q), 3))
    return np.einsum("nij,nj->ni", Q_many(q), v)


def integrate_many(q0, steps: np.ndarray) -> np.ndarray:
    """The attitudes (N, 4) after each of ``steps`` (N, 3), body-frame rotation vectors
    (rad; a gyroscope's ω dt), starting from ``q0``: q_k = q_k-1 ⊗ exp(step_k), normalised."""
    out = np.empty((len(steps), 4))
    q = normalize(np.asarray(q0, float))
    for k, dq in enumerate(quat_from_rotvec_many(steps)):
        q = normalize(quat_mul(q, dq))
        out[k] = q
    return out


def rotate_inv_many(q: np.ndarray, v: np.ndarray) -> np.ndarray:
    """Q(q)ᵀ v for (..., 4) q and (..., 3) or (3,) v (a world vector in the sensor frame):
    :func:`rotate_inv` for many at once."""
    q = np.asarray(q, float)
    v = np.broadcast_to(np.asarray(v, float), q.shape[:-1] + (3,))
    zero = np.zeros(v.shape[:-1] + (1,))
    return quat_mul_many(quat_mul_many(quat_conj_many(q), np.concatenate([zero, v], axis=-1)), q)[..., 1:]


def error_angles(q_est: np.ndarray, q_ref: np.ndarray):
    """Total, heading and inclination error (rad) of (N, 4) estimates against references.

    The error quaternion is ``e = q_est * conj(q_ref)`` (both sensor-to-world), a rotation
    in the world frame; heading is its part about the world's vertical (swing-twist
    decomposition), inclination the rest. This is BROAD's metric.
    """
    q_ref = np.atleast_2d(q_ref)
    e = quat_mul_many(np.atleast_2d(q_est), quat_conj_many(q_ref))
    e0, ez = e[:, 0], e[:, 3]
    total = 2.0 * np.arccos(np.clip(np.abs(e0), 0.0, 1.0))
    heading = 2.0 * np.arctan2(np.abs(ez), np.abs(e0))
    incl = 2.0 * np.arccos(np.clip(np.sqrt(e0 ** 2 + ez ** 2), 0.0, 1.0))
    return total, heading, incl


@compiled
def skew(v):
    """[v]×: the matrix with [v]× w = v × w."""
    S = np.zeros((3, 3))
    S[0, 1] = -v[2]
    S[0, 2] = v[1]
    S[1, 0] = v[2]
    S[1, 2] = -v[0]
    S[2, 0] = -v[1]
    S[2, 1] = v[0]
    return S


@compiled
def compass_matrix(up, ref, R_fallback):
    """The accelerometer/magnetometer rotation matrix (TRIAD, Android's getRotationMatrix):
    rows east, north, up in sensor coordinates, i.e. Q(q) of the sensor-to-world
    orientation. ``up`` is the specific force (it points up at rest), ``ref`` the
    magnetic field (or any vector with a northward horizontal part). If ``ref`` has no
    horizontal part (zero, or vertical), the east axis of ``R_fallback`` projected on the
    horizontal plane is used instead (or its north axis, if that east is vertical)."""
    u = up / norm3(up)
    e = np.cross(ref, u)
    en = norm3(e)
    if not en > 1e-6 * norm3(ref):
        f = R_fallback[0]
        e = f - (f[0] * u[0] + f[1] * u[1] + f[2] * u[2]) * u
        en = norm3(e)
        if en < 1e-6:  # fallback east is vertical too: then its north is horizontal
            e = np.cross(R_fallback[1], u)
            en = norm3(e)
    e = e / en
    R = np.empty((3, 3))
    R[0] = e
    R[1] = np.cross(u, e)
    R[2] = u
    return R


_TOP = np.array([0.0, 1.0, 0.0])  # the phone's top: north when there is no field


@compiled
def q_from_acc_mag(acc, mag, use_mag):
    """Initial alignment: the orientation whose 'up' is the accelerometer's direction
    and, when ``use_mag``, whose north is the horizontal part of the magnetic field
    (:func:`compass_matrix`). Without the magnetometer the phone's top (y) points north
    (or its x axis east, when the top points straight up)."""
    ref = mag if use_mag else _TOP
    return quat_from_matrix(compass_matrix(acc, ref, np.eye(3)))


def field_reference(m_world: np.ndarray) -> np.ndarray:
    """Formula (7): the nominal field ``m0 = (0, sqrt(mx² + my²), mz)`` (µT) from a field
    already levelled into the world frame (no west-east component by definition)."""
    return np.array([0.0, float(np.hypot(m_world[0], m_world[1])), float(m_world[2])])


def attitude_cov_from_quat_cov(q: np.ndarray, Pq: np.ndarray) -> np.ndarray:
    """Covariance (rad², world frame) of the rotation-vector error of a quaternion
    estimate whose 4x4 covariance is ``Pq``: the error rotation is
    ``(q + dq) * conj(q) ≈ [1, dtheta/2]``, so ``dtheta = 2 * vec(dq * conj(q))``."""
    qc = quat_conj(q)
    T = np.empty((3, 4))
    for i in range(4):
        basis = np.zeros(4)
        basis[i] = 1.0
        T[:, i] = 2.0 * quat_mul(basis, qc)[1:]
    return T @ Pq @ T.T


@compiled
def rotate(q, v):
    """Q(q) v (sensor to world) without forming Q: a few dozen flops, no BLAS call."""
    w, x, y, z = q[0], q[1], q[2], q[3]
    # v + 2 w (u x v) + 2 u x (u x v), u = (x, y, z)
    tx = 2.0 * (y * v[2] - z * v[1])
    ty = 2.0 * (z * v[0] - x * v[2])
    tz = 2.0 * (x * v[1] - y * v[0])
    out = np.empty(3)
    out[0] = v[0] + w * tx + (y * tz - z * ty)
    out[1] = v[1] + w * ty + (z * tx - x * tz)
    out[2] = v[2] + w * tz + (x * ty - y * tx)
    return out


@compiled
def rotate_inv(q, v):
    """Q(q)ᵀ v (world to sensor)."""
    qc = np.empty(4)
    qc[0] = q[0]
    qc[1] = -q[1]
    qc[2] = -q[2]
    qc[3] = -q[3]
    return rotate(qc, v)


@compiled
def norm3(v):
    return np.sqrt(v[0] * v[0] + v[1] * v[1] + v[2] * v[2])
