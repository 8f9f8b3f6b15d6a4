"""The program as a user installs it: ``pip install -e .`` WITHOUT extras into a clean
venv (what ``make run`` does), then ``orientlab estimate``, ``orientlab compile`` and
``orientlab serve --source demo`` run from that venv, outside the repository.

The first version crashed at start-up on a fresh machine (scipy, which numba needs for
``@`` in the filters, was only a test extra) and ``make test`` did not notice: it only
ever ran with the test extras installed. These tests would.

The venv is the cached bare one of ``tests/venvs.py`` (``pip install -e .`` only, reused
under a key of the interpreter and pyproject's install tables). numba's cache for these runs is
a fresh directory (``NUMBA_CACHE_DIR``), so the filters are compiled in the bare environment
itself, never loaded from a cache that a fuller environment wrote.
"""

from __future__ import annotations

import csv
import json
import math
import re
import subprocess
import sys
import time
from pathlib import Path

import pytest

from app.estimators import NAMES
from harness import free_ports
from venvs import REPO, bare_venv, clean_env, http_get, run, stop_with_sigint, wait_until_answers

SLOW_S = 900.0      # a safety net for a cold compile on a loaded machine, not a timing claim


def base_python() -> str:
    """The interpreter this venv is made from (a venv made by a venv's python is based on
    the base interpreter anyway; this just says so)."""
    return getattr(sys, "_base_executable", None) or sys.executable


class Bare:
    def __init__(self, venv: Path, numba_cache: Path, work: Path):
        self.venv, self.numba_cache, self.work = venv, numba_cache, work

    def env(self, numba_cache: Path | None = None) -> dict[str, str]:
        return clean_env(self.venv, numba_cache or self.numba_cache)

    def exe(self, name: str) -> Path:
        return self.venv / "bin" / name


@pytest.fixture(scope="module")
def bare(tmp_path_factory) -> Bare:
    work = tmp_path_factory.mktemp("bare")
    with bare_venv(base_python(), "bare", work) as venv:
        yield Bare(venv, work / "numba-cache", work)


def write_motion_csv(path: Path, n: int = 400, fs: float = 100.0) -> int:
    """A phone turning about z at 0.5 rad/s, gravity and a field in the sensor frame."""
    with open(path, "w", newline="") as fh:
        w = csv.writer(fh)
        w.writerow(["t", "acc_x", "acc_y", "acc_z", "gyr_x", "gyr_y", "gyr_z",
                    "mag_x", "mag_y", "mag_z"])
        for k in range(n):
            t = k / fs
            yaw = 0.5 * t
            # the world field (0, 20, -40) µT seen by a sensor turned by yaw about z
            mx, my = 20.0 * math.sin(yaw), 20.0 * math.cos(yaw)
            w.writerow([f"{t:.3f}", 0.0, 0.0, 9.81, 0.0, 0.0, 0.5, f"{mx:.4f}", f"{my:.4f}", -40.0])
    return n


def check_estimate_output(path: Path, n: int) -> None:
    with open(path, newline="") as fh:
        rows = list(csv.reader(fh))
    assert rows[0][:5] == ["t", "qw", "qx", "qy", "qz"]
    assert len(rows) - 1 == n
    last = [float(x) for x in rows[-1][1:5]]
    assert abs(math.sqrt(sum(x * x for x in last)) - 1.0) < 1e-6


def test_bare_venv_has_runtime_dependencies_only(bare):
    r = run([bare.exe("python"), "-c",
             "import importlib.util as u, json; print(json.dumps({m: u.find_spec(m) is not None "
             "for m in ('app', 'numba', 'scipy', 'viser', 'fastapi', 'uvicorn', "
             "'pytest', 'hypothesis', 'playwright', 'vqf')}))"], bare.env(), bare.work)
    found = json.loads(r.stdout)
    assert found["app"] and found["numba"] and found["viser"] and found["scipy"]
    # the test and bench extras are not there: this venv is what `make run` gives
    assert not any(found[m] for m in ("pytest", "hypothesis", "playwright", "vqf")), found
    # and the package it runs is this checkout
    r = run([bare.exe("python"), "-c", "import app.cli; print(app.cli.__file__)"],
            bare.env(), bare.work)
    assert Path(r.stdout.strip()).resolve() == (REPO / "app" / "cli.py").resolve()


def test_bare_first_estimate_compiles_then_compile_readies_every_filter(bare, tmp_path):
    """A user's first steps, on one cold numba cache (a fresh NUMBA_CACHE_DIR; each filter
    compiled once, in the bare venv itself):

    1. the first ``orientlab estimate`` with the lab filter (the one with ``@`` through
       BLAS) compiles it there, and the user is told so;
    2. ``orientlab compile`` then readies every filter, with progress lines along the way
       and nothing "dropped" (there was no stale cache to drop);
    3. every filter estimates without compiling again.
    """
    n = write_motion_csv(tmp_path / "in.csv")
    env = bare.env()
    r = run([bare.exe("orientlab"), "estimate", "in.csv", "-o", "out.csv", "-f", "lab"],
            env, tmp_path)
    assert "orientlab estimate: compiling the lab filter with numba" in r.stderr
    assert "lab ready" in r.stderr
    assert "Traceback" not in r.stderr
    check_estimate_output(tmp_path / "out.csv", n)

    r = run([bare.exe("orientlab"), "compile"], env, tmp_path)
    for name in NAMES:
        assert f"{name} ready" in r.stderr, r.stderr
    # output to a pipe: progress lines all along (the filters other than lab compile
    # here); tests/test_first_start.py times the lines of serve's compile
    assert "dropped" not in r.stderr, r.stderr
    assert re.search(r"compiling .*\(\d+ s\)", r.stderr), r.stderr
    for name in NAMES:
        out = tmp_path / f"{name}.csv"
        r = run([bare.exe("orientlab"), "estimate", "in.csv", "-o", out.name, "-f", name],
                env, tmp_path)
        assert "compiling" not in r.stderr, f"{name} was not compiled by `orientlab compile`"
        check_estimate_output(out, n)


def test_bare_serve_demo_answers_and_stops_on_sigint(bare, tmp_path):
    port, viewer, phone = free_ports(3)
    proc = subprocess.Popen(
        [str(bare.exe("orientlab")), "serve", "--host", "127.0.0.1", "--port", str(port),
         "--viewer-port", str(viewer), "--phone-port", str(phone), "--source", "demo"],
        env=bare.env(), cwd=tmp_path, stdin=subprocess.DEVNULL,
        stdout=open(tmp_path / "stdout.txt", "w"), stderr=open(tmp_path / "stderr.txt", "w"))
    try:
        deadline = time.monotonic() + SLOW_S
        page = wait_until_answers(proc, f"http://127.0.0.1:{port}/", SLOW_S, tmp_path / "stderr.txt")
        status, body = page
        assert status == 200 and b"<title>orientlab" in body
        # the demo phone streams into the filters: samples are counted
        samples = 0
        while samples == 0 and time.monotonic() < deadline:
            _, st = http_get(f"http://127.0.0.1:{port}/api/state")
            samples = json.loads(st)["counts"]["samples"]
            time.sleep(0.2)
        assert samples > 0
        status, _ = http_get(f"http://127.0.0.1:{viewer}/")     # the 3D viewer answers too
        assert status == 200
        banner = (tmp_path / "stdout.txt").read_text()
        assert f":{port}/" in banner and f"port {phone}" in banner
    finally:
        rc = stop_with_sigint(proc)
    err = (tmp_path / "stderr.txt").read_text()
    assert rc == 0, err
    assert "Traceback" not in err, err
