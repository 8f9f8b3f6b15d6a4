"""A phone that lies on a laptop when the stream starts: how soon the room's field takes over.

The simulator's phone (``tests/harness.py``, ``laptop_rows``) lies still for 8 s, then turns
about each axis for 72 s. Until it is picked up (10 s) a field fixed in the world is added to
the earth's 50 µT (the laptop's, or a steel desk's). The default ``robust`` takes the first field
that holds steady for 5 s as its reference; seen from one attitude, the laptop's field is as
steady as the earth's. For each laptop field: when the room's field became the reference (flag
``new_field``), and the heading's RMS error over the stretches that follow.

Usage: ``python benchmarks/first_field.py``.
"""

from __future__ import annotations

import sys
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))
sys.path.insert(0, str(ROOT / "tests"))          # harness: the simulator's laptop scenario

from app.estimators import Reason, make_estimator  # noqa: E402
from app.estimators.base import F_MAG  # noqa: E402
from app.quaternion import error_angles  # noqa: E402
from harness import LAPTOP_LIFT_S, laptop_rows  # noqa: E402

FIELDS_UT = ((30.0, 0.0, -20.0), (100.0, 50.0, -80.0), (0.0, 20.0, 30.0), (20.0, 20.0, 0.0),
             (10.0, 0.0, -5.0))
SPANS_S = ((0.0, LAPTOP_LIFT_S), (LAPTOP_LIFT_S, 20.0), (20.0, 30.0), (30.0, 50.0), (50.0, 80.0))


def main() -> None:
    print(f"phone on a laptop until {LAPTOP_LIFT_S:.0f} s (turning from 8 s): heading RMS error (deg)")
    head = " ".join(f"{a:>4.0f}-{b:<3.0f}s" for a, b in SPANS_S)
    print(f"  {'laptop field (µT, ENU)':<24}{'|m| µT':>7}  {'new field at':>12}  {head}")
    earth = np.array([0.0, 50.0 * np.cos(np.radians(65.0)), -50.0 * np.sin(np.radians(65.0))])
    for f in FIELDS_UT:
        rows, truth = laptop_rows(f)
        res = make_estimator("robust").run(rows.t, rows.gyr, rows.acc, rows.mag, rows.ori)
        h = np.abs(error_angles(res.q, truth)[1]) * 180.0 / np.pi
        new = rows.t[res.flags[:, F_MAG] == Reason.NEW_FIELD]
        at = f"{new[0]:.1f} s" if len(new) else "never"
        spans = " ".join(f"{np.sqrt(np.mean(h[(rows.t >= a) & (rows.t < b)] ** 2)):>10.1f}"
                         for a, b in SPANS_S)
        label = ", ".join(f"{x:g}" for x in f)
        print(f"  {label:<24}{np.linalg.norm(earth + f):>7.1f}  {at:>12}  {spans}")


if __name__ == "__main__":
    main()
