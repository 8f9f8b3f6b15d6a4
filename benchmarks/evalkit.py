"""Shared helpers of the ablation and cross-validation benchmarks: the shared trials, robust's
per-trial errors with any parameter changes, VQF's for comparison.

Data: BROAD (Laidig, Caruso, Cereatti, Seel, Data 6(7):72, 2021, CC-BY-4.0) and the smartphone
attitude benchmark of Michel, Genevès, Fourati, Layaïda (IEEE PerCom 2017, CeCILL 2.1), read from
``../shared/data`` (see ``accuracy_phones.py``). Metric: theirs (total / heading / inclination
RMSE per trial, degrees).

``python benchmarks/evalkit.py [--set KEY=VALUE ...]`` prints robust's and VQF's per-trial
errors on both sets (a quick check while changing the filter).
"""

from __future__ import annotations

import argparse
import json
import sys
from concurrent.futures import ProcessPoolExecutor
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))
sys.path.insert(0, str(ROOT / "benchmarks"))

from accuracy_phones import errors, load_broad, load_phones  # noqa: E402
from app.estimators import make_estimator  # noqa: E402
from app.quaternion import quat_conj_many, quat_mul_many  # noqa: E402

# BROAD's kinds for leave-one-kind-out (from trials.json's groups; an attached magnet is its own)
KINDS = ("undisturbed rotation", "translation", "with rests", "tapping and vibration",
         "stationary magnet", "attached magnet")


def broad_kind(trial: dict) -> str:
    g = set(trial.get("groups", ()))
    if "attached_magnet" in g:
        return "attached magnet"
    if "stationary_magnet" in g:
        return "stationary magnet"
    if "tapping" in g or "vibration" in g:
        return "tapping and vibration"
    if "with_breaks" in g:
        return "with rests"
    if "translation" in g:
        return "translation"
    return "undisturbed rotation"   # rotation without rests, and the combined trial


# issue 19's done-when: held-out total RMSE at most this × VQF's (BROAD's inclination no worse,
# no trial above 2 × VQF + 5°: catastrophic)
BOUNDS = {"broad": 0.95, "phones": 0.85}


def done_when(which: str, held: np.ndarray, vqf: np.ndarray) -> tuple[str, bool]:
    """Issue 19's done-when on per-trial held-out errors ``held`` against VQF's (both (n, 3)):
    the line the cross-validations print, and whether it holds."""
    h, v = held.mean(0), vqf.mean(0)
    bound = BOUNDS[which]
    worst = float(np.max(held[:, 0] - (2 * vqf[:, 0] + 5.0)))
    ok = h[0] / v[0] <= bound and worst < 0 and (which != "broad" or h[2] <= v[2])
    return (f"held-out / VQF: {h[0] / v[0]:.3f} (done-when: ≤ {bound}); inclination {h[2]:.3f} vs "
            f"VQF {v[2]:.3f}; closest trial to 2×VQF+5°: {worst:+.2f}° "
            f"({'none catastrophic' if worst < 0 else 'CATASTROPHIC'})"), ok


_TRIALS: dict[str, list[dict]] = {}


def trials(which: str) -> list[dict]:
    """'broad' or 'phones' (cached per process)."""
    if which not in _TRIALS:
        _TRIALS[which] = load_broad() if which == "broad" else load_phones()
    return _TRIALS[which]


def estimate(tr: dict, params: dict | None = None, method: str = "robust",
             gyr: np.ndarray | None = None) -> np.ndarray:
    """The (N, 4) estimate of ``method`` (robust, another of orientlab's, or VQF) on trial ``tr``,
    with ``params`` changed from its defaults and, when given, ``gyr`` in place of its gyroscope."""
    gyr = tr["gyr"] if gyr is None else gyr
    if method == "VQF":
        from vqf import VQF
        v = VQF(1.0 / tr["fs"], **(params or {}))
        return v.updateBatch(*(np.ascontiguousarray(x) for x in (gyr, tr["acc"], tr["mag"])))["quat9D"]
    return make_estimator(method, params).run(tr["t"], gyr, tr["acc"], tr["mag"]).q


def heading_error(q: np.ndarray, ref: np.ndarray) -> np.ndarray:
    """Signed heading error (rad, modulo 2π): the turn about the vertical of ``q ⊗ ref⁻¹`` (its
    twist about world z; no Euler angles, which fail for an upright phone)."""
    e = quat_mul_many(q, quat_conj_many(ref))
    return 2.0 * np.arctan2(e[:, 3], e[:, 0])


def _run_one(args):
    which, i, params, method = args
    tr = trials(which)[i]
    return errors(estimate(tr, params, method), tr)


_POOL = None


def pool(jobs: int = 2):
    global _POOL
    if _POOL is None and jobs > 1:
        _POOL = ProcessPoolExecutor(jobs)
    return _POOL


def evaluate(which: str, params: dict | None = None, method: str = "robust", jobs: int = 2) -> np.ndarray:
    """Per-trial (total, heading, inclination) RMSE, shape (n, 3), in ``trials(which)`` order."""
    n = len(trials(which))
    tasks = [(which, i, params, method) for i in range(n)]
    p = pool(jobs)
    out = list(p.map(_run_one, tasks, chunksize=1)) if p else [_run_one(t) for t in tasks]
    return np.array(out)


_VQF_CACHE = Path("/tmp/orientlab_vqf_cache.json")


def vqf_errors(which: str) -> np.ndarray:
    """VQF's per-trial errors (cached in /tmp: VQF does not change)."""
    cache = json.loads(_VQF_CACHE.read_text()) if _VQF_CACHE.is_file() else {}
    names = [t["name"] for t in trials(which)]
    if which not in cache or cache[which]["names"] != names:
        cache[which] = {"names": names, "err": evaluate(which, method="VQF").tolist()}
        _VQF_CACHE.write_text(json.dumps(cache))
    return np.array(cache[which]["err"])


def parse_sets(items) -> dict:
    out = {}
    for kv in items:
        k, _, v = kv.partition("=")
        try:
            out[k] = json.loads(v)
        except json.JSONDecodeError:
            out[k] = v
    return out


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--set", action="append", default=[], metavar="KEY=VALUE")
    ap.add_argument("--which", nargs="*", default=["broad", "phones"])
    ap.add_argument("--quiet", action="store_true", help="means only")
    args = ap.parse_args(argv)
    params = parse_sets(args.set) or None
    for which in args.which:
        e, v = evaluate(which, params), vqf_errors(which)
        if not args.quiet:
            for tr, a, b in zip(trials(which), e, v):
                print(f"{tr['name']:<46}{a[0]:7.2f}{a[1]:7.2f}{a[2]:7.2f}   VQF{b[0]:7.2f}")
        print(f"{which:<10} robust {e[:, 0].mean():.3f} ({e[:, 1].mean():.2f}/{e[:, 2].mean():.3f})"
              f"  VQF {v[:, 0].mean():.3f} ({v[:, 1].mean():.2f}/{v[:, 2].mean():.3f})"
              f"  worst {e[:, 0].max():.2f}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
