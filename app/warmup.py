"""Compile the numba filters before they are needed, and say so while it happens.

The estimators' inner loops are numba kernels (``app.jitcache.compiled``): the first run after an
install or a change of their source compiles them (about a minute on 2 cores), later runs load
numba's on-disk cache (``__pycache__`` beside the sources, ``$NUMBA_CACHE_DIR``, or numba's
user cache directory when the sources are read-only) in about a second.

Whatever the output is (a terminal, a pipe, a log file), a compilation prints a line when
it starts, one per filter when it is ready, and one every :data:`HEARTBEAT_S` seconds
between them naming what is being compiled.

- :func:`compile_all` (``orientlab compile``, run by ``make run``/``make test`` at
  install time) compiles every estimator, one process per estimator and up to one
  process per core, so the cache is full before the first start.
- :class:`Warmup` (``orientlab serve``) does it in the background while the page already
  answers: the filters already in numba's cache are loaded into the server's process at
  once, the others are compiled by child processes (one per filter, as ``compile`` does)
  and loaded when their child is done. Its :meth:`~Warmup.status` says which filters are
  ready (``/api/health`` and the page show it); the dashboard's filter task starts once
  all are, and the samples that came meanwhile wait for it in order.
- :func:`prepare` (``orientlab estimate``, one filter) compiles or loads in this process.
"""

from __future__ import annotations

import asyncio
import os
import subprocess
import sys
import tempfile
import threading
import time
from typing import Callable, TextIO

import numpy as np

#: what a user waits for on a cold cache, said in the message (benchmarks/startup.py)
COLD_HINT = "about a minute on 2 cores"
#: a warm start loads the cache within this; longer means numba is compiling
QUIET_S = 3.0
#: while compiling, a progress line at least this often (seconds), on a terminal or not
HEARTBEAT_S = 10.0


def warm_one(name: str, live: bool = True, batch: bool = True) -> None:
    """Run estimator ``name`` through the paths the dashboard (``live``: one sensor
    per row as a stream sends them, and the read-outs) and ``orientlab estimate``
    (``batch``: arrays with and without magnetometer and ORI) take, so numba compiles
    (or loads) them."""
    from app import quaternion as qm
    from app.params import GRAVITY
    from app.estimators import make_estimator

    est = make_estimator(name)
    g, a, m = np.array([0.01, 0.0, 0.0]), np.array([0.0, 0.0, GRAVITY]), np.array([0.0, 20.0, -45.0])
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
    from app.estimators.base import NFLAGS, Reason, split_rows, tally_rows
    nreason = len(Reason)
    kind = np.array([0, 1, 2, 3], dtype=np.int8)
    G, A, M, O = np.empty((4, 3)), np.empty((4, 3)), np.empty((4, 3)), np.empty((4, 4))
    split_rows(kind, np.zeros((4, 4)), G, A, M, O)
    tally_rows(kind, np.zeros(4), np.zeros((4, NFLAGS)), np.zeros((4, 4)),
               np.zeros((3, nreason), np.int64), np.zeros((3, 1 + NFLAGS)), np.zeros((3, 1 + NFLAGS)),
               np.zeros(nreason, dtype=bool))
    # what the dashboard computes from every estimate (read-outs, plots)
    qm.q2euler(o)
    qm.angle_between(o, o)
    qm.q2euler_many(rows(o))
    if batch:   # every path has run: it is in numba's cache now (app.jitcache.is_warm)
        from app.jitcache import mark_warm
        mark_warm(name)


def names() -> tuple[str, ...]:
    from app.estimators import NAMES
    return tuple(NAMES)


def _say(out: TextIO, line: str) -> None:
    try:
        print(line, file=out, flush=True)
    except (OSError, ValueError):   # the reader went away: the work goes on
        pass


def _clock(t0: float) -> str:
    return f"{time.perf_counter() - t0:.0f} s"


# ---------------------------------------------------------------- in this process

