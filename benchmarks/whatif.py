"""What-if re-run speed: a 10-minute 100 Hz recording re-run through every estimator.

Writes a log of the simulated phone (ACC, GYR and ORI at 100 Hz, MAG at 50 Hz: 210 000
lines for 10 minutes) to a temporary folder, then times :func:`app.whatif.rerun` with
every estimator (``robust``, ``lab``, ``complementary``, ``phone`` and the variant
``robust-no-rejection``), once without a patch and once with a patch for ``robust``
(so it runs twice). Prints the rows, the recording's duration, the time spent reading
the log and estimating, per estimator the CPU time, and the ratio to real time
(target: >= 300x), for the whole re-run from the file and for a re-run of the log
already parsed (the server keeps the last two parsed recordings: a what-if is repeated
with new parameters). A warm-up run on a short log first, so numba's compilation is not
counted. Usage: ``python benchmarks/whatif.py [--minutes 10] [--repeat 3]``.
"""

from __future__ import annotations

import argparse
import sys
import tempfile
import time
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))
from app.estimators import NAMES  # noqa: E402
from app.readers import read_recording  # noqa: E402
from app.simulate import Simulation, format_line, stream  # noqa: E402
from app.variants import no_rejection_changes  # noqa: E402
from app.whatif import rerun  # noqa: E402


def write_log(path: Path, seconds: float) -> int:
    boot = Simulation().config.boot_ms
    n = 0
    with open(path, "w") as fh:
        for ms, tag, vals in stream(1):
            if ms - boot > seconds * 1000:
                break
            fh.write(format_line(ms, tag, vals) + "\n")
            n += 1
    return n


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--minutes", type=float, default=10.0)
    ap.add_argument("--repeat", type=int, default=3)
    args = ap.parse_args()
    specs = {n: (n, {}) for n in NAMES}
    specs["robust-no-rejection"] = ("robust", no_rejection_changes("robust"))
    with tempfile.TemporaryDirectory() as d:
        warm = Path(d) / "warm.txt"
        write_log(warm, 5.0)
        rerun(warm, specs, patch={"robust": {"mag_norm_gate_rel": 0.1}})
        log = Path(d) / "ten_minutes.txt"
        lines = write_log(log, args.minutes * 60.0)
        print(f"log: {lines} lines, {log.stat().st_size / 1e6:.1f} MB, "
              f"{args.minutes:g} min of the simulated phone")
        for patch in (None, {"robust": {"mag_norm_gate_rel": 0.1}}):
            best = None
            for _ in range(args.repeat):
                t0 = time.perf_counter()
                out = rerun(log, specs, patch=patch)
                wall = time.perf_counter() - t0
                if best is None or wall < best[0]:
                    best = (wall, out)
            wall, out = best
            label = "no patch" if patch is None else "patch robust.mag_norm_gate_rel=0.1 (robust runs twice)"
            dur = out["duration_s"]
            print(f"\n{label}: {out['rows']} rows, {dur:.1f} s of recording, "
                  f"{len(specs)} estimators (best of {args.repeat})")
            for name, e in out["estimators"].items():
                if e.get("reference"):
                    print(f"  {name:<22}   (the reference itself: its held ORI is scored, not re-run)")
                    continue
                cpu = e["before"]["seconds_cpu"] + (e["after"]["seconds_cpu"] if e["after"] else 0.0)
                print(f"  {name:<22} {cpu:7.3f} s  ({out['rows'] / e['before']['seconds_cpu'] / 1e3:7.0f} k rows/s per run)")
            print(f"  reading the log        {out['read_s']:7.3f} s")
            print(f"  estimating (all)       {out['estimate_s']:7.3f} s  -> {dur / out['estimate_s']:.0f}x real time")
            print(f"  whole re-run (wall)    {wall:7.3f} s  -> {dur / wall:.0f}x real time  (target >= 300x)")
            # what the server does for a repeated what-if: the parsed log is kept
            rec = read_recording(log)
            best_c = None
            for _ in range(args.repeat):
                t0 = time.perf_counter()
                rerun(rec, specs, patch=patch)
                w = time.perf_counter() - t0
                best_c = w if best_c is None else min(best_c, w)
            print(f"  re-run of the parsed log (the server keeps it; wall) {best_c:7.3f} s  -> "
                  f"{dur / best_c:.0f}x real time  (target >= 300x)")


if __name__ == "__main__":
    main()
