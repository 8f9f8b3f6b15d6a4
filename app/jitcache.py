"""How the kernels are compiled: one decorator, and numba's on-disk cache kept true to the sources.

:func:`compiled` is the one decorator of every numba kernel (``app.quaternion`` and the
estimators): cached on disk, and with numpy's error model. Under numba's default (Python's)
error model every float division checks its divisor and may raise ZeroDivisionError; that
check keeps the compiler from moving work out of the per-sample path: the robust filter's
batch speed went from 0.97-0.98 M to 0.99-1.02 M samples/s with numpy's
(``benchmarks/throughput.py``, ``docs/performance.md``). The kernels guard their divisions
themselves (a strength, a time step, a variance is bounded away from zero before it
divides), so the estimates are the same to the bit; a division the guards miss gives inf or
NaN, as numpy does, instead of an exception.

numba checks a cached function against its *own* file only. A compiled function that
calls one from another file (``robust_run`` calls ``base.align_step``,
``kalman.correct``, ``quaternion.rotate``...) carries that code inlined, so after a
change to ``base.py`` alone the cache of ``robust.py`` would still load, with the old
``align_step`` in it: a ``git pull`` would run old filter code without a word.

:func:`ensure_fresh` keeps a digest of every compiled source beside the cache and, when
it differs, drops every cache entry of those sources: the next start compiles them
afresh (``orientlab compile`` says so and does it ahead of time). It runs once per
process, before anything compiled is called: ``app.quaternion`` and the
``app.estimators`` package call it first thing on import (``app.estimators.base`` runs
a compiled function at import: had the check come after it, a fresh install's very
first entry would have been taken for a stale cache and "dropped").

The cache is where numba keeps it: ``$NUMBA_CACHE_DIR`` (numba's own sub-folder per
source folder) when that is set, else ``__pycache__`` beside the sources; the digest is
kept with it, so a cache in ``NUMBA_CACHE_DIR`` is checked (and the one beside the
sources left alone).
"""

from __future__ import annotations

import os
import sys
from functools import cache
from hashlib import sha1, sha256
from pathlib import Path

ROOT = Path(__file__).resolve().parent
STAMP = "numba-sources.sha256"


def compiled(fn):
    """The decorator of every compiled kernel (see above): ``fn`` compiled by numba, cached on
    disk, with numpy's error model. numba is imported here, not with this module, which the
    server reads before it loads any filter."""
    from numba import njit
    return njit(cache=True, error_model="numpy")(fn)


def compiled_sources(root: Path = ROOT) -> list[Path]:
    """Every source file the compiled code depends on: this one (its decorator says how
    they compile) and every file with compiled functions (the estimators' packages too:
    ``estimators/robust/``)."""
    return [root / "jitcache.py", root / "quaternion.py", *sorted((root / "estimators").rglob("*.py"))]


def sources_digest(root: Path = ROOT) -> str:
    h = sha256()
    for p in compiled_sources(root):
        h.update(p.relative_to(root).as_posix().encode() + b"\0" + p.read_bytes() + b"\0")
    return h.hexdigest()


def numba_cache_dir() -> str:
    """numba's ``NUMBA_CACHE_DIR`` (its config, which reads the environment), or ""."""
    try:
        from numba.core import config
        return str(config.CACHE_DIR or "")
    except ImportError:
        return os.environ.get("NUMBA_CACHE_DIR", "")


def cache_dir(src: Path) -> Path:
    """The folder where numba caches the functions of ``src``: under ``NUMBA_CACHE_DIR``
    when it is set (numba's ``UserProvidedCacheLocator``: the source folder's name and
    the SHA-1 of its absolute path), else ``__pycache__`` beside ``src``."""
    base = numba_cache_dir()
    if not base:
        return src.parent / "__pycache__"
    folder = os.path.dirname(os.path.abspath(src))
    return Path(base) / f"{os.path.basename(folder)}_{sha1(folder.encode()).hexdigest()}"


def stamp_path(root: Path = ROOT) -> Path:
    """The digest of the sources the cache was made from, kept with the cache."""
    return cache_dir(root / "estimators" / "__init__.py") / STAMP


def cache_files(root: Path = ROOT) -> list[Path]:
    """numba's cache entries (index and data) of the compiled sources."""
    out = []
    for src in compiled_sources(root):
        out += [f for f in cache_dir(src).glob(src.stem + ".*")
                if f.suffix in (".nbi", ".nbc")]
    return out


@cache
def ensure_fresh() -> bool:
    """:func:`refresh` for this install, once per process."""
    return refresh(ROOT)


def refresh(root: Path) -> bool:
    """Drop the compiled sources' cache entries under ``root`` when any of those
    sources changed since they were cached. True when there were entries to drop (a
    fresh install has none: nothing to say). A read-only install is left as it is."""
    stamp = stamp_path(root)
    digest = sources_digest(root)
    try:
        if stamp.read_text().strip() == digest:
            return False
    except OSError:
        pass
    stale = cache_files(root)
    try:
        for f in stale + list(stamp.parent.glob("warm-*.key")):
            f.unlink(missing_ok=True)
        stamp.parent.mkdir(parents=True, exist_ok=True)
        tmp = stamp.with_suffix(f".{os.getpid()}.tmp")
        tmp.write_text(digest + "\n")
        tmp.replace(stamp)
    except OSError:
        return False
    return bool(stale)


# ---------------------------------------------------------------- which filters are cached

def warm_key(root: Path = ROOT) -> str:
    """What numba's cache of the filters depends on: Python's and numba's versions and
    every compiled source's modification time and size (numba's own test of a cache
    entry against its file)."""
    import numba
    h = sha256(f"{sys.implementation.cache_tag}\0{numba.__version__}\0".encode())
    for p in compiled_sources(root):
        st = p.stat()
        h.update(f"{p.relative_to(root).as_posix()}\0{st.st_mtime_ns}\0{st.st_size}\0".encode())
    return h.hexdigest()


def _marker(name: str, root: Path) -> Path:
    return stamp_path(root).parent / f"warm-{name}.{sys.implementation.cache_tag}.key"


def mark_warm(name: str, root: Path = ROOT) -> None:
    """Filter ``name`` is in numba's cache now (written by :func:`app.warmup.warm_one`
    after running every path of it; dropped with the cache by :func:`refresh`)."""
    m = _marker(name, root)
    try:
        m.parent.mkdir(parents=True, exist_ok=True)
        tmp = m.with_suffix(f".{os.getpid()}.tmp")
        tmp.write_text(warm_key(root) + "\n")
        tmp.replace(m)
    except OSError:     # a read-only install: every start takes it for cold, still right
        pass


def is_warm(name: str, root: Path = ROOT) -> bool:
    """Filter ``name`` loads from numba's cache (no compiling) as far as can be told
    without loading it: it was cached from these very sources by this Python and numba.
    ``orientlab serve`` loads such a filter in its own process and compiles the others
    in child processes."""
    try:
        return _marker(name, root).read_text().strip() == warm_key(root)
    except OSError:
        return False
