"""Accuracy on real phones with motion-capture truth, beside VQF, Madgwick and the phones' own estimate.

Data: the smartphone attitude benchmark of T. Michel, P. Genevès, H. Fourati, N. Layaïda, "On Attitude
Estimation with Smartphones", IEEE PerCom 2017 (tyrex-team/benchmarks-attitude-smartphones, licence
CeCILL 2.1), one person's 42 trials (Nexus 5, iPhone 4S, iPhone 5; 14 motions), read from
``../shared/data/phones-tyrex``; and BROAD (Laidig, Caruso, Cereatti, Seel, Data 6(7):72, 2021,
CC-BY-4.0) from ``../shared/data/broad``.

Metric (both data READMEs): per sample the error quaternion ``e = q_est ⊗ q_ref⁻¹``; its angle is the
total error, split into heading and inclination; RMSE over the evaluated samples of a trial; mean over
the trials of a group. No heading alignment: the truths point at magnetic north.

What it prints, all from one run:
1. per phone × motion × disturbance: robust (default parameters), lab, complementary, VQF (defaults),
   Madgwick (β = 0.1), the phone's own OS estimate; then group means, BROAD's totals for the same
   methods, and the acceptance checks of issue 7 (robust ≤ VQF in total and inclination on each
   dataset; no trial above 2×VQF + 5°).
2. cross-validation: ``tune()`` (below) chooses robust's parameters on a training set by a small grid
   over physically meaningful settings (heading and tilt noise densities); the chosen set is scored on
   the held-out set: two phones → the third, BROAD → phones, phones → BROAD. Printed beside the
   default parameters' score on the same held-out trials.
3. false alarms: the share of magnetometer samples robust refuses (``is_rejected``) on undisturbed
   trials, on the shared app logs (``tests/conftest.py`` REAL_LOGS) and, for contrast, on disturbed
   trials; and the share of accelerometer samples flagged as specific force.

Usage: ``python benchmarks/accuracy_phones.py [--jobs 2] [--no-cv] [--set KEY=VALUE ...]``
(``--set`` changes a default of robust, VALUE as JSON, for ablations).
"""

from __future__ import annotations

import argparse
import importlib.util
import itertools
import json
import sys
import time
from concurrent.futures import ProcessPoolExecutor
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))
sys.path.insert(0, str(ROOT / "benchmarks"))
sys.path.insert(0, str(ROOT / "tests"))

from app.estimators import make_estimator  # noqa: E402
from app.estimators.base import F_ACC, F_MAG, Reason, is_rejected  # noqa: E402
from app.quaternion import error_angles  # noqa: E402

SHARED = ROOT.parent / "shared" / "data"
PHONES = SHARED / "phones-tyrex"
BROAD = SHARED / "broad"
DEG = 180.0 / np.pi
METHODS = ("robust", "lab", "complementary", "VQF", "Madgwick", "OS")

# The grid tune() searches: noise densities that set the correction time constants
# (tilt_noise/gyr_noise, heading_noise/gyr_noise): what a user would tune first.
GRID = {"heading_noise": (0.05, 0.1, 0.2, 0.4), "tilt_noise": (0.01, 0.02, 0.04)}


# ---------------------------------------------------------------- data
def _f64(a) -> np.ndarray:
    return np.ascontiguousarray(a, dtype=np.float64)


def load_phones(data: Path = PHONES) -> list[dict]:
    meta = json.loads((data / "trials.json").read_text())
    out = []
    for f in sorted(data.glob("*.npz")):
        d = np.load(f)
        m = meta.get(f.stem, {})
        out.append(dict(name=f.stem, set="phones", phone=m.get("phone", f.stem.split("_")[0]),
                        motion=m.get("motion", f.stem.split("_")[-1]),
                        dist="Dist" if m.get("disturbed", "_Dist_" in f.stem) else "NoDist",
                        t=d["t"] - d["t"][0], gyr=_f64(d["gyr"]), acc=_f64(d["acc"]), mag=_f64(d["mag"]),
                        ref=_f64(d["gt_quat"]), os=_f64(d["os_quat"]), mask=d["eval_mask"].astype(bool), fs=float(d["fs"])))
    return out


def load_broad(data: Path = BROAD) -> list[dict]:
    meta = json.loads((data / "trials.json").read_text())["trials"]
    out = []
    for f in sorted(data.glob("*.npz")):
        d = np.load(f)
        n = d["gyr"].shape[0]
        out.append(dict(name=f.stem, set="broad", phone="BROAD", motion=f.stem,
                        dist="Dist" if "disturbed" in f.stem and "undisturbed" not in f.stem else "NoDist",
                        groups=meta.get(f.stem, {}).get("groups", []),
                        t=np.arange(n) / float(d["fs"]), gyr=_f64(d["gyr"]), acc=_f64(d["acc"]),
                        mag=_f64(d["mag"]), ref=_f64(d["opt_quat"]), os=None, mask=d["movement"].astype(bool), fs=float(d["fs"])))
    return out


