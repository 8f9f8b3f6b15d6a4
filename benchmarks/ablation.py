"""Ablation and sensitivity of robust's defaults on the shared BROAD and phone trials.

Data: BROAD (Laidig, Caruso, Cereatti, Seel, Data 6(7):72, 2021, CC-BY-4.0) and the smartphone
attitude benchmark of Michel, Genevès, Fourati, Layaïda (IEEE PerCom 2017, CeCILL 2.1), read from
``../shared/data``; their metric (total RMSE per trial, degrees, mean over trials).

1. **Ablation**: each mechanism switched off (its parameter at its "off" value), the change of the
   mean total error on BROAD (all 17, and the 14 without an attached magnet, and the 3 with one:
   one attached-magnet trial moves a 17-trial mean by 0.1-0.4°) and on the 42 phone trials.
2. **Sensitivity**: every numeric parameter at ×0.5 and ×2, likewise. A default at a sharp optimum
   shows as both columns clearly positive; the run ends with the list of those where both cost
   more than ``SHARP`` (2 %) of the defaults' mean, on BROAD's 17 or on the phones' 42.
3. **The rule's reference** (``--only vqf``): VQF's published defaults (Laidig and Seel 2023, its
   ``params``) through the same ×0.5 / ×2 and the same rule on the same trials: how a filter
   whose defaults were not chosen on these trials looks to it.

Usage: ``python benchmarks/ablation.py [--only ablation|sensitivity|vqf] [--params NAME ...]``
(two worker processes; the whole run takes a few minutes on two cores).
"""

from __future__ import annotations

import argparse
import sys
from dataclasses import fields
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))
sys.path.insert(0, str(ROOT / "benchmarks"))

import evalkit  # noqa: E402
from app.estimators.robust import RobustParams  # noqa: E402

# mechanism -> the parameter change that switches it off
MECHANISMS = {
    "hard iron tracking (issue 19)": {"hard_iron_window": 0.0},
    "strength gate": {"mag_norm_gate_rel": 0.0},
    "dip gate": {"mag_dip_gate": 0.0},
    "field turn test": {"mag_turn_gate": 0.0},
    "heading noise from the field's deviation (mag_dev_weight)": {"mag_dev_weight": 0.0},
    "heading noise from the field's wander (evidence)": {"heading_evidence_tau": 0.0},
    "both off, heading_noise back to 0.15 (before item 2)": {"heading_evidence_tau": 0.0,
                                                             "mag_dev_weight": 0.0,
                                                             "heading_noise": 0.15},
    "never lost (recover)": {"mag_lost_time": 0.0},
    "new field acceptance": {"mag_new_field_time": 600.0},
    "refused-turn heading noise": {"refused_turn_noise": 0.0},
    "scale-factor tilt noise": {"gyr_scale_noise": 0.0},
    "tilt loop damping": {"tilt_damping": 0.0},
    "bias from tilt corrections": {"bias_motion_noise": 0.0},
    "bias from the heading's drift": {"heading_drift_window": 0.0},
    "rest detection": {"rest_time": 0.0},
    "bias reset (bias_max)": {"bias_max": 0.0},
    "acc flags": {"acc_flag_angle": 0.0, "acc_flag_rel": 0.0},
    "field delay compensation (mag_delay 0)": {"mag_delay": 0.0},
    "(another value) field delay 3.5 ms instead of 5 ms": {"mag_delay": 0.0035},
    "accelerometer lag compensation (acc_delay_periods 0)": {"acc_delay_periods": 0.0},
}

# not scaled: switches, sensor selection, initial conditions without a physical scale
SKIP = {"use_gyr", "use_acc", "use_mag", "gyr_bias", "max_gap", "gyr_hold", "acc_band_rel",
        "update_rate_hz", "acc_flag_angle", "acc_flag_rel"}


# a default "at a sharp optimum": ×0.5 and ×2 both cost more than this share of the defaults' mean
SHARP = 0.02

_RUNS: dict = {}


def per_trial(which: str, params: dict | None = None, method: str = "robust") -> np.ndarray:
    """Total RMSE per trial (each setting run once per process: the sensitivity's runs are
    read again for where its costs lie)."""
    key = (which, method, tuple(sorted((params or {}).items())))
    if key not in _RUNS:
        _RUNS[key] = evalkit.evaluate(which, params, method=method)[:, 0]
    return _RUNS[key]


def summary(params: dict | None) -> tuple[float, float, float, float]:
    b, ph = per_trial("broad", params), per_trial("phones", params)
    att = np.array(["attached magnet" == evalkit.broad_kind(t) for t in evalkit.trials("broad")])
    return b.mean(), b[~att].mean(), b[att].mean(), ph.mean()


def sharp_at(costs, base, cols) -> list[tuple[str, float, float]]:
    """The sides ``(where, ×0.5 cost, ×2 cost)`` at a sharp optimum: both costs above ``SHARP``
    of the defaults' mean there; ``costs`` holds the ×0.5 and ×2 changes, ``cols`` maps a
    column of them to its set's name."""
    if len(costs) != 2:
        return []
    return [(where, costs[0][c], costs[1][c]) for c, where in cols
            if min(costs[0][c], costs[1][c]) > SHARP * base[c]]


