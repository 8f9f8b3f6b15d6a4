"""BROAD's gyroscope reads a little low, and that is the slow side of the heading's two named
defaults (``gyr_noise`` and ``mag_dev_weight`` in ``ablation.py``'s sharp-optimum list).

A diagnosis on the shared trials, not a default: the scale is fitted against the optical truth
(1, 2), and from the sensors alone at BROAD's rests (3, the product's calibration), which the
phones' trials do not have.

1. **The scale fit.** The gyroscope, its bias from the rest before the movement removed, is
   integrated from the truth's attitude over windows of ``WINDOW_S`` (a quarter window apart);
   the rotation from that to the truth's attitude at the window's end, in the world frame, is
   the window's error. It is fitted by least squares, over all 17 trials at once, with a
   constant bias error per trial (three per trial) and one scale error per sensor axis shared by
   all trials (one IMU). Printed: the three scale errors, and per trial the error's RMS with the
   bias errors alone and with the scales too.
2. **robust with the gyroscope rescaled** by that fit (each axis divided by 1 + its scale
   error): BROAD's mean total RMSE, and the ×0.5 / ×2 sensitivity of the two named defaults,
   beside the same with the gyroscope as recorded.
3. **The same scale from the sensors alone**, as ``orientlab gyro-scale`` measures it
   (:mod:`app.toolkit.gyro_scale`: the tilt at each rest against the gyroscope integrated from
   the rest before; a bias error per trial, a scale error per axis; no truth, no magnetometer).
   Each trial is then run with robust's ``gyr_scale`` set to the scale fitted on the *other*
   16 (leave one out), and the sensitivity of 2 is printed for it too.
4. **The same, per trial, against robust's own estimate** (what a filter could fit online,
   without rests): one scale for all axes and a bias error, fitted over the trial's windows,
   then the trial run with it.
5. **The same, per trial, against the field's heading** (the other online evidence: the
   heading's drift against the net turn about the vertical). The reference is robust's tilt
   with the heading the raw magnetometer gives it (the field's azimuth in robust's world held
   at its trial mean), so robust's own heading is out of it. Only the windows' error about the
   vertical is fitted, beside the same fit against the truth.

Data: BROAD (Laidig, Caruso, Cereatti, Seel, Data 6(7):72, 2021, CC-BY-4.0), read from
``../shared/data/broad`` (skipped when absent).

Usage: ``python benchmarks/scale_lag.py`` (seconds on 2 cores once the filters are compiled).
"""

from __future__ import annotations

import sys
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))
sys.path.insert(0, str(ROOT / "benchmarks"))

from ablation import SHARP  # noqa: E402
from accuracy_phones import BROAD, errors  # noqa: E402
from app.quaternion import Q_many, quat_from_rotvec_many, quat_mul_many, rotate_many  # noqa: E402
from app.toolkit.gyro_scale import Recording, fit, format_report  # noqa: E402
from evalkit import estimate, pool, trials  # noqa: E402
from noise_densities import gyro_alone, window_walk  # noqa: E402

WINDOW_S = 10.0     # s: long against the truth's timing, short against a trial
PARAMS = ("gyr_noise", "mag_dev_weight")
DEG = 180.0 / np.pi


