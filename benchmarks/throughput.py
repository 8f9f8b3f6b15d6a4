"""Throughput of every estimator in batch (samples/s on one core), beside VQF.

Runs each estimator's ``run()`` over the same recording (a BROAD trial when
``../shared/data/broad`` is there, else a generated 285 Hz recording of the same
length), best of several repeats after a warm-up (so JIT compilation is not
counted). VQF's compiled core (``vqf.VQF.updateBatch``) runs the same data, and the robust
filter's own code once more uncompiled (``NUMBA_DISABLE_JIT=1``), to show what numba buys.
Usage: ``python benchmarks/throughput.py [--repeat N]``.
"""

from __future__ import annotations

import argparse
import sys
import time
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))
from app.estimators import NAMES, make_estimator  # noqa: E402

BROAD = ROOT.parent / "shared" / "data" / "broad" / "21_undisturbed_fast_combined.npz"


def recording():
    if BROAD.is_file():
        d = np.load(BROAD)
        fs = float(d["fs"])
        return (np.arange(len(d["gyr"])) / fs, d["gyr"], d["acc"], d["mag"], fs, BROAD.name)
    rng = np.random.default_rng(0)
    n, fs = 40_000, 285.7
    t = np.arange(n) / fs
    gyr = 0.5 * np.sin(np.outer(t, [0.3, 0.5, 0.7])) + 0.01 * rng.standard_normal((n, 3))
    acc = np.array([0, 0, 9.81]) + 0.1 * rng.standard_normal((n, 3))
    mag = np.array([0, 20, -45]) + 0.5 * rng.standard_normal((n, 3))
    return t, gyr, acc, mag, fs, "generated"


def best_of(fn, repeat):
    best = np.inf
    for _ in range(repeat):
        t0 = time.perf_counter()
        fn()
        best = min(best, time.perf_counter() - t0)
    return best


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--repeat", type=int, default=5)
    ap.add_argument("--only", nargs="*")
    ap.add_argument("--parts", action="store_true",
                    help="robust's cost per row with all three sensors, without the "
                         "magnetometer, and with the gyroscope alone (ns per row)")
    args = ap.parse_args(argv)
    if args.parts:
        return parts(args.repeat)
    t, gyr, acc, mag, fs, src = recording()
    n = len(t)
    print(f"recording: {src}, {n} samples at {fs:.1f} Hz; best of {args.repeat} runs, one core\n")
    rows = []
    for name in NAMES:
        if args.only and name not in args.only:
            continue
        make_estimator(name).run(t[:500], gyr[:500], acc[:500], mag[:500])  # warm-up / JIT
        sec = best_of(lambda: make_estimator(name).run(t, gyr, acc, mag), args.repeat)
        rows.append((name, n / sec))
    try:
        from vqf import VQF
        g, a, m = (np.ascontiguousarray(x) for x in (gyr, acc, mag))
        sec = best_of(lambda: VQF(1.0 / fs).updateBatch(g, a, m), args.repeat)
        rows.append(("VQF (C++)", n / sec))
    except ImportError:
        print("!! vqf is not installed (pip install vqf): no VQF figure !!")
    rows.append(("robust, uncompiled", uncompiled_rate()))
    for name, rate in rows:
        print(f"{name:<20}{rate:>14,.0f} samples/s")
    print("\nlive path, one step() per sample as the dashboard calls it (µs per sample):")
    total = 0.0
    for name in NAMES:
        us = step_cost_us(name, t, gyr, acc, mag, args.repeat)
        total += us
        print(f"{name:<20}{us:>14.1f}")
    print(f"{'all four':<20}{total:>14.1f}")
    return 0


def parts(repeat) -> int:
    """robust's batch cost per row (ns) as sensors are left out of the same recording: the
    differences are what the accelerometer's and the magnetometer's paths cost."""
    t, gyr, acc, mag, fs, src = recording()
    none = np.full_like(mag, np.nan)
    print(f"recording: {src}, {len(t)} rows; robust, best of {repeat} runs, one core\n")
    rows = {"gyroscope, accelerometer, magnetometer": (gyr, acc, mag),
            "gyroscope, accelerometer": (gyr, acc, none),
            "gyroscope alone": (gyr, none, none)}
    for label, (g, a, m) in rows.items():
        make_estimator("robust").run(t[:500], g[:500], a[:500], m[:500])  # warm-up / JIT
        sec = best_of(lambda: make_estimator("robust").run(t, g, a, m), repeat)
        print(f"{label:<40}{sec / len(t) * 1e9:8.0f} ns per row")
    return 0


def step_cost_us(name, t, gyr, acc, mag, repeat, n=5000) -> float:
    """Per-sample cost of ``step`` with one sensor per call, as a phone stream arrives
    (the batch figures above hold all three sensors in one row)."""
    calls = []
    for k in range(n // 3):
        calls += [(t[k], {"gyr": gyr[k]}), (t[k] + 1e-4, {"acc": acc[k]}), (t[k] + 2e-4, {"mag": mag[k]})]
    est = make_estimator(name)
    for tk, kw in calls[:30]:
        est.step(tk, **kw)  # warm-up / JIT

    def run():
        e = make_estimator(name)
        for tk, kw in calls:
            e.step(tk, **kw)
    return best_of(run, repeat) / len(calls) * 1e6


_UNCOMPILED = r"""
import sys, time
sys.path.insert(0, sys.argv[1])
sys.path.insert(0, sys.argv[1] + '/benchmarks')
from throughput import recording
from app.estimators import make_estimator
t, gyr, acc, mag, fs, src = recording()
n = 5000
t0 = time.perf_counter()
make_estimator('robust').run(t[:n], gyr[:n], acc[:n], mag[:n])
print(n / (time.perf_counter() - t0))
"""


def uncompiled_rate() -> float:
    """The same robust code run by the plain interpreter (NUMBA_DISABLE_JIT=1: every
    @njit function is ordinary numpy), on 5000 samples: what numba buys."""
    import os
    import subprocess
    out = subprocess.run([sys.executable, "-c", _UNCOMPILED, str(ROOT)], capture_output=True,
                         text=True, env=dict(os.environ, NUMBA_DISABLE_JIT="1"), check=True)
    return float(out.stdout.strip().splitlines()[-1])


if __name__ == "__main__":
    raise SystemExit(main())
