"""Where the default filter finds and removes a magnet on the phone, on every shared trial.

For each trial (BROAD's 17, the phones' 42; ``../shared/data``) the default ``robust`` runs
sample by sample, and every half second while it has a field reference its offset fit is read:
the share of those moments the offset is *tracking* (found, not removed) and *applied*
(removed: flag ``offset``), the offset's size, and how many times as far from the learned
strength the raw field is as the corrected one (the square root of the ratio of their
low-passed squared deviations, the quantity ``hard_iron_ratio`` is compared with; the median
over the moments of each status). Trials where nothing was found are summed up in one line.

Usage: ``python benchmarks/hard_iron.py [--which broad|phones]``.
"""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))
sys.path.insert(0, str(ROOT / "benchmarks"))

from accuracy_phones import BROAD, PHONES, load_broad, load_phones  # noqa: E402
from app.estimators import make_estimator  # noqa: E402
from app.estimators.base import NFLAGS  # noqa: E402
from app.estimators.robust.hardiron import HI_APPLIED, HI_TRACKING  # noqa: E402
from app.estimators.robust.kernel import robust_step  # noqa: E402
from app.estimators.robust.state import S  # noqa: E402

EVERY_S = 0.5


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


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--which", choices=("broad", "phones"))
    args = ap.parse_args(argv)
    found = False
    if args.which in (None, "broad") and (BROAD / "trials.json").is_file():
        found = True
        report("BROAD", load_broad())
    if args.which in (None, "phones") and (PHONES / "trials.json").is_file():
        found = True
        report("phones", load_phones())
    if not found:
        print("no shared trials under ../shared/data: nothing to measure.")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
