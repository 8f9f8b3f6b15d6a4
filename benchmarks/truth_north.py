"""Which north BROAD's truth points at, and how much of the sensitivity of the heading's
parameters on BROAD is that north.

BROAD's ground truth "already points at magnetic north" (its README): its heading was aligned
with the magnetometer. This script shows where that north is, trial by trial, and what it does
to the sensitivity table of ``ablation.py``:

1. **The field's azimuth in the truth's frame** (the field turned into the world by the truth,
   ``atan2(east, north)``, median), at the rest before the movement and during the movement that
   is scored, with the field's strength in both. A field that is the same in both places has the
   same azimuth; where the IMU is carried from its rest into another field, the two differ.
2. **robust's and VQF's total RMSE** with BROAD's metric, and with each trial's constant heading
   offset removed (the truth turned about the vertical by the mean signed heading error of that
   estimate on that trial: the error of the heading's changes, not of its north).
3. **The ×0.5 / ×2 sensitivity** of the defaults ``ablation.py`` names on BROAD (and of
   ``heading_noise``, the other side of the heading's time constant) under both metrics, with
   ablation.py's rule (both sides cost more than ``SHARP`` of the defaults' mean).

Data: BROAD (Laidig, Caruso, Cereatti, Seel, Data 6(7):72, 2021, CC-BY-4.0), read from
``../shared/data/broad`` (skipped when absent).

Usage: ``python benchmarks/truth_north.py`` (seconds on 2 cores once the filters are compiled).
"""

from __future__ import annotations

import sys
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))
sys.path.insert(0, str(ROOT / "benchmarks"))

from ablation import SHARP  # noqa: E402
from accuracy_phones import BROAD  # noqa: E402
from app.quaternion import IDENTITY, error_angles, quat_mul_many, rotate_many  # noqa: E402
from evalkit import estimate, heading_error, pool, trials  # noqa: E402

DEG = 180.0 / np.pi
REST_S = 10.0       # s of the rest before the movement whose field is "the rest's"
PARAMS = ("gyr_noise", "mag_dev_weight", "heading_noise")


def field_north(trial: dict) -> tuple[float, float, float, float]:
    """(azimuth at rest, azimuth in motion, strength at rest, strength in motion): degrees
    east of the truth's north, µT; medians."""
    q, mag, moving = trial["ref"], trial["mag"], trial["mask"]
    known = np.all(np.isfinite(q), 1) & np.all(np.isfinite(mag), 1)
    first_move = int(np.argmax(moving)) if moving.any() else len(q)
    rest = known & (np.arange(len(q)) < first_move) & \
        (np.arange(len(q)) >= first_move - int(REST_S * trial["fs"]))
    move = known & moving
    mw = rotate_many(np.where(known[:, None], q, IDENTITY), mag)
    az = np.arctan2(mw[:, 0], mw[:, 1]) * DEG
    n = np.linalg.norm(mag, axis=1)
    return (float(np.median(az[rest])), float(np.median(az[move])),
            float(np.median(n[rest])), float(np.median(n[move])))


def both_errors(q: np.ndarray, trial: dict) -> tuple[float, float, float]:
    """Total RMSE (degrees) with BROAD's metric, with the trial's constant heading offset
    removed, and that offset (the mean signed heading error, degrees: positive when the
    estimate's north is turned as a field of positive azimuth would turn it)."""
    ref = trial["ref"]
    m = trial["mask"] & np.all(np.isfinite(ref), 1) & np.all(np.isfinite(q), 1)
    q, ref = q[m], ref[m]
    d = float(np.angle(np.mean(np.exp(1j * heading_error(q, ref)))))    # its circular mean
    rz = np.tile([np.cos(d / 2), 0.0, 0.0, np.sin(d / 2)], (len(ref), 1))
    rmse = lambda x: float(np.sqrt(np.mean(x ** 2)) * DEG)  # noqa: E731
    return (rmse(error_angles(q, ref)[0]), rmse(error_angles(q, quat_mul_many(rz, ref))[0]),
            d * DEG)


