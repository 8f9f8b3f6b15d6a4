"""The program on Python 3.10, the oldest interpreter ``pyproject.toml`` admits
(``requires-python = ">=3.10"``; Ubuntu 22.04's python3, common on lab PCs).

A bare ``pip install -e .`` (no test extras) into a 3.10 venv, then (a) every module of
``app`` imports there and (b) ``orientlab serve --source none`` starts, answers
``GET /api/health`` and stops on SIGINT with exit 0 and no traceback. The first version
imported ``tomllib`` (3.11+) unguarded in ``app/server/presets.py``: serve died at
start-up with ``ModuleNotFoundError: No module named 'tomllib'``.

Skipped when no ``/root/.pyenv/versions/3.10.*/bin/python`` exists or when
``ORIENTLAB_SKIP_PY310=1``. The venv is cached as in ``tests/test_install.py``: reused
only under a key made of the interpreter's version and pyproject's dependency and build
tables (it only ever receives ``pip install -e .`` without extras), one run at a time
(a lock file), the package re-installed (editable, ``--no-deps``) from this checkout
every run. ``NUMBA_DISABLE_JIT=1``: nothing is compiled (import and start-up are what
is checked here; the filters' compilation is tests/test_install.py's business).
"""

from __future__ import annotations

import contextlib
import fcntl
import glob
import hashlib
import json
import os
import shutil
import signal
import subprocess
import sys
import time
import urllib.request
from pathlib import Path

import pytest

from harness import free_port

try:
    import tomllib
except ImportError:  # Python 3.10
    import tomli as tomllib

REPO = Path(__file__).resolve().parents[2]
INSTALL_S = 600.0     # a cold pip install (numba, scipy, viser...) on a loaded machine
START_S = 120.0       # serve without JIT starts in a few seconds


def _py310() -> str | None:
    found = sorted(glob.glob("/root/.pyenv/versions/3.10.*/bin/python"))
    return found[-1] if found else None


PY310 = _py310()

pytestmark = [
    pytest.mark.skipif(os.environ.get("ORIENTLAB_SKIP_PY310") == "1",
                       reason="ORIENTLAB_SKIP_PY310=1"),
    pytest.mark.skipif(PY310 is None, reason="no /root/.pyenv/versions/3.10.*/bin/python"),
]


def _venv_key(version: str) -> str:
    meta = tomllib.loads((REPO / "pyproject.toml").read_text(encoding="utf-8"))
    proj = meta["project"]
    what = {"python": version, "platform": sys.platform,
            "dependencies": sorted(proj.get("dependencies", [])),
            "requires-python": proj.get("requires-python"),
            "build-system": meta.get("build-system")}
    return hashlib.sha256(json.dumps(what, sort_keys=True).encode()).hexdigest()[:16]


def _cache_root() -> Path:
    base = os.environ.get("ORIENTLAB_TEST_CACHE") or os.path.join(
        os.environ.get("XDG_CACHE_HOME") or os.path.expanduser("~/.cache"), "orientlab-tests")
    return Path(base)


def _env(venv: Path) -> dict[str, str]:
    env = {k: v for k, v in os.environ.items()
           if k not in ("PYTHONPATH", "PYTHONHOME", "PYTHONSTARTUP", "VIRTUAL_ENV",
                        "PYTHONUSERBASE", "NUMBA_CACHE_DIR", "ORIENTLAB_PRESETS")}
    dev_bin = str(Path(sys.executable).parent)
    path = [p for p in env.get("PATH", "").split(os.pathsep) if p and p != dev_bin]
    env["PATH"] = os.pathsep.join([str(venv / "bin")] + path)
    env["VIRTUAL_ENV"] = str(venv)
    env["PYTHONNOUSERSITE"] = "1"
    env["PYTHONDONTWRITEBYTECODE"] = "1"
    env["NUMBA_DISABLE_JIT"] = "1"
    return env


def _run(cmd, env, cwd, timeout) -> subprocess.CompletedProcess:
    r = subprocess.run([str(c) for c in cmd], env=env, cwd=cwd, capture_output=True, text=True,
                       timeout=timeout, stdin=subprocess.DEVNULL)
    if r.returncode != 0:
        raise AssertionError(f"{' '.join(map(str, cmd))} -> exit {r.returncode}\n"
                             f"stdout:\n{r.stdout[-3000:]}\nstderr:\n{r.stderr[-5000:]}")
    return r


