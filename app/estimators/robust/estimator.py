"""``RobustEKF``: the robust filter as an :class:`~app.estimators.base.Estimator`.

It holds the parameter vector (rebuilt on every change of the parameters), the state
vector and the 6x6 covariance, hands rows to the compiled kernels (:mod:`.kernel`) and
reads its estimates and diagnostics out of the state's named slots.
"""

from __future__ import annotations

import numpy as np

from app.estimators.base import Diagnostics, Estimator, index_ok, vec3
from app.estimators.robust.hardiron import HI_STATUS
from app.estimators.robust.heading import deviation_density, evidence_density
from app.estimators.robust.kernel import robust_run, robust_step
from app.estimators.robust.params import RobustParams, param_vector
from app.params import GRAVITY
from app.estimators.robust.state import S, new_state


class RobustEKF(Estimator):
    name = "robust"
    title = "Robust error-state EKF (default)"
    Params = RobustParams

    def _on_params(self) -> None:
        self._p = param_vector(self._params)

    STATE = Estimator.STATE + ("_s", "_P")     # derived from the parameters: _p

    def _state_error(self) -> str | None:
        if not index_ok(self._s[S.hi_status], len(HI_STATUS)):
            return f"hard-iron status {self._s[S.hi_status]!r}"
        return super()._state_error()

    def _reset_state(self) -> None:
        self._s = new_state()
        self._P = np.eye(6) * 1e-4

    def _step(self, t, gyr, acc, mag, ori, flags) -> None:
        robust_step(self._s, self._P, self._p, t, gyr, acc, mag, flags)

    def _run_rows(self, t, G, A, M, O, qs, flags) -> None:
        robust_run(self._s, self._P, self._p, t, G, A, M, qs, flags)

    @property
    def t(self) -> float:
        return float(self._s[S.t])

    @property
    def initialized(self) -> bool:
        return bool(self._s[S.aligned])

    @property
    def q(self) -> np.ndarray:
        return self._s[S.q:S.q + 4].copy()

    def attitude_cov(self) -> np.ndarray:
        return self._P[0:3, 0:3].copy()

    @property
    def gyr_bias(self) -> np.ndarray:
        return self._s[S.bias:S.bias + 3].copy()

    @property
    def covariance(self) -> np.ndarray:
        return self._P.copy()

    def diagnostics(self):
        """Diagnostics: gravity as the reference, the learned field (None until learned)."""
        p, s = self._params, self._s
        ok = bool(s[S.ref_ok])
        ref_n, dip = float(s[S.ref_norm]), float(s[S.ref_dip])
        wander = float(s[S.hv_var]) if s[S.hv_ok] and p.heading_evidence_tau > 0 else 0.0
        return Diagnostics(
            g0=(0.0, 0.0, GRAVITY),
            # the expected field in world coordinates (µT): north and the learned dip
            m0=vec3((0.0, ref_n * np.cos(dip), ref_n * np.sin(dip))) if ok else None,
            acc_band=(GRAVITY * (1 - p.acc_band_rel), GRAVITY * (1 + p.acc_band_rel))
            if p.acc_band_rel > 0 else None,
            mag_band=(ref_n * (1 - p.mag_norm_gate_rel), ref_n * (1 + p.mag_norm_gate_rel))
            if p.mag_norm_gate_rel > 0 and ok else None,
            mag_ref_norm=ref_n if ok else None,
            mag_ref_dip=dip if ok else None,
            acc_lp_world=vec3(s[S.acc_lp:S.acc_lp + 3]),
            gyr_bias=vec3(s[S.bias:S.bias + 3]),
            rest=bool(s[S.rest]),
            mag_offset=vec3(s[S.hi_o:S.hi_o + 3]),
            mag_offset_status=HI_STATUS[int(s[S.hi_status])],
            heading_wander=float(np.sqrt(wander)),
            heading_noise_now=float(np.sqrt(p.heading_noise ** 2 + evidence_density(wander)
                                             + deviation_density(s, self._p))),
        )

    @property
    def mag_offset(self) -> tuple[np.ndarray, str]:
        """The sensor-fixed field offset removed now (µT, sensor frame; zero unless applied)
        and the status of its fit ("none", "tracking", "applied")."""
        return self._s[S.hi_applied:S.hi_applied + 3].copy(), HI_STATUS[int(self._s[S.hi_status])]