def windows(tr: dict, ref: np.ndarray | None = None) -> tuple[np.ndarray, np.ndarray]:
    """Per window: the world-frame error (3,) and its regressors (3, 6): the world-frame
    integrals of a unit bias error about each sensor axis, and of a unit scale error of each.
    Against the truth, or against ``ref`` (an estimate's attitude, row by row)."""
    t = tr["t"]
    ref = tr["ref"] if ref is None else ref
    g, qg = gyro_alone(tr)
    dt = np.diff(t, prepend=t[0])
    known = np.all(np.isfinite(ref), axis=1)
    R = Q_many(np.where(known[:, None], ref, [1.0, 0.0, 0.0, 0.0]))
    x = np.concatenate([R * dt[:, None, None], R * (g * dt[:, None])[:, None, :]], axis=2)
    csum = np.concatenate([np.zeros((1, 3, 6)), np.cumsum(x, axis=0)])
    n = int(round(WINDOW_S * tr["fs"]))
    i0 = np.arange(0, len(t) - n, max(1, n // 4))
    i1 = i0 + n
    bad = np.concatenate([[0], np.cumsum(~(known & tr["mask"]))])
    good = bad[i1 + 1] == bad[i0]
    i0, i1 = i0[good], i1[good]
    return window_walk(ref, qg, i0, i1), csum[i1 + 1] - csum[i0 + 1]


def fit_scale(all_windows) -> tuple[np.ndarray, list[tuple[float, float, float]]]:
    """The shared per-axis scale errors (the gyroscope reads (1 + s) × the turn), and per trial
    the windows' RMS error (degrees): as measured, with bias errors fitted, with the scales too."""
    nt = len(all_windows)
    ncol = 3 * nt + 3
    rows, ys = [], []
    for k, (ew, x) in enumerate(all_windows):
        a = np.zeros((len(ew), 3, ncol))
        a[:, :, 3 * k:3 * k + 3] = x[:, :, :3]
        a[:, :, 3 * nt:] = x[:, :, 3:]
        rows.append(a.reshape(-1, ncol))
        ys.append(ew.reshape(-1))
    A, Y = np.concatenate(rows), np.concatenate(ys)
    c_all = np.linalg.lstsq(A, Y, rcond=None)[0]
    c_bias = np.linalg.lstsq(A[:, :3 * nt], Y, rcond=None)[0]
    out, off = [], 0
    for ew, _ in all_windows:
        m = slice(off, off + ew.size)
        off += ew.size
        rms = lambda r: float(np.sqrt(np.mean(r ** 2)) * DEG) if r.size else np.nan  # noqa: E731
        out.append((rms(Y[m]), rms(Y[m] - A[m, :3 * nt] @ c_bias), rms(Y[m] - A[m] @ c_all)))
    # a gyroscope reading (1 + s) × the turn over-turns by s × it (window_walk's sign): the
    # scale regressor's coefficient
    return c_all[3 * nt:], out


def calibrations(leave_out: int | None) -> np.ndarray:
    """``orientlab gyro-scale`` over BROAD's trials, but ``leave_out``: the scale errors (3,)."""
    return fit([Recording(tr["name"], tr["t"], tr["gyr"], tr["acc"])
                for i, tr in enumerate(trials("broad")) if i != leave_out]).scale


def own_estimate_fit(i: int) -> tuple[float, float]:
    """Trial ``i``'s isotropic scale error (one for all three axes) and its σ from the residual,
    fitted with a bias error over the windows against robust's own estimate, as a filter could
    online: no truth, no rests."""
    tr = trials("broad")[i]
    e, x = windows(tr, estimate(tr))
    a = np.concatenate([x[:, :, :3], x[:, :, 3:].sum(axis=2, keepdims=True)], axis=2).reshape(-1, 4)
    y = e.reshape(-1)
    c = np.linalg.lstsq(a, y, rcond=None)[0]
    r = y - a @ c
    cov = (r @ r) / max(1, len(y) - 4) * np.linalg.pinv(a.T @ a)
    return float(c[3]), float(np.sqrt(cov[3, 3]))


def field_fit(i: int) -> tuple[float, float, float, float]:
    """Trial ``i``'s isotropic scale error and its σ from the windows' error about the vertical
    (a bias error fitted too): against the truth, then against the field's heading on robust's
    tilt (module doc, 5)."""
    tr = trials("broad")[i]
    q = estimate(tr)
    mw = rotate_many(q, np.nan_to_num(tr["mag"]))
    az = np.arctan2(mw[:, 0], mw[:, 1])          # the field's azimuth, clockwise from north
    # a heading error e (counter-clockwise) shows the field at az - e: turn it back by az - mean
    back = np.outer(az - np.angle(np.mean(np.exp(1j * az))), [0.0, 0.0, 1.0])
    qf = quat_mul_many(quat_from_rotvec_many(back), q)
    out = []
    for ref in (None, qf):
        e, x = windows(tr, ref)
        a = np.concatenate([x[:, 2, :3], x[:, 2, 3:].sum(axis=1, keepdims=True)], axis=1)
        c = np.linalg.lstsq(a, e[:, 2], rcond=None)[0]
        r = e[:, 2] - a @ c
        cov = (r @ r) / max(1, len(r) - 4) * np.linalg.pinv(a.T @ a)
        out += [float(c[3]), float(np.sqrt(cov[3, 3]))]
    return tuple(out)


def _run(args) -> tuple[float, float, float]:
    i, params, scale, how = args
    tr = trials("broad")[i]
    if how == "param":           # robust's gyr_scale, as a calibration sets it
        return errors(estimate(tr, {**(params or {}), "gyr_scale": [float(v) for v in scale]}), tr)
    if how == "vqf":             # VQF with the gyroscope rescaled alike
        return errors(estimate(tr, None, "VQF", gyr=tr["gyr"] / (1.0 + np.asarray(scale))), tr)
    return errors(estimate(tr, params, gyr=tr["gyr"] / (1.0 + np.asarray(scale))), tr)


def means(params: dict | None, scale, how: str = "rescale") -> np.ndarray:
    """Mean (total, heading, inclination) RMSE over BROAD's trials, degrees; ``scale`` one
    (3,) for all trials or one per trial (n, 3); ``how``: the recorded gyroscope rescaled, or
    robust's ``gyr_scale`` parameter ("param")."""
    n = len(trials("broad"))
    per = np.broadcast_to(np.asarray(scale, dtype=float), (n, 3))
    tasks = [(i, params, per[i], how) for i in range(n)]
    return np.mean(np.array(list(pool().map(_run, tasks, chunksize=1))), axis=0)


def sensitivity(label: str, scale, defaults, how: str = "rescale") -> None:
    """Print the mean with ``scale`` and the ×0.5 / ×2 change of each of ``PARAMS``."""
    m = means(None, scale, how)
    base = m[0]
    cells = []
    for name in PARAMS:
        v = getattr(defaults, name)
        lo = means({name: v * 0.5}, scale, how)[0] - base
        hi = means({name: v * 2.0}, scale, how)[0] - base
        sharp = min(lo, hi) > SHARP * base
        cells.append(f"{name} {lo:+.3f} / {hi:+.3f}{' (sharp)' if sharp else ''}")
    print(f"   {label:<40} {base:.3f} ({m[1]:.2f} / {m[2]:.3f})   " + "   ".join(cells))


def main() -> int:
    if not BROAD.is_dir():
        print(f"skipped: {BROAD} is absent")
        return 0
    from app.estimators.robust import RobustParams
    defaults = RobustParams()
    tr_all = trials("broad")
    scale, per_trial = fit_scale([windows(tr) for tr in tr_all])
    print(f"1. BROAD's gyroscope, one scale error per axis over the 17 trials ({WINDOW_S:.0f} s windows): "
          + "  ".join(f"{ax} {s * 100:+.3f} %" for ax, s in zip("xyz", scale)))
    print(f"\n   {'trial':<46}windows' RMS error (°): as measured / bias errors fitted / and the scales")
    for tr, (a, b, c) in zip(tr_all, per_trial):
        print(f"   {tr['name']:<46}{a:6.2f} / {b:5.2f} / {c:5.2f}")
    print(f"\n2. robust on BROAD (mean total RMSE, heading / inclination, °), and ×0.5 / ×2 of the named "
          f"defaults (a sharp optimum: both sides cost more than {SHARP:.0%} of the mean)")
    sensitivity("gyroscope as recorded", np.zeros(3), defaults)
    sensitivity("gyroscope rescaled by the truth's fit", scale, defaults)

    print("\n3. From the sensors alone (orientlab gyro-scale over the 17 trials):")
    recs = [Recording(tr["name"], tr["t"], tr["gyr"], tr["acc"]) for tr in tr_all]
    print("   " + format_report(fit(recs)).rstrip("\n").replace("\n", "\n   "))
    loo = np.array(list(pool().map(calibrations, range(len(tr_all)), chunksize=1)))
    print("   fitted on the other 16 trials, per axis over the 17 held-out trials: "
          + "  ".join(f"{ax} {lo * 100:+.3f} to {hi * 100:+.3f} %"
                      for ax, lo, hi in zip("xyz", loo.min(0), loo.max(0))))
    sensitivity("gyr_scale from the sensors, leave one out", loo, defaults, how="param")
    v0, v1 = means(None, np.zeros(3), "vqf"), means(None, loo, "vqf")
    print(f"   VQF, gyroscope as recorded {v0[0]:.3f} ({v0[1]:.2f} / {v0[2]:.3f}), rescaled alike "
          f"{v1[0]:.3f} ({v1[1]:.2f} / {v1[2]:.3f})")

    fits = list(pool().map(own_estimate_fit, range(len(tr_all)), chunksize=1))
    per = np.array([[k, k, k] for k, _ in fits])
    tasks = lambda sc: [(i, None, sc[i], "rescale") for i in range(len(tr_all))]  # noqa: E731
    before = np.array(list(pool().map(_run, tasks(np.zeros((len(tr_all), 3))), chunksize=1)))
    after = np.array(list(pool().map(_run, tasks(per), chunksize=1)))
    print(f"\n4. Per trial, against robust's own estimate ({WINDOW_S:.0f} s windows, a bias error and one scale "
          f"for all axes): the scale ± its σ from the residual, and the trial's total RMSE (°) as recorded / "
          f"rescaled by it")
    for tr, (k, sd), b, a in zip(tr_all, fits, before, after):
        print(f"   {tr['name']:<46}{k * 100:+.3f} ± {sd * 100:.3f} %   {b[0]:5.2f} / {a[0]:5.2f}")
    print(f"   mean: {before[:, 0].mean():.3f} / {after[:, 0].mean():.3f}")

    print(f"\n5. Per trial, about the vertical only ({WINDOW_S:.0f} s windows, a bias error and one scale for "
          f"all axes): the scale ± its σ against the truth, and against the field's heading on robust's tilt")
    for tr, (kt, st, kf, sf) in zip(tr_all, pool().map(field_fit, range(len(tr_all)), chunksize=1)):
        print(f"   {tr['name']:<46}{kt * 100:+.3f} ± {st * 100:.3f} %   {kf * 100:+.3f} ± {sf * 100:.3f} %")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
