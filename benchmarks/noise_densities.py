"""What the sensors' noise measures against the optical truth: the physics behind ``gyr_noise``,
``tilt_noise``, ``heading_noise`` and ``mag_norm_gate_rel``.

The filter models each sensor's error at the time scale of its correction (seconds to tens of
seconds) as a white noise density. This measures those densities on the trials with optical
truth, without the filter and without its error metric:

- **gyroscope** (``gyr_noise``, rad/√s): the gyroscope, its bias removed (the mean of the
  trial's still seconds, as ``gyro_scale.py``), is integrated over a window of T seconds from
  the truth's attitude at its start; the rotation from that to the truth's attitude at its end,
  in the world frame, is the attitude's random walk over T. Its RMS per axis over √T is the
  density: the vertical axis (heading) and the two horizontal ones (tilt) apart.
- **accelerometer** (``tilt_noise``, rad·√s): the specific force turned into the world by the
  truth, its direction against the vertical (two small angles), averaged over T seconds; the
  RMS of that mean times √T is the density of the gravity direction at time scale T.
- **magnetometer** (``heading_noise``, rad·√s): the field turned into the world by the truth
  (``mag_delay`` removed as the filter does), its heading less the trial's mean heading,
  averaged over T; RMS × √T.
- **the field's strength** (``mag_norm_gate_rel``): the strength low-passed as the strength gate
  sees it (``mag_norm_dip_tau``), its relative deviation from the trial's median over the
  moving part; the 95th and 99th percentiles per trial (median over the group's trials, and the
  largest): how far an undisturbed field swings, which a strength gate must let through.

For a white noise the figures are the same at every T. Below the truth's own noise (a short T)
they are too high; a bias (the gyroscope's left over, a field bent in one place) makes them grow
with T. BROAD's trials are split by kind (``evalkit.KINDS``); a "steady field" is one of the
kinds without a magnet. The phones' truth is synchronised less tightly than BROAD's: their
gyroscope figures do not grow with T (the truth's timing error dominates) and are printed for
completeness only; their biases (the gyroscope less the truth's rate, averaged over the trial)
are printed per group as the population a start-up σ (``bias_init``) stands for. The RMS (what a Kalman filter's variance is) is heavy-tailed here; the
median-based figure (the median of the squares over 0.455, a Gaussian's ratio) shows the bulk.

Usage: ``python benchmarks/noise_densities.py`` (reads ``../shared/data``; skips what is absent).
"""

from __future__ import annotations

import sys
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))
sys.path.insert(0, str(ROOT / "benchmarks"))

from accuracy_phones import BROAD, PHONES, load_broad, load_phones  # noqa: E402
from app.estimators.robust import RobustParams  # noqa: E402
from app.estimators.robust.state import lp_coef  # noqa: E402
from app.quaternion import (Q_many, integrate_many, quat_conj_many, quat_mul_many,  # noqa: E402
                            rotvec_from_quat_many, wrap_angle)
from evalkit import KINDS, broad_kind  # noqa: E402
from gyro_scale import rates  # noqa: E402

SCALES = (2.0, 5.0, 10.0, 20.0)      # s: the time scales of the filter's corrections
STEP_S = 0.25                       # s between the starts of two gyroscope windows
CHI2_MEDIAN = 0.455                 # median of a squared standard normal


def _valid(tr: dict) -> np.ndarray:
    return np.all(np.isfinite(tr["ref"]), axis=1)


def _bias(tr: dict) -> np.ndarray:
    """The gyroscope's bias: the mean of its still seconds (BROAD marks them), else the mean of
    the gyroscope less the truth's rate (``gyro_scale.rates``)."""
    still = ~tr["mask"]
    if tr["set"] == "broad" and still.sum() > tr["fs"]:
        return np.nanmean(tr["gyr"][still], axis=0)
    w_true, w_gyr = rates(tr, moving_only=False)
    return np.mean(w_gyr - w_true, axis=0)


