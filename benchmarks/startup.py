"""What a first (cold numba cache) and a second start cost.

Runs the installed ``orientlab`` of this interpreter's environment as a user does, each
time in a fresh process, with numba's cache in a fresh directory (``NUMBA_CACHE_DIR``)
for the cold runs and the same directory again for the warm ones:

- ``orientlab estimate`` of a generated 3,000-row CSV (30 s at 100 Hz), default filter;
- ``orientlab serve --source demo`` on free loopback ports, until the page answers
  (``GET /`` and ``/api/state`` with samples), then Ctrl-C (SIGINT);
- ``orientlab compile`` (what ``make run`` does once after installing: every filter,
  one process per core), then ``serve`` once more.

Prints wall time and the CPU time of the child processes (user + system, all cores;
for serve, what it used until the page answered),
the number of cores and the load average before each run: on a shared machine the wall
time grows with the load, the CPU time much less.

    python benchmarks/startup.py            # all of it (~2-4 min on 2 idle cores)
    python benchmarks/startup.py --only estimate
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


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--only", choices=("estimate", "serve", "compile"), action="append")
    args = ap.parse_args()
    only = set(args.only or ("estimate", "serve", "compile"))
    print(f"orientlab start-up, {os.cpu_count()} cores, python {sys.version.split()[0]}")
    print(f"{'what':<52} {'wall s':>8} {'cpu s':>8}   machine")
    line = lambda what, wall, cpu: print(f"{what:<52} {wall:8.1f} {cpu:8.1f}   {load()}", flush=True)  # noqa: E731
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
    return 0


if __name__ == "__main__":
    sys.exit(main())
