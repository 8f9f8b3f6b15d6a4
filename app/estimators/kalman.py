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
def correct(P, H, R, innov, nis_gate, mask=None):
    """Generic EKF measurement update with an innovation gate.

    ``nis_gate <= 0`` switches the gate off. ``mask`` (optional, one 0/1 per state)
    names the states the update may change; the gain rows of the others are zeroed
    (a "consider" update: a heading measurement that must not tilt the attitude).
    Returns ``(accepted, nis, dx, P_new)``; when the gate refuses, ``dx`` is zero
    and ``P_new`` is ``P`` (unchanged). The covariance update is Joseph's form,
    which stays right for the masked (sub-optimal) gain and keeps P symmetric.
    """
    nis, K, S = nis_and_gain(P, H, R, innov)
    n = P.shape[0]
    if not np.isfinite(nis) or (nis_gate > 0.0 and nis > nis_gate):
        return False, nis, np.zeros(n), P
    if mask is not None:
        for i in range(n):
            if mask[i] == 0.0:
                K[i, :] = 0.0
    dx = K @ innov
    IKH = np.eye(n) - K @ H
    P_new = IKH @ P @ IKH.T + K @ R @ K.T
    P_new = 0.5 * (P_new + P_new.T)
    return True, nis, dx, P_new
