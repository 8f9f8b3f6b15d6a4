"""How far the 2σ cones can be trusted: robust's own covariance against its error to the
optical truth, on the shared trials.

The page draws each axis's cone from the filter's ``attitude_cov`` (2σ). This runs robust
with its defaults over each trial, reads the covariance every 0.5 s as the page would, and
counts how often the true error is inside it:

- heading: the error about the vertical inside ±2σ of ``P[2, 2]`` (a Gaussian: 95 %);
- tilt: the error's horizontal part inside the 95 % circle of a 2-D Gaussian with the mean
  of ``P[0, 0]`` and ``P[1, 1]`` (radius 2.45σ).

It prints per trial the two shares, the median σ and the RMS error (degrees), then each set's
mean. A filter whose covariance describes its error has both shares near 0.95.

``python benchmarks/coverage.py [broad] [phones]`` (both by default; a minute or two).
"""

from __future__ import annotations

import sys

import numpy as np

from evalkit import trials
from app.estimators import make_estimator
from app.quaternion import quat_conj_many, quat_mul_many

STEP_S = 0.5          # the covariance read this often (the page reads it 20 times a second)
TILT_95 = 2.45        # a 2-D Gaussian's 95 % circle, in σ


def coverage(tr: dict) -> tuple[float, float, float, float, float, float]:
    est = make_estimator("robust")
    n = len(tr["t"])
    k = max(1, int(STEP_S * tr["fs"]))
    qs, covs, rows = [], [], []
    for a in range(0, n, k):
        b = min(n, a + k)
        r = est.run(tr["t"][a:b], tr["gyr"][a:b], tr["acc"][a:b], tr["mag"][a:b])
        qs.append(r.q[-1])
        covs.append(est.attitude_cov())
        rows.append(b - 1)
    rows = np.array(rows)
    ref = tr["ref"][rows]
    m = tr["mask"][rows] & np.all(np.isfinite(ref), axis=1)
    e = quat_mul_many(np.array(qs)[m], quat_conj_many(ref[m]))
    e = e * np.where(e[:, :1] < 0.0, -1.0, 1.0)
    angle = 2.0 * np.arccos(np.clip(e[:, 0], -1.0, 1.0))
    axis = e[:, 1:] / np.maximum(np.sin(angle / 2.0), 1e-12)[:, None]
    rv = axis * angle[:, None]                     # the error as a world-frame rotation vector
    P = np.array(covs)[m]
    s_head = np.sqrt(P[:, 2, 2])
    s_tilt = np.sqrt(0.5 * (P[:, 0, 0] + P[:, 1, 1]))
    head, tilt = np.abs(rv[:, 2]), np.hypot(rv[:, 0], rv[:, 1])
    deg = np.degrees
    return (float(np.mean(head < 2.0 * s_head)), float(np.mean(tilt < TILT_95 * s_tilt)),
            float(deg(np.median(s_head))), float(deg(np.sqrt(np.mean(head ** 2)))),
            float(deg(np.median(s_tilt))), float(deg(np.sqrt(np.mean(tilt ** 2) / 2.0))))


def main(argv: list[str]) -> int:
    for which in argv or ["broad", "phones"]:
        out = []
        print(f"{which}: trial, heading inside 2σ, tilt inside its 95 % circle | heading σ "
              "(median) and RMS error | tilt σ per axis (median) and RMS error per axis, degrees")
        for tr in trials(which):
            c = coverage(tr)
            out.append(c)
            print(f"  {tr['name']:<44} {c[0]:.2f} {c[1]:.2f} | {c[2]:.2f} {c[3]:.2f} | {c[4]:.2f} {c[5]:.2f}")
        a = np.mean(np.array(out), axis=0)
        print(f"{which} mean of {len(out)}: heading inside 2σ {a[0]:.3f}, tilt inside 95 % {a[1]:.3f}; "
              f"tilt σ {a[4]:.2f}° against an RMS error of {a[5]:.2f}° per axis")
    return 0


if __name__ == "__main__":
    sys.exit(main(sys.argv[1:]))
