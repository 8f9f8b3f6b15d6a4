"""Cross-validation of a tuning procedure: the five defaults that were set with the shared trials
in view are set again in every fold, from the training trials alone, and the held-out trials are
scored.

Data: BROAD (Laidig, Caruso, Cereatti, Seel, Data 6(7):72, 2021, CC-BY-4.0) and the smartphone
attitude benchmark of Michel, Genevès, Fourati, Layaïda (IEEE PerCom 2017, CeCILL 2.1), read from
``../shared/data``; their metric (total / heading / inclination RMSE per trial, degrees).

``crossval.py`` holds out the choice of one value among ×0.5 / ×1 / ×2 of the defaults, so its
held-out figures still stand on the defaults themselves. Five of robust's defaults were set with
these very trials in view (``REFIT``, the ones ``RobustParams.default_from`` labels "shared
trials"). Here each fold sets all five again by coordinate descent on a grid (×⅛ to ×8 of a
start, √2 apart; passes until one changes nothing; a tie keeps the value nearer the current
one), by the lowest mean total error on its training trials, and then scores the kind (BROAD)
or the phone held out. ``heading_drift_window`` follows them: it is the heading's time
constant, heading_noise / gyr_noise (its default_from).

The start (``start()``) is only partly free of the trials: heading_noise and
mag_norm_gate_rel start from VQF's tauMag (9 s) and magNormTh (10 %), but gyr_noise (0.005)
and refused_turn_noise (0.01) have no outside source and start at the defaults themselves,
and tilt_noise at gyr_noise × VQF's tauAcc, which is its default too. So the whole run is
repeated with every start shifted by a quarter, a half and three quarters of a grid step
(``PHASES``): then no grid point is a default, and the spread over the phases is what the
choice of start is worth. The folds are crossval.py's: BROAD leave one kind out (an attached
magnet its own class), phones leave one phone out. This scores the tuning procedure, not the
shipped defaults; it does not hold out the filter's structure, developed on all the shared
trials, nor the grid's span.

Usage: ``python benchmarks/refit_cv.py [--per-trial] [--phases 0 0.125 ...]`` (about seven
minutes per phase on two cores: half an hour for the four by default).
"""

from __future__ import annotations

import argparse
import math
import sys
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))
sys.path.insert(0, str(ROOT / "benchmarks"))

import evalkit  # noqa: E402
from crossval import folds  # noqa: E402
from app.estimators.robust import RobustParams  # noqa: E402

# the defaults set with the shared trials in view, in the order the descent sets them
REFIT = ("gyr_noise", "tilt_noise", "heading_noise", "refused_turn_noise", "mag_norm_gate_rel")
_LABELLED = {k for k, v in RobustParams.default_from.items() if v.startswith("shared trials")}
if set(REFIT) != _LABELLED:   # the labels in the code are the list: this script follows them
    raise SystemExit(f"refit_cv.REFIT {sorted(REFIT)} is not what RobustParams.default_from labels "
                     f"'shared trials' {sorted(_LABELLED)}: give each a start() and a place in REFIT")
STEPS = tuple(2.0 ** (k / 2.0) for k in range(-6, 7))   # ×⅛ … ×8, √2 apart
PHASES = (0.0, 0.125, 0.25, 0.375)   # the start shifted by 2^phase: 0, ¼, ½, ¾ of a grid step
MAX_PASSES = 6


def start(phase: float = 0.0) -> dict:
    """Where every fold starts, shifted by 2^phase: gyr_noise 0.005 rad/√s and
    refused_turn_noise 0.01 (1 % of a turn per √s) are the defaults (no outside source);
    tilt_noise and heading_noise make the tilt's and the heading's time constants at rest
    VQF's tauAcc (3 s) and tauMag (9 s); mag_norm_gate_rel is VQF's magNormTh (10 %)."""
    g = 0.005
    s0 = {"gyr_noise": g, "tilt_noise": g * 3.0, "heading_noise": g * 9.0,
          "refused_turn_noise": 0.01, "mag_norm_gate_rel": 0.10}
    return {k: v * 2.0 ** phase for k, v in s0.items()}


def with_tied(setting: dict) -> dict:
    """The parameters a run sets: the five, and heading_drift_window, which follows them."""
    return dict(setting, heading_drift_window=setting["heading_noise"] / setting["gyr_noise"])


class Scores:
    """Per-trial errors of each setting of the five, computed once (folds share their paths)."""

    def __init__(self, which: str):
        self.which, self.cache = which, {}

    def __call__(self, setting: dict) -> np.ndarray:
        key = tuple(round(setting[k], 12) for k in REFIT)
        if key not in self.cache:
            self.cache[key] = evalkit.evaluate(self.which, with_tied(setting))
        return self.cache[key]


def refit(scores: Scores, train: np.ndarray, s0: dict) -> tuple[dict, int]:
    """The five set by coordinate descent on the training trials from ``s0``, and the number
    of passes it took (the last one changes nothing; MAX_PASSES + 1: it ran out, and says so)."""
    cur = dict(s0)
    for n in range(1, MAX_PASSES + 1):
        moved = False
        for k in REFIT:
            def cost(c, k=k, was=cur[k]):
                return (scores(c)[train, 0].mean(), abs(math.log(c[k] / was)))
            best = min((dict(cur, **{k: s0[k] * f}) for f in STEPS), key=cost)
            moved |= not math.isclose(best[k], cur[k])
            cur = best
        if not moved:
            return cur, n
    print(f"  (the descent had not converged after {MAX_PASSES} passes)")
    return cur, MAX_PASSES + 1