def prepare(out: TextIO | None = None, prog: str = "orientlab",
            quiet_s: float = QUIET_S, only: tuple[str, ...] | None = None,
            live: bool = True, batch: bool = False,
            heartbeat_s: float = HEARTBEAT_S) -> float:
    """Compile (or load from the cache) the estimators ``only`` (default: all) in this
    process, their ``live`` (``serve``) and/or ``batch`` (``estimate``) paths. Silent when
    that is quick; otherwise one line says that numba compiles, then one line per
    estimator when it is ready, and meanwhile a ticking clock on a terminal or a progress
    line every ``heartbeat_s`` seconds elsewhere. Returns the seconds spent. Exceptions
    of the compilation are raised here."""
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
        _say(out, f"{prog}: compiling {what} with numba: once after an install or an update "
                  f"({COLD_HINT}); later starts load {'it' if len(todo) == 1 else 'them'} from "
                  f"the cache (`orientlab compile` does it ahead of time)")
    shown = 0
    said = time.perf_counter()
    while True:
        fin = finished.wait(1.0 if tty else 0.25)
        while shown < len(done):
            name, s = done[shown]
            shown += 1
            if tty:
                out.write("\r\033[K")
            _say(out, f"{prog}:   [{shown}/{len(todo)}] {name} ready ({s:.1f} s)")
            said = time.perf_counter()
        if fin:
            break
        if shown < len(todo):
            if tty:
                out.write(f"\r\033[K{prog}:   [{shown + 1}/{len(todo)}] compiling {todo[shown]}... "
                          f"{_clock(t0)}")
                out.flush()
            elif time.perf_counter() - said >= heartbeat_s:
                _say(out, f"{prog}:   [{shown + 1}/{len(todo)}] still compiling "
                          f"{todo[shown]} ({_clock(t0)})")
                said = time.perf_counter()
    if error:
        raise error[0]
    total = time.perf_counter() - t0
    _say(out, f"{prog}: filters ready in {total:.1f} s")
    return total


# ---------------------------------------------------------------- in the background

WAITING, COMPILING, LOADING, READY, FAILED = "waiting", "compiling", "loading", "ready", "failed"


class _Child:
    """``python -m app.warmup NAME``: compiles one filter into numba's on-disk cache."""

    def __init__(self, name: str):
        self.name = name
        self.log = tempfile.TemporaryFile(mode="w+")     # a file, not a pipe: no deadlock
        self.proc = subprocess.Popen([sys.executable, "-m", "app.warmup", name],
                                     stdin=subprocess.DEVNULL, stdout=subprocess.DEVNULL,
                                     stderr=self.log, text=True)
        self.t0 = time.perf_counter()

    def poll(self) -> int | None:
        return self.proc.poll()

    def errors(self) -> str:
        if self.log.closed:
            return ""
        self.log.seek(0)
        text = self.log.read()
        self.log.close()
        return text.rstrip()

    def stop(self) -> None:
        if self.proc.poll() is None:
            self.proc.terminate()
            try:
                self.proc.wait(timeout=5)
            except subprocess.TimeoutExpired:
                self.proc.kill()
                self.proc.wait()
        if not self.log.closed:
            self.log.close()


