"""How many bytes a recording of a 500 Hz phone writes per minute, before and after the
compact estimates (issue 21, item 2).

What it does
------------
- simulates a phone at 500 Hz (ACC, GYR and MAG every 2 ms, the phone's own ORI at
  100 Hz: :class:`app.sources.simulate.SimConfig`) for ``--seconds`` of stream time;
- feeds it, in 10 ms chunks as a receiver does, through a real live core
  (:class:`app.live.core.LiveCore`: every estimator) with a real
  :class:`~app.toolkit.session_recorder.RecordingService` on its hooks, as the server
  wires it, not paced (stream time, not wall time, is what a minute means here);
- once with the committed version of ``app/toolkit/recording.py`` and
  ``app/toolkit/session_recorder.py`` (``git show HEAD:...`` into temporary modules; the
  work tree and git are left alone), once with this tree's (``orientlab serve``'s
  defaults: estimates at 20 rows/s per estimator, gzip-compressed);
- the phone session has no truth (a real phone), so no ``truth`` rows.

What it prints
--------------
Per version: the bytes of each file and of the recording per minute of stream, and the
rate (kB/s); then the ratio. ``--before-only`` / ``--after-only`` run one.

Run: ``.venv/bin/python benchmarks/recording_bytes.py [--seconds 30]``.
"""

from __future__ import annotations

import argparse
import importlib.util
import subprocess
import sys
import tempfile
import time
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

from app.live.core import LiveCore  # noqa: E402
from app.sources.samples import Sample  # noqa: E402
from app.sources.simulate import SimConfig, simulate  # noqa: E402

RATE_HZ = 500
CHUNK_MS = 10


def committed_modules(tmp: Path):
    """The committed recording.py and session_recorder.py as modules of their own."""
    mods = {}
    for name, path in (("committed_recording", "app/toolkit/recording.py"),
                       ("committed_session_recorder", "app/toolkit/session_recorder.py")):
        text = subprocess.run(["git", "show", f"HEAD:{path}"], cwd=ROOT, check=True,
                              capture_output=True, text=True).stdout
        text = text.replace("from app.toolkit.recording import", "from committed_recording import")
        f = tmp / f"{name}.py"
        f.write_text(text)
        spec = importlib.util.spec_from_file_location(name, f)
        mod = importlib.util.module_from_spec(spec)
        sys.modules[name] = mod
        spec.loader.exec_module(mod)
        mods[name] = mod
    return mods["committed_session_recorder"].RecordingService


def phone_samples(seconds: float) -> list[Sample]:
    p = 1000 // RATE_HZ
    cfg = SimConfig(acc_period_ms=p, gyr_period_ms=p, mag_period_ms=p, ori_period_ms=10)
    return [Sample(*s) for s in simulate(duration_s=seconds, config=cfg, seed=5).samples]


def record(service_cls, samples: list[Sample], folder: Path) -> tuple[dict[str, int], float]:
    """Record ``samples`` through a live core and ``service_cls``: bytes per file, and the
    stream seconds recorded."""
    core = LiveCore()
    rs = service_cls(core, folder)
    s = core.open_session("phone", "simulated 500 Hz phone")
    core.start(s)
    rs.start("bench")
    t0 = samples[0].time_ms
    i = 0
    wall = time.perf_counter()
    while i < len(samples):
        j = i
        end = samples[i].time_ms + CHUNK_MS
        while j < len(samples) and samples[j].time_ms < end:
            j += 1
        released = core.feed(s, samples[i:j])
        core.process(s, released)
        i = j
    core.process(s, core.close_session(s, "end of the benchmark"))
    rs.tick()
    rs.stop()
    spent = time.perf_counter() - wall
    sizes = {p.name.replace("bench", "NAME"): p.stat().st_size for p in sorted(folder.iterdir())}
    seconds = (samples[-1].time_ms - t0) / 1000.0
    print(f"    ({len(samples)} samples through the core and the recorder in {spent:.1f} s)")
    return sizes, seconds


def report(label: str, sizes: dict[str, int], seconds: float) -> float:
    per_min = {k: v * 60.0 / seconds for k, v in sizes.items()}
    total = sum(per_min.values())
    print(f"  {label}: {total / 1e6:8.2f} MB per minute of a {RATE_HZ} Hz phone "
          f"({total / 60.0 / 1e3:.0f} kB/s, {total * 60 / 1e9:.2f} GB an hour)")
    for k, v in per_min.items():
        print(f"      {k:28s} {v / 1e6:8.2f} MB/min")
    return total


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--seconds", type=float, default=30.0, help="stream seconds recorded")
    ap.add_argument("--before-only", action="store_true")
    ap.add_argument("--after-only", action="store_true")
    args = ap.parse_args()
    samples = phone_samples(args.seconds)
    core = LiveCore()                   # compile (or load) the filters before timing
    s = core.open_session("phone", "warm-up")
    core.start(s)
    core.process(s, core.feed(s, samples[:2000]))
    print(f"recording bytes of a {RATE_HZ} Hz phone (ACC, GYR, MAG; ORI 100 Hz), "
          f"{args.seconds:g} s of stream")
    totals = {}
    with tempfile.TemporaryDirectory() as tmp:
        tmp = Path(tmp)
        if not args.after_only:
            old = committed_modules(tmp)
            d = tmp / "before"
            d.mkdir()
            totals["before"] = report("before (committed: every row, plain CSV)",
                                      *record(old, samples, d))
        if not args.before_only:
            from app.toolkit.session_recorder import RecordingService
            d = tmp / "after"
            d.mkdir()
            totals["after"] = report("after (estimates 20 rows/s per estimator, gzip)",
                                     *record(RecordingService, samples, d))
    if len(totals) == 2:
        print(f"  after / before: {totals['after'] / totals['before']:.3f} "
              f"({totals['before'] / totals['after']:.1f}x smaller)")
    return 0


if __name__ == "__main__":
    sys.exit(main())