def load_app_logs() -> list[dict]:
    from conftest import REAL_LOGS
    from app.sources.readers import read_log_data
    out = []
    for rel in REAL_LOGS:
        p = SHARED / "sensorfusion-app" / rel
        if p.is_file():
            r = read_log_data(p)
            out.append(dict(name=p.stem, t=r.t, gyr=r.gyr, acc=r.acc, mag=r.mag))
    return out


# ---------------------------------------------------------------- methods
def errors(q: np.ndarray, trial: dict) -> tuple[float, float, float]:
    """(total, heading, inclination) RMSE in degrees over the trial's evaluated samples."""
    ref = trial["ref"]
    m = trial["mask"] & np.all(np.isfinite(ref), axis=1) & np.all(np.isfinite(q), axis=1)
    tot, head, inc = error_angles(q[m], ref[m])
    rmse = lambda x: float(np.sqrt(np.mean(x ** 2)) * DEG)  # noqa: E731
    return rmse(tot), rmse(head), rmse(inc)


def run_method(method: str, trial: dict, params: dict | None = None):
    """(q, flags or None) of ``method`` on ``trial``."""
    if method == "OS":
        return trial["os"], None
    if method == "VQF":
        from vqf import VQF
        v = VQF(1.0 / trial["fs"])
        out = v.updateBatch(*(np.ascontiguousarray(trial[k]) for k in ("gyr", "acc", "mag")))
        # VQF's own disturbance decision per sample, in the flag record's mag column
        flags = np.full((len(trial["t"]), F_MAG + 1), float(Reason.USED))
        flags[np.asarray(out["magDistDetected"], dtype=bool), F_MAG] = float(Reason.NORM)
        return out["quat9D"], flags
    if method == "Madgwick":
        from madgwick import madgwick_batch
        return madgwick_batch(trial["gyr"], trial["acc"], trial["mag"], trial["fs"], 0.1), None
    res = make_estimator(method, params).run(trial["t"], trial["gyr"], trial["acc"], trial["mag"])
    return res.q, res.flags


def rejected_share(flags: np.ndarray, col: int) -> tuple[int, int]:
    """(refused, valid) samples of one sensor column: refused as ``is_rejected`` decides."""
    codes = flags[:, col].astype(int)
    valid = ~np.isin(codes, [Reason.ABSENT, Reason.DISABLED, Reason.INVALID, Reason.WAIT, Reason.LATE])
    rej = np.array([is_rejected(c) for c in range(len(Reason))])[codes]
    return int(np.sum(rej & valid)), int(np.sum(valid))


def _job(args):
    method, trial, params = args
    q, flags = run_method(method, trial, params)
    out = {"err": errors(q, trial) if trial.get("ref") is not None else None}
    if flags is not None:
        out["mag_rej"] = rejected_share(flags, F_MAG)
        if flags.shape[1] > F_ACC:
            out["acc_rej"] = rejected_share(flags, F_ACC)
    return out


class Runner:
    def __init__(self, jobs: int):
        self.pool = ProcessPoolExecutor(jobs) if jobs > 1 else None

    def map(self, tasks):
        if self.pool is None:
            return [_job(t) for t in tasks]
        return list(self.pool.map(_job, tasks, chunksize=1))

    def close(self) -> None:
        """Join the workers before the interpreter exits (its exit hook otherwise writes to a
        pipe that may be closed already, and prints an error after the figures)."""
        if self.pool is not None:
            self.pool.shutdown()


def score(runner: Runner, method: str, trials: list[dict], params: dict | None = None) -> list[dict]:
    return runner.map([(method, tr, params) for tr in trials])


# ---------------------------------------------------------------- tuning (for the cross-validation)
def tune(runner: Runner, trials: list[dict], base: dict) -> tuple[dict, float]:
    """Robust's parameters chosen on ``trials``: the grid point of ``GRID`` (on top of ``base``)
    with the lowest mean total RMSE. Returns (parameters, their training error)."""
    best, best_e = None, np.inf
    keys = list(GRID)
    for values in itertools.product(*(GRID[k] for k in keys)):
        p = dict(base, **dict(zip(keys, values)))
        e = np.mean([r["err"][0] for r in score(runner, "robust", trials, p)])
        if e < best_e:
            best, best_e = p, e
    return best, float(best_e)


def mean_err(results: list[dict]) -> np.ndarray:
    return np.mean([r["err"] for r in results], axis=0)


