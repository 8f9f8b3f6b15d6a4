"""What-if re-run speed: a 10-minute 100 Hz recording re-run through every estimator.

Writes a log of the simulated phone (ACC, GYR and ORI at 100 Hz, MAG at 50 Hz: 201 000
lines for 10 minutes) to a temporary folder, then times :func:`app.toolkit.whatif.rerun` with
every estimator (``robust``, ``lab``, ``complementary``, ``phone`` and the variant
``robust-no-rejection``), once without a patch and once with a patch for ``robust``
(so it runs twice). Prints the rows, the recording's duration, per estimator the CPU
time, and the ratio to real time (target: >= 300x) for

- **cold**: the whole re-run counted from the file (reading the log with
  :func:`app.sources.readers.read_log_data`, then every estimator), as the first what-if on a
  recording;
- **warm**: a re-run of the log already parsed (the server keeps the last two parsed
  recordings: a what-if is repeated with new parameters).

Each figure is the best of ``--repeat`` runs, as wall time and as this process's CPU
time (the machine may be shared: the load average is printed before and after; the CPU
figure is what the code costs, the wall figure what a user waits on a loaded machine).
The log is also read once line by line (:func:`app.sources.readers.iter_chunks`, the streaming
reader the whole-file read replaces for a what-if) for comparison. A warm-up run on a
short log first, so numba's compilation is not counted.
Usage: ``python benchmarks/whatif.py [--minutes 10] [--repeat 3]``.
"""

from __future__ import annotations

import argparse
import os
import sys
import tempfile
import time
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))
from app.estimators import NAMES  # noqa: E402
from app.sources.readers import iter_chunks, read_log_data
from app.sources.sensorfusion import format_line
from app.sources.simulate import Simulation, stream
from app.toolkit.variants import no_rejection_changes
from app.toolkit.whatif import rerun


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


def timed(fn, repeat: int):
    """(best wall s, best CPU s, the result of the fastest run by wall time)."""
    walls, cpus, outs = [], [], []
    for _ in range(repeat):
        t0, c0 = time.perf_counter(), time.process_time()
        outs.append(fn())
        walls.append(time.perf_counter() - t0)
        cpus.append(time.process_time() - c0)
    return min(walls), min(cpus), outs[walls.index(min(walls))]


def load() -> str:
    return "load average " + " ".join(f"{x:.1f}" for x in os.getloadavg())


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--minutes", type=float, default=10.0)
    ap.add_argument("--repeat", type=int, default=3)
    args = ap.parse_args()
    specs = {n: (n, {}) for n in NAMES}
    specs["robust-no-rejection"] = ("robust", no_rejection_changes("robust"))
    print(f"{load()} ({os.cpu_count()} CPUs)")
    with tempfile.TemporaryDirectory() as d:
        warm = Path(d) / "warm.txt"
        write_log(warm, 5.0)
        rerun(warm, specs, patch={"robust": {"mag_norm_gate_rel": 0.1}})
        log = Path(d) / "ten_minutes.txt"
        lines = write_log(log, args.minutes * 60.0)
        print(f"log: {lines} lines, {log.stat().st_size / 1e6:.1f} MB, "
              f"{args.minutes:g} min of the simulated phone")
        wall, cpu, rec = timed(lambda: read_log_data(log), args.repeat)
        print(f"reading it whole (read_log_data)      {wall:6.3f} s wall, {cpu:6.3f} s CPU")
        t0, c0 = time.perf_counter(), time.process_time()
        n_rows = sum(len(c) for c in iter_chunks(log))
        print(f"reading it line by line (iter_chunks)  {time.perf_counter() - t0:6.3f} s wall, "
              f"{time.process_time() - c0:6.3f} s CPU ({n_rows} rows; once)")
        for patch in (None, {"robust": {"mag_norm_gate_rel": 0.1}}):
            wall, cpu, out = timed(lambda: rerun(log, specs, patch=patch), args.repeat)
            label = "no patch" if patch is None else "patch robust.mag_norm_gate_rel=0.1 (robust runs twice)"
            dur = out["duration_s"]
            print(f"\n{label}: {out['rows']} rows, {dur:.1f} s of recording, "
                  f"{len(specs)} estimators (best of {args.repeat})")
            for name, e in out["estimators"].items():
                if e.get("reference"):
                    print(f"  {name:<22}   (the reference itself: its held ORI is scored, not re-run)")
                    continue
                c = e["before"]["seconds_cpu"] + (e["after"]["seconds_cpu"] if e["after"] else 0.0)
                print(f"  {name:<22} {c:7.3f} s  ({out['rows'] / e['before']['seconds_cpu'] / 1e3:7.0f} k rows/s per run)")
            print(f"  reading the log        {out['read_s']:7.3f} s")
            print(f"  estimating (all)       {out['estimate_s']:7.3f} s  -> {dur / out['estimate_s']:.0f}x real time")
            print(f"  cold: whole re-run from the file   {wall:6.3f} s wall -> {dur / wall:4.0f}x, "
                  f"{cpu:6.3f} s CPU -> {dur / cpu:4.0f}x real time  (target >= 300x)")
            w_wall, w_cpu, _ = timed(lambda: rerun(rec, specs, patch=patch), args.repeat)
            print(f"  warm: re-run of the parsed log     {w_wall:6.3f} s wall -> {dur / w_wall:4.0f}x, "
                  f"{w_cpu:6.3f} s CPU -> {dur / w_cpu:4.0f}x real time  (target >= 300x)")
    print(load())


if __name__ == "__main__":
    main()
