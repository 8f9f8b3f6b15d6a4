"""``phone``: the phone's own orientation estimate (the app's ORI tag), passed through.

Android's rotation-vector sensor already fuses the phone's sensors; the Sensor Fusion
app streams it as ORI ``w x y z`` (scalar first, sensor->world ENU, our convention), or
rarely as ``x y z`` only, with ``w = sqrt(1 - x² - y² - z²)``. This estimator shows it
beside ours: each ORI sample is normalised (unit length, ``w >= 0``) and held until the
next one. It uses no other sensor: their samples are flagged DISABLED (present but not
used by this estimator) or ABSENT. Before the first ORI sample it is not initialised
and its estimate is the identity.
"""

from __future__ import annotations

import numpy as np

from .. import quaternion as qm
from ..params import CommonParams
from .base import F_ACC, F_GYR, F_MAG, Estimator, Reason


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


class PhoneOrientation(Estimator):
    name = "phone"
    title = "Phone's own estimate (ORI)"
    Params = CommonParams

    def _reset_state(self) -> None:
        self._q = np.array([1.0, 0.0, 0.0, 0.0])
        self._init = False
        self._ori_t = float("nan")

    def _step(self, t, gyr, acc, mag, ori, flags) -> None:
        row = self._begin_row(t, gyr, acc, mag, flags)
        if row is None:
            return
        # the sensors are never used: a present sample is "switched off" for this estimator
        for col, st in ((F_GYR, row.gyr), (F_ACC, row.acc), (F_MAG, row.mag)):
            if st == Reason.USED:
                flags[col] = Reason.DISABLED
        q = ori_quaternion(ori)
        if q is not None:
            self._q = q
            self._init = True
            self._ori_t = t

    @property
    def initialized(self) -> bool:
        return self._init

    @property
    def q(self) -> np.ndarray:
        return self._q.copy()

    def attitude_cov(self) -> None:
        return None

    def diagnostics(self) -> dict:
        """Time (s) of the ORI sample shown and its age at the last row."""
        return {"ori_t": self._ori_t, "ori_age": self.t - self._ori_t}
