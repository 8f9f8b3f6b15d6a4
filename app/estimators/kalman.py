"""The one measurement update every estimator and every sensor model shares.

``correct`` is the EKF measurement update in its Joseph form with the Mahalanobis
distance (normalised innovation squared, NIS) computed first, so a gate can refuse
the update before anything changes. The caller owns what the state correction
means: the lab EKF adds it to the quaternion, the error-state filter injects it
multiplicatively. Written for numba (no Python objects), run as plain numpy too.
"""

from __future__ import annotations

import numpy as np
from numba import njit


@njit(cache=True)
def nis_and_gain(P, H, R, innov):
    """Innovation covariance, NIS and Kalman gain for ``z - h(x) = innov``.

    Returns ``(nis, K, S)``; ``nis`` is ``innov' S^-1 innov`` (chi-square with
    ``len(innov)`` degrees of freedom when the model is honest).
    """
    PHt = P @ H.T
    S = H @ PHt + R
    Sinv = np.linalg.inv(S)
    nis = innov @ (Sinv @ innov)
    K = PHt @ Sinv
    return nis, K, S


@njit(cache=True)
def correct(P, H, R, innov, nis_gate):
    """Generic EKF measurement update with an innovation gate.

    ``nis_gate <= 0`` switches the gate off. Returns ``(accepted, nis, dx, P_new)``;
    when the gate refuses, ``dx`` is zero and ``P_new`` is ``P`` (unchanged).
    The covariance update is Joseph's form, which keeps P symmetric positive
    semi-definite even with a sub-optimal gain.
    """
    nis, K, S = nis_and_gain(P, H, R, innov)
    n = P.shape[0]
    if not np.isfinite(nis) or (nis_gate > 0.0 and nis > nis_gate):
        return False, nis, np.zeros(n), P
    dx = K @ innov
    IKH = np.eye(n) - K @ H
    P_new = IKH @ P @ IKH.T + K @ R @ K.T
    P_new = 0.5 * (P_new + P_new.T)
    return True, nis, dx, P_new
