"""Clean environments for the tests that run the program as a user installs it: a venv that
only ever receives ``pip install -e .`` (no extras), on this interpreter
(``tests/test_install.py``) or on each other Python the README names
(``tests/server/test_pythons.py``); and what those tests share: running a child, reading a
URL, stopping a server with SIGINT.

A venv is reused between runs only under a key made of the interpreter's version and
pyproject's dependency and build tables, so a reused venv holds exactly what a fresh one would
(a dependency dropped from pyproject changes the key; an import of an undeclared package finds
nothing there). The package itself is re-installed (editable, ``--no-deps``) from this checkout
every run. Other checkouts' suites on this machine use the same venvs: one at a time (a lock
file), since each points its editable install at its own checkout. The cache lives in
``$ORIENTLAB_TEST_CACHE``, else ``$XDG_CACHE_HOME/orientlab-tests`` or ``~/.cache/orientlab-tests``.
"""

from __future__ import annotations

import contextlib
import fcntl
import hashlib
import json
import os
import shutil
import signal
import subprocess
import sys
import time
import urllib.request
from concurrent.futures import ThreadPoolExecutor
from pathlib import Path
from typing import Iterator

try:
    import tomllib
except ImportError:  # Python 3.10
    import tomli as tomllib

REPO = Path(__file__).resolve().parents[1]
INSTALL_S = 900.0     # a cold pip install (numba, scipy, viser...) on a loaded machine


def cache_root() -> Path:
    base = os.environ.get("ORIENTLAB_TEST_CACHE") or os.path.join(
        os.environ.get("XDG_CACHE_HOME") or os.path.expanduser("~/.cache"), "orientlab-tests")
    return Path(base)


def venv_key(python_version: str) -> str:
    """What a venv of ``pip install -e .`` holds depends on: the interpreter's version and
    pyproject's dependency and build tables."""
    meta = tomllib.loads((REPO / "pyproject.toml").read_text(encoding="utf-8"))
    proj = meta["project"]
    what = {"python": python_version, "platform": sys.platform,
            "dependencies": sorted(proj.get("dependencies", [])),
            "requires-python": proj.get("requires-python"),
            "build-system": meta.get("build-system")}
    return hashlib.sha256(json.dumps(what, sort_keys=True).encode()).hexdigest()[:16]


def run(cmd, env, cwd, timeout=INSTALL_S, check=True) -> subprocess.CompletedProcess:
    """Run a child (no stdin); with ``check``, a non-zero exit fails with its output."""
    r = subprocess.run([str(c) for c in cmd], env=env, cwd=cwd, capture_output=True, text=True,
                       timeout=timeout, stdin=subprocess.DEVNULL)
    if check and r.returncode != 0:
        raise AssertionError(f"{' '.join(map(str, cmd))} -> exit {r.returncode}\n"
                             f"stdout:\n{r.stdout[-3000:]}\nstderr:\n{r.stderr[-5000:]}")
    return r


def clean_env(venv: Path, numba_cache: Path | None = None, jit: bool = True) -> dict[str, str]:
    """This process's environment as a user's shell with ``venv`` activated would have it:
    none of the developer's Python settings, the developer's venv off the PATH. numba's
    cache in ``numba_cache`` (a cold one: compiled in this environment itself); ``jit``
    False: nothing compiled (``NUMBA_DISABLE_JIT=1``)."""
    env = {k: v for k, v in os.environ.items()
           if k not in ("PYTHONPATH", "PYTHONHOME", "PYTHONSTARTUP", "VIRTUAL_ENV", "PYTHONUSERBASE",
                        "NUMBA_DISABLE_JIT", "NUMBA_CACHE_DIR", "ORIENTLAB_PRESETS")}
    dev_bin = str(Path(sys.executable).parent)
    path = [p for p in env.get("PATH", "").split(os.pathsep) if p and p != dev_bin]
    env["PATH"] = os.pathsep.join([str(venv / "bin")] + path)
    env["VIRTUAL_ENV"] = str(venv)
    env["PYTHONNOUSERSITE"] = "1"
    if numba_cache is not None:
        env["NUMBA_CACHE_DIR"] = str(numba_cache)
    if not jit:
        env["NUMBA_DISABLE_JIT"] = "1"
        env["PYTHONDONTWRITEBYTECODE"] = "1"
    return env


