"""The one measurement update every estimator and every sensor model shares.

``correct`` is the EKF measurement update in its Joseph form with the Mahalanobis
distance (normalised innovation squared, NIS) computed first, so a gate can refuse
the update before anything changes. The caller owns what the state correction
means: the lab EKF adds it to the quaternion, the error-state filter injects it
multiplicatively. Written for numba (no Python objects), run as plain numpy too.

The matrices here are tiny (at most 6x6), so the products are written as plain
loops: numba compiles them to a few hundred flops, where a BLAS or LAPACK call
would cost more in overhead than the arithmetic itself.
"""

from __future__ import annotations

import numpy as np
from numba import njit


@njit(cache=True)
def mm(A, B):
    """A @ B for small matrices."""
    n, k = A.shape
    m = B.shape[1]
    C = np.zeros((n, m))
    for i in range(n):
        for l in range(k):
            a = A[i, l]
            if a != 0.0:
                for j in range(m):
                    C[i, j] += a * B[l, j]
    return C


@njit(cache=True)
def inv_small(S):
    """Inverse of a small symmetric positive definite matrix (closed form up to 2x2,
    Gauss-Jordan with partial pivoting above). A singular S gives NaNs."""
    m = S.shape[0]
    out = np.empty((m, m))
    if m == 1:
        out[0, 0] = 1.0 / S[0, 0]
        return out
    if m == 2:
        det = S[0, 0] * S[1, 1] - S[0, 1] * S[1, 0]
        out[0, 0] = S[1, 1] / det
        out[0, 1] = -S[0, 1] / det
        out[1, 0] = -S[1, 0] / det
        out[1, 1] = S[0, 0] / det
        return out
    A = S.copy()
    for i in range(m):
        for j in range(m):
            out[i, j] = 1.0 if i == j else 0.0
    for c in range(m):
        piv = c
        for r in range(c + 1, m):
            if abs(A[r, c]) > abs(A[piv, c]):
                piv = r
        if A[piv, c] == 0.0:
            out[:, :] = np.nan
            return out
        if piv != c:
            for j in range(m):
                A[c, j], A[piv, j] = A[piv, j], A[c, j]
                out[c, j], out[piv, j] = out[piv, j], out[c, j]
        d = 1.0 / A[c, c]
        for j in range(m):
            A[c, j] *= d
            out[c, j] *= d
        for r in range(m):
            if r != c:
                f = A[r, c]
                if f != 0.0:
                    for j in range(m):
                        A[r, j] -= f * A[c, j]
                        out[r, j] -= f * out[c, j]
    return out


@njit(cache=True)
def nis_and_gain(P, H, R, innov):
    """Innovation covariance, NIS and Kalman gain for ``z - h(x) = innov``.

    Returns ``(nis, K, S, PHt)``; ``nis`` is ``innov' S^-1 innov`` (chi-square with
    ``len(innov)`` degrees of freedom when the model is honest). Zeros of H (most
    of it, for these sensor models) are skipped. The products are written out (the
    same sums, in the same order, as :func:`mm` would form them) so a call makes no
    array beyond the four it returns and the inverse: in a filter running at a million
    samples a second, an allocation costs more than the arithmetic.
    """
    n = P.shape[0]
    m = H.shape[0]
    PHt = np.zeros((n, m))  # P H' = (H P)' for a symmetric P
    for a in range(m):
        for l in range(n):
            h = H[a, l]
            if h != 0.0:
                for j in range(n):
                    PHt[j, a] += h * P[l, j]
    S = np.empty((m, m))
    for a in range(m):
        for b in range(m):
            v = 0.0
            for l in range(n):
                h = H[a, l]
                if h != 0.0:
                    v += h * PHt[l, b]
            S[a, b] = R[a, b] + v
    Sinv = inv_small(S)
    nis = 0.0
    for i in range(m):
        for j in range(m):
            nis += innov[i] * Sinv[i, j] * innov[j]
    K = np.zeros((n, m))
    for i in range(n):
        for l in range(m):
            c = PHt[i, l]
            if c != 0.0:
                for j in range(m):
                    K[i, j] += c * Sinv[l, j]
    return nis, K, S, PHt


@njit(cache=True)
def correct(P, H, R, innov, nis_gate, mask=None):
    """Generic EKF measurement update with an innovation gate; updates ``P`` in place.

    ``nis_gate <= 0`` switches the gate off. ``mask`` (optional, one 0/1 per state)
    names the states the update may change; the gain rows of the others are zeroed
    (a "consider" update: a heading measurement that must not tilt the attitude).
    Returns ``(accepted, nis, dx)``; when the gate refuses, ``dx`` is zero and ``P``
    is left as it was.

    The covariance update is Joseph's form ``(I - K H) P (I - K H)' + K R K'``
    multiplied out, ``P - K (PH')' - PH' K' + K S K'``: exact for any gain (so it
    stays right for the masked one), symmetric by construction, and O(n² m).
    """
    nis, K, S, PHt = nis_and_gain(P, H, R, innov)
    n = P.shape[0]
    m = innov.shape[0]
    dx = np.zeros(n)
    if not np.isfinite(nis) or (nis_gate > 0.0 and nis > nis_gate):
        return False, nis, dx
    if mask is not None:
        for i in range(n):
            if mask[i] == 0.0:
                for j in range(m):
                    K[i, j] = 0.0
    for i in range(n):
        for j in range(m):
            dx[i] += K[i, j] * innov[j]
    # K S, row by row into S's place is not possible (S is used by every row): the
    # rows of K S are formed where they are used, with mm's order of the sum
    KSi = np.empty(m)
    for i in range(n):
        for a in range(m):
            KSi[a] = 0.0
        for l in range(m):
            c = K[i, l]
            if c != 0.0:
                for a in range(m):
                    KSi[a] += c * S[l, a]
        for j in range(i, n):
            v = 0.0
            for a in range(m):
                v += -K[i, a] * PHt[j, a] - PHt[i, a] * K[j, a] + KSi[a] * K[j, a]
            P[i, j] += v
            if j != i:
                P[j, i] = P[i, j]
    return True, nis, dx