def gyro_alone(tr: dict) -> tuple[np.ndarray, np.ndarray]:
    """The gyroscope, its bias (``_bias``) removed and NaN as 0 (rad/s), and the attitude it
    alone integrates from the identity, sample by sample (``q_k = q_k-1 ⊗ exp(ω dt)``)."""
    t = tr["t"]
    g = np.nan_to_num(tr["gyr"] - _bias(tr))
    dt = np.diff(t, prepend=t[0])
    return g, integrate_many((1.0, 0.0, 0.0, 0.0), g * dt[:, None])


def window_walk(ref: np.ndarray, qg: np.ndarray, i0: np.ndarray, i1: np.ndarray) -> np.ndarray:
    """World-frame rotation vectors (rad) from the gyroscope's attitude to the truth's at the end
    of each window ``i0 → i1``, the gyroscope started from the truth's attitude at ``i0``: a
    gyroscope that over-turns by δ gives +δ."""
    turn = quat_mul_many(quat_conj_many(qg[i0]), qg[i1])                  # body frame, over the window
    err = quat_mul_many(quat_mul_many(quat_conj_many(ref[i1]), ref[i0]), turn)
    err_w = quat_mul_many(quat_mul_many(ref[i1], err), quat_conj_many(ref[i1]))
    return rotvec_from_quat_many(err_w)


def gyro_walk(tr: dict, T: float) -> np.ndarray:
    """World-frame rotation vectors (rad) from the gyroscope's attitude to the truth's after T s."""
    _, qg = gyro_alone(tr)
    n = int(round(T * tr["fs"]))
    i0 = np.arange(0, len(tr["t"]) - n, max(1, int(round(STEP_S * tr["fs"]))))
    i1 = i0 + n
    ok = _valid(tr)
    i0, i1 = i0[ok[i0] & ok[i1]], i1[ok[i0] & ok[i1]]
    return window_walk(tr["ref"], qg, i0, i1)


def _window_means(x: np.ndarray, ok: np.ndarray, n: int) -> np.ndarray:
    nb = len(x) // n
    good = ok[: nb * n].reshape(nb, n).all(axis=1)
    return x[: nb * n].reshape(nb, n, -1).mean(axis=1)[good]


def tilt_and_heading(tr: dict, T: float, mag_delay: float) -> tuple[np.ndarray, np.ndarray]:
    """Means over T s of the accelerometer's tilt (two angles) and the field's heading (rad)."""
    ok = _valid(tr)
    R = Q_many(np.where(ok[:, None], tr["ref"], [1.0, 0.0, 0.0, 0.0]))
    a = np.einsum("nij,nj->ni", R, tr["acc"])
    a /= np.linalg.norm(a, axis=1)[:, None]
    tilt = np.stack([a[:, 1], -a[:, 0]], axis=1)       # small angles about x and y
    mag = tr["mag"] - mag_delay * np.cross(tr["gyr"] - _bias(tr), tr["mag"])
    m = np.einsum("nij,nj->ni", R, mag)
    h = np.arctan2(m[:, 0], m[:, 1])
    h0 = np.angle(np.mean(np.exp(1j * h[ok])))
    dh = wrap_angle(h - h0)[:, None]
    n = max(1, int(round(T * tr["fs"])))
    ok = ok & np.all(np.isfinite(tr["acc"]), axis=1) & np.all(np.isfinite(tr["mag"]), axis=1)
    return _window_means(tilt, ok, n), _window_means(dh, ok, n)


def strength_swing(tr: dict, tau: float) -> tuple[float, float]:
    """95th and 99th percentiles of |strength / median - 1| over the trial's moving part, the
    strength low-passed over ``tau`` (the gate's ``mag_norm_dip_tau``)."""
    ok = tr["mask"] & np.all(np.isfinite(tr["mag"]), axis=1)
    n = np.linalg.norm(tr["mag"][ok], axis=1)
    t = tr["t"][ok]
    lp = np.empty_like(n)
    acc = n[0]
    for k in range(len(n)):        # the gate's own low-pass
        acc += lp_coef(t[k] - t[k - 1] if k else 0.0, tau) * (n[k] - acc)
        lp[k] = acc
    d = np.abs(lp / np.median(n) - 1.0)
    return float(np.percentile(d, 95)), float(np.percentile(d, 99))