def python_version(python: str) -> str:
    return subprocess.run([python, "-c", "import sys; print(sys.version.split()[0])"],
                          capture_output=True, text=True, check=True).stdout.strip()


@contextlib.contextmanager
def bare_venv(python: str, name: str, work: Path) -> Iterator[Path]:
    """The venv ``<name>-venv-<key>`` of ``python`` with this checkout installed as ``make
    run`` installs it (``pip install -e .``, no extras), made once and reused; held under
    its lock while the block runs."""
    with _locked_venv(python, name) as (venv, key):
        env = clean_env(venv)
        if not _build(python, venv, key, env, work):
            run([venv / "bin" / "python", "-m", "pip", "install", "-q", "--no-deps",
                 "--force-reinstall", "-e", REPO], env, work)
        yield venv


@contextlib.contextmanager
def _locked_venv(python: str, name: str) -> Iterator[tuple[Path, str]]:
    """The path and key of the venv ``name`` of ``python``, held under its lock."""
    root = cache_root()
    root.mkdir(parents=True, exist_ok=True)
    key = venv_key(python_version(python))
    with open(root / f"{name}-venv-{key}.lock", "w") as lock:
        fcntl.flock(lock, fcntl.LOCK_EX)
        yield root / f"{name}-venv-{key}", key


def _build(python: str, venv: Path, key: str, env: dict[str, str], work: Path) -> bool:
    """Make the venv (``pip install -e .``) unless a complete one is there; True if made."""
    if (venv / ".complete").is_file():
        return False
    shutil.rmtree(venv, ignore_errors=True)
    run([python, "-m", "venv", venv], env, work)
    run([venv / "bin" / "python", "-m", "pip", "install", "-q", "-e", REPO], env, work)
    (venv / ".complete").write_text(key + "\n")
    return True


def prebuild_bare_venvs(wanted: list[tuple[str, str]], work: Path) -> None:
    """Make the bare venvs ``(python, name)`` that are missing, all at once (each is a pip
    child, each under its own lock): on a fresh machine (CI) they cost about the time of
    the slowest instead of the sum. :func:`bare_venv` then finds them made."""
    def one(python: str, name: str) -> None:
        with _locked_venv(python, name) as (venv, key):
            _build(python, venv, key, clean_env(venv), work)
    with ThreadPoolExecutor(max_workers=max(1, len(wanted))) as pool:
        for f in [pool.submit(one, py, name) for py, name in wanted]:
            f.result()


def http_get(url: str, timeout: float = 5.0) -> tuple[int, bytes]:
    with urllib.request.urlopen(url, timeout=timeout) as resp:
        return resp.status, resp.read()


def wait_until_answers(proc: subprocess.Popen, url: str, seconds: float, stderr: Path,
                       what: str = "serve") -> tuple[int, bytes]:
    """GET ``url`` until the server child answers it: (status, body). Fails, quoting the end
    of the child's ``stderr`` file, when the child exits first or ``seconds`` pass."""
    deadline = time.monotonic() + seconds
    while True:
        if proc.poll() is not None:
            raise AssertionError(f"{what} exited {proc.returncode}:\n{stderr.read_text()[-5000:]}")
        if time.monotonic() > deadline:
            raise AssertionError(f"{url} never answered:\n{stderr.read_text()[-5000:]}")
        with contextlib.suppress(OSError):
            return http_get(url)
        time.sleep(0.2)


def stop_with_sigint(proc: subprocess.Popen, timeout: float = 60.0) -> int:
    """Ctrl-C for a server child (if still running); its exit code. A child that does not
    stop is killed and the test fails."""
    if proc.poll() is None:
        proc.send_signal(signal.SIGINT)
    try:
        return proc.wait(timeout=timeout)
    except subprocess.TimeoutExpired:
        proc.kill()
        proc.wait()
        raise AssertionError("serve did not stop on SIGINT") from None
