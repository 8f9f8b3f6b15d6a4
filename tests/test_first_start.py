"""The first start after a fresh clone, as a user meets it: output to a pipe (``make run
> log``, a service, an IDE's console), a cold numba cache.

- ``orientlab serve`` answers the page and ``/api/health`` while the filters still
  compile, health says which are not ready, the page shows it, and a line on the pipe
  says each filter as it becomes ready, with a progress line at least every
  ``HEARTBEAT_S`` seconds between;
- ``orientlab compile`` says each filter too, with the same progress lines, and does not
  claim that a cache was dropped when it compiles into an empty cache (a fresh clone:
  ``app.estimators.base`` ran a compiled function on import, before the sources' digest
  was first written, so that entry was taken for a stale cache);
- ``pip install -e .`` prints no boxed setuptools warning.

Each server and compile runs on a copy of the repository's ``app/``, ``static/`` and
``configs/`` (what a fresh clone holds: no ``__pycache__``). ``FIRST_START_SOURCE=DIR``
copies them from another checkout instead (to show these tests failing on an older one).
"""

from __future__ import annotations

import contextlib
import fcntl
import json
import os
import re
import shutil
import subprocess
import sys
import threading
import time
import urllib.error
import urllib.request
from pathlib import Path

import pytest

from app.estimators import NAMES
from harness import CHROMIUM, chromium_page, free_ports
from venvs import cache_root, http_get, stop_with_sigint

REPO = Path(__file__).resolve().parents[1]
SOURCE = Path(os.environ.get("FIRST_START_SOURCE") or REPO)
HEARTBEAT_S = 10.0          # app.warmup.HEARTBEAT_S, what a user is promised
MAX_SILENCE_S = HEARTBEAT_S + 5.0
SLOW_S = 600.0              # a safety net for a cold compile on a loaded machine


def fresh_copy(dst: Path) -> Path:
    """The code, pages and presets of the checkout, without any numba cache."""
    for part in ("app", "static", "configs"):
        shutil.copytree(SOURCE / part, dst / part,
                        ignore=shutil.ignore_patterns("__pycache__", "*.pyc"))
    return dst


def env_for(copy: Path, numba_cache: Path | None) -> dict[str, str]:
    env = {k: v for k, v in os.environ.items()
           if k not in ("NUMBA_DISABLE_JIT", "NUMBA_CACHE_DIR", "PYTHONPATH")}
    env["PYTHONPATH"] = str(copy)
    env["PYTHONUNBUFFERED"] = "1"
    if numba_cache is not None:
        env["NUMBA_CACHE_DIR"] = str(numba_cache)
    return env


class Lines:
    """A child's output pipe read line by line, each line with the time it came."""

    def __init__(self, stream):
        self.lines: list[tuple[float, str]] = []
        self._t = threading.Thread(target=self._read, args=(stream,), daemon=True)
        self._t.start()

    def _read(self, stream) -> None:
        for line in iter(stream.readline, ""):
            self.lines.append((time.monotonic(), line.rstrip("\n")))

    def text(self) -> str:
        return "\n".join(s for _, s in self.lines)

    def first(self, pattern: str) -> float | None:
        rx = re.compile(pattern)
        return next((t for t, s in list(self.lines) if rx.search(s)), None)

    def join(self, timeout: float = 10.0) -> None:
        self._t.join(timeout)


def max_silence(lines: list[tuple[float, str]], start: str, end: str) -> float:
    """The longest time without a line between the line matching ``start`` and the
    one matching ``end``."""
    t = [ts for ts, _ in lines]
    i = next(k for k, (_, s) in enumerate(lines) if re.search(start, s))
    j = next(k for k, (_, s) in enumerate(lines) if re.search(end, s))
    return max((b - a for a, b in zip(t[i:j], t[i + 1:j + 1])), default=0.0)


# ---------------------------------------------------------------- the cache's digest

def test_a_fresh_clone_has_no_stale_cache_to_drop(tmp_path):
    """Importing the estimators on a fresh clone compiles one small function
    (``base.new_flags``, at import) into the empty cache: the freshness check must
    come first, or that entry is "dropped" and the user told the sources changed."""
    copy = fresh_copy(tmp_path)
    r = subprocess.run([sys.executable, "-c",
                        "import app.estimators\n"
                        "from app.jitcache import ensure_fresh, cache_files\n"
                        "print(ensure_fresh(), len(cache_files()))"],
                       cwd=copy, env=env_for(copy, None), capture_output=True, text=True,
                       timeout=300)
    assert r.returncode == 0, r.stderr
    dropped, entries = r.stdout.split()
    assert dropped == "False", "a fresh clone's first import reported a stale cache"
    assert int(entries) > 0       # the entry written at import is still there


