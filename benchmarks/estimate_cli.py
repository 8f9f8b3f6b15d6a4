"""Benchmark of ``orientlab estimate`` on a long recording: speed and bounded memory.

Generates a one-hour 100 Hz CSV (360 000 rows: smooth 3D rotation with walking-like
accelerations, sensor noise and a gyroscope bias) in a temporary directory, runs
``orientlab estimate`` on it with the default filter in a child process, and prints

- the wall time of the whole command (reading, estimating, writing),
- the CLI's own ``N samples in S s (R samples/s)`` line (estimation time only),
- the peak resident memory of the child (``resource.getrusage(RUSAGE_CHILDREN)``),
  beside the input and output file sizes.

The same is first done on a file a quarter as long (90 000 rows, still several chunks):
the peak memory of the one-hour run is about that of the short one, i.e. it does not
grow with the file (the CLI processes the file in chunks). Usage:
``.venv/bin/python benchmarks/estimate_cli.py [--minutes 60] [--filter NAME]``.
"""

from __future__ import annotations

import argparse
import resource
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import numpy as np

REPO = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(REPO))
from app.quaternion import quat_conj_many, quat_from_rotvec_many, quat_mul_many, rotate_inv_many  # noqa: E402

FS = 100.0


def _axis_angle(axis: int, angle: np.ndarray) -> np.ndarray:
    return quat_from_rotvec_many(np.outer(angle, np.eye(3)[axis]))


def make_recording(path: Path, n: int, seed: int = 0) -> None:
    """Write ``n`` rows of realistic phone motion at 100 Hz to ``path`` (CSV)."""
    rng = np.random.default_rng(seed)
    t = np.arange(n + 1) / FS
    yaw = 0.8 * np.sin(2 * np.pi * t / 47.0) + 0.002 * t
    pitch = 0.5 * np.sin(2 * np.pi * t / 13.0) * np.sin(2 * np.pi * t / 310.0)
    roll = 0.3 * np.sin(2 * np.pi * t / 7.3 + 1.0)
    q = quat_mul_many(quat_mul_many(_axis_angle(2, yaw), _axis_angle(0, pitch)), _axis_angle(1, roll))
    dq = quat_mul_many(quat_conj_many(q[:-1]), q[1:])       # body-frame increment
    gyr = 2.0 * dq[:, 1:] * FS
    q, t = q[:-1], t[:-1]
    lin = 0.6 * np.stack([np.sin(2 * np.pi * 1.8 * t), np.cos(2 * np.pi * 1.8 * t),
                          np.sin(2 * np.pi * 3.6 * t)], axis=1)     # walking-like, world
    acc = rotate_inv_many(q, np.array([0.0, 0.0, 9.81]) + lin)
    mag = rotate_inv_many(q, np.array([0.0, 15.0, -45.0]))
    gyr += [0.01, -0.02, 0.005] + rng.normal(0, 0.003, (n, 3))
    acc += rng.normal(0, 0.05, (n, 3))
    mag += rng.normal(0, 0.4, (n, 3))
    data = np.column_stack([t, gyr, acc, mag])
    header = "t,gyr_x,gyr_y,gyr_z,acc_x,acc_y,acc_z,mag_x,mag_y,mag_z"
    np.savetxt(path, data, delimiter=",", header=header, comments="", fmt="%.6f")


def run(src: Path, out: Path, name: str | None) -> tuple[float, str, int]:
    """(wall s, the CLI's samples/s line, peak RSS of the children so far in MB)."""
    cmd = [sys.executable, "-m", "app.cli", "estimate", str(src), "--out", str(out), "--quiet"]
    if name:
        cmd += ["--filter", name]
    t0 = time.perf_counter()
    proc = subprocess.run(cmd, cwd=REPO, capture_output=True, text=True)
    wall = time.perf_counter() - t0
    if proc.returncode != 0:
        sys.exit(f"orientlab estimate failed: {proc.stderr.strip()}")
    line = proc.stderr.strip().splitlines()[-1]
    peak_mb = resource.getrusage(resource.RUSAGE_CHILDREN).ru_maxrss / 1024.0
    return wall, line, int(peak_mb)


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--minutes", type=float, default=60.0, help="length of the long file")
    ap.add_argument("--filter", default=None, help="estimator (default: the CLI's default)")
    args = ap.parse_args()
    with tempfile.TemporaryDirectory(prefix="orientlab-bench-") as tmp:
        tmp = Path(tmp)
        print(f"{'rows':>8} {'input MB':>9} {'output MB':>10} {'wall s':>8} "
              f"{'peak RSS MB':>12}  CLI line")
        for minutes in (args.minutes / 4.0, args.minutes):
            n = int(round(minutes * 60 * FS))
            src, out = tmp / f"in_{n}.csv", tmp / f"out_{n}.csv"
            make_recording(src, n)
            wall, line, peak = run(src, out, args.filter)
            print(f"{n:>8} {src.stat().st_size / 1e6:>9.1f} {out.stat().st_size / 1e6:>10.1f} "
                  f"{wall:>8.2f} {peak:>12}  {line}", flush=True)
            src.unlink()
            out.unlink()
    print("peak RSS is the maximum over the child processes so far: equal figures for "
          "both files mean memory does not grow with the file.")


if __name__ == "__main__":
    main()
