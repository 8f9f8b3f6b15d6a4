"""``lab``: the lab manual's EKF, structure (4a), as a student writes it.

State ``x = q`` (4 quaternion components), covariance ``P`` (4x4); the gyroscope is
the input. Hold this file beside the manual:

- time update (Section 4.1): ``q <- F q``, ``P <- F P Fᵀ + G Rw Gᵀ`` with
  ``F = exp(1/2 S(ω) T)`` (exact, 2j) or ``I + 1/2 S(ω) T`` (approximate, 2k) and
  ``G = T/2 S̄(q)``; with the gyroscope off or missing, a random walk
  ``P <- P + rw_noise² T I``;
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

import math

import numpy as np
from numba import njit

from .. import quaternion as qm
from ..params import CommonParams, DEG, ParamError, param
from .base import ALIGN_WAIT_S, F_ACC, F_ACC_NIS, F_ACC_VAL, F_MAG, F_MAG_NIS, F_MAG_VAL, Estimator, Reason
from .kalman import correct



@dataclass(frozen=True)
class LabParams(CommonParams):
    time_update: str = param("exact", choices=("exact", "approx"),
                             doc="exact (2j) or approximate (2k) quaternion time update")
    gyr_noise: float = param(0.01, unit="rad/s", lo=1e-6, hi=1.0, user_unit="deg/s", user_scale=DEG,
                             log=True, doc="gyroscope noise σ (Rw = σ² I per sample)")
    acc_noise: float = param(0.5, unit="m/s²", lo=1e-4, hi=20.0, log=True,
                             doc="accelerometer noise σ (Ra = σ² I)")
    mag_noise: float = param(2.0, unit="µT", lo=1e-3, hi=100.0, log=True,
                             doc="magnetometer noise σ (Rm = σ² I)")
    gyr_cov: tuple | None = param(None, unit="(rad/s)²", length=9, optional=True, tunable=False,
                                  doc="full Rw (row-major 3x3) from calibration; overrides gyr_noise")
    acc_cov: tuple | None = param(None, unit="(m/s²)²", length=9, optional=True, tunable=False,
                                  doc="full Ra (row-major 3x3) from calibration; overrides acc_noise")
    mag_cov: tuple | None = param(None, unit="µT²", length=9, optional=True, tunable=False,
                                  doc="full Rm (row-major 3x3) from calibration; overrides mag_noise")
    rw_noise: float = param(0.3, unit="1/√s", lo=1e-6, hi=10.0, log=True,
                            doc="random-walk noise of q without gyroscope (P += σ² T I)")
    g0: tuple = param((0.0, 0.0, 9.81), unit="m/s²", lo=-20.0, hi=20.0, tunable=False,
                      doc="nominal gravity (specific force at rest) in world coordinates")
    m0: tuple | None = param(None, unit="µT", length=3, lo=-200.0, hi=200.0, optional=True,
                             tunable=False, doc="nominal field in world coordinates; None: "
                             "from the data at alignment, formula (7)")
    gyr_bias: tuple = param((0.0, 0.0, 0.0), unit="rad/s", lo=-1.0, hi=1.0, tunable=False,
                            doc="gyroscope bias subtracted from every sample (calibration)")
    acc_band_rel: float = param(0.25, lo=0.0, hi=1.0,
                                doc="accelerometer used only while | |a| - |g0| | <= this × |g0|; 0: off")
    mag_band_rel: float = param(0.2, lo=0.0, hi=1.0,
                                doc="magnetometer used only while | L_k - |m0| | <= this × |m0|; 0: off")
    mag_band_uT: tuple | None = param(None, unit="µT", length=2, lo=0.0, hi=1000.0, optional=True,
                                      tunable=False, doc="absolute band (lo, hi) for L_k, as report A's "
                                      "35-55 µT; overrides mag_band_rel when given")
    mag_alpha: float = param(0.01, lo=0.0, hi=1.0, doc="α of the field-strength filter L_k")
    nis_gate: float = param(0.0, lo=0.0, hi=1000.0,
                            doc="innovation gate on NIS (χ², 3 dof) for both updates; 0: off")
    p0: float = param(0.1, lo=1e-8, hi=10.0, log=True, tunable=False,
                      doc="initial P = p0 I after alignment")
    m0_learn_time: float = param(2.0, unit="s", lo=0.0, hi=60.0, tunable=False,
                                 doc="when m0 is not given: learn it by (7) from the mean field of "
                                     "this long after alignment (the accelerometer levels it meanwhile)")

    def check(self) -> None:
        if np.linalg.norm(self.g0) < 1.0:
            raise ParamError("g0", "must be a gravity vector (|g0| >= 1 m/s²)")
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


@njit(cache=True)
def _jacobian(q, v0):
    """d/dq of Q(q)ᵀ v0: column i is dQ/dq_i ᵀ v0 (the manual's mu_g / mu_m)."""
    D = qm.dQdq(q)
    H = np.empty((3, 4))
    for i in range(4):
        H[:, i] = D[i].T @ v0
    return H


@njit(cache=True)
def tu_qw(x, P, omega, T, Rw, exact):
    """The manual's time update (Section 4.1): x <- F x, P <- F P Fᵀ + G Rw Gᵀ with
    F from (2j) or (2k) and G = T/2 S̄(x); x normalised (4.4)."""
    F = qm.F_exact(omega, T) if exact else qm.F_approx(omega, T)
    G = 0.5 * T * qm.S_bar(x)
    return qm.normalize(F @ x), F @ P @ F.T + G @ Rw @ G.T


@njit(cache=True)
def mu_h(x, P, y, v0, R, nis_gate):
    """The manual's measurement updates mu_g (v0 = g0) and mu_m (v0 = m0):
    h(x) = Q(x)ᵀ v0 through the shared ``correct`` (P in place), then normalised.
    Returns (accepted, NIS, x)."""
    h = qm.Q(x).T @ v0
    ok, nis, dx = correct(P, _jacobian(x, v0), R, y - h, nis_gate)
    if ok:
        x = qm.normalize(x + dx)
    return ok, nis, x


class LabEKF(Estimator):
    name = "lab"
    title = "Lab EKF (4a)"
    Params = LabParams

    def _on_params(self) -> None:
        p = self._params
        self._Rw = _cov(p.gyr_cov, p.gyr_noise)
        self._Ra = _cov(p.acc_cov, p.acc_noise)
        self._Rm = _cov(p.mag_cov, p.mag_noise)
        self._g0 = np.array(p.g0, dtype=float)
        self._g0_norm = float(np.linalg.norm(self._g0))
        self._bias = np.array(p.gyr_bias, dtype=float)
        if getattr(self, "_init", False) and p.m0 is not None:
            self._m0 = np.array(p.m0, dtype=float)

    def _reset_state(self) -> None:
        self.x = np.array([1.0, 0.0, 0.0, 0.0])
        self.P = self._params.p0 * np.eye(4)
        self._init = False
        self._acc_wait = None   # (t, acc) waiting for a magnetometer sample to align
        self._m0 = None if self._params.m0 is None else np.array(self._params.m0, dtype=float)
        self.L = float("nan")
        self._m_mean = np.zeros(3)  # world-frame field averaged while m0 is learned
        self._m_n = 0
        self._m_t = float("nan")
        self._t_align = float("nan")

    # ------------------------------------------------------------------ helpers
    def _align(self, acc, mag) -> None:
        p = self._params
        use_mag = mag is not None
        self.x = qm.q_from_acc_mag(acc, mag if use_mag else np.zeros(3), use_mag)
        self.P = p.p0 * np.eye(4)
        if self._m0 is not None:
            self.L = float(np.linalg.norm(self._m0))
        self._init = True
        self._acc_wait = None
        self._t_align = self.t

    def _learn_m0(self, mag, flags) -> bool:
        """Formula (7) on the mean field levelled by the current estimate over
        ``m0_learn_time`` (exponentially weighted, so the samples taken while the
        accelerometer was still levelling count little); the heading is then aligned
        with that mean field, as the initial alignment would have done with it.
        True once m0 is known."""
        if self._m0 is not None:
            return True
        mw = qm.Q(self.x) @ mag
        tau = max(self._params.m0_learn_time / 4.0, 1e-3)
        k = 1.0 if self._m_n == 0 else min(1.0, max(self.t - self._m_t, 0.0) / tau)
        self._m_mean += k * (mw - self._m_mean)
        self._m_n += 1
        self._m_t = self.t
        flags[F_MAG] = Reason.WAIT
        if self.t - self._t_align >= self._params.m0_learn_time:
            m = self._m_mean
            psi = np.arctan2(m[0], m[1])  # the mean field's heading east of north
            self.x = qm.normalize(qm.quat_mul(qm.quat_from_rotvec(np.array([0.0, 0.0, psi])), self.x))
            self._m0 = qm.field_reference(m)
            self.L = float(np.linalg.norm(self._m0))
            flags[F_MAG] = Reason.INIT
        return False

    def _time_update(self, w, T) -> None:
        p = self._params
        if w is None:
            self.P = self.P + p.rw_noise ** 2 * T * np.eye(4)
            return
        self.x, self.P = tu_qw(self.x, self.P, w - self._bias, T, self._Rw,
                               p.time_update == "exact")

    def _measurement_update(self, y, v0, R, flags, col_reason, col_nis) -> None:
        ok, nis, self.x = mu_h(self.x, self.P, y, v0, R, self._params.nis_gate)  # P in place
        flags[col_nis] = nis
        if ok:
            flags[col_reason] = Reason.USED
        else:
            flags[col_reason] = Reason.NIS

    # ------------------------------------------------------------------ one row
    def _step(self, t, gyr, acc, mag, ori, flags) -> None:
        row = self._begin_row(t, gyr, acc, mag, flags)
        if row is None:
            return
        p = self._params
        if not self._init:
            self._try_align(t, row, acc, mag, flags)
            return
        if row.dt > 0.0:
            self._time_update(row.w, row.dt)

        if row.acc == Reason.USED:
            n = math.hypot(acc[0], acc[1], acc[2])
            g = self._g0_norm
            flags[F_ACC_VAL] = n
            if p.acc_band_rel > 0.0 and abs(n - g) > p.acc_band_rel * g:
                flags[F_ACC] = Reason.NORM
            else:
                self._measurement_update(acc, self._g0, self._Ra, flags, F_ACC, F_ACC_NIS)

        if row.mag == Reason.USED and self._learn_m0(mag, flags):
            a = p.mag_alpha
            self.L = (1.0 - a) * self.L + a * math.hypot(mag[0], mag[1], mag[2])
            flags[F_MAG_VAL] = self.L
            band = self._mag_band()
            if band is not None and not band[0] <= self.L <= band[1]:
                flags[F_MAG] = Reason.FIELD
            else:
                self._measurement_update(mag, self._m0, self._Rm, flags, F_MAG, F_MAG_NIS)

    def _mag_band(self) -> tuple[float, float] | None:
        """The band L_k must stay in (µT), or None when the gate is off."""
        p = self._params
        if p.mag_band_uT is not None:
            return float(p.mag_band_uT[0]), float(p.mag_band_uT[1])
        if p.mag_band_rel > 0.0 and self._m0 is not None:
            m0n = float(np.linalg.norm(self._m0))
            return m0n * (1 - p.mag_band_rel), m0n * (1 + p.mag_band_rel)
        return None

    def _try_align(self, t, row, acc, mag, flags) -> None:
        """Initial alignment from the first accelerometer (+ magnetometer) sample."""
        p = self._params
        for col, st in ((0, row.gyr), (F_ACC, row.acc), (F_MAG, row.mag)):
            if st == Reason.USED:
                flags[col] = Reason.WAIT
        if row.acc == Reason.USED:
            if not p.use_mag:
                self._align(acc, None)
                flags[F_ACC] = Reason.INIT
                return
            self._acc_wait = (t, acc.copy())
        if row.mag == Reason.USED and self._acc_wait is not None:
            self._align(self._acc_wait[1], mag)
            flags[F_MAG] = Reason.INIT
            return
        if self._acc_wait is not None and t - self._acc_wait[0] > ALIGN_WAIT_S:
            self._align(self._acc_wait[1], None)  # no magnetometer came: heading 0
            flags[F_ACC] = Reason.INIT
            return
        if not p.use_acc and (row.mag == Reason.USED or row.gyr == Reason.USED):
            # no accelerometer: start level and let the updates (or the gyro) take over
            self._init = True
            self._t_align = t

    # ------------------------------------------------------------------ read-outs
    @property
    def initialized(self) -> bool:
        return self._init

    @property
    def q(self) -> np.ndarray:
        return self.x.copy()

    def attitude_cov(self) -> np.ndarray:
        return qm.attitude_cov_from_quat_cov(self.x, self.P)

    @property
    def gyr_bias(self) -> np.ndarray:
        return self._bias.copy()

    def diagnostics(self) -> dict:
        p = self._params
        g = float(np.linalg.norm(self._g0))
        return {
            "acc_band": (g * (1 - p.acc_band_rel), g * (1 + p.acc_band_rel)) if p.acc_band_rel > 0 else None,
            "mag_band": self._mag_band(),
            "L_k": self.L,
            "m0": None if self._m0 is None else self._m0.tolist(),
            "g0": self._g0.tolist(),
            "nis_gate": p.nis_gate,
        }
