"""How fast the gyroscope turns the heading in motion: the physics behind ``heading_drift_window``.

For every trial with optical truth (BROAD's research IMU, the phones of phones-tyrex), robust
runs with its defaults but the magnetometer off (``use_mag=False``): the heading is then the
gyroscope's, its bias learned only at rest and from the tilt corrections. A line fitted to the
signed heading error against the truth over the evaluated samples gives the drift rate about
the vertical (°/s) and the residual about it. A drift that is a line in time is a bias the rest
did not teach (a MEMS gyroscope's bias in motion is not the one at rest); a large residual is
something else (scale error in turns, a tilt error).

Usage: ``python benchmarks/heading_drift.py`` (reads ``../shared/data``; skips what is absent).
"""

from __future__ import annotations

import sys
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))
sys.path.insert(0, str(ROOT / "benchmarks"))

import evalkit  # noqa: E402
from accuracy_phones import BROAD, PHONES  # noqa: E402
from app.estimators import make_estimator  # noqa: E402

DEG = 180.0 / np.pi


def drift(trial: dict) -> tuple[float, float]:
    """(drift rate °/s, rms residual °) of the heading with the magnetometer off."""
    q = make_estimator("robust", {"use_mag": False}).run(trial["t"], trial["gyr"], trial["acc"],
                                                         trial["mag"]).q
    ref = trial["ref"]
    m = trial["mask"] & np.all(np.isfinite(ref), axis=1) & np.all(np.isfinite(q), axis=1)
    e = np.unwrap(evalkit.heading_error(q[m], ref[m]))
    t = trial["t"][m] - trial["t"][m][0]
    a = np.stack([np.ones_like(t), t], axis=1)
    c, *_ = np.linalg.lstsq(a, e, rcond=None)
    return float(c[1] * DEG), float(np.std(e - a @ c) * DEG)


def main() -> int:
    for which, path in (("broad", BROAD), ("phones", PHONES)):
        if not Path(path).exists():
            print(f"{which}: the shared data is not here ({path}): skipped")
            continue
        rows = []
        print(f"\n{which}: heading drift with the magnetometer off (°/s), rms residual about the line (°)")
        for tr in evalkit.trials(which):
            rate, res = drift(tr)
            kind = evalkit.broad_kind(tr) if which == "broad" else tr["name"].split("_")[0]
            rows.append((kind, rate))
            print(f"  {tr['name'][:46]:<46} {rate:+7.3f}   {res:5.2f}")
        print(f"  {which}: median |drift| per group")
        for kind in dict.fromkeys(k for k, _ in rows):
            r = [abs(v) for k, v in rows if k == kind]
            print(f"    {kind:<24} {np.median(r):.3f} °/s  (n {len(r)})")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