def density(x: np.ndarray, T: float, scale_by_root: bool) -> tuple[float, float]:
    """(RMS-based, median-based) density of samples x at time scale T."""
    if x.size == 0:
        return np.nan, np.nan
    ms, med = float(np.mean(x ** 2)), float(np.median(x ** 2) / CHI2_MEDIAN)
    if scale_by_root:       # a random walk: σ(T) = d √T
        return np.sqrt(ms / T), np.sqrt(med / T)
    return np.sqrt(ms * T), np.sqrt(med * T)   # an averaged white noise: σ(T) = d / √T


def _cells(vals) -> str:
    return "  ".join(f"{a:.4f} ({b:.4f})" for a, b in vals)


def report(label: str, trials: list[dict], groups: dict[str, list[int]], mag_delay: float,
           tau: float) -> None:
    head = "  ".join(f"T={T:>4.0f} s        " for T in SCALES)
    print(f"{label}: RMS-based density (median-based)\n  {'':<34}{head}")
    for name, idx in groups.items():
        if not idx:
            continue
        sel = [trials[i] for i in idx]
        walks = {T: np.concatenate([gyro_walk(tr, T) for tr in sel]) for T in SCALES}
        th = {T: [tilt_and_heading(tr, T, mag_delay) for tr in sel] for T in SCALES}
        bias = np.array([_bias(tr) for tr in sel])
        print(f"  {name} ({len(sel)} trials; gyroscope bias {np.sqrt(np.mean(bias ** 2)):.4f} rad/s RMS "
              f"over trials and axes, largest {np.abs(bias).max():.4f})")
        print(f"    {'gyroscope, heading [rad/√s]':<32}"
              + _cells(density(walks[T][:, 2], T, True) for T in SCALES))
        print(f"    {'gyroscope, tilt [rad/√s]':<32}"
              + _cells(density(walks[T][:, :2].ravel(), T, True) for T in SCALES))
        print(f"    {'accelerometer, tilt [rad·√s]':<32}"
              + _cells(density(np.concatenate([a for a, _ in th[T]]).ravel(), T, False) for T in SCALES))
        print(f"    {'field, heading [rad·√s]':<32}"
              + _cells(density(np.concatenate([h for _, h in th[T]]).ravel(), T, False) for T in SCALES))
        sw = np.array([strength_swing(tr, tau) for tr in sel])
        print(f"    {'field, strength [rel.]':<32}95 %: {np.median(sw[:, 0]):.3f}  99 %: "
              f"{np.median(sw[:, 1]):.3f} (median over trials; largest 99 %: {sw[:, 1].max():.3f})")
    print()


def main() -> int:
    p = RobustParams()
    print("The filter's defaults: gyr_noise %.4f rad/√s, tilt_noise %.4f rad·√s, heading_noise %.4f rad·√s "
          "(in a steady field; the field's measured wander and deviation add to it), mag_delay %.4f s, "
          "mag_norm_gate_rel %.2f\n" % (p.gyr_noise, p.tilt_noise, p.heading_noise, p.mag_delay, p.mag_norm_gate_rel))
    found = False
    if (BROAD / "trials.json").is_file():
        found = True
        trials = load_broad()
        kinds = [broad_kind(tr) for tr in trials]
        steady = [i for i, k in enumerate(kinds) if "magnet" not in k]
        groups = {"steady field (no magnet)": steady}
        groups.update({k: [i for i, kk in enumerate(kinds) if kk == k] for k in KINDS})
        report("BROAD (research IMU, optical truth)", trials, groups, p.mag_delay, p.mag_norm_dip_tau)
    if (PHONES / "trials.json").is_file():
        found = True
        trials = load_phones()
        groups = {d: [i for i, tr in enumerate(trials) if tr["dist"] == d] for d in ("NoDist", "Dist")}
        report("phones-tyrex (motion capture; its timing limits the gyroscope figures)", trials, groups,
               p.mag_delay, p.mag_norm_dip_tau)
    if not found:
        print("no data with optical truth found under ../shared/data: nothing to measure.")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
