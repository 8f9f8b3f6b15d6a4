"""What a first (cold numba cache) and a second start cost.

Runs the installed ``orientlab`` of this interpreter's environment as a user does, each
time in a fresh process, with numba's cache in a fresh directory (``NUMBA_CACHE_DIR``)
for the cold runs and the same directory again for the warm ones:

- ``orientlab estimate`` of a generated 3,000-row CSV (30 s at 100 Hz), default filter;
- ``orientlab serve --source demo`` on free loopback ports, until the page answers
  (``GET /`` and ``/api/state`` with samples), then Ctrl-C (SIGINT);
- ``orientlab compile`` (what ``make run`` does once after installing: every filter,
  one process per core), then ``serve`` once more;
- ``--only clone``: from a fresh clone to the first page, as a new user gets there:
  ``git clone`` (or, with ``--worktree``, a copy of this checkout's files as they are,
  uncommitted changes included), a new venv with ``pip install -e .`` (``make run``'s
  install step), then ``orientlab serve`` at once on the cold cache (until ``GET /``
  answers, then until every filter is ready and the demo's samples are filtered), and
  ``make run``'s order: ``orientlab compile``, then ``serve`` until ``GET /`` answers.
  pip installs from this machine's package index and caches: a first download adds
  its own time.

Prints wall time and the CPU time of the child processes (user + system, all cores;
for serve, what it used until the page answered),
the number of cores and the load average before each run: on a shared machine the wall
time grows with the load, the CPU time much less.

    python benchmarks/startup.py            # all of it (~2-4 min on 2 idle cores)
    python benchmarks/startup.py --only estimate
    python benchmarks/startup.py --only clone [--worktree]    # ~3 min on 2 idle cores
"""

from __future__ import annotations

import argparse
import csv
import json
import math
import os
import resource
import signal
import socket
import subprocess
import sys
import tempfile
import time
import urllib.request
from pathlib import Path


def free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


def cli() -> list[str]:
    return [sys.executable, "-m", "app.cli"]


def child_cpu() -> float:
    r = resource.getrusage(resource.RUSAGE_CHILDREN)
    return r.ru_utime + r.ru_stime


def proc_cpu(pid: int) -> float | None:
    """CPU seconds (user + system, all threads) a running process has used so far
    (Linux /proc), so the figure stops when the page answers, not when the demo,
    running meanwhile, is stopped."""
    try:
        fields = Path(f"/proc/{pid}/stat").read_text().rsplit(")", 1)[1].split()
        return (int(fields[11]) + int(fields[12])) / os.sysconf("SC_CLK_TCK")
    except (OSError, ValueError, IndexError):
        return None


def load() -> str:
    try:
        return f"load {os.getloadavg()[0]:.1f}"
    except OSError:
        return "load ?"


def write_csv(path: Path, n: int = 3000, fs: float = 100.0) -> None:
    with open(path, "w", newline="") as fh:
        w = csv.writer(fh)
        w.writerow(["t", "acc_x", "acc_y", "acc_z", "gyr_x", "gyr_y", "gyr_z", "mag_x", "mag_y", "mag_z"])
        for k in range(n):
            t, yaw = k / fs, 0.5 * k / fs
            w.writerow([f"{t:.3f}", 0.0, 0.0, 9.81, 0.0, 0.0, 0.5,
                        f"{20 * math.sin(yaw):.4f}", f"{20 * math.cos(yaw):.4f}", -40.0])


def env_with(cache: Path) -> dict[str, str]:
    env = dict(os.environ)
    env["NUMBA_CACHE_DIR"] = str(cache)
    env.pop("NUMBA_DISABLE_JIT", None)
    return env


def time_estimate(src: Path, cache: Path, work: Path) -> tuple[float, float]:
    c0, t0 = child_cpu(), time.perf_counter()
    subprocess.run(cli() + ["estimate", str(src), "-o", str(work / "out.csv"), "--quiet"],
                   env=env_with(cache), cwd=work, check=True, stdin=subprocess.DEVNULL,
                   stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL)
    return time.perf_counter() - t0, child_cpu() - c0


def time_compile(cache: Path, work: Path) -> tuple[float, float]:
    c0, t0 = child_cpu(), time.perf_counter()
    subprocess.run(cli() + ["compile"], env=env_with(cache), cwd=work, check=True,
                   stdin=subprocess.DEVNULL, stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL)
    return time.perf_counter() - t0, child_cpu() - c0


def _answers(port: int) -> bool:
    try:
        with urllib.request.urlopen(f"http://127.0.0.1:{port}/", timeout=2) as r:
            if r.status != 200:
                return False
        with urllib.request.urlopen(f"http://127.0.0.1:{port}/api/state", timeout=2) as r:
            return json.loads(r.read())["counts"]["samples"] > 0
    except (OSError, ValueError, KeyError):
        return False