def steps_of(setting: dict) -> str:
    d = RobustParams()
    return ", ".join(f"{k} {setting[k]:.3g}" + (" (default)" if math.isclose(setting[k], getattr(d, k))
                                               else "") for k in REFIT)


def run_phase(phase: float, scores: dict, per_trial: bool) -> dict:
    """One whole cross-validation with the start shifted by 2^phase; prints its tables and
    returns its figures per set."""
    s0 = start(phase)
    print(f"\n# start shifted by 2^{phase:g}: " + ", ".join(f"{k} {v:.3g}" for k, v in s0.items()))
    out = {}
    for which in ("broad", "phones"):
        trs = evalkit.trials(which)
        base = evalkit.evaluate(which)
        at_start = scores[which](s0)
        vqf = evalkit.vqf_errors(which)
        held = np.full_like(base, np.nan)
        passes = []
        print(f"\n## {which}: leave one {'kind' if which == 'broad' else 'phone'} out, the five set "
              "again in each fold\n")
        print("| held out | n | set on the rest | held-out | defaults | start | VQF |")
        print("|---|---|---|---|---|---|---|")
        for name, test in folds(which):
            chosen, n = refit(scores[which], ~test, s0)
            passes.append(n)
            held[test] = scores[which](chosen)[test]
            h, b, st, v = (x[test].mean(0) for x in (held, base, at_start, vqf))
            print(f"| {name} | {int(test.sum())} | {steps_of(chosen)} | {h[0]:.2f} "
                  f"({h[1]:.2f}/{h[2]:.2f}) | {b[0]:.2f} | {st[0]:.2f} | {v[0]:.2f} ({v[1]:.2f}/{v[2]:.2f}) |")
        h, b, st, v = (x.mean(0) for x in (held, base, at_start, vqf))
        print(f"| **all, held out** | {len(trs)} | | **{h[0]:.2f}** ({h[1]:.2f}/{h[2]:.3f}) | "
              f"{b[0]:.2f} ({b[1]:.2f}/{b[2]:.3f}) | {st[0]:.2f} ({st[1]:.2f}/{st[2]:.3f}) | "
              f"{v[0]:.2f} ({v[1]:.2f}/{v[2]:.3f}) |")
        if which == "broad":
            att = np.array([evalkit.broad_kind(t) == "attached magnet" for t in trs])
            for lab, m in (("without attached magnet", ~att), ("attached magnet", att)):
                a, bb, ss, c = (x[m].mean(0) for x in (held, base, at_start, vqf))
                print(f"| {lab} | {int(m.sum())} | | {a[0]:.2f} ({a[1]:.2f}/{a[2]:.2f}) | {bb[0]:.2f} | "
                      f"{ss[0]:.2f} | {c[0]:.2f} |")
        line, ok = evalkit.done_when(which, held, vqf)
        print(f"\n{line}; the start alone: {st[0] / v[0]:.3f} × VQF; passes per fold {passes}")
        if per_trial:
            print("\n| trial | held-out | defaults | start | VQF |\n|---|---|---|---|---|")
            for t, a, bb, ss, c in zip(trs, held, base, at_start, vqf):
                print(f"| {t['name']} | {a[0]:.2f} | {bb[0]:.2f} | {ss[0]:.2f} | {c[0]:.2f} |")
        out[which] = dict(ratio=h[0] / v[0], incl=h[2], vqf_incl=v[2], start=st[0] / v[0],
                          base=b[0] / v[0], ok=ok)
    return out


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--per-trial", action="store_true", help="per trial, for the first phase")
    ap.add_argument("--phases", nargs="+", type=float, default=list(PHASES),
                    help="shifts of the start, in powers of 2 (a grid step is 0.5)")
    args = ap.parse_args(argv)
    d = RobustParams()
    print("defaults: " + ", ".join(f"{k} {getattr(d, k):.3g}" for k in REFIT))
    scores = {w: Scores(w) for w in ("broad", "phones")}
    res = [(ph, run_phase(ph, scores, args.per_trial and i == 0)) for i, ph in enumerate(args.phases)]
    print("\n## Over the starts\n")
    print("| start shifted by | BROAD held-out × VQF (incl.) | phones held-out × VQF (incl.) | "
          "start alone: BROAD, phones | within issue 19's bounds |")
    print("|---|---|---|---|---|")
    for ph, r in res:
        b, p = r["broad"], r["phones"]
        print(f"| 2^{ph:g} | {b['ratio']:.3f} ({b['incl']:.3f}°) | {p['ratio']:.3f} ({p['incl']:.3f}°) | "
              f"{b['start']:.3f}, {p['start']:.3f} | {'yes' if b['ok'] and p['ok'] else 'NO'} |")
    b0, p0 = res[0][1]["broad"], res[0][1]["phones"]
    print(f"| (the defaults, not held out) | {b0['base']:.3f} | {p0['base']:.3f} | | |")
    rb = [r["broad"]["ratio"] for _, r in res]
    rp = [r["phones"]["ratio"] for _, r in res]
    print(f"\nheld-out / VQF over {len(res)} starts: BROAD {min(rb):.3f}–{max(rb):.3f} (VQF's inclination "
          f"{b0['vqf_incl']:.3f}°), phones {min(rp):.3f}–{max(rp):.3f}; within the bounds in "
          f"{sum(r['broad']['ok'] and r['phones']['ok'] for _, r in res)} of {len(res)}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