def row(label, s, base):
    d = [x - y for x, y in zip(s, base)]
    return (f"| {label} | {s[0]:.2f} ({d[0]:+.2f}) | {s[1]:.2f} ({d[1]:+.2f}) | "
            f"{s[2]:.2f} ({d[2]:+.2f}) | {s[3]:.2f} ({d[3]:+.2f}) |")


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--only", choices=("ablation", "sensitivity", "vqf"))
    ap.add_argument("--params", nargs="*", help="sensitivity of these parameters only")
    args = ap.parse_args(argv)
    if args.only == "vqf":
        vqf_reference()
        return 0
    base = summary(None)
    head = ("| {} | BROAD, 17 | BROAD, 14 without attached magnet | BROAD attached magnet, 3 | phones, 42 |\n"
            "|---|---|---|---|---|")
    print("total RMSE (°), mean over trials; in brackets the change from the defaults\n")
    if args.only in (None, "ablation"):
        print("Ablation (each mechanism off):\n")
        print(head.format("mechanism off"))
        print(row("defaults", base, base))
        for label, change in MECHANISMS.items():
            print(row(label, summary(change), base), flush=True)
        print()
    if args.only in (None, "sensitivity"):
        print("Sensitivity (each parameter ×0.5 / ×2):\n")
        print("| parameter | default | ×0.5: BROAD 17 / 14 / 3, phones | ×2: BROAD 17 / 14 / 3, phones |")
        print("|---|---|---|---|")
        d = RobustParams()
        sharp = []
        for f in fields(RobustParams):
            v = getattr(d, f.name)
            if f.name in SKIP or isinstance(v, (bool, tuple)) or not isinstance(v, float) or v == 0.0:
                continue
            if args.params and f.name not in args.params:
                continue
            cells, costs = [], []
            for k in (0.5, 2.0):
                try:
                    s = summary({f.name: v * k})
                except Exception as e:  # a value outside the parameter's range
                    cells.append(f"({type(e).__name__})")
                    continue
                dd = [x - y for x, y in zip(s, base)]
                costs.append(dd)
                cells.append(" / ".join(f"{x:+.2f}" for x in dd))
            print(f"| `{f.name}` | {v:.4g} | {cells[0]} | {cells[1]} |", flush=True)
            sharp += [(f.name, v, *side) for side in sharp_at(costs, base, ((0, "BROAD"), (3, "phones")))]
        print(f"\nAt a sharp optimum (×0.5 and ×2 both cost more than {SHARP:.0%} of the defaults' "
              f"mean): {', '.join(f'{n} on {w} ({a:+.2f} / {b:+.2f})' for n, _, w, a, b in sharp) or 'none'}")
        if sharp:
            concentration(sharp)
    return 0


def concentration(sharp) -> None:
    """For each default at a sharp optimum: how much of each side's cost three trials carry
    (the issue's complaint: a value decided by the chance refusal and acceptance windows of a
    few trials), and the mean change over the others."""
    print("\nWhere each of those costs lies (the three trials that change most; the mean change "
          "over the rest; the mean change ± its standard error over the trials, paired):\n")
    print("| parameter | on | ×0.5: three trials / the rest | ×2: three trials / the rest | "
          "×0.5: mean ± SE | ×2: mean ± SE |")
    print("|---|---|---|---|---|---|")
    for name, v, where, _, _ in sharp:
        which = "broad" if where == "BROAD" else "phones"
        cells, se = [], []
        for k in (0.5, 2.0):
            d = per_trial(which, {name: v * k}) - per_trial(which)
            top = np.argsort(-np.abs(d))[:3]
            rest = np.setdiff1d(np.arange(len(d)), top)
            cells.append(f"{d[top].sum():+.2f} of {d.sum():+.2f} / {d[rest].mean():+.3f}")
            se.append(f"{d.mean():+.2f} ± {d.std(ddof=1) / np.sqrt(len(d)):.2f}")
        print(f"| `{name}` | {where} | {cells[0]} | {cells[1]} | {se[0]} | {se[1]} |", flush=True)


def vqf_reference() -> None:
    """VQF's published defaults through the same sensitivity and the same rule."""
    from vqf import VQF

    base = [per_trial(w, method="VQF").mean() for w in ("broad", "phones")]
    print(f"VQF's defaults: BROAD {base[0]:.2f}, phones {base[1]:.2f}\n")
    print("| VQF parameter | default | ×0.5: BROAD, phones | ×2: BROAD, phones |")
    print("|---|---|---|---|")
    sharp = []
    for name, v in VQF(0.01).params.items():
        if isinstance(v, bool) or not v:
            continue
        costs = [[per_trial(w, {name: v * k}, method="VQF").mean() - b
                  for w, b in zip(("broad", "phones"), base)] for k in (0.5, 2.0)]
        print(f"| `{name}` | {v:g} | {costs[0][0]:+.2f}, {costs[0][1]:+.2f} | "
              f"{costs[1][0]:+.2f}, {costs[1][1]:+.2f} |", flush=True)
        sharp += [f"{name} on {w} ({a:+.2f} / {b:+.2f})"
                  for w, a, b in sharp_at(costs, base, ((0, "BROAD"), (1, "phones")))]
    print(f"\nVQF at a sharp optimum (the same rule): {', '.join(sharp) if sharp else 'none'}")


if __name__ == "__main__":
    raise SystemExit(main())
