"""Compile the numba filters before they are needed, and say so while it happens.

The estimators' inner loops are ``@njit(cache=True)`` functions: the first run after an
install or a change of their source compiles them (about a minute on 2 cores), later runs load
numba's on-disk cache (``__pycache__`` beside the sources, or numba's user cache
directory when that is read-only) in about a second.

- :func:`compile_all` (``orientlab compile``, run by ``make run``/``make test`` at
  install time) compiles every estimator, one process per estimator and up to one
  process per core, so the cache is full before the first start.
- :func:`prepare` (called by ``orientlab serve`` before it opens the page) compiles or
  loads them in this process; when that takes longer than a moment (a cold cache) it
  tells the user what is happening, with one line per estimator when it is ready.
"""

from __future__ import annotations

import os
import subprocess
import sys
import tempfile
import threading
import time
from typing import TextIO

import numpy as np

#: what a user waits for on a cold cache, said in the message (benchmarks/startup.py)
COLD_HINT = "about a minute on 2 cores"
#: a warm start loads the cache within this; longer means numba is compiling
QUIET_S = 3.0


def warm_one(name: str, live: bool = True, batch: bool = True) -> None:
    """Run estimator ``name`` through the paths the dashboard (``live``: one sensor
    per row as a stream sends them, and the read-outs) and ``orientlab estimate``
    (``batch``: arrays with and without magnetometer and ORI) take, so numba compiles
    (or loads) them."""
    from app import quaternion as qm
    from app.estimators import make_estimator

    est = make_estimator(name)
    g, a, m = np.array([0.01, 0.0, 0.0]), np.array([0.0, 0.0, 9.81]), np.array([0.0, 20.0, -45.0])
    o = np.array([1.0, 0.0, 0.0, 0.0])
    n = 40
    rows = lambda v: np.tile(v, (n, 1))      # noqa: E731
    if batch:
        t = np.arange(n) * 0.01
        est.run(t, rows(g), rows(a), rows(m), rows(o))
        est.reset()
        est.run(t, rows(g), rows(a), None, None)
        est.reset()
    if not live:
        return
    for k in range(4):                       # the live path: one sensor per step
        t = 0.01 * k
        est.step(t, gyr=g)
        est.step(t + 0.002, acc=a)
        est.step(t + 0.004, mag=m)
        est.step(t + 0.006, ori=o)
    est.step(0.05, gyr=g, acc=a, mag=m, ori=o)
    est.save_state()
    est.diagnostics()
    est.attitude_cov()
    est.reset()
    # the live ensemble's per-chunk bookkeeping (app.live.ensemble)
    from app.estimators.base import NFLAGS, split_rows, tally_rows
    kind = np.array([0, 1, 2, 3], dtype=np.int8)
    G, A, M, O = np.empty((4, 3)), np.empty((4, 3)), np.empty((4, 3)), np.empty((4, 4))
    split_rows(kind, np.zeros((4, 4)), G, A, M, O)
    tally_rows(kind, np.zeros(4), np.zeros((4, NFLAGS)), np.zeros((4, 4)),
               np.zeros((3, 20), np.int64), np.zeros((3, 1 + NFLAGS)), np.zeros((3, 1 + NFLAGS)),
               np.zeros(20, dtype=bool))
    # what the dashboard computes from every estimate (read-outs, plots)
    qm.q2euler(o)
    qm.angle_between(o, o)
    qm.q2euler_many(rows(o))


def names() -> tuple[str, ...]:
    from app.estimators import NAMES
    return tuple(NAMES)


# ---------------------------------------------------------------- in this process