class Warmup:
    """The filters ``todo`` (default: all, in this order) made ready in the background
    of a running server, with a state per filter (:meth:`status`: waiting, compiling,
    loading, ready, failed).

    A filter whose code is in numba's cache (:func:`app.jitcache.is_warm`) is loaded
    into this process at once (about a second). The others are compiled by child
    processes (``python -m app.warmup NAME``, one per filter, up to ``jobs`` at a time)
    and loaded here when their child is done: this process never compiles a filter
    itself, since numba holds one lock for the whole of a compilation and the server's
    own small compiled calls (``app.quaternion``) would wait behind it. Then it says so:
    one line at the start, one per filter when it is ready, one every ``heartbeat_s``
    seconds between, one at the end; a warm start says nothing.

    ``on_failure(text)`` is called (from a worker thread) when a filter cannot be
    compiled; :meth:`stop` ends the children (at the server's exit)."""

    def __init__(self, todo: tuple[str, ...] | None = None, out: TextIO | None = None,
                 prog: str = "orientlab serve", jobs: int | None = None,
                 quiet_s: float = QUIET_S, heartbeat_s: float = HEARTBEAT_S,
                 note: str = "", on_failure: Callable[[str], None] | None = None):
        self.todo = tuple(todo or names())
        self.out = out if out is not None else sys.stderr
        self.prog, self.note = prog, note
        self.jobs = max(1, jobs or os.cpu_count() or 1)
        self.quiet_s, self.heartbeat_s = quiet_s, heartbeat_s
        self.on_failure = on_failure
        self.error: str | None = None
        self.seconds: float | None = None           # from start to all ready
        self.loud = False                           # it said it compiles
        self.done = threading.Event()               # all ready, or one failed
        self._lock = threading.Condition()
        self._state = {n: WAITING for n in self.todo}
        self._cached = dict.fromkeys(self.todo, False)   # in numba's cache: load it here
        self._spawn: list[str] = []                 # waiting for a child
        self._children: dict[str, _Child] = {}
        self._failed: tuple[str, str] | None = None       # (filter, its child's errors)
        self._loading: tuple[str, float] | None = None    # loaded here since
        self._stopping = threading.Event()
        self._t0 = 0.0

    # ------------------------------------------------------------- read-outs
    def status(self) -> dict[str, str]:
        """``{name: "waiting" | "compiling" | "loading" | "ready" | "failed"}``."""
        with self._lock:
            return dict(self._state)

    @property
    def ready(self) -> bool:
        return self.done.is_set() and self.error is None

    def summary(self) -> str:
        """``robust ready, lab compiling, ...``"""
        return ", ".join(f"{n} {s}" for n, s in self.status().items())

    async def wait_ready(self, poll_s: float = 0.1) -> bool:
        """On an event loop: until every filter is ready (True) or one failed (False)."""
        while not self.done.is_set():
            await asyncio.sleep(poll_s)
        return self.error is None

    # ------------------------------------------------------------- control
    def start(self) -> "Warmup":
        from app.jitcache import is_warm
        if self._stopping.is_set():
            return self
        self._t0 = time.perf_counter()
        for n in self.todo:
            self._cached[n] = is_warm(n)
        self._spawn = [n for n in self.todo if not self._cached[n]]
        if self._spawn:
            self._say_start(self._spawn, f"up to {self.jobs} at a time, one process each")
        threading.Thread(target=self._load_all, name="orientlab-warmup", daemon=True).start()
        threading.Thread(target=self._watch, name="orientlab-warmup-watch", daemon=True).start()
        return self

    def stop(self) -> None:
        """End the children (at the server's exit; numba's cache stays consistent)."""
        self._stopping.set()
        with self._lock:
            children = list(self._children.values())
            self._lock.notify_all()
        for c in children:
            c.stop()

    # ------------------------------------------------------------- the work
    def _say_start(self, which: list[str], how: str) -> None:
        self.loud = True
        what = f"the {which[0]} filter" if len(which) == 1 else \
            f"{len(which)} filters ({', '.join(which)})"
        _say(self.out, f"{self.prog}: compiling {what} with numba, {how}: once after an "
                       f"install or an update ({COLD_HINT}); later starts load them from the "
                       f"cache in seconds" + (f"; {self.note}" if self.note else ""))

    def _next(self, loaded: set[str]) -> str | None:
        """The next filter to load here (in order among those cached), waiting for a
        child if need be; None when stopped or a child failed."""
        with self._lock:
            while not self._stopping.is_set() and self._failed is None:
                for n in self.todo:
                    if n not in loaded and self._cached[n]:
                        self._state[n] = LOADING
                        return n
                self._lock.wait(0.2)
            return None

    def _load_all(self) -> None:
        """This process: each filter once its code is in numba's cache."""
        loaded: set[str] = set()
        name = self.todo[0]
        try:
            while len(loaded) < len(self.todo):
                name = self._next(loaded)
                if name is None:
                    if self._failed is not None:
                        name = self._failed[0]
                        raise RuntimeError(self._failed[1])
                    return
                self._loading = (name, time.perf_counter())
                warm_one(name, live=True, batch=True)
                self._loading = None
                loaded.add(name)
                with self._lock:
                    self._state[name] = READY
                if self.loud:
                    _say(self.out, f"{self.prog}:   [{len(loaded)}/{len(self.todo)}] {name} "
                                   f"ready (after {_clock(self._t0)})")
            self.seconds = time.perf_counter() - self._t0
            if self.loud:
                _say(self.out, f"{self.prog}: filters ready in {self.seconds:.1f} s")
        except BaseException as e:   # said, shown in the status, handed on
            with self._lock:
                self._state[name] = FAILED
            self.error = str(e) if isinstance(e, RuntimeError) else f"{type(e).__name__}: {e}"
            _say(self.out, f"{self.prog}: the {name} filter cannot be compiled: {self.error}")
            self.stop()
            if self.on_failure is not None:
                self.on_failure(self.error)
        finally:
            self._loading = None
            self.done.set()

    def _watch(self) -> None:
        """Run the children; say where it is every heartbeat while compiling."""
        said = time.perf_counter()
        while not self.done.is_set() and not self._stopping.is_set():
            self._run_children()
            now = time.perf_counter()
            cur = self._loading
            if not self.loud and cur is not None and now - cur[1] > self.quiet_s:
                # cached as far as could be told, yet numba compiles: say so
                self._say_start([cur[0]], "in this process")
                said = now
            if self.loud and now - said >= self.heartbeat_s:
                st = self.status()
                busy = [n for n, s in st.items() if s in (COMPILING, LOADING)]
                wait = [n for n, s in st.items() if s == WAITING]
                ready = sum(s == READY for s in st.values())
                _say(self.out, f"{self.prog}:   [{ready}/{len(st)} ready] compiling "
                               f"{', '.join(busy) or '-'}"
                               + (f"; next {', '.join(wait)}" if wait else "")
                               + f" ({_clock(self._t0)})")
                said = now
            self.done.wait(0.1)

    def _run_children(self) -> None:
        for name, c in list(self._children.items()):
            rc = c.poll()
            if rc is None:
                continue
            err = c.errors()
            with self._lock:
                del self._children[name]
                if rc == 0:
                    self._cached[name] = True
                elif self._failed is None:
                    self._failed = (name, f"exit {rc}:\n{err[-4000:]}")
                self._lock.notify_all()
        while len(self._children) < self.jobs and not self._stopping.is_set():
            with self._lock:
                if not self._spawn:
                    return
                name = self._spawn.pop(0)
                self._state[name] = COMPILING
                self._children[name] = _Child(name)