def test_the_digest_is_kept_with_numba_cache_dir(tmp_path):
    """With NUMBA_CACHE_DIR the cache (and its digest) are there, not beside the sources."""
    cache = tmp_path / "cache"
    r = subprocess.run([sys.executable, "-c",
                        "import app.estimators\n"
                        "from app.jitcache import cache_files, stamp_path\n"
                        "print(stamp_path()); print(len(cache_files()))"],
                       cwd=tmp_path, env=env_for(SOURCE, cache), capture_output=True, text=True,
                       timeout=300)
    assert r.returncode == 0, r.stderr
    stamp, entries = r.stdout.split()
    assert Path(stamp).is_file() and Path(stamp).is_relative_to(cache)
    assert int(entries) > 0


# ---------------------------------------------------------------- pip install -e .

def _venv_for_pip(root: Path) -> Path:
    """A venv with only an up-to-date pip (``make run`` upgrades it too: pip shows the
    build backend's warnings since 25), made once and reused: the editable install
    builds in pip's isolated environment, where the warning came from."""
    venv = root / f"pip-only-venv-py{sys.version_info[0]}{sys.version_info[1]}"
    if not (venv / ".complete").is_file():
        shutil.rmtree(venv, ignore_errors=True)
        base = getattr(sys, "_base_executable", None) or sys.executable
        subprocess.run([base, "-m", "venv", str(venv)], check=True, timeout=300)
        subprocess.run([str(venv / "bin" / "python"), "-m", "pip", "install", "-q",
                        "--upgrade", "pip"], check=True, timeout=600)
        (venv / ".complete").write_text("ok\n")
    return venv


def test_editable_install_prints_no_setuptools_warning_box(tmp_path):
    root = cache_root()
    root.mkdir(parents=True, exist_ok=True)
    with open(root / "pip-only-venv.lock", "w") as lock:
        fcntl.flock(lock, fcntl.LOCK_EX)
        venv = _venv_for_pip(root)
        env = {k: v for k, v in os.environ.items() if k not in ("PYTHONPATH", "VIRTUAL_ENV")}
        r = subprocess.run([str(venv / "bin" / "python"), "-m", "pip", "install", "--no-deps",
                            "--force-reinstall", "-e", str(SOURCE)], env=env, cwd=tmp_path,
                           capture_output=True, text=True, timeout=600, stdin=subprocess.DEVNULL)
        out = r.stdout + r.stderr
        assert r.returncode == 0, out[-4000:]
        assert "Successfully installed orientlab" in out
        for boxed in ("!!\n", "********", "Please be careful with folders", "BuildBackendWarning",
                      "SetuptoolsDeprecationWarning"):
            assert boxed not in out, f"pip printed {boxed!r}:\n{out[-4000:]}"
        # and the editable install runs this checkout, from anywhere
        r = subprocess.run([str(venv / "bin" / "python"), "-c",
                            "import app.jitcache; print(app.jitcache.__file__)"],
                           env=env, cwd=tmp_path, capture_output=True, text=True, timeout=60)
        assert Path(r.stdout.strip()).resolve() == (SOURCE / "app" / "jitcache.py").resolve(), r.stderr


# ---------------------------------------------------------------- orientlab compile

# ---------------------------------------------------------------- orientlab serve

def _health(port: int) -> dict | None:
    with contextlib.suppress(OSError, ValueError):
        return json.loads(http_get(f"http://127.0.0.1:{port}/api/health")[1])
    return None


def _patch(port: int, token: str, body: dict) -> tuple[int, str, str | None]:
    """PATCH /api/params as the presenter: (status, body text, Retry-After)."""
    req = urllib.request.Request(f"http://127.0.0.1:{port}/api/params", method="PATCH",
                                 data=json.dumps(body).encode(),
                                 headers={"Content-Type": "application/json",
                                          "X-Orientlab-Token": token})
    try:
        with urllib.request.urlopen(req, timeout=30) as r:
            return r.status, r.read().decode(), r.headers.get("Retry-After")
    except urllib.error.HTTPError as e:
        return e.code, e.read().decode(), e.headers.get("Retry-After")