def time_serve(cache: Path, work: Path, timeout: float = 900.0) -> tuple[float, float, float]:
    """Seconds until the page answers (with demo samples counted), CPU seconds used by
    then, and seconds from SIGINT to exit."""
    port = free_port()
    c0, t0 = child_cpu(), time.perf_counter()
    p = subprocess.Popen(cli() + ["serve", "--host", "127.0.0.1", "--port", str(port),
                                  "--viewer-port", str(free_port()), "--phone-port",
                                  str(free_port()), "--source", "demo"],
                         env=env_with(cache), cwd=work, stdin=subprocess.DEVNULL,
                         stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL)
    try:
        while not _answers(port):
            if p.poll() is not None:
                raise SystemExit(f"serve exited with {p.returncode} before the page answered")
            if time.perf_counter() - t0 > timeout:
                raise SystemExit("the page did not answer")
            time.sleep(0.05)
        ready = time.perf_counter() - t0
        cpu_ready = proc_cpu(p.pid)
        ts = time.perf_counter()
        p.send_signal(signal.SIGINT)
        p.wait(timeout=60)
        stop = time.perf_counter() - ts
    finally:
        if p.poll() is None:
            p.kill()
            p.wait()
    cpu = child_cpu() - c0
    return ready, (cpu_ready if cpu_ready is not None else cpu), stop


# ---------------------------------------------------------------- from a fresh clone

REPO = Path(__file__).resolve().parents[1]


def _health(port: int) -> dict | None:
    try:
        with urllib.request.urlopen(f"http://127.0.0.1:{port}/api/health", timeout=2) as r:
            return json.loads(r.read())
    except (OSError, ValueError):
        return None


def _page(port: int) -> bool:
    try:
        with urllib.request.urlopen(f"http://127.0.0.1:{port}/", timeout=2) as r:
            return r.status == 200
    except OSError:
        return False


def serve_milestones(python: Path, cwd: Path, env: dict[str, str], until_ready: bool,
                     timeout: float = 900.0) -> dict[str, float]:
    """``orientlab serve --source demo`` of that venv: seconds until ``GET /`` answers
    and, with ``until_ready``, until /api/health says every filter is ready and until
    the demo's samples are counted; then Ctrl-C."""
    port = free_port()
    t0 = time.perf_counter()
    p = subprocess.Popen([str(python), "-m", "app.cli", "serve", "--host", "127.0.0.1",
                          "--port", str(port), "--viewer-port", str(free_port()),
                          "--phone-port", str(free_port()), "--source", "demo"],
                         cwd=cwd, env=env, stdin=subprocess.DEVNULL,
                         stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL)
    out: dict[str, float] = {}
    try:
        while True:
            if p.poll() is not None:
                raise SystemExit(f"serve exited with {p.returncode}")
            if time.perf_counter() - t0 > timeout:
                raise SystemExit(f"serve: no answer in {timeout:.0f} s ({out})")
            if "page" not in out and _page(port):
                out["page"] = time.perf_counter() - t0
                h = _health(port) or {}
                out["ready_at_page"] = sum(s == "ready" for s in h.get("filters", {}).values())
                if not until_ready:
                    break
            # (a server without the "ready" field compiled before it answered)
            if "page" in out and "ready" not in out and (_health(port) or {}).get("ready", True):
                out["ready"] = time.perf_counter() - t0
            if "ready" in out and _answers(port):
                out["samples"] = time.perf_counter() - t0
                break
            time.sleep(0.1)
    finally:
        if p.poll() is None:
            p.send_signal(signal.SIGINT)
            try:
                p.wait(timeout=60)
            except subprocess.TimeoutExpired:
                p.kill()
                p.wait()
    return out


