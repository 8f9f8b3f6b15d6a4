"""The live core alone: what the dashboard's filtering costs, without a server.

A simulated phone at 500 Hz per sensor (ACC, GYR, MAG: 1500 samples/s) is fed through
:class:`app.live.LiveCore` in 10 ms chunks (15 lines, bytes), as the receiver hands them over:
parse and reorder (the stream's session), every estimator instance's compiled batch run
(the four builtins and the two ready-made variants, ``robust-no-rejection`` and
``lab-approx``), the per-row bookkeeping and the plots' rings. Prints, best of
``--repeats``, the CPU time (``time.process_time``: other processes on a shared machine
do not count) per sample for each stage and the share of one core at 1500 samples/s.

Run: ``.venv/bin/python benchmarks/live_core.py [--seconds 20] [--repeats 3] [--variants 2]``.
"""

from __future__ import annotations

import argparse
import sys
import time
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

from app.live import LiveCore  # noqa: E402
from app.sources.sensorfusion import format_line
from app.sources.simulate import SimConfig, simulate
from app.toolkit.variants import ready_made
from app.sources.sensorfusion import decode_lines  # noqa: E402
from collections import Counter  # noqa: E402


def feed_chunk(core, s, lines):
    """A chunk of the app's lines as the TCP source feeds it: decoded, then fed."""
    return core.feed(s, decode_lines(lines, Counter()))

RATE_HZ = 500
CHUNK = 15          # lines per 10 ms at 3 x 500 Hz


def one_run(lines: list[bytes], variants: int) -> dict[str, float]:
    core = LiveCore(None)
    for name, (base, params) in list(ready_made(core.ensemble.primary).items())[:variants]:
        core.ensemble.add(name, base, params)
    s = core.open_session("phone", "benchmark")
    core.start(s)
    chunks = [lines[i:i + CHUNK] for i in range(0, len(lines), CHUNK)]
    warm = len(chunks) // 10
    for c in chunks[:warm]:
        core.process(s, feed_chunk(core, s, c))
    t_feed = t_proc = 0.0
    n = 0
    for c in chunks[warm:]:
        t0 = time.process_time()
        released = feed_chunk(core, s, c)
        t1 = time.process_time()
        core.process(s, released)
        t2 = time.process_time()
        t_feed, t_proc = t_feed + t1 - t0, t_proc + t2 - t1
        n += len(c)
    return {"parse + reorder": t_feed / n, "estimators + bookkeeping": t_proc / n,
            "n": n, "names": core.ensemble.names}


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--seconds", type=float, default=20.0)
    ap.add_argument("--repeats", type=int, default=3)
    ap.add_argument("--variants", type=int, default=2, choices=(0, 1, 2))
    args = ap.parse_args()
    cfg = SimConfig(acc_period_ms=1000 // RATE_HZ, gyr_period_ms=1000 // RATE_HZ,
                    mag_period_ms=1000 // RATE_HZ, ori_period_ms=10_000)
    sim = simulate(duration_s=args.seconds, config=cfg, seed=0)
    # bytes without line ends, as the receiver's LineSplitter hands them over
    lines = [format_line(*smp).encode() for smp in sim.samples if smp[1] != "ORI"]
    best = None
    for _ in range(args.repeats):
        r = one_run(lines, args.variants)
        tot = sum(v for k, v in r.items() if k not in ("n", "names"))
        if best is None or tot < best[0]:
            best = (tot, r)
    tot, r = best
    rate = 3 * RATE_HZ
    print(f"live core: {rate} samples/s (ACC/GYR/MAG at {RATE_HZ} Hz), chunks of {CHUNK} lines, "
          f"{r['n']} samples, best of {args.repeats}")
    print(f"  estimators       {len(r['names'])}: {', '.join(r['names'])}")
    for k in ("parse + reorder", "estimators + bookkeeping"):
        print(f"  {k:24s} {r[k] * 1e6:6.1f} µs/sample  {r[k] * rate * 100:5.1f} % of a core")
    print(f"  {'total':24s} {tot * 1e6:6.1f} µs/sample  {tot * rate * 100:5.1f} % of a core")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