def _page_says_filters(url: str, tmp_path: Path) -> str | None:
    """The landing page's filters line in a real Chromium (None without one)."""
    if CHROMIUM is None:
        return None
    pytest.importorskip("playwright.sync_api")
    with chromium_page(url, tmp_path / "profile", (1280, 720), viewer=False) as (page, _):
        badge = page.locator("#filters")
        badge.wait_for(state="visible", timeout=30_000)
        page.wait_for_function("document.getElementById('filters').textContent.length > 0",
                               timeout=30_000)
        return badge.text_content()


def test_serve_answers_while_the_filters_compile(tmp_path):
    copy = fresh_copy(tmp_path / "clone")
    cache = tmp_path / "numba-cache"            # cold
    port, viewer, phone = free_ports(3)
    p = subprocess.Popen([sys.executable, "-m", "app.cli", "serve", "--host", "127.0.0.1",
                          "--port", str(port), "--viewer-port", str(viewer),
                          "--phone-port", str(phone), "--source", "demo"],
                         cwd=copy, env=env_for(copy, cache), stdin=subprocess.DEVNULL,
                         stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)
    out, err = Lines(p.stdout), Lines(p.stderr)
    seen_ready: dict[str, float] = {}
    try:
        deadline = time.monotonic() + SLOW_S
        # 1. the page and the health answer, and say the filters are not all ready yet
        early = None
        while early is None:
            assert p.poll() is None, f"serve exited {p.returncode}:\n{err.text()}"
            assert time.monotonic() < deadline, "the page never answered"
            with contextlib.suppress(OSError):
                status, body = http_get(f"http://127.0.0.1:{port}/")
                h = _health(port)
                if status == 200 and h is not None:
                    early = h
                    assert b"<title>orientlab" in body
            time.sleep(0.2)
        assert early.get("ready") is False and early.get("filters"), \
            f"the page answered only once every filter was ready: {early}"
        assert set(early["filters"]) == set(NAMES), early
        not_ready = [n for n, s in early["filters"].items() if s != "ready"]
        assert not_ready and all(early["filters"][n] in ("waiting", "compiling", "loading")
                                 for n in not_ready), early
        # 1b. a change sent now is refused as "not now" (503, when to retry), and nothing of
        #     it is applied later (it was a 500 after 5 s, then applied once ready)
        token = re.search(r"token=([A-Za-z0-9_-]+)", out.text()).group(1)
        status, answer, retry = _patch(port, token, {"use_mag": False})
        assert status == 503 and retry, (status, answer)
        assert "compiled" in answer and "nothing was applied" in answer, answer
        # 2. the page says it too
        said = _page_says_filters(f"http://127.0.0.1:{port}/", tmp_path)
        if said is not None:
            assert said.startswith("filters: ") and any(n in said for n in not_ready), said
            assert re.search(r"(compiling|waiting|loading)…", said), said
        # 3. each filter becomes ready, and a line says so when it does
        while True:
            assert p.poll() is None, f"serve exited {p.returncode}:\n{err.text()}"
            assert time.monotonic() < deadline, f"not all ready:\n{err.text()}"
            h = _health(port)
            if h is not None:
                for n, s in h["filters"].items():
                    if s == "ready":
                        seen_ready.setdefault(n, time.monotonic())
                if h["ready"]:
                    break
            time.sleep(0.25)
        assert set(seen_ready) == set(NAMES)
        time.sleep(0.5)
        for n in NAMES:
            said_at = err.first(rf"\] {n} ready\b")
            assert said_at is not None, f"no line says {n} is ready:\n{err.text()}"
            assert said_at <= seen_ready[n] + 2.0, f"{n}'s line came late:\n{err.text()}"
        silence = max_silence(err.lines, r"compiling .*filters", r"filters ready in")
        assert silence <= MAX_SILENCE_S, f"{silence:.0f} s without a line:\n{err.text()}"
        # 4. the samples that waited are filtered, and the stream goes on
        samples = 0
        while samples == 0 and time.monotonic() < deadline:
            samples = json.loads(http_get(f"http://127.0.0.1:{port}/api/state")[1])["counts"]["samples"]
            time.sleep(0.2)
        assert samples > 0
        params = json.loads(http_get(f"http://127.0.0.1:{port}/api/params")[1])
        assert params["use_mag"] is True, "the change refused while compiling was applied later"
        assert _patch(port, token, {"use_mag": False})[0] == 200     # and now it is taken
    finally:
        rc = stop_with_sigint(p)
        out.join()
        err.join()
    assert rc == 0, err.text()
    assert "Traceback" not in err.text(), err.text()
