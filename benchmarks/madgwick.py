"""Madgwick's MARG filter (gradient descent), the benchmark's comparison filter.

Written here in orientlab's conventions (ENU world, scalar-first quaternion from sensor
to world) so no frame conversion of a third-party package can skew the comparison. The
magnetometer reference is learned as in Madgwick's paper: the measured field rotated to
the world frame, its horizontal part put on the north axis. One gain for all trials.
"""

from __future__ import annotations

import numpy as np
from numba import njit


@njit(cache=True)
def madgwick_batch(gyr, acc, mag, fs, beta):
    n = gyr.shape[0]
    out = np.empty((n, 4))
    q0, q1, q2, q3 = 1.0, 0.0, 0.0, 0.0
    dt = 1.0 / fs
    for k in range(n):
        gx, gy, gz = gyr[k, 0], gyr[k, 1], gyr[k, 2]
        # rate of change from the gyroscope: qdot = 1/2 q * (0, w)
        qd0 = 0.5 * (-q1 * gx - q2 * gy - q3 * gz)
        qd1 = 0.5 * (q0 * gx + q2 * gz - q3 * gy)
        qd2 = 0.5 * (q0 * gy - q1 * gz + q3 * gx)
        qd3 = 0.5 * (q0 * gz + q1 * gy - q2 * gx)
        ax, ay, az = acc[k, 0], acc[k, 1], acc[k, 2]
        an = np.sqrt(ax * ax + ay * ay + az * az)
        mx, my, mz = mag[k, 0], mag[k, 1], mag[k, 2]
        mn = np.sqrt(mx * mx + my * my + mz * mz)
        if an > 0.0:
            ax /= an; ay /= an; az /= an
            # objective: f = Q(q)^T d - s for d = up (0,0,1) and the field (0, by, bz)
            # predicted 'up' in the sensor frame: third row of Q(q)
            f1 = 2.0 * (q1 * q3 - q0 * q2) - ax
            f2 = 2.0 * (q0 * q1 + q2 * q3) - ay
            f3 = 2.0 * (0.5 - q1 * q1 - q2 * q2) - az
            s0 = -2.0 * q2 * f1 + 2.0 * q1 * f2
            s1 = 2.0 * q3 * f1 + 2.0 * q0 * f2 - 4.0 * q1 * f3
            s2 = -2.0 * q0 * f1 + 2.0 * q3 * f2 - 4.0 * q2 * f3
            s3 = 2.0 * q1 * f1 + 2.0 * q2 * f2
            if mn > 0.0 and np.isfinite(mn):
                mx /= mn; my /= mn; mz /= mn
                # field in the world frame: h = Q(q) m
                hx = (1 - 2 * (q2 * q2 + q3 * q3)) * mx + 2 * (q1 * q2 - q0 * q3) * my + 2 * (q1 * q3 + q0 * q2) * mz
                hy = 2 * (q1 * q2 + q0 * q3) * mx + (1 - 2 * (q1 * q1 + q3 * q3)) * my + 2 * (q2 * q3 - q0 * q1) * mz
                hz = 2 * (q1 * q3 - q0 * q2) * mx + 2 * (q2 * q3 + q0 * q1) * my + (1 - 2 * (q1 * q1 + q2 * q2)) * mz
                by = np.sqrt(hx * hx + hy * hy)
                bz = hz
                # predicted field in sensor frame: Q(q)^T (0, by, bz) = by * row2 + bz * row3 of Q^T
                p1 = by * 2 * (q1 * q2 + q0 * q3) + bz * 2 * (q1 * q3 - q0 * q2) - mx
                p2 = by * (1 - 2 * (q1 * q1 + q3 * q3)) + bz * 2 * (q0 * q1 + q2 * q3) - my
                p3 = by * 2 * (q2 * q3 - q0 * q1) + bz * (1 - 2 * (q1 * q1 + q2 * q2)) - mz
                # Jacobian transpose times residual (derivatives of the three components wrt q)
                s0 += by * (2 * q3 * p1 + 0.0 * p2 - 2 * q1 * p3) + bz * (-2 * q2 * p1 + 2 * q1 * p2 + 0.0 * p3)
                s1 += by * (2 * q2 * p1 - 4 * q1 * p2 - 2 * q0 * p3) + bz * (2 * q3 * p1 + 2 * q0 * p2 - 4 * q1 * p3)
                s2 += by * (2 * q1 * p1 + 0.0 * p2 + 2 * q3 * p3) + bz * (-2 * q0 * p1 + 2 * q3 * p2 - 4 * q2 * p3)
                s3 += by * (2 * q0 * p1 - 4 * q3 * p2 + 2 * q2 * p3) + bz * (2 * q1 * p1 + 2 * q2 * p2 + 0.0 * p3)
            sn = np.sqrt(s0 * s0 + s1 * s1 + s2 * s2 + s3 * s3)
            if sn > 0.0:
                qd0 -= beta * s0 / sn
                qd1 -= beta * s1 / sn
                qd2 -= beta * s2 / sn
                qd3 -= beta * s3 / sn
        q0 += qd0 * dt; q1 += qd1 * dt; q2 += qd2 * dt; q3 += qd3 * dt
        nn = np.sqrt(q0 * q0 + q1 * q1 + q2 * q2 + q3 * q3)
        q0 /= nn; q1 /= nn; q2 /= nn; q3 /= nn
        out[k, 0] = q0; out[k, 1] = q1; out[k, 2] = q2; out[k, 3] = q3
    return out