def _run(args) -> tuple[float, float, float]:
    i, method, params = args
    tr = trials("broad")[i]
    return both_errors(estimate(tr, params, method), tr)


def run(method: str, params: dict | None = None) -> np.ndarray:
    """(n, 3): per trial, BROAD's total RMSE, the offset-free one, and the offset."""
    tasks = [(i, method, params) for i in range(len(trials("broad")))]
    return np.array(list(pool().map(_run, tasks, chunksize=1)))


def main() -> int:
    if not BROAD.is_dir():
        print(f"skipped: {BROAD} is absent")
        return 0
    from app.estimators.robust import RobustParams
    defaults = RobustParams()
    rob, vqf = run("robust"), run("VQF")
    print("1. The field's azimuth in the truth's frame (° east of its north) and strength (µT),")
    print(f"   the last {REST_S:.0f} s of the rest before the movement, and during the movement\n")
    print(f"{'trial':<46}{'rest':>7}{'moving':>8}{'Δ':>7}{'|m| rest':>10}{'moving':>8}"
          f"   robust: BROAD / offset-free")
    for tr, (a, b, _) in zip(trials("broad"), rob):
        ar, am, nr, nm = field_north(tr)
        print(f"{tr['name']:<46}{ar:+7.1f}{am:+8.1f}{am - ar:+7.1f}{nr:10.1f}{nm:8.1f}   {a:6.2f} / {b:.2f}")
    print("\n2. Total RMSE, mean of the 17 trials: BROAD's metric / each trial's constant heading "
          "offset removed")
    print(f"   robust {rob[:, 0].mean():.3f} / {rob[:, 1].mean():.3f}   "
          f"VQF {vqf[:, 0].mean():.3f} / {vqf[:, 1].mean():.3f}")
    print(f"\n3. ×0.5 / ×2, change of the mean; at a sharp optimum when both sides cost more than "
          f"{SHARP:.0%} of the defaults' mean (BROAD's metric: {SHARP * rob[:, 0].mean():.3f}, "
          f"offset-free: {SHARP * rob[:, 1].mean():.3f})")
    per_trial = {}
    for name in PARAMS:
        v = getattr(defaults, name)
        lo, hi = run("robust", {name: v * 0.5}), run("robust", {name: v * 2.0})
        per_trial[name] = lo, hi
        cells = []
        for col, label in ((0, "BROAD"), (1, "offset-free")):
            a, b = lo[:, col].mean() - rob[:, col].mean(), hi[:, col].mean() - rob[:, col].mean()
            sharp = min(a, b) > SHARP * rob[:, col].mean()
            cells.append(f"{label} {a:+.3f} / {b:+.3f}{' (sharp)' if sharp else ''}")
        print(f"   {name:<16} {v:<9g} " + "   ".join(cells))
    print("\n4. Per trial: the change of BROAD's total RMSE at ×0.5 / ×2, and the constant heading offset "
          "(° ,\n   the sign of a field's azimuth) with the defaults, ×0.5 and ×2. An offset that moves "
          "towards the\n   moving field's azimuth follows that field; one that moves away from both "
          "fields' azimuths is a lag\n   behind the gyroscope's drift (a steady drift d, corrected "
          "with a time constant τ, leaves d·τ)")
    for name in PARAMS[:2]:
        lo, hi = per_trial[name]
        print(f"\n   {name}{'':<33}{'rest':>6}{'moving':>7}   {'cost ×0.5':>9}{'×2':>7}   "
              f"{'offset':>6}{'×0.5':>7}{'×2':>7}")
        for i, tr in enumerate(trials("broad")):
            ar, am, _, _ = field_north(tr)
            print(f"   {tr['name']:<46}{ar:+6.1f}{am:+7.1f}   {lo[i, 0] - rob[i, 0]:+9.2f}"
                  f"{hi[i, 0] - rob[i, 0]:+7.2f}   {rob[i, 2]:+6.2f}{lo[i, 2]:+7.2f}{hi[i, 2]:+7.2f}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