# ---------------------------------------------------------------- main
def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--jobs", type=int, default=2, help="worker processes (at most 2 here)")
    ap.add_argument("--no-cv", action="store_true", help="skip the cross-validation")
    ap.add_argument("--only", nargs="*", help="methods (default: all)")
    ap.add_argument("--set", action="append", default=[], metavar="KEY=VALUE",
                    help="change one of robust's defaults (VALUE as JSON; repeatable)")
    args = ap.parse_args(argv)
    if not (PHONES / "trials.json").is_file():
        print(f"phone data not found at {PHONES}: nothing to benchmark.")
        return 0
    base: dict = {}
    for item in args.set:
        k, _, v = item.partition("=")
        try:
            base[k] = json.loads(v)
        except json.JSONDecodeError:
            base[k] = v
    if base:
        print(f"robust with changed defaults: {base}")
    phones = load_phones()
    broad = load_broad() if (BROAD / "trials.json").is_file() else []
    methods = [m for m in METHODS if not args.only or m in args.only]
    if importlib.util.find_spec("vqf") is None:
        print("!! vqf is not installed (pip install vqf): the VQF column is left out !!")
        methods = [m for m in methods if m != "VQF"]
    for m in methods:  # compile once in this process (numba caches to disk for the workers)
        if m != "OS":
            run_method(m, dict(phones[0], t=phones[0]["t"][:300], gyr=phones[0]["gyr"][:300],
                               acc=phones[0]["acc"][:300], mag=phones[0]["mag"][:300]),
                       base if m == "robust" else None)
    runner = Runner(min(args.jobs, 2))
    t0 = time.perf_counter()
    res = {m: score(runner, m, phones, base if m == "robust" else None) for m in methods}
    resb = {m: score(runner, m, broad, base if m == "robust" else None) for m in methods if m != "OS"}

    print("Smartphone attitude benchmark (Michel, Genevès, Fourati, Layaïda 2017; CeCILL 2.1), "
          f"{len(phones)} trials.\nRMSE in degrees: total (heading/inclination); "
          "robust, lab, complementary with their defaults\n")
    w = 16
    head = f"{'phone':<9}{'motion':<14}{'dist':<7}" + "".join(f"{m:>{w}}" for m in methods)
    print(head)
    print("-" * len(head))
    for i, tr in enumerate(phones):
        cells = "".join(f"{res[m][i]['err'][0]:>7.1f} ({res[m][i]['err'][1]:4.1f}/{res[m][i]['err'][2]:3.1f})"
                        .rjust(w) for m in methods)
        print(f"{tr['phone']:<9}{tr['motion']:<14}{tr['dist']:<7}{cells}")
    print()
    groups = [("all", lambda tr: True)]
    groups += [(ph, lambda tr, ph=ph: tr["phone"] == ph) for ph in sorted({t["phone"] for t in phones})]
    groups += [(d, lambda tr, d=d: tr["dist"] == d) for d in ("NoDist", "Dist")]
    groups += [(mo, lambda tr, mo=mo: tr["motion"] == mo) for mo in sorted({t["motion"] for t in phones})]
    print(f"{'group (mean)':<24}{'n':>3}" + "".join(f"{m:>{w}}" for m in methods))
    for g, sel in groups:
        idx = [i for i, tr in enumerate(phones) if sel(tr)]
        cells = ""
        for m in methods:
            e = mean_err([res[m][i] for i in idx])
            cells += f"{e[0]:>7.2f} ({e[1]:4.1f}/{e[2]:3.1f})".rjust(w)
        print(f"{g:<24}{len(idx):>3}{cells}")

    if broad:
        print(f"\nBROAD (Laidig, Caruso, Cereatti, Seel 2021; CC-BY-4.0), {len(broad)} trials: "
              "mean RMSE total (heading/inclination)")
        bm = [m for m in methods if m != "OS"]
        for g, sel in (("all", lambda tr: True), ("undisturbed", lambda tr: tr["dist"] == "NoDist"),
                       ("disturbed", lambda tr: tr["dist"] == "Dist")):
            idx = [i for i, tr in enumerate(broad) if sel(tr)]
            cells = "".join(f"{mean_err([resb[m][i] for i in idx])[0]:>7.2f} "
                            f"({mean_err([resb[m][i] for i in idx])[1]:4.1f}/"
                            f"{mean_err([resb[m][i] for i in idx])[2]:3.1f})".rjust(w) for m in bm)
            print(f"{g:<24}{len(idx):>3}{cells}")

    # acceptance checks (issue 7)
    if "VQF" in methods and "robust" in methods:
        print("\nChecks against VQF (defaults), robust with one parameter set:")
        for label, trials, r in (("phones-tyrex", phones, res), ("BROAD", broad, resb)):
            if not trials:
                continue
            er, ev = mean_err(r["robust"]), mean_err(r["VQF"])
            print(f"  {label:<13} total robust {er[0]:.2f} vs VQF {ev[0]:.2f}: "
                  f"{'OK' if er[0] <= ev[0] else 'ABOVE'};  inclination {er[2]:.3f} vs {ev[2]:.3f}: "
                  f"{'OK' if er[2] <= ev[2] else 'ABOVE'}")
            ratio = [(a["err"][0] - (2 * b["err"][0] + 5.0), a["err"][0], b["err"][0], tr["name"])
                     for a, b, tr in zip(r["robust"], r["VQF"], trials)]
            worst = max(ratio)
            bad = [x for x in ratio if x[0] > 0]
            print(f"  {'':<13} worst trial vs 2×VQF+5°: {worst[3]} robust {worst[1]:.1f}° vs bound "
                  f"{2 * worst[2] + 5:.1f}° ({len(bad)} trial(s) above)")

    # false alarms
    if "robust" in methods:
        print("\nrobust's refusals (share of valid samples, is_rejected()):")

        def share(rs, key):
            a = sum(r[key][0] for r in rs)
            b = sum(r[key][1] for r in rs)
            return 100.0 * a / max(b, 1)

        for label, rs in (("phones NoDist", [r for r, tr in zip(res["robust"], phones) if tr["dist"] == "NoDist"]),
                          ("phones Dist", [r for r, tr in zip(res["robust"], phones) if tr["dist"] == "Dist"]),
                          ("BROAD undisturbed", [r for r, tr in zip(resb.get("robust", []), broad)
                                                 if tr["dist"] == "NoDist"]),
                          ("BROAD disturbed", [r for r, tr in zip(resb.get("robust", []), broad)
                                               if tr["dist"] == "Dist"])):
            if rs:
                worst = max(100.0 * r["mag_rej"][0] / max(r["mag_rej"][1], 1) for r in rs)
                print(f"  {label:<22} mag refused {share(rs, 'mag_rej'):5.1f} % (worst trial {worst:5.1f} %)"
                      f"   acc flagged {share(rs, 'acc_rej'):5.1f} %")
        logs = load_app_logs()
        if "VQF" in methods:
            for label, sel in (("NoDist", "NoDist"), ("Dist", "Dist")):
                rs = [r for r, tr in zip(res["VQF"], phones) if tr["dist"] == sel]
                print(f"  for comparison, VQF judges the field disturbed on phones {label}: "
                      f"{share(rs, 'mag_rej'):5.1f} % of the samples")
        if logs:
            rl = runner.map([("robust", dict(lg, ref=None), base) for lg in logs])
            for lg, r in zip(logs, rl):
                print(f"  app log {lg['name'][:40]:<40} mag refused {100.0 * r['mag_rej'][0] / max(r['mag_rej'][1], 1):5.1f} %"
                      f"   acc flagged {100.0 * r['acc_rej'][0] / max(r['acc_rej'][1], 1):5.1f} %")
            print(f"  {'all app logs':<22} mag refused {share(rl, 'mag_rej'):5.1f} %   "
                  f"acc flagged {share(rl, 'acc_rej'):5.1f} %")

    if not args.no_cv and "robust" in methods:
        print("\nCross-validation: robust's parameters chosen by tune() (grid "
              + ", ".join(f"{k} {v}" for k, v in GRID.items()) + ") on the training set,\n"
              "scored on the held-out set; mean total RMSE (heading/inclination); defaults on the same trials")
        folds = []
        for ph in sorted({t["phone"] for t in phones}):
            folds.append((f"phones w/o {ph} -> {ph}", [t for t in phones if t["phone"] != ph],
                          [t for t in phones if t["phone"] == ph]))
        if broad:
            folds.append(("BROAD -> phones", broad, phones))
            folds.append(("phones -> BROAD", phones, broad))
        held_all = []
        for label, train, test in folds:
            p, e_train = tune(runner, train, base)
            eh = mean_err(score(runner, "robust", test, p))
            ed = mean_err(score(runner, "robust", test, base))
            chosen = ", ".join(f"{k}={p[k]}" for k in GRID)
            print(f"  {label:<26} chosen {chosen:<36} train {e_train:5.2f}   held-out "
                  f"{eh[0]:5.2f} ({eh[1]:.1f}/{eh[2]:.1f})   defaults {ed[0]:5.2f}")
            held_all.append((label, eh))
        ph = [e for lab, e in held_all if lab.startswith("phones w/o")]
        if ph:
            print(f"  leave-one-phone-out, mean over the three held-out phones: {np.mean([e[0] for e in ph]):.2f}")
    runner.close()
    print(f"\nrun time {time.perf_counter() - t0:.0f} s")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