def clone_to_page(worktree: bool, line) -> None:
    base = getattr(sys, "_base_executable", None) or sys.executable
    with tempfile.TemporaryDirectory(prefix="orientlab-clone-") as d:
        clone = Path(d) / "orientlab"
        t0 = time.perf_counter()
        if worktree:   # this checkout's files as they are (tracked and untracked, not ignored)
            files = subprocess.run(["git", "ls-files", "-z", "--cached", "--others",
                                    "--exclude-standard"], cwd=REPO, check=True,
                                   capture_output=True).stdout.decode().split("\0")
            for f in filter(None, files):
                src = REPO / f
                if src.is_file():
                    (clone / f).parent.mkdir(parents=True, exist_ok=True)
                    (clone / f).write_bytes(src.read_bytes())
        else:
            subprocess.run(["git", "clone", "-q", str(REPO), str(clone)], check=True)
        t_clone = time.perf_counter() - t0
        line("git clone" if not worktree else "copy of the checkout (--worktree)", t_clone, None)
        # make run's install step: a venv, pip upgraded, the package with its dependencies
        c0, t0 = child_cpu(), time.perf_counter()
        env = {k: v for k, v in os.environ.items()
               if k not in ("PYTHONPATH", "VIRTUAL_ENV", "NUMBA_CACHE_DIR", "NUMBA_DISABLE_JIT")}
        venv = clone / ".venv"
        subprocess.run([base, "-m", "venv", str(venv)], check=True, cwd=clone, env=env)
        py = venv / "bin" / "python"
        for cmd in (["install", "-q", "--upgrade", "pip"], ["install", "-q", "-e", "."]):
            subprocess.run([str(py), "-m", "pip", *cmd], check=True, cwd=clone, env=env,
                           stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL)
        t_install = time.perf_counter() - t0
        line("venv + pip install -e . (make run's install step)", t_install, child_cpu() - c0)
        # orientlab serve at once, on a cold numba cache
        cold = dict(env, NUMBA_CACHE_DIR=str(Path(d) / "cold-cache"))
        m = serve_milestones(py, clone, cold, until_ready=True)
        line("serve on a cold cache: GET / answers", m["page"], None)
        print(f"{'  (filters ready then: ' + str(m['ready_at_page']) + ')':<52}")
        line("serve on a cold cache: every filter ready", m["ready"], None)
        line("serve on a cold cache: demo samples filtered", m["samples"], None)
        first_page = t_clone + t_install + m["page"]
        # make run's order: compile ahead (into the clone's __pycache__), then serve
        c0, t0 = child_cpu(), time.perf_counter()
        subprocess.run([str(py), "-m", "app.cli", "compile"], check=True, cwd=clone, env=env,
                       stdin=subprocess.DEVNULL, stdout=subprocess.DEVNULL,
                       stderr=subprocess.DEVNULL)
        t_compile = time.perf_counter() - t0
        line("orientlab compile (make run, cold)", t_compile, child_cpu() - c0)
        w = serve_milestones(py, clone, env, until_ready=False)
        line("serve after compile: GET / answers", w["page"], None)
        print()
        print(f"fresh clone to the first page, serve at once:      {first_page:6.1f} s "
              f"(filters ready at {t_clone + t_install + m['ready']:.1f} s)")
        print(f"fresh clone to the first page, make run's order:   "
              f"{t_clone + t_install + t_compile + w['page']:6.1f} s")


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--only", choices=("estimate", "serve", "compile", "clone"), action="append")
    ap.add_argument("--worktree", action="store_true",
                    help="clone: copy this checkout's files (uncommitted changes too) "
                         "instead of git clone")
    args = ap.parse_args()
    only = set(args.only or ("estimate", "serve", "compile"))
    print(f"orientlab start-up, {os.cpu_count()} cores, python {sys.version.split()[0]}")
    print(f"{'what':<52} {'wall s':>8} {'cpu s':>8}   machine")
    line = lambda what, wall, cpu: print(f"{what:<52} {wall:8.1f} "   # noqa: E731
                                         f"{'' if cpu is None else f'{cpu:.1f}':>8}   {load()}", flush=True)
    with tempfile.TemporaryDirectory(prefix="orientlab-startup-") as d:
        work = Path(d)
        src = work / "in.csv"
        write_csv(src)
        if "estimate" in only:
            cache = work / "cache-estimate"
            line("estimate 3000 rows, first run (cold cache)", *time_estimate(src, cache, work))
            line("estimate 3000 rows, second run", *time_estimate(src, cache, work))
        if "serve" in only:
            cache = work / "cache-serve"
            ready, cpu, stop = time_serve(cache, work)
            line("serve until the page answers, first start (cold)", ready, cpu)
            ready, cpu, stop = time_serve(cache, work)
            line("serve until the page answers, second start", ready, cpu)
            print(f"{'  (Ctrl-C to exit: ' + f'{stop:.1f} s)':<52}")
        if "compile" in only:
            cache = work / "cache-compile"
            line("orientlab compile (make run's install step, cold)", *time_compile(cache, work))
            ready, cpu, _ = time_serve(cache, work)
            line("serve until the page answers, after compile", ready, cpu)
            line("estimate 3000 rows, after compile", *time_estimate(src, cache, work))
    if "clone" in only:
        clone_to_page(args.worktree, line)
    return 0


if __name__ == "__main__":
    sys.exit(main())