# ---------------------------------------------------------------- ahead of time

def compile_all(jobs: int | None = None, out: TextIO | None = None,
                prog: str = "orientlab compile", heartbeat_s: float = HEARTBEAT_S) -> int:
    """Fill numba's cache for every estimator: one child process per estimator, at
    most ``jobs`` at once (default: the number of cores). Prints a line per estimator
    when it is ready and one every ``heartbeat_s`` seconds between (on a terminal or
    not), and returns 0, or 1 with the failing child's error output."""
    out = out if out is not None else sys.stderr
    jobs = max(1, jobs or os.cpu_count() or 1)
    from app.jitcache import ensure_fresh
    if ensure_fresh():   # here, once, before the children load the cache
        _say(out, f"{prog}: the filters' sources changed: their numba cache was dropped")
    todo = list(names())
    n = len(todo)
    _say(out, f"{prog}: compiling {n} estimators with numba ({jobs} at a time; "
              f"done once, cached for every later start)")
    t0 = time.perf_counter()
    said = t0
    running: dict[str, _Child] = {}
    failed = ready = 0
    try:
        while todo or running:
            while todo and len(running) < jobs:
                name = todo.pop(0)
                running[name] = _Child(name)
            for name, c in list(running.items()):
                if c.poll() is None:
                    continue
                err = c.errors()
                del running[name]
                if c.proc.returncode == 0:
                    ready += 1
                    _say(out, f"{prog}:   [{ready}/{n}] {name} ready "
                              f"({time.perf_counter() - c.t0:.1f} s)")
                else:
                    failed += 1
                    _say(out, f"{prog}:   {name} FAILED (exit {c.proc.returncode}):\n{err}")
                said = time.perf_counter()
            if running and time.perf_counter() - said >= heartbeat_s:
                _say(out, f"{prog}:   [{ready}/{n} ready] compiling {', '.join(running)}"
                          + (f"; next {', '.join(todo)}" if todo else "") + f" ({_clock(t0)})")
                said = time.perf_counter()
            time.sleep(0.1)
    finally:
        for c in running.values():   # Ctrl-C: no orphan compiling on
            c.stop()
    _say(out, f"{prog}: {'failed' if failed else 'done'} in {time.perf_counter() - t0:.1f} s")
    return 1 if failed else 0


def _main(argv: list[str]) -> int:
    """``python -m app.warmup NAME...``: compile those estimators in this process."""
    for name in argv or names():
        warm_one(name)
    return 0


if __name__ == "__main__":
    sys.exit(_main(sys.argv[1:]))
