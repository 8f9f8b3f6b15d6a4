"""``lab``: the lab manual's EKF, structure (4a), as a student writes it.

State ``x = q`` (4 quaternion components), covariance ``P`` (4x4); the gyroscope is
the input. Hold this file beside the manual:

- time update (Section 4.1): ``q <- F q``, ``P <- F P Fᵀ + G Rw Gᵀ`` with
  ``F = exp(1/2 S(ω) T)`` (exact, 2j) or ``I + 1/2 S(ω) T`` (approximate, 2k) and
  ``G = T/2 S̄(q)``; with the gyroscope off or missing, a random walk
  ``P <- P + q_rw_noise² T I``;
- accelerometer update (4.2): ``h(q) = Q(q)ᵀ g0``, Jacobian columns ``dQ/dq_i ᵀ g0``,
  refused when ``|a|`` is outside ``|g0| (1 ± acc_band_rel)`` (report A: 0.75 g–1.25 g);
- magnetometer update (4.3): ``h(q) = Q(q)ᵀ m0``, refused when the low-pass filtered
  field strength ``L_k = (1-α) L_k + α |m|`` leaves ``|m0| (1 ± mag_band_rel)``
  (report A's AR filter);
- normalisation after every step (4.4, ``mu_normalizeQ``: unit length, q0 >= 0).

``m0`` is taken from the data at the initial alignment, as formula (7) after levelling
with the accelerometer, unless a preset gives it. Both measurement updates go through
the one shared :func:`app.estimators.kalman.correct`.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import ClassVar

import math

import numpy as np

from app import quaternion as qm
from app.jitcache import compiled
from app.params import GRAVITY, CommonParams, DEG, ParamError, gyr_scale_param, param
from app.estimators.base import (ALIGN_ACC, ALIGN_ACC_MAG, ALIGN_NO_ACC, B_N, B_SEEN, B_T, B_W, B_W_T, F_ACC,
                   F_ACC_NIS, F_ACC_VAL, F_MAG, F_MAG_NIS, F_MAG_VAL, R_FIELD, R_INIT, R_NIS, R_NORM, R_USED,
                   R_WAIT, Diagnostics, Estimator, align_step, begin_row, vec3)
from app.estimators.kalman import correct



M0_MIN_UT = 5.0    # the weakest field m0 may be (the earth's is 25-65 µT, indoors rarely < 15)


@dataclass(frozen=True)
class LabParams(CommonParams):
    time_update: str = param("exact", choices=("exact", "approx"),
                             doc="exact (2j) or approximate (2k) quaternion time update")
    gyr_std: float = param(0.01, unit="rad/s", lo=1e-6, hi=1.0, user_unit="deg/s", user_scale=DEG,
                           log=True, doc="gyroscope noise σ per sample (Rw = σ² I)")
    acc_std: float = param(0.5, unit="m/s²", lo=1e-4, hi=20.0, log=True,
                           doc="accelerometer noise σ per sample (Ra = σ² I)")
    mag_std: float = param(2.0, unit="µT", lo=1e-3, hi=100.0, log=True,
                           doc="magnetometer noise σ per sample (Rm = σ² I)")
    gyr_cov: tuple | None = param(None, unit="(rad/s)²", length=9, optional=True, tunable=False,
                                  doc="full Rw (row-major 3x3) from calibration; overrides gyr_std")
    acc_cov: tuple | None = param(None, unit="(m/s²)²", length=9, optional=True, tunable=False,
                                  doc="full Ra (row-major 3x3) from calibration; overrides acc_std")
    mag_cov: tuple | None = param(None, unit="µT²", length=9, optional=True, tunable=False,
                                  doc="full Rm (row-major 3x3) from calibration; overrides mag_std")
    q_rw_noise: float = param(0.3, unit="1/√s", lo=1e-6, hi=10.0, log=True,
                              doc="random-walk noise density of q without gyroscope (P += σ² T I)")
    g0: tuple = param((0.0, 0.0, GRAVITY), unit="m/s²", lo=-20.0, hi=20.0, tunable=False,
                      doc="nominal gravity (specific force at rest) in world coordinates")
    m0: tuple | None = param(None, unit="µT", length=3, lo=-200.0, hi=200.0, optional=True,
                             tunable=False, doc="nominal field in world coordinates; None: "
                             "from the data at alignment, formula (7)")
    gyr_bias: tuple = param((0.0, 0.0, 0.0), unit="rad/s", lo=-1.0, hi=1.0, tunable=False,
                            doc="gyroscope bias subtracted from every sample (calibration)")
    gyr_scale: tuple = gyr_scale_param()
    acc_band_rel: float = param(0.25, lo=0.0, hi=2.0,
                                doc="accelerometer used only while | |a| - |g0| | <= this × |g0|; 0: off",
                                rejects=True)
    mag_band_rel: float = param(0.2, lo=0.0, hi=1.0,
                                doc="magnetometer used only while | L_k - |m0| | <= this × |m0|; 0: off",
                                rejects=True)
    mag_band_uT: tuple | None = param(None, unit="µT", length=2, lo=0.0, hi=1000.0, optional=True,
                                      tunable=False, doc="absolute band (lo, hi) for L_k, as report A's "
                                      "35-55 µT; overrides mag_band_rel when given", rejects=True)
    mag_alpha: float = param(0.01, lo=0.0, hi=1.0, doc="α of the field-strength filter L_k")
    nis_gate: float = param(0.0, lo=0.0, hi=1000.0,
                            doc="innovation gate on NIS (χ², 3 dof) for both updates; 0: off", rejects=True)
    p0: float = param(0.1, lo=1e-8, hi=10.0, log=True, tunable=False,
                      doc="initial P = p0 I after alignment")
    m0_learn_time: float = param(2.0, unit="s", lo=0.0, hi=60.0, tunable=False,
                                 doc="when m0 is not given: learn it by (7) from the mean field of "
                                     "this long after alignment (an exponentially weighted mean, "
                                     "time constant a quarter of this; the accelerometer levels it "
                                     "meanwhile)")

    # former names (same quantity): presets are translated with a warning, the API refuses
    # them with this message (see app.live.changes)
    renamed: ClassVar[dict[str, tuple[str, str]]] = {
        "gyr_noise": ("gyr_std", "per-sample σ, rad/s"),
        "acc_noise": ("acc_std", "per-sample σ, m/s²"),
        "mag_noise": ("mag_std", "per-sample σ, µT"),
        "rw_noise": ("q_rw_noise", "noise density of q, 1/√s"),
    }

    def check(self) -> None:
        if np.linalg.norm(self.g0) < 1.0:
            raise ParamError("g0", "must be a gravity vector (|g0| >= 1 m/s²)")
        # |m0| is the field-strength band's centre: near zero, every sample is refused
        if self.m0 is not None and np.linalg.norm(self.m0) < M0_MIN_UT:
            raise ParamError("m0", f"must be a magnetic field (|m0| >= {M0_MIN_UT:g} µT; the "
                                   "earth's is 25-65 µT), or null to learn it")
        if self.mag_band_uT is not None and not self.mag_band_uT[0] < self.mag_band_uT[1]:
            raise ParamError("mag_band_uT", "must be (lo, hi) with lo < hi")
        for name in ("gyr_cov", "acc_cov", "mag_cov"):
            c = getattr(self, name)
            if c is not None:
                m = np.array(c).reshape(3, 3)
                if not np.allclose(m, m.T) or np.any(np.linalg.eigvalsh(0.5 * (m + m.T)) <= 0):
                    raise ParamError(name, "must be a symmetric positive definite 3x3 matrix")


def _cov(full, sigma) -> np.ndarray:
    return np.array(full, dtype=float).reshape(3, 3) if full is not None else sigma ** 2 * np.eye(3)


@compiled
def _jacobian(q, v0):
    """d/dq of Q(q)ᵀ v0: column i is dQ/dq_i ᵀ v0 (the manual's mu_g / mu_m)."""
    D = qm.dQdq(q)
    H = np.empty((3, 4))
    for i in range(4):
        H[:, i] = D[i].T @ v0
    return H


@compiled
def tu_qw(x, P, omega, T, Rw, exact):
    """The manual's time update (Section 4.1): x <- F x, P <- F P Fᵀ + G Rw Gᵀ with
    F from (2j) or (2k) and G = T/2 S̄(x); x normalised (4.4)."""
    F = qm.F_exact(omega, T) if exact else qm.F_approx(omega, T)
    G = 0.5 * T * qm.S_bar(x)
    return qm.normalize(F @ x), F @ P @ F.T + G @ Rw @ G.T


@compiled
def mu_h(x, P, y, v0, R, nis_gate):
    """The manual's measurement updates mu_g (v0 = g0) and mu_m (v0 = m0):
    h(x) = Q(x)ᵀ v0 through the shared ``correct`` (P in place), then normalised.
    Returns (accepted, NIS, x)."""
    h = qm.Q(x).T @ v0
    ok, nis, dx = correct(P, _jacobian(x, v0), R, y - h, nis_gate)
    if ok:
        x = qm.normalize(x + dx)
    return ok, nis, x



# ------------------------------------------------------------------ the compiled batch run
# ``LabEKF.run`` (the live dashboard's path and the CLI's) runs the very steps of ``_step``
# below in one compiled loop; ``_step`` stays the readable reference (tests hold them to
# 1e-9). The mutable state travels as one float array (slots below) plus x and P.
# slots 0-5: the row bookkeeping every estimator shares (base.B_*)
L_T, L_SEEN, L_W_T, L_W = B_T, B_SEEN, B_W_T, B_W
(L_INIT, L_WAIT_T, L_M0_OK, L_L, L_M_N, L_M_T, L_T_ALIGN) = range(B_N, B_N + 7)
L_WAIT, L_M0, L_M_MEAN = 13, 16, 19     # 3 each: the waiting accelerometer sample, m0, mean field
L_NSTATE = 22
# parameters: switches, limits, noise, references, gates
(LP_USE_GYR, LP_USE_ACC, LP_USE_MAG, LP_MAX_GAP, LP_GYR_HOLD, LP_EXACT, LP_RW, LP_ACC_BAND,
 LP_BAND_MODE, LP_BAND_LO, LP_BAND_HI, LP_MAG_BAND_REL, LP_ALPHA, LP_NIS, LP_P0, LP_LEARN_T,
 LP_G0N) = range(17)
LP_G0, LP_BIAS, LP_SCALE, LP_N = 17, 20, 23, 26      # g0 (3), gyr_bias (3), 1 / (1 + gyr_scale) (3)


@compiled
def _lab_align(s, x, P, p, acc, mag, use_mag):
    if use_mag:
        q = qm.q_from_acc_mag(acc, mag, True)
    else:
        q = qm.q_from_acc_mag(acc, np.zeros(3), False)
    x[:] = q
    P[:, :] = p[LP_P0] * np.eye(4)
    if s[L_M0_OK] > 0.5:
        s[L_L] = qm.norm3(s[L_M0:L_M0 + 3])
    s[L_INIT] = 1.0
    s[L_WAIT_T] = np.nan
    s[L_T_ALIGN] = s[L_T]


@compiled
def _lab_row(s, x, P, p, Rw, Ra, Rm, t, gyr, acc, mag, f):
    """One row: the time update (4.1), the accelerometer (4.2) and magnetometer (4.3)
    updates with their gates, after the initial alignment; ``s`` the state slots above,
    ``x``/``P`` in place, ``f`` the row's flag record. Uncompiled: ``_lab_row.py_func``."""
    use_gyr, use_acc, use_mag = p[LP_USE_GYR] > 0.5, p[LP_USE_ACC] > 0.5, p[LP_USE_MAG] > 0.5
    go, dt, gs, as_, ms, has_w, w = begin_row(s, t, gyr, acc, mag, use_gyr, use_acc, use_mag,
                                              p[LP_MAX_GAP], p[LP_GYR_HOLD], f)
    if not go:
        return
    if s[L_INIT] < 0.5:   # the initial alignment (decided in base.align_step)
        act = align_step(s, L_WAIT_T, L_WAIT, t, gs, as_, ms, acc, use_acc, use_mag, f)
        if act == ALIGN_ACC or act == ALIGN_ACC_MAG:
            _lab_align(s, x, P, p, s[L_WAIT:L_WAIT + 3].copy(), mag, act == ALIGN_ACC_MAG)
        elif act == ALIGN_NO_ACC:
            s[L_INIT] = 1.0
            s[L_T_ALIGN] = t
        return
    if dt > 0.0:   # time update; a random walk without gyroscope
        if not has_w:
            P[:, :] = P + p[LP_RW] ** 2 * dt * np.eye(4)
        else:
            xn, Pn = tu_qw(x, P, (w - p[LP_BIAS:LP_BIAS + 3]) * p[LP_SCALE:LP_SCALE + 3], dt, Rw, p[LP_EXACT] > 0.5)
            x[:] = xn
            P[:, :] = Pn
    if as_ == R_USED:
        n = math.sqrt(acc[0] * acc[0] + acc[1] * acc[1] + acc[2] * acc[2])
        g = p[LP_G0N]
        f[F_ACC_VAL] = n
        if p[LP_ACC_BAND] > 0.0 and abs(n - g) > p[LP_ACC_BAND] * g:
            f[F_ACC] = R_NORM
        else:
            ok, nis, xn = mu_h(x, P, acc, p[LP_G0:LP_G0 + 3].copy(), Ra, p[LP_NIS])
            x[:] = xn
            f[F_ACC_NIS] = nis
            f[F_ACC] = R_USED if ok else R_NIS
    if ms == R_USED:
        if s[L_M0_OK] < 0.5:
            # m0 not given: formula (7) on the mean field levelled by the current estimate
            # over m0_learn_time (exponentially weighted, so the samples taken while the
            # accelerometer was still levelling count little); then the heading is aligned
            # with that mean field, as the initial alignment would have done with it
            mw = qm.Q(x) @ mag
            tau = max(p[LP_LEARN_T] / 4.0, 1e-3)
            k = 1.0 if s[L_M_N] == 0 else min(1.0, max(t - s[L_M_T], 0.0) / tau)
            for i in range(3):
                s[L_M_MEAN + i] += k * (mw[i] - s[L_M_MEAN + i])
            s[L_M_N] += 1.0
            s[L_M_T] = t
            f[F_MAG] = R_WAIT
            if t - s[L_T_ALIGN] >= p[LP_LEARN_T]:
                m = s[L_M_MEAN:L_M_MEAN + 3].copy()
                psi = np.arctan2(m[0], m[1])
                x[:] = qm.normalize(qm.quat_mul(qm.quat_from_rotvec(np.array([0.0, 0.0, psi])), x))
                s[L_M0] = 0.0
                s[L_M0 + 1] = math.hypot(m[0], m[1])
                s[L_M0 + 2] = m[2]
                s[L_M0_OK] = 1.0
                s[L_L] = qm.norm3(s[L_M0:L_M0 + 3])
                f[F_MAG] = R_INIT
            return
        a = p[LP_ALPHA]
        s[L_L] = (1.0 - a) * s[L_L] + a * math.sqrt(mag[0] * mag[0] + mag[1] * mag[1] + mag[2] * mag[2])
        f[F_MAG_VAL] = s[L_L]
        gate = False
        lo = hi = 0.0
        if p[LP_BAND_MODE] > 0.5:
            gate, lo, hi = True, p[LP_BAND_LO], p[LP_BAND_HI]
        elif p[LP_MAG_BAND_REL] > 0.0:
            m0n = qm.norm3(s[L_M0:L_M0 + 3])
            gate, lo, hi = True, m0n * (1 - p[LP_MAG_BAND_REL]), m0n * (1 + p[LP_MAG_BAND_REL])
        if gate and not lo <= s[L_L] <= hi:
            f[F_MAG] = R_FIELD
        else:
            ok, nis, xn = mu_h(x, P, mag, s[L_M0:L_M0 + 3].copy(), Rm, p[LP_NIS])
            x[:] = xn
            f[F_MAG_NIS] = nis
            f[F_MAG] = R_USED if ok else R_NIS


@compiled
def lab_run(s, x, P, p, Rw, Ra, Rm, T, G, A, M, Qout, Fout):
    """Batch: ``_lab_row`` for every row; the estimate and flags after each."""
    for k in range(T.shape[0]):
        _lab_row(s, x, P, p, Rw, Ra, Rm, T[k], G[k], A[k], M[k], Fout[k])
        Qout[k, :] = x


class LabEKF(Estimator):
    name = "lab"
    title = "Lab EKF (4a)"
    Params = LabParams

    def _on_params(self) -> None:
        p = self._params
        self._Rw = _cov(p.gyr_cov, p.gyr_std)
        self._Ra = _cov(p.acc_cov, p.acc_std)
        self._Rm = _cov(p.mag_cov, p.mag_std)
        self._g0 = np.array(p.g0, dtype=float)
        self._g0_norm = float(np.linalg.norm(self._g0))
        self._bias = np.array(p.gyr_bias, dtype=float)
        if getattr(self, "_s", None) is not None and self._init and p.m0 is not None:
            self._s[L_M0_OK] = 1.0
            self._s[L_M0:L_M0 + 3] = p.m0
        v = np.zeros(LP_N)
        v[LP_USE_GYR], v[LP_USE_ACC], v[LP_USE_MAG] = p.use_gyr, p.use_acc, p.use_mag
        v[LP_MAX_GAP], v[LP_GYR_HOLD] = p.max_gap, p.gyr_hold
        v[LP_EXACT], v[LP_RW], v[LP_ACC_BAND] = p.time_update == "exact", p.q_rw_noise, p.acc_band_rel
        if p.mag_band_uT is not None:
            v[LP_BAND_MODE], v[LP_BAND_LO], v[LP_BAND_HI] = 1.0, p.mag_band_uT[0], p.mag_band_uT[1]
        v[LP_MAG_BAND_REL], v[LP_ALPHA], v[LP_NIS] = p.mag_band_rel, p.mag_alpha, p.nis_gate
        v[LP_P0], v[LP_LEARN_T], v[LP_G0N] = p.p0, p.m0_learn_time, self._g0_norm
        v[LP_G0:LP_G0 + 3], v[LP_BIAS:LP_BIAS + 3] = self._g0, self._bias
        v[LP_SCALE:LP_SCALE + 3] = 1.0 / (1.0 + np.asarray(p.gyr_scale, dtype=float))
        self._pv = v

    def set_params(self, **changes) -> None:
        """As :meth:`Estimator.set_params`; and a given ``m0`` taken away (set to 0 0 0, or a
        preset without it) is learned again at once by (7), over ``m0_learn_time`` from now:
        the given one no longer holds (another phone, another place), so it must not stay in
        force until a reset while the page says "learned"."""
        had = self._params.m0
        super().set_params(**changes)
        if had is not None and self._params.m0 is None and getattr(self, "_s", None) is not None:
            self._s[L_M0_OK] = 0.0
            self._s[L_M_N] = 0.0
            self._s[L_M_MEAN:L_M_MEAN + 3] = 0.0
            if self._init:
                self._s[L_T_ALIGN] = self._s[L_T]

    STATE = Estimator.STATE + ("_s", "_x", "_P")   # derived: _Rw, _Ra, _Rm, _g0, _bias, _pv

    def _reset_state(self) -> None:
        # the whole mutable state in three arrays the compiled row updates in place (slots
        # L_*; read through the properties below)
        self._s = np.full(L_NSTATE, np.nan)
        self._s[L_SEEN] = 0.0
        self._s[L_INIT] = 0.0
        m0 = self._params.m0
        self._s[L_M0_OK] = m0 is not None
        if m0 is not None:
            self._s[L_M0:L_M0 + 3] = m0
        self._s[L_M_N] = 0.0
        self._s[L_M_MEAN:L_M_MEAN + 3] = 0.0  # world-frame field averaged while m0 is learned
        self._x = np.array([1.0, 0.0, 0.0, 0.0])
        self._P = self._params.p0 * np.eye(4)

    # ------------------------------------------------------------------ one row
    def _step(self, t, gyr, acc, mag, ori, flags) -> None:
        """One row through the compiled ``_lab_row`` (the one implementation)."""
        _lab_row(self._s, self._x, self._P, self._pv, self._Rw, self._Ra, self._Rm, t, gyr, acc,
                 mag, flags)

    def _mag_band(self) -> tuple[float, float] | None:
        """The band L_k must stay in (µT), or None when the gate is off."""
        p = self._params
        if p.mag_band_uT is not None:
            return float(p.mag_band_uT[0]), float(p.mag_band_uT[1])
        if p.mag_band_rel > 0.0 and self._m0 is not None:
            m0n = float(np.linalg.norm(self._m0))
            return m0n * (1 - p.mag_band_rel), m0n * (1 + p.mag_band_rel)
        return None

    # ------------------------------------------------------------------ batch (compiled)
    def _run_rows(self, t, G, A, M, O, qs, flags) -> None:
        """Rows in order through the compiled ``lab_run`` (the same steps as ``_step``)."""
        lab_run(self._s, self._x, self._P, self._pv, self._Rw, self._Ra, self._Rm, t, G, A, M,
                qs, flags)

    # ------------------------------------------------------------------ state (views)
    @property
    def x(self) -> np.ndarray:
        """The state: the quaternion estimate (the array the filter updates)."""
        return self._x

    @x.setter
    def x(self, v) -> None:
        self._x[:] = v

    @property
    def P(self) -> np.ndarray:
        return self._P

    @P.setter
    def P(self, v) -> None:
        self._P[:, :] = v

    @property
    def _init(self) -> bool:
        return bool(self._s[L_INIT] > 0.5)

    @_init.setter
    def _init(self, v: bool) -> None:
        self._s[L_INIT] = float(bool(v))

    @property
    def _m0(self) -> np.ndarray | None:
        """m0 in world coordinates (µT): given, or learned; None before."""
        return self._s[L_M0:L_M0 + 3].copy() if self._s[L_M0_OK] > 0.5 else None

    @property
    def L(self) -> float:
        """The low-passed field strength L_k (µT)."""
        return float(self._s[L_L])

    # ------------------------------------------------------------------ read-outs
    @property
    def initialized(self) -> bool:
        return self._init

    @property
    def q(self) -> np.ndarray:
        return self._x.copy()

    def attitude_cov(self) -> np.ndarray:
        return qm.attitude_cov_from_quat_cov(self.x, self.P)

    @property
    def gyr_bias(self) -> np.ndarray:
        return self._bias.copy()

    def field_strength(self) -> float:
        return float(self._s[L_L])

    def field_strength_rows(self, flags: np.ndarray, before: float) -> np.ndarray:
        """L_k after each row: the value the field gate tested (``mag_value`` of a row whose
        magnetometer went through it: used, FIELD or NIS), else unchanged. (The one row
        that learns m0 sets L_k = |m0| without a tested value: it shows from the next.)"""
        code = flags[:, F_MAG]
        through = (code == R_USED) | (code == R_FIELD) | (code == R_NIS)
        vals = np.where(through, flags[:, F_MAG_VAL], np.nan)
        idx = np.where(through, np.arange(len(vals)), -1)
        np.maximum.accumulate(idx, out=idx)
        return np.where(idx >= 0, vals[np.maximum(idx, 0)], before)

    def diagnostics(self) -> Diagnostics:
        p = self._params
        g = float(np.linalg.norm(self._g0))
        return Diagnostics(
            g0=vec3(self._g0), m0=vec3(self._m0),
            acc_band=(g * (1 - p.acc_band_rel), g * (1 + p.acc_band_rel)) if p.acc_band_rel > 0 else None,
            mag_band=self._mag_band(),
            L_k=float(self.L),
            acc_nis_gate=float(p.nis_gate), mag_nis_gate=float(p.nis_gate), nis_gate=float(p.nis_gate),
        )
