"""Cross-validation of robust's settable parameters: leave one kind out on BROAD, one phone out on the
phones; held-out figures beside the defaults' and VQF's, per trial and as means.

Data: BROAD (Laidig, Caruso, Cereatti, Seel, Data 6(7):72, 2021, CC-BY-4.0) and the smartphone
attitude benchmark of Michel, Genevès, Fourati, Layaïda (IEEE PerCom 2017, CeCILL 2.1), read from
``../shared/data``; their metric (total / heading / inclination RMSE per trial, degrees).

For each fold, every numeric parameter of robust (``grid()``: each on its own, ×0.5 / ×1 / ×2
of its default, the others at their defaults: the choice a user would make by looking at the
training trials) may be changed: the one change with the lowest mean total error on the
training trials is made (``--rule argmin``, the default) or, with ``--rule 1se``, the best that
beats the defaults there by more than one standard error; the held-out trials are then scored
with it. A second table does the same for each parameter alone (the folds may change only it):
a parameter whose held-out figure is worse than the defaults' is one whose value the training
trials would have set wrongly. BROAD's kinds (from ``trials.json``'s groups,
``evalkit.broad_kind``): undisturbed rotation, translation, with rests, tapping and vibration,
stationary magnet, attached magnet (its own class: one of those trials moves a 17-trial mean by
0.1-0.4°). Phones: Nexus 5, iPhone 4S, iPhone 5. The done-when of issue 19: held-out BROAD
≤ 0.95 × VQF with inclination no worse, held-out phones ≤ 0.85 × VQF with no catastrophic trial
(none above 2 × VQF + 5°).

Usage: ``python benchmarks/crossval.py [--per-trial] [--rule argmin|1se]`` (about three minutes
on two cores: 99 settings on 59 trials).
"""

from __future__ import annotations

import argparse
import dataclasses
import sys
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))
sys.path.insert(0, str(ROOT / "benchmarks"))

import evalkit  # noqa: E402
from app.estimators.robust import RobustParams  # noqa: E402

def grid() -> tuple[str, ...]:
    """Every parameter a fold may set: each numeric one of robust's (switches, vectors and those
    at 0, off, are not scaled)."""
    d = RobustParams()
    return tuple(f.name for f in dataclasses.fields(d)
                 if type(getattr(d, f.name)) is float and getattr(d, f.name) > 0.0)


def choose(errs: dict, cands: list, train: np.ndarray, rule: str) -> str:
    """The candidate the training trials choose. ``argmin``: the lowest mean total error.
    ``1se``: the lowest among those better than the defaults by more than one standard error
    of the paired difference (Breiman's one-standard-error rule: a choice within the noise
    of the training trials is no evidence), else the defaults."""
    if rule == "argmin":
        return min(cands, key=lambda c: errs[c[0]][train, 0].mean())[0]
    base = errs["defaults"][train, 0]
    best, best_mean = "defaults", base.mean()
    for label, _ in cands:
        d = errs[label][train, 0] - base
        if d.mean() + d.std(ddof=1) / np.sqrt(len(d)) < 0.0 and errs[label][train, 0].mean() < best_mean:
            best, best_mean = label, errs[label][train, 0].mean()
    return best


def candidates():
    d = RobustParams()
    out = [("defaults", {})]
    for k in grid():
        v = getattr(d, k)
        for f in (0.5, 2.0):
            out.append((f"{k} ×{f:g}", {k: v * f}))
    return out


def folds(which: str):
    trs = evalkit.trials(which)
    if which == "broad":
        keys = [evalkit.broad_kind(t) for t in trs]
        names = evalkit.KINDS
    else:
        keys = [t["phone"] for t in trs]
        names = sorted(set(keys))
    for n in names:
        test = np.array([k == n for k in keys])
        if test.any():
            yield n, test


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--per-trial", action="store_true")
    ap.add_argument("--rule", choices=("argmin", "1se"), default="argmin",
                    help="how a fold chooses on its training trials (see choose())")
    args = ap.parse_args(argv)
    cands = candidates()
    for which in ("broad", "phones"):
        trs = evalkit.trials(which)
        errs = {label: evalkit.evaluate(which, p) for label, p in cands}   # (n, 3) each
        vqf = evalkit.vqf_errors(which)
        base = errs["defaults"]
        held = np.full_like(base, np.nan)
        chosen = {}
        print(f"\n## {which}: leave one {'kind' if which == 'broad' else 'phone'} out (rule: {args.rule})\n")
        print("| held out | n | chosen on the rest | held-out | defaults | VQF |")
        print("|---|---|---|---|---|---|")
        for name, test in folds(which):
            train = ~test
            best = choose(errs, cands, train, args.rule)
            chosen[name] = best
            held[test] = errs[best][test]
            h, d, v = held[test].mean(0), base[test].mean(0), vqf[test].mean(0)
            print(f"| {name} | {int(test.sum())} | {best} | {h[0]:.2f} ({h[1]:.2f}/{h[2]:.2f}) | "
                  f"{d[0]:.2f} | {v[0]:.2f} ({v[1]:.2f}/{v[2]:.2f}) |")
        h, d, v = held.mean(0), base.mean(0), vqf.mean(0)
        print(f"| **all, held out** | {len(trs)} | | **{h[0]:.2f}** ({h[1]:.2f}/{h[2]:.3f}) | "
              f"{d[0]:.2f} ({d[1]:.2f}/{d[2]:.3f}) | {v[0]:.2f} ({v[1]:.2f}/{v[2]:.3f}) |")
        if which == "broad":
            att = np.array([evalkit.broad_kind(t) == "attached magnet" for t in trs])
            for lab, m in (("without attached magnet", ~att), ("attached magnet", att)):
                a, b, c = held[m].mean(0), base[m].mean(0), vqf[m].mean(0)
                print(f"| {lab} | {int(m.sum())} | | {a[0]:.2f} ({a[1]:.2f}/{a[2]:.2f}) | {b[0]:.2f} | "
                      f"{c[0]:.2f} |")
        print("\n" + evalkit.done_when(which, held, vqf)[0])
        print(f"\nEach parameter alone ({which}, rule: {args.rule}): the folds may change only it; "
              "worst first\n")
        print("| parameter | chosen per fold | held-out | held-out − defaults |")
        print("|---|---|---|---|")
        rows = []
        for k in grid():
            own = [c for c in cands if c[0] == "defaults" or c[0].split(" ")[0] == k]
            one = np.full_like(base, np.nan)
            picks = []
            for _, test in folds(which):
                best = choose(errs, own, ~test, args.rule)
                one[test] = errs[best][test]
                picks.append("=" if best == "defaults" else best.split(" ")[1])
            m = one.mean(0)
            rows.append((m[0] - d[0], k, " ".join(picks), m))
        for delta, k, picks, m in sorted(rows, key=lambda r: -r[0]):
            print(f"| {k} | {picks} | {m[0]:.3f} ({m[1]:.3f}/{m[2]:.3f}) | {delta:+.3f} |")
        if args.per_trial:
            print("\n| trial | held-out | defaults | VQF |\n|---|---|---|---|")
            for t, a, b, c in zip(trs, held, base, vqf):
                print(f"| {t['name']} | {a[0]:.2f} | {b[0]:.2f} | {c[0]:.2f} |")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
