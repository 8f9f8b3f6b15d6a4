"""The program on each Python the README names (3.10–3.13) besides the one the suite runs on:
3.10 is the oldest ``pyproject.toml`` admits (``requires-python = ">=3.10"``; Ubuntu 22.04's
python3, common on lab PCs), 3.12 is Ubuntu 24.04's, 3.13 the newest numba supports.

For each, a bare ``pip install -e .`` (no test extras) into a venv of that interpreter, then
(a) every module of ``app`` imports there and (b) ``orientlab serve --source none`` starts,
answers ``GET /api/health`` and stops on SIGINT with exit 0 and no traceback. The first
version imported ``tomllib`` (3.11+) unguarded in ``app/server/presets.py``: serve died at
start-up on 3.10 with ``ModuleNotFoundError: No module named 'tomllib'``.

Each version is skipped when no ``$PYENV_ROOT/versions/<version>.*/bin/python`` exists
(pyenv's root, ``~/.pyenv`` by default); all are skipped with ``ORIENTLAB_SKIP_PYTHONS=1``.
The venv is the cached bare one of ``tests/venvs.py`` (``pip install -e .`` only) made from
that interpreter.
``NUMBA_DISABLE_JIT=1``: nothing is compiled (import and start-up are what is checked here;
the filters' compilation is tests/test_install.py's business, on the suite's own Python).
"""

from __future__ import annotations

import glob
import json
import os
import subprocess
import sys
from pathlib import Path

import pytest

from harness import free_ports
from venvs import (REPO, bare_venv, clean_env, prebuild_bare_venvs, python_version, run,
                   stop_with_sigint, wait_until_answers)

START_S = 120.0       # serve without JIT starts in a few seconds


CLAIMED = ("3.10", "3.11", "3.12", "3.13")            # the README's "Python 3.10–3.13"
OWN = "%d.%d" % sys.version_info[:2]                   # the suite itself runs on this one
VERSIONS = tuple(v for v in CLAIMED if v != OWN)


PYENV = os.environ.get("PYENV_ROOT") or os.path.expanduser("~/.pyenv")


def _python(version: str) -> str | None:
    found = sorted(glob.glob(f"{PYENV}/versions/{version}.*/bin/python"),
                   key=lambda p: [int(x) for x in p.split("/")[-3].split(".")])
    return found[-1] if found else None


pytestmark = pytest.mark.skipif(os.environ.get("ORIENTLAB_SKIP_PYTHONS") == "1",
                                reason="ORIENTLAB_SKIP_PYTHONS=1")


@pytest.fixture(scope="module")
def _prebuilt(tmp_path_factory) -> None:
    """Every version's venv made at once when missing (a fresh machine)."""
    wanted = [(py, _venv_name(v)) for v in VERSIONS if (py := _python(v)) is not None]
    prebuild_bare_venvs(wanted, tmp_path_factory.mktemp("prebuild"))


def _venv_name(version: str) -> str:
    return "py" + version.replace(".", "")


@pytest.fixture(scope="module", params=VERSIONS)
def venv_of(request, tmp_path_factory, _prebuilt):
    version = request.param
    python = _python(version)
    if python is None:
        pytest.skip(f"no {PYENV}/versions/{version}.*/bin/python")
    assert python_version(python).startswith(version + "."), python
    work = tmp_path_factory.mktemp(_venv_name(version))
    with bare_venv(python, _venv_name(version), work) as venv:
        yield version, venv, clean_env(venv, jit=False), work


IMPORT_ALL = r"""
import importlib, json, pathlib, sys, traceback
import app
assert "%d.%d" % sys.version_info[:2] == sys.argv[1], sys.version
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


def test_every_module_of_app_imports(venv_of):
    version, venv, env, work = venv_of
    r = run([venv / "bin" / "python", "-c", IMPORT_ALL, version], env, work, 300)
    out = json.loads(r.stdout.strip().splitlines()[-1])
    # the checkout under test, not some other install
    assert [Path(r).resolve() for r in out["roots"]] == [(REPO / "app").resolve()], out["roots"]
    assert {"app.server.presets", "app.cli", "app.server.run"} <= set(out["seen"]), out["seen"]
    assert len(out["seen"]) > 40, out["seen"]
    assert not out["bad"], "\n".join(f"{k}:\n{v}" for k, v in out["bad"].items())


def test_serve_starts_answers_health_and_stops_on_sigint(venv_of, tmp_path):
    version, venv, env, _ = venv_of
    port, viewer, phone = free_ports(3)
    out, err = tmp_path / "stdout.txt", tmp_path / "stderr.txt"
    with open(out, "w") as fo, open(err, "w") as fe:
        proc = subprocess.Popen(
            [str(venv / "bin" / "orientlab"), "serve", "--source", "none",
             "--host", "127.0.0.1", "--port", str(port), "--viewer-port", str(viewer),
             "--phone-port", str(phone), "--presets-dir", str(tmp_path / "presets"),
             "--recordings", str(tmp_path / "recordings")],
            env=env, cwd=tmp_path, stdin=subprocess.DEVNULL, stdout=fo, stderr=fe)
    try:
        health = wait_until_answers(proc, f"http://127.0.0.1:{port}/api/health", START_S, err,
                                    what=f"serve on {version}")
        status, body = health
        assert status == 200, body
        assert json.loads(body)["status"] == "ok", body
    finally:
        rc = stop_with_sigint(proc)
    text = err.read_text()
    assert rc == 0, text[-5000:]
    assert "Traceback" not in text, text[-5000:]
