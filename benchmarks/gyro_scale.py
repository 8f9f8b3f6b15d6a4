"""How far off a real gyroscope's scale factor is: the physics behind ``gyr_scale_noise``.

For every trial with optical truth (BROAD's research IMU, the phones of phones-tyrex), the
body-frame turn rate is taken from the truth (the rotation between two truth samples
``DIFF_S`` apart, over that time) and compared with the gyroscope averaged over the same
span, its bias (the mean of the first still seconds, or 0) removed. Per sensor axis with
enough rotation (RMS rate above ``MIN_RATE``), the least-squares ratio gyroscope/truth - 1
is the scale-factor error. A timing offset between gyroscope and truth, or a smoothed
truth, lowers the ratio: the phones' truth is synchronised less tightly than BROAD's, so
their negative errors are upper bounds, and while running their gyroscopes also saturate.
Prints the error per trial and axis, and the median of the magnitudes per data set.

Usage: ``python benchmarks/gyro_scale.py`` (reads ``../shared/data``; skips what is absent).
"""

from __future__ import annotations

import sys
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))
sys.path.insert(0, str(ROOT / "benchmarks"))

from accuracy_phones import BROAD, PHONES, load_broad, load_phones  # noqa: E402
from app.quaternion import quat_conj_many, quat_mul_many, rotvec_from_quat_many  # noqa: E402

DIFF_S = 0.05        # s between the two truth samples of a rate
MIN_RATE = 0.5       # rad/s RMS about an axis before its scale is judged


def rates(trial: dict, moving_only: bool = True) -> tuple[np.ndarray, np.ndarray]:
    """The body-frame turn rate from the truth (the rotation between two truth samples
    ``DIFF_S`` apart, over that time) and the gyroscope averaged over the same spans (rad/s,
    bias not removed), where both are known (and, with ``moving_only``, the trial moves)."""
    t, q, g = trial["t"], trial["ref"], trial["gyr"]
    d = max(1, int(round(DIFF_S * trial["fs"])))
    ok = np.all(np.isfinite(q[:-d]), 1) & np.all(np.isfinite(q[d:]), 1) & np.all(np.isfinite(g[:-d]), 1)
    if moving_only:
        ok &= trial["mask"][:-d]
    dq = quat_mul_many(quat_conj_many(q[:-d][ok]), q[d:][ok])        # q_k⁻¹ ⊗ q_k+d
    span = t[d:][ok] - t[:-d][ok]
    w_true = rotvec_from_quat_many(dq) / span[:, None]
    # the gyroscope averaged over the same span (samples k+1 .. k+d integrate it)
    csum = np.vstack([np.zeros(3), np.cumsum(np.nan_to_num(g), axis=0)])
    idx = np.nonzero(ok)[0]
    return w_true, (csum[idx + d + 1] - csum[idx + 1]) / d


def scale_errors(trial: dict) -> list[tuple[int, float, float]]:
    """(axis, scale error, RMS rate) for each axis that turned enough."""
    w_true, w_gyr = rates(trial)
    if len(w_true) < 100:
        return []
    g = trial["gyr"]
    still = ~trial["mask"]
    bias = np.nanmean(g[still[: len(g)]], axis=0) if still.sum() > trial["fs"] else np.zeros(3)
    w_gyr = w_gyr - bias
    out = []
    for ax in range(3):
        rms = float(np.sqrt(np.mean(w_true[:, ax] ** 2)))
        if rms < MIN_RATE:
            continue
        s = float(w_gyr[:, ax] @ w_true[:, ax] / (w_true[:, ax] @ w_true[:, ax]))
        out.append((ax, s - 1.0, rms))
    return out


def main() -> int:
    sets = []
    if (BROAD / "trials.json").is_file():
        sets.append(("BROAD (research IMU)", load_broad()))
    if (PHONES / "trials.json").is_file():
        sets.append(("phones-tyrex", load_phones()))
    if not sets:
        print("no data with optical truth found under ../shared/data: nothing to measure.")
        return 0
    print(f"gyroscope scale-factor error against the optical truth (axes turning > {MIN_RATE} rad/s RMS)\n")
    for label, trials in sets:
        mags = []
        print(label)
        for tr in trials:
            errs = scale_errors(tr)
            if errs:
                mags += [abs(e) for _, e, _ in errs]
                cells = "  ".join(f"{'xyz'[ax]} {100 * e:+5.2f} % ({rms:4.1f} rad/s)" for ax, e, rms in errs)
                print(f"  {tr['name'][:44]:<44} {cells}")
        if mags:
            print(f"  median |error| {100 * np.median(mags):.2f} %, 90th percentile "
                  f"{100 * np.percentile(mags, 90):.2f} %, over {len(mags)} trial axes\n")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
