"""Accuracy on BROAD: every orientlab estimator beside VQF and Madgwick, in one run.

BROAD (Laidig, Caruso, Cereatti, Seel: "BROAD - A Benchmark for Robust Inertial
Orientation Estimation", Data 6(7):72, 2021, CC-BY-4.0) gives real IMU trials with
optical ground truth. Its metric, used here: per sample the error quaternion
``e = q_est * conj(q_ref)``; its angle is the total error, split into heading (about the
world's vertical) and inclination; RMSE over the movement phase of each trial; the
mean of those RMSEs over the trials of each group. No heading alignment: the ground
truth points at magnetic north. One parameter set for all trials.

Usage: ``python benchmarks/accuracy_broad.py [--data DIR] [--only NAME ...]``
(DIR defaults to ``../shared/data/broad`` beside the repository). Needs ``vqf``
(``pip install vqf``; without it the VQF column is left out, said loudly).
"""

from __future__ import annotations

import argparse
import importlib.util
import json
import sys
import time
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))
sys.path.insert(0, str(ROOT / "benchmarks"))

from app.estimators import NAMES, make_estimator  # noqa: E402
from app.quaternion import error_angles  # noqa: E402

DEFAULT_DATA = ROOT.parent / "shared" / "data" / "broad"
DEG = 180.0 / np.pi


def load_trials(data_dir: Path) -> list[dict]:
    trials = []
    meta = json.loads((data_dir / "trials.json").read_text())["trials"]
    for f in sorted(data_dir.glob("*.npz")):
        d = np.load(f)
        trials.append(dict(name=f.stem, groups=meta.get(f.stem, {}).get("groups", ["all_trials"]),
                           acc=d["acc"], gyr=d["gyr"], mag=d["mag"], ref=d["opt_quat"],
                           movement=d["movement"].astype(bool), fs=float(d["fs"])))
    return trials


def trial_errors(q_est: np.ndarray, trial: dict) -> tuple[float, float, float]:
    """(total, heading, inclination) RMSE in degrees over the movement phase."""
    ref = trial["ref"]
    m = trial["movement"] & np.all(np.isfinite(ref), axis=1) & np.all(np.isfinite(q_est), axis=1)
    tot, head, inc = error_angles(q_est[m], ref[m])
    rmse = lambda x: float(np.sqrt(np.mean(x ** 2)) * DEG)  # noqa: E731
    return rmse(tot), rmse(head), rmse(inc)


def run_orientlab(name: str, params: dict | None = None):
    def run(trial):
        est = make_estimator(name, params)
        n = trial["gyr"].shape[0]
        t = np.arange(n) / trial["fs"]
        return est.run(t, trial["gyr"], trial["acc"], trial["mag"]).q
    return run


def run_vqf(trial):
    from vqf import VQF
    v = VQF(1.0 / trial["fs"])
    out = v.updateBatch(np.ascontiguousarray(trial["gyr"]), np.ascontiguousarray(trial["acc"]),
                        np.ascontiguousarray(trial["mag"]))
    return out["quat9D"]


def run_madgwick(trial, beta: float = 0.1):
    from madgwick import madgwick_batch
    return madgwick_batch(trial["gyr"], trial["acc"], trial["mag"], trial["fs"], beta)


def evaluate(run, trials) -> dict[str, tuple[float, float, float]]:
    return {tr["name"]: trial_errors(run(tr), tr) for tr in trials}


def group_table(results: dict[str, dict], trials: list[dict]) -> list[tuple]:
    groups: dict[str, list[str]] = {}
    for tr in trials:
        for g in tr["groups"]:
            groups.setdefault(g, []).append(tr["name"])
    rows = []
    for g, names in groups.items():
        row = [g, len(names)]
        for method, per_trial in results.items():
            e = np.array([per_trial[n] for n in names])
            row.append(tuple(e.mean(axis=0)))
        rows.append(tuple(row))
    return rows


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--data", type=Path, default=DEFAULT_DATA)
    ap.add_argument("--only", nargs="*", help="methods to run (default: all)")
    ap.add_argument("--per-trial", action="store_true", help="also print every trial")
    ap.add_argument("--set", action="append", default=[], metavar="NAME:KEY=VALUE",
                    help="change a parameter of one of our estimators, e.g. "
                         "robust:mag_norm_gate_rel=0.05 (VALUE as JSON; repeatable)")
    args = ap.parse_args(argv)
    if not (args.data / "trials.json").is_file():
        print(f"BROAD data not found at {args.data}: nothing to benchmark.")
        return 0
    trials = load_trials(args.data)
    overrides: dict[str, dict] = {}
    for item in args.set:
        name, _, kv = item.partition(":")
        key, _, value = kv.partition("=")
        try:
            value = json.loads(value)
        except json.JSONDecodeError:
            pass
        overrides.setdefault(name, {})[key] = value
    methods = {n: run_orientlab(n, overrides.get(n)) for n in NAMES if n != "phone"}  # no ORI in BROAD
    if overrides:
        print("changed parameters: " + "; ".join(f"{n}: {p}" for n, p in overrides.items()))
    if importlib.util.find_spec("vqf") is not None:
        methods["VQF"] = run_vqf
    else:
        print("!! vqf is not installed (pip install vqf): the VQF column is left out !!")
    methods["Madgwick"] = run_madgwick
    if args.only:
        methods = {k: v for k, v in methods.items() if k in args.only}
    results, timings = {}, {}
    for name, run in methods.items():
        run(trials[0])  # warm-up (JIT compilation) outside the timing
        t0 = time.perf_counter()
        results[name] = evaluate(run, trials)
        timings[name] = time.perf_counter() - t0
    n_samples = sum(tr["gyr"].shape[0] for tr in trials)
    print(f"BROAD: {len(trials)} trials, {n_samples} samples; RMSE in degrees, "
          "total / heading / inclination, mean over the trials of each group\n")
    head = f"{'group':<20}{'n':>3}  " + "".join(f"{m:>24}" for m in results)
    print(head)
    print("-" * len(head))
    for row in group_table(results, trials):
        cells = "".join(f"{e[0]:8.2f}{e[1]:8.2f}{e[2]:8.2f}" for e in row[2:])
        print(f"{row[0]:<20}{row[1]:>3}  {cells}")
    if args.per_trial:
        print()
        for tr in trials:
            cells = "".join(f"{results[m][tr['name']][0]:24.2f}" for m in results)
            print(f"{tr['name']:<42}{cells}")
    print("\nrun time for all trials (s): " + ", ".join(f"{m} {t:.1f}" for m, t in timings.items()))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
