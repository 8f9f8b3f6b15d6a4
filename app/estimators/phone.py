"""``phone``: the phone's own orientation estimate (the app's ORI tag), passed through.

Android's rotation-vector sensor already fuses the phone's sensors; the Sensor Fusion
app streams it as ORI ``w x y z`` (scalar first, sensor->world ENU, our convention), or
rarely as ``x y z`` only, with ``w = sqrt(1 - x² - y² - z²)``. This estimator shows it
beside ours: each ORI sample is normalised (unit length, ``w >= 0``) and held until the
next one, for at most :data:`ORI_HOLD_S` of stream time: an app that stopped sending
ORI while its other sensors go on has no estimate of its own any more. It uses no other
sensor: their samples are flagged DISABLED (present but not used by this estimator) or
ABSENT. Before the first ORI sample, and once the held one expired, it is not initialised
and its estimate is the identity.
"""

from __future__ import annotations

import numpy as np

from app import quaternion as qm
from app.jitcache import compiled
from app.params import CommonParams
from app.estimators.base import (B_N, B_SEEN, F_ACC, F_GYR, F_MAG, R_DISABLED, R_USED,
                   Diagnostics, Estimator, begin_row)

P_INIT, P_ORI_T = B_N, B_N + 1      # state slots after the row bookkeeping
# how long an ORI sample is held: as long as a sensor may pause in a phone app's batches
# before it counts as stopped (app.sources.ordering.STOPPED_S)
ORI_HOLD_S = 3.0


def ori_quaternion(ori) -> np.ndarray | None:
    """The unit quaternion (w >= 0) of an ORI sample of 4 (w x y z) or 3 (x y z) values;
    None if it is absent (None, all NaN) or unusable (non-finite, zero, or a vector part
    longer than 1)."""
    if ori is None:
        return None
    v = np.asarray(ori, dtype=float).reshape(-1)
    if v.size and np.isnan(v[0]) and np.isnan(v).all():  # the common case: no ORI in this row
        return None
    if v.size == 3:
        if not np.all(np.isfinite(v)):
            return None
        s = 1.0 - float(v @ v)
        if s < -1e-6:
            return None
        v = np.concatenate(([np.sqrt(max(s, 0.0))], v))
    if v.size != 4 or not np.all(np.isfinite(v)) or not np.any(v != 0.0):
        return None
    return qm.normalize(v)


@compiled
def _ori_valid(v):
    """The 4-value case of :func:`ori_quaternion`: finite and not all zero."""
    nz = False
    for i in range(4):
        if not np.isfinite(v[i]):
            return False
        if v[i] != 0.0:
            nz = True
    return nz


@compiled
def phone_run(s, q, use, max_gap, gyr_hold, T, G, A, M, O, Qout, Fout):
    """Batch: every row's bookkeeping (``begin_row``; a present sensor sample is "switched
    off" for this estimator), and each valid ORI sample normalised and held. ``s``: the
    row bookkeeping (slots ``B_*``), then init and the time of the ORI shown; ``q`` in place."""
    for k in range(T.shape[0]):
        f = Fout[k]
        go, dt, gs, as_, ms, has_w, w = begin_row(s, T[k], G[k], A[k], M[k], use[0], use[1],
                                                  use[2], max_gap, gyr_hold, f)
        if go:
            f[F_GYR] = R_DISABLED if gs == R_USED else f[F_GYR]
            f[F_ACC] = R_DISABLED if as_ == R_USED else as_
            f[F_MAG] = R_DISABLED if ms == R_USED else ms
            o = O[k]
            if _ori_valid(o):
                q[:] = qm.normalize(o)
                s[P_INIT] = 1.0
                s[P_ORI_T] = T[k]
            elif s[P_INIT] > 0.5 and T[k] - s[P_ORI_T] > ORI_HOLD_S:
                q[:] = 0.0                    # expired: no estimate (the identity)
                q[0] = 1.0
                s[P_INIT] = 0.0
        Qout[k, :] = q


class PhoneOrientation(Estimator):
    name = "phone"
    title = "Phone's own estimate (ORI)"
    reference = True
    Params = CommonParams

    def _on_params(self) -> None:
        p = self._params
        self._use = np.array([p.use_gyr, p.use_acc, p.use_mag], dtype=bool)

    STATE = Estimator.STATE + ("_s", "_q")     # derived from the parameters: _use

    def _reset_state(self) -> None:
        # the row bookkeeping (slots B_*), init and the time of the ORI shown; q apart
        self._s = np.full(B_N + 2, np.nan)
        self._s[B_SEEN] = 0.0
        self._s[P_INIT] = 0.0
        self._q = np.array([1.0, 0.0, 0.0, 0.0])

    def _step(self, t, gyr, acc, mag, ori, flags) -> None:
        """One row through the compiled ``phone_run`` (the one implementation)."""
        o = ori_quaternion(ori)        # also takes the 3-value form and refuses |v| > 1
        p = self._params
        phone_run(self._s, self._q, self._use, p.max_gap, p.gyr_hold, np.array([t], dtype=float),
                  gyr.reshape(1, 3), acc.reshape(1, 3), mag.reshape(1, 3),
                  (np.full(4, np.nan) if o is None else o).reshape(1, 4), np.empty((1, 4)),
                  flags.reshape(1, -1))

    def _run_rows(self, t, G, A, M, O, qs, flags) -> None:
        """Rows in order through the compiled ``phone_run`` (the steps of ``_step``)."""
        p = self._params
        phone_run(self._s, self._q, self._use, p.max_gap, p.gyr_hold, t, G, A, M, O, qs, flags)

    @property
    def _init(self) -> bool:
        return bool(self._s[P_INIT] > 0.5)

    @property
    def _ori_t(self) -> float:
        return float(self._s[P_ORI_T])

    @property
    def initialized(self) -> bool:
        return self._init

    @property
    def q(self) -> np.ndarray:
        return self._q.copy()

    def attitude_cov(self) -> None:
        return None

    def diagnostics(self) -> Diagnostics:
        """Time (s) of the ORI sample shown and its age at the last row."""
        return Diagnostics(ori_t=float(self._ori_t), ori_age=float(self.t - self._ori_t))
