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

from app.jitcache import compiled


@compiled
def work_size(n: int, m: int) -> int:
    """Floats of the scratch :func:`correct` needs for n states and m measurements."""
    return 2 * n * m + 3 * m * m + n + m


@compiled
def correct(P, H, R, innov, nis_gate, mask=None, work=None):
    """Generic EKF measurement update with an innovation gate; updates ``P`` in place.

    ``nis_gate <= 0`` switches the gate off. ``mask`` (optional, one 0/1 per state)
    names the states the update may change; the gain rows of the others are zeroed
    (a "consider" update: a heading measurement that must not tilt the attitude).
    Returns ``(accepted, nis, dx)``; when the gate refuses, ``dx`` is zero and ``P``
    is left as it was. ``nis`` is ``innov' S^-1 innov`` with ``S = H P H' + R`` (chi-square
    with ``len(innov)`` degrees of freedom when the model is honest).

    ``work`` (optional, at least :func:`work_size` floats): the scratch of the products,
    so that an update makes no array (a filter running at a million samples a second
    spends more on an allocation than on this arithmetic); ``dx`` is then a view into it,
    valid until the next call with the same scratch. Without it the scratch is made here.

    The covariance update is Joseph's form ``(I - K H) P (I - K H)' + K R K'``
    multiplied out, ``P - K (PH')' - PH' K' + K S K'``: exact for any gain (so it
    stays right for the masked one), symmetric by construction, and O(n² m). Zeros of
    H (most of it, for these sensor models) are skipped.
    """
    n = P.shape[0]
    m = H.shape[0]
    if work is None:
        work = np.empty(work_size(n, m))
    # scratch, row-major: PH' (n x m), S (m x m), S^-1 (m x m), K (n x m), dx (n), a row of
    # K S (m), and the copy of S the inverse reduces (m x m)
    o_s = n * m
    o_si = o_s + m * m
    o_k = o_si + m * m
    o_dx = o_k + n * m
    o_ks = o_dx + n
    o_a = o_ks + m
    for i in range(n * m):
        work[i] = 0.0
    for a in range(m):                       # PH' = (H P)' for a symmetric P
        for l in range(n):
            h = H[a, l]
            if h != 0.0:
                for j in range(n):
                    work[j * m + a] += h * P[l, j]
    for a in range(m):                       # S = H PH' + R
        for b in range(m):
            v = 0.0
            for l in range(n):
                h = H[a, l]
                if h != 0.0:
                    v += h * work[l * m + b]
            work[o_s + a * m + b] = R[a, b] + v
    _inv_small(work, o_s, o_si, o_a, m)
    nis = 0.0
    for i in range(m):
        for j in range(m):
            nis += innov[i] * work[o_si + i * m + j] * innov[j]
    for i in range(n * m):                   # K = PH' S^-1
        work[o_k + i] = 0.0
    for i in range(n):
        for l in range(m):
            c = work[i * m + l]
            if c != 0.0:
                for j in range(m):
                    work[o_k + i * m + j] += c * work[o_si + l * m + j]
    dx = work[o_dx:o_dx + n]
    for i in range(n):
        dx[i] = 0.0
    if not np.isfinite(nis) or (nis_gate > 0.0 and nis > nis_gate):
        return False, nis, dx
    if mask is not None:
        for i in range(n):
            if mask[i] == 0.0:
                for j in range(m):
                    work[o_k + i * m + j] = 0.0
    for i in range(n):
        for j in range(m):
            dx[i] += work[o_k + i * m + j] * innov[j]
    # the rows of K S are formed where they are used
    for i in range(n):
        for a in range(m):
            work[o_ks + a] = 0.0
        for l in range(m):
            c = work[o_k + i * m + l]
            if c != 0.0:
                for a in range(m):
                    work[o_ks + a] += c * work[o_s + l * m + a]
        for j in range(i, n):
            v = 0.0
            for a in range(m):
                v += (-work[o_k + i * m + a] * work[j * m + a] - work[i * m + a] * work[o_k + j * m + a]
                      + work[o_ks + a] * work[o_k + j * m + a])
            P[i, j] += v
            if j != i:
                P[j, i] = P[i, j]
    return True, nis, dx


@compiled
def _inv_small(w, o_s, o_out, o_a, m):
    """Inverse of the small symmetric positive definite m x m matrix at ``w[o_s:]`` into
    ``w[o_out:]`` (row-major; closed form up to 2x2, Gauss-Jordan with partial pivoting
    above, reducing a copy at ``w[o_a:]``). A singular matrix gives NaNs."""
    if m == 1:
        w[o_out] = 1.0 / w[o_s]
        return
    if m == 2:
        det = w[o_s] * w[o_s + 3] - w[o_s + 1] * w[o_s + 2]
        w[o_out] = w[o_s + 3] / det
        w[o_out + 1] = -w[o_s + 1] / det
        w[o_out + 2] = -w[o_s + 2] / det
        w[o_out + 3] = w[o_s] / det
        return
    for i in range(m):
        for j in range(m):
            w[o_a + i * m + j] = w[o_s + i * m + j]
            w[o_out + i * m + j] = 1.0 if i == j else 0.0
    for c in range(m):
        piv = c
        for r in range(c + 1, m):
            if abs(w[o_a + r * m + c]) > abs(w[o_a + piv * m + c]):
                piv = r
        if w[o_a + piv * m + c] == 0.0:
            for i in range(m * m):
                w[o_out + i] = np.nan
            return
        if piv != c:
            for j in range(m):
                ca, pa = o_a + c * m + j, o_a + piv * m + j
                w[ca], w[pa] = w[pa], w[ca]
                co, po = o_out + c * m + j, o_out + piv * m + j
                w[co], w[po] = w[po], w[co]
        d = 1.0 / w[o_a + c * m + c]
        for j in range(m):
            w[o_a + c * m + j] *= d
            w[o_out + c * m + j] *= d
        for r in range(m):
            if r != c:
                f = w[o_a + r * m + c]
                if f != 0.0:
                    for j in range(m):
                        w[o_a + r * m + j] -= f * w[o_a + c * m + j]
                        w[o_out + r * m + j] -= f * w[o_out + c * m + j]
