"""Where the default filter finds and removes a magnet on the phone, on every shared trial.

For each trial (BROAD's 17, the phones' 42; ``../shared/data``) the default ``robust`` runs
sample by sample, and every half second while it has a field reference its offset fit is read:
the share of those moments the offset is *tracking* (found, not removed) and *applied*
(removed: flag ``offset``), the offset's size, and how many times as far from the learned
strength the raw field is as the corrected one (the square root of the ratio of their
low-passed squared deviations, the quantity ``hard_iron_ratio`` is compared with; the median
over the moments of each status). Trials where nothing was found are summed up in one line.

Then the simulator (no data needed): the turning phone of ``tests/estimators/test_hard_iron.py``
(``harness.magnet_rows``: 126 s of turns about each axis, a 0.5 °/s gyroscope bias about z) with
a magnet of each size stuck on it from 30 s to 100 s: the heading's RMS error from 60 s to 100 s with the tracking
and without it (``hard_iron_window=0``), and the share of those samples with the offset removed.

Usage: ``python benchmarks/hard_iron.py [--which broad|phones|sim]``.
"""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))
sys.path.insert(0, str(ROOT / "benchmarks"))
sys.path.insert(0, str(ROOT / "tests"))          # harness: the simulator's magnet scenario

from accuracy_phones import BROAD, PHONES, load_broad, load_phones  # noqa: E402
from app.estimators import make_estimator  # noqa: E402
from app.estimators.base import NFLAGS  # noqa: E402
from app.estimators.robust.hardiron import HI_APPLIED, HI_TRACKING  # noqa: E402
from app.estimators.robust.kernel import robust_step  # noqa: E402
from app.estimators.robust.state import S  # noqa: E402

EVERY_S = 0.5
SIM_MAGNETS_UT = (6.0, 8.0, 9.0, 10.0, 12.0, 15.0, 30.0)


def trace(tr: dict) -> np.ndarray:
    """Rows (status, ratio, |offset| µT) every EVERY_S while a field reference is learned."""
    est = make_estimator("robust")
    s, P, p = est._s, est._P, est._p          # the kernel's own arrays: stepped as run() does
    f = np.empty(NFLAGS)
    every = max(1, int(round(EVERY_S * tr["fs"])))
    out = []
    for k in range(len(tr["t"])):
        f[:] = np.nan
        robust_step(s, P, p, tr["t"][k], tr["gyr"][k], tr["acc"][k], tr["mag"][k], f)
        if k % every == 0 and s[S.ref_ok] != 0.0:
            ratio = np.sqrt(s[S.hi_dev_raw] / max(s[S.hi_dev_cor], 1e-12))
            out.append((s[S.hi_status], ratio, float(np.linalg.norm(s[S.hi_o:S.hi_o + 3]))))
    return np.array(out).reshape(-1, 3)


def _med(x: np.ndarray) -> str:
    return f"{np.median(x):6.1f}" if len(x) else "     -"


def report(label: str, trials: list[dict]) -> None:
    print(f"{label}: share of the time with a field reference; ratio = raw / corrected rms "
          f"deviation from the learned strength (median)")
    print(f"  {'trial':<46} {'tracking':>8} {'applied':>8} {'ratio tr.':>9} {'ratio ap.':>9} {'|o| ap. µT':>10}")
    quiet = []
    for tr in trials:
        R = trace(tr)
        if len(R) == 0:
            quiet.append(tr["name"])
            continue
        tk, ap = R[:, 0] == HI_TRACKING, R[:, 0] == HI_APPLIED
        if not tk.any() and not ap.any():
            quiet.append(tr["name"])
            continue
        print(f"  {tr['name'][:46]:<46} {100 * tk.mean():7.0f}% {100 * ap.mean():7.0f}% "
              f"{_med(R[tk, 1]):>9} {_med(R[ap, 1]):>9} {_med(R[ap, 2]):>10}")
    print(f"  no offset found on {len(quiet)} trials\n")


def simulator() -> None:
    from app.estimators import Reason
    from app.estimators.base import F_MAG
    from app.quaternion import error_angles
    from harness import MAGNET_OFF_S, MAGNET_ON_S, magnet_rows

    base, truth = magnet_rows(0.0)
    late = (base.t > MAGNET_ON_S + 30.0) & (base.t < MAGNET_OFF_S)
    has = np.isfinite(base.mag[:, 0])
    print(f"simulator: a magnet on the turning phone from {MAGNET_ON_S:.0f} s to {MAGNET_OFF_S:.0f} s "
          f"(field {np.nanmean(np.linalg.norm(base.mag, axis=1)):.0f} µT); heading RMS error "
          f"{MAGNET_ON_S + 30:.0f}-{MAGNET_OFF_S:.0f} s")
    print(f"  {'magnet µT':>9} {'tracked °':>10} {'not tracked °':>14} {'removed':>8}")
    for size in SIM_MAGNETS_UT:
        rows, _ = magnet_rows(size)
        out = []
        for params in ({}, {"hard_iron_window": 0.0}):
            r = make_estimator("robust", params).run(rows.t, rows.gyr, rows.acc, rows.mag, rows.ori)
            _, h, _ = error_angles(r.q[late], truth[late])
            out.append((float(np.degrees(np.sqrt(np.mean(h ** 2)))),
                        float(np.mean(r.flags[late & has, F_MAG] == Reason.OFFSET))))
        print(f"  {size:9.0f} {out[0][0]:10.1f} {out[1][0]:14.1f} {100 * out[0][1]:7.0f}%")
    print()


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--which", choices=("broad", "phones", "sim"))
    args = ap.parse_args(argv)
    found = False
    if args.which in (None, "broad") and (BROAD / "trials.json").is_file():
        found = True
        report("BROAD", load_broad())
    if args.which in (None, "phones") and (PHONES / "trials.json").is_file():
        found = True
        report("phones", load_phones())
    if not found and args.which != "sim":
        print("no shared trials under ../shared/data: nothing to measure there.\n")
    if args.which in (None, "sim"):
        simulator()
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