def prepare(out: TextIO | None = None, prog: str = "orientlab",
            quiet_s: float = QUIET_S, only: tuple[str, ...] | None = None,
            live: bool = True, batch: bool = False) -> float:
    """Compile (or load from the cache) the estimators ``only`` (default: all) in this
    process, their ``live`` (``serve``) and/or ``batch`` (``estimate``) paths. Silent when
    that is quick; otherwise one line says that numba compiles, then one line per
    estimator when it is ready (and, on a terminal, a ticking clock). Returns the
    seconds spent. Exceptions of the compilation are raised here."""
    out = out if out is not None else sys.stderr
    todo = only or names()
    done: list[tuple[str, float]] = []
    error: list[BaseException] = []
    finished = threading.Event()
    t0 = time.perf_counter()

    def work() -> None:
        try:
            for name in todo:
                ts = time.perf_counter()
                warm_one(name, live=live, batch=batch)
                done.append((name, time.perf_counter() - ts))
        except BaseException as e:  # handed to the caller's thread
            error.append(e)
        finally:
            finished.set()

    th = threading.Thread(target=work, name="orientlab-compile", daemon=True)
    th.start()
    if finished.wait(quiet_s) and not error:
        return time.perf_counter() - t0
    tty = hasattr(out, "isatty") and out.isatty()
    if not error:
        what = f"the {todo[0]} filter" if len(todo) == 1 else f"the {len(todo)} filters"
        print(f"{prog}: compiling {what} with numba: once after an install or an update "
              f"({COLD_HINT}); later starts load {'it' if len(todo) == 1 else 'them'} from "
              f"the cache (`orientlab compile` does it ahead of time)", file=out, flush=True)
    shown = 0
    while True:
        fin = finished.wait(1.0 if tty else 0.25)
        while shown < len(done):
            name, s = done[shown]
            shown += 1
            if tty:
                out.write("\r\033[K")
            print(f"{prog}:   [{shown}/{len(todo)}] {name} ready ({s:.1f} s)", file=out, flush=True)
        if fin:
            break
        if tty and shown < len(todo):
            out.write(f"\r\033[K{prog}:   [{shown + 1}/{len(todo)}] compiling {todo[shown]}... "
                      f"{time.perf_counter() - t0:.0f} s")
            out.flush()
    if error:
        raise error[0]
    total = time.perf_counter() - t0
    print(f"{prog}: filters ready in {total:.1f} s", file=out, flush=True)
    return total


# ---------------------------------------------------------------- ahead of time

def compile_all(jobs: int | None = None, out: TextIO | None = None,
                prog: str = "orientlab compile") -> int:
    """Fill numba's cache for every estimator: one child process per estimator, at
    most ``jobs`` at once (default: the number of cores). Prints a line per estimator
    and returns 0, or 1 with the failing child's error output."""
    out = out if out is not None else sys.stderr
    jobs = max(1, jobs or os.cpu_count() or 1)
    from app.jitcache import ensure_fresh
    if ensure_fresh():   # here, once, before the children load the cache
        print(f"{prog}: the filters' sources changed: their numba cache was dropped",
              file=out, flush=True)
    todo = list(names())
    print(f"{prog}: compiling {len(todo)} estimators with numba ({jobs} at a time; "
          f"done once, cached for every later start)", file=out, flush=True)
    t0 = time.perf_counter()
    running: dict[str, tuple[subprocess.Popen, float, object]] = {}
    failed = 0
    env = dict(os.environ)
    while todo or running:
        while todo and len(running) < jobs:
            name = todo.pop(0)
            log = tempfile.TemporaryFile(mode="w+")   # a file, not a pipe: no deadlock
            p = subprocess.Popen([sys.executable, "-m", "app.warmup", name], env=env,
                                 stdout=subprocess.DEVNULL, stderr=log, text=True)
            running[name] = (p, time.perf_counter(), log)
        for name, (p, ts, log) in list(running.items()):
            if p.poll() is None:
                continue
            log.seek(0)
            err = log.read()
            log.close()
            del running[name]
            if p.returncode == 0:
                print(f"{prog}:   {name} ready ({time.perf_counter() - ts:.1f} s)", file=out, flush=True)
            else:
                failed += 1
                print(f"{prog}:   {name} FAILED (exit {p.returncode}):\n{err.rstrip()}", file=out, flush=True)
        time.sleep(0.1)
    print(f"{prog}: {'failed' if failed else 'done'} in {time.perf_counter() - t0:.1f} s",
          file=out, flush=True)
    return 1 if failed else 0


def _main(argv: list[str]) -> int:
    """``python -m app.warmup NAME...``: compile those estimators in this process."""
    for name in argv or names():
        warm_one(name)
    return 0


if __name__ == "__main__":
    sys.exit(_main(sys.argv[1:]))