@pytest.fixture(scope="module")
def venv310(tmp_path_factory):
    version = subprocess.run([PY310, "-c", "import sys; print(sys.version.split()[0])"],
                             capture_output=True, text=True, check=True).stdout.strip()
    assert version.startswith("3.10."), version
    root = _cache_root()
    root.mkdir(parents=True, exist_ok=True)
    key = _venv_key(version)
    venv = root / f"py310-venv-{key}"
    work = tmp_path_factory.mktemp("py310")
    with open(root / f"py310-venv-{key}.lock", "w") as lock:
        fcntl.flock(lock, fcntl.LOCK_EX)    # other checkouts' suites share this venv
        env = _env(venv)
        if not (venv / ".complete").is_file():
            shutil.rmtree(venv, ignore_errors=True)
            _run([PY310, "-m", "venv", venv], env, work, 120)
            _run([venv / "bin" / "python", "-m", "pip", "install", "-q", "-e", REPO],
                 env, work, INSTALL_S)
            (venv / ".complete").write_text(key + "\n")
        else:
            _run([venv / "bin" / "python", "-m", "pip", "install", "-q", "--no-deps",
                  "--force-reinstall", "-e", REPO], env, work, INSTALL_S)
        yield venv, env, work


IMPORT_ALL = r"""
import importlib, json, pathlib, sys, traceback
import app
assert sys.version_info[:2] == (3, 10), sys.version
roots = [pathlib.Path(p) for p in app.__path__ if pathlib.Path(p).is_dir()]   # a namespace package
names = sorted({".".join(("app",) + f.relative_to(r).with_suffix("").parts).removesuffix(".__init__")
                for r in roots for f in r.rglob("*.py") if "__pycache__" not in f.parts})
bad = {}
for name in names:
    try:
        importlib.import_module(name)
    except BaseException:
        bad[name] = traceback.format_exc()[-1500:]
print(json.dumps({"roots": [str(r) for r in roots], "seen": names, "bad": bad}))
"""


def test_every_module_of_app_imports_on_310(venv310):
    venv, env, work = venv310
    r = _run([venv / "bin" / "python", "-c", IMPORT_ALL], env, work, 300)
    out = json.loads(r.stdout.strip().splitlines()[-1])
    # the checkout under test, not some other install
    assert [Path(r).resolve() for r in out["roots"]] == [(REPO / "app").resolve()], out["roots"]
    assert {"app.server.presets", "app.cli", "app.server.run"} <= set(out["seen"]), out["seen"]
    assert len(out["seen"]) > 40, out["seen"]
    assert not out["bad"], "\n".join(f"{k}:\n{v}" for k, v in out["bad"].items())


def _get(url: str, timeout: float = 5.0) -> tuple[int, bytes]:
    with urllib.request.urlopen(url, timeout=timeout) as resp:
        return resp.status, resp.read()


def test_serve_starts_answers_health_and_stops_on_sigint_on_310(venv310, tmp_path):
    venv, env, _ = venv310
    port, viewer, phone = free_port(), free_port(), free_port()
    out, err = tmp_path / "stdout.txt", tmp_path / "stderr.txt"
    with open(out, "w") as fo, open(err, "w") as fe:
        proc = subprocess.Popen(
            [str(venv / "bin" / "orientlab"), "serve", "--source", "none",
             "--host", "127.0.0.1", "--port", str(port), "--viewer-port", str(viewer),
             "--phone-port", str(phone), "--presets-dir", str(tmp_path / "presets"),
             "--recordings", str(tmp_path / "recordings")],
            env=env, cwd=tmp_path, stdin=subprocess.DEVNULL, stdout=fo, stderr=fe)
    try:
        deadline = time.monotonic() + START_S
        health = None
        while health is None:
            if proc.poll() is not None:
                raise AssertionError(f"serve exited {proc.returncode} on 3.10:\n"
                                     f"{err.read_text()[-5000:]}")
            if time.monotonic() > deadline:
                raise AssertionError(f"/api/health never answered:\n{err.read_text()[-5000:]}")
            with contextlib.suppress(OSError):
                health = _get(f"http://127.0.0.1:{port}/api/health")
            time.sleep(0.2)
        status, body = health
        assert status == 200, body
        assert json.loads(body)["status"] == "ok", body
    finally:
        if proc.poll() is None:
            proc.send_signal(signal.SIGINT)
        try:
            rc = proc.wait(timeout=60)
        except subprocess.TimeoutExpired:
            proc.kill()
            proc.wait()
            raise AssertionError("serve did not stop on SIGINT")
    text = err.read_text()
    assert rc == 0, text[-5000:]
    assert "Traceback" not in text, text[-5000:]
